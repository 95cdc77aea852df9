//! Local stereo bundle adjustment: residual Jacobians against central finite differences,
//! recovery of a synthetic window (every third keyframe observing from a second viewpoint) from a perturbed and noisy start, fixed keyframes held
//! exactly, the gauge fixed by one keyframe, centre priors, gross outliers flagged,
//! interruption, bad input.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use dhptam_core::geometry::Se3;
use dhptam_core::solver::stereo_ba::stereo_ba_residual;
use dhptam_core::solver::{
    solve_stereo_ba, BaKeyframe, BaObservation, CentrePrior, LmOptions, Loss, StereoBaOptions,
    StereoIntrinsics, Termination,
};
use dhptam_core::Error;
use nalgebra::{Matrix3, Vector2, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// Centre of the second camera pair of the synthetic windows (see `window`), metres.
const SECOND_VIEWPOINT: Vector3<f64> = Vector3::new(0.01, 0.03, -0.02);

const K: StereoIntrinsics = StereoIntrinsics {
    fx: 450.0,
    fy: 460.0,
    cx: 320.0,
    cy: 240.0,
    baseline: 0.12,
};

struct Window {
    keyframes: Vec<BaKeyframe>,
    points: Vec<Vector3<f64>>,
    observations: Vec<BaObservation>,
}

/// `n_kf` keyframes 0.25 m apart along x with a small yaw each, looking +z at points 3–9 m
/// ahead; every keyframe that sees a point in its 640×480 image observes it, one in four
/// observations monocular. Pixels carry Gaussian noise of `sigma` px.
fn window(n_kf: usize, n_pt: usize, sigma: f64, seed: u64) -> Window {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    let keyframes: Vec<BaKeyframe> = (0..n_kf)
        .map(|i| {
            let world_from_cam = Se3::exp(&Vector6::new(
                0.25 * i as f64,
                0.02 * i as f64,
                0.05 * i as f64,
                0.0,
                0.015 * i as f64,
                0.0,
            ));
            BaKeyframe {
                cam_from_world: world_from_cam.inverse(),
                fixed: false,
                prior: None,
            }
        })
        .collect();
    let points: Vec<Vector3<f64>> = (0..n_pt)
        .map(|_| {
            Vector3::new(
                r.random_range(-3.0..4.5),
                r.random_range(-2.0..2.0),
                r.random_range(3.0..9.0),
            )
        })
        .collect();
    let noise = Normal::new(0.0, sigma.max(1e-300)).unwrap();
    let mut observations = Vec::new();
    for (j, x) in points.iter().enumerate() {
        for (i, kf) in keyframes.iter().enumerate() {
            // Every third keyframe's images are a second camera pair's view, centred at
            // `SECOND_VIEWPOINT` in its axes (as event images warped into frame cameras).
            let viewpoint = if i % 3 == 2 {
                SECOND_VIEWPOINT
            } else {
                Vector3::zeros()
            };
            let p = kf.cam_from_world.transform_point(x) - viewpoint;
            let (u, v) = (K.fx * p.x / p.z + K.cx, K.fy * p.y / p.z + K.cy);
            if p.z < 0.5 || !(0.0..640.0).contains(&u) || !(0.0..480.0).contains(&v) {
                continue;
            }
            let mut e = || {
                if sigma > 0.0 {
                    noise.sample(&mut r)
                } else {
                    0.0
                }
            };
            let pixel = Vector2::new(u + e(), v + e());
            let u_right = ((i + j) % 4 != 3).then(|| K.fx * (p.x - K.baseline) / p.z + K.cx + e());
            observations.push(BaObservation {
                keyframe: i,
                point: j,
                pixel,
                u_right,
                viewpoint,
                sigma: 1.0,
            });
        }
    }
    Window {
        keyframes,
        points,
        observations,
    }
}

/// Moves the free keyframes by ~0.01 rad / 5 cm and every point by ~5 cm.
fn perturb(w: &Window, seed: u64) -> (Vec<BaKeyframe>, Vec<Vector3<f64>>) {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    let keyframes = w
        .keyframes
        .iter()
        .map(|kf| {
            if kf.fixed {
                return *kf;
            }
            let d = Vector6::from_fn(|i, _| {
                let s = if i < 3 { 0.05 } else { 0.01 };
                r.random_range(-s..s)
            });
            BaKeyframe {
                cam_from_world: Se3::exp(&d) * kf.cam_from_world,
                fixed: false,
                prior: None,
            }
        })
        .collect();
    let points = w
        .points
        .iter()
        .map(|p| p + Vector3::from_fn(|_, _| r.random_range(-0.05..0.05)))
        .collect();
    (keyframes, points)
}

fn pose_error(a: &Se3, b: &Se3) -> (f64, f64) {
    let d = (*a * b.inverse()).log();
    (d.fixed_rows::<3>(0).norm(), d.fixed_rows::<3>(3).norm())
}

fn options(iterations: usize) -> StereoBaOptions {
    StereoBaOptions {
        lm: LmOptions {
            max_iterations: iterations,
            ..Default::default()
        },
        ..Default::default()
    }
}

#[test]
fn residual_jacobians_match_finite_differences() {
    let w = window(4, 60, 0.0, 1);
    let h = 1e-6;
    let mut checked = 0;
    for o in &w.observations {
        let pose = Se3::exp(&Vector6::new(0.01, -0.02, 0.03, 0.01, 0.005, -0.01))
            * w.keyframes[o.keyframe].cam_from_world;
        let x = w.points[o.point] + Vector3::new(0.03, -0.02, 0.05);
        let (r0, jp, jx, dim) =
            stereo_ba_residual(&K, &pose, &x, &o.pixel, o.u_right, &o.viewpoint, 1e-6).unwrap();
        assert_eq!(dim, if o.u_right.is_some() { 3 } else { 2 });
        if dim == 2 {
            assert_eq!(r0.z, 0.0);
        }
        for c in 0..6 {
            let mut d = Vector6::zeros();
            d[c] = h;
            let plus = stereo_ba_residual(
                &K,
                &(Se3::exp(&d) * pose),
                &x,
                &o.pixel,
                o.u_right,
                &o.viewpoint,
                1e-6,
            )
            .unwrap()
            .0;
            let minus = stereo_ba_residual(
                &K,
                &(Se3::exp(&-d) * pose),
                &x,
                &o.pixel,
                o.u_right,
                &o.viewpoint,
                1e-6,
            )
            .unwrap()
            .0;
            let fd = (plus - minus) / (2.0 * h);
            for row in 0..3 {
                let scale = 1.0 + jp[(row, c)].abs();
                assert!(
                    (fd[row] - jp[(row, c)]).abs() < 1e-4 * scale,
                    "pose column {c} row {row}: analytic {} numeric {}",
                    jp[(row, c)],
                    fd[row]
                );
            }
        }
        for c in 0..3 {
            let mut d = Vector3::zeros();
            d[c] = h;
            let plus =
                stereo_ba_residual(&K, &pose, &(x + d), &o.pixel, o.u_right, &o.viewpoint, 1e-6)
                    .unwrap()
                    .0;
            let minus =
                stereo_ba_residual(&K, &pose, &(x - d), &o.pixel, o.u_right, &o.viewpoint, 1e-6)
                    .unwrap()
                    .0;
            let fd = (plus - minus) / (2.0 * h);
            for row in 0..3 {
                let scale = 1.0 + jx[(row, c)].abs();
                assert!(
                    (fd[row] - jx[(row, c)]).abs() < 1e-4 * scale,
                    "point column {c} row {row}: analytic {} numeric {}",
                    jx[(row, c)],
                    fd[row]
                );
            }
        }
        checked += 1;
    }
    assert!(checked > 100, "only {checked} observations checked");
    assert!(
        w.observations
            .iter()
            .any(|o| o.viewpoint == SECOND_VIEWPOINT),
        "no observation from the second viewpoint checked"
    );
    // Behind the camera: no residual.
    let kf = &w.keyframes[0];
    let behind = kf
        .cam_from_world
        .inverse()
        .transform_point(&Vector3::new(0.0, 0.0, -2.0));
    assert!(stereo_ba_residual(
        &K,
        &kf.cam_from_world,
        &behind,
        &Vector2::zeros(),
        None,
        &Vector3::zeros(),
        1e-6
    )
    .is_none());
}

#[test]
fn noiseless_window_converges_to_ground_truth() {
    let mut w = window(6, 300, 0.0, 2);
    w.keyframes[0].fixed = true;
    w.keyframes[1].fixed = true;
    let (mut keyframes, mut points) = perturb(&w, 3);
    let result = solve_stereo_ba(
        &K,
        &mut keyframes,
        &mut points,
        &w.observations,
        &options(50),
        None,
    )
    .unwrap();
    assert!(result.report.final_cost < 1e-12, "{:?}", result.report);
    assert!(result.report.initial_cost > 1e3);
    for (est, truth) in keyframes.iter().zip(&w.keyframes) {
        let (dt, dr) = pose_error(&est.cam_from_world, &truth.cam_from_world);
        assert!(dt < 1e-6 && dr < 1e-7, "pose error {dt} m {dr} rad");
    }
    // Points with a stereo observation are determined (a single monocular ray is not).
    let mut determined = vec![false; w.points.len()];
    for o in &w.observations {
        determined[o.point] |= o.u_right.is_some();
    }
    assert!(determined.iter().filter(|&&d| d).count() > 250);
    for ((est, truth), _) in points
        .iter()
        .zip(&w.points)
        .zip(&determined)
        .filter(|(_, &d)| d)
    {
        assert!(
            (est - truth).norm() < 1e-5,
            "point error {}",
            (est - truth).norm()
        );
    }
    assert!(result.inliers.iter().all(|&b| b));
    assert_eq!(result.inliers.len(), w.observations.len());
}

#[test]
fn noisy_window_converges_near_ground_truth_and_fixed_keyframes_stay() {
    let mut w = window(8, 800, 0.5, 4);
    w.keyframes[0].fixed = true;
    w.keyframes[3].fixed = true;
    let (mut keyframes, mut points) = perturb(&w, 5);
    let fixed_before: Vec<Se3> = [0, 3]
        .iter()
        .map(|&i| keyframes[i].cam_from_world)
        .collect();
    let (_, start_rot) = pose_error(&keyframes[5].cam_from_world, &w.keyframes[5].cam_from_world);
    assert!(start_rot > 1e-3);
    // The cost of the ground truth under the noisy observations: the level to reach.
    let stopped = AtomicBool::new(true);
    let truth_cost = solve_stereo_ba(
        &K,
        &mut w.keyframes.clone(),
        &mut w.points.clone(),
        &w.observations,
        &options(1),
        Some(&stopped),
    )
    .unwrap()
    .report
    .initial_cost;
    let result = solve_stereo_ba(
        &K,
        &mut keyframes,
        &mut points,
        &w.observations,
        &options(30),
        None,
    )
    .unwrap();
    let r = &result.report;
    assert!(r.initial_cost > 10.0 * truth_cost, "{r:?}");
    assert!(r.final_cost <= truth_cost, "{r:?} vs truth {truth_cost}");
    // Exactly where they were, to the bit.
    assert_eq!(keyframes[0].cam_from_world, fixed_before[0]);
    assert_eq!(keyframes[3].cam_from_world, fixed_before[1]);
    for (est, truth) in keyframes.iter().zip(&w.keyframes) {
        let (dt, dr) = pose_error(&est.cam_from_world, &truth.cam_from_world);
        assert!(dt < 5e-3 && dr < 5e-4, "pose error {dt} m {dr} rad");
    }
    let mut errors: Vec<f64> = points
        .iter()
        .zip(&w.points)
        .map(|(a, b)| (a - b).norm())
        .collect();
    errors.sort_by(f64::total_cmp);
    assert!(
        errors[errors.len() / 2] < 0.02,
        "median point error {}",
        errors[errors.len() / 2]
    );
    // With σ = 0.5 px nearly every observation is under the 7.815 px² bound.
    let inliers = result.inliers.iter().filter(|&&b| b).count();
    assert!(inliers as f64 > 0.98 * w.observations.len() as f64);
}

#[test]
fn one_fixed_keyframe_fixes_the_gauge() {
    // Stereo observations fix the scale; one fixed keyframe fixes the frame: the window comes
    // back to the absolute ground truth, not just to a similar configuration.
    let mut w = window(5, 300, 0.0, 6);
    w.keyframes[2].fixed = true;
    let (mut keyframes, mut points) = perturb(&w, 7);
    solve_stereo_ba(
        &K,
        &mut keyframes,
        &mut points,
        &w.observations,
        &options(50),
        None,
    )
    .unwrap();
    for (est, truth) in keyframes.iter().zip(&w.keyframes) {
        let (dt, dr) = pose_error(&est.cam_from_world, &truth.cam_from_world);
        assert!(dt < 1e-6 && dr < 1e-7, "pose error {dt} m {dr} rad");
    }
    assert_eq!(keyframes[2].cam_from_world, w.keyframes[2].cam_from_world);
}

/// The last keyframe free, started 4 cm off its true centre, the others fixed (so the points
/// are pinned): a centre prior at the start pulls it back there as far as its information
/// allows, and a negligible one leaves the observations in charge.
#[test]
fn a_centre_prior_holds_a_keyframe_as_far_as_its_information_allows() {
    let w = window(4, 150, 0.0, 21);
    let truth = w.keyframes[3].cam_from_world;
    let start = Se3::exp(&Vector6::new(0.03, -0.02, 0.02, 0.0, 0.0, 0.0)) * truth;
    let start_centre = start.inverse().translation;
    let true_centre = truth.inverse().translation;
    let solve = |information: f64| {
        let mut kfs: Vec<BaKeyframe> = w
            .keyframes
            .iter()
            .enumerate()
            .map(|(i, kf)| BaKeyframe {
                cam_from_world: if i == 3 { start } else { kf.cam_from_world },
                fixed: i < 3,
                prior: (i == 3).then_some(CentrePrior {
                    centre: start_centre,
                    information: Matrix3::identity() * information,
                }),
            })
            .collect();
        let mut points = w.points.clone();
        let r = solve_stereo_ba(
            &K,
            &mut kfs,
            &mut points,
            &w.observations,
            &options(50),
            None,
        )
        .unwrap();
        assert!(r.report.final_cost <= r.report.initial_cost);
        kfs[3].cam_from_world.inverse().translation
    };
    // Negligible: the observations win (4 cm → under 10 µm).
    let free = solve(1e-6);
    assert!(
        (free - true_centre).norm() < 1e-5,
        "{}",
        (free - true_centre).norm()
    );
    // Overwhelming (σ = 0.1 µm): the keyframe stays where the prior puts it.
    let held = solve(1e14);
    assert!(
        (held - start_centre).norm() < 1e-5,
        "{}",
        (held - start_centre).norm()
    );
    // In between: the centre ends strictly between the two.
    let between = solve(1e6);
    let (to_truth, to_start) = (
        (between - true_centre).norm(),
        (between - start_centre).norm(),
    );
    assert!(to_truth > 1e-4 && to_start > 1e-4, "{to_truth} {to_start}");
    assert!(to_truth + to_start < 1.05 * (start_centre - true_centre).norm());
}

#[test]
fn gross_outliers_are_down_weighted_and_flagged() {
    let mut w = window(6, 400, 0.3, 8);
    w.keyframes[0].fixed = true;
    w.keyframes[1].fixed = true;
    let mut r = ChaCha8Rng::seed_from_u64(9);
    let mut corrupted = vec![false; w.observations.len()];
    for (s, o) in w.observations.iter_mut().enumerate() {
        if s % 5 == 0 {
            let sign = |b: bool| if b { 1.0 } else { -1.0 };
            o.pixel += Vector2::new(
                sign(r.random_bool(0.5)) * r.random_range(20.0..60.0),
                sign(r.random_bool(0.5)) * r.random_range(20.0..60.0),
            );
            corrupted[s] = true;
        }
    }
    let (start_k, start_p) = perturb(&w, 10);
    let worst = |keyframes: &[BaKeyframe]| {
        keyframes
            .iter()
            .zip(&w.keyframes)
            .map(|(e, t)| pose_error(&e.cam_from_world, &t.cam_from_world))
            .fold((0.0f64, 0.0f64), |a, b| (a.0.max(b.0), a.1.max(b.1)))
    };
    // Plain least squares for comparison.
    let (mut keyframes, mut points) = (start_k.clone(), start_p.clone());
    let plain = StereoBaOptions {
        loss: Loss::Trivial,
        ..options(50)
    };
    solve_stereo_ba(
        &K,
        &mut keyframes,
        &mut points,
        &w.observations,
        &plain,
        None,
    )
    .unwrap();
    let (plain_t, plain_r) = worst(&keyframes);
    let (mut keyframes, mut points) = (start_k, start_p);
    let result = solve_stereo_ba(
        &K,
        &mut keyframes,
        &mut points,
        &w.observations,
        &options(50),
        None,
    )
    .unwrap();
    let (dt, dr) = worst(&keyframes);
    assert!(dt < 0.01 && dr < 2e-3, "pose error {dt} m {dr} rad");
    assert!(
        dt < 0.5 * plain_t && dr < 0.5 * plain_r,
        "Huber {dt} m {dr} rad vs plain {plain_t} m {plain_r} rad"
    );
    // A point seen by few keyframes can follow its corrupted observation; nearly all others
    // stand out.
    let missed = result
        .inliers
        .iter()
        .zip(&corrupted)
        .filter(|(&f, &b)| f && b)
        .count();
    let bad = corrupted.iter().filter(|&&b| b).count();
    assert!(
        missed * 50 < bad,
        "{missed} of {bad} corrupted observations flagged inliers"
    );
    let clean_inliers = result
        .inliers
        .iter()
        .zip(&corrupted)
        .filter(|(&f, &b)| f && !b)
        .count();
    let clean = corrupted.iter().filter(|&&b| !b).count();
    assert!(
        clean_inliers as f64 > 0.95 * clean as f64,
        "{clean_inliers} of {clean}"
    );
}

#[test]
fn threads_do_not_change_the_result() {
    let mut w = window(6, 300, 0.5, 11);
    w.keyframes[0].fixed = true;
    let (k1, p1) = perturb(&w, 12);
    let (mut ka, mut pa) = (k1.clone(), p1.clone());
    let (mut kb, mut pb) = (k1, p1);
    let ra = solve_stereo_ba(&K, &mut ka, &mut pa, &w.observations, &options(10), None).unwrap();
    let opt = StereoBaOptions {
        threads: 2,
        ..options(10)
    };
    let rb = solve_stereo_ba(&K, &mut kb, &mut pb, &w.observations, &opt, None).unwrap();
    assert!((ra.report.final_cost - rb.report.final_cost).abs() < 1e-9 * ra.report.final_cost);
    for (a, b) in ka.iter().zip(&kb) {
        let (dt, dr) = pose_error(&a.cam_from_world, &b.cam_from_world);
        assert!(dt < 1e-8 && dr < 1e-9);
    }
}

#[test]
fn a_set_stop_flag_returns_the_start_unchanged() {
    let mut w = window(4, 100, 0.5, 13);
    w.keyframes[0].fixed = true;
    let (mut keyframes, mut points) = perturb(&w, 14);
    let (k0, p0) = (keyframes.clone(), points.clone());
    let stop = AtomicBool::new(true);
    let result = solve_stereo_ba(
        &K,
        &mut keyframes,
        &mut points,
        &w.observations,
        &options(10),
        Some(&stop),
    )
    .unwrap();
    assert_eq!(result.report.termination, Termination::Interrupted);
    assert_eq!(result.report.iterations, 0);
    assert_eq!(result.report.final_cost, result.report.initial_cost);
    assert_eq!(keyframes, k0);
    assert_eq!(points, p0);
    assert_eq!(result.inliers.len(), w.observations.len());
}

#[test]
fn stopping_from_another_thread_interrupts_a_long_solve() {
    // A large window with every stopping tolerance off: thousands of iterations would be
    // allowed; the flag, set 20 ms in, ends it with the best estimate so far.
    let mut w = window(20, 20_000, 0.5, 15);
    w.keyframes[0].fixed = true;
    let (mut keyframes, mut points) = perturb(&w, 16);
    let stop = Arc::new(AtomicBool::new(false));
    let setter = {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(20));
            stop.store(true, Ordering::Relaxed);
        })
    };
    let opt = StereoBaOptions {
        lm: LmOptions {
            max_iterations: 100_000,
            function_tolerance: 0.0,
            gradient_tolerance: 0.0,
            parameter_tolerance: 0.0,
            min_trust_radius: 1e-300,
            ..Default::default()
        },
        ..Default::default()
    };
    let result = solve_stereo_ba(
        &K,
        &mut keyframes,
        &mut points,
        &w.observations,
        &opt,
        Some(&stop),
    )
    .unwrap();
    setter.join().unwrap();
    let r = &result.report;
    assert_eq!(r.termination, Termination::Interrupted, "{r:?}");
    assert!(r.iterations < 100_000);
    assert!(r.final_cost <= r.initial_cost);
    // The estimate written back is the one whose cost is reported.
    let mut check_k = keyframes.clone();
    let mut check_p = points.clone();
    let stopped = AtomicBool::new(true);
    let again = solve_stereo_ba(
        &K,
        &mut check_k,
        &mut check_p,
        &w.observations,
        &opt,
        Some(&stopped),
    )
    .unwrap();
    assert!((again.report.initial_cost - r.final_cost).abs() <= 1e-9 * r.final_cost);
}

