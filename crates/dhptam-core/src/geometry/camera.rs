//! Camera models: pinhole, radial-tangential (`plumb_bob`) and Kannala–Brandt KB4 (equidistant).
//!
//! Every model maps a point `p = (x, y, z)` in the camera frame (x right, y down, z forward,
//! metres) to a pixel `(u, v)` and back to a unit bearing vector, with the analytic Jacobian
//! `∂(u, v)/∂p`. Pixel (0, 0) is the centre of the top-left pixel (the OpenCV and Basalt
//! convention). Parameters follow OpenCV's order so calibrations copy over unchanged:
//! radtan `[fx, fy, cx, cy, k1, k2, p1, p2, k3]`, kb4 `[fx, fy, cx, cy, k1, k2, k3, k4]`.

use nalgebra::{Matrix2, Matrix2x3, Vector2, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{ensure_finite, Error, Result};

/// Points closer to the camera plane than this (metres along z) are not projected by the
/// perspective models.
pub const MIN_DEPTH: f64 = 1e-9;

/// Newton iterations allowed when inverting a distortion model.
const MAX_UNDISTORT_ITERATIONS: usize = 30;

/// Projection and back-projection of one camera model.
pub trait Projective {
    /// The pixel of a point in the camera frame, or `None` when the model cannot image it
    /// (behind a perspective camera, outside the model's monotonic range).
    fn project(&self, p: &Vector3<f64>) -> Option<Vector2<f64>> {
        self.project_with_jacobian(p).map(|(uv, _)| uv)
    }

    /// The pixel and the 2×3 Jacobian `∂(u, v)/∂(x, y, z)`.
    fn project_with_jacobian(&self, p: &Vector3<f64>) -> Option<(Vector2<f64>, Matrix2x3<f64>)>;

    /// The unit bearing vector of a pixel, or `None` when the pixel lies outside the model's
    /// invertible range (or the iterative inversion does not converge).
    fn unproject(&self, uv: &Vector2<f64>) -> Option<Vector3<f64>>;
}

/// The ideal perspective camera.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pinhole {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

/// Pinhole with Brown–Conrady radial-tangential distortion (ROS `plumb_bob`, OpenCV's default
/// five coefficients).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RadTan {
    /// The undistorted projection.
    pub pinhole: Pinhole,
    /// Radial coefficient of r².
    pub k1: f64,
    /// Radial coefficient of r⁴.
    pub k2: f64,
    /// First tangential coefficient.
    pub p1: f64,
    /// Second tangential coefficient.
    pub p2: f64,
    /// Radial coefficient of r⁶.
    pub k3: f64,
}

/// Kannala–Brandt with four coefficients (OpenCV `fisheye`, Basalt `kb4`, Kalibr
/// `pinhole-equi`): the image radius is θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), where θ is
/// the angle between the ray and the optical axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Kb4 {
    /// The linear part (focal lengths and principal point).
    pub pinhole: Pinhole,
    /// Coefficients k1..k4 of θ², θ⁴, θ⁶, θ⁸.
    pub k: [f64; 4],
}

/// One of the supported models.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "lowercase")]
pub enum CameraModel {
    /// No distortion.
    Pinhole(Pinhole),
    /// Radial-tangential distortion.
    RadTan(RadTan),
    /// Kannala–Brandt equidistant fisheye.
    Kb4(Kb4),
}

/// A camera: its model and its image size.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Projection model and parameters.
    pub model: CameraModel,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

