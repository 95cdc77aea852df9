//! SLAM back-end costs per stage, on synthetic sequences with ~1 000 stereo features a frame
//! (`slam::synthetic`, 5 500 landmarks, 0.5 px noise, 10 % outliers, 32-D float descriptors):
//! - tracking one frame: stereo matching + local-map search + two motion-only refinements
//!   (excluding feature extraction and keyframe insertion), after 60 frames of mapping;
//!   The tracking row is repeated on a map built without the mapping fusion (the baseline);
//! - fusion of duplicate points and re-finding for one keyframe, on a copy of the map;
//! - local mapping for one keyframe (local BA over the window + culling), on a copy of the map;
//! - loop detection for one keyframe without a loop (embedding, place query, verification);
//! - loop detection + correction for the keyframe that closes the loop (verification by PnP in
//!   both directions,
//!   pose graph over all keyframes, point correction, fusion), on a copy of the map.
//!
//! `RAYON_NUM_THREADS=1 cargo bench -p dhptam-core --bench slam` (one core).

use std::sync::{Mutex, RwLock};

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use dhptam_core::config::Config;
use dhptam_core::matching::{best_two, Descriptors};
use dhptam_core::place::{embedding, PlaceDatabase};
use dhptam_core::slam::loop_closing::detect_and_close;
use dhptam_core::slam::synthetic::{generate, SyntheticFrame, SyntheticOptions};
use dhptam_core::slam::tracking::{
    last_pose, stereo_match, track_local_map, StereoFrame, TrackContext,
};
use dhptam_core::slam::{
    fuse_and_refind, local_mapping, DisparityCorrection, FrameFeatures, Map, System,
};

fn track(system: &mut System, f: &SyntheticFrame) {
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
    let right = FrameFeatures {
        keypoints: &f.right.keypoints,
        descriptors: Descriptors::float(&f.right.descriptors, 32).unwrap(),
        sigmas: None,
        sigma_scale: 1.0,
        disparity: DisparityCorrection::IDENTITY,
        event_stereo: None,
        viewpoint: [0.0; 3],
        dvs_biased: false,
        quiet: false,
    };
    system.track(f.t_ns, left, right).unwrap();
}

fn options(frames: usize, turns: f64) -> SyntheticOptions {
    SyntheticOptions {
        landmarks: 5500,
        frames,
        turns,
        seed: 2,
        ..Default::default()
    }
}

fn tracking(c: &mut Criterion) {
    // The map built with the mapping fusion, and without it (the back-end before the fusion
    // existed: the same tracking code, the baseline of the first row).
    for fuse in [true, false] {
        track_bench(c, fuse);
    }
}

fn track_bench(c: &mut Criterion, fuse: bool) {
    let o = options(200, 0.5);
    let frames = generate(&o);
    let mut config = Config::default();
    config.mapping.fuse = fuse;
    let mut system = System::new(o.calib, config.clone(), false).unwrap();
    frames[..60].iter().for_each(|f| track(&mut system, f));
    let f = &frames[60];
    eprintln!(
        "tracking frame: {} left, {} right features; map (fusion {fuse}): {} points, {:?}",
        f.left.keypoints.len() / 2,
        f.right.keypoints.len() / 2,
        system.with_map(|m| m.points.len()),
        system.fusion_totals(),
    );
    let suffix = if fuse { "" } else { "_map_without_fusion" };
    let ctx = TrackContext {
        calib: &o.calib,
        cfg: &config.tracking,
        tri: &config.triangulation,
    };
    let state = system.tracker_state().clone();
    let xy = |v: &[f32]| -> Vec<[f32; 2]> { v.chunks_exact(2).map(|c| [c[0], c[1]]).collect() };
    let (lxy, rxy) = (xy(&f.left.keypoints), xy(&f.right.keypoints));
    let (ld, rd) = (
        Descriptors::float(&f.left.descriptors, 32).unwrap(),
        Descriptors::float(&f.right.descriptors, 32).unwrap(),
    );
    system.with_map(|map| {
        let predicted = state.velocity * last_pose(map, &state).unwrap().inverse();
        let mut g = c.benchmark_group("slam");
        g.bench_function(format!("track_frame_1000_features{suffix}"), |b| {
            b.iter(|| {
                let u_right = stereo_match(ctx.calib, ctx.cfg, ctx.tri, &lxy, ld, &rxy, rd);
                let frame = StereoFrame {
                    t_ns: f.t_ns,
                    keypoints: lxy.clone(),
                    u_right,
                    sigmas: vec![1.0; lxy.len()],
                    viewpoints: vec![[0.0; 3]; lxy.len()],
                    descriptors: ld,
                    dvs_biased: false,
                    quiet: false,
                };
                let t = track_local_map(map, &state, &frame, &ctx, predicted).unwrap();
                assert!(t.inliers > 300);
                t
            })
        });
        if fuse {
            g.bench_function("stereo_match_1000_features", |b| {
                b.iter(|| stereo_match(ctx.calib, ctx.cfg, ctx.tri, &lxy, ld, &rxy, rd))
            });
        }
        g.finish();
    });
    if !fuse {
        return;
    }
    let map: Map = system.with_map(|m| m.clone());
    let kf = *map.keyframes.keys().last().unwrap();
    let mut g = c.benchmark_group("slam");
    g.sample_size(20);
    let probe = RwLock::new(map.clone());
    let report = fuse_and_refind(
        &probe,
        kf,
        &o.calib,
        &config.mapping,
        &config.tracking,
        &config.triangulation,
        None,
    )
    .unwrap();
    eprintln!("fusion of keyframe {kf} (already mapped once): {report:?}");
    g.bench_function("fusion_per_keyframe", |b| {
        b.iter_batched(
            || RwLock::new(map.clone()),
            |m| {
                fuse_and_refind(
                    &m,
                    kf,
                    &o.calib,
                    &config.mapping,
                    &config.tracking,
                    &config.triangulation,
                    None,
                )
                .unwrap()
            },
            BatchSize::LargeInput,
        )
    });
    g.bench_function("local_mapping_per_keyframe", |b| {
        b.iter_batched(
            || RwLock::new(map.clone()),
            |m| {
                local_mapping(
                    &m,
                    kf,
                    &o.calib,
                    &config.mapping,
                    &config.tracking,
                    &config.triangulation,
                    None,
                )
                .unwrap()
            },
            BatchSize::LargeInput,
        )
    });
    g.finish();
}

