//! Synthetic stereo feature sequences with ground truth, for tests and benchmarks.
//!
//! Landmarks lie on a rough cylinder around the world y axis (y points down); the camera
//! moves on a circle inside it, looking outwards, so a sequence of more than one turn
//! revisits its start. Each landmark has a random unit descriptor; every observation adds
//! Gaussian noise to it (renormalised) and to its pixel, and a fraction of observations are
//! outliers placed at random pixels. `drift_deg` injects drift: landmarks outside the start
//! sector (|azimuth| > `start_half_angle_deg`) appear rotated about the y axis by an angle
//! growing linearly to `drift_deg` and shifted along y by up to `drift_m` at the last frame, so odometry drifts away from the truth
//! while the start sector stays undeformed (a loop closure there can recover).

use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::StereoCalibration;
use crate::geometry::{Se3, So3};

/// Parameters of [`generate`].
#[derive(Clone, Debug)]
pub struct SyntheticOptions {
    /// Camera calibration.
    pub calib: StereoCalibration,
    /// Number of landmarks.
    pub landmarks: usize,
    /// Number of frames.
    pub frames: usize,
    /// Turns of the circle covered by the whole sequence.
    pub turns: f64,
    /// Radius of the camera circle, metres.
    pub radius_m: f64,
    /// Landmark distance from the axis: uniform in this range, metres.
    pub wall_m: (f64, f64),
    /// Landmark height: uniform in ±this, metres.
    pub half_height_m: f64,
    /// Pixel noise σ, pixels.
    pub pixel_noise: f64,
    /// Fraction of observations replaced by random pixels.
    pub outlier_fraction: f64,
    /// Descriptor length (unit float rows).
    pub descriptor_dim: usize,
    /// Per-component σ of the noise added to each observation's descriptor.
    pub descriptor_noise: f64,
    /// Injected yaw drift reached at the last frame, degrees (0: none).
    pub drift_deg: f64,
    /// Injected vertical (world y) drift reached at the last frame, metres (0: none).
    pub drift_m: f64,
    /// Half-width of the undeformed start sector, degrees.
    pub start_half_angle_deg: f64,
    /// Frame period, nanoseconds.
    pub period_ns: i64,
    /// Random seed.
    pub seed: u64,
    /// Centre of the camera pair the features are measured with, in the left camera's axes
    /// (same orientation and baseline), metres: zero for the left camera itself; e.g. an event
    /// pair beside the frame cameras. `world_from_cam` stays the left camera's pose.
    pub viewpoint_m: [f64; 3],
}

impl Default for SyntheticOptions {
    fn default() -> Self {
        Self {
            calib: StereoCalibration {
                fx: 400.0,
                fy: 400.0,
                cx: 320.0,
                cy: 240.0,
                baseline_m: 0.12,
                width: 640,
                height: 480,
            },
            landmarks: 3000,
            frames: 200,
            turns: 0.5,
            radius_m: 1.0,
            wall_m: (4.0, 7.0),
            half_height_m: 1.5,
            pixel_noise: 0.5,
            outlier_fraction: 0.1,
            descriptor_dim: 32,
            descriptor_noise: 0.03,
            drift_deg: 0.0,
            drift_m: 0.0,
            start_half_angle_deg: 60.0,
            period_ns: 50_000_000,
            seed: 1,
            viewpoint_m: [0.0; 3],
        }
    }
}

/// One image's features.
#[derive(Clone, Debug, Default)]
pub struct SyntheticView {
    /// Keypoints (x, y) interleaved, pixels.
    pub keypoints: Vec<f32>,
    /// Descriptors, `descriptor_dim` values per keypoint.
    pub descriptors: Vec<f32>,
}

/// One stereo frame with its ground truth.
#[derive(Clone, Debug)]
pub struct SyntheticFrame {
    /// Timestamp, nanoseconds.
    pub t_ns: i64,
    /// True `world_from_cam` of the left camera.
    pub world_from_cam: Se3,
    /// Left features.
    pub left: SyntheticView,
    /// Right features.
    pub right: SyntheticView,
}

/// The camera pose at azimuth `theta` (radians) on the circle, looking outwards.
pub fn circle_pose(theta: f64, radius_m: f64) -> Se3 {
    let z = Vector3::new(theta.sin(), 0.0, theta.cos());
    let y = Vector3::new(0.0, 1.0, 0.0);
    let x = y.cross(&z);
    let r = Matrix3::from_columns(&[x, y, z]);
    let rotation = So3::from_matrix(&r).unwrap_or_else(|_| So3::identity());
    Se3::new(rotation, z * radius_m)
}