impl Pinhole {
    /// The 3×3 calibration matrix K.
    pub fn k_matrix(&self) -> nalgebra::Matrix3<f64> {
        nalgebra::Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// Normalised image coordinates (x/z, y/z) of a pixel.
    fn normalise(&self, uv: &Vector2<f64>) -> Vector2<f64> {
        Vector2::new((uv.x - self.cx) / self.fx, (uv.y - self.cy) / self.fy)
    }

    /// Pixel of normalised coordinates.
    fn to_pixel(self, m: &Vector2<f64>) -> Vector2<f64> {
        Vector2::new(self.fx * m.x + self.cx, self.fy * m.y + self.cy)
    }

    fn focal(&self) -> Matrix2<f64> {
        Matrix2::new(self.fx, 0.0, 0.0, self.fy)
    }
}

/// (x/z, y/z) and its Jacobian with respect to p; `None` for z below [`MIN_DEPTH`].
fn perspective_divide(p: &Vector3<f64>) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
    if p.z < MIN_DEPTH {
        return None;
    }
    let iz = 1.0 / p.z;
    let m = Vector2::new(p.x * iz, p.y * iz);
    let j = Matrix2x3::new(iz, 0.0, -m.x * iz, 0.0, iz, -m.y * iz);
    Some((m, j))
}

impl Projective for Pinhole {
    fn project_with_jacobian(&self, p: &Vector3<f64>) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        let (m, j) = perspective_divide(p)?;
        Some((self.to_pixel(&m), self.focal() * j))
    }

    fn unproject(&self, uv: &Vector2<f64>) -> Option<Vector3<f64>> {
        let m = self.normalise(uv);
        Some(Vector3::new(m.x, m.y, 1.0).normalize())
    }
}

impl RadTan {
    /// Distorted normalised coordinates and their 2×2 Jacobian with respect to the undistorted
    /// ones:
    /// `x_d = x ρ + 2 p1 x y + p2 (r² + 2x²)`, `y_d = y ρ + p1 (r² + 2y²) + 2 p2 x y`,
    /// `ρ = 1 + k1 r² + k2 r⁴ + k3 r⁶`.
    fn distort(&self, m: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        let (x, y) = (m.x, m.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let d_radial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2); // ∂ρ/∂(r²)
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        let cross = 2.0 * x * y * d_radial + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let j = Matrix2::new(
            radial + 2.0 * x * x * d_radial + 2.0 * self.p1 * y + 6.0 * self.p2 * x,
            cross,
            cross,
            radial + 2.0 * y * y * d_radial + 6.0 * self.p1 * y + 2.0 * self.p2 * x,
        );
        (Vector2::new(xd, yd), j)
    }

    /// Whether the radial distortion `r ↦ r ρ(r²)` is increasing on `[0, r]`, i.e. whether
    /// `r` lies before the fold where the model starts mapping farther rays back towards the
    /// centre. Its derivative `g(s) = 1 + 3 k1 s + 5 k2 s² + 7 k3 s³` (s = r²) starts at 1, so
    /// it is positive on [0, s] iff it is positive at s and at its interior stationary points,
    /// the roots of `g'(s) = 3 k1 + 10 k2 s + 21 k3 s²`.
    fn radially_monotonic(&self, r2: f64) -> bool {
        let g = |s: f64| 1.0 + s * (3.0 * self.k1 + s * (5.0 * self.k2 + s * 7.0 * self.k3));
        let at_r = g(r2);
        if at_r.is_nan() || at_r <= 0.0 {
            return false;
        }
        let (a, b, c) = (21.0 * self.k3, 10.0 * self.k2, 3.0 * self.k1);
        let mut stationary = [f64::NAN; 2];
        if a == 0.0 {
            if b != 0.0 {
                stationary[0] = -c / b;
            }
        } else {
            let disc = b * b - 4.0 * a * c;
            if disc >= 0.0 {
                let sq = disc.sqrt();
                stationary = [(-b - sq) / (2.0 * a), (-b + sq) / (2.0 * a)];
            }
        }
        stationary
            .iter()
            .all(|&s| !(s > 0.0 && s < r2) || g(s) > 0.0)
    }
}

