//! Camera trajectories: sampled `world_from_body` poses with geodesic interpolation,
//! readers for TUM and CSV trajectory files, built-in motions inside the desk room, and the
//! fitting of a recorded trajectory into the room.
//!
//! The body is the rig's IMU frame; cameras hang off it through their `imu_from_cam`.

use std::f64::consts::{PI, TAU};
use std::path::Path;

use nalgebra::{Matrix3, Vector3};

use super::scene::CameraRegion;
use crate::error::{Error, Result};
use crate::geometry::{Se3, So3};

/// Poses sampled in time, interpolated on SE(3) geodesics in between.
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory {
    t_ns: Vec<i64>,
    world_from_body: Vec<Se3>,
}

impl Trajectory {
    /// A trajectory from strictly increasing times and one pose per time (at least two).
    pub fn new(t_ns: Vec<i64>, world_from_body: Vec<Se3>) -> Result<Self> {
        if t_ns.len() != world_from_body.len() || t_ns.len() < 2 {
            return Err(Error::invalid(
                "trajectory",
                "at least two samples, one pose per time",
                format!("{} times and {} poses", t_ns.len(), world_from_body.len()),
            ));
        }
        if let Some(i) = t_ns.windows(2).position(|w| w[1] <= w[0]) {
            return Err(Error::invalid(
                format!("trajectory time[{}]", i + 1),
                "strictly increasing times",
                format!("{} after {}", t_ns[i + 1], t_ns[i]),
            ));
        }
        Ok(Self {
            t_ns,
            world_from_body,
        })
    }

    /// Sample times, nanoseconds.
    pub fn times_ns(&self) -> &[i64] {
        &self.t_ns
    }

    /// Sampled poses.
    pub fn poses(&self) -> &[Se3] {
        &self.world_from_body
    }

    /// First and last sample time.
    pub fn span_ns(&self) -> (i64, i64) {
        (self.t_ns[0], self.t_ns[self.t_ns.len() - 1])
    }

    /// The pose at `t_ns`, clamped to the first/last sample outside the span.
    pub fn pose_at(&self, t_ns: i64) -> Se3 {
        let i = self.t_ns.partition_point(|&t| t <= t_ns);
        if i == 0 {
            return self.world_from_body[0];
        }
        if i == self.t_ns.len() {
            return self.world_from_body[i - 1];
        }
        let (t0, t1) = (self.t_ns[i - 1], self.t_ns[i]);
        let s = (t_ns - t0) as f64 / (t1 - t0) as f64;
        self.world_from_body[i - 1].interpolate(&self.world_from_body[i], s)
    }

    /// Samples `f(t)` (t in seconds from 0) every `1/rate_hz` over `[0, duration_ns]`.
    pub fn from_fn(duration_ns: i64, rate_hz: f64, f: impl Fn(f64) -> Se3) -> Result<Self> {
        if duration_ns <= 0 || !rate_hz.is_finite() || rate_hz <= 0.0 {
            return Err(Error::invalid(
                "trajectory duration and rate",
                "positive values",
                format!("{duration_ns} ns at {rate_hz} Hz"),
            ));
        }
        let step = (1e9 / rate_hz).round().max(1.0) as i64;
        let mut t_ns: Vec<i64> = (0..)
            .map(|k| k * step)
            .take_while(|&t| t < duration_ns)
            .collect();
        t_ns.push(duration_ns);
        let poses = t_ns.iter().map(|&t| f(t as f64 * 1e-9)).collect();
        Self::new(t_ns, poses)
    }

    /// Reads a TUM trajectory (`t[s] x y z qx qy qz qw`, whitespace separated, `#` comments).
    pub fn read_tum(path: &Path) -> Result<Self> {
        read_table(
            path,
            |line| line.split_whitespace().collect::<Vec<_>>(),
            1e9,
        )
    }

    /// Reads a CSV trajectory (`timestamp[ns], x, y, z, qx, qy, qz, qw`, `#` comments).
    pub fn read_csv(path: &Path) -> Result<Self> {
        read_table(
            path,
            |line| line.split(',').map(str::trim).collect::<Vec<_>>(),
            1.0,
        )
    }