#[test]
fn bad_input_is_rejected_with_the_field_named() {
    let w = window(3, 20, 0.0, 17);
    let (mut keyframes, mut points) = (w.keyframes.clone(), w.points.clone());
    let mut obs = w.observations.clone();
    obs[3].point = 99;
    let err =
        solve_stereo_ba(&K, &mut keyframes, &mut points, &obs, &options(5), None).unwrap_err();
    assert!(
        matches!(err, Error::InvalidInput { ref what, .. } if what == "observations[3]"),
        "{err}"
    );
    let mut obs = w.observations.clone();
    obs[1].pixel.x = f64::NAN;
    let err =
        solve_stereo_ba(&K, &mut keyframes, &mut points, &obs, &options(5), None).unwrap_err();
    assert!(err.to_string().contains("observations[1]"), "{err}");
    let err = solve_stereo_ba(&K, &mut keyframes, &mut points, &[], &options(5), None).unwrap_err();
    assert!(err.to_string().contains("observations"), "{err}");
    let opt = StereoBaOptions {
        loss: Loss::Huber(-1.0),
        ..options(5)
    };
    let err =
        solve_stereo_ba(&K, &mut keyframes, &mut points, &w.observations, &opt, None).unwrap_err();
    assert!(err.to_string().contains("loss scale"), "{err}");
    assert_eq!(keyframes, w.keyframes);
}
