//! Stereo rectification on seeded random rigs (pinhole, radtan and kb4 cameras, baselines of
//! 5–20 cm, relative rotations of a few degrees): matching rows, projection matrices, remap
//! tables, the balance parameter, resampling and degenerate input.

use dhptam_core::config::RectificationConfig;
use dhptam_core::geometry::rectify::REMAP_INVALID;
use dhptam_core::geometry::{
    remap_bilinear_f32, remap_bilinear_u8, Camera, Projective, RectifiedStereo, Se3, Side, So3,
    StereoRig,
};
use dhptam_core::Error;
use nalgebra::{Vector2, Vector3, Vector4};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const RIGS: usize = 21;

fn jitter(rng: &mut ChaCha8Rng, value: f64, relative: f64) -> f64 {
    value * (1.0 + rng.random_range(-relative..relative))
}

/// A camera of model `kind % 3` with plausible, slightly randomised parameters.
fn random_camera(rng: &mut ChaCha8Rng, kind: usize) -> Camera {
    match kind % 3 {
        0 => Camera::new(
            "pinhole",
            &[
                jitter(rng, 460.0, 0.03),
                jitter(rng, 460.0, 0.03),
                jitter(rng, 320.0, 0.03),
                jitter(rng, 240.0, 0.03),
            ],
            640,
            480,
        ),
        1 => Camera::new(
            "radtan",
            &[
                jitter(rng, 460.0, 0.03),
                jitter(rng, 458.0, 0.03),
                jitter(rng, 318.0, 0.03),
                jitter(rng, 247.0, 0.03),
                jitter(rng, -0.28, 0.1),
                jitter(rng, 0.07, 0.1),
                rng.random_range(-2e-4..2e-4),
                rng.random_range(-2e-4..2e-4),
                0.0,
            ],
            640,
            480,
        ),
        _ => Camera::new(
            "kb4",
            &[
                jitter(rng, 750.0, 0.02),
                jitter(rng, 749.0, 0.02),
                jitter(rng, 511.0, 0.02),
                jitter(rng, 507.0, 0.02),
                jitter(rng, 0.0037, 0.1),
                jitter(rng, 0.0143, 0.1),
                jitter(rng, -0.0285, 0.1),
                jitter(rng, 0.0143, 0.1),
            ],
            1024,
            1024,
        ),
    }
    .unwrap()
}

/// A rig with the right camera 5–20 cm to the right of the left one (off-axis by up to a
/// centimetre) and turned by up to 3° about a random axis.
fn random_rig(rng: &mut ChaCha8Rng, kind: usize) -> StereoRig {
    let axis = Vector3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    )
    .normalize();
    let rotation = So3::exp(&(axis * rng.random_range(0.0..3.0_f64).to_radians()));
    let centre_in_left = Vector3::new(
        rng.random_range(0.05..0.2),
        rng.random_range(-0.01..0.01),
        rng.random_range(-0.01..0.01),
    );
    // p_right = R (p_left − c).
    let right_from_left = Se3::new(rotation, -(rotation * centre_in_left));
    StereoRig {
        left: random_camera(rng, kind),
        right: random_camera(rng, kind),
        right_from_left,
    }
}

fn config(balance: f64) -> RectificationConfig {
    RectificationConfig {
        balance,
        ..Default::default()
    }
}

/// A point 1–20 m in front of the left camera that both cameras image.
fn random_point(rng: &mut ChaCha8Rng, rig: &StereoRig) -> Vector3<f64> {
    loop {
        let uv = Vector2::new(
            rng.random_range(0.0..f64::from(rig.left.width - 1)),
            rng.random_range(0.0..f64::from(rig.left.height - 1)),
        );
        let p = rig.left.unproject(&uv).unwrap() * rng.random_range(1.0..20.0);
        if let Some(uv_r) = rig.right.project(&rig.right_from_left.transform_point(&p)) {
            if rig.right.contains(&uv_r) {
                return p;
            }
        }
    }
}

fn dehomogenise(h: &nalgebra::Vector3<f64>) -> Vector2<f64> {
    Vector2::new(h.x / h.z, h.y / h.z)
}

