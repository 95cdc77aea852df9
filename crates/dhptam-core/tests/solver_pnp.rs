//! PnP: every P3P solution reprojects its three points exactly and one of them is the true
//! pose; RANSAC recovers the pose through 30–50 % outliers with pixel noise, is reproducible
//! for a seed, and refuses too few points or degenerate configurations clearly.

use dhptam_core::geometry::Se3;
use dhptam_core::solver::pnp::p3p;
use dhptam_core::solver::{solve_pnp_ransac, PnpRansacOptions, StereoIntrinsics};
use dhptam_core::Error;
use nalgebra::{Vector2, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const K: StereoIntrinsics = StereoIntrinsics {
    fx: 450.0,
    fy: 460.0,
    cx: 320.0,
    cy: 240.0,
    baseline: 0.12,
};

fn project(pose: &Se3, x: &Vector3<f64>) -> Vector2<f64> {
    let p = pose.transform_point(x);
    Vector2::new(K.fx * p.x / p.z + K.cx, K.fy * p.y / p.z + K.cy)
}

/// `n` world points in front of `truth` (1–12 m), their pixels with Gaussian noise `sigma`,
/// and the first `outliers` fraction replaced by random pixels.
fn scene(
    truth: &Se3,
    n: usize,
    sigma: f64,
    outliers: f64,
    seed: u64,
) -> (Vec<Vector3<f64>>, Vec<Vector2<f64>>, Vec<bool>) {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0, sigma.max(1e-300)).unwrap();
    let world_from_cam = truth.inverse();
    let mut points = Vec::new();
    let mut pixels = Vec::new();
    let mut clean = Vec::new();
    for i in 0..n {
        let z = r.random_range(1.0..12.0);
        let pc = Vector3::new(
            r.random_range(-0.65..0.65) * z,
            r.random_range(-0.5..0.5) * z,
            z,
        );
        let x = world_from_cam.transform_point(&pc);
        let mut px = project(truth, &x);
        if sigma > 0.0 {
            px += Vector2::new(noise.sample(&mut r), noise.sample(&mut r));
        }
        let is_outlier = (i as f64) < outliers * n as f64;
        if is_outlier {
            px = Vector2::new(r.random_range(0.0..640.0), r.random_range(0.0..480.0));
        }
        points.push(x);
        pixels.push(px);
        clean.push(!is_outlier);
    }
    (points, pixels, clean)
}

fn pose_error(a: &Se3, b: &Se3) -> (f64, f64) {
    let d = (*a * b.inverse()).log();
    (d.fixed_rows::<3>(0).norm(), d.fixed_rows::<3>(3).norm())
}

fn truth(seed: u64) -> Se3 {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    Se3::exp(&Vector6::from_fn(|i, _| {
        if i < 3 {
            r.random_range(-2.0..2.0)
        } else {
            r.random_range(-1.0..1.0)
        }
    }))
}

#[test]
fn p3p_recovers_the_true_pose_among_exact_solutions() {
    let mut total_solutions = 0;
    for trial in 0..200u64 {
        let t = truth(trial);
        let (points, pixels, _) = scene(&t, 3, 0.0, 0.0, 1000 + trial);
        let world = [points[0], points[1], points[2]];
        let rays = [0, 1, 2].map(|i| {
            Vector3::new(
                (pixels[i].x - K.cx) / K.fx,
                (pixels[i].y - K.cy) / K.fy,
                1.0,
            )
            .normalize()
        });
        let solutions = p3p(&world, &rays);
        assert!(
            !solutions.is_empty() && solutions.len() <= 4,
            "trial {trial}: {} solutions",
            solutions.len()
        );
        total_solutions += solutions.len();
        // Every solution is exact: each world point lies on its ray, in front of the camera.
        for s in &solutions {
            for i in 0..3 {
                let p = s.transform_point(&world[i]);
                assert!(p.z > 0.0);
                let err = (p.normalize() - rays[i]).norm();
                assert!(err < 1e-9, "trial {trial}: ray error {err}");
            }
        }
        let best = solutions.iter().map(|s| pose_error(s, &t)).fold(
            (f64::INFINITY, f64::INFINITY),
            |a, b| if b.0 + b.1 < a.0 + a.1 { b } else { a },
        );
        assert!(
            best.0 < 1e-8 * (1.0 + t.translation.norm()) && best.1 < 1e-9,
            "trial {trial}: closest solution off by {best:?}"
        );
    }
    // More than one solution appears in general: the check above covers the ambiguous ones.
    assert!(total_solutions > 200, "{total_solutions}");
}

#[test]
fn p3p_rejects_degenerate_triangles() {
    let ray = Vector3::new(0.0, 0.0, 1.0);
    let collinear = [
        Vector3::new(0.0, 0.0, 5.0),
        Vector3::new(1.0, 0.0, 5.0),
        Vector3::new(2.0, 0.0, 5.0),
    ];
    let rays = [
        ray,
        Vector3::new(0.2, 0.0, 1.0).normalize(),
        Vector3::new(0.4, 0.0, 1.0).normalize(),
    ];
    assert!(p3p(&collinear, &rays).is_empty());
    let coincident = [collinear[0], collinear[0], collinear[2]];
    assert!(p3p(&coincident, &rays).is_empty());
}

