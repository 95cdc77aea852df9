//! Tracking: rectified stereo matching of a frame, projection-guided matching against the
//! local map, motion-only refinement, the keyframe decision and keyframe creation.

use std::collections::BTreeMap;

use nalgebra::{Matrix3, Vector2, Vector3};
use rayon::prelude::*;

use super::map::{FrameRecord, Keyframe, Map, MapPoint};
use super::{StereoCalibration, TrackState};
use crate::config::{TrackingConfig, TriangulationConfig};
use crate::geometry::{triangulate_rectified, Se3};
use crate::matching::{best_two, DescriptorKind, Descriptors, MatchOptions, OwnedDescriptors};
use crate::solver::{refine_pose_seen_from, LmOptions, Loss, PoseObservation, PoseOptions};

/// A frame's left features with their stereo matches.
pub struct StereoFrame<'a> {
    /// Timestamp, nanoseconds.
    pub t_ns: i64,
    /// Left keypoints (x, y), rectified pixels.
    pub keypoints: Vec<[f32; 2]>,
    /// Right column of each left keypoint's stereo match; NaN when unmatched.
    pub u_right: Vec<f32>,
    /// Measurement noise σ of each left keypoint, pixels (finite, positive); its stereo
    /// match shares it.
    pub sigmas: Vec<f32>,
    /// Centre of the camera pair whose view each keypoint is, in the rectified left frame
    /// camera's axes, metres: zero for the frame cameras' own images, the event cameras'
    /// centre for event images warped into the frame cameras through the plane at infinity
    /// (`[fusion] event_viewpoint`). Tracking, new points and bundle adjustment model the
    /// keypoint from there.
    pub viewpoints: Vec<[f32; 3]>,
    /// Left descriptors.
    pub descriptors: Descriptors<'a>,
    /// The images are the fusion's DVS-biased rendering: the keyframe floor is `[tracking]
    /// dvs_keyframe_min_tracked` instead of `keyframe_min_tracked`.
    pub dvs_biased: bool,
    /// The event window is quiet (`[fusion] quiet_ratio`: few events against the usual
    /// count, so the camera is likely at rest and the event images show sensor noise): when
    /// the frame cannot be tracked its pose is held ([`hold_pose`]) instead of relocalised or
    /// started as a new map segment.
    pub quiet: bool,
}

/// The least number of tracked points under which `frame` becomes a keyframe whatever its
/// reference keyframe tracked: `[tracking] dvs_keyframe_min_tracked` for the fusion's
/// DVS-biased images, `keyframe_min_tracked` otherwise.
pub fn keyframe_floor(cfg: &TrackingConfig, frame: &StereoFrame) -> u32 {
    if frame.dvs_biased {
        cfg.dvs_keyframe_min_tracked
    } else {
        cfg.keyframe_min_tracked
    }
}

/// The descriptor thresholds of the configuration for a descriptor kind.
pub fn match_options(cfg: &TrackingConfig, kind: DescriptorKind) -> MatchOptions {
    let mut o = MatchOptions::for_kind(kind);
    if cfg.max_descriptor_distance > 0.0 {
        o.max_distance = cfg.max_descriptor_distance as f32;
    }
    o.ratio = cfg.ratio as f32;
    o
}

/// Matches left to right keypoints of a rectified pair: same row within
/// `cfg.stereo_row_px`, disparity in the range of the triangulation depth limits, then
/// the descriptor distance and ratio tests. Returns the right column per left keypoint
/// (NaN when unmatched).
pub fn stereo_match(
    calib: &StereoCalibration,
    cfg: &TrackingConfig,
    tri: &TriangulationConfig,
    left_xy: &[[f32; 2]],
    left: Descriptors,
    right_xy: &[[f32; 2]],
    right: Descriptors,
) -> Vec<f32> {
    let options = match_options(cfg, left.kind());
    let band = cfg.stereo_row_px as f32;
    let focal_baseline = calib.fx * calib.baseline_m;
    let d_min = (focal_baseline / tri.max_depth_m) as f32;
    let d_max = (focal_baseline / tri.min_depth_m.max(1e-6)) as f32;
    // Right keypoints bucketed by integer row.
    let rows = calib.height as usize + 1;
    let mut by_row: Vec<Vec<u32>> = vec![Vec::new(); rows];
    for (j, p) in right_xy.iter().enumerate() {
        if p[1].is_finite() && p[1] >= 0.0 && (p[1] as usize) < rows {
            by_row[p[1] as usize].push(j as u32);
        }
    }
    left_xy
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let (x, y) = (p[0], p[1]);
            let lo = (y - band).floor().max(0.0) as usize;
            let hi = ((y + band).floor().max(0.0) as usize).min(rows - 1);
            if lo > hi {
                return f32::NAN;
            }
            let candidates = (lo..=hi).flat_map(|r| by_row[r].iter()).filter_map(|&j| {
                let q = right_xy[j as usize];
                let d = x - q[0];
                ((q[1] - y).abs() <= band && d >= d_min && d <= d_max).then_some(j as usize)
            });
            match best_two(left.row(i), right, candidates) {
                Some((j, best, second))
                    if best <= options.max_distance && best < options.ratio * second =>
                {
                    right_xy[j][0]
                }
                _ => f32::NAN,
            }
        })
        .collect()
}

/// Keypoint indices in square cells, for lookups around a pixel.
pub struct Grid {
    cell: f32,
    cols: usize,
    rows: usize,
    cells: Vec<Vec<u32>>,
}