#[test]
fn rectified_frames_differ_by_the_baseline_only() {
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    for k in 0..RIGS {
        let rig = random_rig(&mut rng, k);
        let rect = RectifiedStereo::new(&rig, &config(0.0)).unwrap();
        // rect_right_from_rect_left = rect_right_from_right · right_from_left · left_from_rect_left.
        let rr_from_rl = Se3::new(rect.rect_right_from_right, Vector3::zeros())
            * rig.right_from_left
            * Se3::new(rect.rect_left_from_left.inverse(), Vector3::zeros());
        assert!(
            rr_from_rl.rotation.angle() < 1e-12,
            "rig {k}: rectified frames rotated by {}",
            rr_from_rl.rotation.angle()
        );
        let expected = Vector3::new(-rect.baseline_m, 0.0, 0.0);
        assert!(
            (rr_from_rl.translation - expected).norm() < 1e-12,
            "rig {k}: {:?}",
            rr_from_rl.translation
        );
        assert!((rect.baseline_m - rig.right_from_left.translation.norm()).abs() < 1e-15);
        assert!(rect.baseline_m > 0.0 && rect.pinhole.fx == rect.pinhole.fy);
    }
}

#[test]
fn rectified_pixels_share_rows_and_match_the_projection_matrices() {
    let mut rng = ChaCha8Rng::seed_from_u64(32);
    for k in 0..RIGS {
        let rig = random_rig(&mut rng, k);
        let balance = [0.0, 0.5, 1.0][k % 3];
        let mut cfg = config(balance);
        if k % 4 == 1 {
            (cfg.width, cfg.height) = (400, 300);
        }
        let rect = RectifiedStereo::new(&rig, &cfg).unwrap();
        let (p_left, p_right) = (rect.projection_left(), rect.projection_right());
        for _ in 0..20 {
            let p = random_point(&mut rng, &rig);
            let uv_l = rig.left.project(&p).unwrap();
            let uv_r = rig
                .right
                .project(&rig.right_from_left.transform_point(&p))
                .unwrap();
            let rl = rect.rectify_pixel(Side::Left, &uv_l).unwrap();
            let rr = rect.rectify_pixel(Side::Right, &uv_r).unwrap();
            assert!(
                (rl.y - rr.y).abs() < 1e-6,
                "rig {k} ({}): rows {} and {}",
                rig.left.model.name(),
                rl.y,
                rr.y
            );
            let disparity = rl.x - rr.x;
            assert!(disparity > 0.0, "rig {k}: disparity {disparity}");

            let p_rect = rect.rect_left_from_left * p;
            let h = Vector4::new(p_rect.x, p_rect.y, p_rect.z, 1.0);
            let via_p_left = dehomogenise(&(p_left * h));
            let via_p_right = dehomogenise(&(p_right * h));
            assert!(
                (via_p_left - rl).norm() < 1e-6,
                "rig {k}: P_left {via_p_left:?} vs {rl:?}"
            );
            assert!(
                (via_p_right - rr).norm() < 1e-6,
                "rig {k}: P_right {via_p_right:?} vs {rr:?}"
            );
            assert!((rect.project_left(&p_rect).unwrap() - rl).norm() < 1e-6);
            assert!((rect.project_right(&p_rect).unwrap() - rr).norm() < 1e-6);
            // Depth from disparity.
            let depth = rect.pinhole.fx * rect.baseline_m / disparity;
            assert!(
                (depth - p_rect.z).abs() < 1e-6 * p_rect.z.powi(2),
                "rig {k}: depth {depth} vs {}",
                p_rect.z
            );
        }
    }
}

#[test]
fn remap_tables_point_back_to_the_source_pixels() {
    let mut rng = ChaCha8Rng::seed_from_u64(33);
    for k in 0..4 {
        let rig = random_rig(&mut rng, k);
        let rect = RectifiedStereo::new(&rig, &config([0.0, 1.0, 0.3][k % 3])).unwrap();
        let w = rect.width as usize;
        for side in [Side::Left, Side::Right] {
            let (map_x, map_y) = rect.remap_tables(side);
            assert_eq!(map_x.len(), w * rect.height as usize);
            assert_eq!(map_y.len(), map_x.len());
            let mut checked = 0;
            while checked < 50 {
                let (u, v) = (
                    rng.random_range(0..rect.width) as usize,
                    rng.random_range(0..rect.height) as usize,
                );
                let (mx, my) = (map_x[v * w + u], map_y[v * w + u]);
                if mx == REMAP_INVALID && my == REMAP_INVALID {
                    continue;
                }
                let source = Vector2::new(f64::from(mx), f64::from(my));
                let exact = rect
                    .unrectify_pixel(side, &Vector2::new(u as f64, v as f64))
                    .unwrap();
                assert!(
                    (source - exact).norm() < 1e-3,
                    "rig {k} {side:?}: table {source:?} vs {exact:?}"
                );
                let back = rect.rectify_pixel(side, &source).unwrap();
                let err = (back - Vector2::new(u as f64, v as f64)).norm();
                assert!(err < 1e-3, "rig {k} {side:?} at ({u}, {v}): table points at {source:?}, which rectifies to {back:?}");
                checked += 1;
            }
        }
    }
}

