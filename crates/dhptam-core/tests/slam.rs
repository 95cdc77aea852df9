//! End-to-end tests of the SLAM back-end on synthetic stereo feature sequences.
//!
//! Sizes are kept small (≈ 150–200 features a frame) so the unoptimised `cargo test` build
//! stays quick; `tests/test_system.py` runs the same scenarios at ≈ 600 features a frame.

use dhptam_core::config::Config;
use dhptam_core::fusion::{Depth, EventStereo, FusionMode};
use dhptam_core::geometry::{Pinhole, Se3, So3};
use dhptam_core::matching::Descriptors;
use dhptam_core::place::{embedding, PlaceDatabase};
use dhptam_core::slam::loop_closing::{detect_and_close, verify_loop};
use dhptam_core::slam::synthetic::{generate, SyntheticFrame, SyntheticOptions};
use dhptam_core::slam::tracking::{
    insert_keyframe, reference_motion, retrack_after_correction, stereo_match, track_local_map,
    StereoFrame, TrackContext, TrackerState,
};
use dhptam_core::slam::{
    fuse_and_refind, local_mapping, DisparityCorrection, FrameFeatures, FrameRecord, Map, System,
    TrackResult, TrackState,
};
use nalgebra::{Matrix3, Vector2, Vector3};
use std::sync::{Mutex, RwLock};

mod common;
use common::{ate, frame_features, positions, track, truth_positions, view_features};

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
    let truth = truth_positions(&frames);
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

/// The slow turn the keyframe-floor tests run: at a floor of 150 it makes more keyframes than
/// at 50.
fn floor_sequence(frames: usize) -> (SyntheticOptions, Vec<SyntheticFrame>) {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames,
        turns: 0.1,
        seed: 3,
        ..Default::default()
    };
    let frames = generate(&o);
    (o, frames)
}

/// Tracks `frames` with every image flagged `dvs_biased` (or not).
fn track_flagged(s: &mut System, frames: &[SyntheticFrame], dvs_biased: bool) {
    for f in frames {
        let (mut left, mut right) = frame_features(f);
        left.dvs_biased = dvs_biased;
        right.dvs_biased = dvs_biased;
        s.track(f.t_ns, left, right).unwrap();
    }
}

/// Two runs' keyframe counts are equal and their trajectories the same pose for pose.
fn assert_same_run(a: &(usize, Vec<(i64, Se3)>), b: &(usize, Vec<(i64, Se3)>)) {
    assert_eq!(a.0, b.0, "keyframes");
    assert_eq!(a.1.len(), b.1.len());
    for (x, y) in a.1.iter().zip(&b.1) {
        assert_eq!(x.1.matrix(), y.1.matrix());
    }
}

#[test]
fn mode_events_takes_its_own_keyframe_floor() {
    let (o, frames) = floor_sequence(40);
    let run = |mode: FusionMode, events_floor: u32| {
        let mut config = Config::default();
        config.fusion.mode = mode;
        config.tracking.events_keyframe_min_tracked = events_floor;
        let mut s = System::new(o.calib, config, false).unwrap();
        frames.iter().for_each(|f| {
            track(&mut s, f);
        });
        (s.keyframe_trajectory().len(), s.trajectory())
    };
    let fusion = run(FusionMode::Fusion, 150);
    let events = run(FusionMode::Events, 150);
    let events_at_50 = run(FusionMode::Events, 50);
    eprintln!(
        "keyframes: fusion {}, events {}, events with floor 50 {}",
        fusion.0, events.0, events_at_50.0
    );
    assert!(
        events.0 > fusion.0,
        "events {} keyframes, fusion {}",
        events.0,
        fusion.0
    );
    // The floor is the only difference mode `events` makes to the back-end.
    assert_same_run(&events_at_50, &fusion);
}

#[test]
fn dvs_biased_frames_take_their_own_keyframe_floor() {
    let (o, frames) = floor_sequence(40);
    let run = |dvs_biased: bool, dvs_floor: u32| {
        let mut config = Config::default();
        config.tracking.dvs_keyframe_min_tracked = dvs_floor;
        let mut s = System::new(o.calib, config, false).unwrap();
        track_flagged(&mut s, &frames, dvs_biased);
        (s.keyframe_trajectory().len(), s.trajectory())
    };
    let plain = run(false, 150);
    let dvs = run(true, 150);
    let dvs_at_50 = run(true, 50);
    eprintln!(
        "keyframes: plain {}, DVS-biased {}, DVS-biased with floor 50 {}",
        plain.0, dvs.0, dvs_at_50.0
    );
    assert!(
        dvs.0 > plain.0,
        "DVS-biased {} keyframes, plain {}",
        dvs.0,
        plain.0
    );
    // The floor is all the flag changes: at the plain floor the run is the same.
    assert_same_run(&dvs_at_50, &plain);
}

