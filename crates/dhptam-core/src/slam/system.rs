//! [`System`]: the facade that owns the map, tracks frames on the caller's thread and drives
//! local mapping (and loop closing) either on worker threads or inline.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender};
use std::sync::{Arc, Condvar, Mutex, RwLock};
use std::thread::JoinHandle;
use std::time::Instant;

use nalgebra::Vector3;

use super::loop_closing::{detect_and_close, verify};
use super::map::Map;
use super::mapping::{cull_keyframes, fuse_and_refind, local_mapping};
use super::tracking::{
    bootstrap, bridge_keyframe, commit_tracked, consecutive_pose, constant_velocity_prediction,
    hold_before, hold_pose, last_pose, predict_only, reference_motion, reference_pose,
    reinitialise, retrack_after_correction, stereo_match, track_local_map, Bridge, StereoFrame,
    TrackContext, Tracked, TrackerState,
};
use super::{lock, persist, read_lock, write_lock, StereoCalibration, TrackResult, TrackState};
use crate::config::Config;
use crate::error::{ensure_sigmas, Error, Result};
use crate::fusion::{EventStereo, FusionMode};
use crate::geometry::Se3;
use crate::matching::{DescriptorKind, Descriptors};
use crate::place::PlaceDatabase;

/// One image's features: keypoints `(x, y)` row-major as `[x0, y0, x1, y1, …]` (rectified
/// pixels), one descriptor row per keypoint and optionally each keypoint's measurement noise.
#[derive(Clone, Copy, Debug)]
pub struct FrameFeatures<'a> {
    /// Keypoints, 2 numbers each.
    pub keypoints: &'a [f32],
    /// Descriptors, one row per keypoint.
    pub descriptors: Descriptors<'a>,
    /// Measurement noise σ per keypoint, pixels (finite, positive), e.g. `1.2^octave` for
    /// ORB; `None`: 1 px each. Only the left image's are used (a stereo match shares its
    /// left keypoint's σ), and only with `[tracking] keypoint_sigma = "octave"`.
    pub sigmas: Option<&'a [f32]>,
    /// Factor on every keypoint σ of the image (finite, positive), with either
    /// `keypoint_sigma`: images known to locate keypoints less precisely as a whole, e.g.
    /// event-dominated fusion (`[tracking] dvs_sigma_scale`, applied by the Python front-end).
    pub sigma_scale: f32,
    /// How the pair's stereo disparities relate to the frame cameras' (the left image's is
    /// used): identity for frames; for event images warped into the frame cameras, the
    /// correction the Python front-end computes (`Frontend.event_disparity`).
    pub disparity: DisparityCorrection,
    /// For event images warped into the frame cameras: reads each stereo match through the
    /// event cameras' geometry (both pixels unwarped, triangulated with the event pair,
    /// projected into the frame cameras), which moves the left keypoint and its right column
    /// to where the frame cameras would have seen the point (the left image's is used; with
    /// it, `disparity` must be the identity). `None`: keypoints as measured.
    pub event_stereo: Option<&'a EventStereo>,
    /// Centre of the camera pair whose view the image is, in the rectified left frame
    /// camera's axes, metres (the left image's is used): zero for the frame cameras' own
    /// images; for event images warped into the frame cameras through the plane at infinity,
    /// the rectified left event camera's centre (`Frontend.event_viewpoint`), so that
    /// tracking, new points and bundle adjustment model each keypoint from where it was seen.
    /// Mind that this holds exactly only through the plane at infinity, with the event pair's
    /// disparities mapped to the frame baseline (`disparity`).
    pub viewpoint: [f32; 3],
    /// Whether the image is the fusion's DVS-biased rendering (event-dominated, mode
    /// `fusion`); a frame of such images gets the keyframe floor `[tracking]
    /// dvs_keyframe_min_tracked` (the left image's is used).
    pub dvs_biased: bool,
    /// Whether the frame's event window is quiet (`[fusion] quiet_ratio`: a small fraction
    /// of the usual event count, so the camera is likely at rest): when the frame cannot be
    /// tracked its pose is held (state `Held`) instead of relocalised or started as a new
    /// map segment of noise points (the left image's is used).
    pub quiet: bool,
}

/// Maps a stereo match's measured disparity `d = u_left − u_right` of an image pair to the
/// disparity the rectified frame cameras (baseline and focal length of the map) would see:
/// `scale · d + offset_px`.
///
/// Event images warped into the frame cameras keep the event cameras' parallax: through a
/// plane at depth `D` a point at depth `Z` shows the disparity `f b_e / Z − f (b_e − b_f) / D`
/// for event and frame baselines `b_e`, `b_f` (along the rectified rows) and focal length
/// `f`, so `scale = b_f / b_e` and `offset_px = scale · f (b_e − b_f) / D` (0 through the
/// plane at infinity) give back `f b_f / Z`. Without it the event pair's points come out
/// `b_f / b_e` times too near (−9 % on the simulator's rig).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DisparityCorrection {
    /// Factor on the measured disparity (finite, positive).
    pub scale: f32,
    /// Pixels added after the factor (finite).
    pub offset_px: f32,
}

impl DisparityCorrection {
    /// Frame images: the disparity as measured.
    pub const IDENTITY: Self = Self {
        scale: 1.0,
        offset_px: 0.0,
    };

    /// The right column after the correction of `u_left`'s match at `u_right`; NaN when
    /// unmatched or when the corrected disparity is not positive.
    pub fn apply(&self, u_left: f32, u_right: f32) -> f32 {
        if *self == Self::IDENTITY || !u_right.is_finite() {
            return u_right;
        }
        let d = self.scale * (u_left - u_right) + self.offset_px;
        if d > 0.0 {
            u_left - d
        } else {
            f32::NAN
        }
    }
}