impl Grid {
    /// Bins the keypoints of an image of `width` × `height` pixels.
    pub fn new(keypoints: &[[f32; 2]], width: u32, height: u32, cell: f32) -> Self {
        let cols = (width as f32 / cell).ceil().max(1.0) as usize;
        let rows = (height as f32 / cell).ceil().max(1.0) as usize;
        let mut cells = vec![Vec::new(); cols * rows];
        for (i, p) in keypoints.iter().enumerate() {
            if let Some(c) = Self::index(cell, cols, rows, p[0], p[1]) {
                cells[c].push(i as u32);
            }
        }
        Self {
            cell,
            cols,
            rows,
            cells,
        }
    }

    fn index(cell: f32, cols: usize, rows: usize, x: f32, y: f32) -> Option<usize> {
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        let (c, r) = ((x / cell) as usize, (y / cell) as usize);
        (c < cols && r < rows).then_some(r * cols + c)
    }

    /// Keypoints within `radius` pixels of (x, y).
    pub fn near<'g>(
        &'g self,
        keypoints: &'g [[f32; 2]],
        x: f32,
        y: f32,
        radius: f32,
    ) -> impl Iterator<Item = usize> + 'g {
        let c0 = ((x - radius) / self.cell).floor().max(0.0) as usize;
        let c1 = (((x + radius) / self.cell).floor().max(0.0) as usize).min(self.cols - 1);
        let r0 = ((y - radius) / self.cell).floor().max(0.0) as usize;
        let r1 = (((y + radius) / self.cell).floor().max(0.0) as usize).min(self.rows - 1);
        let r2 = radius * radius;
        (r0..=r1)
            .flat_map(move |r| (c0..=c1).map(move |c| r * self.cols + c))
            .flat_map(move |c| self.cells[c].iter())
            .map(|&i| i as usize)
            .filter(move |&i| {
                let p = keypoints[i];
                (p[0] - x).powi(2) + (p[1] - y).powi(2) <= r2
            })
    }
}

/// Projection of map points into one rectified stereo view for a guided search: the view's
/// pose, the frustum (image bounds, depth range of `[triangulation]`), the viewing-angle limit
/// and the descriptor thresholds of `[tracking]`, and the search radius in pixels.
pub(crate) struct Projection<'a> {
    calib: &'a StereoCalibration,
    tri: &'a TriangulationConfig,
    rotation: Matrix3<f64>,
    translation: Vector3<f64>,
    centre: Vector3<f64>,
    /// Centre of the camera pair whose view the keypoints are, in the view's axes.
    viewpoint: Vector3<f64>,
    cos_max: f64,
    options: MatchOptions,
    radius: f32,
}

impl<'a> Projection<'a> {
    /// The projection into a view at `cam_from_world` whose descriptors are of `kind`.
    pub(crate) fn new(
        cam_from_world: &Se3,
        calib: &'a StereoCalibration,
        cfg: &TrackingConfig,
        tri: &'a TriangulationConfig,
        kind: DescriptorKind,
        radius: f32,
    ) -> Self {
        Self {
            calib,
            tri,
            rotation: cam_from_world.rotation.matrix(),
            translation: cam_from_world.translation,
            centre: cam_from_world.inverse().translation,
            viewpoint: Vector3::zeros(),
            cos_max: cfg.max_view_angle_deg.to_radians().cos(),
            options: match_options(cfg, kind),
            radius,
        }
    }

    /// The same projection for keypoints seen from `viewpoint` (the view's axes, metres; see
    /// `StereoFrame::viewpoints`).
    pub(crate) fn seen_from(mut self, viewpoint: Vector3<f64>) -> Self {
        self.viewpoint = viewpoint;
        self
    }

    /// The keypoint (index, descriptor distance) that point `p` matches in the view
    /// (`keypoints`, their right-image columns `u_right` (NaN: no stereo match), `descriptors`,
    /// `grid` over the keypoints): `p` must project inside the frustum and be seen within the
    /// viewing-angle limit of its normal; candidates lie within the radius of the projection
    /// (and of the predicted right column where they have one); the best must pass the
    /// distance threshold and the ratio test against the second best.
    pub(crate) fn best_match(
        &self,
        p: &MapPoint,
        keypoints: &[[f32; 2]],
        u_right: &[f32],
        descriptors: Descriptors<'_>,
        grid: &Grid,
    ) -> Option<(usize, f32)> {
        let (calib, radius) = (self.calib, self.radius);
        let pc = self.rotation * p.position + self.translation - self.viewpoint;
        if pc.z < self.tri.min_depth_m || pc.z > self.tri.max_depth_m {
            return None;
        }
        let u = calib.fx * pc.x / pc.z + calib.cx;
        let v = calib.fy * pc.y / pc.z + calib.cy;
        if !(u >= 0.0 && v >= 0.0 && u < calib.width as f64 && v < calib.height as f64) {
            return None;
        }
        let ray = p.position - self.centre;
        if ray.dot(&p.normal) < self.cos_max * ray.norm() {
            return None;
        }
        let ur = (u - calib.fx * calib.baseline_m / pc.z) as f32;
        let (u, v) = (u as f32, v as f32);
        let candidates = grid.near(keypoints, u, v, radius).filter(|&i| {
            let m = u_right[i];
            !m.is_finite() || (m - ur).abs() <= radius
        });
        let (i, best, second) = best_two(p.descriptor.view(), descriptors, candidates)?;
        (best <= self.options.max_distance && best < self.options.ratio * second)
            .then_some((i, best))
    }
}