#[test]
fn the_threaded_back_end_maps_each_dvs_biased_keyframe_before_the_next_frame() {
    // A DVS-biased keyframe is adjusted before the next frame is tracked, as the synchronous
    // back-end does: with every frame DVS-biased the threaded run gives the synchronous poses.
    let (o, frames) = floor_sequence(30);
    let run = |threaded: bool| {
        let mut s = System::new(o.calib, Config::default(), threaded).unwrap();
        track_flagged(&mut s, &frames, true);
        let waits = s.timing().get("mapping_wait").map_or(0, |t| t.count);
        s.shutdown();
        (s.trajectory(), waits)
    };
    let (sync, sync_waits) = run(false);
    let (threaded, threaded_waits) = run(true);
    assert_eq!(sync_waits, 0);
    assert!(threaded_waits > 2, "{threaded_waits} waits");
    assert_eq!(sync.len(), threaded.len());
    for (a, b) in sync.iter().zip(&threaded) {
        let d = (a.1.translation - b.1.translation).norm();
        assert!(d < 1e-9, "frame at {} ns: {d} m apart", a.0);
    }
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
    // The covariances are saved too: the smoothed trajectory (which weighs every frame by its
    // own) is the uninterrupted run's, the first 30 frames included.
    let (a, b) = (reference.trajectory(), second.trajectory());
    assert_eq!(a.len(), b.len());
    for ((ta, pa), (tb, pb)) in a.iter().zip(&b) {
        assert_eq!(ta, tb);
        let d = (pa.translation - pb.translation).norm();
        assert!(d < 1e-9, "frame {ta}: smoothed centres differ by {d}");
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
    let truth = truth_positions(&frames[..tracked]);
    let e = ate(&positions(&traj), &truth);
    eprintln!("threaded ATE {e:.4} m over {tracked} frames");
    assert!(e < 0.1, "ATE {e}");
    // After shutdown, tracking is refused.
    let f = &frames[1500];
    let left = FrameFeatures {
        keypoints: &f.left.keypoints,
        descriptors: Descriptors::float(&f.left.descriptors, 32).unwrap(),
        sigmas: None,
        sigma_scale: 1.0,
        disparity: DisparityCorrection::IDENTITY,
        event_stereo: None,
        viewpoint: [0.0; 3],
        dvs_biased: false,
        quiet: false,
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
    let truth = truth_positions(frames);
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

/// A keyframe inserted directly from a synthetic frame at `world_from_cam`, its stereo points
/// triangulated anew (no association to existing points). `mono` keypoints (indices) lose
/// their stereo match first, so they get no point.
fn insert_frame(map: &mut Map, f: &SyntheticFrame, world_from_cam: Se3, mono: &[usize]) -> u64 {
    let config = Config::default();
    let calib = SyntheticOptions::default().calib;
    let mut frame = stereo_frame(f);
    for &i in mono {
        frame.u_right[i] = f32::NAN;
    }
    insert_keyframe(
        map,
        &frame,
        world_from_cam,
        &[],
        &calib,
        &config.triangulation,
    )
    .0
}

/// The stereo frame the tracker makes of a synthetic frame (its left keypoints stereo-matched).
fn stereo_frame(f: &SyntheticFrame) -> StereoFrame<'_> {
    let config = Config::default();
    let calib = SyntheticOptions::default().calib;
    let xy = |v: &[f32]| -> Vec<[f32; 2]> { v.chunks_exact(2).map(|c| [c[0], c[1]]).collect() };
    let (lxy, rxy) = (xy(&f.left.keypoints), xy(&f.right.keypoints));
    let ld = Descriptors::float(&f.left.descriptors, 32).unwrap();
    let rd = Descriptors::float(&f.right.descriptors, 32).unwrap();
    let u_right = stereo_match(
        &calib,
        &config.tracking,
        &config.triangulation,
        &lxy,
        ld,
        &rxy,
        rd,
    );
    StereoFrame {
        t_ns: f.t_ns,
        sigmas: vec![1.0; lxy.len()],
        viewpoints: vec![[0.0; 3]; lxy.len()],
        keypoints: lxy,
        u_right,
        descriptors: ld,
        dvs_biased: false,
        quiet: false,
    }
}

#[test]
fn a_frame_tracked_before_a_loop_correction_is_tracked_again_after_it() {
    // Threaded mapping: the loop-closing thread may move the map between the tracker's read of
    // it and its commit. The frame's pose, in the old coordinates, must not be stored relative
    // to a keyframe that has moved: it is tracked again against the corrected map.
    let o = SyntheticOptions::default();
    let frames = generate(&o);
    let config = Config::default();
    let ctx = TrackContext {
        calib: &o.calib,
        cfg: &config.tracking,
        tri: &config.triangulation,
    };
    let (f0, f1) = (&frames[0], &frames[1]);
    let mut map = Map::default();
    let kf = insert_frame(&mut map, f0, f0.world_from_cam, &[]);
    let record = FrameRecord {
        t_ns: f0.t_ns,
        keyframe: kf,
        kf_from_cam: Se3::identity(),
        predicted: false,
        held: false,
        position_cov: None,
    };
    let state = TrackerState {
        last: Some(record),
        reference: Some(kf),
        measured: Some(record),
        ..Default::default()
    };
    let frame = stereo_frame(f1);
    let gap = |a: &Se3, b: &Se3| (a.inverse() * *b).translation.norm();
    let truth = f1.world_from_cam.inverse();
    let tracked = track_local_map(&map, &state, &frame, &ctx, f0.world_from_cam.inverse()).unwrap();
    assert!(gap(&tracked.cam_from_world, &truth) < 0.01);
    // No correction since: the tracked pose stands.
    assert!(retrack_after_correction(&map, &state, &frame, &ctx, map.corrections, 15).is_none());

    // A loop correction moves the whole map: world' = correction · world.
    let correction = Se3::new(
        So3::exp(&Vector3::new(0.0, 4f64.to_radians(), 0.0)),
        Vector3::new(0.15, -0.05, 0.1),
    );
    let before = map.corrections;
    for k in map.keyframes.values_mut() {
        k.world_from_cam = correction * k.world_from_cam;
    }
    for p in map.points.values_mut() {
        p.position = correction.transform_point(&p.position);
        p.normal = correction.rotation * p.normal;
    }
    map.corrections += 1;
    let (again, last) = retrack_after_correction(&map, &state, &frame, &ctx, before, 15).unwrap();
    let corrected = truth * correction.inverse();
    assert!(gap(&again.cam_from_world, &corrected) < 0.01);
    assert!(again.inliers >= 15);
    assert!(gap(&last.unwrap(), &(correction * f0.world_from_cam)) < 1e-9);
    // The pose tracked before the correction is off by it in the new coordinates.
    assert!(gap(&tracked.cam_from_world, &corrected) > 0.1);
}

#[test]
fn a_pose_tracked_before_its_keyframe_moved_is_carried_with_it() {
    // A bundle adjustment written back between tracking and commit moves the reference
    // keyframe and its points: the tracked pose is carried by the keyframe's motion.
    let o = SyntheticOptions::default();
    let frames = generate(&o);
    let mut map = Map::default();
    let kf = insert_frame(&mut map, &frames[0], frames[0].world_from_cam, &[]);
    let state = TrackerState {
        reference: Some(kf),
        ..Default::default()
    };
    let then = map.keyframes[&kf].world_from_cam;
    assert!(reference_motion(&map, &state, Some(then)).is_none());
    assert!(reference_motion(&map, &state, None).is_none());
    let step = Se3::new(
        So3::exp(&Vector3::new(0.01, 0.0, -0.02)),
        Vector3::new(0.03, 0.0, 0.01),
    );
    map.keyframes.get_mut(&kf).unwrap().world_from_cam = step * then;
    let moved = reference_motion(&map, &state, Some(then)).unwrap();
    // A frame tracked at `world_from_cam` relative to the old keyframe pose keeps its pose
    // relative to the keyframe once carried.
    let world_from_cam = frames[1].world_from_cam;
    let carried = moved * world_from_cam;
    let before = then.inverse() * world_from_cam;
    let after = map.keyframes[&kf].world_from_cam.inverse() * carried;
    assert!((before.inverse() * after).log().norm() < 1e-12);
    // A reference that is gone: nothing to carry.
    let gone = TrackerState {
        reference: Some(kf + 100),
        ..Default::default()
    };
    assert!(reference_motion(&map, &gone, Some(then)).is_none());
}

#[test]
fn the_centre_prior_holds_a_weakly_placed_keyframe_in_the_local_adjustment() {
    // Keyframe 1 goes in 2 cm off its true pose, observing keyframe 0's points. The local
    // adjustment (keyframe 0 the gauge) moves it towards the truth; with `[mapping]
    // centre_prior_scale` and a measured 1 mm tracking deviation, a factor of 0.001 (1 µm)
    // holds it where it was put when it counts as weakly tied (`centre_prior_below` above
    // its shared points), and leaves it free otherwise or with 0 (no prior).
    let o = SyntheticOptions::default();
    let frames = generate(&o);
    let adjusted_centre = |scale: f64, below: u32| {
        let mut config = Config::default();
        config.mapping.centre_prior_scale = scale;
        config.mapping.centre_prior_below = below;
        let ctx = TrackContext {
            calib: &o.calib,
            cfg: &config.tracking,
            tri: &config.triangulation,
        };
        let (f0, f1) = (&frames[0], &frames[3]);
        let mut map = Map::default();
        let kf0 = insert_frame(&mut map, f0, f0.world_from_cam, &[]);
        let state = TrackerState {
            reference: Some(kf0),
            ..Default::default()
        };
        let frame = stereo_frame(f1);
        let tracked =
            track_local_map(&map, &state, &frame, &ctx, f1.world_from_cam.inverse()).unwrap();
        assert!(tracked.inliers > 50, "{} inliers", tracked.inliers);
        let off = Se3::new(So3::identity(), Vector3::new(0.02, 0.0, 0.0)) * f1.world_from_cam;
        let (kf1, _) = insert_keyframe(&mut map, &frame, off, &tracked.matches, &o.calib, ctx.tri);
        for (t_ns, keyframe) in [(f0.t_ns, kf0), (f1.t_ns, kf1)] {
            map.trajectory.push(FrameRecord {
                t_ns,
                keyframe,
                kf_from_cam: Se3::identity(),
                predicted: false,
                held: false,
                position_cov: Some(Matrix3::identity() * 1e-6),
            });
        }
        let map = std::sync::RwLock::new(map);
        let c = &config;
        local_mapping(
            &map,
            kf1,
            &o.calib,
            &c.mapping,
            &c.tracking,
            &c.triangulation,
            None,
        )
        .unwrap();
        let m = map.read().unwrap();
        (
            m.keyframes[&kf1].centre(),
            off.translation,
            f1.world_from_cam.translation,
        )
    };
    for (scale, below) in [(0.0, u32::MAX), (1e-3, 1)] {
        let (free, start, truth) = adjusted_centre(scale, below);
        assert!(
            (free - truth).norm() < 0.5 * (start - truth).norm(),
            "scale {scale}, below {below}: {:.4} m from the truth, started {:.4} m",
            (free - truth).norm(),
            (start - truth).norm()
        );
    }
    let (held, start, _) = adjusted_centre(1e-3, u32::MAX);
    assert!(
        (held - start).norm() < 1e-4,
        "held {:.6} m away",
        (held - start).norm()
    );
}

/// Two keyframes at the two ends of a loop (a bit more than one turn apart), each with its own
/// points; the query's whole part of the map is displaced by a drift transform.
fn loop_pair() -> (Map, u64, u64) {
    loop_pair_with_drift(3.0)
}

/// `loop_pair` with the drift turning the query's part by `drift_deg` about the vertical.
fn loop_pair_with_drift(drift_deg: f64) -> (Map, u64, u64) {
    let o = SyntheticOptions {
        landmarks: 1500,
        frames: 200,
        turns: 1.05,
        seed: 4,
        ..Default::default()
    };
    let frames = generate(&o);
    let (first, last) = (&frames[0], &frames[frames.len() - 1]);
    let drift = Se3::new(
        So3::exp(&Vector3::new(0.0, drift_deg.to_radians(), 0.0)),
        Vector3::new(0.2, 0.1, -0.3),
    );
    let mut map = Map::default();
    let candidate = insert_frame(&mut map, first, first.world_from_cam, &[]);
    let query = insert_frame(&mut map, last, drift * last.world_from_cam, &[]);
    (map, query, candidate)
}

fn point_ids(map: &Map, kf: u64) -> Vec<u64> {
    map.keyframes[&kf]
        .points
        .iter()
        .flatten()
        .copied()
        .collect()
}

#[test]
fn loop_verification_needs_both_directions_to_agree() {
    let config = Config::default();
    let (lc, tc) = (&config.loop_closing, &config.tracking);
    let calib = SyntheticOptions::default().calib;
    let need = lc.min_inliers as usize;
    let (map, query, candidate) = loop_pair();

    // A true loop (under drift) passes both ways, the relative poses agree.
    let (check, m) = verify_loop(&map, query, candidate, &calib, tc, lc).unwrap();
    eprintln!("true loop: {check:?}");
    assert!(check.accepted, "{check:?}");
    assert!(check.forward.1 >= need && check.backward.1 >= need);
    let (r, t) = check.disagreement.unwrap();
    assert!(
        r < 0.5 * lc.max_disagreement_deg && t < 0.5 * lc.max_disagreement_m,
        "{check:?}"
    );
    let m = m.unwrap();
    assert_eq!(m.candidate, candidate);

    // The query's points scrambled (each takes another's position): the forward direction
    // still passes, the backward one finds no pose → rejected.
    let mut scrambled = map.clone();
    let ids = point_ids(&scrambled, query);
    let positions: Vec<Vector3<f64>> = ids.iter().map(|id| scrambled.points[id].position).collect();
    for (k, id) in ids.iter().enumerate() {
        scrambled.points.get_mut(id).unwrap().position = positions[(k * 7 + 3) % ids.len()];
    }
    let (check, m) = verify_loop(&scrambled, query, candidate, &calib, tc, lc).unwrap();
    eprintln!("backward broken: {check:?}");
    assert!(check.forward.1 >= need, "{check:?}");
    assert_eq!(check.backward.1, 0, "{check:?}");
    assert!(!check.accepted && m.is_none());

    // The same with the candidate's points: backward passes, forward fails → rejected.
    let mut scrambled = map.clone();
    let ids = point_ids(&scrambled, candidate);
    let positions: Vec<Vector3<f64>> = ids.iter().map(|id| scrambled.points[id].position).collect();
    for (k, id) in ids.iter().enumerate() {
        scrambled.points.get_mut(id).unwrap().position = positions[(k * 7 + 3) % ids.len()];
    }
    let (check, m) = verify_loop(&scrambled, query, candidate, &calib, tc, lc).unwrap();
    eprintln!("forward broken: {check:?}");
    assert_eq!(check.forward.1, 0, "{check:?}");
    assert!(check.backward.1 >= need, "{check:?}");
    assert!(!check.accepted && m.is_none());

    // The query's points moved rigidly by 5° about the query camera's vertical axis, its pose
    // not: both directions find a pose, but the relative poses disagree → rejected.
    let mut bent = map.clone();
    let q_pose = bent.keyframes[&query].world_from_cam;
    let turn = q_pose
        * Se3::new(
            So3::exp(&Vector3::new(0.0, 5f64.to_radians(), 0.0)),
            Vector3::zeros(),
        )
        * q_pose.inverse();
    for id in point_ids(&bent, query) {
        let p = bent.points.get_mut(&id).unwrap();
        p.position = turn.transform_point(&p.position);
    }
    let (check, m) = verify_loop(&bent, query, candidate, &calib, tc, lc).unwrap();
    eprintln!("inconsistent: {check:?}");
    assert!(
        check.forward.1 >= need && check.backward.1 >= need,
        "{check:?}"
    );
    let (r, _) = check.disagreement.unwrap();
    assert!(r > lc.max_disagreement_deg, "{check:?}");
    assert!(!check.accepted && m.is_none());
}

#[test]
fn a_loop_that_would_turn_a_keyframe_of_one_map_too_far_is_rejected() {
    let calib = SyntheticOptions::default().calib;
    let (map, query, candidate) = loop_pair_with_drift(60.0);
    let close = |mut map: Map, max_correction_deg: f64| {
        let mut config = Config::default();
        // Synthetic descriptors are random per frame: place recognition is not under test.
        config.loop_closing.skip_recent = 0;
        config.loop_closing.min_score = 0.0;
        config.loop_closing.max_correction_deg = max_correction_deg;
        let mut db = PlaceDatabase::new();
        let e = embedding(map.keyframes[&candidate].descriptors.view()).unwrap();
        db.add(candidate, e).unwrap();
        let loops_before = map.loops.len();
        let lock = RwLock::new(std::mem::take(&mut map));
        let found = detect_and_close(
            &lock,
            &Mutex::new(db),
            query,
            &calib,
            &config.tracking,
            &config.loop_closing,
        )
        .unwrap();
        let map = lock.into_inner().unwrap();
        assert_eq!(map.loops.len() - loops_before, usize::from(found.is_some()));
        found
    };
    // The 60° drift is rigid, so the loop verifies; within one map it turns the query too far.
    assert_eq!(close(map.clone(), 180.0), Some(candidate));
    assert_eq!(close(map.clone(), 45.0), None);
    // A query that starts a map segment of its own has a guessed pose: the loop joins it.
    let mut segmented = map;
    segmented.segment_starts.insert(query);
    assert_eq!(close(segmented, 45.0), Some(candidate));
}

fn observations_per_point(map: &Map) -> f64 {
    let total: usize = map.points.values().map(|p| p.observations.len()).sum();
    total as f64 / map.points.len() as f64
}

#[test]
fn fusion_merges_duplicates_and_refinds_points() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 100,
        turns: 0.25,
        seed: 6,
        ..Default::default()
    };
    let frames = generate(&o);
    // The two keyframes share no points (not covisible): they meet as temporal neighbours.
    let mut config = Config::default();
    config.mapping.fuse_temporal = 2;
    // Two keyframes five frames apart, inserted without association (as after tracking loss):
    // every landmark both see is in the map twice. A quarter of the second keyframe's
    // keypoints have no stereo match, so no point: those are for re-finding.
    let mut map = Map::default();
    let a = insert_frame(&mut map, &frames[0], frames[0].world_from_cam, &[]);
    let n = frames[5].left.keypoints.len() / 2;
    let mono: Vec<usize> = (0..n).filter(|i| i % 4 == 0).collect();
    let b = insert_frame(&mut map, &frames[5], frames[5].world_from_cam, &mono);
    assert!(map.keyframes[&b].covisible.is_empty());
    let (points_before, per_point_before) = (map.points.len(), observations_per_point(&map));
    let old_ids = point_ids(&map, b);
    // Interrupted before it starts (a newer keyframe is waiting): nothing changes.
    let stopped = std::sync::RwLock::new(map.clone());
    let stop = std::sync::atomic::AtomicBool::new(true);
    let report = fuse_and_refind(
        &stopped,
        b,
        &o.calib,
        &config.mapping,
        &config.tracking,
        &config.triangulation,
        Some(&stop),
    )
    .unwrap();
    assert!(report.interrupted && report.merged + report.refound == 0);
    assert_eq!(stopped.into_inner().unwrap().points.len(), points_before);
    let lock = std::sync::RwLock::new(map);
    let report = fuse_and_refind(
        &lock,
        b,
        &o.calib,
        &config.mapping,
        &config.tracking,
        &config.triangulation,
        None,
    )
    .unwrap();
    let map = lock.into_inner().unwrap();
    eprintln!(
        "{report:?}: {points_before} → {} points, {per_point_before:.2} → {:.2} observations each",
        map.points.len(),
        observations_per_point(&map)
    );
    assert_eq!(report.neighbours, 1);
    // Most of the second keyframe's points are duplicates of the first's landmarks.
    assert!(
        2 * report.merged > old_ids.len(),
        "{report:?} of {}",
        old_ids.len()
    );
    assert!(report.refound > 20, "{report:?}");
    assert_eq!(map.points.len(), points_before - report.merged);
    assert!(observations_per_point(&map) > 1.2 * per_point_before);
    // The keyframes are now covisible through the fused points.
    assert!(map.keyframes[&b].covisible[&a] as usize >= report.merged);
    // Every fused-away id resolves to a live point that the second keyframe observes.
    let gone: Vec<u64> = old_ids
        .iter()
        .copied()
        .filter(|id| !map.points.contains_key(id))
        .collect();
    assert_eq!(gone.len(), report.merged);
    for id in gone {
        let live = map.resolve(id);
        assert!(map.points[&live].observations.contains_key(&b));
        assert!(map.points[&live].observations.contains_key(&a));
    }
    // Fused points are right: the merged observations in both keyframes are of one landmark
    // (their keypoints agree with the point's projection within the fusion radius).
    let r = config.mapping.fuse_radius_px + 2.0;
    for p in map.points.values().filter(|p| p.observations.len() == 2) {
        for (kf, &f) in &p.observations {
            let k = &map.keyframes[kf];
            let pc = k.world_from_cam.inverse().transform_point(&p.position);
            let u = o.calib.fx * pc.x / pc.z + o.calib.cx;
            let v = o.calib.fy * pc.y / pc.z + o.calib.cy;
            let kp = k.keypoints[f as usize];
            let e = ((u - kp[0] as f64).powi(2) + (v - kp[1] as f64).powi(2)).sqrt();
            assert!(e < r, "point {} off by {e} px in keyframe {kf}", p.id);
        }
    }
    // A keyframe observes each point once, and the slots agree with the observations.
    for k in map.keyframes.values() {
        for (f, p) in k.points.iter().enumerate() {
            if let Some(p) = p {
                assert_eq!(map.points[p].observations[&k.id] as usize, f);
            }
        }
    }
}

