//! Bundle adjustment on BAL cameras: the residual's Jacobians against central finite
//! differences, recovery of a synthetic scene from a perturbed start (dense and sparse reduced
//! systems, fixed cameras for the gauge), robustness to 20 % gross outliers, and a BAL file
//! written and solved to its known optimum.

use dhptam_core::io::{BalObservation, BalProblem};
use dhptam_core::solver::ba::{bal_camera_plus, bal_project, bal_residual_jacobians};
use dhptam_core::solver::{solve_bal, BundleOptions, LinearSolver, LmOptions, Loss, Termination};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// Cameras on a ring looking at the origin (BAL cameras look down −z), points in a ball.
fn synthetic_scene(n_cameras: usize, n_points: usize, seed: u64) -> BalProblem {
    let mut r = rng(seed);
    let mut cameras = Vec::new();
    for i in 0..n_cameras {
        let a = i as f64 / n_cameras as f64 * std::f64::consts::TAU;
        // A camera at c = 10 (cos a, 0, sin a) whose −z axis points at the origin: the world
        // direction −c/|c| must map to (0, 0, −1), so the camera z axis is c/|c|.
        let z = nalgebra::Vector3::new(a.cos(), 0.0, a.sin());
        let y = nalgebra::Vector3::new(0.0, 1.0, 0.0);
        let x = y.cross(&z);
        let rot = nalgebra::Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
        let rot = nalgebra::Rotation3::from_matrix_unchecked(rot);
        let w = rot.scaled_axis();
        let c = z * 10.0;
        let t = -(rot * c);
        cameras.push([
            w.x,
            w.y,
            w.z,
            t.x,
            t.y,
            t.z,
            500.0 + r.random_range(-50.0..50.0),
            r.random_range(-0.05..0.05),
            r.random_range(-0.01..0.01),
        ]);
    }
    let points: Vec<[f64; 3]> = (0..n_points)
        .map(|_| {
            [
                r.random_range(-2.0..2.0),
                r.random_range(-2.0..2.0),
                r.random_range(-2.0..2.0),
            ]
        })
        .collect();
    let mut observations = Vec::new();
    for (j, p) in points.iter().enumerate() {
        for (i, c) in cameras.iter().enumerate() {
            // Every camera sees every point except a sparse, deterministic subset.
            if (i + 3 * j) % 5 == 4 {
                continue;
            }
            observations.push(BalObservation {
                camera: i,
                point: j,
                pixel: bal_project(c, p),
            });
        }
    }
    BalProblem {
        cameras,
        points,
        observations,
    }
}

fn perturbed(truth: &BalProblem, seed: u64, camera_noise: f64, point_noise: f64) -> BalProblem {
    let mut r = rng(seed);
    let mut p = truth.clone();
    for c in p.cameras.iter_mut().skip(2) {
        let mut d = [0.0; 9];
        for (k, v) in d.iter_mut().enumerate().take(6) {
            *v = r.random_range(-1.0..1.0) * camera_noise * if k < 3 { 0.1 } else { 1.0 };
        }
        d[6] = r.random_range(-1.0..1.0) * camera_noise * 10.0;
        *c = bal_camera_plus(c, &d);
    }
    for x in p.points.iter_mut().flatten() {
        *x += r.random_range(-1.0..1.0) * point_noise;
    }
    p
}

fn max_point_error(a: &BalProblem, b: &BalProblem) -> f64 {
    a.points
        .iter()
        .zip(&b.points)
        .map(|(p, q)| {
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        })
        .fold(0.0, f64::max)
}

fn rms_point_error(a: &BalProblem, b: &BalProblem) -> f64 {
    let s: f64 = a
        .points
        .iter()
        .zip(&b.points)
        .map(|(p, q)| (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2))
        .sum();
    (s / a.points.len() as f64).sqrt()
}

#[test]
fn residual_jacobians_match_finite_differences() {
    let scene = synthetic_scene(6, 20, 1);
    let h = 1e-6;
    for o in scene.observations.iter().take(40) {
        let cam = scene.cameras[o.camera];
        let pt = scene.points[o.point];
        let (_, jc, jp) = bal_residual_jacobians(&cam, &pt, &o.pixel);
        for k in 0..9 {
            let mut d = [0.0; 9];
            d[k] = h;
            let plus = bal_project(&bal_camera_plus(&cam, &d), &pt);
            d[k] = -h;
            let minus = bal_project(&bal_camera_plus(&cam, &d), &pt);
            for r in 0..2 {
                let fd = (plus[r] - minus[r]) / (2.0 * h);
                let scale = 1.0 + fd.abs();
                assert!(
                    (fd - jc[r * 9 + k]).abs() < 1e-5 * scale,
                    "camera column {k} row {r}: analytic {} vs numeric {fd}",
                    jc[r * 9 + k]
                );
            }
        }
        for k in 0..3 {
            let mut p = pt;
            p[k] += h;
            let plus = bal_project(&cam, &p);
            p[k] -= 2.0 * h;
            let minus = bal_project(&cam, &p);
            for r in 0..2 {
                let fd = (plus[r] - minus[r]) / (2.0 * h);
                assert!(
                    (fd - jp[r * 3 + k]).abs() < 1e-5 * (1.0 + fd.abs()),
                    "point column {k} row {r}: analytic {} vs numeric {fd}",
                    jp[r * 3 + k]
                );
            }
        }
    }
}

