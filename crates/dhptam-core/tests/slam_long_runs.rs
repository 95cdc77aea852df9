//! Long-run behaviour of the SLAM back-end (issue 10) on synthetic stereo feature sequences:
//! keyframe and map-point culling, map consistency, merging a new map segment on loop closure,
//! and mapping/loop closing saturated with a shutdown under load.

use dhptam_core::config::Config;
use dhptam_core::geometry::Se3;
use dhptam_core::slam::synthetic::{generate, SyntheticFrame, SyntheticOptions};
use dhptam_core::slam::{
    keyframes_at_place, redundancy, replaced_horizon, Map, System, TrackState,
};
use nalgebra::Vector3;

mod common;
use common::{ate, track, truth_positions};

/// Asserts the map is consistent and the place database holds exactly its keyframes.
fn assert_consistent(system: &System) {
    let errors = system.with_map(Map::check_invariants);
    assert!(errors.is_empty(), "map inconsistent: {errors:#?}");
    let keyframes: Vec<u64> = system.with_map(|m| m.keyframes.keys().copied().collect());
    let place = system.place_ids();
    assert!(
        place.iter().all(|id| keyframes.contains(id)),
        "place database holds removed keyframes: {place:?} vs {keyframes:?}"
    );
}

/// Every frame becomes a keyframe (the tracked count is always under the minimum).
fn every_frame_a_keyframe(config: &mut Config) {
    config.tracking.keyframe_min_tracked = 1_000_000;
}

/// Runs `frames` synchronously; returns the system and the ATE of its trajectory.
fn run(frames: &[SyntheticFrame], calib_from: &SyntheticOptions, config: Config) -> (System, f64) {
    let mut system = System::new(calib_from.calib, config, false).unwrap();
    for f in frames {
        let r = track(&mut system, f);
        assert_ne!(r.state, TrackState::Lost, "frame {} lost", f.t_ns);
    }
    let traj = system.trajectory();
    assert_eq!(
        traj.len(),
        frames.len(),
        "frames missing from the trajectory"
    );
    let estimated: Vec<Vector3<f64>> = traj.iter().map(|(_, p)| p.translation).collect();
    let truth = truth_positions(frames);
    let e = ate(&estimated, &truth);
    (system, e)
}

/// A short, slow sequence (20 frames) run with the default configuration.
fn short_run() -> System {
    let o = SyntheticOptions {
        landmarks: 800,
        frames: 20,
        turns: 0.02,
        seed: 2,
        ..Default::default()
    };
    run(&generate(&o), &o, Config::default()).0
}