/// Runs `frames` through a synchronous system; frames in `glitch` have their descriptors
/// negated (left and right alike: stereo matching still works, matching to the map does
/// not). Returns the ATE, the system, and the number of re-initialisations.
fn run_with_glitch(
    frames: &[SyntheticFrame],
    glitch: std::ops::Range<usize>,
    config: Config,
) -> (f64, System, usize) {
    let calib = SyntheticOptions::default().calib;
    let mut system = System::new(calib, config, false).unwrap();
    let mut restarts = 0;
    for (i, f) in frames.iter().enumerate() {
        let r = if glitch.contains(&i) {
            let mut g = f.clone();
            g.left.descriptors.iter_mut().for_each(|x| *x = -*x);
            g.right.descriptors.iter_mut().for_each(|x| *x = -*x);
            track(&mut system, &g)
        } else {
            track(&mut system, f)
        };
        assert_ne!(r.state, TrackState::Lost, "frame {i} lost");
        if i > 0 && r.state == TrackState::Initialised {
            restarts += 1;
        }
    }
    let truth = truth_positions(frames);
    (
        ate(&positions(&system.trajectory()), &truth),
        system,
        restarts,
    )
}

/// Whether the covisibility graph connects the last keyframe to the first.
fn reaches_first_keyframe(m: &Map) -> bool {
    let last = *m.keyframes.keys().last().unwrap();
    let mut seen = vec![last];
    let mut frontier = vec![last];
    while let Some(k) = frontier.pop() {
        for &c in m.keyframes[&k].covisible.keys() {
            if !seen.contains(&c) {
                seen.push(c);
                frontier.push(c);
            }
        }
    }
    seen.contains(&0)
}