impl Projective for RadTan {
    fn project_with_jacobian(&self, p: &Vector3<f64>) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        let (m, j_m) = perspective_divide(p)?;
        let (md, j_d) = self.distort(&m);
        // Past the fold the pixel would belong to another, nearer-axis ray as well.
        if !self.radially_monotonic(m.norm_squared()) || j_d.determinant() <= 0.0 {
            return None;
        }
        Some((self.pinhole.to_pixel(&md), self.pinhole.focal() * j_d * j_m))
    }

    fn unproject(&self, uv: &Vector2<f64>) -> Option<Vector3<f64>> {
        let target = self.pinhole.normalise(uv);
        // Newton on distort(m) = target, starting from the distorted point itself.
        let mut m = target;
        for _ in 0..MAX_UNDISTORT_ITERATIONS {
            let (md, j) = self.distort(&m);
            let residual = md - target;
            if residual.norm_squared() < 1e-30 {
                break;
            }
            m -= j.try_inverse()? * residual;
            if !m.x.is_finite() || !m.y.is_finite() {
                return None;
            }
        }
        let (md, j) = self.distort(&m);
        // Reject non-converged solutions and solutions past the fold, where the model stops
        // being one-to-one (see `radially_monotonic`; the determinant covers the tangential
        // terms).
        if (md - target).norm() > 1e-10 * (1.0 + target.norm())
            || j.determinant() <= 0.0
            || !self.radially_monotonic(m.norm_squared())
        {
            return None;
        }
        Some(Vector3::new(m.x, m.y, 1.0).normalize())
    }
}

impl Kb4 {
    /// θ_d(θ) and dθ_d/dθ.
    fn theta_d(&self, theta: f64) -> (f64, f64) {
        let [k1, k2, k3, k4] = self.k;
        let t2 = theta * theta;
        let poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)));
        let d_poly = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)));
        (theta * poly, d_poly)
    }
}

impl Projective for Kb4 {
    fn project_with_jacobian(&self, p: &Vector3<f64>) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        let (x, y, z) = (p.x, p.y, p.z);
        let r2 = x * x + y * y;
        let r = r2.sqrt();
        let theta = r.atan2(z);
        let (theta_d, d_theta_d) = self.theta_d(theta);
        if d_theta_d <= 0.0 || (r2 + z * z) < MIN_DEPTH * MIN_DEPTH {
            // Past the turning point of the polynomial the model is not one-to-one.
            return None;
        }
        if r < 1e-8 * z.abs().max(MIN_DEPTH) {
            // On the optical axis θ_d/r → 1/z: the model is locally the pinhole one.
            if z <= 0.0 {
                return None;
            }
            return self.pinhole.project_with_jacobian(p);
        }
        let Pinhole { fx, fy, cx, cy } = self.pinhole;
        let s = theta_d / r; // image radius per unit of r
        let rho2 = r2 + z * z;
        // ∂s/∂x = x (θ_d' z / (r² ρ²) − θ_d / r³), likewise for y; ∂θ/∂z = −r / ρ².
        let ds = d_theta_d * z / (r2 * rho2) - theta_d / (r2 * r);
        let dz = -d_theta_d / rho2; // ∂s/∂z = θ_d' ∂θ/∂z / r
        let uv = Vector2::new(fx * s * x + cx, fy * s * y + cy);
        let j = Matrix2x3::new(
            fx * (s + x * x * ds),
            fx * x * y * ds,
            fx * x * dz,
            fy * x * y * ds,
            fy * (s + y * y * ds),
            fy * y * dz,
        );
        Some((uv, j))
    }

    fn unproject(&self, uv: &Vector2<f64>) -> Option<Vector3<f64>> {
        let m = self.pinhole.normalise(uv);
        let theta_d = m.norm();
        if theta_d < 1e-12 {
            return Some(Vector3::new(m.x, m.y, 1.0).normalize());
        }
        // Newton on θ_d(θ) = θ_d from θ = θ_d, stopping on the residual so that the last
        // evaluation doubles as the validity check (no extra polynomial evaluation).
        let tolerance = 1e-15 * (1.0 + theta_d);
        let mut theta = theta_d;
        let mut converged = false;
        for _ in 0..MAX_UNDISTORT_ITERATIONS {
            let (f, df) = self.theta_d(theta);
            if df <= 0.0 || !theta.is_finite() {
                return None;
            }
            let residual = f - theta_d;
            if residual.abs() <= tolerance {
                converged = true;
                break;
            }
            let step = residual / df;
            theta -= step;
            if step.abs() <= 1e-15 * (1.0 + theta.abs()) {
                // Rounding can keep the residual a few ulp above the tolerance; a step this
                // small means θ no longer changes.
                converged = true;
                break;
            }
        }
        if !converged || !(0.0..std::f64::consts::PI).contains(&theta) {
            return None;
        }
        let (sin_t, cos_t) = theta.sin_cos();
        Some(Vector3::new(
            sin_t * m.x / theta_d,
            sin_t * m.y / theta_d,
            cos_t,
        ))
    }
}

