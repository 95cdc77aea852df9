//! Triangulation of points seen in two or more calibrated views.
//!
//! [`triangulate_linear`] solves the homogeneous DLT on bearing vectors: a world point X
//! (homogeneous) seen along the unit bearing f by a camera `cam_from_world = (R, t)` satisfies
//! `f × (R X + t w) = 0`, three equations of rank two per view. Stacking them gives `A X = 0`,
//! solved by the right singular vector of A with the smallest singular value.
//!
//! [`triangulate`] refines that estimate by Gauss–Newton on the pixel reprojection error of
//! rectified (pinhole) observations and then checks depth, parallax and residuals;
//! [`triangulate_rectified`] is the closed form for a rectified stereo pair. A rejection is a
//! per-point outcome ([`Rejected`]), not an error of the program.

use nalgebra::{DMatrix, Matrix3, Vector2, Vector3};

use super::camera::{Pinhole, Projective};
use super::se3::Se3;
use super::so3::hat;
use crate::config::TriangulationConfig;

/// A triangulated point that passed every check.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Triangulated {
    /// The point in the world frame (for [`triangulate_rectified`]: the rectified left frame).
    pub point_world: Vector3<f64>,
    /// Largest angle between two observing rays, degrees.
    pub parallax_deg: f64,
    /// Largest reprojection error over the views, pixels.
    pub max_reprojection_px: f64,
}

/// Why a correspondence was not turned into a point.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum Rejected {
    /// Fewer than two observations.
    #[error("{views} view(s) given; triangulation needs at least 2")]
    TooFewViews {
        /// Number of observations given.
        views: usize,
    },
    /// The poses and the observations do not pair up.
    #[error("{poses} poses but {observations} observations")]
    MismatchedViews {
        /// Number of poses.
        poses: usize,
        /// Number of observations.
        observations: usize,
    },
    /// The rays do not determine a finite point (coincident camera centres, parallel rays,
    /// non-finite input).
    #[error("the observations do not determine a finite point")]
    Degenerate,
    /// The point lies behind (or on the image plane of) a camera.
    #[error("the point lies behind camera {view}")]
    BehindCamera {
        /// Index of the first such view.
        view: usize,
    },
    /// The point is closer than `min_depth_m` to a camera.
    #[error(
        "the point is {depth_m:.3} m in front of camera {view}, closer than the minimum depth"
    )]
    TooClose {
        /// Index of the first such view.
        view: usize,
        /// Its depth in that view, metres.
        depth_m: f64,
    },
    /// The point is farther than `max_depth_m` from the first camera.
    #[error("the point is {depth_m:.3} m in front of the first camera, beyond the maximum depth")]
    TooFar {
        /// Its depth in the first view, metres (infinite for zero disparity).
        depth_m: f64,
    },
    /// The rays are too close to parallel for a usable depth.
    #[error("the largest angle between the rays is {deg:.3}°, below the minimum parallax")]
    LowParallax {
        /// Largest angle between two rays, degrees.
        deg: f64,
    },
    /// After refinement the point still reprojects too far from an observation.
    #[error("reprojection error {px:.3} px exceeds the maximum")]
    ReprojectionError {
        /// The largest reprojection error, pixels.
        px: f64,
    },
}

/// The point that the bearings (unit or not, in each camera's frame) of `cams_from_world`
/// point at, by homogeneous DLT. `None` with fewer than two views, mismatched lengths,
/// coincident camera centres, a point at infinity or non-finite input.
///
/// The world is moved to the first camera centre and scaled by the mean distance to the other
/// centres before solving, so the result does not depend on the units or the world origin.
pub fn triangulate_linear(
    cams_from_world: &[Se3],
    bearings: &[Vector3<f64>],
) -> Option<Vector3<f64>> {
    let n = cams_from_world.len();
    if n < 2 || bearings.len() != n {
        return None;
    }
    let centres: Vec<Vector3<f64>> = cams_from_world
        .iter()
        .map(|c| c.inverse().translation)
        .collect();
    let origin = centres[0];
    let scale = centres[1..]
        .iter()
        .map(|c| (c - origin).norm())
        .sum::<f64>()
        / (n - 1) as f64;
    if !(scale.is_finite() && scale > 0.0) {
        return None;
    }
    let mut a = DMatrix::<f64>::zeros(3 * n, 4);
    for (i, (cam_from_world, bearing)) in cams_from_world.iter().zip(bearings).enumerate() {
        let f = bearing.try_normalize(0.0)?;
        // With X = origin + scale · Y: R X + t = scale (R Y + (R origin + t) / scale).
        let r = cam_from_world.rotation.matrix();
        let t = (r * origin + cam_from_world.translation) / scale;
        let f_hat = hat(&f);
        a.fixed_view_mut::<3, 3>(3 * i, 0).copy_from(&(f_hat * r));
        a.fixed_view_mut::<3, 1>(3 * i, 3).copy_from(&(f_hat * t));
    }
    if a.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let svd = a.svd(false, true);
    let v_t = svd.v_t?;
    let smallest = svd
        .singular_values
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?
        .0;
    let h = v_t.row(smallest);
    let y = Vector3::new(h[0], h[1], h[2]);
    if h[3].abs() <= 1e-12 * y.norm() {
        return None;
    }
    let point = origin + y * (scale / h[3]);
    point.iter().all(|v| v.is_finite()).then_some(point)
}