#[test]
fn fusion_joins_map_segments_after_reinitialisation() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 90,
        turns: 0.2,
        seed: 9,
        ..Default::default()
    };
    let frames = generate(&o);
    // Relocalisation is switched off (no keyframe pair reaches a cosine of 1), so a frame that
    // cannot be tracked starts a new map segment: the glitch frame one of its own, the frame
    // after it another, whose points duplicate the first segment's landmarks.
    let mut config = Config::default();
    config.loop_closing.min_score = 1.0;
    // Linking the new segment to the old one needs the temporal neighbours (off by default).
    config.mapping.fuse_temporal = 2;
    config.mapping.fuse = false;
    let (ate_off, off, restarts) = run_with_glitch(&frames, 40..41, config.clone());
    assert_eq!(restarts, 2);
    config.mapping.fuse = true;
    let (ate_on, on, restarts_on) = run_with_glitch(&frames, 40..41, config);
    assert_eq!(restarts_on, 2);
    let stats = |s: &System| s.with_map(|m| (m.points.len(), observations_per_point(m)));
    let ((n_off, per_off), (n_on, per_on)) = (stats(&off), stats(&on));
    let totals = on.fusion_totals();
    eprintln!(
        "without fusion: {n_off} points, {per_off:.2} observations each, ATE {ate_off:.4} m; \
         with: {n_on} points, {per_on:.2} each, ATE {ate_on:.4} m; {totals:?}"
    );
    assert_eq!(off.fusion_totals().merged, 0);
    assert!(totals.merged > 50, "{totals:?}");
    assert!(totals.refound > 0, "{totals:?}");
    assert!(n_on < n_off, "{n_on} points with fusion, {n_off} without");
    assert!(
        per_on > per_off,
        "{per_on} observations per point vs {per_off}"
    );
    // The segments are joined: the last keyframe's neighbourhood reaches back past the glitch.
    assert!(!off.with_map(reaches_first_keyframe));
    assert!(on.with_map(reaches_first_keyframe));
    assert!(
        ate_on <= ate_off * 1.05 + 1e-3,
        "ATE {ate_on} with fusion, {ate_off} without"
    );
}

/// A frame's features with the descriptors negated (the "other appearance": stereo matching
/// works within it, matching against the normal map does not).
fn negated(f: &SyntheticFrame) -> SyntheticFrame {
    let mut g = f.clone();
    g.left.descriptors.iter_mut().for_each(|x| *x = -*x);
    g.right.descriptors.iter_mut().for_each(|x| *x = -*x);
    g
}

/// Frames `switched` look the other way (negated descriptors). With `bridge`, the switch
/// in is bridged at the last normal frame (already tracked) and the switch out at the first
/// normal frame (tracked with its other rendering first), as `dhptam run` does.
fn run_with_switches(
    frames: &[SyntheticFrame],
    switched: std::ops::Range<usize>,
    bridge: bool,
) -> (f64, System, usize) {
    let calib = SyntheticOptions::default().calib;
    let mut config = Config::default();
    // No relocalisation: a frame that cannot be tracked starts a new segment at once.
    config.loop_closing.min_score = 1.0;
    let mut system = System::new(calib, config, false).unwrap();
    let mut restarts = 0;
    for (i, f) in frames.iter().enumerate() {
        let other = negated(f);
        let r = if bridge && i == switched.end {
            // Leaving: track the rendering that matches the map, then bridge to the real one.
            let r = track(&mut system, &other);
            let b = system
                .bridge(f.t_ns, frame_features(&other), frame_features(f))
                .unwrap();
            assert!(b.is_some(), "bridge out refused at frame {i}");
            r
        } else if switched.contains(&i) {
            track(&mut system, &other)
        } else {
            track(&mut system, f)
        };
        assert_ne!(r.state, TrackState::Lost, "frame {i} lost");
        if i > 0 && r.state == TrackState::Initialised {
            restarts += 1;
        }
        if bridge && i + 1 == switched.start {
            // Entering: this frame was tracked normally; bridge it to its other rendering.
            let b = system
                .bridge(f.t_ns, frame_features(f), frame_features(&other))
                .unwrap()
                .expect("bridge in refused");
            assert!(b.linked >= 50 && b.other_points >= 50, "{b:?}");
        }
    }
    let truth = truth_positions(frames);
    (
        ate(&positions(&system.trajectory()), &truth),
        system,
        restarts,
    )
}

#[test]
fn bridge_keyframes_keep_one_map_across_appearance_switches() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 90,
        turns: 0.2,
        seed: 9,
        ..Default::default()
    };
    let frames = generate(&o);
    let (ate_off, off, restarts_off) = run_with_switches(&frames, 40..60, false);
    let (ate_on, on, restarts_on) = run_with_switches(&frames, 40..60, true);
    let totals = on.tracking_totals();
    eprintln!(
        "without bridges: {restarts_off} restarts, ATE {ate_off:.4} m; with: {restarts_on}, \
         ATE {ate_on:.4} m, {totals:?}"
    );
    // Without bridges each switch starts a new segment; with them none does.
    assert_eq!(restarts_off, 2);
    assert_eq!(off.tracking_totals().segments, 2);
    assert_eq!(restarts_on, 0);
    assert_eq!(totals.bridges, 2);
    assert_eq!(totals.segments, 0);
    assert_eq!(on.trajectory().len(), frames.len());
    // One map: the last keyframe's covisibility reaches the first one.
    assert!(on.with_map(reaches_first_keyframe));
    assert!(!off.with_map(reaches_first_keyframe));
    assert!(ate_on < 0.03, "ATE {ate_on} m with bridges");
    // Bridge keyframes share their frame's timestamp: listed once.
    let kt = on.keyframe_trajectory();
    assert!(kt.windows(2).all(|w| w[0].0 < w[1].0));
}

#[test]
fn bridge_is_refused_for_a_frame_that_is_not_the_last_tracked() {
    let o = SyntheticOptions {
        landmarks: 600,
        frames: 5,
        turns: 0.02,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut system = System::new(o.calib, Config::default(), false).unwrap();
    // Nothing tracked yet.
    let other = negated(&frames[0]);
    assert!(system
        .bridge(
            frames[0].t_ns,
            frame_features(&frames[0]),
            frame_features(&other)
        )
        .unwrap()
        .is_none());
    for f in &frames[..3] {
        track(&mut system, f);
    }
    // Frame 1 is not the last tracked frame.
    assert!(system
        .bridge(
            frames[1].t_ns,
            frame_features(&frames[1]),
            frame_features(&other)
        )
        .unwrap()
        .is_none());
    let t = system.tracking_totals();
    assert_eq!((t.bridges, t.bridges_refused), (0, 2));
    let keyframes = system.with_map(|m| m.keyframes.len());
    let other2 = negated(&frames[2]);
    let b = system
        .bridge(
            frames[2].t_ns,
            frame_features(&frames[2]),
            frame_features(&other2),
        )
        .unwrap()
        .expect("bridge at the last tracked frame");
    assert_eq!(system.tracking_totals().bridges, 1);
    assert_eq!(system.with_map(|m| m.keyframes.len()), keyframes + 1);
    assert_eq!(system.tracker_state().reference, Some(b.keyframe));
    // The next frame, seen the other way, tracks against the bridge.
    let r = track(&mut system, &negated(&frames[3]));
    assert_eq!(r.state, TrackState::Ok);
}

/// Issue 8, illumination floods: frames 40-42 are predicted (`System::predict`), frames 43-59
/// look the other way. The bridge from the last measured frame (39) goes in after the flood,
/// at frame 39's pose; the next frame, seen the other way, tracks against it: no new segment.
#[test]
fn a_bridge_spans_predicted_frames() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 70,
        turns: 0.2,
        seed: 9,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut config = Config::default();
    config.loop_closing.min_score = 1.0; // no relocalisation: a failure starts a segment
    let mut system = System::new(o.calib, config, false).unwrap();
    // Nothing to predict from before initialisation: lost, nothing recorded.
    assert_eq!(
        system.predict(frames[0].t_ns).unwrap().state,
        TrackState::Lost
    );
    assert!(system.trajectory().is_empty());
    for f in &frames[..40] {
        track(&mut system, f);
    }
    let keyframes = system.with_map(|m| m.keyframes.len());
    for f in &frames[40..43] {
        let r = system.predict(f.t_ns).unwrap();
        assert_eq!(
            (r.state, r.inliers, r.keyframe),
            (TrackState::Predicted, 0, false)
        );
    }
    assert_eq!(system.with_map(|m| m.keyframes.len()), keyframes);
    let b = system
        .bridge(
            frames[39].t_ns,
            frame_features(&frames[39]),
            frame_features(&negated(&frames[39])),
        )
        .unwrap()
        .expect("bridge from the last measured frame refused");
    assert!(b.linked >= 50 && b.other_points >= 50, "{b:?}");
    let at_bridge = system.with_map(|m| m.keyframes[&b.keyframe].world_from_cam);
    let trajectory = system.trajectory();
    assert_eq!(trajectory.len(), 43);
    // At frame 39's pose (up to the bundle adjustment that ran on the bridge), not at the
    // last predicted frame's three steps on.
    let to_39 = (at_bridge.translation - trajectory[39].1.translation).norm();
    let to_42 = (at_bridge.translation - trajectory[42].1.translation).norm();
    assert!(
        to_39 < 0.25 * to_42,
        "{to_39} m from frame 39, {to_42} m from frame 42"
    );
    for f in &frames[43..60] {
        let r = track(&mut system, &negated(f));
        assert_eq!(r.state, TrackState::Ok, "frame at {} ns", f.t_ns);
    }
    let totals = system.tracking_totals();
    assert_eq!(
        (totals.predicted, totals.segments, totals.bridges),
        (3, 0, 1)
    );
    // A bridge from an older frame than the last measured one is refused.
    assert!(system
        .bridge(
            frames[50].t_ns,
            frame_features(&frames[50]),
            frame_features(&negated(&frames[50]))
        )
        .unwrap()
        .is_none());
    let truth = truth_positions(&frames[..60]);
    let error = ate(&positions(&system.trajectory()), &truth);
    assert!(error < 0.03, "ATE {error} m");
}

