//! Motion-only pose refinement: the camera pose alone is optimised against fixed 3-D points,
//! as tracking does for every frame.
//!
//! The unknown is `cam_from_world`, updated on the left, T ← exp(δ) T with δ = [ρ, φ], so a
//! point P = T X moves by ∂P/∂δ = [I | −[P]×]. Observations are rectified-stereo triples
//! (u_left, v, u_right) or monocular pixels (u, v) of a pinhole camera; the right camera sits
//! at +baseline along the left camera's x axis:
//!
//! ```text
//! u_l = fx X/Z + cx,   v = fy Y/Z + cy,   u_r = fx (X − b)/Z + cx
//! ```
//!
//! Points at depth Z ≤ `min_depth` contribute nothing at that estimate.
//!
//! Observations may come from a camera pair whose centre sits at a *viewpoint* c in the left
//! camera's axes, with the left camera's orientation and baseline (an event pair's images
//! warped into the frame cameras through the plane at infinity are that pair's view):
//! [`refine_pose_seen_from`] takes one per observation, and the observation sees
//! P = T X − c, whose Jacobian is ∂π/∂P · [I | −[T X]×]. The viewpoints travel beside the
//! observations so that a solve without any runs the plain code.
//!
//! Each observation may carry its own measurement noise σ (pixels, the same on every row of
//! a stereo triple): [`refine_pose_weighted`] whitens residual and Jacobian rows by 1/σ, so
//! the cost is ½ Σ ρ(‖r‖²/σ²) and the loss scale and outlier bound, stated for σ = 1 px,
//! become σ times as wide in pixels for that observation.

use nalgebra::{Matrix6, SMatrix, Vector2, Vector3, Vector6};

use super::lm::{self, LeastSquares, LmOptions, LmReport, Step};
use super::robust::Loss;
use crate::error::{ensure_sigmas, Error, Result};
use crate::geometry::Se3;

/// Rectified stereo (or monocular, ignoring `baseline`) pinhole intrinsics.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StereoIntrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Distance from the left to the right camera centre along the left x axis, metres.
    pub baseline: f64,
}

/// One observation of a fixed world point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PoseObservation {
    /// A left-camera pixel.
    Mono {
        /// World point.
        point: Vector3<f64>,
        /// Measured (u, v).
        pixel: Vector2<f64>,
    },
    /// A rectified stereo match: left pixel and right column.
    Stereo {
        /// World point.
        point: Vector3<f64>,
        /// Measured (u_left, v).
        pixel: Vector2<f64>,
        /// Measured u_right.
        u_right: f64,
    },
}

/// Options of [`refine_pose`].
#[derive(Clone, Debug, PartialEq)]
pub struct PoseOptions {
    /// Loss on each observation's squared pixel error (tracking uses Huber).
    pub loss: Loss,
    /// Points nearer than this (metres, along the optical axis) are ignored.
    pub min_depth: f64,
    /// Squared pixel error above which an observation counts as an outlier in the result
    /// (with per-observation σ: the squared whitened error ‖r‖²/σ²).
    pub outlier_threshold_sq: f64,
    /// The LM loop's options (tracking runs a fixed small number of iterations).
    pub lm: LmOptions,
}

impl Default for PoseOptions {
    fn default() -> Self {
        Self {
            // √7.815 px: the 95 % χ² bound of a 3-dof stereo residual at σ = 1 px.
            loss: Loss::Huber(7.815f64.sqrt()),
            min_depth: 1e-6,
            outlier_threshold_sq: 7.815,
            lm: LmOptions {
                max_iterations: 10,
                ..Default::default()
            },
        }
    }
}

