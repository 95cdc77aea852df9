//! Motion-only pose refinement: the stereo and monocular residual Jacobians against central
//! finite differences, recovery of the true pose from a perturbed start, and 20 % gross
//! outliers down-weighted by the Huber loss and flagged in the inlier statistics; per-observation
//! σ: conflicting observations pull the pose in proportion to 1/σ², the outlier bound widens
//! with σ, bad σ are refused.

use dhptam_core::geometry::Se3;
use dhptam_core::solver::pose::{pose_residual, pose_residual_seen_from};
use dhptam_core::solver::{
    refine_pose, refine_pose_seen_from, refine_pose_weighted, LmOptions, Loss, PoseObservation,
    PoseOptions, StereoIntrinsics,
};
use nalgebra::{Vector2, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const K: StereoIntrinsics = StereoIntrinsics {
    fx: 450.0,
    fy: 460.0,
    cx: 320.0,
    cy: 240.0,
    baseline: 0.12,
};

fn scene(n: usize, seed: u64, truth: &Se3) -> Vec<PoseObservation> {
    scene_seen_from(n, seed, truth, Vector3::zeros())
}

/// Noise-free observations made by a camera pair whose centre sits at `viewpoint` in the
/// true camera's axes (same orientation and baseline).
fn scene_seen_from(
    n: usize,
    seed: u64,
    truth: &Se3,
    viewpoint: Vector3<f64>,
) -> Vec<PoseObservation> {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    let world_from_cam = truth.inverse();
    (0..n)
        .map(|i| {
            // Points in front of the true camera, 1–15 m away.
            let pc = Vector3::new(
                r.random_range(-4.0..4.0),
                r.random_range(-3.0..3.0),
                r.random_range(1.0..15.0),
            );
            let point = world_from_cam.transform_point(&pc);
            let pc = pc - viewpoint;
            let pixel = Vector2::new(K.fx * pc.x / pc.z + K.cx, K.fy * pc.y / pc.z + K.cy);
            if i % 4 == 3 {
                PoseObservation::Mono { point, pixel }
            } else {
                PoseObservation::Stereo {
                    point,
                    pixel,
                    u_right: K.fx * (pc.x - K.baseline) / pc.z + K.cx,
                }
            }
        })
        .collect()
}

fn truth() -> Se3 {
    Se3::exp(&Vector6::new(0.3, -0.2, 1.0, 0.1, -0.3, 0.05))
}

type Residual = Option<(Vector3<f64>, nalgebra::SMatrix<f64, 3, 6>, usize)>;

/// Each observation's analytic Jacobian at `start` against central finite differences of
/// `residual` (pose, observation) over the left-multiplied update.
fn assert_jacobians_match(
    obs: &[PoseObservation],
    start: &Se3,
    residual: impl Fn(&Se3, &PoseObservation) -> Residual,
) {
    let h = 1e-6;
    for o in obs {
        let (_, j, dim) = residual(start, o).unwrap();
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let (rp, _, _) = residual(&(Se3::exp(&d) * *start), o).unwrap();
            let (rm, _, _) = residual(&(Se3::exp(&-d) * *start), o).unwrap();
            let fd = (rp - rm) / (2.0 * h);
            for row in 0..dim {
                assert!(
                    (fd[row] - j[(row, k)]).abs() < 1e-5 * (1.0 + fd[row].abs()),
                    "row {row} column {k}: {} vs {}",
                    j[(row, k)],
                    fd[row]
                );
            }
        }
    }
}

#[test]
fn residual_jacobians_match_finite_differences() {
    let pose = truth();
    let obs = scene(40, 1, &pose);
    let start = Se3::exp(&Vector6::new(0.02, 0.01, -0.03, 0.01, 0.02, -0.01)) * pose;
    assert_jacobians_match(&obs, &start, |p, o| pose_residual(&K, p, o, 1e-6));
}

#[test]
fn residual_jacobians_match_finite_differences_with_a_viewpoint() {
    let pose = truth();
    let c = Vector3::new(0.01, -0.03, 0.02);
    let obs = scene_seen_from(40, 7, &pose, c);
    let start = Se3::exp(&Vector6::new(0.02, 0.01, -0.03, 0.01, 0.02, -0.01)) * pose;
    assert_jacobians_match(&obs, &start, |p, o| {
        pose_residual_seen_from(&K, p, o, &c, 1e-6)
    });
}