#[test]
fn ransac_is_exact_on_noiseless_data() {
    let t = truth(7);
    let (points, pixels, _) = scene(&t, 60, 0.0, 0.0, 8);
    let result = solve_pnp_ransac(&K, &points, &pixels, &PnpRansacOptions::default())
        .unwrap()
        .unwrap();
    assert_eq!(result.inlier_count, 60);
    assert!(result.inliers.iter().all(|&b| b));
    let (dt, dr) = pose_error(&result.cam_from_world, &t);
    assert!(dt < 1e-8 && dr < 1e-9, "{dt} {dr}");
    // An all-inlier set needs very few iterations at 99.9 % confidence.
    assert!(result.iterations <= 3, "{}", result.iterations);
}

#[test]
fn ransac_survives_outliers_with_noise() {
    for (outliers, seed) in [(0.3, 11u64), (0.4, 12), (0.5, 13)] {
        let t = truth(seed);
        let (points, pixels, clean) = scene(&t, 200, 0.5, outliers, seed + 100);
        let options = PnpRansacOptions {
            threshold_px: 2.0,
            seed,
            ..Default::default()
        };
        let result = solve_pnp_ransac(&K, &points, &pixels, &options)
            .unwrap()
            .unwrap();
        let (dt, dr) = pose_error(&result.cam_from_world, &t);
        assert!(
            dt < 0.05 && dr < 5e-3,
            "{outliers}: pose error {dt} m {dr} rad"
        );
        let true_positive = result
            .inliers
            .iter()
            .zip(&clean)
            .filter(|(&f, &c)| f && c)
            .count();
        let n_clean = clean.iter().filter(|&&c| c).count();
        // 2 px at σ = 0.5 px keeps nearly every clean point; a random pixel rarely lands
        // within 2 px of the right place.
        assert!(
            true_positive as f64 >= 0.95 * n_clean as f64,
            "{outliers}: {true_positive}/{n_clean}"
        );
        assert!(
            result.inlier_count - true_positive <= 3,
            "{outliers}: {} false inliers",
            result.inlier_count - true_positive
        );
        assert_eq!(
            result.inlier_count,
            result.inliers.iter().filter(|&&b| b).count()
        );
        // Adaptive stopping: far fewer than the cap.
        assert!(
            result.iterations < options.max_iterations,
            "{}",
            result.iterations
        );
        // The same seed gives the same answer.
        let again = solve_pnp_ransac(&K, &points, &pixels, &options)
            .unwrap()
            .unwrap();
        assert_eq!(again, result);
    }
}

#[test]
fn no_model_or_clear_errors_for_bad_input() {
    let t = truth(21);
    let (points, pixels, _) = scene(&t, 30, 0.5, 0.0, 22);
    // Fewer than 4 correspondences.
    let err =
        solve_pnp_ransac(&K, &points[..3], &pixels[..3], &PnpRansacOptions::default()).unwrap_err();
    assert!(
        matches!(err, Error::InvalidInput { ref what, .. } if what == "points_world"),
        "{err}"
    );
    // Mismatched lengths.
    let err =
        solve_pnp_ransac(&K, &points, &pixels[..10], &PnpRansacOptions::default()).unwrap_err();
    assert!(err.to_string().contains("pixels"), "{err}");
    // Non-finite input names the entry.
    let mut bad = pixels.clone();
    bad[5].y = f64::NAN;
    let err = solve_pnp_ransac(&K, &points, &bad, &PnpRansacOptions::default()).unwrap_err();
    assert!(err.to_string().contains("pixels[5]"), "{err}");
    let opt = PnpRansacOptions {
        confidence: 1.0,
        ..Default::default()
    };
    assert!(solve_pnp_ransac(&K, &points, &pixels, &opt).is_err());
    // Fewer points than min_inliers: no model.
    let opt = PnpRansacOptions {
        min_inliers: 31,
        ..Default::default()
    };
    assert!(solve_pnp_ransac(&K, &points, &pixels, &opt)
        .unwrap()
        .is_none());
    // Pure noise: no pose explains 20 random correspondences.
    let mut r = ChaCha8Rng::seed_from_u64(23);
    let random: Vec<Vector2<f64>> = (0..30)
        .map(|_| Vector2::new(r.random_range(0.0..640.0), r.random_range(0.0..480.0)))
        .collect();
    let opt = PnpRansacOptions {
        min_inliers: 20,
        ..Default::default()
    };
    assert!(solve_pnp_ransac(&K, &points, &random, &opt)
        .unwrap()
        .is_none());
    // All points on one line: every sample is degenerate.
    let line: Vec<Vector3<f64>> = (0..10)
        .map(|i| Vector3::new(i as f64 * 0.1, 0.0, 5.0))
        .collect();
    let line_px: Vec<Vector2<f64>> = line.iter().map(|x| project(&Se3::identity(), x)).collect();
    let opt = PnpRansacOptions {
        min_inliers: 4,
        max_iterations: 50,
        ..Default::default()
    };
    assert!(solve_pnp_ransac(&K, &line, &line_px, &opt)
        .unwrap()
        .is_none());
}