/// Projection-guided search: every candidate map point projected with `cam_from_world`
/// (frustum and viewing-angle culled) is matched to the nearest-in-descriptor keypoint within
/// `radius`; each keypoint keeps its best point. Returns per keypoint (point id, distance).
#[allow(clippy::too_many_arguments)]
pub fn search_projected(
    map: &Map,
    points: &[u64],
    frame: &StereoFrame,
    grid: &Grid,
    calib: &StereoCalibration,
    cfg: &TrackingConfig,
    tri: &TriangulationConfig,
    cam_from_world: &Se3,
    radius: f32,
) -> Vec<Option<(u64, f32)>> {
    let projection = Projection::new(
        cam_from_world,
        calib,
        cfg,
        tri,
        frame.descriptors.kind(),
        radius,
    )
    // A tracked frame is one image: its keypoints share one viewpoint.
    .seen_from(
        frame
            .viewpoints
            .first()
            .map_or(Vector3::zeros(), |c| c.map(f64::from).into()),
    );
    let found: Vec<Option<(usize, u64, f32)>> = points
        .par_iter()
        .map(|&id| {
            let p = map.points.get(&id)?;
            let (i, d) = projection.best_match(
                p,
                &frame.keypoints,
                &frame.u_right,
                frame.descriptors,
                grid,
            )?;
            Some((i, id, d))
        })
        .collect();
    let mut per_feature: Vec<Option<(u64, f32)>> = vec![None; frame.keypoints.len()];
    for (i, id, d) in found.into_iter().flatten() {
        match per_feature[i] {
            Some((_, old)) if old <= d => {}
            _ => per_feature[i] = Some((id, d)),
        }
    }
    per_feature
}

/// The tracker's state between frames.
#[derive(Clone, Debug)]
pub struct TrackerState {
    /// The last tracked frame relative to its keyframe.
    pub last: Option<FrameRecord>,
    /// Constant-velocity model: `cam_from_world(k) · world_from_cam(k−1)`.
    pub velocity: Se3,
    /// The reference keyframe (the newest keyframe).
    pub reference: Option<u64>,
    /// Whether the last frame was lost.
    pub lost: bool,
    /// The last frame whose pose was measured (tracked, bootstrapped, re-initialised or
    /// bridged); `last` differs from it after frames moved on by [`predict_only`].
    pub measured: Option<FrameRecord>,
    /// Whether `velocity` is a relocalised frame's step (`[tracking] relocalised_velocity`)
    /// rather than the motion between two tracked frames.
    pub velocity_relocalised: bool,
    /// Whether the last frame started a new map segment (`reinitialise`) and no frame has
    /// been tracked or relocalised since: its pose was the motion model's extrapolation.
    pub fresh_segment: bool,
    /// Whether the last frame's pose was held at rest ([`hold_pose`]) and no frame has been
    /// tracked since: a prediction from it keeps the camera at rest.
    pub at_rest: bool,
}

impl Default for TrackerState {
    fn default() -> Self {
        Self {
            last: None,
            velocity: Se3::identity(),
            reference: None,
            lost: false,
            measured: None,
            velocity_relocalised: false,
            fresh_segment: false,
            at_rest: false,
        }
    }
}

/// The outcome of matching and refining one frame against the local map.
pub struct Tracked {
    /// Refined `cam_from_world`.
    pub cam_from_world: Se3,
    /// Inlier map point per keypoint.
    pub matches: Vec<Option<u64>>,
    /// Number of inliers.
    pub inliers: usize,
    /// Covariance of the last refinement ([`crate::solver::PoseResult::covariance`]).
    pub covariance: Option<nalgebra::Matrix6<f64>>,
}

/// Pose observations with their σ, viewpoints and keypoint indices.
type Observations = (
    Vec<PoseObservation>,
    Vec<f64>,
    Vec<Vector3<f64>>,
    Vec<usize>,
);

/// Observations for refinement from keypoint → point matches.
fn observations(map: &Map, frame: &StereoFrame, matches: &[Option<u64>]) -> Observations {
    let mut obs = Vec::new();
    let mut sigmas = Vec::new();
    let mut viewpoints = Vec::new();
    let mut which = Vec::new();
    for (i, m) in matches.iter().enumerate() {
        let Some(p) = m.and_then(|id| map.points.get(&id)) else {
            continue;
        };
        let kp = frame.keypoints[i];
        let pixel = Vector2::new(kp[0] as f64, kp[1] as f64);
        let ur = frame.u_right[i];
        obs.push(if ur.is_finite() {
            PoseObservation::Stereo {
                point: p.position,
                pixel,
                u_right: ur as f64,
            }
        } else {
            PoseObservation::Mono {
                point: p.position,
                pixel,
            }
        });
        sigmas.push(frame.sigmas[i] as f64);
        viewpoints.push(frame.viewpoints[i].map(f64::from).into());
        which.push(i);
    }
    (obs, sigmas, viewpoints, which)
}

/// Options of the motion-only refinement.
pub fn pose_options(cfg: &TrackingConfig, tri: &TriangulationConfig) -> PoseOptions {
    PoseOptions {
        loss: Loss::Huber(cfg.huber_px),
        min_depth: tri.min_depth_m.max(1e-6),
        outlier_threshold_sq: cfg.huber_px * cfg.huber_px,
        lm: LmOptions {
            max_iterations: cfg.refine_iterations as usize,
            ..Default::default()
        },
    }
}

