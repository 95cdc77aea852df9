//! The simulator: a scene, a four-camera rig on a trajectory, lighting, frames and events.
//!
//! Cameras are indexed like TUM-VIE / Basalt: 0 left frame, 1 right frame, 2 left event,
//! 3 right event. Frames are produced on request at their exposure start; events are produced
//! up to a requested time, so a caller can interleave the two and stream both to disk.
//!
//! Event cameras are rendered at an adaptive rate: the next render is placed so that the
//! largest per-pixel change of log intensity stays under `max_log_step` (predicted from the
//! previous step's rate of change; a render that overshoots is discarded and the step
//! halved), within `[min_step_ns, max_step_ns]`. Between two accepted renders the log
//! intensity is treated as linear (see [`super::events`]).

use super::events::{Event, EventGenerator, EventParams};
use super::frames::{Profile, Sensor, SensorParams};
use super::render::{render, render_depth, RayTable};
use super::scene::Scene;
use super::trajectory::Trajectory;
use crate::error::{Error, Result};
use crate::geometry::{Camera, Se3};

/// Number of cameras in the rig.
pub const CAMERA_COUNT: usize = 4;

/// One camera of the rig.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigCamera {
    /// Model, parameters and size.
    pub camera: Camera,
    /// Pose of the camera in the body (IMU) frame.
    pub imu_from_cam: Se3,
}

/// Everything that shapes the output besides the scene, the rig and the trajectory.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimParams {
    /// The event pixel model.
    pub events: EventParams,
    /// The frame sensor and its auto-exposure.
    pub sensor: SensorParams,
    /// Renders averaged over a frame's exposure (motion blur); at least 1.
    pub blur_samples: u32,
    /// Largest per-pixel log-intensity change between two event-camera renders.
    pub max_log_step: f64,
    /// Shortest interval between event-camera renders, nanoseconds.
    pub min_step_ns: i64,
    /// Longest interval between event-camera renders, nanoseconds.
    pub max_step_ns: i64,
    /// Offset added to the irradiance before taking its logarithm (a pixel's dark level).
    pub log_eps: f64,
}

impl SimParams {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<()> {
        self.events.validate()?;
        self.sensor.validate()?;
        let ok = self.blur_samples >= 1
            && self.max_log_step > 0.0
            && self.min_step_ns > 0
            && self.max_step_ns >= self.min_step_ns
            && self.log_eps > 0.0;
        if ok {
            Ok(())
        } else {
            Err(Error::invalid(
                "simulation parameters",
                "blur_samples ≥ 1, max_log_step > 0, 0 < min_step ≤ max_step, log_eps > 0",
                format!("{self:?}"),
            ))
        }
    }
}

/// A stereo frame pair.
#[derive(Clone, Debug, PartialEq)]
pub struct FramePair {
    /// Start of exposure, nanoseconds.
    pub t_ns: i64,
    /// Exposure time, nanoseconds.
    pub exposure_ns: i64,
    /// Left image, row-major 8-bit.
    pub left: Vec<u8>,
    /// Right image, row-major 8-bit.
    pub right: Vec<u8>,
}

struct EventCamera {
    generator: EventGenerator,
    next_step_ns: i64,
}

/// The running simulation.
pub struct Simulator {
    scene: Scene,
    rig: [RigCamera; CAMERA_COUNT],
    rays: Vec<RayTable>,
    trajectory: Trajectory,
    profile: Profile,
    duration_ns: i64,
    params: SimParams,
    sensor: Sensor,
    frame_index: u64,
    event_cameras: Vec<EventCamera>,
    renders: u64,
}

impl Simulator {
    /// Sets up the rig at time 0 (the event cameras take their first render there).
    /// `duration_ns` defines the lighting profile's time axis.
    pub fn new(
        scene: Scene,
        rig: [RigCamera; CAMERA_COUNT],
        trajectory: Trajectory,
        profile: Profile,
        duration_ns: i64,
        params: SimParams,
        seed: u64,
    ) -> Result<Self> {
        params.validate()?;
        scene.validate()?;
        if duration_ns <= 0 {
            return Err(Error::invalid(
                "duration",
                "a positive duration",
                duration_ns,
            ));
        }
        let rays: Vec<RayTable> = rig.iter().map(|c| RayTable::new(&c.camera)).collect();
        let mut sim = Self {
            scene,
            rig,
            rays,
            trajectory,
            profile,
            duration_ns,
            params,
            sensor: Sensor::new(params.sensor, seed)?,
            frame_index: 0,
            event_cameras: Vec::new(),
            renders: 0,
        };
        for (i, cam) in [2usize, 3].into_iter().enumerate() {
            let log = sim.log_image(cam, 0);
            let generator = EventGenerator::new(
                sim.rays[cam].width(),
                params.events,
                seed.wrapping_add(1 + i as u64),
                0,
                &log,
            )?;
            sim.event_cameras.push(EventCamera {
                generator,
                next_step_ns: params.min_step_ns,
            });
        }
        Ok(sim)
    }

    /// The rig.
    pub fn rig(&self) -> &[RigCamera; CAMERA_COUNT] {
        &self.rig
    }

    /// The scene.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The body trajectory.
    pub fn trajectory(&self) -> &Trajectory {
        &self.trajectory
    }

    /// Renders performed so far (frames and events, all cameras).
    pub fn render_count(&self) -> u64 {
        self.renders
    }

