//! The map shared by tracking, mapping and loop closing: keyframes and map points in arenas
//! keyed by `u64` ids, with the covisibility graph and the per-frame trajectory.
//!
//! Ordered maps (`BTreeMap`) keep every iteration order independent of hashing, so the
//! synchronous mode gives the same results on every run.

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{Matrix3, Vector3};

use crate::error::Result;
use crate::geometry::Se3;
use crate::matching::{distance, OwnedDescriptor, OwnedDescriptors};

/// A keyframe: a tracked stereo frame kept in the map.
#[derive(Clone, Debug)]
pub struct Keyframe {
    /// Id in [`Map::keyframes`].
    pub id: u64,
    /// Timestamp, nanoseconds.
    pub t_ns: i64,
    /// Pose of the rectified left camera, `world_from_cam`.
    pub world_from_cam: Se3,
    /// Left keypoints (x = column, y = row), rectified pixels.
    pub keypoints: Vec<[f32; 2]>,
    /// Matched right-image column per keypoint, rectified pixels; NaN when unmatched.
    pub u_right: Vec<f32>,
    /// Measurement noise σ per keypoint, pixels (1 for every keypoint with
    /// `[tracking] keypoint_sigma = "unit"`); weighs its observations in bundle adjustment.
    pub sigmas: Vec<f32>,
    /// Centre of the camera pair whose view each keypoint is, in this keyframe's left-camera
    /// axes, metres (zero: the frame cameras; see `tracking::StereoFrame::viewpoints`).
    pub viewpoints: Vec<[f32; 3]>,
    /// Left descriptors, one row per keypoint.
    pub descriptors: OwnedDescriptors,
    /// Map point observed by each keypoint, if any.
    pub points: Vec<Option<u64>>,
    /// Covisibility: keyframe id → number of map points both observe.
    pub covisible: BTreeMap<u64, u32>,
    /// Map points tracked in the frame that became this keyframe (the keyframe criterion's
    /// reference count).
    pub tracked: usize,
}

impl Keyframe {
    /// Camera centre in the world frame, metres.
    pub fn centre(&self) -> Vector3<f64> {
        self.world_from_cam.translation
    }

    /// The `n` most covisible keyframes, heaviest first (ties by id).
    pub fn best_covisible(&self, n: usize) -> Vec<u64> {
        let mut v: Vec<(u64, u32)> = self.covisible.iter().map(|(&k, &w)| (k, w)).collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        v.into_iter().take(n).map(|(k, _)| k).collect()
    }
}

/// A 3-D landmark.
#[derive(Clone, Debug)]
pub struct MapPoint {
    /// Id in [`Map::points`].
    pub id: u64,
    /// Position in the world frame, metres.
    pub position: Vector3<f64>,
    /// Representative descriptor: the one of the observation that created the point; after a
    /// fusion, the observation's descriptor closest (median distance) to the others'.
    pub descriptor: OwnedDescriptor,
    /// Observations: keyframe id → keypoint index in that keyframe.
    pub observations: BTreeMap<u64, u32>,
    /// Mean viewing direction (unit, world frame, from the cameras towards the point).
    pub normal: Vector3<f64>,
    /// The keyframe that created the point (its reference for loop corrections).
    pub first_keyframe: u64,
}

/// One tracked frame of the trajectory, stored relative to its reference keyframe so that
/// keyframe corrections (bundle adjustment, loop closure) carry over to it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameRecord {
    /// Timestamp, nanoseconds.
    pub t_ns: i64,
    /// The reference keyframe.
    pub keyframe: u64,
    /// Pose of the frame in the keyframe's camera frame, `kf_from_cam`.
    pub kf_from_cam: Se3,
    /// Whether the pose is a motion-model prediction without a measurement
    /// ([`super::tracking::predict_only`], [`super::tracking::hold_pose`]); see
    /// [`Map::trajectory_poses`].
    pub predicted: bool,
    /// Whether the pose was held at rest for a quiet frame that could not be tracked
    /// ([`super::tracking::hold_pose`]; `predicted` too). The camera is taken to have stayed
    /// where it stopped: [`Map::trajectory_poses`] keeps the held pose, and the trajectory
    /// smoother weighs the frame like a measured one (`position_cov`: the last measured
    /// frame's) instead of letting its motion prior carry the last speed into the rest.
    pub held: bool,
    /// Covariance of the camera centre as the tracker measured it against the map, m², in
    /// the frame's own camera axes (the translation block of [`crate::solver::PoseResult`]'s
    /// covariance); `None` where no refinement placed the frame (the first frame of a map
    /// segment, predictions). Weighs the frame in the trajectory smoother ([`super::smoothing`]).
    pub position_cov: Option<Matrix3<f64>>,
}

