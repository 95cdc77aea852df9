//! Solver speed on the problem sizes the SLAM threads see:
//! - motion-only refinement: 1 000 stereo observations, 10 LM iterations, Huber loss;
//! - local stereo bundle adjustment as the mapping thread runs it (SE(3) keyframes, rectified
//!   stereo and mono observations): 10 keyframes, 2 000 points, 10 000 observations, Huber
//!   loss, two keyframes fixed, one thread, ≤ 10 iterations from a perturbed start;
//! - the same sizes on the BAL camera model (9 unknowns per keyframe), kept for context.
//!
//! `cargo bench -p dhptam-core --bench solver`

use criterion::{criterion_group, criterion_main, Criterion};
use dhptam_core::geometry::Se3;
use dhptam_core::io::{BalObservation, BalProblem};
use dhptam_core::solver::ba::bal_project;
use dhptam_core::solver::{
    refine_pose, solve_bal, solve_stereo_ba, BaKeyframe, BaObservation, BundleOptions, LmOptions,
    Loss, PoseObservation, PoseOptions, StereoBaOptions, StereoIntrinsics,
};
use nalgebra::{Vector2, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn motion_only(c: &mut Criterion) {
    let k = StereoIntrinsics {
        fx: 450.0,
        fy: 450.0,
        cx: 320.0,
        cy: 240.0,
        baseline: 0.12,
    };
    let truth = Se3::exp(&Vector6::new(0.3, -0.2, 1.0, 0.1, -0.3, 0.05));
    let world_from_cam = truth.inverse();
    let mut r = ChaCha8Rng::seed_from_u64(1);
    let obs: Vec<PoseObservation> = (0..1000)
        .map(|_| {
            let pc = Vector3::new(
                r.random_range(-4.0..4.0),
                r.random_range(-3.0..3.0),
                r.random_range(1.0..15.0),
            );
            let noise = Vector2::new(r.random_range(-0.5..0.5), r.random_range(-0.5..0.5));
            PoseObservation::Stereo {
                point: world_from_cam.transform_point(&pc),
                pixel: Vector2::new(k.fx * pc.x / pc.z + k.cx, k.fy * pc.y / pc.z + k.cy) + noise,
                u_right: k.fx * (pc.x - k.baseline) / pc.z + k.cx + noise.x,
            }
        })
        .collect();
    let start = Se3::exp(&Vector6::new(0.02, -0.01, 0.03, 0.01, 0.005, -0.01)) * truth;
    // Exactly 10 iterations: no early stop.
    let options = PoseOptions {
        lm: LmOptions {
            max_iterations: 10,
            function_tolerance: 0.0,
            gradient_tolerance: 0.0,
            parameter_tolerance: 0.0,
            ..Default::default()
        },
        ..Default::default()
    };
    c.bench_function("motion_only_1000_stereo_10_iterations", |b| {
        b.iter(|| refine_pose(start, &k, &obs, &options).map(|r| r.report.iterations))
    });
}

fn local_ba_problem() -> BalProblem {
    let mut r = ChaCha8Rng::seed_from_u64(2);
    // Ten keyframes along a 2 m arc looking at a wall of points 4–8 m ahead.
    let cameras: Vec<[f64; 9]> = (0..10)
        .map(|i| {
            let x = i as f64 * 0.2;
            // BAL cameras look down −z; a small yaw per keyframe.
            let yaw = 0.02 * i as f64;
            [0.0, yaw, 0.0, -x, 0.0, 0.0, 450.0, 0.0, 0.0]
        })
        .collect();
    let points: Vec<[f64; 3]> = (0..2000)
        .map(|_| {
            [
                r.random_range(-3.0..5.0),
                r.random_range(-2.0..2.0),
                -r.random_range(4.0..8.0),
            ]
        })
        .collect();
    let mut observations = Vec::new();
    for (j, p) in points.iter().enumerate() {
        // Five of the ten keyframes see each point: 10 000 observations.
        for k in 0..5 {
            let i = (j + 2 * k) % 10;
            let px = bal_project(&cameras[i], p);
            observations.push(BalObservation {
                camera: i,
                point: j,
                pixel: [
                    px[0] + r.random_range(-0.5..0.5),
                    px[1] + r.random_range(-0.5..0.5),
                ],
            });
        }
    }
    let mut problem = BalProblem {
        cameras,
        points,
        observations,
    };
    for p in problem.points.iter_mut().flatten() {
        *p += r.random_range(-0.02..0.02);
    }
    for c in problem.cameras.iter_mut().skip(2) {
        for v in c.iter_mut().take(6) {
            *v += r.random_range(-0.005..0.005);
        }
    }
    problem
}

fn local_ba(c: &mut Criterion) {
    let problem = local_ba_problem();
    let options = BundleOptions {
        loss: Loss::Huber(2.0),
        threads: 1,
        fixed_cameras: vec![0, 1],
        lm: LmOptions {
            max_iterations: 10,
            ..Default::default()
        },
        ..Default::default()
    };
    let mut group = c.benchmark_group("local_ba");
    group.sample_size(20);
    group.bench_function("10_keyframes_2000_points_10000_obs_huber_1_thread", |b| {
        b.iter(|| {
            let mut p = problem.clone();
            solve_bal(&mut p, &options).map(|r| r.iterations)
        })
    });
    group.finish();
}

/// Ten keyframes 0.2 m apart along x (small yaw each) looking +z at 2 000 points 4–8 m ahead;
/// each point seen by five keyframes, three in four observations stereo, σ ≈ 0.3 px noise.
fn stereo_window() -> (
    StereoIntrinsics,
    Vec<BaKeyframe>,
    Vec<Vector3<f64>>,
    Vec<BaObservation>,
) {
    let k = StereoIntrinsics {
        fx: 450.0,
        fy: 450.0,
        cx: 320.0,
        cy: 240.0,
        baseline: 0.12,
    };
    let mut r = ChaCha8Rng::seed_from_u64(3);
    let truth: Vec<Se3> = (0..10)
        .map(|i| {
            Se3::exp(&Vector6::new(
                0.2 * i as f64,
                0.0,
                0.0,
                0.0,
                0.02 * i as f64,
                0.0,
            ))
            .inverse()
        })
        .collect();
    let points: Vec<Vector3<f64>> = (0..2000)
        .map(|_| {
            Vector3::new(
                r.random_range(-1.5..3.5),
                r.random_range(-2.0..2.0),
                r.random_range(4.0..8.0),
            )
        })
        .collect();
    let mut observations = Vec::new();
    for (j, x) in points.iter().enumerate() {
        for s in 0..5 {
            let i = (j + 2 * s) % 10;
            let p = truth[i].transform_point(x);
            let mut e = || r.random_range(-0.5..0.5);
            observations.push(BaObservation {
                keyframe: i,
                point: j,
                pixel: Vector2::new(k.fx * p.x / p.z + k.cx + e(), k.fy * p.y / p.z + k.cy + e()),
                u_right: (s != 4).then(|| k.fx * (p.x - k.baseline) / p.z + k.cx + e()),
                viewpoint: Vector3::zeros(),
                sigma: 1.0,
            });
        }
    }
    let keyframes = truth
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let d = Vector6::from_fn(|_, _| r.random_range(-0.005..0.005));
            BaKeyframe {
                cam_from_world: if i < 2 { *t } else { Se3::exp(&d) * *t },
                fixed: i < 2,
                prior: None,
            }
        })
        .collect();
    let points = points
        .iter()
        .map(|p| p + Vector3::from_fn(|_, _| r.random_range(-0.02..0.02)))
        .collect();
    (k, keyframes, points, observations)
}

