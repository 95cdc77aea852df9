//! Typed configuration: one struct per stage, loaded from TOML.
//!
//! Every field has its default and its documentation in one place, the [`config_section!`]
//! invocation below; the same text is printed by `dhptam config --defaults` through
//! [`Config::defaults_toml`]. Unknown keys are rejected with the key named, values are checked
//! by each section's `validate`, and a resolved configuration round-trips through
//! [`Config::to_toml`].

use std::fmt::Write as _;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::events::PolarityMode;
use crate::fusion::FusionMode;

/// What every configuration section provides to [`Config`].
trait Section {
    /// Writes the fields as TOML `key = value` lines, each preceded by its documentation.
    fn write_commented(&self, out: &mut String);
    /// Checks every field against its documented range, naming the key on failure.
    fn validate(&self) -> Result<()>;
}

/// Declares a configuration section: the struct, its `Default`, and a writer of commented TOML
/// built from the fields' doc comments, so the documentation cannot drift from the defaults.
macro_rules! config_section {
    (
        $(#[doc = $sdoc:literal])*
        $name:ident {
            $( $(#[doc = $doc:literal])* $field:ident : $ty:ty = $default:expr ),* $(,)?
        }
    ) => {
        $(#[doc = $sdoc])*
        #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
        #[serde(deny_unknown_fields, default)]
        pub struct $name {
            $( $(#[doc = $doc])* pub $field: $ty, )*
        }

        impl Default for $name {
            fn default() -> Self {
                Self { $( $field: $default, )* }
            }
        }

        impl Section for $name {
            fn write_commented(&self, out: &mut String) {
                $(
                    $( let _ = writeln!(out, "#{}", $doc); )*
                    let value = toml::Value::try_from(&self.$field)
                        .map(|v| v.to_string())
                        .unwrap_or_else(|e| format!("\"<unserialisable: {e}>\""));
                    let _ = writeln!(out, "{} = {}\n", stringify!($field), value);
                )*
            }

            fn validate(&self) -> Result<()> {
                self.check()
            }
        }
    };
}

/// Severity threshold for messages from the core.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LogLevel {
    /// Only errors.
    Error,
    /// Errors and warnings.
    Warn,
    /// Progress information (the default).
    Info,
    /// Per-stage details.
    Debug,
    /// Everything, including per-frame internals.
    Trace,
}

impl LogLevel {
    /// The level's name as written in TOML and accepted by `DHPTAM_LOG`.
    pub fn as_str(self) -> &'static str {
        match self {
            LogLevel::Error => "error",
            LogLevel::Warn => "warn",
            LogLevel::Info => "info",
            LogLevel::Debug => "debug",
            LogLevel::Trace => "trace",
        }
    }
}

config_section! {
    /// Logging.
    LogConfig {
        /// Threshold for messages from dhptam: "error", "warn", "info", "debug" or "trace".
        /// The environment variable DHPTAM_LOG, when set, takes precedence.
        level: LogLevel = LogLevel::Info,
    }
}

config_section! {
    /// Stereo rectification of the frame-camera pair (and of the event-camera pair).
    RectificationConfig {
        /// How much of the source images the rectified view keeps, in [0, 1]: 0 crops to a
        /// view where every pixel has a source pixel, 1 keeps every source pixel (with black
        /// borders); OpenCV calls this alpha.
        balance: f64 = 0.0,
        /// Width of the rectified images in pixels; 0 uses the left camera's width.
        width: u32 = 0,
        /// Height of the rectified images in pixels; 0 uses the left camera's height.
        height: u32 = 0,
    }
}

config_section! {
    /// Triangulation of stereo and multi-view correspondences.
    TriangulationConfig {
        /// Points closer than this to any observing camera are rejected, metres.
        min_depth_m: f64 = 0.1,
        /// Points farther than this from the first observing camera are rejected, metres.
        max_depth_m: f64 = 40.0,
        /// Minimum angle between the observing rays, degrees; smaller parallax gives depth too
        /// uncertain to map.
        min_parallax_deg: f64 = 0.5,
        /// Maximum reprojection error after refinement in any view, pixels of the rectified
        /// (pinhole) camera.
        max_reprojection_px: f64 = 2.0,
        /// Gauss–Newton iterations refining the linear (DLT) estimate.
        refine_iterations: u32 = 5,
    }
}

config_section! {
    /// The events+frames simulator (`dhptam simulate`).
    SimConfig {
        /// Frame rate of the stereo frame cameras, Hz.
        fps: f64 = 20.0,
        /// Renders averaged over each frame's exposure (motion blur).
        blur_samples: u32 = 3,
        /// Nominal ON contrast threshold C+ (change of log intensity).
        contrast_on: f64 = 0.2,
        /// Nominal OFF contrast threshold C- (change of log intensity, positive).
        contrast_off: f64 = 0.2,
        /// Standard deviation of the per-pixel thresholds around C+/C- (mismatch).
        contrast_sigma: f64 = 0.03,
        /// Refractory period of an event pixel, microseconds.
        refractory_us: f64 = 100.0,
        /// Background-activity rate of a pixel at the reference intensity, Hz; it grows as
        /// sqrt(reference / intensity) in darker pixels (capped at 30x).
        noise_rate_hz: f64 = 0.1,
        /// Intensity (illumination x reflectance) at which the noise rate is noise_rate_hz.
        noise_reference_intensity: f64 = 0.5,
        /// Offset added to the intensity before its logarithm (the pixel's dark level).
        log_eps: f64 = 0.0002,
        /// Largest per-pixel log-intensity change allowed between two event-camera renders.
        max_log_step: f64 = 1.0,
        /// Shortest interval between event-camera renders, microseconds.
        min_render_step_us: f64 = 2000.0,
        /// Longest interval between event-camera renders, microseconds.
        max_render_step_us: f64 = 10000.0,
        /// Shortest frame exposure, milliseconds.
        min_exposure_ms: f64 = 1.0,
        /// Longest frame exposure, milliseconds.
        max_exposure_ms: f64 = 20.0,
        /// Exposure of the first frame, milliseconds.
        initial_exposure_ms: f64 = 4.0,
        /// Mean 8-bit level the auto-exposure aims at.
        ae_target_mean: f64 = 110.0,
        /// Fraction of the (log) exposure correction applied per frame, in (0, 1]; lower lags more.
        ae_rate: f64 = 0.3,
        /// Photo-electrons per second per unit intensity.
        sensitivity_e_per_s: f64 = 1500000.0,
        /// Full-well capacity in electrons (maps to 255).
        full_well_e: f64 = 10000.0,
        /// Read noise, electrons RMS.
        read_noise_e: f64 = 5.0,
    }
}

config_section! {
    /// Event representations (E3CT, SPEC-NOTES §3 and docs/E3CT.md).
    EventsConfig {
        /// Sharpness α of the E3CT decay kernel exp(−α((a − η/2)/(η/6))²), a the event's age
        /// at the end of its window in ms; the paper uses 0.5.
        alpha: f64 = 0.5,
        /// Span η of the decay kernel in milliseconds (peak at age η/2); the paper uses 30.
        eta_ms: f64 = 30.0,
        /// Temporal channels of the E3CT (3 in the paper: a synthetic RGB image), 2 to 64.
        channels: u32 = 3,
        /// "both": ON and OFF events share the channels (the paper); "split": ON events fill
        /// the first `channels` channels and OFF events the next ones (ablations).
        polarity: PolarityMode = PolarityMode::Both,
        /// Each channel is divided by this percentile of its non-zero values (pooled over the
        /// left and right tensors of a stereo window) and clipped to [0, 1]; in (0, 100].
        normalise_percentile: f64 = 99.0,
        /// Hot pixels (raw pixels firing on their own; `events::hot`, docs/E3CT.md): a pixel's
        /// events are dropped before any representation while it fires at least
        /// `hot_pixel_min_rate_hz` and this many times more than each of its 8 neighbours;
        /// 0 turns the detector off, otherwise > 1.
        hot_pixel_ratio: f64 = 4.0,
        /// The least event rate of a hot pixel, Hz.
        hot_pixel_min_rate_hz: f64 = 50.0,
        /// Time constant of the per-pixel event rates the detector compares, seconds.
        hot_pixel_time_s: f64 = 1.0,
    }
}

config_section! {
    /// Spatial hybridisation and fusion of events and frames (SPEC-NOTES §4).
    FusionConfig {
        /// "fusion" (frames and events with the online β), "frames" (β = 0) or "events" (β = 1).
        mode: FusionMode = FusionMode::Fusion,
        /// Upper bound on β (the paper's example caps it at 0.3); 1 leaves it uncapped.
        beta_max: f64 = 1.0,
        /// Upper bound on β of APS-biased frames only (well-exposed frames with features),
        /// the paper's example cap of 0.3 applied where it does not undo the mode: DVS-biased
        /// frames keep their β ≥ 1/2. 1 leaves min(r, 1 − r) uncapped (docs/FUSION.md).
        aps_beta_max: f64 = 0.3,
        /// Lower bound on β of DVS-biased frames (under- or over-exposed frames, or frames
        /// with too few features). The paper's max(r, 1 − r) is at least 1/2, so any value up
        /// to 0.5 leaves it as it is; 1 renders such frames from their events alone.
        dvs_beta_min: f64 = 0.5,
        /// Pixels at or below this 8-bit value count as under-exposed.
        dark_level: f64 = 20.0,
        /// Pixels at or above this 8-bit value count as over-exposed.
        bright_level: f64 = 235.0,
        /// A frame with more than this fraction of under/over-exposed pixels fails the
        /// exposure test: it is stretched when its signal allows (`recover_exposure`), and
        /// its β is chosen against `dvs_clipped_fraction`.
        max_clipped_fraction: f64 = 0.5,
        /// A frame, stretched or not, with more than this fraction of under/over-exposed
        /// pixels switches the fusion to the DVS-biased mode. Raised to 0.95 (stretched
        /// saturated frames kept APS-biased) it helped the HDR-lit real trajectories and cost
        /// the HDR demo (docs/BENCHMARKS.md, "HDR lighting on the real trajectories: what the
        /// event cameras' offset explains").
        dvs_clipped_fraction: f64 = 0.5,
        /// A frame on which fewer features than this are detected switches the fusion to the
        /// DVS-biased mode, when the caller counts them (`Frontend(feature_counter=...)`;
        /// `dhptam run` counts none: docs/BENCHMARKS.md, "Checked, no change: the paper's
        /// feature-count criterion in runs"). Also the least features on each image of a flood
        /// frame leaving a DVS-biased segment for it to be tracked on its frames (`flood_frames`).
        min_features: u32 = 100,
        /// A frame that fails the exposure test (`max_clipped_fraction`) has its grey levels
        /// between the 1st and 99th percentile stretched over 0–255 before β is chosen and
        /// features are extracted, in modes `fusion` and `frames`, when that range holds at
        /// least `recover_min_snr` noise deviations (`fusion::exposure`, docs/FUSION.md).
        recover_exposure: bool = true,
        /// Least range / noise ratio of a failed frame for it to be stretched; ≥ 0.
        recover_min_snr: f64 = 20.0,
        /// Depth in metres of the plane the event pixels are warped through; 0 warps at
        /// infinity (rotation only).
        plane_depth_m: f64 = 0.0,
        /// Constant pixel offset δP_align (x, y) added after the event→frame warp.
        align_px: [f64; 2] = [0.0, 0.0],
        /// Bridge keyframes at switches between the APS- and DVS-biased modes (issue 8): the
        /// front-end also blends the frame with good raw data (the last APS-biased one) with
        /// the neighbouring frame's β, and the tracker inserts one keyframe holding the
        /// features of both images at that frame's tracked pose (`System::bridge`), so the
        /// map stays one piece across the switch. Off: a switch that cannot be tracked
        /// starts a new map segment (`[tracking] reinitialise`).
        bridge: bool = true,
        /// Illumination floods (issue 8): an event window with at least `flood_polarity` of its
        /// events of one polarity, and more events of that polarity than `flood_ratio` times
        /// its usual count (half the median event count of the previous `flood_history`
        /// windows: scene motion gives both polarities alike), is a global lighting change
        /// (every pixel fires as the light ramps), not scene motion; its E3CT shows the
        /// sensor's threshold pattern, not edges. 0 turns the detection off.
        flood_ratio: f64 = 2.5,
        /// Share of one polarity (ON or OFF) in a window, in (0.5, 1], from which a window
        /// whose dominant polarity bursts past `flood_ratio` is a flood (scene motion gives
        /// both polarities).
        flood_polarity: f64 = 0.8,
        /// Previous windows whose median event count a window is compared with.
        flood_history: u32 = 10,
        /// Flood frames are not tracked: the tracker moves the pose on with its motion model
        /// (`System::predict`: no matching, no keyframe, no new map segment) and tracks the
        /// next clean frame against the map; bridges at a fusion-mode switch span the flood.
        /// Off: flood frames are tracked like any other (still flagged in `frames.csv`).
        flood_predict: bool = true,
        /// With `flood_predict`, leaving a DVS-biased segment across a flood (the last clean
        /// frame was DVS-biased): a flood frame whose two frames pass the exposure test is
        /// rendered from its frames alone (β = 0, bias `frames`: its events are the flood's)
        /// and tracked when at least `min_features` features are found on each, otherwise
        /// predicted like any flood frame; the first clean frame after the flood, when its
        /// frames pass, is rendered from them alone too. Off: every flood frame is predicted
        /// and the first clean frame blended as usual.
        flood_frames: bool = true,
        /// Quiet event windows (issue 8): a window with fewer events than `quiet_ratio` times
        /// its usual count (the median event count of the last `flood_history` windows that
        /// were not quiet) is flagged quiet: the camera has likely stopped, and the event
        /// images show sensor noise, whose "features" still stereo-match by chance. A quiet
        /// frame is tracked as usual; when it cannot be, its pose is held at rest (state
        /// `held`: no relocalisation, no new map segment of noise points), so the camera
        /// moving again is tracked against the same map. On the simulator's sequences the
        /// windows at rest held 1.1 % of the usual count or less in normal light, 3.1 % after
        /// a slow stop (whose last moving windows lower the median) and 5.9 % in the 40×
        /// darker room, where the sensor's noise is stronger; the turning points of the
        /// `1d-trans` preset's back-and-forth motion 3.8–5.1 %, every other moving window
        /// 9.8 % or more. Holding those turning points (at 0.08) made mode `events` worse
        /// there on 6 of 7 seeds, so the default stays under them: rests in the dark
        /// and the end of a slow stop may go unflagged. A window without any event (a
        /// covered lens, a gap in the stream) is missing data, never quiet. 0 turns the
        /// detection off.
        quiet_ratio: f64 = 0.03,
        /// Quiet event windows by their structure (issue 8): a window is also quiet when, in
        /// both event cameras, the pixels with a firing neighbour beyond what chance gives at
        /// that density (`events::Activity::structured_share`) cover less than this share of
        /// the sensor, and under 10 % of the pixels fired. Sensor noise fires pixels
        /// independently, so the share stays near zero at rest whatever the noise rate and
        /// needs no history: it flags the rests `quiet_ratio` misses (in the 40× darker
        /// room, at the start of a sequence) and never initialises a map on noise. On the
        /// simulator's sequences (`benches/bench_quiet_structure.py`) windows at rest gave
        /// 0.11–0.23 % of the sensor (the most in the dark room), moving ones 0.31 % or more
        /// (the 128-pixel rig in the dark; turning points of the `1d-trans` back-and-forth
        /// motion 0.45–0.51 %). 0 turns this test off.
        quiet_structure: f64 = 0.0025,
        /// Depth of the event→frame warp plane during `dhptam run` (issue 8): "plane" warps
        /// every frame through `plane_depth_m`; "tracked" warps frame k through a plane at
        /// the median depth of the map points frame k−1 was tracked with
        /// (`System::tracked_depth`), falling back to `plane_depth_m` before initialisation
        /// and after a lost frame. "tracked" puts the warped event pixels about 5× nearer the
        /// frame pixels of the same points (median 0.4–0.7 px against 2.4–3.2 px) but raised
        /// the `fusion` trajectory error on 4 of the 6 sequences measured (docs/BENCHMARKS.md,
        /// "Accuracy: event→frame warp depth from tracked map points"), hence the default.
        warp_depth: String = "plane".to_string(),
        /// The cameras mode `events` tracks in (issue 8): "event", the rectified event
        /// cameras themselves (the E3CT is not resampled; each image gets a black border of
        /// `Frontend.EVENT_BORDER_PX` so that feature detectors reach its edges; the poses
        /// written are still the frame camera's, through the rig's extrinsics); "frame", the
        /// event images warped into the rectified frame cameras like the fusion mode's;
        /// "auto", "event" where the event cameras are sensors of their own and "frame" where
        /// they are the frame cameras' pixels (a DAVIS-like rig: the warp is the identity).
        /// "event" lowered the `events` error on 26 of 30 short runs with separate event
        /// cameras and raised it on both trajectories played whole (25 s, 60 s: "frame" is
        /// the setting to try for long fast sequences), and on all 3 DAVIS-like runs, where
        /// only the border differs (docs/BENCHMARKS.md, "Mode `events` in the event cameras'
        /// own geometry").
        /// The other modes always work in the frame cameras.
        events_geometry: String = "auto".to_string(),
        /// Bin width of the tracked warp depth, in pixels of event→frame parallax: the depth
        /// is rounded in inverse depth to bins this many pixels of parallax wide (at the
        /// frame camera's focal length and the event-to-frame offset), so the warp maps are
        /// reused while the scene depth drifts; the rounding moves warped pixels by at most
        /// half of it. The warp keeps the previous frame's depth while the tracked one is
        /// within one bin of it (no back-and-forth at a bin edge). 0: no rounding.
        warp_depth_step_px: f64 = 0.5,
        /// Stereo disparities of event-dominated images (`dvs`-biased fusion, mode `events`)
        /// read with the event cameras' geometry (issue 8): warped into the frame cameras,
        /// an event pair keeps the event cameras' parallax, so its disparity is mapped to the
        /// frame cameras' before triangulation (`DisparityCorrection`; the front-end's
        /// `Frontend.event_disparity`). Off: read as frame disparities, which puts event
        /// points `b_frame / b_event` times too near (−9 % on the simulator's rig).
        event_disparity: bool = true,
        /// How `event_disparity` reads a stereo match of event-dominated images:
        /// "disparity" maps the disparity alone (`DisparityCorrection`, first order along
        /// the rows) and leaves the keypoints where the warp put them; "exact" unwarps both
        /// pixels into the rectified event cameras, triangulates them with the event pair
        /// and projects the point into the frame cameras, moving the keypoint to where the
        /// frame camera would have seen it (`fusion::EventStereo`; the event cameras'
        /// centres differ from the frame cameras', 3 cm on the simulator's rig). Keypoints
        /// without a stereo match stay where the warp put them either way. "exact" raised
        /// the error in mode `events` and did not lower it in `fusion` (docs/BENCHMARKS.md,
        /// "HDR lighting on the real trajectories: what the event cameras' offset
        /// explains"), hence the default.
        event_stereo: String = "disparity".to_string(),
        /// Event-dominated images warped into the frame cameras through the plane at
        /// infinity are the event cameras' view: the same orientation, the event cameras'
        /// centres (3 cm below the frame cameras' on the simulator's rig). On: their
        /// keypoints are modelled from the left event camera's centre in tracking, new map
        /// points and bundle adjustment (`FrameFeatures::viewpoint`; the front-end's
        /// `Frontend.event_viewpoint`), with the disparity correction of `event_disparity`.
        /// Off, or through a plane at finite depth (`warp_depth`, `plane_depth_m`): they are
        /// read as the frame cameras' own.
        event_viewpoint: bool = false,
    }
}

config_section! {
    /// Keypoint extraction (`dhptam.features`, issue 6); read by `dhptam.features.from_config`.
    FeaturesConfig {
        /// Extractor: "r2d2", "superpoint", "orb" or "sift".
        extractor: String = "r2d2".to_owned(),
        /// Weight file of a learned extractor: a path, or a known name ("r2d2_WASF_N16",
        /// "faster2d2_WASF_N16", "superpoint_v1"); empty for the extractor's default. Lookup
        /// order: this path, $DHPTAM_WEIGHTS_DIR, the user cache, a checksum-verified download.
        weights: String = String::new(),
        /// Torch device: "auto" (CUDA when available, else CPU), "cpu", "cuda" or "cuda:N".
        device: String = "auto".to_owned(),
        /// CPU threads of torch (process-wide) or OpenCV; 0 keeps the library's default.
        threads: u32 = 0,
        /// Keypoints kept per image, best scores first; 0 (the default) sets it from the image
        /// size (`dhptam.features.keypoint_budget`: one per 256 px², 1000 to 8000).
        max_keypoints: u32 = 0,
        /// Arithmetic of a learned extractor's network trunk: "float32", "bfloat16" (2–4×
        /// faster on CPUs with AMX or AVX-512-BF16, emulated and slower elsewhere), "float16"
        /// (CUDA only) or "int8" (R2D2 on the CPU only). ORB and SIFT take "float32" only.
        precision: String = "float32".to_owned(),
        /// R2D2's image pyramid, fractions of the image in (0, 1]; empty for 1, 0.75 and 0.5.
        /// [1.0] with the faster2d2 weights and a bfloat16 or int8 trunk is the fast CPU
        /// setting (docs/FEATURES.md). R2D2 only.
        scales: Vec<f64> = Vec::new(),
    }
}

// --- SLAM back-end (issue 7) ---
config_section! {
    /// Tracking: stereo matching, projection-guided matching, pose refinement, keyframes.
    TrackingConfig {
        /// Rectified stereo matches may differ in row by at most this, pixels.
        stereo_row_px: f64 = 2.0,
        /// Descriptor ratio test: best distance < ratio × second best (1 turns it off).
        ratio: f64 = 0.9,
        /// Largest descriptor distance of a match; 0 uses the descriptor kind's default
        /// (L2 in [0, 2] for unit float descriptors, Hamming bits for binary ones).
        max_descriptor_distance: f64 = 0.0,
        /// Side of the square cells of the keypoint grid used for candidate lookup, pixels.
        cell_px: f64 = 15.0,
        /// Search radius around a map point's projection, pixels (the paper's 15 px).
        radius_px: f64 = 15.0,
        /// Search radius of the second pass when the first found too few matches, pixels.
        wide_radius_px: f64 = 25.0,
        /// Fewer matches than this after the first pass triggers the wide second pass.
        min_matches: u32 = 50,
        /// Fewer inliers than this after refinement: the frame is lost.
        min_tracked: u32 = 15,
        /// A tracked pose whose camera centre lies farther from the constant-velocity
        /// prediction than this fraction of the median depth of its inlier points is
        /// rejected as implausible, and the frame goes on to relocalisation like one with too
        /// few inliers; 0 turns the check off. Between two frames that still see the same
        /// map points the camera moves a small part of their distance: the fastest simulated
        /// trajectory (the whole ecd_poster_6dof, 20 Hz) departs from constant velocity by
        /// at most 0.03–0.06 of the scene depth per frame, while poses tracked there on 15–40
        /// wrongly matched inliers jumped by up to the whole depth (docs/BENCHMARKS.md, "A
        /// tracked pose that jumps away from the motion model"). The bound is per frame:
        /// departures grow with the square of the frame interval, so for frame rates well
        /// under 10 Hz raise it.
        max_jump_ratio: f64 = 0.25,
        /// Map points seen under a larger angle from their mean viewing direction are not
        /// searched, degrees.
        max_view_angle_deg: f64 = 60.0,
        /// Covisible keyframes (besides the reference) whose points form the local map.
        local_keyframes: u32 = 10,
        /// New keyframe when the tracked points fall under this fraction of the reference
        /// keyframe's.
        keyframe_ratio: f64 = 0.9,
        /// New keyframe also whenever fewer points than this are tracked.
        keyframe_min_tracked: u32 = 50,
        /// `keyframe_min_tracked` of mode `events` (`[fusion] mode = "events"`), which replaces it
        /// there; the same 50 by default. An event image pair matches 3–4× fewer points than a
        /// frame pair, so a keyframe whose own count was set by a weak frame can hold off new ones
        /// on fast translations (up to 19 frames, about 1 s, on the quadrotor trajectory). 150
        /// about doubles the keyframes of mode `events`: with `--sync`, or threaded at sensor rate
        /// (`--realtime`), it lowered the error on every demo seed tried (sync mean 2.60 → 1.86 %
        /// of the path) and on both normal-light 8 s real trajectories; threaded as fast as the
        /// cores allow it changed nothing, and both trajectories played whole got worse (quadrotor
        /// 0.53 → 1.05 %), so it is not the default (docs/BENCHMARKS.md, "A keyframe floor of its
        /// own for mode `events`").
        events_keyframe_min_tracked: u32 = 50,
        /// `keyframe_min_tracked` of the fusion's DVS-biased frames (event-dominated images
        /// of mode `fusion`, flagged by the caller: `System.track(..., dvs_biased=True)`).
        /// Such images look unlike the frames most of the map was built from, so what they
        /// match is mostly the points of the last DVS-biased keyframes. At the plain floor of
        /// 50 a DVS-biased frame tracked on 60 points made no keyframe, the next one matched
        /// 30, and the keyframe made there, at a weakly determined pose, took the segment off
        /// course. Under this floor nearly every DVS-biased frame becomes a keyframe, and the
        /// threaded back-end maps each one before the next frame is tracked, as the
        /// synchronous back-end does (otherwise each would interrupt the adjustment of the
        /// last). On the HDR-lit real trajectories, 16 short runs, it lowered `fusion`'s mean
        /// error from 2.74 to 1.20 % synchronously and from 2.59 to 1.39 % threaded; the demo
        /// moved from 0.52 to 0.55 % (docs/BENCHMARKS.md, "A keyframe floor of its own for
        /// DVS-biased frames"). Equal to `keyframe_min_tracked`: the plain floor.
        dvs_keyframe_min_tracked: u32 = 150,
        /// The first keyframe needs at least this many triangulated stereo matches.
        init_min_points: u32 = 30,
        /// When a frame can be neither tracked nor relocalised, start a new map segment from
        /// its own stereo points at the constant-velocity pose, so tracking resumes at once
        /// (after an abrupt change of appearance, e.g. the fusion switching between frame- and
        /// event-dominated images); the old keyframes stay for relocalisation and loop
        /// closing. Off: the system stays lost until relocalisation succeeds.
        reinitialise: bool = true,
        /// When a frame right after a tracked one is not tracked from the motion model and
        /// none of the place query's candidates relocalises it, relocalisation also tries the
        /// last frame's reference keyframe (PnP against its map points) before the frame
        /// starts a new map segment. Off: the place query's candidates only
        /// (docs/BENCHMARKS.md, "Relocalisation against the reference keyframe").
        relocalise_reference: bool = true,
        /// A frame relocalised right after a tracked frame of the same map segment takes the
        /// step from that frame as its velocity (when the step itself passes the
        /// `max_jump_ratio` check, from the last pose at rest), instead of restarting from
        /// rest. Over fast turns the motion model misses frame after frame, and a velocity
        /// from rest makes the next frame miss again; but on the HDR-lit poster trajectory
        /// played whole, R2D2 went from 0.24 % to 4.3 % with it and `segment_velocity =
        /// "rest"`, and to 240 % with `"measured"` (docs/BENCHMARKS.md, "The relocalised
        /// step's velocity, measured again"), so it is off.
        relocalised_velocity: bool = false,
        /// The velocity a new map segment (`reinitialise`) goes on with: `"kept"`, the one
        /// the motion model placed it with; `"rest"`, none; `"measured"`, the kept one unless
        /// it is a relocalised frame's step (`relocalised_velocity`), which is dropped (so
        /// `"kept"` and `"measured"` differ only with that setting on). A segment started
        /// right after another one that no frame was tracked against goes on from rest under
        /// every value: a run of such frames is extrapolated over two frames at most.
        segment_velocity: String = "kept".to_owned(),
        /// Frames whose mean motion is the velocity of predicted (untracked) frames
        /// (`System::predict`, across illumination floods): the motion between the last
        /// measured frame and the one this many frames before it, taken to the 1/n power; 1
        /// uses the last frame-to-frame motion (noisier on event-dominated images).
        predict_velocity_frames: u32 = 4,
        /// Levenberg–Marquardt iterations of each motion-only refinement.
        refine_iterations: u32 = 10,
        /// Huber scale and outlier bound of the refinement, pixels (√7.815: the 95 % χ²
        /// bound of a 3-dof stereo residual at σ = 1 px).
        huber_px: f64 = 2.795,
        /// Measurement noise σ of each keypoint in the motion-only refinement, the local
        /// bundle adjustment and their outlier bounds (residuals whitened by 1/σ, so the
        /// Huber scale and outlier bound above, stated for σ = 1 px, widen by σ):
        /// "octave" takes the extractor's per-keypoint σ (ORB: 1.2^octave, SIFT: 2^octave,
        /// R2D2: the inverse of its pyramid scale; 1 for single-scale extractors); "unit"
        /// gives every keypoint σ = 1 px. Default "unit": with ORB, "octave" was not more
        /// accurate across the simulator's sequences (docs/BENCHMARKS.md, "per-keypoint σ").
        keypoint_sigma: String = "unit".to_owned(),
        /// Factor on the keypoint σ of frames whose fusion is DVS-biased (event-dominated
        /// images locate corners less precisely than frames), with either `keypoint_sigma`
        /// ("unit": σ = this factor on those frames); applied by the Python front-end
        /// (`dhptam.run`). 1 (default: 1.4 did not help on the HDR demo) leaves σ as it is.
        dvs_sigma_scale: f64 = 1.0,
        /// Acceleration-noise spectral density q, m²/s³, of the smoother that re-estimates
        /// the written trajectory's camera centres from every tracked frame, each weighted by
        /// the covariance of its own pose refinement (`slam::smoothing`, docs/ARCHITECTURE.md);
        /// 0 writes the centres as tracked. Tracking itself never sees the smoothed poses.
        /// Default 0.03: 0.003 already bends the fast shaking of the `6dof` preset, 0.01–0.03
        /// help every simulated sequence in `fusion` and `frames` (docs/BENCHMARKS.md, "The
        /// trajectory smoother").
        smoothing_q: f64 = 0.03,
    }
}

config_section! {
    /// Local mapping: local bundle adjustment and map point culling.
    MappingConfig {
        /// Keyframes optimised by each local bundle adjustment (the new one and its most
        /// covisible); other keyframes observing their points are held fixed.
        window: u32 = 10,
        /// At most this many fixed keyframes take part.
        max_fixed: u32 = 10,
        /// Levenberg–Marquardt iterations of the local bundle adjustment.
        ba_iterations: u32 = 30,
        /// A Gaussian prior on the camera centre of each weakly tied free keyframe (see
        /// `centre_prior_below`) in the local bundle adjustment: at its centre before the
        /// adjustment, with the covariance the tracker measured for the frame that became the
        /// keyframe times this factor squared (a keyframe whose frame had no measured
        /// covariance, e.g. a map's first, gets none). Such a keyframe then moves about as
        /// far as its tracking uncertainty allows, not as far as its own new points let it
        /// slide (an event-dominated keyframe after a switch of the fusion's mode). On the
        /// HDR-lit real trajectories it halved `fusion`'s error and changed no other bench
        /// by more than noise (docs/BENCHMARKS.md, "A centre prior for weakly tied
        /// keyframes"). 0: no prior.
        centre_prior_scale: f64 = 0.5,
        /// Weakly tied: fewer than this many of the keyframe's map points are observed by
        /// another keyframe too (twice `[tracking] keyframe_min_tracked`, the tracker's own
        /// measure of a weak frame). Raising it towards every keyframe's count gave the prior
        /// to well-tied keyframes as well and cost accuracy (docs/BENCHMARKS.md).
        centre_prior_below: u32 = 100,
        /// A point observed by fewer keyframes than `min_observers` once this many keyframes
        /// have been added after its creation is removed.
        cull_after_keyframes: u32 = 3,
        /// See `cull_after_keyframes`.
        min_observers: u32 = 2,
        /// Keyframes the tracker may queue for the mapping thread before it waits.
        queue: u32 = 8,
        /// Before the bundle adjustment, fuse duplicate map points and re-find points: the new
        /// keyframe's points are projected into its neighbour keyframes and theirs into it; a
        /// projection matching a keypoint that observes another point merges the two points,
        /// one matching a free keypoint adds the observation.
        fuse: bool = true,
        /// Most covisible keyframes searched by the fusion.
        fuse_neighbours: u32 = 10,
        /// Keyframes preceding the new one (by id) also searched, covisible or not: they link
        /// a new map segment started after tracking loss to the previous one. Off by default:
        /// a new segment starts at the constant-velocity guess, and merging its points into the
        /// old segment's turns that guess's error into map corruption (on the HDR demo, fusion
        /// mode went from 4.2 % to 10–45 % ATE with 2); raise it when re-initialisations come
        /// from short glitches on otherwise smooth motion.
        fuse_temporal: u32 = 0,
        /// Largest distance between a point's projection and the keypoint it fuses with,
        /// pixels (in the left image and, for stereo keypoints, in the right column).
        fuse_radius_px: f64 = 4.0,
        // --- culling (issue 10) ---
        /// After each keyframe's bundle adjustment, remove redundant older keyframes where the
        /// map holds more than `keyframes_per_place` keyframes at the new keyframe's place (see
        /// `place_radius_ratio`): the map then grows with the places visited, not with the
        /// length of the run. A keyframe is removed only when it is redundant
        /// (`redundant_fraction`), old enough (`cull_min_age`), outside the new keyframe's
        /// local bundle-adjustment window, and its removal leaves every covisible keyframe at
        /// least `cull_keep_shared` points seen by another keyframe. The map's first keyframe,
        /// loop keyframes and the first keyframes of map segments are never removed. On by
        /// default (docs/BENCHMARKS.md, "Keyframe culling by place").
        cull_keyframes: bool = true,
        /// Keyframes the map may hold at one place (position within `place_radius_ratio` of
        /// the scene depth, optical axes within `place_max_angle_deg`) before the most
        /// redundant are removed. 0 removes every redundant keyframe covisible with the new one,
        /// wherever it is (ORB-SLAM's rule; on the sparse tiny rig it drifted: BENCHMARKS.md).
        keyframes_per_place: u32 = 3,
        /// Radius of a place: this fraction of the new keyframe's median point depth, metres
        /// per metre (0.05: about 3° of parallax between two keyframes at the edge). 0.1 with
        /// `place_max_angle_deg` 30 held too few viewpoints for relocalisation on the synthetic
        /// circle (`relocalises_after_a_jump_to_a_known_place`).
        place_radius_ratio: f64 = 0.05,
        /// Largest angle between the optical axes of two keyframes at one place, degrees.
        place_max_angle_deg: f64 = 15.0,
        /// At most this many keyframes are removed after each new keyframe (so a removal never
        /// cascades through the map in one step).
        cull_max_per_keyframe: u32 = 2,
        /// A keyframe is kept if removing it would leave a covisible keyframe fewer than this
        /// many map points observed by some other keyframe too (or fewer than it has now, when
        /// it has fewer): every neighbour stays tied to the map by enough shared points.
        cull_keep_shared: u32 = 20,
        /// Only keyframes at least this many keyframes older than the one being mapped are
        /// examined: the recent window keeps all its constraints while the camera explores
        /// (culling inside it too tripled the drift on the 30-minute run).
        cull_min_age: u32 = 10,
        /// A keyframe is redundant when at least this fraction of its map points are each
        /// observed by `redundant_observers` other keyframes at the same or a finer scale.
        redundant_fraction: f64 = 0.9,
        /// See `redundant_fraction`.
        redundant_observers: u32 = 3,
        /// "The same or a finer scale": the other keyframe is at most this many times the
        /// keyframe's distance from the point (1.2: one level of a 1.2-ratio image pyramid
        /// coarser, as ORB-SLAM allows; keypoints carry no scale here, distance stands in).
        redundant_distance_ratio: f64 = 1.2,
        /// "A similar viewing direction": the other keyframe's ray to the point is within this
        /// angle of the keyframe's own, degrees (a point seen only from elsewhere does not make
        /// the keyframe's view of it redundant).
        redundant_max_angle_deg: f64 = 30.0,
        /// A point older than `cull_after_keyframes` that the window's keyframes observe in
        /// less than this fraction of those whose view it projects into (at least 3 of them)
        /// is removed: rarely found when predicted visible. 0 (the default) turns this off;
        /// ORB-SLAM uses 0.25 (per frame rather than per keyframe).
        min_found_ratio: f64 = 0.0,
        // --- end culling ---
        /// Levenberg–Marquardt iterations of the bundle adjustment of the whole map that
        /// `dhptam run` does after the last frame (`System::refine_map`: every keyframe and
        /// point, the first keyframe of each map segment held); the written trajectory, map and
        /// keyframes are those after it (a few tens of ms on the simulator's 4 s sequences;
        /// docs/BENCHMARKS.md, "whole-map bundle adjustment"). 0 turns it off.
        final_ba_iterations: u32 = 20,
    }
}

config_section! {
    /// Loop closing and relocalisation (place recognition + RANSAC PnP).
    LoopClosingConfig {
        /// Detect and close loops.
        enabled: bool = true,
        /// Smallest cosine similarity of two keyframes' embeddings to be a loop candidate.
        min_score: f64 = 0.8,
        /// Candidates verified per keyframe (best scores first).
        candidates: u32 = 3,
        /// The most recent keyframes are never loop candidates.
        skip_recent: u32 = 20,
        /// PnP inliers needed to accept a loop or a relocalisation.
        min_inliers: u32 = 30,
        /// RANSAC inlier threshold, pixels.
        ransac_threshold_px: f64 = 3.0,
        /// RANSAC iteration cap.
        ransac_iterations: u32 = 300,
        /// RANSAC seed (fixed: the synchronous mode gives the same results every run).
        seed: u64 = 7,
        /// A loop is verified by PnP in both directions (the query's keypoints against the
        /// candidate's map points and the candidate's keypoints against the query's); the two
        /// relative poses `candidate_from_query` may differ in rotation by at most this,
        /// degrees.
        max_disagreement_deg: f64 = 2.0,
        /// See `max_disagreement_deg`: largest difference in translation, metres.
        max_disagreement_m: f64 = 0.1,
        /// A verified loop between two keyframes of one map (one segment, or segments that
        /// loops have joined) is rejected when it would turn the query keyframe by more than
        /// this, degrees: tracking does not drift that far, a look-alike place does. Loops
        /// that join a new map segment to the rest are exempt, since that segment's pose is a
        /// guess. True loops in the benchmarks turned it by at most 20.5°; a false one, on a
        /// place seen from the opposite side, by 166° (docs/BENCHMARKS.md, "A keyframe floor
        /// of its own for mode `events`").
        max_correction_deg: f64 = 45.0,
    }
}
// --- end SLAM back-end ---

// --- SLAM back-end (issue 7) ---
impl TrackingConfig {
    fn check(&self) -> Result<()> {
        for (key, v) in [
            ("tracking.stereo_row_px", self.stereo_row_px),
            ("tracking.cell_px", self.cell_px),
            ("tracking.radius_px", self.radius_px),
            ("tracking.wide_radius_px", self.wide_radius_px),
            ("tracking.huber_px", self.huber_px),
            ("tracking.dvs_sigma_scale", self.dvs_sigma_scale),
        ] {
            check(key, v.is_finite() && v > 0.0, "a positive number", v)?;
        }
        check(
            "tracking.smoothing_q",
            self.smoothing_q.is_finite() && self.smoothing_q >= 0.0,
            "a non-negative number (0: off)",
            self.smoothing_q,
        )?;
        check(
            "tracking.segment_velocity",
            ["kept", "rest", "measured"].contains(&self.segment_velocity.as_str()),
            "\"kept\", \"rest\" or \"measured\"",
            format!("{:?}", self.segment_velocity),
        )?;
        check(
            "tracking.keypoint_sigma",
            ["octave", "unit"].contains(&self.keypoint_sigma.as_str()),
            "\"octave\" or \"unit\"",
            format!("{:?}", self.keypoint_sigma),
        )?;
        check(
            "tracking.ratio",
            self.ratio > 0.0 && self.ratio <= 1.0,
            "a value in (0, 1]",
            self.ratio,
        )?;
        check(
            "tracking.keyframe_ratio",
            (0.0..=1.0).contains(&self.keyframe_ratio),
            "a value in [0, 1]",
            self.keyframe_ratio,
        )?;
        check(
            "tracking.max_descriptor_distance",
            self.max_descriptor_distance >= 0.0,
            "a non-negative number",
            self.max_descriptor_distance,
        )?;
        check(
            "tracking.max_view_angle_deg",
            self.max_view_angle_deg > 0.0 && self.max_view_angle_deg <= 180.0,
            "a value in (0, 180]",
            self.max_view_angle_deg,
        )?;
        check(
            "tracking.min_tracked",
            self.min_tracked >= 6,
            "at least 6",
            self.min_tracked,
        )?;
        check(
            "tracking.max_jump_ratio",
            self.max_jump_ratio.is_finite() && self.max_jump_ratio >= 0.0,
            "a finite fraction >= 0 (0: off)",
            self.max_jump_ratio,
        )?;
        check(
            "tracking.refine_iterations",
            self.refine_iterations >= 1,
            "at least 1",
            self.refine_iterations,
        )
    }
}

impl MappingConfig {
    fn check(&self) -> Result<()> {
        check(
            "mapping.window",
            self.window >= 1,
            "at least 1",
            self.window,
        )?;
        check("mapping.queue", self.queue >= 1, "at least 1", self.queue)?;
        check(
            "mapping.centre_prior_scale",
            self.centre_prior_scale.is_finite() && self.centre_prior_scale >= 0.0,
            "a finite number >= 0 (0: no prior)",
            self.centre_prior_scale,
        )?;
        check(
            "mapping.fuse_radius_px",
            self.fuse_radius_px.is_finite() && self.fuse_radius_px > 0.0,
            "a positive number",
            self.fuse_radius_px,
        )?;
        check(
            "mapping.ba_iterations",
            self.ba_iterations >= 1,
            "at least 1",
            self.ba_iterations,
        )?;
        // --- culling (issue 10) ---
        check(
            "mapping.redundant_fraction",
            self.redundant_fraction > 0.0 && self.redundant_fraction <= 1.0,
            "a value in (0, 1]",
            self.redundant_fraction,
        )?;
        check(
            "mapping.redundant_observers",
            self.redundant_observers >= 1,
            "at least 1",
            self.redundant_observers,
        )?;
        check(
            "mapping.redundant_distance_ratio",
            self.redundant_distance_ratio.is_finite() && self.redundant_distance_ratio >= 1.0,
            "a number ≥ 1",
            self.redundant_distance_ratio,
        )?;
        check(
            "mapping.min_found_ratio",
            (0.0..=1.0).contains(&self.min_found_ratio),
            "a value in [0, 1]",
            self.min_found_ratio,
        )?;
        check(
            "mapping.place_radius_ratio",
            self.place_radius_ratio.is_finite() && self.place_radius_ratio > 0.0,
            "a positive number",
            self.place_radius_ratio,
        )?;
        for (key, v) in [
            ("mapping.place_max_angle_deg", self.place_max_angle_deg),
            (
                "mapping.redundant_max_angle_deg",
                self.redundant_max_angle_deg,
            ),
        ] {
            check(
                key,
                v > 0.0 && v <= 180.0,
                "an angle in (0, 180] degrees",
                v,
            )?;
        }
        check(
            "mapping.cull_max_per_keyframe",
            self.cull_max_per_keyframe >= 1,
            "at least 1",
            self.cull_max_per_keyframe,
        )
        // --- end culling ---
    }
}

impl LoopClosingConfig {
    fn check(&self) -> Result<()> {
        check(
            "loop_closing.min_score",
            (-1.0..=1.0).contains(&self.min_score),
            "a cosine in [-1, 1]",
            self.min_score,
        )?;
        check(
            "loop_closing.min_inliers",
            self.min_inliers >= 6,
            "at least 6",
            self.min_inliers,
        )?;
        check(
            "loop_closing.ransac_threshold_px",
            self.ransac_threshold_px > 0.0,
            "a positive number",
            self.ransac_threshold_px,
        )?;
        check(
            "loop_closing.max_disagreement_deg",
            self.max_disagreement_deg >= 0.0,
            "a non-negative number",
            self.max_disagreement_deg,
        )?;
        check(
            "loop_closing.max_disagreement_m",
            self.max_disagreement_m >= 0.0,
            "a non-negative number",
            self.max_disagreement_m,
        )?;
        check(
            "loop_closing.max_correction_deg",
            (0.0..=180.0).contains(&self.max_correction_deg),
            "between 0 and 180 (180: off)",
            self.max_correction_deg,
        )
    }
}
// --- end SLAM back-end ---

impl LogConfig {
    fn check(&self) -> Result<()> {
        Ok(())
    }
}

impl RectificationConfig {
    fn check(&self) -> Result<()> {
        check(
            "rectification.balance",
            (0.0..=1.0).contains(&self.balance),
            "a value in [0, 1]",
            self.balance,
        )?;
        check(
            "rectification.width/height",
            (self.width == 0) == (self.height == 0),
            "both 0 (use the left camera's size) or both positive",
            format!("{}×{}", self.width, self.height),
        )
    }
}

impl TriangulationConfig {
    fn check(&self) -> Result<()> {
        check(
            "triangulation.min_depth_m",
            self.min_depth_m > 0.0,
            "a positive depth",
            self.min_depth_m,
        )?;
        check(
            "triangulation.max_depth_m",
            self.max_depth_m > self.min_depth_m,
            "a depth above min_depth_m",
            self.max_depth_m,
        )?;
        check(
            "triangulation.min_parallax_deg",
            (0.0..90.0).contains(&self.min_parallax_deg),
            "an angle in [0, 90)",
            self.min_parallax_deg,
        )?;
        check(
            "triangulation.max_reprojection_px",
            self.max_reprojection_px > 0.0,
            "a positive error",
            self.max_reprojection_px,
        )
    }
}

impl SimConfig {
    fn check(&self) -> Result<()> {
        let positive = [
            ("sim.fps", self.fps),
            ("sim.contrast_on", self.contrast_on),
            ("sim.contrast_off", self.contrast_off),
            (
                "sim.noise_reference_intensity",
                self.noise_reference_intensity,
            ),
            ("sim.log_eps", self.log_eps),
            ("sim.max_log_step", self.max_log_step),
            ("sim.min_render_step_us", self.min_render_step_us),
            ("sim.min_exposure_ms", self.min_exposure_ms),
            ("sim.ae_target_mean", self.ae_target_mean),
            ("sim.ae_rate", self.ae_rate),
            ("sim.sensitivity_e_per_s", self.sensitivity_e_per_s),
            ("sim.full_well_e", self.full_well_e),
        ];
        for (key, value) in positive {
            check(
                key,
                value > 0.0 && value.is_finite(),
                "a positive number",
                value,
            )?;
        }
        let non_negative = [
            ("sim.contrast_sigma", self.contrast_sigma),
            ("sim.refractory_us", self.refractory_us),
            ("sim.noise_rate_hz", self.noise_rate_hz),
            ("sim.read_noise_e", self.read_noise_e),
        ];
        for (key, value) in non_negative {
            check(
                key,
                value >= 0.0 && value.is_finite(),
                "a number >= 0",
                value,
            )?;
        }
        check(
            "sim.blur_samples",
            self.blur_samples >= 1,
            "at least 1",
            self.blur_samples,
        )?;
        check(
            "sim.max_render_step_us",
            self.max_render_step_us >= self.min_render_step_us,
            "at least min_render_step_us",
            self.max_render_step_us,
        )?;
        check(
            "sim.max_exposure_ms",
            self.max_exposure_ms >= self.min_exposure_ms,
            "at least min_exposure_ms",
            self.max_exposure_ms,
        )?;
        check(
            "sim.initial_exposure_ms",
            (self.min_exposure_ms..=self.max_exposure_ms).contains(&self.initial_exposure_ms),
            "a value between min_exposure_ms and max_exposure_ms",
            self.initial_exposure_ms,
        )?;
        check(
            "sim.ae_rate",
            self.ae_rate <= 1.0,
            "a value in (0, 1]",
            self.ae_rate,
        )?;
        check(
            "sim.ae_target_mean",
            self.ae_target_mean < 255.0,
            "a level below 255",
            self.ae_target_mean,
        )
    }
}

impl EventsConfig {
    fn check(&self) -> Result<()> {
        check(
            "events.alpha",
            self.alpha.is_finite() && self.alpha > 0.0,
            "a positive number",
            self.alpha,
        )?;
        check(
            "events.eta_ms",
            self.eta_ms.is_finite() && self.eta_ms > 0.0,
            "a positive span in milliseconds",
            self.eta_ms,
        )?;
        check(
            "events.channels",
            (2..=64).contains(&self.channels),
            "between 2 and 64",
            self.channels,
        )?;
        check(
            "events.normalise_percentile",
            self.normalise_percentile > 0.0 && self.normalise_percentile <= 100.0,
            "a percentile in (0, 100]",
            self.normalise_percentile,
        )?;
        check(
            "events.hot_pixel_ratio",
            self.hot_pixel_ratio == 0.0
                || (self.hot_pixel_ratio.is_finite() && self.hot_pixel_ratio > 1.0),
            "0 (off) or a ratio above 1",
            self.hot_pixel_ratio,
        )?;
        check(
            "events.hot_pixel_min_rate_hz",
            self.hot_pixel_min_rate_hz.is_finite() && self.hot_pixel_min_rate_hz > 0.0,
            "a positive rate in Hz",
            self.hot_pixel_min_rate_hz,
        )?;
        check(
            "events.hot_pixel_time_s",
            self.hot_pixel_time_s.is_finite() && self.hot_pixel_time_s > 0.0,
            "a positive time in seconds",
            self.hot_pixel_time_s,
        )
    }
}

impl FusionConfig {
    fn check(&self) -> Result<()> {
        check(
            "fusion.beta_max",
            (0.0..=1.0).contains(&self.beta_max),
            "a weight in [0, 1]",
            self.beta_max,
        )?;
        check(
            "fusion.aps_beta_max",
            (0.0..=1.0).contains(&self.aps_beta_max),
            "a weight in [0, 1]",
            self.aps_beta_max,
        )?;
        check(
            "fusion.dvs_beta_min",
            (0.0..=1.0).contains(&self.dvs_beta_min),
            "a weight in [0, 1]",
            self.dvs_beta_min,
        )?;
        check(
            "fusion.dark_level/bright_level",
            (0.0..=255.0).contains(&self.dark_level)
                && (0.0..=255.0).contains(&self.bright_level)
                && self.dark_level < self.bright_level,
            "0 <= dark_level < bright_level <= 255",
            format!("{} and {}", self.dark_level, self.bright_level),
        )?;
        check(
            "fusion.max_clipped_fraction",
            (0.0..=1.0).contains(&self.max_clipped_fraction),
            "a fraction in [0, 1]",
            self.max_clipped_fraction,
        )?;
        check(
            "fusion.dvs_clipped_fraction",
            (0.0..=1.0).contains(&self.dvs_clipped_fraction),
            "a fraction in [0, 1]",
            self.dvs_clipped_fraction,
        )?;
        check(
            "fusion.recover_min_snr",
            self.recover_min_snr.is_finite() && self.recover_min_snr >= 0.0,
            "a ratio >= 0",
            self.recover_min_snr,
        )?;
        check(
            "fusion.plane_depth_m",
            self.plane_depth_m.is_finite() && self.plane_depth_m >= 0.0,
            "0 (infinity) or a positive depth",
            self.plane_depth_m,
        )?;
        check(
            "fusion.align_px",
            self.align_px.iter().all(|v| v.is_finite()),
            "two finite offsets",
            format!("{:?}", self.align_px),
        )?;
        check(
            "fusion.flood_ratio",
            self.flood_ratio == 0.0 || (self.flood_ratio.is_finite() && self.flood_ratio > 1.0),
            "0 (off) or a ratio above 1",
            self.flood_ratio,
        )?;
        check(
            "fusion.flood_polarity",
            self.flood_polarity > 0.5 && self.flood_polarity <= 1.0,
            "a share in (0.5, 1]",
            self.flood_polarity,
        )?;
        check(
            "fusion.quiet_ratio",
            (0.0..1.0).contains(&self.quiet_ratio),
            "0 (off) or a fraction below 1",
            self.quiet_ratio,
        )?;
        check(
            "fusion.quiet_structure",
            (0.0..1.0).contains(&self.quiet_structure),
            "0 (off) or a share of the sensor below 1",
            self.quiet_structure,
        )?;
        check(
            "fusion.flood_history",
            self.flood_history >= 1,
            "at least 1 window",
            self.flood_history,
        )?;
        check(
            "fusion.warp_depth",
            ["tracked", "plane"].contains(&self.warp_depth.as_str()),
            "\"tracked\" or \"plane\"",
            format!("{:?}", self.warp_depth),
        )?;
        check(
            "fusion.events_geometry",
            ["auto", "event", "frame"].contains(&self.events_geometry.as_str()),
            "\"auto\", \"event\" or \"frame\"",
            format!("{:?}", self.events_geometry),
        )?;
        check(
            "fusion.warp_depth_step_px",
            self.warp_depth_step_px.is_finite() && self.warp_depth_step_px >= 0.0,
            "0 (no rounding) or a positive parallax in pixels",
            self.warp_depth_step_px,
        )?;
        check(
            "fusion.event_stereo",
            ["exact", "disparity"].contains(&self.event_stereo.as_str()),
            "\"exact\" or \"disparity\"",
            format!("{:?}", self.event_stereo),
        )
    }
}

impl FeaturesConfig {
    fn check(&self) -> Result<()> {
        check(
            "features.extractor",
            ["r2d2", "superpoint", "orb", "sift"].contains(&self.extractor.as_str()),
            "\"r2d2\", \"superpoint\", \"orb\" or \"sift\"",
            format!("{:?}", self.extractor),
        )?;
        let device_ok = match self.device.as_str() {
            "auto" | "cpu" | "cuda" => true,
            other => other
                .strip_prefix("cuda:")
                .is_some_and(|n| n.parse::<u32>().is_ok()),
        };
        check(
            "features.device",
            device_ok,
            "\"auto\", \"cpu\", \"cuda\" or \"cuda:N\"",
            format!("{:?}", self.device),
        )?;
        let learned = matches!(self.extractor.as_str(), "r2d2" | "superpoint");
        let precision_ok = match self.precision.as_str() {
            "float32" => true,
            "bfloat16" | "float16" => learned,
            "int8" => self.extractor == "r2d2",
            _ => false,
        };
        check(
            "features.precision",
            precision_ok,
            &format!(
                "\"float32\", \"bfloat16\", \"float16\" or \"int8\" (reduced precisions for the learned \
                 extractors, int8 for r2d2 only; extractor is {:?})",
                self.extractor
            ),
            format!("{:?}", self.precision),
        )?;
        check(
            "features.scales",
            self.scales.iter().all(|s| *s > 0.0 && *s <= 1.0),
            "fractions of the image in (0, 1]",
            format!("{:?}", self.scales),
        )?;
        check(
            "features.scales",
            self.scales.is_empty() || self.extractor == "r2d2",
            &format!(
                "an empty list: scales are R2D2's (extractor is {:?})",
                self.extractor
            ),
            format!("{:?}", self.scales),
        )
    }
}

fn check(key: &str, ok: bool, expected: &str, got: impl ToString) -> Result<()> {
    if ok {
        Ok(())
    } else {
        Err(Error::Config {
            source_name: String::new(),
            message: format!("{key}: expected {expected}, got {}", got.to_string()),
        })
    }
}

/// Declares [`Config`] from its sections: one line per `[table]`, in the order printed by
/// `dhptam config --defaults`.
macro_rules! config_root {
    ($( $(#[doc = $doc:literal])* $field:ident : $ty:ty ),* $(,)?) => {
        /// The whole configuration, one table per stage.
        #[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
        #[serde(deny_unknown_fields, default)]
        pub struct Config {
            $( $(#[doc = $doc])* pub $field: $ty, )*
        }

        impl Config {
            /// The sections with their table names.
            fn sections(&self) -> Vec<(&'static str, &dyn Section)> {
                vec![$( (stringify!($field), &self.$field as &dyn Section), )*]
            }
        }
    };
}

config_root! {
    /// `[log]`
    log: LogConfig,
    /// `[rectification]`
    rectification: RectificationConfig,
    /// `[triangulation]`
    triangulation: TriangulationConfig,
    /// `[events]`
    events: EventsConfig,
    /// `[fusion]`
    fusion: FusionConfig,
    /// `[sim]`
    sim: SimConfig,
    /// `[features]`
    features: FeaturesConfig,
    /// `[tracking]`
    tracking: TrackingConfig,
    /// `[mapping]`
    mapping: MappingConfig,
    /// `[loop_closing]`
    loop_closing: LoopClosingConfig,
}

impl Config {
    /// Parses TOML; keys left out keep their defaults. `source_name` (a path or `"<string>"`)
    /// names the origin in errors.
    pub fn from_toml_str(text: &str, source_name: &str) -> Result<Self> {
        let config: Config = toml::from_str(text).map_err(|e| Error::Config {
            source_name: source_name.to_owned(),
            message: e.to_string().trim_end().to_owned(),
        })?;
        config.validate().map_err(|e| match e {
            Error::Config { message, .. } => Error::Config {
                source_name: source_name.to_owned(),
                message,
            },
            other => other,
        })?;
        Ok(config)
    }

    /// Reads and parses a TOML file.
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            action: "read",
            path: path.to_owned(),
            source,
        })?;
        Self::from_toml_str(&text, &path.display().to_string())
    }

    /// Checks every value against its documented range.
    pub fn validate(&self) -> Result<()> {
        self.sections()
            .into_iter()
            .try_for_each(|(_, section)| section.validate())
    }

    /// The configuration as plain TOML.
    pub fn to_toml(&self) -> String {
        // Serialising plain structs of numbers, strings and enums cannot fail.
        toml::to_string(self).unwrap_or_default()
    }

    /// The configuration as TOML with every field's documentation as comments.
    pub fn to_commented_toml(&self) -> String {
        let mut out = String::from(
            "# dhptam configuration. Every key is optional: a missing key keeps the value shown.\n\n",
        );
        for (name, section) in self.sections() {
            let _ = writeln!(out, "[{name}]");
            section.write_commented(&mut out);
        }
        out.truncate(out.trim_end().len());
        out.push('\n');
        out
    }

    /// The default configuration, documented: what `dhptam config --defaults` prints.
    pub fn defaults_toml() -> String {
        Config::default().to_commented_toml()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_round_trip_through_commented_toml() {
        let text = Config::defaults_toml();
        assert!(text.contains("[triangulation]") && text.contains("# Minimum angle"));
        assert_eq!(
            Config::from_toml_str(&text, "<defaults>").unwrap(),
            Config::default()
        );
    }

    #[test]
    fn partial_file_keeps_other_defaults() {
        let c = Config::from_toml_str("[triangulation]\nmin_depth_m = 0.3\n", "<string>").unwrap();
        assert_eq!(c.triangulation.min_depth_m, 0.3);
        assert_eq!(c.rectification, RectificationConfig::default());
    }

    #[test]
    fn unknown_key_is_named() {
        let err =
            Config::from_toml_str("[triangulation]\nmin_dept_m = 0.3\n", "my.toml").unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.contains("my.toml") && msg.contains("min_dept_m"),
            "{msg}"
        );
        let err = Config::from_toml_str("[tracker]\n", "my.toml").unwrap_err();
        assert!(err.to_string().contains("tracker"), "{err}");
    }

    #[test]
    fn out_of_range_value_is_named() {
        let err = Config::from_toml_str("[rectification]\nbalance = 2.0\n", "x.toml").unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.contains("x.toml") && msg.contains("rectification.balance") && msg.contains('2'),
            "{msg}"
        );
        let err = Config::from_toml_str("[log]\nlevel = \"loud\"\n", "x.toml").unwrap_err();
        assert!(err.to_string().contains("loud"), "{err}");
    }

    #[test]
    fn hot_pixel_settings_are_checked() {
        let off = Config::from_toml_str("[events]\nhot_pixel_ratio = 0.0\n", "h.toml").unwrap();
        assert_eq!(off.events.hot_pixel_ratio, 0.0);
        for bad in [
            "hot_pixel_ratio = 1.0",
            "hot_pixel_ratio = -2.0",
            "hot_pixel_min_rate_hz = 0.0",
            "hot_pixel_time_s = -1.0",
        ] {
            let err = Config::from_toml_str(&format!("[events]\n{bad}\n"), "h.toml").unwrap_err();
            let key = bad.split(' ').next().unwrap();
            assert!(err.to_string().contains(&format!("events.{key}")), "{err}");
        }
    }

    #[test]
    fn loop_correction_limit_is_checked() {
        let off = Config::from_toml_str("[loop_closing]\nmax_correction_deg = 180\n", "l.toml");
        assert_eq!(off.unwrap().loop_closing.max_correction_deg, 180.0);
        for bad in ["-1.0", "181.0"] {
            let toml = format!("[loop_closing]\nmax_correction_deg = {bad}\n");
            let err = Config::from_toml_str(&toml, "l.toml")
                .unwrap_err()
                .to_string();
            assert!(
                err.contains("loop_closing.max_correction_deg")
                    && err.contains(bad.trim_end_matches(".0")),
                "{err}"
            );
        }
    }

    #[test]
    fn events_geometry_is_checked() {
        assert_eq!(Config::default().fusion.events_geometry, "auto");
        let frame =
            Config::from_toml_str("[fusion]\nevents_geometry = \"frame\"\n", "g.toml").unwrap();
        assert_eq!(frame.fusion.events_geometry, "frame");
        let err =
            Config::from_toml_str("[fusion]\nevents_geometry = \"both\"\n", "g.toml").unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.contains("fusion.events_geometry") && msg.contains("both"),
            "{msg}"
        );
    }

    #[test]
    fn exposure_recovery_settings_are_checked() {
        let off = Config::from_toml_str("[fusion]\nrecover_exposure = false\n", "e.toml").unwrap();
        assert!(!off.fusion.recover_exposure);
        assert!(Config::default().fusion.recover_exposure);
        for bad in ["recover_min_snr = -1.0", "recover_min_snr = inf"] {
            let err = Config::from_toml_str(&format!("[fusion]\n{bad}\n"), "e.toml").unwrap_err();
            assert!(err.to_string().contains("fusion.recover_min_snr"), "{err}");
        }
    }

    #[test]
    fn features_section_checks_extractor_and_device() {
        let c = Config::from_toml_str(
            "[features]\nextractor = \"sift\"\ndevice = \"cuda:1\"\n",
            "f.toml",
        )
        .unwrap();
        assert_eq!(c.features.extractor, "sift");
        assert_eq!(c.features.max_keypoints, 0, "0: from the image size");
        let err =
            Config::from_toml_str("[features]\nextractor = \"surf\"\n", "f.toml").unwrap_err();
        assert!(err.to_string().contains("features.extractor"), "{err}");
        let err = Config::from_toml_str("[features]\ndevice = \"gpu\"\n", "f.toml").unwrap_err();
        assert!(err.to_string().contains("features.device"), "{err}");
    }

    #[test]
    fn features_section_checks_precision_and_scales_against_the_extractor() {
        let c = Config::from_toml_str(
            "[features]\nweights = \"faster2d2_WASF_N16\"\nprecision = \"int8\"\nscales = [1.0]\n",
            "f.toml",
        )
        .unwrap();
        assert_eq!(
            (c.features.precision.as_str(), c.features.scales.as_slice()),
            ("int8", &[1.0][..])
        );
        let bad = [
            ("precision = \"int4\"", "features.precision"),
            (
                "extractor = \"superpoint\"\nprecision = \"int8\"",
                "features.precision",
            ),
            (
                "extractor = \"orb\"\nprecision = \"bfloat16\"",
                "features.precision",
            ),
            ("scales = [1.0, 0.0]", "features.scales"),
            ("scales = [1.5]", "features.scales"),
            ("extractor = \"sift\"\nscales = [1.0]", "features.scales"),
        ];
        for (body, key) in bad {
            let err =
                Config::from_toml_str(&format!("[features]\n{body}\n"), "f.toml").unwrap_err();
            assert!(err.to_string().contains(key), "{body}: {err}");
        }
    }

    #[test]
    fn wrong_type_is_rejected() {
        let err = Config::from_toml_str("[triangulation]\nmin_depth_m = \"near\"\n", "x.toml")
            .unwrap_err();
        assert!(err.to_string().contains("min_depth_m"), "{err}");
    }
}