/// Where a fused map point went ([`Map::replaced`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Redirect {
    /// The live point that absorbed the removed one.
    pub target: u64,
    /// [`Map::next_keyframe`] when the point was fused: how old the entry is, in keyframes.
    pub stamp: u64,
}

/// Keyframes, map points, covisibility, loops and the trajectory.
#[derive(Clone, Debug, Default)]
pub struct Map {
    /// Keyframes by id.
    pub keyframes: BTreeMap<u64, Keyframe>,
    /// Map points by id.
    pub points: BTreeMap<u64, MapPoint>,
    /// Next keyframe id to hand out.
    pub next_keyframe: u64,
    /// Next map point id to hand out.
    pub next_point: u64,
    /// Accepted loop closures (query keyframe id, matched keyframe id).
    pub loops: Vec<(u64, u64)>,
    /// Every tracked frame, in order.
    pub trajectory: Vec<FrameRecord>,
    /// Loop corrections applied so far: a bundle adjustment prepared before a correction
    /// discards its result.
    pub corrections: u64,
    /// Points fused into others: removed id → the point that absorbed it. An id held across a
    /// lock release (the tracker's matches, the fusion's proposals) is looked up with
    /// [`Map::resolve`]; not saved. Bounded: entries always name the final point (a fusion of
    /// the absorbing point redirects them), entries whose point was removed are dropped, and
    /// [`Map::prune_replaced`] drops entries older than any id a reader can still hold.
    pub replaced: BTreeMap<u64, Redirect>,
    /// First keyframes of map segments not yet joined to the segment before them: tracking
    /// started a new segment there at a guessed pose ([`super::tracking::reinitialise`]), so
    /// the relative pose to the keyframe before it is no measurement. Loop closing leaves the
    /// odometry edge across such a boundary out of the pose graph and removes the entry once
    /// a loop joins the two segments. The first keyframe of the map is implicit.
    pub segment_starts: BTreeSet<u64>,
}

impl Map {
    /// World pose of a trajectory record; `None` if its keyframe is gone.
    pub fn frame_pose(&self, record: &FrameRecord) -> Option<Se3> {
        self.keyframes
            .get(&record.keyframe)
            .map(|kf| kf.world_from_cam * record.kf_from_cam)
    }

    /// [`Map::trajectory_poses`] with the camera centres of each map segment re-estimated by
    /// the trajectory smoother ([`super::smoothing`], acceleration-noise density `q`, m²/s³):
    /// each measured frame weighted by its [`FrameRecord::position_cov`] (a measured frame
    /// without one, such as a segment's first, by the segment's median covariance, and so is
    /// a frame held at rest), predicted frames placed by the motion prior. Orientations are those of `trajectory_poses`.
    pub fn smoothed_trajectory_poses(&self, q: f64) -> Result<Vec<(i64, Se3)>> {
        let records: Vec<&FrameRecord> = self
            .trajectory
            .iter()
            .filter(|r| self.keyframes.contains_key(&r.keyframe))
            .collect();
        let mut poses = self.trajectory_poses();
        let mut start = 0;
        while start < poses.len() {
            let segment = self.segment_of(records[start].keyframe);
            let end = (start..poses.len())
                .find(|&j| self.segment_of(records[j].keyframe) != segment)
                .unwrap_or(poses.len());
            self.smooth_segment(&records[start..end], &mut poses[start..end], q)?;
            start = end;
        }
        Ok(poses)
    }