impl Default for DisparityCorrection {
    fn default() -> Self {
        Self::IDENTITY
    }
}

/// Running statistics of one stage's wall time.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageStats {
    /// Number of calls.
    pub count: u64,
    /// Total seconds.
    pub total_s: f64,
    /// Longest call, seconds.
    pub max_s: f64,
}

impl StageStats {
    /// Mean seconds per call (0 without calls).
    pub fn mean_s(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.total_s / self.count as f64
        }
    }
}

/// State shared by the tracker and the worker threads.
pub(crate) struct Shared {
    pub(crate) map: RwLock<Map>,
    pub(crate) timings: Mutex<BTreeMap<&'static str, StageStats>>,
    /// Set by the tracker when a keyframe is queued: the running bundle adjustment stops.
    pub(crate) interrupt: AtomicBool,
    /// Set by shutdown: workers skip queued work and exit.
    pub(crate) shutdown: AtomicBool,
    pub(crate) calib: StereoCalibration,
    pub(crate) config: Config,
    /// Keyframe embeddings for loop detection and relocalisation.
    pub(crate) place: Mutex<PlaceDatabase>,
    /// Running totals of the mapping fusion.
    pub(crate) fusion: Mutex<FusionTotals>,
    /// Keyframes removed as redundant by the mapping thread so far.
    pub(crate) culled_keyframes: AtomicU64,
    /// Keyframes the mapping thread has finished (`u64::MAX` once it has stopped), with the
    /// condition the tracker waits on for a DVS-biased keyframe ([`System::track`]).
    pub(crate) mapped: (Mutex<u64>, Condvar),
}

/// Running totals of the mapping thread's fusion of duplicate points and re-finding.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FusionTotals {
    /// Duplicate map points fused into others.
    pub merged: u64,
    /// Observations added by re-finding points in keyframes.
    pub refound: u64,
}

impl Shared {
    /// Counts `n` more keyframes as mapped (saturating) and wakes a waiting tracker.
    fn mapped_one(&self, n: u64) {
        let mut done = lock(&self.mapped.0);
        *done = done.saturating_add(n);
        self.mapped.1.notify_all();
    }

    pub(crate) fn time<T>(&self, stage: &'static str, f: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let out = f();
        let s = start.elapsed().as_secs_f64();
        let mut t = lock(&self.timings);
        let e = t.entry(stage).or_default();
        e.count += 1;
        e.total_s += s;
        e.max_s = e.max_s.max(s);
        out
    }

    /// Local mapping for keyframe `kf` (logs and swallows numerical failures: the map keeps
    /// the tracker's estimates).
    pub(crate) fn map_keyframe(&self, kf: u64, stop: Option<&AtomicBool>) {
        let c = &self.config;
        if c.mapping.fuse {
            let r = self.time("fusion", || {
                fuse_and_refind(
                    &self.map,
                    kf,
                    &self.calib,
                    &c.mapping,
                    &c.tracking,
                    &c.triangulation,
                    stop,
                )
            });
            match r {
                Ok(report) => {
                    let mut t = lock(&self.fusion);
                    t.merged += report.merged as u64;
                    t.refound += report.refound as u64;
                }
                Err(e) => log::warn!("mapping: keyframe {kf}: fusion failed: {e}"),
            }
        }
        // Debug log: how far the adjustment moved each keyframe (a weakly linked keyframe can
        // slide far from where it was tracked).
        let centres_before: Option<Vec<(u64, Vector3<f64>)>> = log::log_enabled!(log::Level::Debug)
            .then(|| {
                read_lock(&self.map)
                    .keyframes
                    .iter()
                    .map(|(&k, v)| (k, v.centre()))
                    .collect()
            });
        let r = self.time("local_ba", || {
            local_mapping(
                &self.map,
                kf,
                &self.calib,
                &c.mapping,
                &c.tracking,
                &c.triangulation,
                stop,
            )
        });
        if let Err(e) = r {
            log::warn!("mapping: keyframe {kf}: bundle adjustment failed: {e}");
        }
        if let Some(before) = centres_before {
            let m = read_lock(&self.map);
            let moved: Vec<String> = before
                .iter()
                .filter_map(|(k, c)| {
                    let d = (m.keyframes.get(k)?.centre() - c).norm();
                    (d > 0.0).then(|| format!("{k}: {:.1} mm", 1e3 * d))
                })
                .collect();
            let moved = if moved.is_empty() {
                "none".to_owned()
            } else {
                moved.join(", ")
            };
            log::debug!("mapping: keyframe {kf}: keyframe centres moved: {moved}");
        }
        // Keyframe culling (issue 10), after the bundle adjustment; it is cheap (one pass over
        // the covisible keyframes' points under the write lock), so it runs even when a newer
        // keyframe interrupted the adjustment.
        if c.mapping.cull_keyframes {
            let report = self.time("keyframe_culling", || {
                cull_keyframes(&self.map, &self.place, kf, &c.mapping)
            });
            self.culled_keyframes
                .fetch_add(report.removed.len() as u64, Ordering::Relaxed);
        }
        if kf % MAP_SIZE_LOG_EVERY == 0 {
            let m = read_lock(&self.map);
            if let Some(k) = m.keyframes.get(&kf) {
                log::info!(
                    "mapping: map at t={} ns: {} keyframes, {} points ({} keyframes culled so far)",
                    k.t_ns,
                    m.keyframes.len(),
                    m.points.len(),
                    self.culled_keyframes.load(Ordering::Relaxed)
                );
            }
        }
    }

    /// Loop detection and correction for keyframe `kf` (failures are logged).
    pub(crate) fn close_loops(&self, kf: u64) {
        let c = &self.config;
        let r = self.time("loop_closing", || {
            detect_and_close(
                &self.map,
                &self.place,
                kf,
                &self.calib,
                &c.tracking,
                &c.loop_closing,
            )
        });
        if let Err(e) = r {
            log::warn!("loop: keyframe {kf}: {e}");
        }
    }
}