    /// The same motion, rigidly moved, scaled and re-timed into `region`: times shift to
    /// start at 0; positions are scaled about their centroid so that their bounding box fits
    /// the region (never enlarged) and centred in it; the whole trajectory is rotated about
    /// the vertical so that the mean optical axis (body z) points at the region's target, and
    /// tilted so that it looks level-or-down at it.
    pub fn fitted_into(&self, region: &CameraRegion) -> Result<Self> {
        let n = self.world_from_body.len() as f64;
        let centroid = self
            .world_from_body
            .iter()
            .fold(Vector3::zeros(), |acc, p| acc + p.translation)
            / n;
        let mean_axis = self
            .world_from_body
            .iter()
            .fold(Vector3::zeros(), |acc, p| acc + p.rotation * Vector3::z());
        if mean_axis.norm() < 1e-6 * n {
            return Err(Error::numerical(
                "trajectory fitting",
                "the camera looks in every direction equally; no mean viewing direction",
            ));
        }
        let centre = (region.min + region.max) / 2.0;
        let wanted = (region.target - centre).normalize();
        // The rotation taking the mean axis onto the wanted direction.
        let align = So3::from_unit_quaternion(
            nalgebra::UnitQuaternion::rotation_between(&mean_axis.normalize(), &wanted)
                .unwrap_or_else(|| {
                    nalgebra::UnitQuaternion::from_axis_angle(&Vector3::z_axis(), PI)
                }),
        );
        let rotated: Vec<Vector3<f64>> = self
            .world_from_body
            .iter()
            .map(|p| align * (p.translation - centroid))
            .collect();
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for p in &rotated {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        let half_room = (region.max - region.min) / 2.0;
        let mut scale: f64 = 1.0;
        for a in 0..3 {
            let half_extent = (hi[a] - lo[a]) / 2.0;
            if half_extent > 1e-12 {
                scale = scale.min(half_room[a] / half_extent);
            }
        }
        let middle = (lo + hi) / 2.0;
        let t0 = self.t_ns[0];
        let poses = self
            .world_from_body
            .iter()
            .zip(&rotated)
            .map(|(p, r)| Se3::new(align * p.rotation, centre + (r - middle) * scale))
            .collect();
        Self::new(self.t_ns.iter().map(|t| t - t0).collect(), poses)
    }
}

fn read_table(path: &Path, split: impl Fn(&str) -> Vec<&str>, to_ns: f64) -> Result<Trajectory> {
    let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
        action: "read",
        path: path.to_owned(),
        source,
    })?;
    let mut t_ns = Vec::new();
    let mut poses = Vec::new();
    let parse_error = |line: usize, message: String| Error::Parse {
        path: path.to_owned(),
        line,
        message,
    };
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields = split(line);
        if fields.len() != 8 {
            return Err(parse_error(
                i + 1,
                format!(
                    "expected 8 fields (t x y z qx qy qz qw), found {}",
                    fields.len()
                ),
            ));
        }
        let mut v = [0.0; 8];
        for (k, f) in fields.iter().enumerate() {
            v[k] = f
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| {
                    parse_error(i + 1, format!("field {} is not a number: {f:?}", k + 1))
                })?;
        }
        let pose =
            Se3::from_translation_quaternion_xyzw([v[1], v[2], v[3]], [v[4], v[5], v[6], v[7]])
                .map_err(|e| parse_error(i + 1, e.to_string()))?;
        let t = (v[0] * to_ns).round() as i64;
        if let Some(&last) = t_ns.last() {
            if t <= last {
                return Err(parse_error(
                    i + 1,
                    format!("time {} does not increase", v[0]),
                ));
            }
        }
        t_ns.push(t);
        poses.push(pose);
    }
    if t_ns.len() < 2 {
        return Err(parse_error(
            text.lines().count().max(1),
            "fewer than two poses".into(),
        ));
    }
    Trajectory::new(t_ns, poses)
}

/// The built-in motions.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BuiltinMotion {
    /// A slow spiral in front of the desk, looking at it (the demo's motion).
    DeskSpiral,
    /// Back and forth along the x axis at a fixed orientation, like TUM-VIE `1d-trans`.
    Translation1d,
    /// Fast shaking in all six degrees of freedom around a point in front of the desk.
    Shake6dof,
    /// One loop around the middle of the room looking outwards, ending where it started
    /// (revisits the start for loop closure).
    ClosedLoop,
}