fn unit(rng: &mut ChaCha8Rng, dim: usize, base: Option<&[f32]>, sigma: f64) -> Vec<f32> {
    let n = Normal::new(0.0, 1.0).unwrap_or_else(|_| unreachable!());
    let mut v: Vec<f32> = (0..dim)
        .map(|i| {
            let e = n.sample(rng);
            match base {
                Some(b) => b[i] + (sigma * e) as f32,
                None => e as f32,
            }
        })
        .collect();
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
    v.iter_mut().for_each(|x| *x /= norm);
    v
}

/// Generates a sequence.
pub fn generate(o: &SyntheticOptions) -> Vec<SyntheticFrame> {
    let mut rng = ChaCha8Rng::seed_from_u64(o.seed);
    let c = &o.calib;
    let landmarks: Vec<(Vector3<f64>, Vec<f32>, f64)> = (0..o.landmarks)
        .map(|_| {
            let a = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
            let r = rng.random_range(o.wall_m.0..o.wall_m.1);
            let y = rng.random_range(-o.half_height_m..o.half_height_m);
            let d = unit(&mut rng, o.descriptor_dim, None, 0.0);
            (Vector3::new(r * a.sin(), y, r * a.cos()), d, a)
        })
        .collect();
    let noise = Normal::new(0.0, o.pixel_noise.max(1e-12)).unwrap_or_else(|_| unreachable!());
    let viewpoint = Vector3::from(o.viewpoint_m);
    let steps = o.frames.saturating_sub(1).max(1) as f64;
    (0..o.frames)
        .map(|i| {
            let s = i as f64 / steps;
            let theta = 2.0 * std::f64::consts::PI * o.turns * s;
            let pose = circle_pose(theta, o.radius_m);
            let cam_from_world = pose.inverse();
            let drift = Se3::new(
                So3::exp(&Vector3::new(0.0, (o.drift_deg * s).to_radians(), 0.0)),
                Vector3::new(0.0, o.drift_m * s, 0.0),
            );
            let drifting = o.drift_deg != 0.0 || o.drift_m != 0.0;
            let mut left = SyntheticView::default();
            let mut right = SyntheticView::default();
            for (x, d, azimuth) in &landmarks {
                let deformed = azimuth.abs() > o.start_half_angle_deg.to_radians();
                let xw = if deformed && drifting {
                    drift.transform_point(x)
                } else {
                    *x
                };
                let p = cam_from_world.transform_point(&xw) - viewpoint;
                if p.z < 0.3 {
                    continue;
                }
                let u = c.fx * p.x / p.z + c.cx;
                let v = c.fy * p.y / p.z + c.cy;
                let ur = u - c.fx * c.baseline_m / p.z;
                let inside = |u: f64, v: f64| {
                    u >= 0.0 && v >= 0.0 && u < c.width as f64 && v < c.height as f64
                };
                if !inside(u, v) {
                    continue;
                }
                let (mut ul, mut vl) = (u + noise.sample(&mut rng), v + noise.sample(&mut rng));
                if rng.random::<f64>() < o.outlier_fraction {
                    ul = rng.random_range(0.0..c.width as f64);
                    vl = rng.random_range(0.0..c.height as f64);
                }
                left.keypoints.extend([ul as f32, vl as f32]);
                left.descriptors.extend(unit(
                    &mut rng,
                    o.descriptor_dim,
                    Some(d),
                    o.descriptor_noise,
                ));
                if inside(ur, v) {
                    let (mut u2, mut v2) =
                        (ur + noise.sample(&mut rng), v + noise.sample(&mut rng));
                    if rng.random::<f64>() < o.outlier_fraction {
                        u2 = rng.random_range(0.0..c.width as f64);
                        v2 = rng.random_range(0.0..c.height as f64);
                    }
                    right.keypoints.extend([u2 as f32, v2 as f32]);
                    right.descriptors.extend(unit(
                        &mut rng,
                        o.descriptor_dim,
                        Some(d),
                        o.descriptor_noise,
                    ));
                }
            }
            SyntheticFrame {
                t_ns: i as i64 * o.period_ns,
                world_from_cam: pose,
                left,
                right,
            }
        })
        .collect()
}