/// Running totals of how tracking kept (or did not keep) the map in one piece.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TrackingTotals {
    /// Bridge keyframes inserted ([`System::bridge`]).
    pub bridges: u64,
    /// Bridge requests refused (last frame lost or not the bridge's, too few re-matches).
    pub bridges_refused: u64,
    /// New map segments started at the constant-velocity pose (`[tracking] reinitialise`).
    pub segments: u64,
    /// Frames relocalised against an older keyframe, or whose track was picked up again from
    /// the motion model after a loss (with as many inliers as a relocalisation needs).
    pub relocalisations: u64,
    /// Frames moved on by the motion model without being tracked ([`System::predict`]).
    pub predicted: u64,
    /// Quiet frames that could not be tracked and kept the last pose (state `Held`), and
    /// quiet frames of event images before the first map, held at its pose.
    pub held: u64,
    /// Tracked poses rejected for jumping away from the constant-velocity prediction
    /// (`[tracking] max_jump_ratio`); each such frame went on to relocalisation.
    pub implausible: u64,
}

/// The mapping thread logs the map's size (INFO) after every this many keyframe ids.
const MAP_SIZE_LOG_EVERY: u64 = 20;

/// The SLAM system. See the module documentation.
pub struct System {
    shared: Arc<Shared>,
    state: TrackerState,
    totals: TrackingTotals,
    descriptor: Option<(DescriptorKind, usize)>,
    threaded: bool,
    mapping_tx: Option<SyncSender<u64>>,
    /// Keyframes handed to the mapping thread so far.
    sent: u64,
    workers: Vec<JoinHandle<()>>,
    closed: bool,
    /// Median depth (m, rectified left camera) of the map points the last measured frame
    /// tracked ([`System::tracked_depth`]).
    tracked_depth: Option<f64>,
    /// Times of the quiet frames of event images seen before the first map (the camera at
    /// rest): held at the first map's pose once it is made ([`super::tracking::hold_before`]).
    rest_before_map: Vec<i64>,
}

/// Median of the depths (z in `cam_from_world`'s camera, metres) of the map points `ids`;
/// points behind the camera or no longer in the map are skipped, `None` when none is left.
fn median_point_depth(
    map: &Map,
    cam_from_world: &Se3,
    ids: impl IntoIterator<Item = u64>,
) -> Option<f64> {
    let mut z: Vec<f64> = ids
        .into_iter()
        .filter_map(|id| map.points.get(&id))
        .map(|p| cam_from_world.transform_point(&p.position).z)
        .filter(|z| z.is_finite() && *z > 0.0)
        .collect();
    if z.is_empty() {
        return None;
    }
    let mid = z.len() / 2;
    let (_, m, _) = z.select_nth_unstable_by(mid, f64::total_cmp);
    Some(*m)
}

/// How far a tracked pose jumped from the motion model's prediction.
struct Jump {
    distance_m: f64,
    depth_m: f64,
    inliers: usize,
}

/// Distance in metres between the camera centres of `tracked` and of the motion model's
/// `predicted` `cam_from_world`.
fn distance_from_prediction(tracked: &Tracked, predicted: &Se3) -> f64 {
    (tracked.cam_from_world.inverse().translation - predicted.inverse().translation).norm()
}

/// The jump of `tracked`'s camera centre from the one `predicted` (`cam_from_world`) places,
/// when it exceeds `ratio` times the median depth of the tracked inliers; `None` when it
/// does not, when `ratio` is 0 (off) or when no inlier lies in front of the camera.
fn implausible_jump(map: &Map, tracked: &Tracked, predicted: &Se3, ratio: f64) -> Option<Jump> {
    if ratio <= 0.0 {
        return None;
    }
    let inliers = tracked.matches.iter().flatten().copied();
    let depth_m = median_point_depth(map, &tracked.cam_from_world, inliers)?;
    let distance_m = distance_from_prediction(tracked, predicted);
    (distance_m > ratio * depth_m).then_some(Jump {
        distance_m,
        depth_m,
        inliers: tracked.inliers,
    })
}

fn mapping_worker(shared: Arc<Shared>, rx: Receiver<u64>, loops: SyncSender<u64>) {
    while let Ok(kf) = rx.recv() {
        if shared.shutdown.load(Ordering::Acquire) {
            break;
        }
        shared.interrupt.store(false, Ordering::Release);
        shared.map_keyframe(kf, Some(&shared.interrupt));
        shared.mapped_one(1);
        if loops.send(kf).is_err() {
            break;
        }
    }
    // Nothing more will be mapped: a tracker waiting for it goes on.
    shared.mapped_one(u64::MAX);
}

fn loop_worker(shared: Arc<Shared>, rx: Receiver<u64>) {
    while let Ok(kf) = rx.recv() {
        if shared.shutdown.load(Ordering::Acquire) {
            break;
        }
        shared.close_loops(kf);
    }
}

fn spawn(name: &str, f: impl FnOnce() + Send + 'static) -> Result<JoinHandle<()>> {
    std::thread::Builder::new()
        .name(name.into())
        .spawn(f)
        .map_err(|e| Error::Numerical {
            operation: "starting a SLAM thread",
            reason: e.to_string(),
        })
}

