//! Property tests of the camera models on seeded random pixels and points: project/unproject
//! round trips, analytic Jacobians against central differences, validity limits, parameter
//! validation and the batch API.

use dhptam_core::geometry::{Camera, CameraModel, Projective};
use nalgebra::{Matrix2x3, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SAMPLES: usize = 20;

fn pinhole() -> Camera {
    Camera::new("pinhole", &[460.0, 458.0, 319.5, 239.5], 640, 480).unwrap()
}

/// EuRoC-like radial-tangential camera.
fn radtan() -> Camera {
    Camera::new(
        "radtan",
        &[460.0, 458.5, 318.2, 247.1, -0.28, 0.07, 1e-4, -2e-4, 0.0],
        640,
        480,
    )
    .unwrap()
}

/// TUM-VIE-like Kannala–Brandt camera.
fn kb4() -> Camera {
    Camera::new(
        "kb4",
        &[750.0, 749.2, 511.3, 506.8, 0.0037, 0.0143, -0.0285, 0.0143],
        1024,
        1024,
    )
    .unwrap()
}

fn cameras() -> [Camera; 3] {
    [pinhole(), radtan(), kb4()]
}

/// A pixel anywhere in the image, corners included (half the samples on the border).
fn random_pixel(rng: &mut ChaCha8Rng, camera: &Camera, i: usize) -> Vector2<f64> {
    let (w, h) = (
        f64::from(camera.width) - 1.0,
        f64::from(camera.height) - 1.0,
    );
    let mut uv = Vector2::new(rng.random_range(0.0..=w), rng.random_range(0.0..=h));
    match i % 4 {
        1 => uv.x = if rng.random_bool(0.5) { 0.0 } else { w },
        2 => uv.y = if rng.random_bool(0.5) { 0.0 } else { h },
        3 => {
            uv = Vector2::new(
                if rng.random_bool(0.5) { 0.0 } else { w },
                if rng.random_bool(0.5) { 0.0 } else { h },
            )
        }
        _ => {}
    }
    uv
}

/// A point 0.5–20 m away whose ray passes through the image.
fn random_point(rng: &mut ChaCha8Rng, camera: &Camera, i: usize) -> Vector3<f64> {
    let bearing = camera.unproject(&random_pixel(rng, camera, i)).unwrap();
    bearing * rng.random_range(0.5..20.0)
}

#[test]
fn project_of_unproject_returns_the_pixel() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    for camera in cameras() {
        for i in 0..SAMPLES {
            let uv = random_pixel(&mut rng, &camera, i);
            let bearing = camera
                .unproject(&uv)
                .unwrap_or_else(|| panic!("{}: no bearing for {uv:?}", camera.model.name()));
            assert!(
                (bearing.norm() - 1.0).abs() < 1e-14,
                "bearing not unit: {bearing:?}"
            );
            let depth = rng.random_range(0.2..50.0);
            let back = camera.project(&(bearing * depth)).unwrap();
            let err = (back - uv).norm();
            assert!(
                err < 1e-9,
                "{}: {uv:?} -> {back:?}, error {err:e} px",
                camera.model.name()
            );
        }
    }
}

#[test]
fn unproject_of_project_returns_the_bearing() {
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    for camera in cameras() {
        for _ in 0..SAMPLES {
            // Directions built without the model under test: within ±30° of the axis.
            let p = Vector3::new(
                rng.random_range(-0.55..0.55),
                rng.random_range(-0.4..0.4),
                1.0,
            ) * rng.random_range(0.3..30.0);
            let uv = camera.project(&p).unwrap();
            let bearing = camera.unproject(&uv).unwrap();
            let err = (bearing - p.normalize()).norm();
            assert!(
                err < 1e-12,
                "{}: {p:?} -> {uv:?} -> {bearing:?}, error {err:e}",
                camera.model.name()
            );
        }
    }
}