/// Observations from a camera 3 cm below the tracked one: with their viewpoint the true pose
/// comes back; read as the tracked camera's own, the centre is off by about the offset. Zero
/// viewpoints give exactly the plain refinement; a wrong count or a NaN is refused.
#[test]
fn observations_from_another_viewpoint_recover_the_true_pose() {
    let pose = truth();
    let c = Vector3::new(0.0, 0.03, 0.0);
    let obs = scene_seen_from(200, 8, &pose, c);
    let options = PoseOptions {
        loss: Loss::Trivial,
        lm: LmOptions {
            max_iterations: 30,
            ..Default::default()
        },
        ..Default::default()
    };
    let start = Se3::exp(&Vector6::new(0.05, -0.05, 0.05, 0.02, -0.02, 0.01)) * pose;
    let sigmas = vec![1.0; obs.len()];
    let seen = refine_pose_seen_from(start, &K, &obs, &sigmas, &vec![c; obs.len()], &options);
    let err = (seen.unwrap().cam_from_world * pose.inverse()).log().norm();
    assert!(err < 1e-7, "pose error {err}");
    let zeros = vec![Vector3::zeros(); obs.len()];
    let plain = refine_pose_weighted(start, &K, &obs, &sigmas, &options).unwrap();
    let as_own = refine_pose_seen_from(start, &K, &obs, &sigmas, &zeros, &options).unwrap();
    assert_eq!(plain.cam_from_world, as_own.cam_from_world);
    let centre_err =
        (plain.cam_from_world.inverse().translation - pose.inverse().translation).norm();
    assert!(
        (0.02..0.04).contains(&centre_err),
        "the unmodelled offset moves the centre by {centre_err} m"
    );
    let short = refine_pose_seen_from(start, &K, &obs, &sigmas, &zeros[1..], &options);
    assert!(short.unwrap_err().to_string().contains("viewpoints"));
    let mut bad = zeros.clone();
    bad[3].y = f64::NAN;
    let nan = refine_pose_seen_from(start, &K, &obs, &sigmas, &bad, &options);
    assert!(nan.unwrap_err().to_string().contains("viewpoints[3]"));
}

#[test]
fn recovers_true_pose_from_perturbed_start() {
    let pose = truth();
    let obs = scene(200, 2, &pose);
    let start = Se3::exp(&Vector6::new(0.1, -0.05, 0.1, 0.05, -0.04, 0.03)) * pose;
    let options = PoseOptions {
        loss: Loss::Trivial,
        lm: LmOptions {
            max_iterations: 30,
            ..Default::default()
        },
        ..Default::default()
    };
    let result = refine_pose(start, &K, &obs, &options).unwrap();
    let err = (result.cam_from_world * pose.inverse()).log().norm();
    assert!(err < 1e-9, "pose error {err}");
    assert_eq!(result.inlier_count, obs.len());
    assert!(result.inlier_rms < 1e-6);
}

#[test]
fn huber_refinement_survives_20_percent_outliers() {
    let pose = truth();
    let mut obs = scene(500, 3, &pose);
    let mut r = ChaCha8Rng::seed_from_u64(4);
    let mut corrupted = vec![false; obs.len()];
    for (i, o) in obs.iter_mut().enumerate() {
        if i % 5 == 0 {
            corrupted[i] = true;
            let shift = Vector2::new(r.random_range(20.0..60.0), r.random_range(-60.0..-20.0));
            match o {
                PoseObservation::Mono { pixel, .. } | PoseObservation::Stereo { pixel, .. } => {
                    *pixel += shift
                }
            }
        }
    }
    let start = Se3::exp(&Vector6::new(0.05, 0.05, -0.05, 0.02, 0.02, -0.02)) * pose;
    let lm = LmOptions {
        max_iterations: 30,
        ..Default::default()
    };
    let plain = refine_pose(
        start,
        &K,
        &obs,
        &PoseOptions {
            loss: Loss::Trivial,
            lm: lm.clone(),
            ..Default::default()
        },
    )
    .unwrap();
    let robust = refine_pose(
        start,
        &K,
        &obs,
        &PoseOptions {
            lm,
            ..Default::default()
        },
    )
    .unwrap();
    let err = |p: &Se3| (*p * pose.inverse()).log().norm();
    // Huber keeps a bounded pull per outlier: a small bias, an order of magnitude under the
    // least-squares one; the Tukey loss removes it entirely.
    assert!(
        err(&robust.cam_from_world) < 2e-3,
        "robust {}",
        err(&robust.cam_from_world)
    );
    assert!(err(&plain.cam_from_world) > 10.0 * err(&robust.cam_from_world));
    let tukey = refine_pose(
        robust.cam_from_world,
        &K,
        &obs,
        &PoseOptions {
            loss: Loss::Tukey(5.0),
            lm: LmOptions {
                max_iterations: 30,
                ..Default::default()
            },
            ..Default::default()
        },
    )
    .unwrap();
    assert!(
        err(&tukey.cam_from_world) < 1e-9,
        "tukey {}",
        err(&tukey.cam_from_world)
    );
    // The inlier flags at the Tukey result are exactly the uncorrupted observations.
    let flagged: Vec<bool> = tukey.inliers.iter().map(|&i| !i).collect();
    assert_eq!(flagged, corrupted);
}