/// Refines a pose from matches twice, dropping the first pass's outliers.
pub fn refine_matches(
    map: &Map,
    frame: &StereoFrame,
    mut matches: Vec<Option<u64>>,
    predicted: Se3,
    calib: &StereoCalibration,
    options: &PoseOptions,
) -> Option<Tracked> {
    let k = calib.intrinsics();
    let mut pose = predicted;
    let mut covariance = None;
    for _ in 0..2 {
        let (obs, sigmas, viewpoints, which) = observations(map, frame, &matches);
        if obs.len() < 6 {
            return None;
        }
        let r = refine_pose_seen_from(pose, &k, &obs, &sigmas, &viewpoints, options);
        let r = match r {
            Ok(r) => r,
            Err(e) => {
                log::debug!("tracking: refinement failed: {e}");
                return None;
            }
        };
        pose = r.cam_from_world;
        covariance = r.covariance;
        for (k, &i) in which.iter().enumerate() {
            if !r.inliers[k] {
                matches[i] = None;
            }
        }
    }
    let inliers = matches.iter().flatten().count();
    Some(Tracked {
        cam_from_world: pose,
        matches,
        inliers,
        covariance,
    })
}

/// Inserts a keyframe for `frame` at `world_from_cam`: keypoints matched to map points
/// (`matches`) become observations, unmatched stereo keypoints that triangulate within the
/// limits become new map points. Returns the keyframe id and its number of map points.
pub fn insert_keyframe(
    map: &mut Map,
    frame: &StereoFrame,
    world_from_cam: Se3,
    matches: &[Option<u64>],
    calib: &StereoCalibration,
    tri: &TriangulationConfig,
) -> (u64, usize) {
    let id = map.next_keyframe;
    map.next_keyframe += 1;
    let n = frame.keypoints.len();
    map.keyframes.insert(
        id,
        Keyframe {
            id,
            t_ns: frame.t_ns,
            world_from_cam,
            keypoints: frame.keypoints.clone(),
            u_right: frame.u_right.clone(),
            sigmas: frame.sigmas.clone(),
            viewpoints: frame.viewpoints.clone(),
            descriptors: frame.descriptors.to_owned(),
            points: vec![None; n],
            covisible: BTreeMap::new(),
            tracked: 0,
        },
    );
    let pinhole = calib.pinhole();
    let centre = world_from_cam.translation;
    for i in 0..n {
        if let Some(Some(p)) = matches.get(i) {
            map.add_observation(id, i, *p);
            continue;
        }
        let ur = frame.u_right[i];
        if !ur.is_finite() {
            continue;
        }
        let kp = frame.keypoints[i];
        let uv = Vector2::new(kp[0] as f64, kp[1] as f64);
        let Ok(t) = triangulate_rectified(&pinhole, calib.baseline_m, &uv, ur as f64, tri) else {
            continue;
        };
        // The pair measured the point from its viewpoint, with the keyframe's orientation.
        let viewpoint: Vector3<f64> = frame.viewpoints[i].map(f64::from).into();
        let position = world_from_cam.transform_point(&(t.point_world + viewpoint));
        let pid = map.next_point;
        map.next_point += 1;
        let normal = (position - centre)
            .try_normalize(0.0)
            .unwrap_or(Vector3::z());
        map.points.insert(
            pid,
            MapPoint {
                id: pid,
                position,
                descriptor: frame.descriptors.row(i).to_owned(),
                observations: BTreeMap::new(),
                normal,
                first_keyframe: id,
            },
        );
        map.add_observation(id, i, pid);
    }
    let count = map.keyframes[&id].points.iter().flatten().count();
    if let Some(kf) = map.keyframes.get_mut(&id) {
        kf.tracked = count;
    }
    (id, count)
}

/// Removes a keyframe and the points only it observed.
pub fn remove_keyframe(map: &mut Map, id: u64) {
    let Some(kf) = map.keyframes.get(&id) else {
        return;
    };
    let points: Vec<u64> = kf.points.iter().flatten().copied().collect();
    for p in points {
        map.remove_observation(id, p);
        if map
            .points
            .get(&p)
            .is_some_and(|p| p.observations.is_empty())
        {
            map.points.remove(&p);
        }
    }
    map.keyframes.remove(&id);
    map.rereference_points(id);
}

/// What tracking one frame produced.
pub struct FrameOutcome {
    /// Tracking state of the frame.
    pub state: TrackState,
    /// `world_from_cam` (for a lost frame: the constant-velocity prediction).
    pub world_from_cam: Se3,
    /// Inlier map points.
    pub inliers: usize,
    /// The keyframe created from this frame, if any.
    pub keyframe: Option<u64>,
}

/// The settings tracking reads.
pub struct TrackContext<'c> {
    /// Calibration.
    pub calib: &'c StereoCalibration,
    /// `[tracking]`.
    pub cfg: &'c TrackingConfig,
    /// `[triangulation]` (depth limits of stereo points and the frustum).
    pub tri: &'c TriangulationConfig,
}

