//! Triangulation on seeded random scenes: exact recovery without noise, a stated accuracy with
//! pixel noise, each rejection from a constructed case, and the rectified fast path against
//! the general solver.

use dhptam_core::config::TriangulationConfig;
use dhptam_core::geometry::{
    triangulate, triangulate_linear, triangulate_rectified, Pinhole, Projective, Rejected, Se3, So3,
};
use nalgebra::{Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SAMPLES: usize = 20;

/// A standard normal sample by Box–Muller, so that no extra crate is needed.
fn normal(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

const PINHOLE: Pinhole = Pinhole {
    fx: 460.0,
    fy: 460.0,
    cx: 320.0,
    cy: 240.0,
};

/// A camera at `centre` looking at `target`, turned by up to ~5° more so the point is off-centre.
fn looking_at(rng: &mut ChaCha8Rng, centre: Vector3<f64>, target: Vector3<f64>) -> Se3 {
    let z = (target - centre).normalize();
    let x = Vector3::new(0.0, 1.0, 0.0).cross(&z).normalize();
    let y = z.cross(&x);
    let world_from_cam_rot =
        So3::from_matrix(&nalgebra::Matrix3::from_columns(&[x, y, z])).unwrap();
    let wobble = So3::exp(&Vector3::new(
        rng.random_range(-0.08..0.08),
        rng.random_range(-0.08..0.08),
        rng.random_range(-0.3..0.3),
    ));
    Se3::new(world_from_cam_rot * wobble, centre).inverse()
}

/// A point 2–8 m from the origin and 2–4 cameras within a metre of the origin looking at it.
fn random_scene(rng: &mut ChaCha8Rng, views: usize) -> (Vector3<f64>, Vec<Se3>) {
    let direction = Vector3::new(
        rng.random_range(-0.5..0.5),
        rng.random_range(-0.5..0.5),
        1.0,
    )
    .normalize();
    let point = direction * rng.random_range(2.0..8.0);
    let cams = (0..views)
        .map(|_| {
            let centre = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-0.3..0.3),
                rng.random_range(-0.5..0.5),
            );
            looking_at(rng, centre, point)
        })
        .collect();
    (point, cams)
}

fn observe(cams: &[Se3], point: &Vector3<f64>) -> Vec<Vector2<f64>> {
    cams.iter()
        .map(|c| PINHOLE.project(&c.transform_point(point)).unwrap())
        .collect()
}

fn centre(cam_from_world: &Se3) -> Vector3<f64> {
    cam_from_world.inverse().translation
}

#[test]
fn noise_free_observations_give_the_point_back() {
    let mut rng = ChaCha8Rng::seed_from_u64(41);
    let config = TriangulationConfig {
        max_depth_m: 100.0,
        min_parallax_deg: 0.0,
        ..Default::default()
    };
    for i in 0..SAMPLES {
        let (point, cams) = random_scene(&mut rng, 2 + i % 3);
        let pixels = observe(&cams, &point);
        let bearings: Vec<Vector3<f64>> = cams
            .iter()
            .map(|c| c.transform_point(&point) * rng.random_range(0.1..3.0))
            .collect();
        let linear = triangulate_linear(&cams, &bearings).unwrap();
        assert!(
            (linear - point).norm() < 1e-9 * point.norm(),
            "sample {i}: DLT {linear:?} vs {point:?}"
        );

        let t = triangulate(&cams, &pixels, &PINHOLE, &config).unwrap();
        let err = (t.point_world - point).norm();
        assert!(
            err < 1e-9 * point.norm(),
            "sample {i}: {:?} vs {point:?}, error {err:e}",
            t.point_world
        );
        assert!(t.max_reprojection_px < 1e-6);
    }
    // The result does not depend on where the world origin is or on the units.
    let (point, cams) = random_scene(&mut rng, 3);
    let shift = Se3::new(So3::identity(), Vector3::new(1e4, -2e4, 5e3));
    let shifted: Vec<Se3> = cams.iter().map(|c| *c * shift.inverse()).collect();
    let bearings: Vec<Vector3<f64>> = cams.iter().map(|c| c.transform_point(&point)).collect();
    let far = triangulate_linear(&shifted, &bearings).unwrap();
    assert!(
        (far - shift.transform_point(&point)).norm() < 1e-8,
        "{far:?}"
    );
    assert!(triangulate_linear(&cams[..1], &bearings[..1]).is_none());
    assert!(triangulate_linear(&cams, &bearings[..2]).is_none());
}