fn recovers_truth(linear_solver: LinearSolver) {
    let truth = synthetic_scene(8, 60, 2);
    let mut problem = perturbed(&truth, 3, 0.05, 0.05);
    // Two fixed cameras and the fixed intrinsics of the rest leave no gauge freedom: the
    // scene has a unique optimum, the truth, at zero cost.
    let options = BundleOptions {
        linear_solver,
        threads: 2,
        fixed_cameras: vec![0, 1],
        lm: LmOptions {
            max_iterations: 100,
            function_tolerance: 1e-14,
            ..Default::default()
        },
        ..Default::default()
    };
    let report = solve_bal(&mut problem, &options).unwrap();
    assert!(
        report.initial_cost > 1e3,
        "the start is perturbed: {}",
        report.initial_cost
    );
    assert!(
        report.final_cost < 1e-12,
        "final cost {}",
        report.final_cost
    );
    assert!(max_point_error(&problem, &truth) < 1e-6);
    for (c, t) in problem.cameras.iter().zip(&truth.cameras) {
        for k in 0..9 {
            assert!(
                (c[k] - t[k]).abs() < 1e-5 * (1.0 + t[k].abs()),
                "{c:?} vs {t:?}"
            );
        }
    }
}

#[test]
fn dense_schur_recovers_synthetic_scene() {
    recovers_truth(LinearSolver::Dense);
}

#[test]
fn sparse_schur_recovers_synthetic_scene() {
    recovers_truth(LinearSolver::Sparse);
}

#[test]
fn dense_and_sparse_take_the_same_steps() {
    let truth = synthetic_scene(7, 40, 4);
    let start = perturbed(&truth, 5, 0.05, 0.05);
    let run = |ls| {
        let mut p = start.clone();
        let opts = BundleOptions {
            linear_solver: ls,
            threads: 1,
            fixed_cameras: vec![0, 1],
            lm: LmOptions {
                max_iterations: 5,
                ..Default::default()
            },
            ..Default::default()
        };
        (solve_bal(&mut p, &opts).unwrap(), p)
    };
    let (rd, pd) = run(LinearSolver::Dense);
    let (rs, ps) = run(LinearSolver::Sparse);
    assert_eq!(rd.successful_steps, rs.successful_steps);
    for ((cd, _), (cs, _)) in rd.history.iter().zip(&rs.history) {
        assert!((cd - cs).abs() <= 1e-8 * cd.max(1e-12));
    }
    assert!(max_point_error(&pd, &ps) < 1e-8);
}

#[test]
fn huber_loss_recovers_truth_despite_gross_outliers() {
    let truth = synthetic_scene(10, 100, 6);
    let mut problem = perturbed(&truth, 7, 0.0, 0.05);
    let mut r = rng(8);
    let n = problem.observations.len();
    // 20 % of the observations moved by 30–80 px.
    for o in problem.observations.iter_mut().take(n) {
        if r.random_range(0.0..1.0) < 0.2 {
            let a: f64 = r.random_range(0.0..std::f64::consts::TAU);
            let m: f64 = r.random_range(30.0..80.0);
            o.pixel[0] += m * a.cos();
            o.pixel[1] += m * a.sin();
        }
    }
    let base = BundleOptions {
        threads: 2,
        fixed_cameras: (0..10).collect(),
        lm: LmOptions {
            max_iterations: 500,
            function_tolerance: 1e-12,
            ..Default::default()
        },
        ..Default::default()
    };
    let mut plain = problem.clone();
    solve_bal(&mut plain, &base).unwrap();
    let plain_err = rms_point_error(&plain, &truth);
    // Points triangulated from fixed cameras, 20 % of their observations gross outliers.
    // Huber keeps a bounded pull of δ per outlier (a biased but close optimum), Cauchy's pull
    // fades with distance, Tukey's vanishes beyond δ: the tolerances follow that order.
    for (loss, tolerance) in [
        (Loss::Huber(1.0), 2e-2),
        (Loss::Cauchy(1.0), 1e-3),
        (Loss::Tukey(5.0), 1e-6),
    ] {
        let mut robust = problem.clone();
        let report = solve_bal(
            &mut robust,
            &BundleOptions {
                loss,
                ..base.clone()
            },
        )
        .unwrap();
        assert_ne!(report.termination, Termination::NoDecrease);
        let err = rms_point_error(&robust, &truth);
        assert!(err < tolerance, "{loss:?}: rms point error {err}");
        assert!(
            plain_err > 10.0 * err,
            "{loss:?}: {err} vs least squares {plain_err}"
        );
    }
}

#[test]
fn bal_file_round_trip_solves_to_known_optimum() {
    let dir = std::env::temp_dir().join(format!("dhptam-solver-ba-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("problem-8-50-test.txt");
    let truth = synthetic_scene(8, 50, 9);
    perturbed(&truth, 10, 0.03, 0.03).write(&path).unwrap();
    let mut problem = BalProblem::read(&path).unwrap();
    let report = solve_bal(
        &mut problem,
        &BundleOptions {
            fixed_cameras: vec![0, 1],
            lm: LmOptions {
                max_iterations: 100,
                function_tolerance: 1e-14,
                ..Default::default()
            },
            ..Default::default()
        },
    )
    .unwrap();
    assert!(report.final_cost < 1e-12);
    assert!(max_point_error(&problem, &truth) < 1e-6);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn gauge_free_problem_converges_without_fixed_cameras() {
    // No camera fixed: a 7-dof similarity gauge freedom; LM damping keeps the system solvable
    // and the cost still reaches zero (the optimum is a manifold, any point of it will do).
    let truth = synthetic_scene(6, 40, 11);
    let mut problem = perturbed(&truth, 12, 0.02, 0.02);
    let report = solve_bal(
        &mut problem,
        &BundleOptions {
            lm: LmOptions {
                max_iterations: 200,
                function_tolerance: 1e-14,
                ..Default::default()
            },
            ..Default::default()
        },
    )
    .unwrap();
    assert!(report.final_cost < 1e-8 * report.initial_cost, "{report:?}");
}
