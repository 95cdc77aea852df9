//! Helpers shared by the SLAM integration tests (`slam.rs`, `slam_long_runs.rs`).

// Each test crate compiles this module and uses its own subset of it.
#![allow(dead_code)]

use dhptam_core::fusion::EventStereo;
use dhptam_core::geometry::Se3;
use dhptam_core::matching::Descriptors;
use dhptam_core::slam::synthetic::{SyntheticFrame, SyntheticView};
use dhptam_core::slam::{DisparityCorrection, FrameFeatures, System, TrackResult};
use nalgebra::{Matrix3, Vector3};

/// One synthetic view's features (32-float descriptors, 1 px each) read with `disparity` and
/// `event_stereo`.
pub fn view_features<'a>(
    view: &'a SyntheticView,
    disparity: DisparityCorrection,
    event_stereo: Option<&'a EventStereo>,
) -> FrameFeatures<'a> {
    FrameFeatures {
        keypoints: &view.keypoints,
        descriptors: Descriptors::float(&view.descriptors, 32).unwrap(),
        sigmas: None,
        sigma_scale: 1.0,
        disparity,
        event_stereo,
        viewpoint: [0.0; 3],
        dvs_biased: false,
        quiet: false,
    }
}

/// One synthetic frame's (left, right) features as measured.
pub fn frame_features(f: &SyntheticFrame) -> (FrameFeatures<'_>, FrameFeatures<'_>) {
    let plain = |view| view_features(view, DisparityCorrection::IDENTITY, None);
    (plain(&f.left), plain(&f.right))
}

/// Tracks one synthetic frame (32-float descriptors).
pub fn track(system: &mut System, f: &SyntheticFrame) -> TrackResult {
    let (left, right) = frame_features(f);
    system.track(f.t_ns, left, right).unwrap()
}

/// The true camera centres of `frames`, in order (what [`ate`] compares a trajectory with).
pub fn truth_positions(frames: &[SyntheticFrame]) -> Vec<Vector3<f64>> {
    frames
        .iter()
        .map(|f| f.world_from_cam.translation)
        .collect()
}

/// The rigid transform (rotation, translation) that best maps `estimated` onto `truth`
/// (Horn/Umeyama without scale).
pub fn align(estimated: &[Vector3<f64>], truth: &[Vector3<f64>]) -> (Matrix3<f64>, Vector3<f64>) {
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
    (r, mt - r * me)
}

/// RMS position error after the best rigid alignment.
pub fn ate(estimated: &[Vector3<f64>], truth: &[Vector3<f64>]) -> f64 {
    let (r, t) = align(estimated, truth);
    let sum: f64 = estimated
        .iter()
        .zip(truth)
        .map(|(e, g)| (r * e + t - g).norm_squared())
        .sum();
    (sum / estimated.len() as f64).sqrt()
}

/// The positions of `(t_ns, world_from_cam)` poses.
pub fn positions(poses: &[(i64, Se3)]) -> Vec<Vector3<f64>> {
    poses.iter().map(|(_, p)| p.translation).collect()
}