/// Issue 8, event images warped into the frame cameras: a disparity correction with scale
/// 1/2 reads every stereo match as twice as far, and a bad correction is refused by name.
#[test]
fn disparity_correction_scales_the_stereo_depths() {
    let o = SyntheticOptions {
        frames: 1,
        seed: 8,
        ..Default::default()
    };
    let f = &generate(&o)[0];
    let median_depth = |disparity: DisparityCorrection| {
        let mut system = System::new(o.calib, Config::default(), false).unwrap();
        let (left, right) = (
            view_features(&f.left, disparity, None),
            view_features(&f.right, disparity, None),
        );
        let r = system.track(f.t_ns, left, right)?;
        assert_eq!(r.state, TrackState::Initialised);
        let mut z: Vec<f64> = system.map_points().iter().map(|p| p[2]).collect();
        z.sort_by(f64::total_cmp);
        Ok::<f64, dhptam_core::error::Error>(z[z.len() / 2])
    };
    let plain = median_depth(DisparityCorrection::IDENTITY).unwrap();
    let halved = median_depth(DisparityCorrection {
        scale: 0.5,
        offset_px: 0.0,
    })
    .unwrap();
    assert!((halved / plain - 2.0).abs() < 0.05, "{plain} -> {halved}");
    let err = median_depth(DisparityCorrection {
        scale: 0.0,
        offset_px: 0.0,
    })
    .unwrap_err()
    .to_string();
    assert!(err.contains("left.disparity"), "{err}");
    // The arithmetic: scale · (u_left − u_right) + offset, NaN when not positive.
    let c = DisparityCorrection {
        scale: 0.9,
        offset_px: 0.5,
    };
    assert!((c.apply(100.0, 90.0) - (100.0 - 9.5)).abs() < 1e-5);
    assert!(c.apply(100.0, 101.0).is_nan());
    assert!(c.apply(100.0, f32::NAN).is_nan());
    assert_eq!(DisparityCorrection::IDENTITY.apply(100.0, 101.0), 101.0);
}

/// Issue 8, event images read through the event cameras' geometry: a reading whose event
/// pair is the frame pair changes no map point; one whose event baseline is twice the frame
/// baseline reads every match as twice as far; a disparity correction next to it is refused.
#[test]
fn event_stereo_reading_triangulates_with_the_event_pair() {
    let o = SyntheticOptions {
        frames: 1,
        seed: 8,
        ..Default::default()
    };
    let f = &generate(&o)[0];
    let c = o.calib;
    let k = Pinhole {
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
    };
    let reading = |event_baseline: f64| {
        // The right event camera at +event_baseline along x of the left one (which is the
        // left frame camera): seen from the right frame camera, event_baseline − b along x.
        let right = Se3::new(
            So3::identity(),
            Vector3::new(event_baseline - c.baseline_m, 0.0, 0.0),
        );
        EventStereo::new(
            k,
            event_baseline,
            k,
            c.baseline_m,
            [Se3::identity(), right],
            Depth::Infinity,
            Vector2::zeros(),
        )
        .unwrap()
    };
    let map = |reading: Option<&EventStereo>, disparity: DisparityCorrection| {
        let mut system = System::new(c, Config::default(), false).unwrap();
        let (left, right) = (
            view_features(&f.left, disparity, reading),
            view_features(&f.right, disparity, reading),
        );
        system.track(f.t_ns, left, right)?;
        Ok::<_, dhptam_core::error::Error>(system.map_points())
    };
    let median_z = |points: &[[f64; 3]]| {
        let mut z: Vec<f64> = points.iter().map(|p| p[2]).collect();
        z.sort_by(f64::total_cmp);
        z[z.len() / 2]
    };
    let plain = map(None, DisparityCorrection::IDENTITY).unwrap();
    let same = map(Some(&reading(c.baseline_m)), DisparityCorrection::IDENTITY).unwrap();
    assert_eq!(plain.len(), same.len());
    let moved = plain
        .iter()
        .zip(&same)
        .map(|(a, b)| (0..3).map(|i| (a[i] - b[i]).abs()).fold(0.0, f64::max))
        .fold(0.0, f64::max);
    assert!(
        moved < 1e-4,
        "a co-located event pair moved points {moved} m"
    );
    let doubled = map(
        Some(&reading(2.0 * c.baseline_m)),
        DisparityCorrection::IDENTITY,
    )
    .unwrap();
    let ratio = median_z(&doubled) / median_z(&plain);
    assert!((ratio - 2.0).abs() < 0.05, "depth ratio {ratio}");
    let err = map(
        Some(&reading(c.baseline_m)),
        DisparityCorrection {
            scale: 0.9,
            offset_px: 0.0,
        },
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("left.disparity"), "{err}");
}

/// The whole-map bundle adjustment pulls a map whose keyframes and points were all knocked
/// off (2 cm, 0.5°) back to where tracking had them, holding the first keyframe and every
/// segment start fixed.
#[test]
fn global_bundle_adjustment_undoes_a_perturbation_of_the_whole_map() {
    use dhptam_core::slam::global_bundle_adjustment;
    use std::sync::RwLock;
    let o = SyntheticOptions {
        frames: 120,
        turns: 0.3,
        seed: 12,
        ..Default::default()
    };
    let frames = generate(&o);
    let config = Config::default();
    let mut system = System::new(o.calib, config.clone(), false).unwrap();
    frames.iter().for_each(|f| {
        track(&mut system, f);
    });
    let tracked: Map = system.with_map(|m| m.clone());
    let ids: Vec<u64> = tracked.keyframes.keys().copied().collect();
    assert!(ids.len() >= 8, "{} keyframes", ids.len());
    let (first, anchor) = (ids[0], ids[ids.len() / 2]);
    let mut map = tracked.clone();
    map.segment_starts.insert(anchor);
    let mut rng = 7u64;
    let mut noise = || {
        // xorshift: reproducible without a random-number crate in this test.
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng % 2001) as f64 / 1000.0 - 1.0
    };
    for (id, k) in map.keyframes.iter_mut() {
        if *id != first && *id != anchor {
            let kick = Se3::new(
                So3::exp(&(Vector3::new(noise(), noise(), noise()) * 0.5f64.to_radians())),
                Vector3::new(noise(), noise(), noise()) * 0.02,
            );
            k.world_from_cam = k.world_from_cam * kick;
        }
    }
    for p in map.points.values_mut() {
        p.position += Vector3::new(noise(), noise(), noise()) * 0.02;
    }
    let offset = |m: &Map| {
        let sum: f64 = ids
            .iter()
            .map(|id| (m.keyframes[id].centre() - tracked.keyframes[id].centre()).norm_squared())
            .sum();
        (sum / ids.len() as f64).sqrt()
    };
    let before = offset(&map);
    let shared = RwLock::new(map);
    let report = global_bundle_adjustment(
        &shared,
        &o.calib,
        &config.tracking,
        &config.triangulation,
        20,
        None,
    )
    .unwrap();
    let map = shared.into_inner().unwrap();
    let after = offset(&map);
    eprintln!("keyframe centres off by {before:.4} m before, {after:.4} m after: {report:?}");
    assert_eq!((report.fixed, report.optimised), (2, ids.len() - 2));
    assert_eq!(report.points, tracked.points.len());
    assert!(before > 0.01 && after < 0.1 * before, "{before} -> {after}");
    for id in [first, anchor] {
        assert_eq!(
            map.keyframes[&id].world_from_cam,
            tracked.keyframes[&id].world_from_cam
        );
    }
    assert_eq!(map.check_invariants(), Vec::<String>::new());
}