#[test]
fn balance_zero_sees_only_valid_pixels_and_balance_one_sees_every_pixel() {
    let mut rng = ChaCha8Rng::seed_from_u64(34);
    for k in 0..4 {
        let rig = random_rig(&mut rng, k);
        let inner = RectifiedStereo::new(&rig, &config(0.0)).unwrap();
        for side in [Side::Left, Side::Right] {
            let camera = *inner.camera(side);
            let (map_x, map_y) = inner.remap_tables(side);
            let outside = map_x
                .iter()
                .zip(&map_y)
                .filter(|(&x, &y)| !camera.contains(&Vector2::new(f64::from(x), f64::from(y))))
                .count();
            assert_eq!(
                outside, 0,
                "rig {k} {side:?}: {outside} rectified pixels have no source pixel at balance 0"
            );
        }

        // At balance 1 every source border pixel lands inside the rectified image.
        let outer = RectifiedStereo::new(&rig, &config(1.0)).unwrap();
        let (w, h) = (f64::from(outer.width - 1), f64::from(outer.height - 1));
        for side in [Side::Left, Side::Right] {
            let camera = *outer.camera(side);
            let (cw, ch) = (f64::from(camera.width - 1), f64::from(camera.height - 1));
            let border = (0..camera.width)
                .flat_map(|u| {
                    [
                        Vector2::new(f64::from(u), 0.0),
                        Vector2::new(f64::from(u), ch),
                    ]
                })
                .chain((0..camera.height).flat_map(|v| {
                    [
                        Vector2::new(0.0, f64::from(v)),
                        Vector2::new(cw, f64::from(v)),
                    ]
                }));
            for uv in border {
                let r = outer.rectify_pixel(side, &uv).unwrap();
                let tol = 1e-6;
                assert!(
                    r.x >= -tol && r.y >= -tol && r.x <= w + tol && r.y <= h + tol,
                    "rig {k} {side:?}: {uv:?} -> {r:?} outside"
                );
            }
        }
        // More balance keeps more of the source: the focal length shrinks.
        let middle = RectifiedStereo::new(&rig, &config(0.5)).unwrap();
        assert!(
            inner.pinhole.fx > middle.pinhole.fx && middle.pinhole.fx > outer.pinhole.fx,
            "rig {k}"
        );
    }
}

