//! End-to-end tests of the SLAM back-end on synthetic stereo feature sequences.
//!
//! Sizes are kept small (≈ 150–200 features a frame) so the unoptimised `cargo test` build
//! stays quick; `tests/test_system.py` runs the same scenarios at ≈ 600 features a frame.

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
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 100,
        turns: 0.25,
        ..Default::default()
    };
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
    assert!(kfs > 2 && kfs < frames.len(), "{kfs} keyframes");
}

#[test]
fn save_load_continue_gives_the_same_poses() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 60,
        turns: 0.15,
        seed: 3,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut reference = System::new(o.calib, Config::default(), false).unwrap();
    let expected: Vec<TrackResult> = frames.iter().map(|f| track(&mut reference, f)).collect();

    let dir = std::env::temp_dir().join(format!("dhptam-slam-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("map.bin");
    let mut first = System::new(o.calib, Config::default(), false).unwrap();
    for f in &frames[..30] {
        track(&mut first, f);
    }
    first.save_map(&path).unwrap();
    let mut second = System::new(o.calib, Config::default(), false).unwrap();
    second.load_map(&path).unwrap();
    assert_eq!(second.trajectory().len(), 30);
    for (f, e) in frames[30..].iter().zip(&expected[30..]) {
        let r = track(&mut second, f);
        assert_eq!(r.state, e.state);
        assert_eq!(r.keyframe, e.keyframe);
        let d = (r.world_from_cam.inverse() * e.world_from_cam).log().norm();
        assert!(d < 1e-9, "frame {}: poses differ by {d}", f.t_ns);
    }
    // A truncated file is refused with its name.
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let err = second.load_map(&path).unwrap_err().to_string();
    assert!(err.contains("map.bin"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn synchronous_mode_is_deterministic() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 30,
        turns: 0.075,
        seed: 5,
        ..Default::default()
    };
    let frames = generate(&o);
    let run = || {
        let mut s = System::new(o.calib, Config::default(), false).unwrap();
        frames.iter().for_each(|f| {
            track(&mut s, f);
        });
        s.trajectory()
    };
    let (a, b) = (run(), run());
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.1.matrix(), y.1.matrix());
    }
}

#[test]
fn threaded_stress_and_prompt_shutdown() {
    let o = SyntheticOptions {
        landmarks: 500,
        frames: 2000,
        turns: 2.0,
        seed: 11,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut system = System::new(o.calib, Config::default(), true).unwrap();
    let mut tracked = 0;
    for f in &frames[..1500] {
        let r = track(&mut system, f);
        assert_ne!(r.state, TrackState::Lost, "frame {} lost", f.t_ns);
        tracked += 1;
    }
    let start = std::time::Instant::now();
    system.shutdown();
    eprintln!("shutdown took {:?}", start.elapsed());
    let traj = system.trajectory();
    assert_eq!(traj.len(), tracked);
    assert!(traj.windows(2).all(|w| w[0].0 < w[1].0));
    assert!(traj
        .iter()
        .all(|(_, p)| p.matrix().iter().all(|v| v.is_finite())));
    let truth: Vec<Vector3<f64>> = frames[..tracked]
        .iter()
        .map(|f| f.world_from_cam.translation)
        .collect();
    let e = ate(&positions(&traj), &truth);
    eprintln!("threaded ATE {e:.4} m over {tracked} frames");
    assert!(e < 0.1, "ATE {e}");
    // After shutdown, tracking is refused.
    let f = &frames[1500];
    let left = FrameFeatures {
        keypoints: &f.left.keypoints,
        descriptors: Descriptors::float(&f.left.descriptors, 32).unwrap(),
    };
    assert!(system.track(f.t_ns, left, left).is_err());
}

fn run_loop(frames: &[SyntheticFrame], o: &SyntheticOptions, closing: bool) -> (f64, System) {
    let mut config = Config::default();
    config.loop_closing.enabled = closing;
    config.mapping.ba_iterations = 10;
    let mut system = System::new(o.calib, config, false).unwrap();
    for f in frames {
        let r = track(&mut system, f);
        assert_ne!(r.state, TrackState::Lost, "frame {} lost", f.t_ns);
    }
    let truth: Vec<Vector3<f64>> = frames
        .iter()
        .map(|f| f.world_from_cam.translation)
        .collect();
    (ate(&positions(&system.trajectory()), &truth), system)
}

#[test]
fn loop_closure_halves_the_injected_drift() {
    let o = SyntheticOptions {
        landmarks: 900,
        frames: 320,
        turns: 1.15,
        drift_deg: 4.0,
        drift_m: 0.4,
        seed: 21,
        ..Default::default()
    };
    let frames = generate(&o);
    let (before, open) = run_loop(&frames, &o, false);
    assert!(open.loop_closures().is_empty());
    let (after, closed) = run_loop(&frames, &o, true);
    let loops = closed.loop_closures();
    eprintln!("ATE without loop closing {before:.4} m, with {after:.4} m, loops {loops:?}");
    assert!(!loops.is_empty(), "no loop detected");
    // The loop joins the last quarter turn to the start.
    let (query, matched) = loops[0];
    assert!(query > frames[frames.len() * 3 / 4].t_ns && matched < frames[frames.len() / 4].t_ns);
    assert!(
        before > 0.04,
        "the injected drift did not show ({before} m)"
    );
    assert!(
        after <= 0.5 * before,
        "ATE {after} m after closure vs {before} m before"
    );
}

#[test]
fn relocalises_after_a_jump_to_a_known_place() {
    let o = SyntheticOptions {
        landmarks: 1200,
        frames: 200,
        seed: 8,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut system = System::new(o.calib, Config::default(), false).unwrap();
    let mut results = Vec::new();
    for f in &frames[..120] {
        results.push(track(&mut system, f));
    }
    // The camera "teleports" back to where frame 30 was taken (timestamps keep increasing).
    let mut jumped = frames[30].clone();
    jumped.t_ns = frames[120].t_ns;
    let r = track(&mut system, &jumped);
    assert_eq!(r.state, TrackState::Relocalised, "{} inliers", r.inliers);
    assert!(r.keyframe);
    let d = (results[30].world_from_cam.inverse() * r.world_from_cam)
        .log()
        .norm();
    assert!(
        d < 0.02,
        "relocalised pose differs from the first visit's by {d}"
    );
    // Tracking goes on from there.
    let mut next = frames[31].clone();
    next.t_ns = frames[121].t_ns;
    assert_eq!(track(&mut system, &next).state, TrackState::Ok);
}
