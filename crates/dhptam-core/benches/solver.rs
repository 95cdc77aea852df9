//! Solver speed on the problem sizes the SLAM threads see:
//! - motion-only refinement: 1 000 stereo observations, 10 LM iterations, Huber loss;
//! - local bundle adjustment: 10 keyframes, 2 000 points, 10 000 observations, Huber loss,
//!   two keyframes fixed, one thread, 10 iterations from a perturbed start.
//!
//! `cargo bench -p dhptam-core --bench solver`

use criterion::{criterion_group, criterion_main, Criterion};
use dhptam_core::geometry::Se3;
use dhptam_core::io::{BalObservation, BalProblem};
use dhptam_core::solver::ba::bal_project;
use dhptam_core::solver::{
    refine_pose, solve_bal, BundleOptions, LmOptions, Loss, PoseObservation, PoseOptions,
    StereoIntrinsics,
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

criterion_group!(benches, motion_only, local_ba);
criterion_main!(benches);