impl Projective for CameraModel {
    fn project_with_jacobian(&self, p: &Vector3<f64>) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        match self {
            CameraModel::Pinhole(c) => c.project_with_jacobian(p),
            CameraModel::RadTan(c) => c.project_with_jacobian(p),
            CameraModel::Kb4(c) => c.project_with_jacobian(p),
        }
    }

    fn unproject(&self, uv: &Vector2<f64>) -> Option<Vector3<f64>> {
        match self {
            CameraModel::Pinhole(c) => c.unproject(uv),
            CameraModel::RadTan(c) => c.unproject(uv),
            CameraModel::Kb4(c) => c.unproject(uv),
        }
    }
}

impl CameraModel {
    /// The model's name as used in files and the Python API: `pinhole`, `radtan`, `kb4`.
    pub fn name(&self) -> &'static str {
        match self {
            CameraModel::Pinhole(_) => "pinhole",
            CameraModel::RadTan(_) => "radtan",
            CameraModel::Kb4(_) => "kb4",
        }
    }

    /// The linear part (focal lengths and principal point).
    pub fn pinhole(&self) -> &Pinhole {
        match self {
            CameraModel::Pinhole(c) => c,
            CameraModel::RadTan(c) => &c.pinhole,
            CameraModel::Kb4(c) => &c.pinhole,
        }
    }

    /// The parameters in OpenCV order (see the module documentation).
    pub fn params(&self) -> Vec<f64> {
        let Pinhole { fx, fy, cx, cy } = *self.pinhole();
        let mut v = vec![fx, fy, cx, cy];
        match self {
            CameraModel::Pinhole(_) => {}
            CameraModel::RadTan(c) => v.extend([c.k1, c.k2, c.p1, c.p2, c.k3]),
            CameraModel::Kb4(c) => v.extend(c.k),
        }
        v
    }

    /// Builds a model from its name and parameters in OpenCV order. Radtan also accepts four
    /// distortion coefficients (k3 = 0).
    pub fn from_params(name: &str, params: &[f64]) -> Result<Self> {
        let expected = match name {
            "pinhole" => "4 parameters [fx, fy, cx, cy]",
            "radtan" | "plumb_bob" => "8 or 9 parameters [fx, fy, cx, cy, k1, k2, p1, p2(, k3)]",
            "kb4" | "equidistant" | "fisheye" => "8 parameters [fx, fy, cx, cy, k1, k2, k3, k4]",
            other => {
                return Err(Error::invalid(
                    "camera model",
                    "one of pinhole, radtan (plumb_bob), kb4 (equidistant, fisheye)",
                    format!("{other:?}"),
                ))
            }
        };
        ensure_finite(&format!("{name} parameters"), params)?;
        let count_ok = match name {
            "pinhole" => params.len() == 4,
            "radtan" | "plumb_bob" => params.len() == 8 || params.len() == 9,
            _ => params.len() == 8,
        };
        if !count_ok {
            return Err(Error::invalid(
                format!("{name} parameters"),
                expected,
                format!("{} values", params.len()),
            ));
        }
        let pinhole = Pinhole {
            fx: params[0],
            fy: params[1],
            cx: params[2],
            cy: params[3],
        };
        if pinhole.fx <= 0.0 || pinhole.fy <= 0.0 {
            return Err(Error::invalid(
                format!("{name} focal lengths"),
                "fx > 0 and fy > 0",
                format!("fx = {}, fy = {}", pinhole.fx, pinhole.fy),
            ));
        }
        Ok(match name {
            "pinhole" => CameraModel::Pinhole(pinhole),
            "radtan" | "plumb_bob" => CameraModel::RadTan(RadTan {
                pinhole,
                k1: params[4],
                k2: params[5],
                p1: params[6],
                p2: params[7],
                k3: params.get(8).copied().unwrap_or(0.0),
            }),
            _ => CameraModel::Kb4(Kb4 {
                pinhole,
                k: [params[4], params[5], params[6], params[7]],
            }),
        })
    }
}

