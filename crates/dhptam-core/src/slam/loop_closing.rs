//! Loop closing and relocalisation through place recognition.
//!
//! Every keyframe's embedding (normalised mean descriptor) goes into a [`PlaceDatabase`].
//! A new keyframe queries it, skipping itself, its covisible keyframes and the most recent
//! ones; each candidate is verified by RANSAC PnP in both directions (the keyframe's keypoints
//! against the map points around the candidate, and the candidate's keypoints against the map
//! points around the keyframe), accepted only when both succeed and the relative poses they
//! imply agree ([`verify_loop`]). An accepted loop adds
//! an edge to a pose graph over all keyframes (odometry edges: the relative poses before the
//! correction between keyframes consecutive by id, plus the edges of earlier loops; every
//! edge with unit information), which is optimised;
//! no odometry edge crosses the boundary of a map segment that tracking started after a loss
//! until a loop joins the two segments, so a loop between segments moves the new segment onto
//! the old one as a whole (issue 10);
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

/// One direction of a verification: descriptor matches of keypoints to map points, and the
/// RANSAC PnP pose with its inliers (`None` when there were too few matches or no pose).
struct Direction {
    /// Descriptor matches that passed the distance and ratio tests.
    matches: usize,
    /// `cam_from_world` of the camera of the keypoints and its inlier pairs
    /// (keypoint index, map point id).
    pose: Option<(Se3, Vec<(usize, u64)>)>,
}

impl Direction {
    fn inliers(&self) -> usize {
        self.pose.as_ref().map_or(0, |p| p.1.len())
    }
}