#[test]
fn jacobians_match_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    for camera in cameras() {
        for i in 0..SAMPLES {
            let p = random_point(&mut rng, &camera, i);
            let (uv, j) = camera.project_with_jacobian(&p).unwrap();
            assert_eq!(uv, camera.project(&p).unwrap());
            let h = 1e-6 * p.norm();
            let mut numeric = Matrix2x3::zeros();
            for k in 0..3 {
                let mut d = Vector3::zeros();
                d[k] = h;
                let plus = camera.project(&(p + d)).unwrap();
                let minus = camera.project(&(p - d)).unwrap();
                numeric.set_column(k, &((plus - minus) / (2.0 * h)));
            }
            let err = (j - numeric).amax() / j.amax();
            assert!(
                err < 1e-6,
                "{} at {p:?}: relative error {err:e}\n{j}\n{numeric}",
                camera.model.name()
            );
        }
    }
    // On (and next to) the optical axis, where the KB4 projection switches to its pinhole limit.
    let camera = kb4();
    for p in [
        Vector3::new(0.0, 0.0, 2.0),
        Vector3::new(1e-9, -2e-9, 2.0),
        Vector3::new(3e-7, 1e-7, 1.0),
    ] {
        let (_, j) = camera.project_with_jacobian(&p).unwrap();
        let h = 1e-6;
        for k in 0..3 {
            let mut d = Vector3::zeros();
            d[k] = h;
            let col =
                (camera.project(&(p + d)).unwrap() - camera.project(&(p - d)).unwrap()) / (2.0 * h);
            assert!(
                (j.column(k) - col).amax() < 1e-6 * j.amax(),
                "kb4 near the axis at {p:?}, column {k}"
            );
        }
    }
}