#[test]
fn noisy_observations_stay_within_the_depth_uncertainty() {
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let sigma_px = 0.5;
    let config = TriangulationConfig {
        max_depth_m: 100.0,
        min_parallax_deg: 0.0,
        max_reprojection_px: 10.0,
        ..Default::default()
    };
    for i in 0..SAMPLES {
        let (point, cams) = random_scene(&mut rng, 2 + i % 3);
        let pixels: Vec<Vector2<f64>> = observe(&cams, &point)
            .into_iter()
            .map(|uv| uv + Vector2::new(normal(&mut rng), normal(&mut rng)) * sigma_px)
            .collect();
        let t = triangulate(&cams, &pixels, &PINHOLE, &config).unwrap();
        // Depth error of a two-ray intersection ≈ σ z² / (f b); allow 6 of those, b the widest
        // baseline and z the farthest range.
        let baseline = cams
            .iter()
            .flat_map(|a| cams.iter().map(move |b| (centre(a) - centre(b)).norm()))
            .fold(0.0, f64::max);
        let range = cams
            .iter()
            .map(|c| (point - centre(c)).norm())
            .fold(0.0, f64::max);
        let tolerance = 6.0 * sigma_px * range * range / (PINHOLE.fx * baseline);
        let err = (t.point_world - point).norm();
        assert!(err < tolerance, "sample {i}: error {err:.4} m > {tolerance:.4} m (baseline {baseline:.2} m, range {range:.2} m)");
        assert!(
            t.max_reprojection_px < 4.0 * sigma_px,
            "sample {i}: {} px",
            t.max_reprojection_px
        );
        // Gauss–Newton ends at a minimum of the reprojection cost: its gradient vanishes there
        // (the DLT estimate alone leaves gradients of order 0.1 px²/m).
        let cost = |x: &Vector3<f64>| -> f64 {
            observe(&cams, x)
                .iter()
                .zip(&pixels)
                .map(|(a, b)| (a - b).norm_squared())
                .sum()
        };
        let h = 1e-6;
        let gradient = Vector3::from_fn(|k, _| {
            let d = Vector3::from_fn(|j, _| if j == k { h } else { 0.0 });
            (cost(&(t.point_world + d)) - cost(&(t.point_world - d))) / (2.0 * h)
        });
        assert!(
            gradient.norm() < 1e-3,
            "sample {i}: cost gradient {gradient:?} px²/m at the refined point"
        );
    }
}

/// Two cameras with the same orientation, the second `baseline` to the right.
fn stereo(baseline: Vector3<f64>) -> [Se3; 2] {
    [Se3::identity(), Se3::new(So3::identity(), -baseline)]
}

#[test]
fn each_rejection_has_a_case() {
    let config = TriangulationConfig::default();
    let cams = stereo(Vector3::new(0.5, 0.0, 0.0));
    let point = Vector3::new(0.4, -0.2, 5.0);
    let pixels = observe(&cams, &point);
    assert!(triangulate(&cams, &pixels, &PINHOLE, &config).is_ok());

    assert_eq!(
        triangulate(&cams[..1], &pixels[..1], &PINHOLE, &config),
        Err(Rejected::TooFewViews { views: 1 })
    );
    assert_eq!(
        triangulate(&cams, &[pixels[0], pixels[1], pixels[0]], &PINHOLE, &config),
        Err(Rejected::MismatchedViews {
            poses: 2,
            observations: 3
        })
    );
    // Same centre: a rotation only, no depth.
    let rotated = [
        Se3::identity(),
        Se3::new(So3::exp(&Vector3::new(0.0, 0.05, 0.0)), Vector3::zeros()),
    ];
    assert_eq!(
        triangulate(&rotated, &observe(&rotated, &point), &PINHOLE, &config),
        Err(Rejected::Degenerate)
    );
    assert_eq!(
        triangulate(
            &cams,
            &[pixels[0], Vector2::new(f64::NAN, 1.0)],
            &PINHOLE,
            &config
        ),
        Err(Rejected::Degenerate)
    );

    // The second camera stands 10 m ahead, facing the same way: the point is behind it. Its
    // pixel is that of the mirrored ray (what the DLT, blind to the sign, would accept).
    let ahead = stereo(Vector3::new(0.0, 0.0, 10.0));
    let behind = ahead[1].transform_point(&point);
    let mirrored = PINHOLE.project(&-behind).unwrap();
    assert_eq!(
        triangulate(&ahead, &[pixels[0], mirrored], &PINHOLE, &config),
        Err(Rejected::BehindCamera { view: 1 })
    );

    let near = Vector3::new(0.01, 0.0, 0.05);
    let close_cams = stereo(Vector3::new(0.02, 0.0, 0.0));
    match triangulate(&close_cams, &observe(&close_cams, &near), &PINHOLE, &config) {
        Err(Rejected::TooClose { view: 0, depth_m }) => assert!((depth_m - 0.05).abs() < 1e-9),
        other => panic!("too close: {other:?}"),
    }

    let wide = stereo(Vector3::new(5.0, 0.0, 0.0));
    let far = Vector3::new(2.0, 1.0, 60.0);
    match triangulate(&wide, &observe(&wide, &far), &PINHOLE, &config) {
        Err(Rejected::TooFar { depth_m }) => assert!((depth_m - 60.0).abs() < 1e-6),
        other => panic!("too far: {other:?}"),
    }

    let narrow = stereo(Vector3::new(0.1, 0.0, 0.0));
    let distant = Vector3::new(1.0, 0.5, 30.0);
    match triangulate(&narrow, &observe(&narrow, &distant), &PINHOLE, &config) {
        Err(Rejected::LowParallax { deg }) => assert!((deg - 0.19).abs() < 0.01, "{deg}"),
        other => panic!("low parallax: {other:?}"),
    }

    // A 10 px row mismatch cannot be explained by any point: about 5 px remain in each view.
    let inconsistent = [pixels[0], pixels[1] + Vector2::new(0.0, 10.0)];
    match triangulate(&cams, &inconsistent, &PINHOLE, &config) {
        Err(Rejected::ReprojectionError { px }) => assert!((px - 5.0).abs() < 0.1, "{px}"),
        other => panic!("reprojection: {other:?}"),
    }
    // Every rejection explains itself.
    assert!(Rejected::LowParallax { deg: 0.2 }
        .to_string()
        .contains("0.200°"));
}