/// Bootstraps the map from the first stereo frame (identity pose).
pub fn bootstrap(
    map: &mut Map,
    state: &mut TrackerState,
    frame: &StereoFrame,
    ctx: &TrackContext,
) -> FrameOutcome {
    let (id, count) = insert_keyframe(map, frame, Se3::identity(), &[], ctx.calib, ctx.tri);
    if count < ctx.cfg.init_min_points as usize {
        log::info!(
            "tracking: t={} ns: {count} stereo points, {} needed to initialise",
            frame.t_ns,
            ctx.cfg.init_min_points
        );
        remove_keyframe(map, id);
        return FrameOutcome {
            state: TrackState::Lost,
            world_from_cam: Se3::identity(),
            inliers: 0,
            keyframe: None,
        };
    }
    log::info!(
        "tracking: initialised at t={} ns with {count} points",
        frame.t_ns
    );
    let record = FrameRecord {
        t_ns: frame.t_ns,
        keyframe: id,
        kf_from_cam: Se3::identity(),
        predicted: false,
        held: false,
        position_cov: None,
    };
    map.trajectory.push(record);
    *state = TrackerState {
        last: Some(record),
        velocity: Se3::identity(),
        reference: Some(id),
        lost: false,
        measured: Some(record),
        velocity_relocalised: false,
        fresh_segment: false,
        at_rest: false,
    };
    FrameOutcome {
        state: TrackState::Initialised,
        world_from_cam: Se3::identity(),
        inliers: count,
        keyframe: Some(id),
    }
}

/// Records the frames at `times_ns`, seen before the map began with keyframe `keyframe`
/// (quiet frames of event images, whose camera was at rest), as held at that keyframe's
/// pose ([`FrameRecord::held`]), just before the keyframe's own record. Returns how many;
/// times at or after the keyframe's record are skipped.
pub fn hold_before(map: &mut Map, keyframe: u64, times_ns: &[i64]) -> usize {
    let Some(at) = map.trajectory.iter().position(|r| r.keyframe == keyframe) else {
        return 0;
    };
    let first = map.trajectory[at].t_ns;
    let held: Vec<FrameRecord> = times_ns
        .iter()
        .filter(|&&t| t < first)
        .map(|&t_ns| FrameRecord {
            t_ns,
            keyframe,
            kf_from_cam: Se3::identity(),
            predicted: true,
            held: true,
            position_cov: None,
        })
        .collect();
    let count = held.len();
    if count > 0 {
        log::info!("tracking: {count} quiet frames before the first map held at its pose");
    }
    map.trajectory.splice(at..at, held);
    count
}

/// Starts a new map segment from `frame`'s own stereo points at `world_from_cam` (the
/// constant-velocity prediction) when the frame could be neither tracked nor relocalised.
/// A segment started right after another one that no frame was tracked against goes on from
/// rest whatever `[tracking] segment_velocity` says, so a run of such frames is extrapolated
/// over two frames at most and then holds its pose. Two cover the usual glitch (one frame
/// the map does not match, then one that does not match that frame's segment) while the
/// camera moves on smoothly; extrapolating at every frame of a longer run (a camera come to
/// rest in front of event cameras that see only noise) would carry the trajectory away at
/// the last measured speed.
/// Returns `None` when the frame has too few stereo points (the frame stays lost).
pub fn reinitialise(
    map: &mut Map,
    state: &mut TrackerState,
    frame: &StereoFrame,
    ctx: &TrackContext,
    world_from_cam: Se3,
) -> Option<FrameOutcome> {
    let chained = state.fresh_segment;
    let (id, count) = insert_keyframe(map, frame, world_from_cam, &[], ctx.calib, ctx.tri);
    if count < ctx.cfg.init_min_points as usize {
        remove_keyframe(map, id);
        return None;
    }
    map.segment_starts.insert(id);
    log::info!(
        "tracking: t={} ns: neither tracked nor relocalised; new map segment (keyframe {id}, \
         {count} points) at the constant-velocity pose{}",
        frame.t_ns,
        if chained {
            "; the next one, if any, at rest"
        } else {
            ""
        }
    );
    let record = FrameRecord {
        t_ns: frame.t_ns,
        keyframe: id,
        kf_from_cam: Se3::identity(),
        predicted: false,
        held: false,
        position_cov: None,
    };
    map.trajectory.push(record);
    state.last = Some(record);
    state.measured = Some(record);
    state.reference = Some(id);
    state.lost = false;
    state.fresh_segment = true;
    state.at_rest = false;
    let from_rest = chained
        || match ctx.cfg.segment_velocity.as_str() {
            "kept" => false,
            "rest" => true,
            _ => state.velocity_relocalised,
        };
    if from_rest {
        state.velocity = Se3::identity();
        state.velocity_relocalised = false;
    }
    Some(FrameOutcome {
        state: TrackState::Initialised,
        world_from_cam,
        inliers: count,
        keyframe: Some(id),
    })
}

/// Matches a frame against the local map around the prediction and refines its pose.
pub fn track_local_map(
    map: &Map,
    state: &TrackerState,
    frame: &StereoFrame,
    ctx: &TrackContext,
    predicted: Se3,
) -> Option<Tracked> {
    let reference = state.reference?;
    let kf = map.keyframes.get(&reference)?;
    let mut local = vec![reference];
    local.extend(kf.best_covisible(ctx.cfg.local_keyframes as usize));
    let points = map.points_of(&local);
    let grid = Grid::new(
        &frame.keypoints,
        ctx.calib.width,
        ctx.calib.height,
        ctx.cfg.cell_px as f32,
    );
    let search = |radius: f64| {
        search_projected(
            map,
            &points,
            frame,
            &grid,
            ctx.calib,
            ctx.cfg,
            ctx.tri,
            &predicted,
            radius as f32,
        )
    };
    let mut found = search(ctx.cfg.radius_px);
    if found.iter().flatten().count() < ctx.cfg.min_matches as usize {
        found = search(ctx.cfg.wide_radius_px);
    }
    let matches: Vec<Option<u64>> = found.into_iter().map(|m| m.map(|(p, _)| p)).collect();
    refine_matches(
        map,
        frame,
        matches,
        predicted,
        ctx.calib,
        &pose_options(ctx.cfg, ctx.tri),
    )
}