impl BuiltinMotion {
    /// Every motion with its name.
    pub const ALL: [(&'static str, BuiltinMotion); 4] = [
        ("desk_spiral", BuiltinMotion::DeskSpiral),
        ("translation_1d", BuiltinMotion::Translation1d),
        ("shake_6dof", BuiltinMotion::Shake6dof),
        ("closed_loop", BuiltinMotion::ClosedLoop),
    ];

    /// Parses a motion name.
    pub fn parse(name: &str) -> Result<Self> {
        Self::ALL
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, m)| *m)
            .ok_or_else(|| {
                Error::invalid(
                    "trajectory",
                    "desk_spiral, translation_1d, shake_6dof or closed_loop",
                    format!("{name:?}"),
                )
            })
    }

    /// The motion over `duration_ns`, sampled at 1 kHz, in the desk room (`region`).
    pub fn trajectory(self, duration_ns: i64, region: &CameraRegion) -> Result<Trajectory> {
        let duration_s = duration_ns as f64 * 1e-9;
        let target = region.target;
        let start = Vector3::new(0.0, -0.2, 1.3);
        match self {
            BuiltinMotion::DeskSpiral => Trajectory::from_fn(duration_ns, 1000.0, |t| {
                // Radius grows from 0.1 to 0.35 m while the camera circles twice per 10 s.
                let s = t / duration_s.max(1e-9);
                let angle = TAU * t / 5.0;
                let radius = 0.1 + 0.25 * s;
                let eye = start
                    + Vector3::new(
                        radius * angle.cos(),
                        0.15 * (TAU * t / 7.0).sin(),
                        0.6 * radius * angle.sin(),
                    );
                look_at(&eye, &(target + Vector3::new(0.15 * angle.sin(), 0.0, 0.0)))
            }),
            BuiltinMotion::Translation1d => Trajectory::from_fn(duration_ns, 1000.0, |t| {
                let eye = start + Vector3::new(0.5 * (TAU * t / 4.0).sin(), 0.0, 0.0);
                Se3::new(look_at(&start, &target).rotation, eye)
            }),
            BuiltinMotion::Shake6dof => Trajectory::from_fn(duration_ns, 1000.0, |t| {
                let wobble = |f: f64, phase: f64| (TAU * f * t + phase).sin();
                let eye = start
                    + Vector3::new(
                        0.08 * wobble(1.1, 0.0),
                        0.06 * wobble(1.7, 1.0),
                        0.07 * wobble(1.3, 2.0),
                    );
                let base = look_at(&eye, &target);
                let shake = So3::exp(&Vector3::new(
                    0.15 * wobble(1.9, 0.5),
                    0.12 * wobble(2.3, 1.5),
                    0.10 * wobble(1.5, 2.5),
                ));
                Se3::new(base.rotation * shake, eye)
            }),
            BuiltinMotion::ClosedLoop => {
                let centre = Vector3::new(0.0, 0.25, 1.3);
                let radius = 0.3;
                Trajectory::from_fn(duration_ns, 1000.0, |t| {
                    // One full turn over 90 % of the sequence, then the start view again.
                    let s = (t / (0.9 * duration_s.max(1e-9))).min(1.0);
                    let phase = 0.5 - 0.5 * (PI * s).cos(); // smooth start and stop
                    let heading = PI / 2.0 + TAU * phase;
                    let out = Vector3::new(heading.cos(), heading.sin(), 0.0);
                    let eye = centre + out * radius;
                    look_at(&eye, &(eye + out * 2.0 - Vector3::new(0.0, 0.0, 0.6)))
                })
            }
        }
    }
}

/// `world_from_cam` of a camera at `eye` looking at `target` (z forward, x right, y down,
/// world z up).
pub fn look_at(eye: &Vector3<f64>, target: &Vector3<f64>) -> Se3 {
    let z = (target - eye).normalize();
    let up = Vector3::z();
    let x = {
        let c = z.cross(&up);
        if c.norm() < 1e-9 {
            Vector3::x()
        } else {
            c.normalize()
        }
    };
    let y = z.cross(&x);
    let r = Matrix3::from_columns(&[x, y, z]);
    // Orthonormal by construction, determinant +1: from_matrix cannot fail here.
    let rotation = So3::from_matrix(&r).unwrap_or_default();
    Se3::new(rotation, *eye)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::scene::Scene;

    #[test]
    fn look_at_points_the_optical_axis_at_the_target_with_image_down_being_world_down() {
        let eye = Vector3::new(0.0, 0.0, 1.0);
        let pose = look_at(&eye, &Vector3::new(0.0, 2.0, 1.0));
        let axis = pose.rotation * Vector3::z();
        assert!((axis - Vector3::y()).norm() < 1e-12);
        assert!((pose.rotation * Vector3::y() + Vector3::z()).norm() < 1e-12);
        assert!((pose.rotation * Vector3::x() - Vector3::x()).norm() < 1e-12);
    }

    #[test]
    fn interpolation_hits_samples_and_midpoints() {
        let a = Se3::identity();
        let b = Se3::exp(&nalgebra::Vector6::new(1.0, 0.0, 0.0, 0.0, 0.0, 0.4));
        let traj = Trajectory::new(vec![0, 100], vec![a, b]).unwrap();
        assert_eq!(traj.pose_at(-5), a);
        assert_eq!(traj.pose_at(100), b);
        let mid = traj.pose_at(50);
        assert!((mid.log() - b.log() * 0.5).norm() < 1e-12);
    }

    #[test]
    fn builtins_stay_inside_the_room_region() {
        let region = Scene::desk_room_region();
        for (_, motion) in BuiltinMotion::ALL {
            let traj = motion.trajectory(10_000_000_000, &region).unwrap();
            for p in traj.poses() {
                let t = p.translation;
                assert!(
                    (0..3).all(|a| t[a] >= region.min[a] && t[a] <= region.max[a]),
                    "{motion:?} leaves the region at {t:?}"
                );
            }
        }
    }

    #[test]
    fn fitting_scales_into_the_region_and_looks_at_the_target() {
        let region = Scene::desk_room_region();
        // A 20 m line looking along −x.
        let traj = Trajectory::from_fn(1_000_000_000, 100.0, |t| {
            look_at(
                &Vector3::new(20.0 * t, 5.0, 3.0),
                &Vector3::new(-100.0, 5.0, 3.0),
            )
        })
        .unwrap();
        let fitted = traj.fitted_into(&region).unwrap();
        let centre = (region.min + region.max) / 2.0;
        let wanted = (region.target - centre).normalize();
        for p in fitted.poses() {
            let t = p.translation;
            assert!((0..3).all(|a| t[a] >= region.min[a] - 1e-9 && t[a] <= region.max[a] + 1e-9));
            assert!(((p.rotation * Vector3::z()) - wanted).norm() < 1e-9);
        }
    }
}