#[test]
fn rectified_fast_path_matches_the_general_solver() {
    let mut rng = ChaCha8Rng::seed_from_u64(43);
    let config = TriangulationConfig::default();
    for i in 0..SAMPLES {
        let pinhole = Pinhole {
            fx: rng.random_range(300.0..800.0),
            fy: 0.0,
            cx: rng.random_range(300.0..340.0),
            cy: rng.random_range(230.0..250.0),
        };
        let pinhole = Pinhole {
            fy: pinhole.fx,
            ..pinhole
        };
        let baseline = rng.random_range(0.05..0.2);
        // Ordinary points (parallax ≥ 0.57°), too close ones, too far ones.
        let depth = [
            rng.random_range(0.5..5.0),
            rng.random_range(0.03..0.09),
            rng.random_range(45.0..60.0),
        ][i % 3];
        let point = Vector3::new(
            rng.random_range(-0.4..0.4) * depth,
            rng.random_range(-0.3..0.3) * depth,
            depth,
        );
        let cams = stereo(Vector3::new(baseline, 0.0, 0.0));
        let uv_left = pinhole.project(&point).unwrap();
        let u_right = pinhole.project(&cams[1].transform_point(&point)).unwrap().x;

        let fast = triangulate_rectified(&pinhole, baseline, &uv_left, u_right, &config);
        let general = triangulate(
            &cams,
            &[uv_left, Vector2::new(u_right, uv_left.y)],
            &pinhole,
            &config,
        );
        match (fast, general) {
            (Ok(a), Ok(b)) => {
                assert!(
                    (a.point_world - point).norm() < 1e-9 * depth,
                    "sample {i}: {:?} vs {point:?}",
                    a.point_world
                );
                assert!(
                    (a.point_world - b.point_world).norm() < 1e-9 * depth,
                    "sample {i}"
                );
                assert!((a.parallax_deg - b.parallax_deg).abs() < 1e-9, "sample {i}");
                assert!(a.max_reprojection_px < 1e-9 && b.max_reprojection_px < 1e-6);
            }
            (Err(a), Err(b)) => {
                assert_eq!(
                    std::mem::discriminant(&a),
                    std::mem::discriminant(&b),
                    "sample {i}: {a:?} vs {b:?}"
                );
                assert!(
                    i % 3 != 0,
                    "sample {i}: an ordinary point was rejected: {a:?}"
                );
            }
            (a, b) => panic!("sample {i} at depth {depth}: fast {a:?}, general {b:?}"),
        }
    }
    let uv = Vector2::new(300.0, 200.0);
    assert_eq!(
        triangulate_rectified(&PINHOLE, 0.1, &uv, 300.0, &config),
        Err(Rejected::TooFar {
            depth_m: f64::INFINITY
        })
    );
    assert_eq!(
        triangulate_rectified(&PINHOLE, 0.1, &uv, 310.0, &config),
        Err(Rejected::BehindCamera { view: 0 })
    );
    assert_eq!(
        triangulate_rectified(&PINHOLE, 0.0, &uv, 290.0, &config),
        Err(Rejected::Degenerate)
    );
    assert_eq!(
        triangulate_rectified(&PINHOLE, 0.1, &uv, f64::NAN, &config),
        Err(Rejected::Degenerate)
    );
}