/// Sum of squared pixel residuals of `point` over the views, or `None` when a view cannot
/// project it.
fn reprojection_cost(
    cams_from_world: &[Se3],
    pixels: &[Vector2<f64>],
    pinhole: &Pinhole,
    point: &Vector3<f64>,
) -> Option<f64> {
    cams_from_world
        .iter()
        .zip(pixels)
        .try_fold(0.0, |acc, (cam_from_world, uv)| {
            Some(
                acc + (pinhole.project(&cam_from_world.transform_point(point))? - uv)
                    .norm_squared(),
            )
        })
}

/// Gauss–Newton on `Σ |π(R_i X + t_i) − uv_i|²` over X, with `∂r_i/∂X = J_π R_i`. A step is
/// kept only if it lowers the cost, so refinement never makes the linear estimate worse.
fn refine(
    cams_from_world: &[Se3],
    pixels: &[Vector2<f64>],
    pinhole: &Pinhole,
    mut point: Vector3<f64>,
    iterations: u32,
) -> Vector3<f64> {
    let Some(mut cost) = reprojection_cost(cams_from_world, pixels, pinhole, &point) else {
        return point;
    };
    for _ in 0..iterations {
        let mut h = Matrix3::zeros();
        let mut g = Vector3::zeros();
        for (cam_from_world, uv) in cams_from_world.iter().zip(pixels) {
            let Some((projected, j_p)) =
                pinhole.project_with_jacobian(&cam_from_world.transform_point(&point))
            else {
                return point;
            };
            let j = j_p * cam_from_world.rotation.matrix();
            h += j.transpose() * j;
            g += j.transpose() * (projected - uv);
        }
        let Some(step) = h.cholesky().map(|c| c.solve(&-g)) else {
            return point;
        };
        let candidate = point + step;
        match reprojection_cost(cams_from_world, pixels, pinhole, &candidate) {
            Some(c) if c < cost => {
                point = candidate;
                cost = c;
            }
            _ => return point,
        }
        if step.norm() <= 1e-12 * (1.0 + point.norm()) {
            break;
        }
    }
    point
}

/// Largest angle between two of the rays, degrees; `atan2(|a × b|, a · b)` stays accurate
/// for nearly parallel rays where `acos` does not.
fn max_parallax_deg(rays_world: &[Vector3<f64>]) -> f64 {
    let mut max = 0.0_f64;
    for (i, a) in rays_world.iter().enumerate() {
        for b in &rays_world[i + 1..] {
            max = max.max(a.cross(b).norm().atan2(a.dot(b)));
        }
    }
    max.to_degrees()
}

/// The depth, range, parallax and residual checks shared by both triangulation paths.
fn check(
    cams_from_world: &[Se3],
    pixels: &[Vector2<f64>],
    pinhole: &Pinhole,
    point: Vector3<f64>,
    parallax_deg: f64,
    config: &TriangulationConfig,
) -> Result<Triangulated, Rejected> {
    let mut max_reprojection_px = 0.0_f64;
    for (view, (cam_from_world, uv)) in cams_from_world.iter().zip(pixels).enumerate() {
        let p_cam = cam_from_world.transform_point(&point);
        if p_cam.z <= 0.0 {
            return Err(Rejected::BehindCamera { view });
        }
        if p_cam.z < config.min_depth_m {
            return Err(Rejected::TooClose {
                view,
                depth_m: p_cam.z,
            });
        }
        let projected = pinhole
            .project(&p_cam)
            .ok_or(Rejected::BehindCamera { view })?;
        max_reprojection_px = max_reprojection_px.max((projected - uv).norm());
    }
    let depth_m = cams_from_world[0].transform_point(&point).z;
    if depth_m > config.max_depth_m {
        return Err(Rejected::TooFar { depth_m });
    }
    if parallax_deg < config.min_parallax_deg {
        return Err(Rejected::LowParallax { deg: parallax_deg });
    }
    if max_reprojection_px > config.max_reprojection_px {
        return Err(Rejected::ReprojectionError {
            px: max_reprojection_px,
        });
    }
    Ok(Triangulated {
        point_world: point,
        parallax_deg,
        max_reprojection_px,
    })
}