    /// Smooths the centres of one segment's `poses` (with their `records`) in place.
    fn smooth_segment(
        &self,
        records: &[&FrameRecord],
        poses: &mut [(i64, Se3)],
        q: f64,
    ) -> Result<()> {
        let mut measured: Vec<Matrix3<f64>> =
            records.iter().filter_map(|r| r.position_cov).collect();
        if measured.len() < 2 {
            return Ok(());
        }
        measured.sort_by(|a, b| a.trace().total_cmp(&b.trace()));
        let fallback = measured[measured.len() / 2];
        // Frames sharing a timestamp (a bridge keyframe) are one sample; each keeps its own
        // offset from the first of them.
        let mut samples: Vec<super::smoothing::CentreSample> = Vec::with_capacity(poses.len());
        let mut sample_of = Vec::with_capacity(poses.len());
        for (r, (t_ns, pose)) in records.iter().zip(poses.iter()) {
            let t_s = *t_ns as f64 * 1e-9;
            if samples.last().is_some_and(|s| s.t_s >= t_s) {
                sample_of.push(samples.len() - 1);
                continue;
            }
            let information = if r.predicted && !r.held {
                None
            } else {
                // Σ_c = R Σ_ρ Rᵀ with R the camera's orientation in the world.
                let rot = pose.rotation.matrix();
                let cov = rot * r.position_cov.unwrap_or(fallback) * rot.transpose();
                cov.try_inverse()
                    .filter(|m| m.iter().all(|x| x.is_finite()))
            };
            sample_of.push(samples.len());
            samples.push(super::smoothing::CentreSample {
                t_s,
                centre: pose.translation,
                information,
            });
        }
        let smoothed = super::smoothing::smooth_centres(&samples, q)?;
        for ((_, pose), &k) in poses.iter_mut().zip(&sample_of) {
            pose.translation += smoothed[k] - samples[k].centre;
        }
        Ok(())
    }

    /// `(t_ns, world_from_cam)` of every trajectory record whose keyframe still exists, in
    /// order. A run of predicted records between two measured ones (frames whose images
    /// carried no measurement, e.g. an illumination flood) is placed on the geodesic between
    /// those two measured poses, by time: once the frame after the run is measured, the
    /// interpolation uses both sides, where the prediction made while tracking extrapolated
    /// from one. A predicted run with no measured record after it keeps its predictions.
    /// Frames held at rest ([`FrameRecord::held`]) keep their pose and bound a run like
    /// measured ones.
    pub fn trajectory_poses(&self) -> Vec<(i64, Se3)> {
        let poses: Vec<(&FrameRecord, Se3)> = self
            .trajectory
            .iter()
            .filter_map(|r| self.frame_pose(r).map(|p| (r, p)))
            .collect();
        let mut out: Vec<(i64, Se3)> = poses.iter().map(|(r, p)| (r.t_ns, *p)).collect();
        // Held frames keep their pose (the camera taken to be at rest): they end a run.
        let anchor = |r: &FrameRecord| !r.predicted || r.held;
        let mut i = 0;
        while i < poses.len() {
            if anchor(poses[i].0) {
                i += 1;
                continue;
            }
            let end = (i..poses.len())
                .find(|&j| anchor(poses[j].0))
                .unwrap_or(poses.len());
            if i > 0 && end < poses.len() {
                let (a, pose_a) = poses[i - 1];
                let (b, pose_b) = poses[end];
                let span = (b.t_ns - a.t_ns) as f64;
                if span > 0.0 {
                    for (k, slot) in out.iter_mut().enumerate().take(end).skip(i) {
                        let s = (poses[k].0.t_ns - a.t_ns) as f64 / span;
                        slot.1 = pose_a.interpolate(&pose_b, s);
                    }
                }
            }
            i = end;
        }
        out
    }

    /// The id a point lives on under: `point` itself, or the point it was fused into (entries
    /// always name the final point, see [`Map::merge_points`], so one look-up suffices).
    pub fn resolve(&self, point: u64) -> u64 {
        self.replaced.get(&point).map_or(point, |r| r.target)
    }

    /// Drops the [`Map::replaced`] entries of fusions made before the last `horizon`
    /// keyframes were inserted. A reader holds point ids across a lock release for one
    /// tracking or mapping step at most, during which at most the mapping queue's length plus
    /// two keyframes can be inserted; an id older than that is held by nobody.
    pub fn prune_replaced(&mut self, horizon: u64) {
        let oldest = self.next_keyframe.saturating_sub(horizon);
        self.replaced.retain(|_, r| r.stamp >= oldest);
    }