/// `f` with only its first `n` keypoints in each image (the synthetic views list the
/// landmarks in the same order, so the kept ones still match across the pair).
fn with_keypoints(f: &SyntheticFrame, n: usize, dim: usize) -> SyntheticFrame {
    let mut out = f.clone();
    for view in [&mut out.left, &mut out.right] {
        view.keypoints.truncate(2 * n);
        view.descriptors.truncate(dim * n);
    }
    out
}

#[test]
fn picking_the_track_up_after_a_loss_needs_relocalisation_evidence() {
    let o = SyntheticOptions {
        landmarks: 1200,
        frames: 80,
        seed: 9,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut config = Config::default();
    config.tracking.reinitialise = false;
    let needed = config.loop_closing.min_inliers as usize;
    let mut system = System::new(o.calib, config, false).unwrap();
    for f in &frames[..40] {
        track(&mut system, f);
    }
    // Two frames without a feature: lost, the motion model still close to the truth.
    let blank = with_keypoints(&frames[40], 0, o.descriptor_dim);
    assert_eq!(track(&mut system, &blank).state, TrackState::Lost);
    // A frame with fewer matches than a relocalisation needs (but more than `min_tracked`)
    // does not end the loss: after a loss the stale motion model needs the same evidence.
    let few = with_keypoints(&frames[41], needed - 5, o.descriptor_dim);
    let r = track(&mut system, &few);
    assert_eq!(
        r.state,
        TrackState::Lost,
        "picked up with {} inliers",
        r.inliers
    );
    // A full frame picks the track up, as a relocalisation: a keyframe, the velocity restarted.
    let r = track(&mut system, &frames[42]);
    assert_eq!(r.state, TrackState::Relocalised, "{} inliers", r.inliers);
    assert!(r.keyframe && r.inliers >= needed);
    let first = frames[0].world_from_cam.inverse();
    let error = |r: &TrackResult, f: &SyntheticFrame| {
        ((first * f.world_from_cam).inverse() * r.world_from_cam)
            .log()
            .norm()
    };
    assert!(error(&r, &frames[42]) < 0.02, "{}", error(&r, &frames[42]));
    let next = track(&mut system, &frames[43]);
    assert_eq!(next.state, TrackState::Ok);
    assert!(
        error(&next, &frames[43]) < 0.02,
        "{}",
        error(&next, &frames[43])
    );
    assert_eq!(system.tracking_totals().relocalisations, 1);
}

/// Runs a synthetic quarter circle with keypoint noise `pixel_noise` (smoother at `q`);
/// returns the system, the true centres and the mean trace of the measured covariances.
fn run_noisy(pixel_noise: f64, q: f64) -> (System, Vec<Vector3<f64>>, f64) {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 120,
        turns: 0.25,
        pixel_noise,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut config = Config::default();
    config.tracking.smoothing_q = q;
    let mut system = System::new(o.calib, config, false).unwrap();
    for f in &frames {
        track(&mut system, f);
    }
    let truth = truth_positions(&frames);
    let traces: Vec<f64> = system.with_map(|map| {
        map.trajectory
            .iter()
            .filter_map(|r| r.position_cov.map(|c| c.trace()))
            .collect()
    });
    assert!(
        traces.len() > 100,
        "{} frames with a covariance",
        traces.len()
    );
    let mean = traces.iter().sum::<f64>() / traces.len() as f64;
    (system, truth, mean)
}

#[test]
fn the_smoother_weighs_each_frame_by_its_measured_covariance() {
    // Noisy keypoints (1.5 px): tracked centres scatter by millimetres from frame to frame.
    let (system, truth, noisy_trace) = run_noisy(1.5, 0.01);
    let tracked = system.tracked_trajectory();
    let smoothed = system.trajectory();
    assert_eq!(tracked.len(), truth.len());
    assert_eq!(smoothed.len(), truth.len());
    // Orientations and times are untouched; only centres move.
    for (a, b) in tracked.iter().zip(&smoothed) {
        assert_eq!(a.0, b.0);
        assert!((a.1.rotation.inverse() * b.1.rotation).angle() < 1e-12);
    }
    let (e_tracked, e_smoothed) = (
        ate(&positions(&tracked), &truth),
        ate(&positions(&smoothed), &truth),
    );
    eprintln!("ATE tracked {e_tracked:.5} m, smoothed {e_smoothed:.5} m");
    assert!(e_smoothed < 0.8 * e_tracked, "{e_smoothed} vs {e_tracked}");
    // The covariance follows the keypoints' real scatter (s² from the residuals), not their
    // nominal σ (1 px for every keypoint here): three times the noise, about nine times
    // the variance.
    let (_, _, quiet_trace) = run_noisy(0.5, 0.01);
    let ratio = noisy_trace / quiet_trace;
    eprintln!("covariance trace 1.5 px / 0.5 px: {ratio:.2}");
    assert!((5.0..16.0).contains(&ratio), "trace ratio {ratio}");
}

/// Issue 8, the whole ecd_poster_6dof trajectory: poses tracked on a few wrongly matched
/// inliers jumped a metre or more from the motion model's prediction. `[tracking]
/// max_jump_ratio` rejects a tracked pose farther from the prediction than that fraction of
/// its inliers' median depth; the frame then goes on to relocalisation, like one with too
/// few inliers. The default never fires on ordinary motion, and a bound below the
/// sequence's own frame-to-frame departures from constant velocity fires on every frame.
#[test]
fn a_pose_far_from_the_motion_model_is_rejected_and_relocalised() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 40,
        turns: 0.1,
        seed: 4,
        pixel_noise: 0.5,
        ..Default::default()
    };
    let frames = generate(&o);
    let run = |ratio: f64| {
        let mut config = Config::default();
        config.tracking.max_jump_ratio = ratio;
        let mut system = System::new(o.calib, config, false).unwrap();
        let lost = frames
            .iter()
            .filter(|f| track(&mut system, f).state == TrackState::Lost)
            .count() as u64;
        (system.tracking_totals(), lost, system)
    };
    let (totals, lost, system) = run(Config::default().tracking.max_jump_ratio);
    assert_eq!(totals.implausible, 0, "{totals:?}");
    assert_eq!(lost, 0);
    let truth = truth_positions(&frames);
    let error = ate(&positions(&system.trajectory()), &truth);
    assert!(error < 0.02, "ATE {error} m");
    // Off: the same run.
    let (off, _, _) = run(0.0);
    assert_eq!(off, totals);
    // A bound of a micrometre per metre of depth: every frame tracked from a valid motion
    // model is rejected, and each goes on to relocalisation (or a new segment).
    let (strict, lost, _) = run(1e-6);
    assert!(strict.implausible >= 30, "{strict:?}");
    assert_eq!(
        strict.relocalisations + strict.segments + lost,
        strict.implausible,
        "{strict:?}, {lost} lost"
    );
    // A bad bound is refused by name.
    let mut config = Config::default();
    config.tracking.max_jump_ratio = -1.0;
    let err = System::new(o.calib, config, false)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("max_jump_ratio"), "{err}");
}

#[test]
fn a_frame_the_motion_model_misses_is_relocalised_against_its_reference_keyframe() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 30,
        turns: 0.1,
        seed: 5,
        pixel_noise: 0.5,
        ..Default::default()
    };
    let frames = generate(&o);
    // Every pose tracked from the motion model is rejected (a bound of a micrometre per metre
    // of depth), and the place query proposes nothing (no candidates): only the reference
    // keyframe can pick a frame up.
    let run = |reference: bool| {
        let mut config = Config::default();
        config.tracking.max_jump_ratio = 1e-6;
        config.tracking.relocalise_reference = reference;
        config.loop_closing.candidates = 0;
        let mut system = System::new(o.calib, config, false).unwrap();
        let states: Vec<TrackState> = frames.iter().map(|f| track(&mut system, f).state).collect();
        (system.tracking_totals(), states, system)
    };
    let (on, states, system) = run(true);
    assert!(on.implausible >= 25, "{on:?}");
    assert_eq!(on.relocalisations, on.implausible, "{on:?}");
    assert_eq!(on.segments, 0, "{on:?}");
    assert!(
        states[1..].iter().all(|s| *s == TrackState::Relocalised),
        "{states:?}"
    );
    let truth = truth_positions(&frames);
    let error = ate(&positions(&system.trajectory()), &truth);
    assert!(error < 0.02, "ATE {error} m");
    // Off: nothing picks the frames up, and each starts a new map segment.
    let (off, _, _) = run(false);
    assert_eq!(off.relocalisations, 0, "{off:?}");
    assert_eq!(off.segments, off.implausible, "{off:?}");
}