/// Matches the keypoints' descriptors to the map points `ids` and runs RANSAC PnP on the
/// 3-D–2-D pairs.
#[allow(clippy::too_many_arguments)]
fn match_and_solve(
    map: &Map,
    ids: &[u64],
    keypoints: &[[f32; 2]],
    descriptors: Descriptors,
    calib: &StereoCalibration,
    tracking: &TrackingConfig,
    cfg: &LoopClosingConfig,
) -> Result<Direction> {
    let none = |matches| Direction {
        matches,
        pose: None,
    };
    if ids.len() < cfg.min_inliers as usize {
        return Ok(none(0));
    }
    let mut train = OwnedDescriptors::new(descriptors.kind(), descriptors.width());
    for id in ids {
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
        return Ok(none(pairs.len()));
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
    let matches = pairs.len();
    let Some(pnp) = pnp.filter(|p| p.inlier_count >= cfg.min_inliers as usize) else {
        return Ok(none(matches));
    };
    let inliers = pairs
        .into_iter()
        .zip(&pnp.inliers)
        .filter_map(|(p, &ok)| ok.then_some(p))
        .collect();
    Ok(Direction {
        matches,
        pose: Some((pnp.cam_from_world, inliers)),
    })
}

/// Map points of keyframe `kf` and of its most covisible neighbours.
fn neighbourhood_points(map: &Map, kf: u64) -> Vec<u64> {
    let Some(k) = map.keyframes.get(&kf) else {
        return Vec::new();
    };
    let mut around = vec![kf];
    around.extend(k.best_covisible(CANDIDATE_NEIGHBOURS));
    map.points_of(&around)
}

/// Matches query descriptors to the points around `candidate` and verifies by RANSAC PnP (one
/// direction: what relocalisation of a frame, which has no map points, can do).
pub fn verify(
    map: &Map,
    candidate: u64,
    keypoints: &[[f32; 2]],
    descriptors: Descriptors,
    calib: &StereoCalibration,
    tracking: &TrackingConfig,
    cfg: &LoopClosingConfig,
) -> Result<Option<PlaceMatch>> {
    let ids = neighbourhood_points(map, candidate);
    let d = match_and_solve(map, &ids, keypoints, descriptors, calib, tracking, cfg)?;
    let matches = d.matches;
    match d.pose {
        Some((cam_from_world, pairs)) => Ok(Some(PlaceMatch {
            candidate,
            cam_from_world,
            pairs,
        })),
        None => {
            log::debug!("place: candidate {candidate}: {matches} descriptor matches, no PnP pose");
            Ok(None)
        }
    }
}

/// The numbers behind a loop verification (both directions), for logging and tests.
#[derive(Clone, Debug, PartialEq)]
pub struct LoopCheck {
    /// Query keyframe.
    pub query: u64,
    /// Candidate keyframe.
    pub candidate: u64,
    /// Forward: descriptor matches of the query's keypoints to the candidate's neighbourhood
    /// points, and PnP inliers (0 when PnP failed).
    pub forward: (usize, usize),
    /// Backward: descriptor matches of the candidate's keypoints to the query's neighbourhood
    /// points, and PnP inliers (0 when PnP failed).
    pub backward: (usize, usize),
    /// Disagreement of the two relative poses `candidate_from_query`, rotation in degrees and
    /// translation in metres; `None` unless both directions found a pose.
    pub disagreement: Option<(f64, f64)>,
    /// Whether the loop is accepted: both directions found a pose and they agree within
    /// `max_disagreement_deg` / `max_disagreement_m`.
    pub accepted: bool,
}

/// Verifies a loop between keyframes `query` and `candidate` by RANSAC PnP in both directions:
/// the query's keypoints against the map points around the candidate (the query's pose in the
/// candidate's part of the map), and the candidate's keypoints against the map points around
/// the query (the candidate's pose in the query's part). Each gives the relative pose
/// `candidate_from_query` in its own part of the map; the loop is accepted only when both
/// directions succeed and the two agree. Returns the check's numbers and, when accepted, the
/// forward match (used for the correction).
pub fn verify_loop(
    map: &Map,
    query: u64,
    candidate: u64,
    calib: &StereoCalibration,
    tracking: &TrackingConfig,
    cfg: &LoopClosingConfig,
) -> Result<(LoopCheck, Option<PlaceMatch>)> {
    let mut check = LoopCheck {
        query,
        candidate,
        forward: (0, 0),
        backward: (0, 0),
        disagreement: None,
        accepted: false,
    };
    let (Some(q), Some(c)) = (map.keyframes.get(&query), map.keyframes.get(&candidate)) else {
        return Ok((check, None));
    };
    let ids = neighbourhood_points(map, candidate);
    let forward = match_and_solve(
        map,
        &ids,
        &q.keypoints,
        q.descriptors.view(),
        calib,
        tracking,
        cfg,
    )?;
    check.forward = (forward.matches, forward.inliers());
    let ids = neighbourhood_points(map, query);
    let backward = match_and_solve(
        map,
        &ids,
        &c.keypoints,
        c.descriptors.view(),
        calib,
        tracking,
        cfg,
    )?;
    check.backward = (backward.matches, backward.inliers());
    let (Some((q_cam_from_world, pairs)), Some((c_cam_from_world, _))) =
        (forward.pose, backward.pose)
    else {
        return Ok((check, None));
    };
    // Forward: the query placed in the candidate's part of the map.
    let c_from_q_forward = c.world_from_cam.inverse() * q_cam_from_world.inverse();
    // Backward: the candidate placed in the query's part of the map.
    let c_from_q_backward = c_cam_from_world * q.world_from_cam;
    let error = c_from_q_forward.inverse() * c_from_q_backward;
    let rotation_deg = error.rotation.log().norm().to_degrees();
    let translation_m = error.translation.norm();
    check.disagreement = Some((rotation_deg, translation_m));
    check.accepted =
        rotation_deg <= cfg.max_disagreement_deg && translation_m <= cfg.max_disagreement_m;
    let m = check.accepted.then_some(PlaceMatch {
        candidate,
        cam_from_world: q_cam_from_world,
        pairs,
    });
    Ok((check, m))
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
            let (check, mut m) = verify_loop(&map, kf, c, calib, tracking, cfg)?;
            let mut agreement = match check.disagreement {
                Some((r, t)) => format!(
                    "relative poses differ by {r:.2} deg / {t:.3} m (limits {:.2} deg / {:.3} m)",
                    cfg.max_disagreement_deg, cfg.max_disagreement_m
                ),
                None => "no relative pose to compare".to_string(),
            };
            // Within one map the tracked poses are measurements: a loop that would turn the
            // query keyframe by more than tracking can drift matched a look-alike place.
            if let Some(turn) = m.as_ref().map(|m| correction_deg(k.world_from_cam, m)) {
                if turn > cfg.max_correction_deg && Segments::of(&map).same_map(kf, c) {
                    agreement += &format!(
                        "; it would turn the keyframe by {turn:.1} deg within one map (limit \
                         {:.1} deg)",
                        cfg.max_correction_deg
                    );
                    m = None;
                }
            }
            log::info!(
                "loop: keyframe {kf}: candidate {c} (score {score:.3}) {}: forward {} matches / {} \
                 PnP inliers, backward {} matches / {} PnP inliers (at least {} needed), {agreement}",
                if m.is_some() { "accepted" } else { "rejected" },
                check.forward.0,
                check.forward.1,
                check.backward.0,
                check.backward.1,
                cfg.min_inliers,
            );
            if let Some(m) = m {
                found = Some(m);
                break;
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

/// How far, in degrees, a loop match `m` turns its query keyframe from `world_from_cam`.
fn correction_deg(world_from_cam: Se3, m: &PlaceMatch) -> f64 {
    (world_from_cam.inverse() * m.cam_from_world.inverse())
        .rotation
        .angle()
        .to_degrees()
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
    // Map segments (issue 10): the relative pose across an unjoined segment boundary is a
    // guess, not a measurement, so no odometry edge crosses it; each segment is one group of
    // keyframes, and loops (earlier ones and this one) join groups.
    let Segments { starts, mut groups } = {
        let mut s = Segments::of(map);
        s.join(kf, m.candidate);
        s
    };
    let mut edges = Vec::new();
    for i in 1..ids.len() {
        if starts.binary_search(&ids[i]).is_err() {
            edges.push(edge(i - 1, i, old[i - 1].inverse() * old[i]));
        }
    }
    // Earlier loops stay closed: their pairs keep today's relative poses.
    for (a, b) in &map.loops {
        if let (Some(&i), Some(&j)) = (index.get(a), index.get(b)) {
            edges.push(edge(j, i, old[j].inverse() * old[i]));
        }
    }
    let corrected_query = m.cam_from_world.inverse();
    edges.push(edge(ci, qi, old[ci].inverse() * corrected_query));
    // The gauge: the first keyframe, and the first keyframe of the oldest segment of every
    // group that no loop ties to the first segment (those segments keep their pose).
    let mut fixed = vec![0];
    let mut anchored = vec![groups.find(0)];
    for (g, &s) in starts.iter().enumerate() {
        let root = groups.find(g + 1);
        if !anchored.contains(&root) {
            anchored.push(root);
            fixed.push(index[&s]);
        }
    }
    let mut graph = PoseGraph3 {
        ids: (0..ids.len()).collect(),
        poses: old.clone(),
        edges,
        fixed,
    };
    let report = solve_pose_graph3(&mut graph, &PoseGraphOptions::default())?;
    log::info!(
        "loop: pose graph over {} keyframes, cost {:.3e} → {:.3e}; the loop moves keyframe {kf} \
         by {:.3} m / {:.2} deg",
        ids.len(),
        report.initial_cost,
        report.final_cost,
        (old[qi].inverse() * corrected_query).translation.norm(),
        correction_deg(old[qi], m)
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
                // The old point keeps its id; `q` resolves to it (ids held by tracking).
                map.merge_points(old_point, q);
            }
            None => map.add_observation(kf, feature, old_point),
        }
    }
    map.loops.push((kf, m.candidate));
    // Segments now in the same group as the segment before them are joined: the corrected
    // relative pose across their boundary is a measurement from here on.
    for (g, &s) in starts.iter().enumerate() {
        if groups.find(g + 1) == groups.find(g) {
            map.segment_starts.remove(&s);
            log::info!(
                "loop: keyframe {kf}: the map segment starting at keyframe {s} is joined to the \
                 one before it (loop with keyframe {})",
                m.candidate
            );
        }
    }
    map.corrections += 1;
    Ok(())
}

/// Disjoint sets over map segments (union by smaller root, path halving).
struct Groups(Vec<usize>);

/// The map's segments (the ids of their first keyframes, each still in the map) and the
/// groups that loops have joined them into.
struct Segments {
    starts: Vec<u64>,
    groups: Groups,
}

impl Segments {
    fn of(map: &Map) -> Self {
        let starts: Vec<u64> = map
            .segment_starts
            .iter()
            .copied()
            .filter(|s| map.keyframes.contains_key(s))
            .collect();
        let groups = Groups::new(starts.len() + 1);
        let mut s = Self { starts, groups };
        for &(a, b) in &map.loops {
            s.join(a, b);
        }
        s
    }

    /// The segment of keyframe `id`: 0 before the first start, i after the i-th.
    fn segment(&self, id: u64) -> usize {
        self.starts.partition_point(|&s| s <= id)
    }

    fn join(&mut self, a: u64, b: u64) {
        let (a, b) = (self.segment(a), self.segment(b));
        self.groups.join(a, b);
    }

    /// Whether keyframes `a` and `b` lie in one map: one segment, or segments joined by loops.
    fn same_map(&mut self, a: u64, b: u64) -> bool {
        let (a, b) = (self.segment(a), self.segment(b));
        self.groups.find(a) == self.groups.find(b)
    }
}

impl Groups {
    fn new(n: usize) -> Self {
        Self((0..n).collect())
    }

    fn find(&mut self, mut i: usize) -> usize {
        while self.0[i] != i {
            self.0[i] = self.0[self.0[i]];
            i = self.0[i];
        }
        i
    }

    fn join(&mut self, a: usize, b: usize) {
        let (a, b) = (self.find(a), self.find(b));
        let (lo, hi) = (a.min(b), a.max(b));
        self.0[hi] = lo;
    }
}