    /// Adds the observation (keyframe, keypoint) → point and updates covisibility; a point
    /// fused into another (see [`Map::resolve`]) is replaced by that one. Does nothing if the
    /// keyframe or point is missing or the point is already observed by this keyframe.
    pub fn add_observation(&mut self, kf: u64, feature: usize, point: u64) {
        let point = self.resolve(point);
        let Some(p) = self.points.get_mut(&point) else {
            return;
        };
        if p.observations.contains_key(&kf) || !self.keyframes.contains_key(&kf) {
            return;
        }
        let others: Vec<u64> = p.observations.keys().copied().collect();
        p.observations.insert(kf, feature as u32);
        for o in others {
            if let Some(k) = self.keyframes.get_mut(&o) {
                *k.covisible.entry(kf).or_insert(0) += 1;
            }
            if let Some(k) = self.keyframes.get_mut(&kf) {
                *k.covisible.entry(o).or_insert(0) += 1;
            }
        }
        if let Some(k) = self.keyframes.get_mut(&kf) {
            if let Some(slot) = k.points.get_mut(feature) {
                *slot = Some(point);
            }
        }
        self.update_normal(point);
    }

    /// Removes the observation of `point` by `kf` and updates covisibility.
    pub fn remove_observation(&mut self, kf: u64, point: u64) {
        let Some(p) = self.points.get_mut(&point) else {
            return;
        };
        let Some(feature) = p.observations.remove(&kf) else {
            return;
        };
        let others: Vec<u64> = p.observations.keys().copied().collect();
        for o in others {
            decrement(self.keyframes.get_mut(&o), kf);
            decrement(self.keyframes.get_mut(&kf), o);
        }
        if let Some(k) = self.keyframes.get_mut(&kf) {
            if let Some(slot) = k.points.get_mut(feature as usize) {
                *slot = None;
            }
        }
    }

    /// Removes a map point with all its observations.
    pub fn remove_point(&mut self, point: u64) {
        let observers: Vec<u64> = match self.points.get(&point) {
            Some(p) => p.observations.keys().copied().collect(),
            None => return,
        };
        for kf in observers {
            self.remove_observation(kf, point);
        }
        self.points.remove(&point);
        // Ids fused into it now resolve to a missing point, like the id itself would.
        self.replaced.retain(|_, r| r.target != point);
    }

    /// Fuses point `drop` into point `keep` (two estimates of one landmark): `drop`'s
    /// observations move to `keep` (a keyframe observing both keeps its observation of
    /// `keep`), `drop` is removed and recorded in [`Map::replaced`], and `keep`'s normal and
    /// representative descriptor are recomputed. `keep`'s position stays. Returns `false`
    /// (and changes nothing) when either point is missing or they are the same.
    pub fn merge_points(&mut self, keep: u64, drop: u64) -> bool {
        if keep == drop || !self.points.contains_key(&keep) {
            return false;
        }
        let Some(d) = self.points.get(&drop) else {
            return false;
        };
        let moved: Vec<(u64, u32)> = d.observations.iter().map(|(&k, &f)| (k, f)).collect();
        for (kf, feature) in moved {
            self.remove_observation(kf, drop);
            self.add_observation(kf, feature as usize, keep);
        }
        self.points.remove(&drop);
        // Path compression: whatever resolved to `drop` now resolves to `keep` directly.
        let stamp = self.next_keyframe;
        for r in self.replaced.values_mut().filter(|r| r.target == drop) {
            r.target = keep;
        }
        self.replaced.insert(
            drop,
            Redirect {
                target: keep,
                stamp,
            },
        );
        self.update_descriptor(keep);
        self.update_normal(keep);
        true
    }

    /// Sets a point's representative descriptor to the observation descriptor with the
    /// smallest median distance to the other observations' descriptors.
    pub fn update_descriptor(&mut self, point: u64) {
        let Some(p) = self.points.get(&point) else {
            return;
        };
        let rows: Vec<_> = p
            .observations
            .iter()
            .filter_map(|(kf, &f)| {
                let k = self.keyframes.get(kf)?;
                ((f as usize) < k.descriptors.len()).then(|| k.descriptors.view().row(f as usize))
            })
            .collect();
        if rows.len() < 2 {
            return;
        }
        let mut best: Option<(f32, usize)> = None;
        for (i, a) in rows.iter().enumerate() {
            let mut d: Vec<f32> = rows
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, b)| distance(*a, *b))
                .collect();
            d.sort_by(f32::total_cmp);
            let median = d[d.len() / 2];
            if best.is_none_or(|(m, _)| median < m) {
                best = Some((median, i));
            }
        }
        if let Some((_, i)) = best {
            let descriptor = rows[i].to_owned();
            if let Some(p) = self.points.get_mut(&point) {
                p.descriptor = descriptor;
            }
        }
    }

    /// Recomputes a point's mean viewing direction from its observers' centres.
    pub fn update_normal(&mut self, point: u64) {
        let Some(p) = self.points.get(&point) else {
            return;
        };
        let mut sum = Vector3::zeros();
        for kf in p.observations.keys() {
            if let Some(k) = self.keyframes.get(kf) {
                let d = p.position - k.centre();
                let n = d.norm();
                if n > 0.0 {
                    sum += d / n;
                }
            }
        }
        let n = sum.norm();
        if n > 0.0 {
            if let Some(p) = self.points.get_mut(&point) {
                p.normal = sum / n;
            }
        }
    }

    /// Map points observed by the given keyframes, ascending ids, no repeats.
    pub fn points_of(&self, keyframes: &[u64]) -> Vec<u64> {
        let mut ids: Vec<u64> = keyframes
            .iter()
            .filter_map(|k| self.keyframes.get(k))
            .flat_map(|k| k.points.iter().flatten().copied())
            .filter(|p| self.points.contains_key(p))
            .collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    }
}