impl System {
    /// A system for `calib` with `config` (validated); `threaded` runs mapping on its own
    /// thread, otherwise inline and deterministic. In `[fusion] mode = "events"` the
    /// tracker's keyframe floor is `[tracking] events_keyframe_min_tracked`.
    pub fn new(calib: StereoCalibration, mut config: Config, threaded: bool) -> Result<Self> {
        config.validate()?;
        if config.fusion.mode == FusionMode::Events {
            config.tracking.keyframe_min_tracked = config.tracking.events_keyframe_min_tracked;
        }
        let shared = Arc::new(Shared {
            map: RwLock::new(Map::default()),
            timings: Mutex::new(BTreeMap::new()),
            interrupt: AtomicBool::new(false),
            shutdown: AtomicBool::new(false),
            calib,
            config,
            place: Mutex::new(PlaceDatabase::new()),
            fusion: Mutex::new(FusionTotals::default()),
            culled_keyframes: AtomicU64::new(0),
            mapped: (Mutex::new(0), Condvar::new()),
        });
        let mut system = Self {
            shared,
            state: TrackerState::default(),
            totals: TrackingTotals::default(),
            descriptor: None,
            threaded,
            mapping_tx: None,
            sent: 0,
            workers: Vec::new(),
            closed: false,
            tracked_depth: None,
            rest_before_map: Vec::new(),
        };
        if threaded {
            let queue = system.shared.config.mapping.queue as usize;
            let (tx, rx) = sync_channel(queue);
            let (loop_tx, loop_rx) = sync_channel(queue);
            let shared = Arc::clone(&system.shared);
            system
                .workers
                .push(spawn("dhptam-loop", move || loop_worker(shared, loop_rx))?);
            let shared = Arc::clone(&system.shared);
            system.workers.push(spawn("dhptam-mapping", move || {
                mapping_worker(shared, rx, loop_tx)
            })?);
            system.mapping_tx = Some(tx);
        }
        Ok(system)
    }

    /// The calibration.
    pub fn calibration(&self) -> &StereoCalibration {
        &self.shared.calib
    }

    /// Whether mapping runs on its own thread.
    pub fn threaded(&self) -> bool {
        self.threaded
    }

