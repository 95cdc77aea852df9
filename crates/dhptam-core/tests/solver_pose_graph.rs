//! Pose graphs: edge Jacobians against central finite differences on SE(3) and SE(2),
//! recovery of synthetic ground truth from a perturbed start with the gauge held by the first
//! vertex, g2o files written and solved to their known optimum, and wrong loop closures
//! down-weighted by a robust loss.

use dhptam_core::geometry::Se3;
use dhptam_core::io::g2o::{EdgeSe2, EdgeSe3, Pose2, PoseGraph, PoseGraph2, PoseGraph3};
use dhptam_core::solver::pose_graph::{solve_pose_graph2, solve_pose_graph3, GraphPose};
use dhptam_core::solver::{LmOptions, Loss, PoseGraphOptions};
use nalgebra::{Matrix3, Matrix6, SMatrix, SVector, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

fn random_vec<const D: usize>(r: &mut ChaCha8Rng, scale: f64) -> SVector<f64, D> {
    SVector::<f64, D>::from_fn(|_, _| r.random_range(-scale..scale))
}

fn check_jacobians<P: GraphPose<D>, const D: usize>(ti: P, tj: P, z: P) {
    let (e, ji, jj) = P::between_error_jacobians(&ti, &tj, &z);
    let e0 = P::between_error(&ti, &tj, &z);
    assert!((e - e0).norm() < 1e-12);
    let h = 1e-6;
    for k in 0..D {
        let mut d = SVector::<f64, D>::zeros();
        d[k] = h;
        let num_i = (P::between_error(&ti.plus(&d), &tj, &z)
            - P::between_error(&ti.plus(&-d), &tj, &z))
            / (2.0 * h);
        let num_j = (P::between_error(&ti, &tj.plus(&d), &z)
            - P::between_error(&ti, &tj.plus(&-d), &z))
            / (2.0 * h);
        assert!(
            (num_i - ji.column(k)).norm() < 1e-6,
            "∂e/∂δi column {k}: {num_i} vs {}",
            ji.column(k)
        );
        assert!(
            (num_j - jj.column(k)).norm() < 1e-6,
            "∂e/∂δj column {k}: {num_j} vs {}",
            jj.column(k)
        );
    }
}

#[test]
fn se3_edge_jacobians_match_finite_differences() {
    let mut r = rng(1);
    for _ in 0..20 {
        let ti = Se3::exp(&random_vec::<6>(&mut r, 2.0));
        let tj = Se3::exp(&random_vec::<6>(&mut r, 2.0));
        // Measurements near and far from the current relative pose (large errors too).
        let z = (ti.inverse() * tj) * Se3::exp(&random_vec::<6>(&mut r, 0.8));
        check_jacobians(ti, tj, z);
    }
}

#[test]
fn se2_edge_jacobians_match_finite_differences() {
    let mut r = rng(2);
    let pose = |r: &mut ChaCha8Rng| Pose2 {
        x: r.random_range(-5.0..5.0),
        y: r.random_range(-5.0..5.0),
        theta: r.random_range(-3.0..3.0),
    };
    for _ in 0..20 {
        let (ti, tj, z) = (pose(&mut r), pose(&mut r), pose(&mut r));
        check_jacobians(ti, tj, z);
    }
}

fn relative2(a: &Pose2, b: &Pose2) -> Pose2 {
    let (s, c) = a.theta.sin_cos();
    let (dx, dy) = (b.x - a.x, b.y - a.y);
    let t = b.theta - a.theta;
    Pose2 {
        x: c * dx + s * dy,
        y: -s * dx + c * dy,
        theta: t.sin().atan2(t.cos()),
    }
}

/// A loop of poses with odometry edges and a few loop closures, measurements exact.
fn synthetic_graph3(n: usize, seed: u64) -> (Vec<Se3>, Vec<EdgeSe3>) {
    let mut r = rng(seed);
    let mut poses = vec![Se3::identity()];
    for k in 1..n {
        let step = Vector6::new(
            1.0,
            0.0,
            0.0,
            0.0,
            0.05,
            2.0 * std::f64::consts::PI / n as f64,
        );
        let noise = random_vec::<6>(&mut r, 0.05);
        poses.push(poses[k - 1] * Se3::exp(&(step + noise)));
    }
    let info = Matrix6::from_diagonal(&Vector6::new(100.0, 100.0, 100.0, 400.0, 400.0, 400.0));
    let mut edges = Vec::new();
    let add = |i: usize, j: usize, edges: &mut Vec<EdgeSe3>| {
        edges.push(EdgeSe3 {
            from: i,
            to: j,
            measurement: poses[i].inverse() * poses[j],
            information: info,
        })
    };
    for k in 1..n {
        add(k - 1, k, &mut edges);
    }
    for k in (0..n - 5).step_by(3) {
        add(k, (k + 7) % n, &mut edges);
    }
    (poses, edges)
}

fn synthetic_graph2(n: usize, seed: u64) -> (Vec<Pose2>, Vec<EdgeSe2>) {
    let mut r = rng(seed);
    let mut poses = vec![Pose2::default()];
    for k in 1..n {
        let p = poses[k - 1];
        let th = p.theta + 2.0 * std::f64::consts::PI / n as f64 + r.random_range(-0.05..0.05);
        poses.push(Pose2 {
            x: p.x + th.cos(),
            y: p.y + th.sin(),
            theta: th.sin().atan2(th.cos()),
        });
    }
    let info = Matrix3::new(50.0, 5.0, 0.0, 5.0, 40.0, 1.0, 0.0, 1.0, 200.0);
    let mut edges = Vec::new();
    for k in 1..n {
        edges.push(EdgeSe2 {
            from: k - 1,
            to: k,
            measurement: relative2(&poses[k - 1], &poses[k]),
            information: info,
        });
    }
    for k in (0..n - 5).step_by(2) {
        let j = (k + 9) % n;
        edges.push(EdgeSe2 {
            from: k,
            to: j,
            measurement: relative2(&poses[k], &poses[j]),
            information: info,
        });
    }
    (poses, edges)
}

fn tight() -> PoseGraphOptions {
    PoseGraphOptions {
        threads: 2,
        lm: LmOptions {
            max_iterations: 100,
            function_tolerance: 1e-15,
            ..Default::default()
        },
        ..Default::default()
    }
}

fn se3_distance(a: &Se3, b: &Se3) -> f64 {
    (a.inverse() * *b).log().norm()
}

#[test]
fn se3_graph_recovers_truth_with_first_pose_fixed() {
    let (truth, edges) = synthetic_graph3(40, 3);
    let mut r = rng(4);
    let start: Vec<Se3> = truth
        .iter()
        .enumerate()
        .map(|(k, p)| {
            if k == 0 {
                *p
            } else {
                *p * Se3::exp(&random_vec::<6>(&mut r, 0.2))
            }
        })
        .collect();
    let mut graph = PoseGraph3 {
        ids: (0..truth.len()).collect(),
        poses: start,
        edges,
        fixed: vec![],
    };
    let report = solve_pose_graph3(&mut graph, &tight()).unwrap();
    assert!(report.initial_cost > 100.0);
    assert!(report.final_cost < 1e-12, "{report:?}");
    // Gauge: the first vertex was held, so the solution is the truth itself, not a copy of it
    // moved rigidly.
    assert_eq!(graph.poses[0], truth[0]);
    for (p, t) in graph.poses.iter().zip(&truth) {
        assert!(se3_distance(p, t) < 1e-7);
    }
}

#[test]
fn se2_graph_recovers_truth_with_first_pose_fixed() {
    let (truth, edges) = synthetic_graph2(50, 5);
    let mut r = rng(6);
    let start: Vec<Pose2> = truth
        .iter()
        .enumerate()
        .map(|(k, p)| {
            if k == 0 {
                *p
            } else {
                p.plus(&random_vec::<3>(&mut r, 0.3))
            }
        })
        .collect();
    let mut graph = PoseGraph2 {
        ids: (0..truth.len()).collect(),
        poses: start,
        edges,
        fixed: vec![],
    };
    let report = solve_pose_graph2(&mut graph, &tight()).unwrap();
    assert!(report.final_cost < 1e-12, "{report:?}");
    for (p, t) in graph.poses.iter().zip(&truth) {
        let e = relative2(t, p);
        assert!(
            e.x.abs() + e.y.abs() + e.theta.abs() < 1e-6,
            "{p:?} vs {t:?}"
        );
    }
}

#[test]
fn g2o_files_solve_to_known_optimum_and_round_trip() {
    let dir = std::env::temp_dir().join(format!("dhptam-solver-pg-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (truth, edges) = synthetic_graph3(30, 7);
    let mut r = rng(8);
    let graph = PoseGraph::Se3(PoseGraph3 {
        // Vertex ids need not be 0..n.
        ids: (0..truth.len()).map(|k| 100 + 2 * k).collect(),
        poses: truth
            .iter()
            .map(|p| *p * Se3::exp(&random_vec::<6>(&mut r, 0.1)))
            .collect(),
        edges,
        fixed: vec![0],
    });
    let path = dir.join("graph.g2o");
    graph.write(&path).unwrap();
    let PoseGraph::Se3(mut read) = PoseGraph::read(&path).unwrap() else {
        panic!("an SE3 graph was written")
    };
    assert_eq!(
        read.ids,
        (0..truth.len()).map(|k| 100 + 2 * k).collect::<Vec<_>>()
    );
    assert_eq!(read.fixed, vec![0]);
    let report = solve_pose_graph3(&mut read, &tight()).unwrap();
    assert!(report.final_cost < 1e-12);
    // The optimum is the truth moved by the fixed vertex's offset.
    let offset = read.poses[0] * truth[0].inverse();
    for (p, t) in read.poses.iter().zip(&truth) {
        assert!(se3_distance(p, &(offset * *t)) < 1e-7);
    }
    // Written back and read again, the optimised graph keeps its cost at the optimum.
    let out = dir.join("optimised.g2o");
    PoseGraph::Se3(read.clone()).write(&out).unwrap();
    let PoseGraph::Se3(mut again) = PoseGraph::read(&out).unwrap() else {
        panic!("an SE3 graph was written")
    };
    let report = solve_pose_graph3(&mut again, &tight()).unwrap();
    assert!(report.initial_cost < 1e-12, "{}", report.initial_cost);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn robust_loss_rejects_wrong_loop_closures() {
    let (truth, mut edges) = synthetic_graph2(60, 9);
    let mut r = rng(10);
    // Corrupt every fifth edge (20 %), odometry and loop closures alike.
    let n_edges = edges.len();
    let mut corrupted = 0;
    for (k, e) in edges.iter_mut().enumerate() {
        if k % 5 == 2 {
            e.measurement = Pose2 {
                x: r.random_range(-5.0..5.0),
                y: r.random_range(-5.0..5.0),
                theta: r.random_range(-3.0..3.0),
            };
            corrupted += 1;
        }
    }
    assert!(corrupted * 5 >= n_edges - 4, "{corrupted} of {n_edges}");
    let start = PoseGraph2 {
        ids: (0..truth.len()).collect(),
        poses: truth.clone(),
        edges,
        fixed: vec![],
    };
    let error = |g: &PoseGraph2| {
        g.poses
            .iter()
            .zip(&truth)
            .map(|(p, t)| {
                let e = relative2(t, p);
                (e.x * e.x + e.y * e.y).sqrt()
            })
            .fold(0.0, f64::max)
    };
    let mut plain = start.clone();
    solve_pose_graph2(&mut plain, &tight()).unwrap();
    let mut robust = start.clone();
    let options = PoseGraphOptions {
        loss: Loss::Cauchy(1.0),
        ..tight()
    };
    solve_pose_graph2(&mut robust, &options).unwrap();
    // Starting from odometry-consistent poses the outliers pull least squares metres away;
    // the Cauchy loss stays within a few centimetres of the truth.
    assert!(error(&plain) > 0.5, "least squares error {}", error(&plain));
    assert!(error(&robust) < 0.1, "robust error {}", error(&robust));
}

#[test]
fn information_matrix_weights_the_cost() {
    // One edge, one free vertex: the cost is ½ eᵀΩe for the start's error e exactly.
    let a = Se3::identity();
    let b = Se3::exp(&Vector6::new(0.1, -0.2, 0.3, 0.01, 0.02, -0.03));
    let z = Se3::identity();
    let info = SMatrix::<f64, 6, 6>::from_fn(|r, c| if r == c { 2.0 + r as f64 } else { 0.1 });
    let e = Se3::between_error(&a, &b, &z);
    let expected = 0.5 * (e.transpose() * info * e)[0];
    let mut graph = PoseGraph3 {
        ids: vec![0, 1],
        poses: vec![a, b],
        edges: vec![EdgeSe3 {
            from: 0,
            to: 1,
            measurement: z,
            information: info,
        }],
        fixed: vec![],
    };
    let report = solve_pose_graph3(&mut graph, &tight()).unwrap();
    assert!((report.initial_cost - expected).abs() < 1e-14 * expected.max(1.0));
    assert!(report.final_cost < 1e-20);
    let _ = Vector3::<f64>::zeros();
}