/// The last tracked frame's `world_from_cam`, through its (possibly corrected) keyframe.
pub fn last_pose(map: &Map, state: &TrackerState) -> Option<Se3> {
    state.last.as_ref().and_then(|r| map.frame_pose(r))
}

/// The last frame's `world_from_cam` when a frame relocalised against keyframe `kf` follows
/// it directly in the same map segment (the tracker was not lost), so that the step between
/// the two is a measured motion; `None` otherwise.
pub fn consecutive_pose(map: &Map, state: &TrackerState, kf: u64) -> Option<Se3> {
    let last = state.last.as_ref().filter(|_| !state.lost)?;
    (map.segment_of(last.keyframe) == map.segment_of(kf)).then_some(())?;
    map.frame_pose(last)
}

/// The last frame's `world_from_cam` ([`last_pose`]) and the constant-velocity prediction of
/// the next frame's `cam_from_world` from it (from the origin before any frame).
pub fn constant_velocity_prediction(map: &Map, state: &TrackerState) -> (Option<Se3>, Se3) {
    let last = last_pose(map, state);
    (
        last,
        state.velocity * last.unwrap_or_else(Se3::identity).inverse(),
    )
}

/// `world_from_cam` of the reference keyframe, `None` without one (or when it is gone).
pub fn reference_pose(map: &Map, state: &TrackerState) -> Option<Se3> {
    state
        .reference
        .and_then(|r| map.keyframes.get(&r))
        .map(|k| k.world_from_cam)
}

/// How the reference keyframe moved since `then`, its `world_from_cam` when the frame was
/// tracked: `now · then⁻¹`, the change of coordinates of the map around it (threaded mapping:
/// a bundle adjustment may write back between the tracker's read of the map and its commit).
/// A pose tracked against the old points is carried into the new coordinates by it
/// (`world_from_cam' = motion · world_from_cam`), so that stored relative to the moved
/// keyframe it stays where it was measured. `None` when the keyframe did not move or is gone.
pub fn reference_motion(map: &Map, state: &TrackerState, then: Option<Se3>) -> Option<Se3> {
    let (then, now) = (then?, reference_pose(map, state)?);
    (now != then).then(|| now * then.inverse())
}

/// The frame tracked again when a loop correction moved the map after it was tracked
/// (threaded mapping: the loop-closing thread may correct between the tracker's read of the
/// map and its commit). `corrections` is [`Map::corrections`] when the frame was tracked;
/// while it is unchanged the tracked pose stands and this returns `None`. Otherwise the pose
/// is in the old coordinates and, stored relative to a keyframe that has since moved, would
/// be wrong by the correction: the frame is tracked again from the constant-velocity
/// prediction off the corrected last pose, giving `Some((tracked, last pose))` when that
/// has at least `needed` inliers, `None` when not (the caller keeps its pose).
pub fn retrack_after_correction(
    map: &Map,
    state: &TrackerState,
    frame: &StereoFrame,
    ctx: &TrackContext,
    corrections: u64,
    needed: usize,
) -> Option<(Tracked, Option<Se3>)> {
    if map.corrections == corrections {
        return None;
    }
    let (last, predicted) = constant_velocity_prediction(map, state);
    let tracked =
        track_local_map(map, state, frame, ctx, predicted).filter(|t| t.inliers >= needed);
    match &tracked {
        Some(t) => log::info!(
            "tracking: t={} ns tracked again after a loop correction ({} inliers)",
            frame.t_ns,
            t.inliers
        ),
        None => log::warn!(
            "tracking: t={} ns not tracked again after a loop correction; its pose is kept",
            frame.t_ns
        ),
    }
    tracked.map(|t| (t, last))
}

/// Records a tracked frame: keyframe decision, keyframe insertion, trajectory, tracker state.
pub fn commit_tracked(
    map: &mut Map,
    state: &mut TrackerState,
    frame: &StereoFrame,
    ctx: &TrackContext,
    tracked: Tracked,
    previous_world_from_cam: Option<Se3>,
    relocalised: bool,
) -> FrameOutcome {
    let world_from_cam = tracked.cam_from_world.inverse();
    state.velocity = match (relocalised, previous_world_from_cam) {
        (false, Some(prev)) => tracked.cam_from_world * prev,
        _ => Se3::identity(),
    };
    state.velocity_relocalised = false;
    state.fresh_segment = false;
    state.at_rest = false;
    let reference_tracked = match state.reference.and_then(|r| map.keyframes.get_mut(&r)) {
        Some(k) if k.tracked == 0 => {
            k.tracked = tracked.inliers;
            tracked.inliers
        }
        Some(k) => k.tracked,
        None => 0,
    };
    let need_keyframe = relocalised
        || state
            .reference
            .is_none_or(|r| !map.keyframes.contains_key(&r))
        || (tracked.inliers as f64) < ctx.cfg.keyframe_ratio * reference_tracked as f64
        || tracked.inliers < keyframe_floor(ctx.cfg, frame) as usize;
    let mut keyframe = None;
    if need_keyframe {
        let (id, count) = insert_keyframe(
            map,
            frame,
            world_from_cam,
            &tracked.matches,
            ctx.calib,
            ctx.tri,
        );
        log::debug!(
            "tracking: keyframe {id} at t={} ns: {} tracked, {count} points",
            frame.t_ns,
            tracked.inliers
        );
        // The keyframe's reference count is set by the first frame tracked after it (which
        // sees the keyframe's new points too): comparing with the keyframe's own point count
        // would make every frame a keyframe, comparing with what it matched almost none.
        if let Some(kf) = map.keyframes.get_mut(&id) {
            kf.tracked = 0;
        }
        state.reference = Some(id);
        keyframe = Some(id);
    }
    let record = state
        .reference
        .and_then(|r| map.keyframes.get(&r))
        .map(|kf| FrameRecord {
            t_ns: frame.t_ns,
            keyframe: kf.id,
            kf_from_cam: kf.world_from_cam.inverse() * world_from_cam,
            predicted: false,
            held: false,
            position_cov: tracked
                .covariance
                .map(|c| c.fixed_view::<3, 3>(0, 0).into_owned()),
        });
    if let Some(record) = record {
        map.trajectory.push(record);
        state.last = Some(record);
        state.measured = Some(record);
    }
    state.lost = false;
    FrameOutcome {
        state: if relocalised {
            TrackState::Relocalised
        } else {
            TrackState::Ok
        },
        world_from_cam,
        inliers: tracked.inliers,
        keyframe,
    }
}