    fn check_features(&mut self, side: &str, f: &FrameFeatures) -> Result<Vec<[f32; 2]>> {
        let n = f.descriptors.len();
        if f.keypoints.len() != 2 * n {
            return Err(Error::invalid(
                format!("{side}.keypoints"),
                format!("{n} rows of (x, y), one per descriptor"),
                format!("{} numbers", f.keypoints.len()),
            ));
        }
        if let Some(i) = f.keypoints.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                format!("{side}.keypoints[{}]", i / 2),
                "finite coordinates",
                f.keypoints[i],
            ));
        }
        if !(f.sigma_scale.is_finite() && f.sigma_scale > 0.0) {
            return Err(Error::invalid(
                format!("{side}.sigma_scale"),
                "a finite positive factor",
                f.sigma_scale,
            ));
        }
        if let Some(s) = f.sigmas {
            ensure_sigmas(&format!("{side}.sigmas"), s, n)?;
        }
        let d = f.disparity;
        if !(d.scale.is_finite() && d.scale > 0.0 && d.offset_px.is_finite()) {
            return Err(Error::invalid(
                format!("{side}.disparity"),
                "a finite positive scale and a finite offset",
                format!("scale {}, offset {} px", d.scale, d.offset_px),
            ));
        }
        if let Some(i) = f.viewpoint.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                format!("{side}.viewpoint[{i}]"),
                "a finite camera centre in metres",
                f.viewpoint[i],
            ));
        }
        if f.event_stereo.is_some() && d != DisparityCorrection::IDENTITY {
            return Err(Error::invalid(
                format!("{side}.disparity"),
                "the identity with an event-stereo reading (the reading corrects disparities itself)",
                format!("scale {}, offset {} px", d.scale, d.offset_px),
            ));
        }
        let this = (f.descriptors.kind(), f.descriptors.width());
        match self.descriptor {
            Some(d) if d != this => {
                return Err(Error::invalid(
                    format!("{side}.descriptors"),
                    format!("{:?} descriptors of width {} (as the map's)", d.0, d.1),
                    format!("{:?} of width {}", this.0, this.1),
                ))
            }
            _ => self.descriptor = Some(this),
        }
        Ok(f.keypoints.chunks_exact(2).map(|c| [c[0], c[1]]).collect())
    }

    /// Checks one stereo pair's features and matches them left to right.
    fn stereo_frame<'f>(
        &mut self,
        t_ns: i64,
        left: FrameFeatures<'f>,
        right: FrameFeatures<'f>,
    ) -> Result<StereoFrame<'f>> {
        let mut left_xy = self.check_features("left", &left)?;
        let right_xy = self.check_features("right", &right)?;
        let shared = &self.shared;
        let c = &shared.config;
        let mut u_right = shared.time("stereo_match", || {
            stereo_match(
                &shared.calib,
                &c.tracking,
                &c.triangulation,
                &left_xy,
                left.descriptors,
                &right_xy,
                right.descriptors,
            )
        });
        match left.event_stereo {
            Some(reading) => {
                for (u, kp) in u_right.iter_mut().zip(left_xy.iter_mut()) {
                    if !u.is_finite() {
                        continue;
                    }
                    match reading.frame_reading(*kp, *u) {
                        Some((p, ur)) => (*kp, *u) = (p, ur),
                        None => *u = f32::NAN,
                    }
                }
            }
            None => {
                for (u, kp) in u_right.iter_mut().zip(&left_xy) {
                    *u = left.disparity.apply(kp[0], *u);
                }
            }
        }
        let scale = left.sigma_scale;
        let sigmas = match left.sigmas {
            Some(s) if c.tracking.keypoint_sigma == "octave" => {
                s.iter().map(|v| v * scale).collect()
            }
            _ => vec![scale; left_xy.len()],
        };
        Ok(StereoFrame {
            t_ns,
            dvs_biased: left.dvs_biased,
            quiet: left.quiet,
            viewpoints: vec![left.viewpoint; left_xy.len()],
            keypoints: left_xy,
            u_right,
            sigmas,
            descriptors: left.descriptors,
        })
    }

    /// Inserts a bridge keyframe at the last tracked frame (timestamp `t_ns`) across a change
    /// of image appearance, e.g. the fusion switching between frame- and event-dominated
    /// images: `primary` are the features of the image that frame was tracked with, `other`
    /// those of the same sensor data rendered the other way (see
    /// [`super::tracking::bridge_keyframe`]). Returns the keyframe and its counts, or `None`
    /// when the bridge was refused (the last frame is not at `t_ns`, was lost, or too few
    /// primary features matched the map again); mapping runs (or is queued) as for any
    /// keyframe.
    pub fn bridge(
        &mut self,
        t_ns: i64,
        primary: (FrameFeatures, FrameFeatures),
        other: (FrameFeatures, FrameFeatures),
    ) -> Result<Option<Bridge>> {
        if self.closed {
            return Err(Error::invalid(
                "system",
                "a running system",
                "one shut down",
            ));
        }
        let primary = self.stereo_frame(t_ns, primary.0, primary.1)?;
        let other = self.stereo_frame(t_ns, other.0, other.1)?;
        let shared = Arc::clone(&self.shared);
        let c = &shared.config;
        let ctx = TrackContext {
            calib: &shared.calib,
            cfg: &c.tracking,
            tri: &c.triangulation,
        };
        let bridge = shared.time("bridge", || {
            let mut map = write_lock(&shared.map);
            bridge_keyframe(&mut map, &mut self.state, &primary, &other, &ctx)
        });
        match bridge {
            Some(b) => {
                self.totals.bridges += 1;
                self.after_keyframe(b.keyframe);
            }
            None => {
                self.totals.bridges_refused += 1;
                log::info!(
                    "tracking: no bridge at t={t_ns} ns (last frame lost, elsewhere, or unmatched)"
                );
            }
        }
        Ok(bridge)
    }

    /// Totals of bridges, new map segments and relocalisations since the start.
    pub fn tracking_totals(&self) -> TrackingTotals {
        self.totals
    }

    /// Median depth in metres, along the rectified left camera's optical axis, of the map
    /// points the last [`System::track`] call measured its pose with (its inliers; after a
    /// bootstrap or re-initialisation, the points its keyframe created). `None` before the
    /// first frame, after a lost frame or when no such point lies in front of the camera.
    /// [`System::predict`] leaves it unchanged. The front-end warps the next frame's events
    /// through a plane at this depth (`[fusion] warp_depth = "tracked"`).
    pub fn tracked_depth(&self) -> Option<f64> {
        self.tracked_depth
    }

    /// Tracks one stereo frame; inserts a keyframe and runs (or queues) mapping when needed.
    pub fn track(
        &mut self,
        t_ns: i64,
        left: FrameFeatures,
        right: FrameFeatures,
    ) -> Result<TrackResult> {
        if self.closed {
            return Err(Error::invalid(
                "system",
                "a running system",
                "one shut down",
            ));
        }
        let start = Instant::now();
        let frame = self.stereo_frame(t_ns, left, right)?;
        let shared = Arc::clone(&self.shared);
        let c = &shared.config;
        let ctx = TrackContext {
            calib: &shared.calib,
            cfg: &c.tracking,
            tri: &c.triangulation,
        };
        // A quiet window's event images show sensor noise: such images (mode `events`, or
        // fusion's DVS-biased rendering) never start a map or a map segment.
        let noise_only = frame.quiet && (c.fusion.mode == FusionMode::Events || frame.dvs_biased);
        let outcome = if self.state.reference.is_none() {
            if noise_only {
                log::info!("tracking: t={t_ns} ns: quiet event window; not initialised on noise");
                self.rest_before_map.push(t_ns);
                self.lose(t_ns, &Se3::identity())
            } else {
                let mut map = write_lock(&shared.map);
                let outcome = bootstrap(&mut map, &mut self.state, &frame, &ctx);
                // The camera sat still until the first map: those frames are held at its
                // pose. A frame with structure that did not initialise may have moved.
                let rest = std::mem::take(&mut self.rest_before_map);
                if let Some(kf) = outcome.keyframe {
                    self.totals.held += hold_before(&mut map, kf, &rest) as u64;
                }
                outcome
            }
        } else {
            // After a loss the motion model is stale (the last pose is frames old): picking
            // the track up again from it needs the evidence a relocalisation needs, and the
            // velocity restarts (the step to the last pose spans the lost frames).
            let reacquired = self.state.lost;
            let (tracked, previous, predicted, corrections, reference) = {
                let map = read_lock(&shared.map);
                let (previous, predicted) = constant_velocity_prediction(&map, &self.state);
                let mut tracked = shared.time("track_local_map", || {
                    track_local_map(&map, &self.state, &frame, &ctx, predicted)
                });
                if let Some(t) = tracked.as_ref() {
                    log::debug!(
                        "tracking: frame at t={t_ns} ns: {} inliers, centre {:.1} mm from the \
                         motion model's prediction",
                        t.inliers,
                        1e3 * distance_from_prediction(t, &predicted)
                    );
                }
                // A stale motion model (after a loss) predicts nothing to compare with.
                if previous.is_some() && !reacquired {
                    if let Some(jump) = tracked
                        .as_ref()
                        .and_then(|t| implausible_jump(&map, t, &predicted, ctx.cfg.max_jump_ratio))
                    {
                        self.totals.implausible += 1;
                        log::info!(
                            "tracking: pose at t={t_ns} ns rejected: {:.3} m from the motion \
                             model's prediction, {:.2} × the median depth {:.2} m of its {} \
                             inliers",
                            jump.distance_m,
                            jump.distance_m / jump.depth_m,
                            jump.depth_m,
                            jump.inliers
                        );
                        tracked = None;
                    }
                }
                let reference = reference_pose(&map, &self.state);
                (tracked, previous, predicted, map.corrections, reference)
            };
            let needed = if reacquired {
                ctx.cfg.min_tracked.max(c.loop_closing.min_inliers)
            } else {
                ctx.cfg.min_tracked
            };
            match tracked.filter(|t| t.inliers >= needed as usize) {
                Some(mut t) => {
                    let mut map = write_lock(&shared.map);
                    let mut previous = previous;
                    // The mapping threads may have moved the map between the tracking above
                    // and this commit. A loop correction: track again against the corrected
                    // map, under the write lock. A bundle adjustment (or a failed re-track):
                    // the pose moves with the reference keyframe.
                    if let Some((retracked, last)) = retrack_after_correction(
                        &map,
                        &self.state,
                        &frame,
                        &ctx,
                        corrections,
                        needed as usize,
                    ) {
                        t = retracked;
                        previous = last;
                    } else if let Some(moved) = reference_motion(&map, &self.state, reference) {
                        t.cam_from_world = t.cam_from_world * moved.inverse();
                        previous = last_pose(&map, &self.state);
                    }
                    if reacquired {
                        self.totals.relocalisations += 1;
                        log::info!(
                            "tracking: tracking regained at t={t_ns} ns from the motion model ({} inliers)",
                            t.inliers
                        );
                    }
                    self.tracked_depth = median_point_depth(
                        &map,
                        &t.cam_from_world,
                        t.matches.iter().flatten().copied(),
                    );
                    // As a relocalisation (`reacquired`): keyframe, velocity from rest.
                    commit_tracked(
                        &mut map,
                        &mut self.state,
                        &frame,
                        &ctx,
                        t,
                        previous,
                        reacquired,
                    )
                }
                // A quiet window (the camera likely at rest): its event images show sensor
                // noise, which neither relocalises nor makes a map segment worth keeping.
                None if frame.quiet && (!self.state.lost || noise_only) => {
                    let mut map = write_lock(&shared.map);
                    match hold_pose(&mut map, &mut self.state, t_ns) {
                        Some(held) => {
                            self.totals.held += 1;
                            held
                        }
                        None => self.lose(t_ns, &predicted),
                    }
                }
                None => match shared.time("relocalise", || self.relocalise(&frame, &ctx)) {
                    Some((t, reference)) => {
                        self.totals.relocalisations += 1;
                        let mut map = write_lock(&shared.map);
                        self.tracked_depth = median_point_depth(
                            &map,
                            &t.cam_from_world,
                            t.matches.iter().flatten().copied(),
                        );
                        // The step must be plausible on its own, from the last pose at rest:
                        // checked against the prediction, a step could grow by the check's
                        // bound at every relocalisation of a chain.
                        let step_from = if ctx.cfg.relocalised_velocity {
                            consecutive_pose(&map, &self.state, reference).filter(|last| {
                                let at_rest = last.inverse();
                                implausible_jump(&map, &t, &at_rest, ctx.cfg.max_jump_ratio)
                                    .is_none()
                            })
                        } else {
                            None
                        };
                        let cam_from_world = t.cam_from_world;
                        self.state.reference = Some(reference);
                        let outcome =
                            commit_tracked(&mut map, &mut self.state, &frame, &ctx, t, None, true);
                        if let Some(previous) = step_from {
                            self.state.velocity = cam_from_world * previous;
                            self.state.velocity_relocalised = true;
                        }
                        outcome
                    }
                    None => {
                        let restarted = if ctx.cfg.reinitialise && previous.is_some() {
                            let mut map = write_lock(&shared.map);
                            reinitialise(
                                &mut map,
                                &mut self.state,
                                &frame,
                                &ctx,
                                predicted.inverse(),
                            )
                        } else {
                            None
                        };
                        if restarted.is_some() {
                            self.totals.segments += 1;
                        }
                        restarted.unwrap_or_else(|| self.lose(t_ns, &predicted))
                    }
                },
            }
        };
        {
            let mut t = lock(&shared.timings);
            let e = t.entry("track").or_default();
            let s = start.elapsed().as_secs_f64();
            e.count += 1;
            e.total_s += s;
            e.max_s = e.max_s.max(s);
        }
        match outcome.state {
            TrackState::Lost => self.tracked_depth = None,
            // Bootstrapped or re-initialised: the points the new keyframe created.
            TrackState::Initialised => {
                self.tracked_depth = outcome.keyframe.and_then(|kf| {
                    let map = read_lock(&shared.map);
                    let k = map.keyframes.get(&kf)?;
                    let ids: Vec<u64> = k.points.iter().flatten().copied().collect();
                    median_point_depth(&map, &k.world_from_cam.inverse(), ids)
                });
            }
            _ => {}
        }
        if let Some(kf) = outcome.keyframe {
            self.after_keyframe(kf);
            if frame.dvs_biased {
                // Such keyframes come at nearly every frame, and each would interrupt the
                // adjustment of the last before the next frame tracks against it: the
                // threaded back-end maps it first, as the synchronous one does.
                self.wait_for_mapping();
            }
        }
        Ok(TrackResult {
            t_ns,
            world_from_cam: outcome.world_from_cam,
            state: outcome.state,
            inliers: outcome.inliers,
            keyframe: outcome.keyframe.is_some(),
        })
    }

    /// Moves the pose on to `t_ns` with the constant-velocity model instead of tracking a
    /// frame whose images carry no usable measurement (e.g. an event window flooded by a
    /// lighting change; see [`super::tracking::predict_only`]): the pose is recorded in the
    /// trajectory with state `Predicted`, and neither the map nor the motion model changes,
    /// so the next frame is tracked against the map from an extrapolated prediction. Before
    /// initialisation, after a lost frame or without a reference keyframe there is nothing
    /// to extrapolate from: the result is `Lost` at the last pose (not recorded, the tracker
    /// state unchanged).
    pub fn predict(&mut self, t_ns: i64) -> Result<TrackResult> {
        if self.closed {
            return Err(Error::invalid(
                "system",
                "a running system",
                "one shut down",
            ));
        }
        let shared = Arc::clone(&self.shared);
        let outcome = {
            let mut map = write_lock(&shared.map);
            let frames = shared.config.tracking.predict_velocity_frames;
            predict_only(&mut map, &mut self.state, t_ns, frames)
        };
        Ok(match outcome {
            Some(o) => {
                self.totals.predicted += 1;
                TrackResult {
                    t_ns,
                    world_from_cam: o.world_from_cam,
                    state: o.state,
                    inliers: 0,
                    keyframe: false,
                }
            }
            None => {
                let world_from_cam = {
                    let map = read_lock(&shared.map);
                    last_pose(&map, &self.state).unwrap_or_else(Se3::identity)
                };
                TrackResult {
                    t_ns,
                    world_from_cam,
                    state: TrackState::Lost,
                    inliers: 0,
                    keyframe: false,
                }
            }
        })
    }

    /// Marks the tracker lost at `t_ns` (logged when the loss starts): the frame's outcome,
    /// at the motion model's prediction `predicted` (`cam_from_world`).
    fn lose(&mut self, t_ns: i64, predicted: &Se3) -> super::tracking::FrameOutcome {
        if !self.state.lost {
            log::info!("tracking: lost at t={t_ns} ns");
        }
        self.state.lost = true;
        super::tracking::FrameOutcome {
            state: TrackState::Lost,
            world_from_cam: predicted.inverse(),
            inliers: 0,
            keyframe: None,
        }
    }

    /// PnP verification against candidate keyframes, then tracking against the matched
    /// keyframe's local map from the PnP pose. The candidates: the place query's with the
    /// frame's embedding, then, when the previous frame was tracked, its reference keyframe
    /// (`[tracking] relocalise_reference`).
    fn relocalise(
        &self,
        frame: &StereoFrame,
        ctx: &TrackContext,
    ) -> Option<(super::tracking::Tracked, u64)> {
        let cfg = &self.shared.config.loop_closing;
        let e = crate::place::embedding(frame.descriptors)?;
        let mut candidates: Vec<(u64, Option<f32>)> = lock(&self.shared.place)
            .query(&e, cfg.candidates as usize, cfg.min_score as f32, |_| false)
            .into_iter()
            .map(|(c, score)| (c, Some(score)))
            .collect();
        let map = read_lock(&self.shared.map);
        // Before the frame starts a new map segment: the motion model missed, but the
        // camera is most likely still near the last tracked frame, so its reference keyframe
        // is tried whatever its place score (the query need not rank it among its few
        // candidates, e.g. when a fast turn blurs the event images). It comes last: a
        // candidate the query found is an older, better-anchored part of the map.
        if let Some(r) = self.state.reference.filter(|r| {
            ctx.cfg.relocalise_reference
                && !self.state.lost
                && map.keyframes.contains_key(r)
                && candidates.iter().all(|(c, _)| c != r)
        }) {
            candidates.push((r, None));
        }
        for (c, score) in candidates {
            let v = verify(
                &map,
                c,
                &frame.keypoints,
                frame.descriptors,
                ctx.calib,
                ctx.cfg,
                cfg,
            );
            let m = match v {
                Ok(Some(m)) => m,
                Ok(None) => continue,
                Err(e) => {
                    log::debug!("relocalisation: candidate {c}: {e}");
                    continue;
                }
            };
            let mut state = self.state.clone();
            state.reference = Some(c);
            let tracked = track_local_map(&map, &state, frame, ctx, m.cam_from_world)
                .filter(|t| t.inliers >= ctx.cfg.min_tracked as usize);
            if let Some(t) = tracked {
                let how = match score {
                    Some(score) => format!("score {score:.3}"),
                    None => "the reference keyframe".to_owned(),
                };
                log::info!(
                    "tracking: relocalised at t={} ns against keyframe {c} ({how}, {} inliers)",
                    frame.t_ns,
                    t.inliers
                );
                return Some((t, c));
            }
        }
        None
    }

    /// With the mapping thread: waits until it has finished every keyframe handed to it
    /// (or stopped). Without: returns at once (mapping ran inline).
    fn wait_for_mapping(&self) {
        if self.mapping_tx.is_none() {
            return;
        }
        let shared = &self.shared;
        shared.time("mapping_wait", || {
            let (done, ready) = &shared.mapped;
            let mut mapped = lock(done);
            while *mapped < self.sent && !shared.shutdown.load(Ordering::Acquire) {
                mapped = ready
                    .wait_timeout(mapped, std::time::Duration::from_millis(100))
                    .map(|(g, _)| g)
                    .unwrap_or_else(|e| e.into_inner().0);
            }
        });
    }

    fn after_keyframe(&mut self, kf: u64) {
        match &self.mapping_tx {
            Some(tx) => {
                self.shared.interrupt.store(true, Ordering::Release);
                if tx.send(kf).is_err() {
                    log::warn!("mapping thread gone; keyframe {kf} not optimised");
                } else {
                    self.sent += 1;
                }
            }
            None => {
                self.shared.map_keyframe(kf, None);
                self.shared.close_loops(kf);
            }
        }
    }

    /// Bundle adjustment of the whole map ([`super::global_bundle_adjustment`]) with
    /// `iterations` Levenberg–Marquardt iterations, for after the last frame (e.g. after
    /// [`System::shutdown`]; while the mapping threads still run, a loop correction made
    /// meanwhile discards the result). Timed as stage `global_ba`.
    pub fn refine_map(&self, iterations: u32) -> Result<super::MappingReport> {
        let shared = &self.shared;
        let c = &shared.config;
        shared.time("global_ba", || {
            super::global_bundle_adjustment(
                &shared.map,
                &shared.calib,
                &c.tracking,
                &c.triangulation,
                iterations,
                None,
            )
        })
    }

    /// Timestamps and `world_from_cam` of every tracked frame, in order; predicted frames
    /// between two measured ones are interpolated between them ([`Map::trajectory_poses`]).
    /// With `[tracking] smoothing_q` > 0 the camera centres are those of the trajectory
    /// smoother ([`Map::smoothed_trajectory_poses`]); [`System::tracked_trajectory`] gives
    /// them as tracked.
    pub fn trajectory(&self) -> Vec<(i64, Se3)> {
        let q = self.shared.config.tracking.smoothing_q;
        let map = read_lock(&self.shared.map);
        if q > 0.0 {
            match map.smoothed_trajectory_poses(q) {
                Ok(poses) => return poses,
                Err(e) => log::warn!("trajectory smoother failed ({e}); writing the tracked poses"),
            }
        }
        map.trajectory_poses()
    }

    /// [`System::trajectory`] without the smoother: every frame's centre as tracked.
    pub fn tracked_trajectory(&self) -> Vec<(i64, Se3)> {
        read_lock(&self.shared.map).trajectory_poses()
    }

    /// Timestamps and `world_from_cam` of the keyframes, by id; a bridge keyframe taken at
    /// the same instant as the keyframe before it (same frame, same pose) is listed once.
    pub fn keyframe_trajectory(&self) -> Vec<(i64, Se3)> {
        let map = read_lock(&self.shared.map);
        let mut out: Vec<(i64, Se3)> = Vec::with_capacity(map.keyframes.len());
        for k in map.keyframes.values() {
            if out.last().is_some_and(|l| l.0 == k.t_ns) {
                continue;
            }
            out.push((k.t_ns, k.world_from_cam));
        }
        out
    }

    /// Map point positions, world frame, metres, by id.
    pub fn map_points(&self) -> Vec<[f64; 3]> {
        let map = read_lock(&self.shared.map);
        map.points
            .values()
            .map(|p| [p.position.x, p.position.y, p.position.z])
            .collect()
    }

    /// Accepted loop closures as (query keyframe timestamp, matched keyframe timestamp), ns.
    pub fn loop_closures(&self) -> Vec<(i64, i64)> {
        let map = read_lock(&self.shared.map);
        map.loops
            .iter()
            .filter_map(|(q, m)| Some((map.keyframes.get(q)?.t_ns, map.keyframes.get(m)?.t_ns)))
            .collect()
    }

    /// Per-stage wall-time statistics.
    pub fn timing(&self) -> BTreeMap<String, StageStats> {
        lock(&self.shared.timings)
            .iter()
            .map(|(k, v)| (k.to_string(), *v))
            .collect()
    }

    /// Totals of the fusion of duplicate points and of re-finding, since the start.
    pub fn fusion_totals(&self) -> FusionTotals {
        *lock(&self.shared.fusion)
    }

    /// Keyframes removed as redundant by the mapping thread since the start.
    pub fn culled_keyframes(&self) -> u64 {
        self.shared.culled_keyframes.load(Ordering::Relaxed)
    }

    /// The place database's keyframe ids, ascending (for consistency checks in tests).
    pub fn place_ids(&self) -> Vec<u64> {
        lock(&self.shared.place).ids()
    }

    /// The tracker's state (last frame, velocity, reference keyframe).
    pub fn tracker_state(&self) -> &TrackerState {
        &self.state
    }

    /// A read view of the map (for tests and tools).
    pub fn with_map<T>(&self, f: impl FnOnce(&Map) -> T) -> T {
        f(&read_lock(&self.shared.map))
    }

    /// Writes the map and the tracker state to `path` (atomically: a temporary file renamed).
    pub fn save_map(&self, path: &Path) -> Result<()> {
        let map = read_lock(&self.shared.map);
        persist::save(path, &self.shared.calib, self.descriptor, &map, &self.state)
    }

    /// Replaces the map and the tracker state with those saved in `path`; the calibration
    /// must be the one the map was saved with.
    pub fn load_map(&mut self, path: &Path) -> Result<()> {
        let (calib, descriptor, map, state) = persist::load(path)?;
        if calib != self.shared.calib {
            return Err(Error::invalid(
                format!("calibration of {}", path.display()),
                format!("{:?} (this system's)", self.shared.calib),
                format!("{calib:?}"),
            ));
        }
        let mut db = PlaceDatabase::new();
        for k in map.keyframes.values() {
            if let Some(e) = crate::place::embedding(k.descriptors.view()) {
                db.add(k.id, e)?;
            }
        }
        *lock(&self.shared.place) = db;
        *write_lock(&self.shared.map) = map;
        self.state = state;
        self.descriptor = descriptor;
        // Frames seen before the loaded map are not at its pose.
        self.rest_before_map.clear();
        Ok(())
    }

    /// Stops the worker threads: queued keyframes are dropped, a running bundle adjustment is
    /// interrupted; returns when they have exited. Tracking afterwards is an error.
    pub fn shutdown(&mut self) {
        if self.closed {
            return;
        }
        self.closed = true;
        self.shared.shutdown.store(true, Ordering::Release);
        self.shared.interrupt.store(true, Ordering::Release);
        self.mapping_tx = None;
        for w in self.workers.drain(..) {
            if w.join().is_err() {
                log::error!("a SLAM worker thread panicked");
            }
        }
    }
}

impl Drop for System {
    fn drop(&mut self) {
        self.shutdown();
    }
}