fn database(map: &Map, except: u64) -> PlaceDatabase {
    let mut db = PlaceDatabase::new();
    for k in map.keyframes.values().filter(|k| k.id != except) {
        db.add(k.id, embedding(k.descriptors.view()).unwrap())
            .unwrap();
    }
    db
}

fn loops(c: &mut Criterion) {
    let o = SyntheticOptions {
        drift_deg: 4.0,
        drift_m: 0.4,
        seed: 21,
        ..options(460, 1.15)
    };
    let frames = generate(&o);
    let mut config = Config::default();
    config.loop_closing.enabled = false;
    let mut system = System::new(o.calib, config.clone(), false).unwrap();
    frames[..400].iter().for_each(|f| track(&mut system, f));
    config.loop_closing.enabled = true;
    let map: Map = system.with_map(|m| m.clone());
    let ids: Vec<u64> = map.keyframes.keys().copied().collect();
    let last = *ids.last().unwrap();
    let middle = ids[ids.len() / 2];
    eprintln!(
        "loop map: {} keyframes, {} points",
        map.keyframes.len(),
        map.points.len()
    );
    let mut g = c.benchmark_group("slam");
    g.sample_size(20);
    for (name, kf, expect_loop) in [
        ("loop_detection_no_loop", middle, false),
        ("loop_detection_and_correction", last, true),
    ] {
        g.bench_function(name, |b| {
            b.iter_batched(
                || (RwLock::new(map.clone()), Mutex::new(database(&map, kf))),
                |(m, db)| {
                    let r = detect_and_close(
                        &m,
                        &db,
                        kf,
                        &o.calib,
                        &config.tracking,
                        &config.loop_closing,
                    )
                    .unwrap();
                    assert_eq!(r.is_some(), expect_loop);
                    (m, db)
                },
                BatchSize::LargeInput,
            )
        });
    }
    g.finish();
}

/// Nearest two of 10 000 binary 256-bit descriptors (ORB's size) for each of 1000 queries, one
/// thread: the brute-force search relocalisation and loop verification run against a
/// keyframe's neighbourhood of map points.
fn matching(c: &mut Criterion) {
    // A fixed xorshift stream: the same bytes every run.
    let mut state = 0x9e37_79b9_7f4a_7c15_u64;
    let mut bytes = |n: usize| -> Vec<u8> {
        (0..n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state as u8
            })
            .collect()
    };
    let (queries, train) = (bytes(1000 * 32), bytes(10_000 * 32));
    let queries = Descriptors::binary(&queries, 32).unwrap();
    let train = Descriptors::binary(&train, 32).unwrap();
    let mut g = c.benchmark_group("matching");
    g.sample_size(20);
    g.bench_function("best_two_orb_1000_against_10000", |b| {
        b.iter(|| {
            (0..queries.len())
                .filter_map(|i| best_two(queries.row(i), train, 0..train.len()))
                .map(|(j, _, _)| j)
                .sum::<usize>()
        })
    });
    g.finish();
}

criterion_group!(benches, tracking, loops, matching);
criterion_main!(benches);