/// The mean frame-to-frame motion over the `frames` trajectory steps that end at the last
/// measured frame: `(cam_from_world(m) · world_from_cam(m − n))^(1/n)` on SE(3) (through its
/// logarithm), in the same convention as [`TrackerState::velocity`]. `None` when `frames` is
/// 0 or the trajectory does not reach that far back.
pub fn mean_velocity(map: &Map, state: &TrackerState, frames: u32) -> Option<Se3> {
    let measured = state.measured?;
    let n = frames as usize;
    if n == 0 {
        return None;
    }
    let end = map
        .trajectory
        .iter()
        .rposition(|r| r.t_ns == measured.t_ns)?;
    let start = end.checked_sub(n)?;
    let cam_from_world = map.frame_pose(&map.trajectory[end])?.inverse();
    let world_from_start = map.frame_pose(&map.trajectory[start])?;
    let motion = (cam_from_world * world_from_start).log();
    Some(Se3::exp(&(motion / n as f64)))
}

/// Moves the pose on to `t_ns` with the constant-velocity model without looking at the
/// frame: for frames whose images carry no usable measurement (an event window flooded by a
/// global lighting change, issue 8). The velocity is the mean over `velocity_frames` steps
/// ([`mean_velocity`]; the last step's when the trajectory is shorter). The predicted
/// `world_from_cam` is recorded in the trajectory relative to the reference keyframe and
/// becomes the last frame, so the next frame's prediction extrapolates from it; the velocity,
/// the reference keyframe and the map are unchanged (no matching, no keyframe, no new map
/// segment). Returns `None` when there is nothing to predict from (not initialised yet, the
/// last frame lost, or no reference keyframe).
pub fn predict_only(
    map: &mut Map,
    state: &mut TrackerState,
    t_ns: i64,
    velocity_frames: u32,
) -> Option<FrameOutcome> {
    if state.lost {
        return None;
    }
    let previous = last_pose(map, state)?;
    let reference = state.reference.and_then(|r| map.keyframes.get(&r))?;
    // Held at rest since the last measured frame: the camera stays where it was.
    let velocity = if state.at_rest {
        Se3::identity()
    } else {
        mean_velocity(map, state, velocity_frames).unwrap_or(state.velocity)
    };
    // velocity = cam_from_world(k) · world_from_cam(k−1), so cam_from_world(k) = velocity ·
    // cam_from_world(k−1).
    let world_from_cam = (velocity * previous.inverse()).inverse();
    let reference = (reference.id, reference.world_from_cam);
    Some(record_unmeasured(
        map,
        state,
        reference,
        t_ns,
        world_from_cam,
        false,
        None,
    ))
}

/// Records `world_from_cam` at `t_ns` as an unmeasured frame, relative to the reference
/// keyframe `(id, world_from_cam)`, and makes it the last frame: predicted ([`predict_only`])
/// or `held` at rest ([`hold_pose`]; `position_cov` weighs it in the trajectory smoother).
fn record_unmeasured(
    map: &mut Map,
    state: &mut TrackerState,
    reference: (u64, Se3),
    t_ns: i64,
    world_from_cam: Se3,
    held: bool,
    position_cov: Option<Matrix3<f64>>,
) -> FrameOutcome {
    let record = FrameRecord {
        t_ns,
        keyframe: reference.0,
        kf_from_cam: reference.1.inverse() * world_from_cam,
        predicted: true,
        held,
        position_cov,
    };
    map.trajectory.push(record);
    state.last = Some(record);
    FrameOutcome {
        state: if held {
            TrackState::Held
        } else {
            TrackState::Predicted
        },
        world_from_cam,
        inliers: 0,
        keyframe: None,
    }
}