/// The refined pose with the solve's report and its inlier statistics.
#[derive(Clone, Debug)]
pub struct PoseResult {
    /// The refined `cam_from_world`.
    pub cam_from_world: Se3,
    /// The LM report.
    pub report: LmReport,
    /// Per observation: squared error under the threshold and in front of the camera.
    pub inliers: Vec<bool>,
    /// Number of `true` in `inliers`.
    pub inlier_count: usize,
    /// RMS pixel error over the inliers (0 when there are none).
    pub inlier_rms: f64,
    /// Covariance of the pose update δ = [ρ, φ] at the result (`cam_from_world` perturbed on
    /// the left, ρ in metres and φ in radians, both in the camera's axes): `s² (JᵀJ)⁻¹` over
    /// the inliers' whitened residuals, with `s² = Σ ‖r‖² / (m − 6)` over their `m` scalar
    /// residuals, so the keypoints' real scatter sets it rather than their nominal σ.
    /// `None` with fewer than seven scalar residuals or a singular `JᵀJ`.
    pub covariance: Option<Matrix6<f64>>,
}

/// Residual (predicted − measured) of one observation with its 3×6 Jacobian (rows beyond the
/// residual's length are zero); `None` when the point is behind `min_depth`.
pub fn pose_residual(
    k: &StereoIntrinsics,
    cam_from_world: &Se3,
    obs: &PoseObservation,
    min_depth: f64,
) -> Option<(Vector3<f64>, SMatrix<f64, 3, 6>, usize)> {
    let rt = (cam_from_world.rotation.matrix(), cam_from_world.translation);
    residual::<false>(k, &rt, obs, &NO_VIEWPOINT, min_depth)
}

/// [`pose_residual`] of an observation made from `viewpoint` (metres, in the camera's axes).
pub fn pose_residual_seen_from(
    k: &StereoIntrinsics,
    cam_from_world: &Se3,
    obs: &PoseObservation,
    viewpoint: &Vector3<f64>,
    min_depth: f64,
) -> Option<(Vector3<f64>, SMatrix<f64, 3, 6>, usize)> {
    let rt = (cam_from_world.rotation.matrix(), cam_from_world.translation);
    residual::<true>(k, &rt, obs, viewpoint, min_depth)
}

/// The viewpoint of the camera itself.
const NO_VIEWPOINT: Vector3<f64> = Vector3::new(0.0, 0.0, 0.0);

/// The pose as (R, t): a matrix product per point instead of a quaternion rotation.
type RigidMatrix = (nalgebra::Matrix3<f64>, Vector3<f64>);

/// The observation's point, measured pixel and optional right column.
#[inline]
fn parts(obs: &PoseObservation) -> (&Vector3<f64>, &Vector2<f64>, Option<f64>) {
    match obs {
        PoseObservation::Mono { point, pixel } => (point, pixel, None),
        PoseObservation::Stereo {
            point,
            pixel,
            u_right,
        } => (point, pixel, Some(*u_right)),
    }
}

/// The residual alone, for cost evaluations; `None` behind `min_depth`. With `VIEW` the
/// observation is made from `viewpoint`, without it `viewpoint` is not read.
#[inline]
fn residual_value<const VIEW: bool>(
    k: &StereoIntrinsics,
    (rotation, translation): &RigidMatrix,
    obs: &PoseObservation,
    viewpoint: &Vector3<f64>,
    min_depth: f64,
) -> Option<Vector3<f64>> {
    let (point, pixel, u_right) = parts(obs);
    let p = if VIEW {
        rotation * point + translation - viewpoint
    } else {
        rotation * point + translation
    };
    // NaN depths fail this test too.
    if p.z.partial_cmp(&min_depth) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let iz = 1.0 / p.z;
    Some(Vector3::new(
        k.fx * p.x * iz + k.cx - pixel.x,
        k.fy * p.y * iz + k.cy - pixel.y,
        u_right.map_or(0.0, |ur| k.fx * (p.x - k.baseline) * iz + k.cx - ur),
    ))
}