// --- keyframe culling and map checks (issue 10) ---
impl Map {
    /// The map segment of keyframe `kf`: the first keyframe of its segment (the largest
    /// [`Map::segment_starts`] entry not after it, or the map's first keyframe).
    pub fn segment_of(&self, kf: u64) -> u64 {
        match self.segment_starts.range(..=kf).next_back() {
            Some(&s) => s,
            None => self.keyframes.keys().next().copied().unwrap_or(0),
        }
    }

    /// Removes keyframe `kf` as redundant and keeps everything that referred to it valid:
    /// its observations are removed (points left without any observer are removed too,
    /// points it created take their oldest remaining observer as reference), trajectory
    /// records stored relative to it are re-expressed relative to `substitute` (their world
    /// poses do not change), and covisibility is updated. Returns `false` (and changes
    /// nothing) when `kf` or `substitute` is missing or they are the same. The caller keeps
    /// the place database in step and never culls the keyframes the tracker refers to, loop
    /// keyframes or segment starts (see `mapping::cull_keyframes`).
    pub fn cull_keyframe(&mut self, kf: u64, substitute: u64) -> bool {
        if kf == substitute || !self.keyframes.contains_key(&substitute) {
            return false;
        }
        let Some(k) = self.keyframes.get(&kf) else {
            return false;
        };
        let world_from_kf = k.world_from_cam;
        let points: Vec<u64> = k.points.iter().flatten().copied().collect();
        let substitute_from_world = self.keyframes[&substitute].world_from_cam.inverse();
        let substitute_from_kf = substitute_from_world * world_from_kf;
        for r in self.trajectory.iter_mut().filter(|r| r.keyframe == kf) {
            r.keyframe = substitute;
            r.kf_from_cam = substitute_from_kf * r.kf_from_cam;
        }
        for p in points {
            self.remove_observation(kf, p);
            let Some(point) = self.points.get_mut(&p) else {
                continue;
            };
            match point.observations.keys().next().copied() {
                None => {
                    self.points.remove(&p);
                    self.replaced.retain(|_, r| r.target != p);
                }
                Some(oldest) => {
                    if point.first_keyframe == kf {
                        point.first_keyframe = oldest;
                    }
                    self.update_normal(p);
                }
            }
        }
        // Covisibility entries vanish with the last shared observation; drop any leftover.
        for other in self.keyframes.values_mut() {
            other.covisible.remove(&kf);
        }
        self.keyframes.remove(&kf);
        self.rereference_points(kf);
        true
    }

    /// Points whose reference keyframe is `kf` (removed, or about to be) take their oldest
    /// remaining observer instead. This covers the points `kf` created but no longer observes
    /// (its observation dropped as an outlier or moved by a fusion), which the loop over
    /// `kf`'s own observations does not reach.
    pub(crate) fn rereference_points(&mut self, kf: u64) {
        for p in self.points.values_mut() {
            if p.first_keyframe == kf {
                if let Some(&oldest) = p.observations.keys().next() {
                    p.first_keyframe = oldest;
                }
            }
        }
    }