fn stereo_local_ba(c: &mut Criterion) {
    let (k, keyframes, points, observations) = stereo_window();
    let options = StereoBaOptions {
        loss: Loss::Huber(2.0),
        threads: 1,
        ..Default::default()
    };
    {
        let (mut kf, mut pts) = (keyframes.clone(), points.clone());
        if let Ok(r) = solve_stereo_ba(&k, &mut kf, &mut pts, &observations, &options, None) {
            let r = r.report;
            eprintln!(
                "stereo local BA: {} iterations, cost {:.6e} -> {:.6e}, {}",
                r.iterations,
                r.initial_cost,
                r.final_cost,
                r.termination.name()
            );
        }
    }
    let mut group = c.benchmark_group("stereo_local_ba");
    group.sample_size(30);
    group.bench_function(
        "10_keyframes_2000_points_10000_obs_huber_2_fixed_1_thread",
        |b| {
            b.iter(|| {
                let (mut kf, mut pts) = (keyframes.clone(), points.clone());
                solve_stereo_ba(&k, &mut kf, &mut pts, &observations, &options, None)
                    .map(|r| r.report.iterations)
            })
        },
    );
    // The worst case of the mapping thread's budget: exactly 10 iterations, no early stop.
    let exact = StereoBaOptions {
        lm: LmOptions {
            max_iterations: 10,
            function_tolerance: 0.0,
            gradient_tolerance: 0.0,
            parameter_tolerance: 0.0,
            ..Default::default()
        },
        ..options
    };
    group.bench_function("same_exactly_10_iterations", |b| {
        b.iter(|| {
            let (mut kf, mut pts) = (keyframes.clone(), points.clone());
            solve_stereo_ba(&k, &mut kf, &mut pts, &observations, &exact, None)
                .map(|r| r.report.iterations)
        })
    });
    group.finish();
}

criterion_group!(benches, motion_only, stereo_local_ba, local_ba);
criterion_main!(benches);