/// Keeps the last pose for a quiet frame that could not be tracked ([`StereoFrame::quiet`]:
/// the event window holds a small fraction of the usual events, so the camera is likely at
/// rest and the event images show sensor noise, whose "features" match nothing). The last
/// pose is recorded at `t_ns` relative to the reference keyframe and becomes the last frame,
/// the velocity restarts from rest, and the map is unchanged: no relocalisation on noise and
/// no new map segment of noise points, so when the camera moves again the next frame is
/// tracked against the same map from where it stopped. Returns `None` when there is nothing
/// to hold (not initialised, the last frame lost, or no reference keyframe).
pub fn hold_pose(map: &mut Map, state: &mut TrackerState, t_ns: i64) -> Option<FrameOutcome> {
    if state.lost {
        return None;
    }
    let world_from_cam = last_pose(map, state)?;
    let reference = state.reference.and_then(|r| map.keyframes.get(&r))?;
    if !state.at_rest {
        log::info!("tracking: t={t_ns} ns: quiet event window not tracked; pose held at rest");
    }
    let reference = (reference.id, reference.world_from_cam);
    // As certain as the last measurement: the trajectory smoother takes the held frame as a
    // measured one (see `FrameRecord::held`).
    let covariance = state.measured.and_then(|m| m.position_cov);
    let outcome = record_unmeasured(
        map,
        state,
        reference,
        t_ns,
        world_from_cam,
        true,
        covariance,
    );
    state.velocity = Se3::identity();
    state.velocity_relocalised = false;
    state.at_rest = true;
    Some(outcome)
}

/// What [`bridge_keyframe`] inserted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Bridge {
    /// The bridge keyframe.
    pub keyframe: u64,
    /// Map points of the tracked image re-matched and observed by the bridge keyframe.
    pub linked: usize,
    /// New map points triangulated from the other image's stereo matches.
    pub other_points: usize,
}

/// A bridge keyframe across a change of image appearance (issue 8: the fusion switching
/// between frame- and event-dominated images, whose descriptors do not match each other).
///
/// `primary` is the image the map was tracked with at the last tracked frame (same
/// timestamp), `other` the same sensor data rendered the other way. The primary features are
/// matched again against the local map at the last tracked pose; when at least
/// `min_tracked` of them are inliers, one keyframe holding the features of both images
/// (primary first) is inserted at that pose (`world_from_cam` of the last frame): the
/// primary matches become its observations of the existing map (so it is covisible with the
/// old keyframes and bundle adjustment keeps it tied to them) and the stereo matches of both
/// images become new points. It becomes the reference keyframe, so the next frames, which
/// look like `other`, track against its points. The primary frame may also be the last
/// *measured* frame followed only by predicted ones ([`predict_only`], a flood between the
/// two modes): the keyframe goes in at the primary frame's pose and the last (predicted)
/// frame is re-expressed relative to it. Returns `None` (nothing changed) when neither the
/// last frame nor the last measured one is `primary`'s, the last was lost, or too few
/// primary features match.
pub fn bridge_keyframe(
    map: &mut Map,
    state: &mut TrackerState,
    primary: &StereoFrame,
    other: &StereoFrame,
    ctx: &TrackContext,
) -> Option<Bridge> {
    if state.lost {
        return None;
    }
    let last = state.last?;
    let source = if last.t_ns == primary.t_ns {
        last
    } else {
        state.measured.filter(|m| m.t_ns == primary.t_ns)?
    };
    let world_from_cam = map.frame_pose(&source)?;
    let last_world_from_cam = map.frame_pose(&last)?;
    let tracked = track_local_map(map, state, primary, ctx, world_from_cam.inverse())
        .filter(|t| t.inliers >= ctx.cfg.min_tracked as usize)?;
    let kind = primary.descriptors.kind();
    let mut descriptors = OwnedDescriptors::new(kind, primary.descriptors.width());
    for d in [primary.descriptors, other.descriptors] {
        for i in 0..d.len() {
            descriptors.push(d.row(i)).ok()?;
        }
    }
    let mut keypoints = primary.keypoints.clone();
    keypoints.extend_from_slice(&other.keypoints);
    let mut u_right = primary.u_right.clone();
    u_right.extend_from_slice(&other.u_right);
    let mut sigmas = primary.sigmas.clone();
    sigmas.extend_from_slice(&other.sigmas);
    let mut viewpoints = primary.viewpoints.clone();
    viewpoints.extend_from_slice(&other.viewpoints);
    let both = StereoFrame {
        t_ns: primary.t_ns,
        keypoints,
        u_right,
        sigmas,
        viewpoints,
        descriptors: descriptors.view(),
        dvs_biased: primary.dvs_biased,
        quiet: primary.quiet,
    };
    let mut matches = tracked.matches;
    matches.resize(both.keypoints.len(), None);
    let points_before = map.points.len();
    let (id, count) = insert_keyframe(map, &both, world_from_cam, &matches, ctx.calib, ctx.tri);
    let n_primary = primary.keypoints.len();
    let other_points = map.keyframes[&id].points[n_primary..]
        .iter()
        .flatten()
        .count();
    if let Some(kf) = map.keyframes.get_mut(&id) {
        // As for any new keyframe: the first frame tracked after it sets its reference count.
        kf.tracked = 0;
    }
    let record = FrameRecord {
        t_ns: primary.t_ns,
        keyframe: id,
        kf_from_cam: Se3::identity(),
        predicted: false,
        held: false,
        position_cov: None,
    };
    state.measured = Some(record);
    state.last = Some(if last.t_ns == primary.t_ns {
        record
    } else {
        FrameRecord {
            t_ns: last.t_ns,
            keyframe: id,
            kf_from_cam: world_from_cam.inverse() * last_world_from_cam,
            predicted: last.predicted,
            held: last.held,
            position_cov: None,
        }
    });
    state.reference = Some(id);
    log::info!(
        "tracking: bridge keyframe {id} at t={} ns: {} map points re-matched, {other_points} \
         points from the other image ({count} in all, {} new)",
        primary.t_ns,
        tracked.inliers,
        map.points.len().saturating_sub(points_before)
    );
    Some(Bridge {
        keyframe: id,
        linked: tracked.inliers,
        other_points,
    })
}