/// The residual with its Jacobian ∂r/∂[ρ, φ] = ∂π/∂P · [I | −[Q]×], written out entry by
/// entry (the product has many structural zeros), where Q = T X is the point in the camera
/// and P = Q − viewpoint the point the measuring camera sees (`VIEW` as for
/// [`residual_value`]).
#[inline]
fn residual<const VIEW: bool>(
    k: &StereoIntrinsics,
    (rotation, translation): &RigidMatrix,
    obs: &PoseObservation,
    viewpoint: &Vector3<f64>,
    min_depth: f64,
) -> Option<(Vector3<f64>, SMatrix<f64, 3, 6>, usize)> {
    let (point, pixel, u_right) = parts(obs);
    let p = if VIEW {
        rotation * point + translation - viewpoint
    } else {
        rotation * point + translation
    };
    if p.z.partial_cmp(&min_depth) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let (x, y) = (p.x, p.y);
    let iz = 1.0 / p.z;
    let (xz, yz) = (x * iz, y * iz);
    // Q / z = P / z + viewpoint / z: (x/z, y/z, 1) without a viewpoint.
    let (qxz, qyz, qzz) = if VIEW {
        (
            xz + viewpoint.x * iz,
            yz + viewpoint.y * iz,
            1.0 + viewpoint.z * iz,
        )
    } else {
        (xz, yz, 1.0)
    };
    let (fxz, fyz) = (k.fx * iz, k.fy * iz);
    let mut j = SMatrix::<f64, 3, 6>::zeros();
    // u = fx x/z + cx
    j[(0, 0)] = fxz;
    j[(0, 2)] = -fxz * xz;
    j[(0, 3)] = -k.fx * xz * qyz;
    j[(0, 4)] = k.fx * (qzz + xz * qxz);
    j[(0, 5)] = -k.fx * qyz;
    // v = fy y/z + cy
    j[(1, 1)] = fyz;
    j[(1, 2)] = -fyz * yz;
    j[(1, 3)] = -k.fy * (qzz + yz * qyz);
    j[(1, 4)] = k.fy * qxz * yz;
    j[(1, 5)] = k.fy * qxz;
    let mut r = Vector3::new(k.fx * xz + k.cx - pixel.x, k.fy * yz + k.cy - pixel.y, 0.0);
    let dim = if let Some(ur) = u_right {
        // u_r = fx (x − b)/z + cx
        let xbz = (x - k.baseline) * iz;
        j[(2, 0)] = fxz;
        j[(2, 2)] = -fxz * xbz;
        j[(2, 3)] = -k.fx * xbz * qyz;
        j[(2, 4)] = k.fx * (qzz + xbz * qxz);
        j[(2, 5)] = -k.fx * qyz;
        r.z = k.fx * xbz + k.cx - ur;
        3
    } else {
        2
    };
    Some((r, j, dim))
}

struct PoseProblem<'a> {
    k: StereoIntrinsics,
    observations: &'a [PoseObservation],
    /// 1/σ per observation; empty: σ = 1 px for all.
    weights: &'a [f64],
    /// Viewpoint per observation; empty: every observation the camera's own.
    viewpoints: &'a [Vector3<f64>],
    loss: Loss,
    min_depth: f64,
    pose: Se3,
    candidate: Se3,
    h: Matrix6<f64>,
    g: Vector6<f64>,
    step: Vector6<f64>,
}

