//! Loop closing and relocalisation through place recognition.
//!
//! Every keyframe's embedding (normalised mean descriptor) goes into a [`PlaceDatabase`].
//! A new keyframe queries it, skipping itself, its covisible keyframes and the most recent
//! ones; each candidate is verified by matching the keyframe's descriptors against the map
//! points around the candidate and RANSAC PnP on those 3-D–2-D pairs. An accepted loop adds
//! an edge to a pose graph over all keyframes (odometry edges: the relative poses before the
//! correction, between consecutive and strongly covisible keyframes), which is optimised;
//! map points move with the keyframe that created them, and the loop keyframe's matched
//! points are fused with the old ones. The tracker follows automatically, as its frames are
//! stored relative to keyframes. Relocalisation uses the same query and verification for a
//! lost frame.

use std::collections::BTreeMap;

use nalgebra::{Matrix6, Vector2, Vector3};
use rayon::prelude::*;

use super::map::Map;
use super::tracking::match_options;
use super::StereoCalibration;
use crate::config::{LoopClosingConfig, TrackingConfig};
use crate::error::Result;
use crate::geometry::Se3;
use crate::io::{EdgeSe3, PoseGraph3};
use crate::matching::{best_two, Descriptors, OwnedDescriptors};
use crate::place::PlaceDatabase;
use crate::solver::{solve_pnp_ransac, solve_pose_graph3, PnpRansacOptions, PoseGraphOptions};

/// Keyframes around a candidate whose points take part in verification.
const CANDIDATE_NEIGHBOURS: usize = 5;

/// A verified place match: the query's pose in the map's frame and its 2-D–3-D inliers.
pub struct PlaceMatch {
    /// The matched (candidate) keyframe.
    pub candidate: u64,
    /// `cam_from_world` of the query from PnP against the candidate's points.
    pub cam_from_world: Se3,
    /// Inlier pairs (query keypoint index, map point id).
    pub pairs: Vec<(usize, u64)>,
}

/// Matches query descriptors to the points around `candidate` and verifies by RANSAC PnP.
pub fn verify(
    map: &Map,
    candidate: u64,
    keypoints: &[[f32; 2]],
    descriptors: Descriptors,
    calib: &StereoCalibration,
    tracking: &TrackingConfig,
    cfg: &LoopClosingConfig,
) -> Result<Option<PlaceMatch>> {
    let Some(c) = map.keyframes.get(&candidate) else {
        return Ok(None);
    };
    let mut around = vec![candidate];
    around.extend(c.best_covisible(CANDIDATE_NEIGHBOURS));
    let ids = map.points_of(&around);
    if ids.len() < cfg.min_inliers as usize {
        return Ok(None);
    }
    let mut train = OwnedDescriptors::new(descriptors.kind(), descriptors.width());
    for id in &ids {
        train.push(map.points[id].descriptor.view())?;
    }
    let train = train.view();
    let options = match_options(tracking, descriptors.kind());
    let pairs: Vec<(usize, u64)> = (0..descriptors.len())
        .into_par_iter()
        .filter_map(|i| {
            let (j, best, second) = best_two(descriptors.row(i), train, 0..train.len())?;
            (best <= options.max_distance && best < options.ratio * second).then_some((i, ids[j]))
        })
        .collect();
    if pairs.len() < cfg.min_inliers as usize {
        log::debug!(
            "place: candidate {candidate}: {} descriptor matches",
            pairs.len()
        );
        return Ok(None);
    }
    let points: Vec<Vector3<f64>> = pairs.iter().map(|p| map.points[&p.1].position).collect();
    let pixels: Vec<Vector2<f64>> = pairs
        .iter()
        .map(|p| Vector2::new(keypoints[p.0][0] as f64, keypoints[p.0][1] as f64))
        .collect();
    let pnp = solve_pnp_ransac(
        &calib.intrinsics(),
        &points,
        &pixels,
        &PnpRansacOptions {
            threshold_px: cfg.ransac_threshold_px,
            confidence: 0.999,
            max_iterations: cfg.ransac_iterations as usize,
            min_inliers: cfg.min_inliers as usize,
            seed: cfg.seed,
        },
    )?;
    let Some(pnp) = pnp.filter(|p| p.inlier_count >= cfg.min_inliers as usize) else {
        log::debug!("place: candidate {candidate}: PnP found no pose with enough inliers");
        return Ok(None);
    };
    let inliers = pairs
        .into_iter()
        .zip(&pnp.inliers)
        .filter_map(|(p, &ok)| ok.then_some(p))
        .collect();
    Ok(Some(PlaceMatch {
        candidate,
        cam_from_world: pnp.cam_from_world,
        pairs: inliers,
    }))
}

