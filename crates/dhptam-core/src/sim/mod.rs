//! The stereo events+frames simulator.
//!
//! - [`texture`]: mip-mapped grey textures with trilinear lookup, procedural textures;
//! - [`scene`]: the textured room with boxes, analytic ray intersection;
//! - [`render`]: per-pixel ray casting through any camera model (rayon over rows);
//! - [`frames`]: lighting profiles, auto-exposure, sensor noise and 8-bit quantisation;
//! - [`events`]: the ESIM event generator;
//! - [`trajectory`]: sampled SE(3) trajectories, file readers, built-in motions, fitting;
//! - [`simulator`]: ties them together for a four-camera rig.

pub mod events;
pub mod frames;
pub mod render;
pub mod scene;
pub mod simulator;
pub mod texture;
pub mod trajectory;

pub use events::{Event, EventGenerator, EventParams};
pub use frames::{Profile, Sensor, SensorParams};
pub use render::{render, render_depth, render_image, RayTable};
pub use scene::{CameraRegion, Scene};
pub use simulator::{FramePair, RigCamera, SimParams, Simulator, CAMERA_COUNT};
pub use texture::{Texture, Wrap};
pub use trajectory::{look_at, BuiltinMotion, Trajectory};

use crate::config::SimConfig;

impl SimConfig {
    /// The simulator parameters this configuration section describes.
    pub fn params(&self) -> SimParams {
        let ms = |v: f64| (v * 1e6).round() as i64;
        SimParams {
            events: EventParams {
                contrast_on: self.contrast_on,
                contrast_off: self.contrast_off,
                contrast_sigma: self.contrast_sigma,
                refractory_ns: (self.refractory_us * 1e3).round() as i64,
                noise_rate_hz: self.noise_rate_hz,
                noise_reference_intensity: self.noise_reference_intensity,
            },
            sensor: SensorParams {
                min_exposure_ns: ms(self.min_exposure_ms),
                max_exposure_ns: ms(self.max_exposure_ms),
                initial_exposure_ns: ms(self.initial_exposure_ms),
                target_mean: self.ae_target_mean,
                ae_rate: self.ae_rate,
                sensitivity: self.sensitivity_e_per_s,
                full_well: self.full_well_e,
                read_noise: self.read_noise_e,
            },
            blur_samples: self.blur_samples,
            max_log_step: self.max_log_step,
            min_step_ns: (self.min_render_step_us * 1e3).round() as i64,
            max_step_ns: (self.max_render_step_us * 1e3).round() as i64,
            log_eps: self.log_eps,
        }
    }
}