impl PoseProblem<'_> {
    fn weight(&self, i: usize) -> f64 {
        self.weights.get(i).copied().unwrap_or(1.0)
    }

    fn weight_sq(&self, i: usize) -> f64 {
        let w = self.weight(i);
        w * w
    }

    /// Observation `i`'s viewpoint in a solve with (`VIEW`) or without viewpoints.
    #[inline]
    fn viewpoint<const VIEW: bool>(&self, i: usize) -> &Vector3<f64> {
        if VIEW {
            &self.viewpoints[i]
        } else {
            &NO_VIEWPOINT
        }
    }

    fn cost_at(&self, pose: &Se3) -> f64 {
        // One loop per case, so that a solve without viewpoints runs the plain code.
        if self.viewpoints.is_empty() {
            self.cost_with::<false>(pose)
        } else {
            self.cost_with::<true>(pose)
        }
    }

    fn cost_with<const VIEW: bool>(&self, pose: &Se3) -> f64 {
        let rt = (pose.rotation.matrix(), pose.translation);
        let mut c = 0.0;
        for (i, o) in self.observations.iter().enumerate() {
            let viewpoint = self.viewpoint::<VIEW>(i);
            if let Some(r) = residual_value::<VIEW>(&self.k, &rt, o, viewpoint, self.min_depth) {
                c += self.loss.evaluate(r.norm_squared() * self.weight_sq(i))[0];
            }
        }
        0.5 * c
    }

    fn linearize_with<const VIEW: bool>(&mut self) -> f64 {
        self.h = Matrix6::zeros();
        self.g = Vector6::zeros();
        // The rotation matrix once per linearisation, not once per observation.
        let rt = (self.pose.rotation.matrix(), self.pose.translation);
        for (i, o) in self.observations.iter().enumerate() {
            let viewpoint = self.viewpoint::<VIEW>(i);
            let Some((mut r, mut j, _)) =
                residual::<VIEW>(&self.k, &rt, o, viewpoint, self.min_depth)
            else {
                continue;
            };
            // Whitening: r/σ and J/σ (the robust loss then sees ‖r‖²/σ²).
            let w = self.weight(i);
            if w != 1.0 {
                r *= w;
                j *= w;
            }
            if let Some(corr) = self.loss.corrector(r.norm_squared()) {
                corr.correct_jacobian(&r, &mut j);
                corr.correct_residual(&mut r);
            }
            self.h.gemm_tr(1.0, &j, &j, 1.0);
            self.g.gemv_tr(1.0, &j, &r, 1.0);
        }
        self.g.amax()
    }
}

impl LeastSquares for PoseProblem<'_> {
    fn cost(&mut self) -> f64 {
        self.cost_at(&self.pose)
    }

    fn linearize(&mut self) -> f64 {
        if self.viewpoints.is_empty() {
            self.linearize_with::<false>()
        } else {
            self.linearize_with::<true>()
        }
    }

    fn compute_step(&mut self, mu: f64, lo: f64, hi: f64) -> Option<Step> {
        let d = Vector6::from_fn(|i, _| self.h[(i, i)].clamp(lo, hi));
        let a = self.h + Matrix6::from_diagonal(&(d * mu));
        let step = a.cholesky()?.solve(&-self.g);
        if !step.iter().all(|x| x.is_finite()) {
            return None;
        }
        self.step = step;
        Some(Step {
            model_decrease: 0.5 * (-self.g.dot(&step) + mu * step.component_mul(&step).dot(&d)),
            norm: step.norm(),
        })
    }

    fn candidate_cost(&mut self) -> f64 {
        self.candidate = Se3::exp(&self.step) * self.pose;
        self.cost_at(&self.candidate)
    }

    fn accept(&mut self) {
        self.pose = self.candidate;
    }

    fn state_norm(&self) -> f64 {
        self.pose.log().norm()
    }
}

/// Refines `cam_from_world` against fixed points; returns the pose, the report and which
/// observations are inliers at the result. Every observation has σ = 1 px.
pub fn refine_pose(
    cam_from_world: Se3,
    intrinsics: &StereoIntrinsics,
    observations: &[PoseObservation],
    options: &PoseOptions,
) -> Result<PoseResult> {
    solve(cam_from_world, intrinsics, observations, &[], &[], options)
}

/// [`refine_pose`] with a measurement noise `sigmas[i]` (pixels, finite and positive) per
/// observation: residuals are whitened by 1/σ, so an observation's loss scale and its
/// outlier bound (`options.outlier_threshold_sq`, stated for σ = 1 px) are σ times as wide
/// in pixels. `inlier_rms` stays in pixels.
pub fn refine_pose_weighted(
    cam_from_world: Se3,
    intrinsics: &StereoIntrinsics,
    observations: &[PoseObservation],
    sigmas: &[f64],
    options: &PoseOptions,
) -> Result<PoseResult> {
    ensure_sigmas("sigmas", sigmas, observations.len())?;
    let weights: Vec<f64> = sigmas.iter().map(|s| 1.0 / s).collect();
    solve(
        cam_from_world,
        intrinsics,
        observations,
        &weights,
        &[],
        options,
    )
}

