//! End-to-end tests of the SLAM back-end on synthetic stereo feature sequences.

use dhptam_core::config::Config;
use dhptam_core::geometry::Se3;
use dhptam_core::matching::Descriptors;
use dhptam_core::slam::synthetic::{generate, SyntheticFrame, SyntheticOptions};
use dhptam_core::slam::{FrameFeatures, System, TrackResult, TrackState};
use nalgebra::{Matrix3, Vector3};

fn track(system: &mut System, f: &SyntheticFrame) -> TrackResult {
    let dim = 32;
    let left = FrameFeatures {
        keypoints: &f.left.keypoints,
        descriptors: Descriptors::float(&f.left.descriptors, dim).unwrap(),
    };
    let right = FrameFeatures {
        keypoints: &f.right.keypoints,
        descriptors: Descriptors::float(&f.right.descriptors, dim).unwrap(),
    };
    system.track(f.t_ns, left, right).unwrap()
}

/// RMS position error after the best rigid alignment (Horn/Umeyama without scale).
fn ate(estimated: &[Vector3<f64>], truth: &[Vector3<f64>]) -> f64 {
    let n = estimated.len() as f64;
    let me = estimated.iter().sum::<Vector3<f64>>() / n;
    let mt = truth.iter().sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    for (e, t) in estimated.iter().zip(truth) {
        h += (t - mt) * (e - me).transpose();
    }
    let svd = h.svd(true, true);
    let (u, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * vt;
    let t = mt - r * me;
    let sum: f64 = estimated
        .iter()
        .zip(truth)
        .map(|(e, g)| (r * e + t - g).norm_squared())
        .sum();
    (sum / n).sqrt()
}

fn positions(poses: &[(i64, Se3)]) -> Vec<Vector3<f64>> {
    poses.iter().map(|(_, p)| p.translation).collect()
}

#[test]
fn tracks_every_frame_of_a_noisy_sequence_with_outliers() {
    let o = SyntheticOptions::default();
    let frames = generate(&o);
    let mut system = System::new(o.calib, Config::default(), false).unwrap();
    for f in &frames {
        let r = track(&mut system, f);
        assert!(
            matches!(r.state, TrackState::Ok | TrackState::Initialised),
            "frame {} lost ({} inliers)",
            f.t_ns,
            r.inliers
        );
    }
    let traj = system.trajectory();
    assert_eq!(traj.len(), frames.len());
    let truth: Vec<Vector3<f64>> = frames
        .iter()
        .map(|f| f.world_from_cam.translation)
        .collect();
    let e = ate(&positions(&traj), &truth);
    let kfs = system.keyframe_trajectory().len();
    eprintln!(
        "ATE {e:.4} m over {} frames, {kfs} keyframes, {:?}",
        frames.len(),
        system.timing()
    );
    assert!(e < 0.03, "ATE {e} m");
    assert!(kfs > 2 && kfs < frames.len() / 2, "{kfs} keyframes");
}
