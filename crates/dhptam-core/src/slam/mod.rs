//! The SLAM back-end (SPEC-NOTES §5, issue 7): stereo bootstrapping, tracking against a local
//! map, local mapping with bundle adjustment, and loop closing, over a shared map.
//!
//! Input per frame: keypoints and descriptors of the RECTIFIED left and right images (pinhole,
//! no distortion, the right camera at +baseline along the left x axis). Poses are
//! `world_from_cam` of the rectified left camera; the world frame is the first keyframe's.
//!
//! [`System`] runs tracking on the caller's thread and, in threaded mode, local mapping and
//! loop closing on their own threads, joined by bounded channels; in synchronous mode they
//! run inline after each keyframe and every run gives the same results.

pub mod loop_closing;
pub mod map;
pub mod mapping;
pub mod persist;
pub mod smoothing;
pub mod synthetic;
pub mod system;
pub mod tracking;

use std::sync::{Mutex, MutexGuard, RwLock, RwLockReadGuard, RwLockWriteGuard};

use crate::error::{ensure_finite, Error, Result};
use crate::geometry::camera::Pinhole;
use crate::geometry::Se3;
use crate::solver::StereoIntrinsics;

pub use map::{FrameRecord, Keyframe, Map, MapPoint, Redirect};
pub use mapping::{cull_keyframes, keyframes_at_place, redundancy, replaced_horizon, CullReport};
pub use mapping::{
    fuse_and_refind, global_bundle_adjustment, local_mapping, FusionReport, MappingReport,
};
pub use system::{
    DisparityCorrection, FrameFeatures, FusionTotals, StageStats, System, TrackingTotals,
};
pub use tracking::Bridge;

/// Calibration of the rectified stereo pair: left intrinsics, baseline and image size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StereoCalibration {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Distance from the left to the right camera centre along the left x axis, metres.
    pub baseline_m: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

impl StereoCalibration {
    /// Checks and builds a calibration: positive finite focal lengths and baseline, finite
    /// principal point, non-zero image size.
    pub fn new(
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        baseline_m: f64,
        width: u32,
        height: u32,
    ) -> Result<Self> {
        ensure_finite("calibration", &[fx, fy, cx, cy, baseline_m])?;
        for (what, v) in [
            ("calibration.fx", fx),
            ("calibration.fy", fy),
            ("calibration.baseline_m", baseline_m),
        ] {
            if v <= 0.0 {
                return Err(Error::invalid(what, "a positive number", v));
            }
        }
        if width == 0 || height == 0 {
            return Err(Error::invalid(
                "calibration.width/height",
                "a non-empty image size",
                format!("{width}x{height}"),
            ));
        }
        Ok(Self {
            fx,
            fy,
            cx,
            cy,
            baseline_m,
            width,
            height,
        })
    }

    /// The intrinsics as the solver takes them.
    pub fn intrinsics(&self) -> StereoIntrinsics {
        StereoIntrinsics {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            baseline: self.baseline_m,
        }
    }

    /// The rectified left pinhole.
    pub fn pinhole(&self) -> Pinhole {
        Pinhole {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
        }
    }
}

/// Tracking state of a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrackState {
    /// The frame bootstrapped the map (first keyframe).
    Initialised,
    /// Tracked against the local map.
    Ok,
    /// Not tracked: too few matches (or not enough stereo points to initialise).
    Lost,
    /// Recovered from loss by relocalisation.
    Relocalised,
    /// Not measured: the pose was moved on with the motion model (`System::predict`, e.g.
    /// an event window flooded by a lighting change); the map is unchanged.
    Predicted,
    /// Not measured: a quiet frame (few events against the usual count, so the camera is
    /// likely at rest) that could not be tracked kept the last pose, and the motion model
    /// restarts from rest; the map is unchanged (no relocalisation, no new map segment).
    Held,
}

impl TrackState {
    /// `"initialised"`, `"ok"`, `"lost"`, `"relocalised"`, `"predicted"` or `"held"`.
    pub fn as_str(self) -> &'static str {
        match self {
            TrackState::Initialised => "initialised",
            TrackState::Ok => "ok",
            TrackState::Lost => "lost",
            TrackState::Relocalised => "relocalised",
            TrackState::Predicted => "predicted",
            TrackState::Held => "held",
        }
    }
}

/// The result of tracking one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackResult {
    /// Timestamp, nanoseconds.
    pub t_ns: i64,
    /// `world_from_cam` of the rectified left camera (a lost frame: the prediction).
    pub world_from_cam: Se3,
    /// Tracking state.
    pub state: TrackState,
    /// Inlier map points (for the first frame: points created).
    pub inliers: usize,
    /// Whether the frame became a keyframe.
    pub keyframe: bool,
}

/// Read access that survives a panicked writer (the map stays usable for saving/reporting).
pub(crate) fn read_lock<T>(lock: &RwLock<T>) -> RwLockReadGuard<'_, T> {
    lock.read().unwrap_or_else(|e| e.into_inner())
}

/// Write access that survives a panicked writer.
pub(crate) fn write_lock<T>(lock: &RwLock<T>) -> RwLockWriteGuard<'_, T> {
    lock.write().unwrap_or_else(|e| e.into_inner())
}

/// Mutex access that survives a panicked holder.
pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}