/// [`refine_pose_weighted`] with observation `i` made from `viewpoints[i]` (metres, finite,
/// in the camera's axes; see the module notes). Viewpoints that are all zero give exactly
/// [`refine_pose_weighted`]'s result.
pub fn refine_pose_seen_from(
    cam_from_world: Se3,
    intrinsics: &StereoIntrinsics,
    observations: &[PoseObservation],
    sigmas: &[f64],
    viewpoints: &[Vector3<f64>],
    options: &PoseOptions,
) -> Result<PoseResult> {
    ensure_sigmas("sigmas", sigmas, observations.len())?;
    if viewpoints.len() != observations.len() {
        return Err(Error::invalid(
            "viewpoints",
            format!("one per observation ({})", observations.len()),
            viewpoints.len(),
        ));
    }
    for (i, c) in viewpoints.iter().enumerate() {
        crate::error::ensure_finite(&format!("viewpoints[{i}]"), c.as_slice())?;
    }
    let weights: Vec<f64> = sigmas.iter().map(|s| 1.0 / s).collect();
    // Without any viewpoint the plain code runs.
    let viewpoints = if viewpoints.iter().any(|c| *c != NO_VIEWPOINT) {
        viewpoints
    } else {
        &[]
    };
    solve(
        cam_from_world,
        intrinsics,
        observations,
        &weights,
        viewpoints,
        options,
    )
}

fn solve(
    cam_from_world: Se3,
    intrinsics: &StereoIntrinsics,
    observations: &[PoseObservation],
    weights: &[f64],
    viewpoints: &[Vector3<f64>],
    options: &PoseOptions,
) -> Result<PoseResult> {
    let k = intrinsics;
    crate::error::ensure_finite("intrinsics", &[k.fx, k.fy, k.cx, k.cy, k.baseline])?;
    if observations.is_empty() {
        return Err(Error::invalid("observations", "at least one", 0));
    }
    let mut problem = PoseProblem {
        k: *k,
        observations,
        weights,
        viewpoints,
        loss: options.loss,
        min_depth: options.min_depth,
        pose: cam_from_world,
        candidate: cam_from_world,
        h: Matrix6::zeros(),
        g: Vector6::zeros(),
        step: Vector6::zeros(),
    };
    let report = lm::solve(&mut problem, &options.lm)?;
    let pose = problem.pose;
    let mut inliers = Vec::with_capacity(observations.len());
    let (mut sum, mut count) = (0.0, 0usize);
    // The inliers' information JᵀJ and whitened squared error, for the covariance.
    let (mut h, mut chi2, mut m) = (Matrix6::<f64>::zeros(), 0.0, 0usize);
    for (i, o) in observations.iter().enumerate() {
        let seen = match viewpoints.get(i) {
            Some(c) => pose_residual_seen_from(k, &pose, o, c, options.min_depth),
            None => pose_residual(k, &pose, o, options.min_depth),
        };
        let ok = match seen {
            Some((r, j, dim))
                if r.norm_squared() * problem.weight_sq(i) <= options.outlier_threshold_sq =>
            {
                sum += r.norm_squared() / dim as f64;
                let w2 = problem.weight_sq(i);
                h.gemm_tr(w2, &j, &j, 1.0);
                chi2 += r.norm_squared() * w2;
                m += dim;
                true
            }
            _ => false,
        };
        count += ok as usize;
        inliers.push(ok);
    }
    let covariance = if m > 6 {
        h.cholesky()
            .map(|c| c.inverse() * (chi2 / (m - 6) as f64))
            .filter(|c| c.iter().all(|x| x.is_finite()))
    } else {
        None
    };
    Ok(PoseResult {
        cam_from_world: pose,
        report,
        inliers,
        inlier_count: count,
        inlier_rms: if count > 0 {
            (sum / count as f64).sqrt()
        } else {
            0.0
        },
        covariance,
    })
}