/// Tracks `frames` whose features were measured from `viewpoint` with that viewpoint given
/// (or zero); returns the system.
fn track_from_viewpoint(
    frames: &[SyntheticFrame],
    o: &SyntheticOptions,
    viewpoint: [f32; 3],
) -> System {
    let mut system = System::new(o.calib, Config::default(), false).unwrap();
    for f in frames {
        track_frame_from(&mut system, f, viewpoint);
    }
    system
}

fn track_frame_from(system: &mut System, f: &SyntheticFrame, viewpoint: [f32; 3]) -> TrackResult {
    let (mut left, mut right) = frame_features(f);
    left.viewpoint = viewpoint;
    right.viewpoint = viewpoint;
    system.track(f.t_ns, left, right).unwrap()
}

#[test]
fn features_seen_from_another_viewpoint_are_modelled_from_it() {
    // The features come from a camera pair 5 cm beside, 3 cm below and 10 cm ahead of the left camera (as an
    // event pair warped into the frame cameras through the plane at infinity): given that
    // viewpoint, tracking, new points and bundle adjustment recover the left camera's path;
    // read as the left camera's own, the path is the other pair's, off by the rotating offset.
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 80,
        turns: 0.5,
        pixel_noise: 0.3,
        outlier_fraction: 0.0,
        viewpoint_m: [0.05, 0.03, 0.1],
        ..Default::default()
    };
    let frames = generate(&o);
    let truth = truth_positions(&frames);
    let modelled = track_from_viewpoint(&frames, &o, [0.05, 0.03, 0.1]);
    let ignored = track_from_viewpoint(&frames, &o, [0.0; 3]);
    let e_modelled = ate(&positions(&modelled.trajectory()), &truth);
    let e_ignored = ate(&positions(&ignored.trajectory()), &truth);
    eprintln!("ATE with the viewpoint {e_modelled:.4} m, without {e_ignored:.4} m");
    assert_eq!(modelled.trajectory().len(), frames.len());
    assert!(e_modelled < 0.005, "ATE {e_modelled} m with the viewpoint");
    assert!(
        e_ignored > 3.0 * e_modelled,
        "ATE {e_ignored} m without the viewpoint against {e_modelled} m with it"
    );

    // The viewpoints travel with the keyframes through a saved map (format version 6): a run
    // saved and loaded half-way continues exactly as the uninterrupted one.
    let dir = std::env::temp_dir().join(format!("dhptam-viewpoint-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("map.bin");
    let mut first = System::new(o.calib, Config::default(), false).unwrap();
    for f in &frames[..40] {
        track_frame_from(&mut first, f, [0.05, 0.03, 0.1]);
    }
    first.save_map(&path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 6);
    let mut second = System::new(o.calib, Config::default(), false).unwrap();
    second.load_map(&path).unwrap();
    for f in &frames[40..] {
        track_frame_from(&mut second, f, [0.05, 0.03, 0.1]);
    }
    for ((ta, pa), (tb, pb)) in modelled.trajectory().iter().zip(&second.trajectory()) {
        assert_eq!(ta, tb);
        let d = (pa.translation - pb.translation).norm();
        assert!(
            d < 1e-9,
            "frame {ta}: centres differ by {d} m after the reload"
        );
    }
    // A map without viewpoints is still written as version 5.
    let mut plain = System::new(o.calib, Config::default(), false).unwrap();
    for f in &frames[..10] {
        track(&mut plain, f);
    }
    plain.save_map(&path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 5);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_relocalised_frame_passes_its_step_on_as_the_velocity() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 200,
        seed: 6,
        ..Default::default()
    };
    let frames = generate(&o);
    // Ten frames at the full rate, then every fifth: from then on each step turns the camera
    // five times further than the motion model expects, well past the wide search window.
    let played: Vec<&SyntheticFrame> = frames[..10]
        .iter()
        .chain(frames[10..].iter().step_by(5))
        .collect();
    let run = |velocity: bool| {
        let mut config = Config::default();
        config.tracking.relocalised_velocity = velocity;
        let mut system = System::new(o.calib, config, false).unwrap();
        let states: Vec<TrackState> = played.iter().map(|f| track(&mut system, f).state).collect();
        let truth: Vec<Vector3<f64>> = played
            .iter()
            .map(|f| f.world_from_cam.translation)
            .collect();
        let error = ate(&positions(&system.trajectory()), &truth);
        (system.tracking_totals(), states, error)
    };
    // With the step's velocity: the first frame of the faster rate is relocalised, and the
    // motion model predicts every frame after it.
    let (on, states, error) = run(true);
    assert_eq!(on.relocalisations, 1, "{on:?} {states:?}");
    assert_eq!(on.segments, 0, "{on:?}");
    assert_eq!(states[11], TrackState::Relocalised, "{states:?}");
    assert!(
        states[12..].iter().all(|s| *s == TrackState::Ok),
        "{states:?}"
    );
    assert!(error < 0.02, "ATE {error} m");
    // From rest: the prediction misses every frame, and each is relocalised again.
    let (off, states, _) = run(false);
    assert!(off.relocalisations >= 30, "{off:?} {states:?}");
}

/// How far apart the tracked camera centres of frames `i - 1` and `i` of a run lie.
fn tracked_step(system: &System, i: usize) -> f64 {
    let poses = system.tracked_trajectory();
    (poses[i].1.translation - poses[i - 1].1.translation).norm()
}

#[test]
fn a_new_map_segment_goes_on_with_the_velocity_its_setting_names() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 200,
        seed: 6,
        ..Default::default()
    };
    let frames = generate(&o);
    // A frame no other frame matches: its descriptors negated, reversed or both (`kind` 0, 1
    // or 2), in the left and right views alike.
    let glitched = |f: &SyntheticFrame, kind: usize| {
        let mut g = f.clone();
        for d in [&mut g.left.descriptors, &mut g.right.descriptors] {
            if kind != 1 {
                d.iter_mut().for_each(|x| *x = -*x);
            }
            if kind != 0 {
                d.chunks_exact_mut(32).for_each(|c| c.reverse());
            }
        }
        g
    };
    // Plays `order` (indices into `frames`), those at the positions in `glitch` each
    // unmatchable in its own way, so each starts a new map segment; returns the system and
    // each frame's state.
    let run = |setting: &str, order: &[usize], glitch: std::ops::Range<usize>| {
        let mut config = Config::default();
        config.tracking.relocalised_velocity = true;
        config.tracking.segment_velocity = setting.to_owned();
        let mut system = System::new(o.calib, config, false).unwrap();
        let states: Vec<TrackState> = order
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                let f = if glitch.contains(&k) {
                    glitched(&frames[i], k % 3)
                } else {
                    frames[i].clone()
                };
                track(&mut system, &f).state
            })
            .collect();
        (system, states)
    };
    // Plays `order` with the frames at positions `glitch` (three) unmatchable, then checks
    // where the second new segment lies from the first (one true step on when `moved`, else at
    // it), and that the third lies at the second under every setting: a run of new segments
    // is extrapolated over two frames at most.
    let check =
        |order: &[usize], glitch: usize, cases: [(&str, bool); 3], relocalised: Option<usize>| {
            let (a, b) = (order[glitch], order[glitch + 1]);
            let step = (frames[b].world_from_cam.translation
                - frames[a].world_from_cam.translation)
                .norm();
            for (setting, moved) in cases {
                let (system, states) = run(setting, &order[..glitch + 3], glitch..glitch + 3);
                if let Some(k) = relocalised {
                    assert_eq!(states[k], TrackState::Relocalised, "{setting}: {states:?}");
                }
                assert_eq!(
                    states[glitch..glitch + 3],
                    [TrackState::Initialised; 3],
                    "{setting}: {states:?}"
                );
                let d = tracked_step(&system, glitch + 1);
                let expected = if moved { step } else { 0.0 };
                assert!(
                    (d - expected).abs() < 0.25 * step,
                    "{setting}: {d} m, true step {step} m"
                );
                let held = tracked_step(&system, glitch + 2);
                assert!(held < 1e-9, "{setting}: the third segment {held} m on");
                assert_eq!(
                    system.tracker_state().velocity,
                    Se3::identity(),
                    "{setting}"
                );
            }
        };
    // A velocity measured between tracked frames: the second of two new segments in a row
    // is placed one step on with "kept" and "measured", at the first one's pose with "rest".
    let full_rate: Vec<usize> = (0..60).collect();
    check(
        &full_rate,
        40,
        [("kept", true), ("measured", true), ("rest", false)],
        None,
    );
    // A relocalised frame's step (ten frames at the full rate, then every fifth: the frame at
    // position 11 is relocalised): carried into the new segments only with "kept".
    let faster: Vec<usize> = (0..10).chain((10..200).step_by(5)).collect();
    check(
        &faster,
        12,
        [("kept", true), ("measured", false), ("rest", false)],
        Some(11),
    );
    // An unknown setting is refused by name.
    let mut config = Config::default();
    config.tracking.segment_velocity = "constant".to_owned();
    let err = System::new(o.calib, config, false)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("segment_velocity"), "{err}");
}