impl Projective for Camera {
    fn project_with_jacobian(&self, p: &Vector3<f64>) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        self.model.project_with_jacobian(p)
    }

    fn unproject(&self, uv: &Vector2<f64>) -> Option<Vector3<f64>> {
        self.model.unproject(uv)
    }
}

/// Points handled per rayon task in the batch functions; large enough to amortise scheduling.
const BATCH_CHUNK: usize = 8192;

impl Camera {
    /// A camera from a model name, parameters in OpenCV order and an image size.
    pub fn new(name: &str, params: &[f64], width: u32, height: u32) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(Error::invalid(
                "image size",
                "width > 0 and height > 0",
                format!("{width}×{height}"),
            ));
        }
        Ok(Self {
            model: CameraModel::from_params(name, params)?,
            width,
            height,
        })
    }

    /// Whether a pixel lies inside the image, pixel centres at integers: u ∈ [−½, w − ½).
    pub fn contains(&self, uv: &Vector2<f64>) -> bool {
        uv.x >= -0.5
            && uv.y >= -0.5
            && uv.x < self.width as f64 - 0.5
            && uv.y < self.height as f64 - 0.5
    }

    /// Projects `N` points stored as `xyz = [x0, y0, z0, x1, ...]` into `uv = [u0, v0, ...]`,
    /// writing NaN for points the model cannot image. Runs in parallel over chunks.
    pub fn project_points(&self, xyz: &[f64], uv: &mut [f64]) -> Result<()> {
        check_batch("points", xyz.len(), 3, "uv", uv.len(), 2)?;
        xyz.par_chunks(3 * BATCH_CHUNK)
            .zip(uv.par_chunks_mut(2 * BATCH_CHUNK))
            .for_each(|(src, dst)| {
                for (p, out) in src.chunks_exact(3).zip(dst.chunks_exact_mut(2)) {
                    let pixel = self.model.project(&Vector3::new(p[0], p[1], p[2]));
                    let pixel = pixel.unwrap_or(Vector2::new(f64::NAN, f64::NAN));
                    out[0] = pixel.x;
                    out[1] = pixel.y;
                }
            });
        Ok(())
    }

    /// Unprojects `N` pixels `uv = [u0, v0, ...]` into unit bearings `xyz`, NaN where the model
    /// cannot invert the pixel. Runs in parallel over chunks.
    pub fn unproject_points(&self, uv: &[f64], xyz: &mut [f64]) -> Result<()> {
        check_batch("pixels", uv.len(), 2, "bearings", xyz.len(), 3)?;
        uv.par_chunks(2 * BATCH_CHUNK)
            .zip(xyz.par_chunks_mut(3 * BATCH_CHUNK))
            .for_each(|(src, dst)| {
                for (q, out) in src.chunks_exact(2).zip(dst.chunks_exact_mut(3)) {
                    let bearing = self.model.unproject(&Vector2::new(q[0], q[1]));
                    let bearing = bearing.unwrap_or(Vector3::new(f64::NAN, f64::NAN, f64::NAN));
                    out.copy_from_slice(bearing.as_slice());
                }
            });
        Ok(())
    }
}

fn check_batch(
    input: &str,
    in_len: usize,
    in_dim: usize,
    output: &str,
    out_len: usize,
    out_dim: usize,
) -> Result<()> {
    if in_len % in_dim != 0 {
        return Err(Error::invalid(
            input,
            format!("a multiple of {in_dim} values"),
            format!("{in_len} values"),
        ));
    }
    let n = in_len / in_dim;
    if out_len != n * out_dim {
        return Err(Error::invalid(
            output,
            format!("{} values for {n} {input}", n * out_dim),
            format!("{out_len} values"),
        ));
    }
    Ok(())
}