#[test]
fn points_behind_a_perspective_camera_are_not_projected() {
    let mut rng = ChaCha8Rng::seed_from_u64(24);
    for camera in [pinhole(), radtan()] {
        for i in 0..SAMPLES {
            let p = random_point(&mut rng, &camera, i);
            assert!(
                camera.project(&-p).is_none(),
                "{}: {:?} projected",
                camera.model.name(),
                -p
            );
            assert!(camera.project(&Vector3::new(p.x, p.y, 0.0)).is_none());
        }
    }
    // KB4 images rays up to the turning point of θ_d(θ), but not the point at the camera centre.
    assert!(kb4().project(&Vector3::zeros()).is_none());
    assert!(kb4().project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
}

#[test]
fn radtan_does_not_image_points_past_the_fold() {
    // With k1 < 0 alone, r_d = r (1 + k1 r²) peaks at r = 1/√(−3 k1); past it the model folds
    // back, so a point there would land on the pixel of a different, nearer-axis point.
    let k1 = -0.28;
    let camera = Camera::new(
        "radtan",
        &[460.0, 460.0, 320.0, 240.0, k1, 0.0, 0.0, 0.0],
        640,
        480,
    )
    .unwrap();
    let r_fold = 1.0 / (-3.0 * k1).sqrt();
    let mut rng = ChaCha8Rng::seed_from_u64(25);
    for _ in 0..SAMPLES {
        let angle = rng.random_range(0.0..std::f64::consts::TAU);
        let r = r_fold * rng.random_range(1.01..1.5);
        let p = Vector3::new(r * angle.cos(), r * angle.sin(), 1.0);
        assert!(
            camera.project(&p).is_none(),
            "point at r = {r:.3} past the fold r = {r_fold:.3} was projected"
        );
        let inside = Vector3::new(0.9 * r_fold * angle.cos(), 0.9 * r_fold * angle.sin(), 1.0);
        assert!(camera.project(&inside).is_some());
    }
    // k1 = −0.4, k2 = 0.05: g(s) = 1 − 1.2 s + 0.25 s² is negative for s ∈ (1.07, 3.73) and
    // positive again beyond, where the local Jacobian looks healthy but the pixels repeat.
    let camera = Camera::new(
        "radtan",
        &[460.0, 460.0, 320.0, 240.0, -0.4, 0.05, 0.0, 0.0],
        640,
        480,
    )
    .unwrap();
    for r2 in [1.2_f64, 2.0, 4.0, 6.0] {
        let p = Vector3::new(r2.sqrt(), 0.0, 1.0);
        assert!(camera.project(&p).is_none(), "r² = {r2} is past the fold");
    }
    assert!(camera.project(&Vector3::new(1.0, 0.0, 1.0)).is_some());
}

#[test]
fn invalid_parameters_are_rejected_with_the_reason() {
    let cases: [(&str, &[f64], &str); 7] = [
        ("fisheye624", &[1.0, 1.0, 0.0, 0.0], "camera model"),
        ("pinhole", &[460.0, 460.0, 320.0], "4 parameters"),
        (
            "radtan",
            &[460.0, 460.0, 320.0, 240.0, 0.1, 0.0, 0.0],
            "8 or 9 parameters",
        ),
        (
            "kb4",
            &[460.0, 460.0, 320.0, 240.0, 0.1, 0.0, 0.0, 0.0, 0.0],
            "8 parameters",
        ),
        ("pinhole", &[460.0, f64::NAN, 320.0, 240.0], "finite"),
        ("pinhole", &[0.0, 460.0, 320.0, 240.0], "fx > 0"),
        (
            "kb4",
            &[460.0, -1.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0],
            "fy > 0",
        ),
    ];
    for (name, params, expected) in cases {
        let err = CameraModel::from_params(name, params)
            .unwrap_err()
            .to_string();
        assert!(err.contains(expected), "{name} {params:?}: {err}");
    }
    assert!(Camera::new("pinhole", &[460.0, 460.0, 320.0, 240.0], 0, 480).is_err());
    // Aliases and the optional k3 of radtan.
    let plumb_bob = CameraModel::from_params(
        "plumb_bob",
        &[460.0, 460.0, 320.0, 240.0, 0.1, 0.2, 0.3, 0.4],
    )
    .unwrap();
    assert_eq!(plumb_bob.name(), "radtan");
    assert_eq!(
        plumb_bob.params(),
        vec![460.0, 460.0, 320.0, 240.0, 0.1, 0.2, 0.3, 0.4, 0.0]
    );
    for camera in cameras() {
        let rebuilt =
            CameraModel::from_params(camera.model.name(), &camera.model.params()).unwrap();
        assert_eq!(rebuilt, camera.model);
    }
}

#[test]
fn batch_calls_match_single_calls() {
    let mut rng = ChaCha8Rng::seed_from_u64(26);
    for camera in cameras() {
        // Enough points for several parallel chunks, with invalid ones mixed in.
        let n = 20_000;
        let mut xyz = Vec::with_capacity(3 * n);
        let mut uv_in = Vec::with_capacity(2 * n);
        for i in 0..n {
            let p = random_point(&mut rng, &camera, i);
            // The camera centre is invalid for every model, z < 0 for the perspective ones.
            let p = match i % 7 {
                3 => Vector3::zeros(),
                4 => Vector3::new(p.x, p.y, -1.0),
                _ => p,
            };
            xyz.extend_from_slice(p.as_slice());
            let uv = random_pixel(&mut rng, &camera, i);
            // KB4 cannot unproject radii past θ_d(π); NaN pixels are never valid.
            let uv = match i % 11 {
                5 => Vector2::new(1e7, 1e7),
                6 => Vector2::new(f64::NAN, uv.y),
                _ => uv,
            };
            uv_in.extend_from_slice(uv.as_slice());
        }
        let mut uv_out = vec![0.0; 2 * n];
        camera.project_points(&xyz, &mut uv_out).unwrap();
        let mut bearings = vec![0.0; 3 * n];
        camera.unproject_points(&uv_in, &mut bearings).unwrap();
        let mut invalid = [0usize; 2];
        for i in 0..n {
            let p = Vector3::new(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]);
            match camera.project(&p) {
                Some(uv) => assert_eq!(&uv_out[2 * i..2 * i + 2], uv.as_slice()),
                None => {
                    invalid[0] += 1;
                    assert!(uv_out[2 * i..2 * i + 2].iter().all(|v| v.is_nan()));
                }
            }
            match camera.unproject(&Vector2::new(uv_in[2 * i], uv_in[2 * i + 1])) {
                Some(b) if b.iter().all(|v| v.is_finite()) => {
                    assert_eq!(&bearings[3 * i..3 * i + 3], b.as_slice())
                }
                _ => {
                    invalid[1] += 1;
                    assert!(bearings[3 * i..3 * i + 3].iter().all(|v| v.is_nan()));
                }
            }
        }
        assert!(
            invalid[0] > 0 && invalid[1] > 0,
            "{}: no invalid entries exercised",
            camera.model.name()
        );
    }
}

#[test]
fn batch_calls_reject_wrong_buffer_sizes() {
    let camera = radtan();
    let mut uv = vec![0.0; 4];
    let err = camera
        .project_points(&[0.0, 0.0, 1.0, 0.0, 0.0], &mut uv)
        .unwrap_err();
    assert!(err.to_string().contains("multiple of 3"), "{err}");
    let err = camera
        .project_points(&[0.0, 0.0, 1.0], &mut uv)
        .unwrap_err();
    assert!(err.to_string().contains("2 values"), "{err}");
    let mut xyz = vec![0.0; 5];
    assert!(camera.unproject_points(&[1.0, 2.0], &mut xyz).is_err());
    assert!(camera
        .unproject_points(&[1.0, 2.0, 3.0], &mut xyz[..3])
        .is_err());
    assert!(camera.unproject_points(&[1.0, 2.0], &mut xyz[..3]).is_ok());
}