    /// Pose of camera `cam` at `t_ns`.
    pub fn world_from_cam(&self, cam: usize, t_ns: i64) -> Se3 {
        self.trajectory.pose_at(t_ns) * self.rig[cam].imu_from_cam
    }

    /// The lighting factor at `t_ns`.
    pub fn illumination(&self, t_ns: i64) -> f64 {
        self.profile
            .illumination(t_ns as f64 / self.duration_ns as f64)
    }

    /// Radiance under unit illumination seen by camera `cam` at `t_ns`.
    pub fn render_radiance(&mut self, cam: usize, t_ns: i64) -> Vec<f32> {
        let mut out = vec![0.0; self.rays[cam].len()];
        let pose = self.world_from_cam(cam, t_ns);
        render(&self.scene, &self.rays[cam], &pose, &mut out);
        self.renders += 1;
        out
    }

    /// Ground-truth depth (camera-frame z, metres; NaN where nothing is hit) seen by camera
    /// `cam` at `t_ns`; see [`render_depth`]. Not counted in the event renders.
    pub fn render_depth(&self, cam: usize, t_ns: i64) -> Vec<f32> {
        let mut out = vec![0.0; self.rays[cam].len()];
        let pose = self.world_from_cam(cam, t_ns);
        render_depth(&self.scene, &self.rays[cam], &pose, &mut out);
        out
    }

    /// `log(illumination · radiance + log_eps)` seen by camera `cam` at `t_ns`.
    fn log_image(&mut self, cam: usize, t_ns: i64) -> Vec<f64> {
        let illumination = self.illumination(t_ns);
        let eps = self.params.log_eps;
        self.render_radiance(cam, t_ns)
            .into_iter()
            .map(|r| (illumination * f64::from(r) + eps).ln())
            .collect()
    }

    /// The next stereo frame pair, exposed from `t_ns` for the auto-exposure's current choice
    /// (times the profile's factor); updates the auto-exposure from the left image.
    pub fn frame_pair(&mut self, t_ns: i64) -> FramePair {
        // The profile's factor may push below the auto-exposure's range (flicker) but never
        // beyond the longest exposure the camera allows.
        let exposure_ns = ((self.sensor.exposure_ns() as f64
            * self.profile.exposure_factor(self.frame_index))
        .round() as i64)
            .clamp(1, self.params.sensor.max_exposure_ns);
        let k = self.params.blur_samples as i64;
        let mut images = Vec::with_capacity(2);
        for cam in [0usize, 1] {
            let mut sum = vec![0.0f32; self.rays[cam].len()];
            for j in 0..k {
                // Sample times at the centres of k equal slices of the exposure.
                let t = t_ns + (2 * j + 1) * exposure_ns / (2 * k);
                let illumination = self.illumination(t) as f32;
                for (s, r) in sum.iter_mut().zip(self.render_radiance(cam, t)) {
                    *s += illumination * r;
                }
            }
            let inv = 1.0 / k as f32;
            sum.iter_mut().for_each(|s| *s *= inv);
            images.push(self.sensor.capture(&sum, exposure_ns));
        }
        let right = images.pop().unwrap_or_default();
        let left = images.pop().unwrap_or_default();
        let mean = left.iter().map(|&v| f64::from(v)).sum::<f64>() / left.len().max(1) as f64;
        self.sensor.auto_expose(mean, exposure_ns);
        self.frame_index += 1;
        FramePair {
            t_ns,
            exposure_ns,
            left,
            right,
        }
    }

    /// Time up to which events have been generated, nanoseconds.
    pub fn events_time_ns(&self) -> i64 {
        self.event_cameras
            .iter()
            .map(|c| c.generator.time_ns())
            .min()
            .unwrap_or(0)
    }

    /// Generates the events of both event cameras up to `t_end_ns`; returns `[left, right]`,
    /// each sorted by time.
    pub fn events_until(&mut self, t_end_ns: i64) -> Result<[Vec<Event>; 2]> {
        let mut out = [Vec::new(), Vec::new()];
        for (i, cam) in [2usize, 3].into_iter().enumerate() {
            self.advance_event_camera(i, cam, t_end_ns, &mut out[i])?;
        }
        Ok(out)
    }

    fn advance_event_camera(
        &mut self,
        i: usize,
        cam: usize,
        t_end_ns: i64,
        out: &mut Vec<Event>,
    ) -> Result<()> {
        let SimParams {
            max_log_step,
            min_step_ns,
            max_step_ns,
            ..
        } = self.params;
        loop {
            let t_prev = self.event_cameras[i].generator.time_ns();
            if t_prev >= t_end_ns {
                return Ok(());
            }
            let step = self.event_cameras[i]
                .next_step_ns
                .clamp(min_step_ns, max_step_ns);
            let t = (t_prev + step).min(t_end_ns);
            let log = self.log_image(cam, t);
            let change = log
                .iter()
                .zip(self.event_cameras[i].generator.previous_log())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f64, f64::max);
            let taken = t - t_prev;
            if change > max_log_step && taken > min_step_ns {
                // Overshot: retry with half the step.
                self.event_cameras[i].next_step_ns = (taken / 2).max(min_step_ns);
                continue;
            }
            self.event_cameras[i].generator.advance(t, &log, 1.0, out)?;
            // Aim the next step at 80 % of the bound at the current rate of change.
            let rate = change / taken as f64;
            let next = if rate > 0.0 {
                (0.8 * max_log_step / rate) as i64
            } else {
                max_step_ns
            };
            self.event_cameras[i].next_step_ns = next.clamp(min_step_ns, max_step_ns);
        }
    }
}