/// Distance between two poses on SE(3) (norm of the tangent of a · b⁻¹).
fn distance(a: &Se3, b: &Se3) -> f64 {
    (*a * b.inverse()).log().norm()
}

#[test]
fn observations_with_larger_sigma_pull_the_pose_less() {
    // Two sets of observations that disagree: one consistent with `precise` (σ = 1 px), the
    // other with `vague`, 5 cm and 0.6° away (σ = 4 px). Weighted least squares puts the
    // estimate about 1/(1 + 16) of the way from `precise` to `vague`; with equal σ it would
    // sit about halfway.
    let precise = truth();
    let vague = Se3::exp(&Vector6::new(0.04, -0.03, 0.0, 0.01, 0.0, 0.0)) * precise;
    let separation = distance(&precise, &vague);
    let mut obs = scene(60, 11, &precise);
    obs.extend(scene(60, 12, &vague));
    let options = PoseOptions {
        loss: Loss::Trivial,
        outlier_threshold_sq: f64::INFINITY,
        lm: LmOptions {
            max_iterations: 50,
            ..Default::default()
        },
        ..Default::default()
    };
    let solve = |sigma_precise: f64, sigma_vague: f64| {
        let mut sigmas = vec![sigma_precise; 60];
        sigmas.extend(vec![sigma_vague; 60]);
        refine_pose_weighted(precise, &K, &obs, &sigmas, &options)
            .unwrap()
            .cam_from_world
    };
    let weighted = solve(1.0, 4.0);
    assert!(
        distance(&weighted, &precise) < 0.15 * separation,
        "σ 1 vs 4 px: {} from the precise pose, {} from the vague one",
        distance(&weighted, &precise),
        distance(&weighted, &vague)
    );
    // The same with the roles swapped: the estimate follows whichever set is precise.
    let swapped = solve(4.0, 1.0);
    assert!(distance(&swapped, &vague) < 0.15 * separation);
    // Equal σ (any common value): between the two, near neither.
    for sigma in [1.0, 4.0] {
        let equal = solve(sigma, sigma);
        assert!(distance(&equal, &precise) > 0.25 * separation);
        assert!(distance(&equal, &vague) > 0.25 * separation);
    }
    // Unit σ is `refine_pose`.
    let unit = refine_pose(precise, &K, &obs, &options)
        .unwrap()
        .cam_from_world;
    assert!(distance(&unit, &solve(1.0, 1.0)) < 1e-9);
}

#[test]
fn outlier_bound_widens_with_sigma() {
    // One observation 4 px off in u: 16 px² exceeds the 7.815 bound at σ = 1 px but its
    // whitened 16/4 = 4 lies inside at σ = 2 px.
    let pose = truth();
    let mut obs = scene(40, 3, &pose);
    if let PoseObservation::Stereo { pixel, .. } = &mut obs[0] {
        pixel.x += 4.0;
    } else {
        panic!("observation 0 is stereo");
    }
    let options = PoseOptions::default();
    let mut sigmas = vec![1.0; obs.len()];
    let r = refine_pose_weighted(pose, &K, &obs, &sigmas, &options).unwrap();
    assert!(!r.inliers[0]);
    assert_eq!(r.inlier_count, obs.len() - 1);
    sigmas[0] = 2.0;
    let r = refine_pose_weighted(pose, &K, &obs, &sigmas, &options).unwrap();
    assert!(r.inliers[0]);
    assert_eq!(r.inlier_count, obs.len());
}

#[test]
fn bad_sigmas_are_refused() {
    let pose = truth();
    let obs = scene(10, 4, &pose);
    let options = PoseOptions::default();
    let short = vec![1.0; obs.len() - 1];
    assert!(refine_pose_weighted(pose, &K, &obs, &short, &options).is_err());
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let mut sigmas = vec![1.0; obs.len()];
        sigmas[3] = bad;
        let e = refine_pose_weighted(pose, &K, &obs, &sigmas, &options).unwrap_err();
        assert!(e.to_string().contains("sigmas[3]"), "{e}");
    }
}