#[test]
fn culling_removes_redundant_keyframes_of_a_slow_sequence_and_keeps_the_map_consistent() {
    // A slow pan (3° over 60 frames) where every frame is made a keyframe: almost all of them
    // see the same points as their neighbours.
    let o = SyntheticOptions {
        landmarks: 1000,
        frames: 60,
        turns: 1.0 / 120.0,
        seed: 12,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut config = Config::default();
    every_frame_a_keyframe(&mut config);
    config.mapping.ba_iterations = 5;
    config.mapping.window = 5;
    config.mapping.max_fixed = 5;
    config.mapping.cull_keyframes = false;
    let (off, ate_off) = run(&frames, &o, config.clone());
    config.mapping.cull_keyframes = true;
    config.mapping.min_found_ratio = 0.25;
    let (on, ate_on) = run(&frames, &o, config);
    let (n_off, n_on) = (
        off.keyframe_trajectory().len(),
        on.keyframe_trajectory().len(),
    );
    let (p_off, p_on) = (off.map_points().len(), on.map_points().len());
    eprintln!(
        "without culling: {n_off} keyframes, {p_off} points, ATE {ate_off:.4} m; with: {n_on} \
         keyframes ({} culled), {p_on} points, ATE {ate_on:.4} m",
        on.culled_keyframes()
    );
    assert_eq!(off.culled_keyframes(), 0);
    assert_eq!(n_off, frames.len());
    assert_eq!(on.culled_keyframes() as usize, n_off - n_on);
    assert!(n_on * 2 < n_off, "{n_on} keyframes kept of {n_off}");
    // Trajectory records of culled keyframes were handed over without moving the frames.
    assert!(ate_on < 0.02, "ATE {ate_on} m with culling");
    assert!(
        ate_on <= 1.5 * ate_off + 0.002,
        "ATE {ate_on} m with culling vs {ate_off} m without"
    );
    assert_consistent(&on);
    assert_consistent(&off);
    // The first keyframe stays; of the keyframes old enough to be examined, what is left is
    // not redundant any more (a culled neighbour can make one redundant again only until the
    // next keyframe's step, so a handful may remain).
    let cfg = Config::default().mapping;
    on.with_map(|m| {
        assert!(m.keyframes.contains_key(&0));
        let newest = *m.keyframes.keys().last().unwrap();
        let examined: Vec<u64> = m
            .keyframes
            .keys()
            .copied()
            .filter(|&k| k != 0 && k + cfg.cull_min_age as u64 <= newest)
            .collect();
        // A slow pan is one place: culling goes on until what is left there is protected
        // (the newest keyframe's bundle-adjustment window) or no longer redundant.
        let window = m.keyframes[&newest].best_covisible(cfg.window as usize - 1);
        let still: Vec<u64> = examined
            .iter()
            .copied()
            .filter(|k| !window.contains(k))
            .filter(|&k| redundancy(m, k, &cfg).is_some_and(|r| r >= cfg.redundant_fraction))
            .collect();
        assert!(
            still.len() <= cfg.cull_max_per_keyframe as usize,
            "{still:?} of {} examined keyframes still redundant",
            examined.len()
        );
        // The recent window is left alone.
        let recent = m
            .keyframes
            .keys()
            .filter(|&&k| k + (cfg.cull_min_age as u64) > newest);
        assert_eq!(recent.count(), cfg.cull_min_age as usize);
    });
}

#[test]
fn the_invariant_check_finds_dangling_ids() {
    let system = short_run();
    let map = system.with_map(Map::clone);
    assert!(map.check_invariants().is_empty());
    let kf = *map.keyframes.keys().last().unwrap();
    // A keyframe removed behind the map's back: observations, covisibility and trajectory
    // records now dangle.
    let mut broken = map.clone();
    broken.keyframes.remove(&kf);
    let errors = broken.check_invariants();
    assert!(
        errors.iter().any(|e| e.contains("missing keyframe")),
        "{errors:?}"
    );
    assert!(
        errors.iter().any(|e| e.contains("trajectory record")),
        "{errors:?}"
    );
    // A covisibility weight off by one.
    let mut broken = map.clone();
    let k = broken.keyframes.get_mut(&kf).unwrap();
    let (&o, _) = k.covisible.iter().next().unwrap();
    *k.covisible.get_mut(&o).unwrap() += 1;
    let errors = broken.check_invariants();
    assert!(
        errors.iter().any(|e| e.contains("covisibility")),
        "{errors:?}"
    );
    // A point removed without its observations.
    let mut broken = map.clone();
    let p = *broken.points.keys().next().unwrap();
    broken.points.remove(&p);
    let errors = broken.check_invariants();
    assert!(
        errors.iter().any(|e| e.contains("missing point")),
        "{errors:?}"
    );
    // Culling through the map keeps it consistent and the trajectory where it was.
    let mut culled = map.clone();
    let victim = culled.keyframes.keys().nth(1).copied().unwrap();
    let substitute = culled.keyframes[&victim].best_covisible(1)[0];
    let before: Vec<Se3> = culled
        .trajectory
        .iter()
        .map(|r| culled.frame_pose(r).unwrap())
        .collect();
    assert!(culled.cull_keyframe(victim, substitute));
    assert!(!culled.keyframes.contains_key(&victim));
    assert!(
        culled.check_invariants().is_empty(),
        "{:?}",
        culled.check_invariants()
    );
    for (r, b) in culled.trajectory.iter().zip(&before) {
        let d = (culled.frame_pose(r).unwrap().inverse() * *b).log().norm();
        assert!(d < 1e-9, "a frame moved by {d}");
    }
    // A point the culled keyframe created but no longer observes (its observation dropped as
    // an outlier) takes another reference keyframe too.
    let mut culled = map.clone();
    let (p, creator) = culled
        .points
        .values()
        .find(|p| p.observations.len() >= 2 && p.observations.contains_key(&p.first_keyframe))
        .map(|p| (p.id, p.first_keyframe))
        .unwrap();
    let substitute = culled.keyframes[&creator].best_covisible(1)[0];
    culled.remove_observation(creator, p);
    assert!(culled.points[&p].first_keyframe == creator);
    assert!(culled.cull_keyframe(creator, substitute));
    assert!(
        culled.check_invariants().is_empty(),
        "{:?}",
        culled.check_invariants()
    );
    assert_ne!(culled.points[&p].first_keyframe, creator);
}

#[test]
fn a_new_map_segment_is_merged_on_loop_closure() {
    // A bit more than one turn; a blackout over a quarter turn (no features at all) leaves the
    // camera looking at unmapped walls, so it can neither track nor relocalise and starts a new
    // map segment at the constant-velocity guess (90° off). Back at the start, loop closing
    // finds the old segment.
    let o = SyntheticOptions {
        landmarks: 900,
        frames: 320,
        turns: 1.15,
        seed: 21,
        ..Default::default()
    };
    let frames = generate(&o);
    let blackout = 100..170;
    let mut config = Config::default();
    config.mapping.ba_iterations = 10;
    let mut system = System::new(o.calib, config, false).unwrap();
    // The error of the relative pose between frame 50 (first segment) and `last` (second
    // segment): translation in metres, rotation in degrees.
    let relative_error = |system: &System, tracked: &[usize], last: usize| {
        let traj = system.trajectory();
        let pose = |frame: usize| traj[tracked.iter().position(|&i| i == frame).unwrap()].1;
        let estimated = pose(50).inverse() * pose(last);
        let truth = frames[50].world_from_cam.inverse() * frames[last].world_from_cam;
        let e = truth.inverse() * estimated;
        (e.translation.norm(), e.rotation.log().norm().to_degrees())
    };
    let mut restarts = Vec::new();
    let mut tracked = Vec::new();
    let mut before = None;
    for (i, f) in frames.iter().enumerate() {
        let r = if blackout.contains(&i) {
            let mut dark = f.clone();
            dark.left = Default::default();
            dark.right = Default::default();
            track(&mut system, &dark)
        } else {
            track(&mut system, f)
        };
        if blackout.contains(&i) {
            assert_eq!(r.state, TrackState::Lost, "frame {i} in the blackout");
            continue;
        }
        assert_ne!(r.state, TrackState::Lost, "frame {i} lost");
        if i > 0 && r.state == TrackState::Initialised {
            restarts.push(i);
        }
        tracked.push(i);
        if i > 50 && system.loop_closures().is_empty() {
            // No loop yet: the segment-to-segment error as tracked, without a merge.
            let segments = system.with_map(|m| m.segment_starts.len());
            before = Some((i, relative_error(&system, &tracked, i), segments));
        }
    }
    assert_eq!(
        restarts,
        vec![blackout.end],
        "the new segment starts after the blackout"
    );
    // The trajectory covers every frame outside the blackout.
    assert_eq!(tracked.len(), frames.len() - blackout.len());
    assert_eq!(system.trajectory().len(), tracked.len());
    let loops = system.loop_closures();
    let (frame, before, segments) = before.unwrap();
    let after = relative_error(&system, &tracked, frame);
    eprintln!(
        "frame {frame} relative to frame 50: {:.3} m / {:.1}° before the merge, {:.3} m / \
         {:.2}° after; loops {loops:?}",
        before.0, before.1, after.0, after.1
    );
    assert!(!loops.is_empty(), "no loop closed");
    assert_eq!(segments, 1, "one unjoined segment before the loop");
    let boundary = frames[blackout.end].t_ns;
    assert!(
        loops.iter().any(|&(q, m)| q > boundary && m < boundary),
        "no loop between the segments: {loops:?}"
    );
    assert!(
        system.with_map(|m| m.segment_starts.is_empty()),
        "the segments were not joined"
    );
    assert!(before.1 > 20.0, "the new segment was not off ({before:?})");
    assert!(
        after.0 < 0.1 * before.0 && after.1 < 2.0,
        "{after:?} vs {before:?}"
    );
    // One rigid alignment of the whole trajectory fits both segments.
    let estimated: Vec<Vector3<f64>> = system
        .trajectory()
        .iter()
        .map(|(_, p)| p.translation)
        .collect();
    let truth: Vec<Vector3<f64>> = tracked
        .iter()
        .map(|&i| frames[i].world_from_cam.translation)
        .collect();
    let e = ate(&estimated, &truth);
    eprintln!("ATE after the merge {e:.4} m");
    assert!(e < 0.05, "ATE {e} m after the merge");
    assert_consistent(&system);
}

#[test]
fn saturated_mapping_and_loop_closing_shut_down_under_load() {
    // Tiny queues, every frame a keyframe, culling and loop closing on: the tracker waits on
    // the mapping thread at every frame, and shutdown comes while both queues are full.
    let o = SyntheticOptions {
        landmarks: 500,
        frames: 400,
        turns: 1.15,
        seed: 13,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut config = Config::default();
    every_frame_a_keyframe(&mut config);
    config.mapping.queue = 1;
    config.mapping.cull_keyframes = true;
    config.mapping.min_found_ratio = 0.25;
    config.loop_closing.skip_recent = 5;
    let mut system = System::new(o.calib, config, true).unwrap();
    for f in &frames {
        let r = track(&mut system, f);
        assert_ne!(r.state, TrackState::Lost, "frame {} lost", f.t_ns);
        assert!(r.keyframe);
    }
    let start = std::time::Instant::now();
    system.shutdown();
    eprintln!(
        "shutdown under load took {:?}; {} keyframes left, {} culled, loops {:?}",
        start.elapsed(),
        system.keyframe_trajectory().len(),
        system.culled_keyframes(),
        system.loop_closures()
    );
    let traj = system.trajectory();
    assert_eq!(traj.len(), frames.len());
    assert!(traj.windows(2).all(|w| w[0].0 < w[1].0));
    assert!(system.culled_keyframes() > 0);
    assert_consistent(&system);
    let estimated: Vec<Vector3<f64>> = traj.iter().map(|(_, p)| p.translation).collect();
    let truth = truth_positions(&frames);
    let e = ate(&estimated, &truth);
    eprintln!("ATE {e:.4} m");
    assert!(e < 0.1, "ATE {e} m");
}

/// Keyframes in the map and the ATE of the trajectory so far, after each of `laps` equal
/// parts of `frames` (tracked synchronously, no frame lost).
fn laps(
    frames: &[SyntheticFrame],
    o: &SyntheticOptions,
    config: Config,
    laps: usize,
) -> (System, Vec<usize>, f64) {
    let mut system = System::new(o.calib, config, false).unwrap();
    let mut counts = Vec::new();
    let per_lap = frames.len() / laps;
    for (i, f) in frames.iter().enumerate() {
        let r = track(&mut system, f);
        assert_ne!(r.state, TrackState::Lost, "frame {} lost", f.t_ns);
        if (i + 1) % per_lap == 0 {
            counts.push(system.with_map(|m| m.keyframes.len()));
        }
    }
    let traj = system.trajectory();
    assert_eq!(traj.len(), frames.len());
    let estimated: Vec<Vector3<f64>> = traj.iter().map(|(_, p)| p.translation).collect();
    let truth = truth_positions(frames);
    let e = ate(&estimated, &truth);
    (system, counts, e)
}

#[test]
fn default_culling_stops_keyframe_growth_on_revisits_and_keeps_accuracy() {
    // Two turns of the circle (4° per frame): the 2nd turn revisits the places of the first.
    // With the default policy the keyframe count must stop growing after the first turn
    // (without culling it triples) and the trajectory must stay as accurate as without
    // culling.
    let o = SyntheticOptions {
        landmarks: 600,
        frames: 180,
        turns: 2.0,
        seed: 21,
        ..Default::default()
    };
    let frames = generate(&o);
    let mut config = Config::default();
    assert!(config.mapping.cull_keyframes, "culling is on by default");
    config.mapping.ba_iterations = 5;
    config.mapping.window = 5;
    config.mapping.max_fixed = 5;
    let (on, on_counts, ate_on) = laps(&frames, &o, config.clone(), 2);
    config.mapping.cull_keyframes = false;
    let (_, off_counts, ate_off) = laps(&frames, &o, config.clone(), 2);
    eprintln!(
        "keyframes after each turn: off {off_counts:?} (ATE {ate_off:.4} m), on {on_counts:?} \
         ({} culled, ATE {ate_on:.4} m), fused {} / redirects kept {}",
        on.culled_keyframes(),
        on.fusion_totals().merged,
        on.with_map(|m| m.replaced.len())
    );
    // Without culling the map grows by about as much on each turn.
    assert!(
        off_counts[1] - off_counts[0] > off_counts[0] / 2,
        "{off_counts:?}"
    );
    // Growth over the second turn at most a tenth of the first turn's keyframes.
    assert!(
        on_counts[1] <= on_counts[0] + on_counts[0] / 10,
        "keyframes kept growing: {on_counts:?}"
    );
    assert!(
        on_counts[1] < off_counts[1],
        "{on_counts:?} vs {off_counts:?}"
    );
    assert!(
        ate_on <= 1.25 * ate_off + 0.005,
        "ATE {ate_on} m with culling vs {ate_off} m without"
    );
    assert_consistent(&on);
    // The places of the last turn hold no more than the budget plus what is protected (the
    // newest keyframe's window and the keyframes too young to be examined).
    let cfg = &config.mapping;
    on.with_map(|m| {
        let newest = *m.keyframes.keys().last().unwrap();
        let here = keyframes_at_place(m, newest, cfg);
        assert!(
            here.len() <= (cfg.keyframes_per_place + cfg.window + cfg.cull_min_age) as usize,
            "{} keyframes at the last place",
            here.len()
        );
        // Fused-point redirects are bounded: none older than the horizon.
        let oldest = m.next_keyframe.saturating_sub(replaced_horizon(cfg));
        assert!(m.replaced.values().all(|r| r.stamp >= oldest));
    });
}

#[test]
fn fused_point_redirects_are_compressed_dropped_with_their_point_and_pruned() {
    let system = short_run();
    let mut map = system.with_map(Map::clone);
    map.replaced.clear();
    // Three points fused in a chain a → b → c.
    let ids: Vec<u64> = map.points.keys().copied().collect();
    let [a, b, c] = [ids[0], ids[1], ids[2]];
    assert!(map.merge_points(b, a));
    assert_eq!(map.resolve(a), b);
    assert!(map.merge_points(c, b));
    // Path compression: a resolves to c in one step, no entry names a removed point.
    assert_eq!(map.replaced[&a].target, c);
    assert_eq!(map.resolve(a), c);
    assert_eq!(map.resolve(b), c);
    assert!(
        map.check_invariants().is_empty(),
        "{:?}",
        map.check_invariants()
    );
    // A broken redirect (to a removed point) is reported by the invariant check.
    let mut broken = map.clone();
    broken.points.remove(&c);
    assert!(broken
        .check_invariants()
        .iter()
        .any(|e| e.contains("fused point")));
    // Removing the absorbing point drops the entries that led to it.
    let mut removed = map.clone();
    removed.remove_point(c);
    assert!(removed.replaced.is_empty());
    assert!(removed.check_invariants().is_empty());
    // Entries older than the horizon go; newer ones stay.
    let horizon = 10;
    map.next_keyframe += horizon + 1;
    let d = *map.points.keys().find(|&&p| p != c).unwrap();
    if map.merge_points(c, d) {
        map.prune_replaced(horizon);
        assert_eq!(map.replaced.keys().copied().collect::<Vec<_>>(), vec![d]);
    } else {
        panic!("fusing {d} into {c} refused");
    }
    map.next_keyframe += horizon + 1;
    map.prune_replaced(horizon);
    assert!(map.replaced.is_empty());
}