/// `f`'s view as an event camera at rest would give it (sensor noise), `k` periods later: the
/// signs of its descriptors' entries flipped by a mask drawn afresh for each `k`, the same in
/// both views (stereo pairs still match, nothing matches across frames or the map).
fn noise_view(f: &SyntheticFrame, k: i64, period_ns: i64) -> SyntheticFrame {
    let mut g = f.clone();
    g.t_ns += k * period_ns;
    // splitmix64 draws until about half the 32 signs flip (far from every other mask).
    let mut state = k as u64;
    let mask = loop {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        let m = (z ^ (z >> 31)) & 0xffff_ffff;
        if (14..=18).contains(&m.count_ones()) {
            break m;
        }
    };
    for d in [&mut g.left.descriptors, &mut g.right.descriptors] {
        for c in d.chunks_exact_mut(32) {
            for (j, x) in c.iter_mut().enumerate() {
                if mask >> j & 1 == 1 {
                    *x = -*x;
                }
            }
        }
    }
    g
}

#[test]
fn quiet_event_frames_before_the_first_map_are_held_at_its_pose() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 30,
        seed: 6,
        ..Default::default()
    };
    let frames = generate(&o);
    // The camera rests at frame 0's pose for `rest` frames of noise, then moves along frames
    // 0.. (shifted after the rest).
    let rest = 6i64;
    let run = |mode: FusionMode| {
        let mut config = Config::default();
        config.fusion.mode = mode;
        let mut system = System::new(o.calib, config, false).unwrap();
        let mut states = Vec::new();
        for k in 0..rest {
            let g = noise_view(&frames[0], k - rest, o.period_ns);
            let (mut left, mut right) = frame_features(&g);
            left.quiet = true;
            right.quiet = true;
            states.push(system.track(g.t_ns, left, right).unwrap().state);
        }
        for f in &frames {
            let (left, right) = frame_features(f);
            states.push(system.track(f.t_ns, left, right).unwrap().state);
        }
        (system, states)
    };
    // Mode `events`: no map from noise; the rest is held at the first map's pose once the
    // moving camera makes it.
    let (system, states) = run(FusionMode::Events);
    let r = rest as usize;
    assert!(
        states[..r].iter().all(|s| *s == TrackState::Lost),
        "{states:?}"
    );
    assert_eq!(states[r], TrackState::Initialised, "{states:?}");
    assert_eq!(system.tracking_totals().held, rest as u64);
    assert_eq!(system.tracking_totals().segments, 0);
    let written = system.tracked_trajectory();
    assert_eq!(written.len(), frames.len() + r);
    let first = frames[0].t_ns;
    for (k, (t_ns, pose)) in written[..r].iter().enumerate() {
        assert_eq!(*t_ns, first + (k as i64 - rest) * o.period_ns);
        assert!(
            (written[r].1.inverse() * *pose).log().norm() < 1e-12,
            "frame {k}"
        );
    }
    assert!(written.windows(2).all(|w| w[0].0 < w[1].0));
    // Frame images (mode `fusion`, not DVS-biased) still make a map at rest.
    let (system, states) = run(FusionMode::Fusion);
    assert_eq!(states[0], TrackState::Initialised, "{states:?}");
    assert_eq!(system.tracking_totals().held, rest as u64 - 1);
}

#[test]
fn a_quiet_frame_that_cannot_be_tracked_holds_its_pose_and_keeps_the_map() {
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 80,
        seed: 6,
        ..Default::default()
    };
    let frames = generate(&o);
    // The camera stops at frame 39 for `rest` frames, where the event images show only
    // sensor noise: frame 39's view with the signs of its descriptors' entries flipped by a
    // fresh random mask at every frame, the same in both views (stereo pairs still match,
    // nothing matches across frames or the map), flagged quiet when `quiet`; then it moves
    // on through frames 40.. (their timestamps shifted).
    let (stop, rest) = (39usize, 10i64);
    let noise = |k: i64| noise_view(&frames[stop], k, o.period_ns);
    let run = |quiet: bool| {
        let mut system = System::new(o.calib, Config::default(), false).unwrap();
        let (mut states, mut poses) = (Vec::new(), Vec::new());
        let mut play = |system: &mut System, f: &SyntheticFrame, flagged: bool| {
            let (mut left, mut right) = frame_features(f);
            left.quiet = flagged;
            right.quiet = flagged;
            let r = system.track(f.t_ns, left, right).unwrap();
            states.push(r.state);
            poses.push(r.world_from_cam);
        };
        for (i, f) in frames[..=stop].iter().enumerate() {
            // A quiet window that still tracks (slow motion) is tracked as usual.
            play(&mut system, f, quiet && i == 20);
        }
        let keyframes = system.keyframe_trajectory().len();
        for k in 1..=rest {
            play(&mut system, &noise(k), quiet);
        }
        let keyframes_at_rest = system.keyframe_trajectory().len() - keyframes;
        for f in &frames[stop + 1..] {
            let mut moved = f.clone();
            moved.t_ns += rest * o.period_ns;
            play(&mut system, &moved, false);
        }
        (system, states, poses, keyframes_at_rest)
    };
    let (system, states, held, keyframes_at_rest) = run(true);
    let totals = system.tracking_totals();
    let at_rest = stop + 1..stop + 1 + rest as usize;
    assert_eq!(states[20], TrackState::Ok, "{states:?}");
    assert!(
        states[at_rest.clone()]
            .iter()
            .all(|s| *s == TrackState::Held),
        "{states:?}"
    );
    assert_eq!(totals.held, rest as u64, "{totals:?}");
    assert_eq!(totals.segments, 0, "{totals:?}");
    assert_eq!(totals.relocalisations, 0, "{totals:?}");
    assert_eq!(keyframes_at_rest, 0);
    // Every frame at rest kept the last tracked pose, and the camera moving again is tracked
    // against the same map from there.
    for k in at_rest.clone() {
        let moved = (held[stop].inverse() * held[k]).log().norm();
        assert!(
            moved < 1e-12,
            "frame {k}: {moved} from the last tracked pose"
        );
    }
    let poses = system.tracked_trajectory();
    assert_eq!(poses.len(), states.len(), "{states:?}");
    assert!(
        states[at_rest.end..].iter().all(|s| *s == TrackState::Ok),
        "{states:?}"
    );
    let truth: Vec<Vector3<f64>> = (0..poses.len())
        .map(|k| {
            let i = if at_rest.contains(&k) {
                stop
            } else if k >= at_rest.end {
                k - rest as usize
            } else {
                k
            };
            frames[i].world_from_cam.translation
        })
        .collect();
    let e = ate(&positions(&poses), &truth);
    assert!(e < 0.02, "ATE {e} m");
    // The written trajectory (smoothed) keeps the camera near where it stopped: the smoother
    // takes the held frames as measured rather than carrying the last speed into the rest
    // (as unmeasured frames they drifted up to 0.9 of a step away). The stop and the restart
    // are instantaneous here, and the smoother rounds both corners: the last held frame
    // leans half a step towards the restart.
    let smoothed = system.trajectory();
    let step = (frames[stop + 1].world_from_cam.translation
        - frames[stop].world_from_cam.translation)
        .norm();
    for k in at_rest.start..at_rest.end - 1 {
        let d = (smoothed[k].1.translation - smoothed[stop].1.translation).norm();
        assert!(
            d < 0.4 * step,
            "frame {k}: {d} m from the stop, a step is {step} m"
        );
    }
    // The held flags travel through a saved map (flag 2 of the trajectory records).
    let path = std::env::temp_dir().join(format!("dhptam-held-{}.bin", std::process::id()));
    system.save_map(&path).unwrap();
    let mut loaded = System::new(o.calib, Config::default(), false).unwrap();
    loaded.load_map(&path).unwrap();
    std::fs::remove_file(&path).ok();
    let flags = |s: &System| {
        s.with_map(|m| {
            m.trajectory
                .iter()
                .map(|r| (r.predicted, r.held))
                .collect::<Vec<_>>()
        })
    };
    assert_eq!(flags(&loaded), flags(&system));
    assert_eq!(
        flags(&system)
            .iter()
            .filter(|f| **f == (true, true))
            .count(),
        rest as usize
    );
    // A flood frame predicted after the held ones (`System::predict`) stays at rest too.
    let mut flooded = System::new(o.calib, Config::default(), false).unwrap();
    for f in &frames[..=stop] {
        track(&mut flooded, f);
    }
    let still = noise(1);
    let (mut left, mut right) = frame_features(&still);
    (left.quiet, right.quiet) = (true, true);
    let last = flooded.track(still.t_ns, left, right).unwrap();
    assert_eq!(last.state, TrackState::Held);
    let predicted = flooded.predict(noise(2).t_ns).unwrap();
    assert_eq!(predicted.state, TrackState::Predicted);
    let moved = (last.world_from_cam.inverse() * predicted.world_from_cam)
        .log()
        .norm();
    assert!(moved < 1e-12, "the flood frame predicted {moved} on");
    // The same frames not flagged: each noise frame starts a new map segment.
    let (plain, states, _, keyframes_at_rest) = run(false);
    assert!(plain.tracking_totals().segments >= 2, "{states:?}");
    assert!(keyframes_at_rest >= 2, "{keyframes_at_rest}");
}