#[test]
fn bilinear_remap_reproduces_a_linear_gradient() {
    let (w, h) = (64usize, 48usize);
    // Bilinear interpolation is exact for a linear image.
    let value = |x: f64, y: f64| 10.0 + 2.0 * x + 2.0 * y;
    let src_u8: Vec<u8> = (0..w * h)
        .map(|i| value((i % w) as f64, (i / w) as f64) as u8)
        .collect();
    let src_f32: Vec<f32> = (0..w * h)
        .map(|i| value((i % w) as f64, (i / w) as f64) as f32)
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(35);
    let n = 5000;
    let mut map_x = Vec::with_capacity(n);
    let mut map_y = Vec::with_capacity(n);
    for i in 0..n {
        if i % 10 == 0 {
            map_x.push(REMAP_INVALID);
            map_y.push(REMAP_INVALID);
        } else {
            map_x.push(rng.random_range(0.0..(w - 1) as f32));
            map_y.push(rng.random_range(0.0..(h - 1) as f32));
        }
    }
    let mut dst_u8 = vec![1u8; n];
    let mut dst_f32 = vec![1f32; n];
    remap_bilinear_u8(&src_u8, w, h, &map_x, &map_y, &mut dst_u8).unwrap();
    remap_bilinear_f32(&src_f32, w, h, &map_x, &map_y, &mut dst_f32).unwrap();
    for i in 0..n {
        if map_x[i] == REMAP_INVALID {
            assert_eq!(
                (dst_u8[i], dst_f32[i]),
                (0, 0.0),
                "invalid entries take the border value"
            );
            continue;
        }
        let expected = value(f64::from(map_x[i]), f64::from(map_y[i]));
        assert!(
            (f64::from(dst_f32[i]) - expected).abs() < 1e-3,
            "f32 at ({}, {}): {} vs {expected}",
            map_x[i],
            map_y[i],
            dst_f32[i]
        );
        // The u8 source holds the gradient exactly (integers); the output is rounded.
        let err = (f64::from(dst_u8[i]) - expected).abs();
        assert!(
            err <= 0.5 + 1e-3,
            "u8 at ({}, {}): {} vs {expected}",
            map_x[i],
            map_y[i],
            dst_u8[i]
        );
    }
    // Integer coordinates copy pixels exactly; a half-pixel shift averages neighbours.
    let mut out = [0u8; 2];
    remap_bilinear_u8(&src_u8, w, h, &[5.0, 5.5], &[7.0, 7.0], &mut out).unwrap();
    assert_eq!(out[0], src_u8[7 * w + 5]);
    let avg = (f32::from(src_u8[7 * w + 5]) + f32::from(src_u8[7 * w + 6])) / 2.0;
    assert_eq!(out[1], (avg + 0.5) as u8);
    // Half a pixel past the last column blends with the black border.
    remap_bilinear_u8(
        &src_u8,
        w,
        h,
        &[(w - 1) as f32 + 0.5],
        &[0.0],
        &mut out[..1],
    )
    .unwrap();
    assert_eq!(out[0], ((f32::from(src_u8[w - 1]) / 2.0) + 0.5) as u8);

    let err = remap_bilinear_u8(&src_u8[1..], w, h, &map_x, &map_y, &mut dst_u8).unwrap_err();
    assert!(err.to_string().contains("src"), "{err}");
    assert!(remap_bilinear_u8(&src_u8, w, h, &map_x[1..], &map_y, &mut dst_u8).is_err());
    assert!(remap_bilinear_f32(&src_f32, w, h, &map_x, &map_y, &mut dst_f32[1..]).is_err());
}

#[test]
fn degenerate_rigs_are_rejected() {
    let mut rng = ChaCha8Rng::seed_from_u64(36);
    let rig = random_rig(&mut rng, 1);

    let zero = StereoRig {
        right_from_left: Se3::new(rig.right_from_left.rotation, Vector3::zeros()),
        ..rig
    };
    match RectifiedStereo::new(&zero, &config(0.0)) {
        Err(Error::InvalidInput { what, .. }) => assert!(what.contains("translation"), "{what}"),
        other => panic!("zero baseline: {other:?}"),
    }
    let nan = StereoRig {
        right_from_left: Se3::new(So3::identity(), Vector3::new(f64::NAN, 0.0, 0.0)),
        ..rig
    };
    assert!(matches!(
        RectifiedStereo::new(&nan, &config(0.0)),
        Err(Error::InvalidInput { .. })
    ));

    // Cameras one behind the other: no horizontal rectification.
    let along_axis = StereoRig {
        right_from_left: Se3::new(So3::identity(), Vector3::new(0.01, 0.0, -0.2)),
        ..rig
    };
    let err = RectifiedStereo::new(&along_axis, &config(0.0)).unwrap_err();
    assert!(
        matches!(err, Error::Numerical { .. }) && err.to_string().contains("optical axis"),
        "{err}"
    );

    // Cameras turned 90° apart see nothing in common.
    let turned = StereoRig {
        right_from_left: Se3::new(
            So3::exp(&Vector3::new(0.0, 1.6, 0.0)),
            Vector3::new(-0.1, 0.0, 0.0),
        ),
        ..rig
    };
    assert!(RectifiedStereo::new(&turned, &config(0.0)).is_err());

    let mut bad_camera = rig;
    bad_camera.right.width = 1;
    assert!(matches!(
        RectifiedStereo::new(&bad_camera, &config(0.0)),
        Err(Error::InvalidInput { .. })
    ));
    let bad_size = RectificationConfig {
        width: 1,
        height: 300,
        ..config(0.0)
    };
    assert!(RectifiedStereo::new(&rig, &bad_size).is_err());
    assert!(RectifiedStereo::new(&rig, &config(1.5)).is_err());
}