/// Triangulates one point from pixels of rectified (pinhole) cameras: DLT, then
/// `config.refine_iterations` Gauss–Newton steps on the reprojection error, then the checks,
/// in this order: positive depth in every view, depth ≥ `min_depth_m` in every view, depth ≤
/// `max_depth_m` in the first view, parallax ≥ `min_parallax_deg` (largest angle between the
/// observed rays), reprojection error ≤ `max_reprojection_px` in every view.
pub fn triangulate(
    cams_from_world: &[Se3],
    pixels: &[Vector2<f64>],
    pinhole: &Pinhole,
    config: &TriangulationConfig,
) -> Result<Triangulated, Rejected> {
    if cams_from_world.len() != pixels.len() {
        return Err(Rejected::MismatchedViews {
            poses: cams_from_world.len(),
            observations: pixels.len(),
        });
    }
    if pixels.len() < 2 {
        return Err(Rejected::TooFewViews {
            views: pixels.len(),
        });
    }
    if !(pinhole.fx > 0.0 && pinhole.fy > 0.0)
        || pixels
            .iter()
            .any(|uv| !(uv.x.is_finite() && uv.y.is_finite()))
    {
        return Err(Rejected::Degenerate);
    }
    let bearings: Vec<Vector3<f64>> = pixels
        .iter()
        .map(|uv| {
            Vector3::new(
                (uv.x - pinhole.cx) / pinhole.fx,
                (uv.y - pinhole.cy) / pinhole.fy,
                1.0,
            )
        })
        .collect();
    let linear = triangulate_linear(cams_from_world, &bearings).ok_or(Rejected::Degenerate)?;
    let point = refine(
        cams_from_world,
        pixels,
        pinhole,
        linear,
        config.refine_iterations,
    );
    let rays_world: Vec<Vector3<f64>> = cams_from_world
        .iter()
        .zip(&bearings)
        .map(|(c, f)| c.rotation.inverse() * *f)
        .collect();
    check(
        cams_from_world,
        pixels,
        pinhole,
        point,
        max_parallax_deg(&rays_world),
        config,
    )
}

/// Triangulates a correspondence of a rectified stereo pair: left pixel `uv_left`, right pixel
/// `(u_right, uv_left.y)`. Depth is `z = fx · b / (u_left − u_right)` and the point, in the
/// rectified left frame, is `z · K⁻¹ (u_left, v, 1)`. The checks are those of [`triangulate`]
/// with the views `[identity, right_from_left = (I, (−b, 0, 0))]`; zero disparity is
/// [`Rejected::TooFar`] (infinite depth), negative disparity [`Rejected::BehindCamera`].
pub fn triangulate_rectified(
    pinhole: &Pinhole,
    baseline_m: f64,
    uv_left: &Vector2<f64>,
    u_right: f64,
    config: &TriangulationConfig,
) -> Result<Triangulated, Rejected> {
    let finite = [baseline_m, uv_left.x, uv_left.y, u_right]
        .iter()
        .all(|v| v.is_finite());
    if !(finite && baseline_m > 0.0 && pinhole.fx > 0.0 && pinhole.fy > 0.0) {
        return Err(Rejected::Degenerate);
    }
    let disparity = uv_left.x - u_right;
    if disparity == 0.0 {
        return Err(Rejected::TooFar {
            depth_m: f64::INFINITY,
        });
    }
    if disparity < 0.0 {
        return Err(Rejected::BehindCamera { view: 0 });
    }
    let depth = pinhole.fx * baseline_m / disparity;
    let point = Vector3::new(
        (uv_left.x - pinhole.cx) / pinhole.fx * depth,
        (uv_left.y - pinhole.cy) / pinhole.fy * depth,
        depth,
    );
    let right_from_left = Se3::new(
        super::so3::So3::identity(),
        Vector3::new(-baseline_m, 0.0, 0.0),
    );
    let views = [Se3::identity(), right_from_left];
    let pixels = [*uv_left, Vector2::new(u_right, uv_left.y)];
    // The two rays leave (0, 0, 0) and (b, 0, 0) and meet at the point.
    let baseline = Vector3::new(baseline_m, 0.0, 0.0);
    let parallax_deg = max_parallax_deg(&[point, point - baseline]);
    check(&views, &pixels, pinhole, point, parallax_deg, config)
}