/// Looks for a loop of keyframe `kf` (adding its embedding to `db` afterwards) and closes it.
/// Returns the matched keyframe when a loop was closed.
pub fn detect_and_close(
    map_lock: &std::sync::RwLock<Map>,
    db: &std::sync::Mutex<PlaceDatabase>,
    kf: u64,
    calib: &StereoCalibration,
    tracking: &TrackingConfig,
    cfg: &LoopClosingConfig,
) -> Result<Option<u64>> {
    let found = {
        let map = super::read_lock(map_lock);
        let Some(k) = map.keyframes.get(&kf) else {
            return Ok(None);
        };
        let Some(e) = crate::place::embedding(k.descriptors.view()) else {
            return Ok(None);
        };
        let candidates = {
            let mut db = super::lock(db);
            let skip = cfg.skip_recent as u64;
            let c = db.query(&e, cfg.candidates as usize, cfg.min_score as f32, |id| {
                id == kf || k.covisible.contains_key(&id) || kf.saturating_sub(id) < skip
            });
            db.add(kf, e)?;
            c
        };
        if !cfg.enabled || candidates.is_empty() {
            return Ok(None);
        }
        let mut found = None;
        for (c, score) in candidates {
            let v = verify(
                &map,
                c,
                &k.keypoints,
                k.descriptors.view(),
                calib,
                tracking,
                cfg,
            )?;
            match v {
                Some(m) => {
                    log::info!(
                        "loop: keyframe {kf} matches keyframe {c} (score {score:.3}, {} PnP inliers)",
                        m.pairs.len()
                    );
                    found = Some(m);
                    break;
                }
                None => {
                    log::info!("loop: keyframe {kf}: candidate {c} (score {score:.3}) rejected")
                }
            }
        }
        found
    };
    let Some(m) = found else {
        return Ok(None);
    };
    let mut map = super::write_lock(map_lock);
    correct(&mut map, kf, &m)?;
    Ok(Some(m.candidate))
}

/// Optimises the keyframe pose graph with the loop edge, moves the points and fuses the loop
/// keyframe's matches with the old points.
fn correct(map: &mut Map, kf: u64, m: &PlaceMatch) -> Result<()> {
    let ids: Vec<u64> = map.keyframes.keys().copied().collect();
    let index: BTreeMap<u64, usize> = ids.iter().enumerate().map(|(i, &id)| (id, i)).collect();
    let old: Vec<Se3> = ids
        .iter()
        .map(|id| map.keyframes[id].world_from_cam)
        .collect();
    let (Some(&qi), Some(&ci)) = (index.get(&kf), index.get(&m.candidate)) else {
        return Ok(());
    };
    let edge = |i: usize, j: usize, z: Se3| EdgeSe3 {
        from: i,
        to: j,
        measurement: z,
        information: Matrix6::identity(),
    };
    let mut edges = Vec::new();
    for i in 1..ids.len() {
        edges.push(edge(i - 1, i, old[i - 1].inverse() * old[i]));
    }
    // Earlier loops stay closed: their pairs keep today's relative poses.
    for (a, b) in &map.loops {
        if let (Some(&i), Some(&j)) = (index.get(a), index.get(b)) {
            edges.push(edge(j, i, old[j].inverse() * old[i]));
        }
    }
    let corrected_query = m.cam_from_world.inverse();
    edges.push(edge(ci, qi, old[ci].inverse() * corrected_query));
    let mut graph = PoseGraph3 {
        ids: (0..ids.len()).collect(),
        poses: old.clone(),
        edges,
        fixed: vec![0],
    };
    let report = solve_pose_graph3(&mut graph, &PoseGraphOptions::default())?;
    log::info!(
        "loop: pose graph over {} keyframes, cost {:.3e} → {:.3e}",
        ids.len(),
        report.initial_cost,
        report.final_cost
    );
    // Per keyframe: new_world_from_old_world.
    let delta: Vec<Se3> = graph
        .poses
        .iter()
        .zip(&old)
        .map(|(n, o)| *n * o.inverse())
        .collect();
    for (i, id) in ids.iter().enumerate() {
        if let Some(k) = map.keyframes.get_mut(id) {
            k.world_from_cam = graph.poses[i];
        }
    }
    let point_ids: Vec<u64> = map.points.keys().copied().collect();
    for pid in point_ids {
        let Some(p) = map.points.get(&pid) else {
            continue;
        };
        let reference = index
            .get(&p.first_keyframe)
            .or_else(|| p.observations.keys().next().and_then(|o| index.get(o)));
        if let Some(&r) = reference {
            let moved = delta[r].transform_point(&p.position);
            if let Some(p) = map.points.get_mut(&pid) {
                p.position = moved;
            }
        }
    }
    // Fuse: the loop keyframe's matched keypoints take the old points.
    for &(feature, old_point) in &m.pairs {
        let current = map.keyframes.get(&kf).and_then(|k| k.points[feature]);
        match current {
            Some(q) if q == old_point => {}
            Some(q) => {
                let observers: Vec<(u64, u32)> = map
                    .points
                    .get(&q)
                    .map(|p| p.observations.iter().map(|(a, b)| (*a, *b)).collect())
                    .unwrap_or_default();
                map.remove_point(q);
                for (o, f) in observers {
                    map.add_observation(o, f as usize, old_point);
                }
            }
            None => map.add_observation(kf, feature, old_point),
        }
    }
    map.loops.push((kf, m.candidate));
    map.corrections += 1;
    Ok(())
}