    /// Checks the map's internal consistency and returns every violation found (empty when
    /// consistent): observations and keypoint slots agree both ways and point at existing
    /// keyframes, points and keypoints; covisibility weights equal the number of shared
    /// points, symmetric, with no zero or dangling entries; each point has an observer and an
    /// existing reference keyframe; trajectory records, loops and segment starts refer to
    /// existing keyframes; ids are below the id counters; fused-point redirects lead from a
    /// removed point straight to a live one. Used by tests.
    pub fn check_invariants(&self) -> Vec<String> {
        let mut errors = Vec::new();
        let mut shared: BTreeMap<(u64, u64), u32> = BTreeMap::new();
        for (&id, p) in &self.points {
            if p.id != id || id >= self.next_point {
                errors.push(format!(
                    "point {id}: id field {} / counter {}",
                    p.id, self.next_point
                ));
            }
            if p.observations.is_empty() {
                errors.push(format!("point {id}: no observations"));
            }
            if !self.keyframes.contains_key(&p.first_keyframe) {
                errors.push(format!(
                    "point {id}: reference keyframe {} missing",
                    p.first_keyframe
                ));
            }
            for (&kf, &f) in &p.observations {
                match self.keyframes.get(&kf) {
                    None => errors.push(format!("point {id}: observed by missing keyframe {kf}")),
                    Some(k) if k.points.get(f as usize).copied().flatten() != Some(id) => errors
                        .push(format!(
                            "point {id}: keyframe {kf} keypoint {f} does not hold it"
                        )),
                    Some(_) => {}
                }
            }
            let observers: Vec<u64> = p.observations.keys().copied().collect();
            for (i, &a) in observers.iter().enumerate() {
                for &b in &observers[i + 1..] {
                    *shared.entry((a, b)).or_insert(0) += 1;
                    *shared.entry((b, a)).or_insert(0) += 1;
                }
            }
        }
        for (&id, k) in &self.keyframes {
            if k.id != id || id >= self.next_keyframe {
                errors.push(format!(
                    "keyframe {id}: id field {} / counter {}",
                    k.id, self.next_keyframe
                ));
            }
            if k.points.len() != k.keypoints.len() || k.u_right.len() != k.keypoints.len() {
                errors.push(format!(
                    "keyframe {id}: per-keypoint arrays differ in length"
                ));
            }
            for (f, p) in k.points.iter().enumerate() {
                let Some(p) = p else { continue };
                match self.points.get(p) {
                    None => errors.push(format!(
                        "keyframe {id}: keypoint {f} holds missing point {p}"
                    )),
                    Some(q) if q.observations.get(&id) != Some(&(f as u32)) => {
                        errors.push(format!(
                            "keyframe {id}: keypoint {f} holds point {p}, which does not list it"
                        ))
                    }
                    Some(_) => {}
                }
            }
            for (&o, &w) in &k.covisible {
                let expected = shared.get(&(id, o)).copied().unwrap_or(0);
                if w != expected || o == id {
                    errors.push(format!(
                        "keyframe {id}: covisibility with {o} is {w}, {expected} shared points"
                    ));
                }
            }
        }
        for (&(a, b), &w) in &shared {
            if self
                .keyframes
                .get(&a)
                .is_some_and(|k| !k.covisible.contains_key(&b))
            {
                errors.push(format!(
                    "keyframe {a}: covisibility with {b} ({w} shared points) missing"
                ));
            }
        }
        for (i, r) in self.trajectory.iter().enumerate() {
            if !self.keyframes.contains_key(&r.keyframe) {
                errors.push(format!(
                    "trajectory record {i}: keyframe {} missing",
                    r.keyframe
                ));
            }
        }
        for (a, b) in &self.loops {
            if !self.keyframes.contains_key(a) || !self.keyframes.contains_key(b) {
                errors.push(format!("loop ({a}, {b}): a keyframe is missing"));
            }
        }
        for s in &self.segment_starts {
            if !self.keyframes.contains_key(s) {
                errors.push(format!("segment start {s}: keyframe missing"));
            }
        }
        for (from, r) in &self.replaced {
            if self.points.contains_key(from) || !self.points.contains_key(&r.target) {
                errors.push(format!(
                    "fused point {from} → {}: the source is live or the target is gone",
                    r.target
                ));
            }
        }
        errors
    }
}
// --- end keyframe culling and map checks ---

fn decrement(kf: Option<&mut Keyframe>, other: u64) {
    if let Some(k) = kf {
        if let Some(w) = k.covisible.get_mut(&other) {
            *w -= 1;
            if *w == 0 {
                k.covisible.remove(&other);
            }
        }
    }
}
