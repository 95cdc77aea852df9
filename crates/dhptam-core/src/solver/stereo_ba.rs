//! Local bundle adjustment of SE(3) keyframes and 3-D points from rectified stereo and
//! monocular pixel observations, as the mapping thread runs it over its sliding window.
//!
//! Unknowns: per free keyframe δξ = [ρ, φ] applied on the left, `cam_from_world ← exp(δξ) ·
//! cam_from_world` (as [`super::pose`]), per point δX. A point P = R X + t in the camera
//! frame is observed as (u_l, v) and, for a stereo match, u_r of the right camera at
//! +baseline along x:
//!
//! ```text
//! u_l = fx X/Z + cx,   v = fy Y/Z + cy,   u_r = fx (X − b)/Z + cx
//! ∂P/∂δξ = [I | −[P]×],   ∂P/∂X = R
//! ```
//!
//! The residual is predicted − measured (3 rows for stereo, 2 for mono; the mono third row is
//! zero), under a robust loss on its squared norm. The points are eliminated with the Schur
//! complement of [`super::schur`] (shared with [`super::ba`]): the reduced keyframe system has
//! 6×6 blocks on the covisibility pattern of the free keyframes and is factorised densely for
//! the window sizes the mapping thread uses (sparse above [`super::linear::DENSE_LIMIT`]
//! unknowns). Fixed keyframes enter the
//! residuals but not the unknowns; at least one fixed keyframe (or the stereo baseline and a
//! fixed keyframe) removes the gauge freedom, otherwise the LM damping alone holds the gauge.
//!
//! Observations whose point lies at depth Z ≤ `min_depth` contribute nothing at that estimate.
//!
//! A free keyframe may carry a Gaussian prior on its camera centre ([`CentrePrior`]); it adds
//! one 3×3 block to the keyframe's own normal-equation block and is not robustified.
//!
//! Each observation carries its measurement noise σ (pixels, shared by the rows of a stereo
//! triple): residual and Jacobian rows are whitened by 1/σ, so the cost is ½ Σ ρ(‖r‖²/σ²) and
//! the loss scale and outlier bound, stated for σ = 1 px, are σ times as wide in pixels.

use std::sync::atomic::{AtomicBool, Ordering};

use nalgebra::{Matrix3, SMatrix, Vector2, Vector3};
use rayon::prelude::*;

use super::linear::LinearSolver;
use super::lm::{self, LeastSquares, LmOptions, LmReport, Step};
use super::pose::StereoIntrinsics;
use super::robust::Loss;
use super::schur::{add_observation, split_by_point, Schur};
use crate::error::{ensure_finite, Error, Result};
use crate::geometry::so3::hat;
use crate::geometry::Se3;

type M36 = SMatrix<f64, 3, 6>;

/// One keyframe of the window.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BaKeyframe {
    /// Pose of the rectified left camera: maps world points into the camera frame.
    pub cam_from_world: Se3,
    /// Held at its value (older covisible keyframes, the gauge anchor).
    pub fixed: bool,
    /// A Gaussian prior on the camera centre of a free keyframe (ignored when `fixed`).
    pub prior: Option<CentrePrior>,
}

/// A Gaussian prior on a keyframe's camera centre `c = −Rᵀ t`: the cost gains
/// ½ (c − centre)ᵀ · information · (c − centre), without a robust loss. Its Jacobian with
/// respect to the left-multiplied update [ρ, φ] is [−Rᵀ | 0].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CentrePrior {
    /// The centre the prior pulls towards, world frame, metres.
    pub centre: Vector3<f64>,
    /// Inverse covariance of the centre in world axes, 1/m² (symmetric, positive
    /// semi-definite).
    pub information: Matrix3<f64>,
}

impl CentrePrior {
    /// The residual c − centre of the camera `cam_from_world` with rotation matrix `r`.
    fn residual(&self, cam_from_world: &Se3, r: &Matrix3<f64>) -> Vector3<f64> {
        -(r.transpose() * cam_from_world.translation) - self.centre
    }
}

/// A keyframe's observation of a point in its rectified left image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BaObservation {
    /// Index into the keyframes.
    pub keyframe: usize,
    /// Index into the points.
    pub point: usize,
    /// Measured left pixel (u, v): x = column, y = row.
    pub pixel: Vector2<f64>,
    /// Measured right-image column of a stereo match; `None` for a monocular observation.
    pub u_right: Option<f64>,
    /// Centre of the camera pair that measured it, in the keyframe's left-camera axes, with
    /// the keyframe's orientation and baseline (zero: the keyframe's cameras themselves; an
    /// event image warped into the frame cameras through the plane at infinity is the event
    /// cameras' view): the observation sees the camera point minus this.
    pub viewpoint: Vector3<f64>,
    /// Measurement noise of the keypoint, pixels (finite, positive; 1 for a keypoint located
    /// to the pixel, e.g. `scale^octave` for one detected on an image pyramid).
    pub sigma: f64,
}

/// Options of [`solve_stereo_ba`].
#[derive(Clone, Debug, PartialEq)]
pub struct StereoBaOptions {
    /// Loss on each observation's squared pixel error. Default Huber with δ = √7.815 px.
    pub loss: Loss,
    /// Points nearer than this (metres, along the optical axis) are ignored. Default 1e-6.
    pub min_depth: f64,
    /// Squared whitened error (‖r‖²/σ²) above which an observation is an outlier in the
    /// result (stereo and mono alike). Default 7.815 (95 % χ², 3 dof).
    pub outlier_threshold_sq: f64,
    /// Worker threads for residuals, Jacobians and the elimination (0: one per core).
    /// Default 1: the mapping thread shares the machine with tracking.
    pub threads: usize,
    /// The LM loop's options. Default: those of [`LmOptions`] with 10 iterations.
    pub lm: LmOptions,
}

impl Default for StereoBaOptions {
    fn default() -> Self {
        Self {
            loss: Loss::Huber(7.815f64.sqrt()),
            min_depth: 1e-6,
            outlier_threshold_sq: 7.815,
            threads: 1,
            lm: LmOptions {
                max_iterations: 10,
                ..Default::default()
            },
        }
    }
}

/// What [`solve_stereo_ba`] did.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoBaResult {
    /// The LM report (termination [`super::Termination::Interrupted`] when stopped).
    pub report: LmReport,
    /// Per observation, in the caller's order: in front of the camera with a squared whitened
    /// error ‖r‖²/σ² at most `outlier_threshold_sq`, at the returned estimate.
    pub inliers: Vec<bool>,
}

/// The residual (predicted − measured; third row zero for mono), its Jacobian with respect to
/// the left-multiplied pose update [ρ, φ] and with respect to the world point, and the number
/// of residual rows; `None` when the point lies at depth ≤ `min_depth`.
pub fn stereo_ba_residual(
    k: &StereoIntrinsics,
    cam_from_world: &Se3,
    point: &Vector3<f64>,
    pixel: &Vector2<f64>,
    u_right: Option<f64>,
    viewpoint: &Vector3<f64>,
    min_depth: f64,
) -> Option<(Vector3<f64>, M36, Matrix3<f64>, usize)> {
    let pose = PoseState::new(*cam_from_world);
    residual_jacobians(k, &pose, point, pixel, u_right, viewpoint, min_depth)
        .map(|(r, jp, jx)| (r, jp, jx, if u_right.is_some() { 3 } else { 2 }))
}

/// A pose with its rotation matrix cached.
#[derive(Clone, Copy, Debug)]
struct PoseState {
    se3: Se3,
    rotation: Matrix3<f64>,
}

impl PoseState {
    fn new(se3: Se3) -> Self {
        Self {
            se3,
            rotation: se3.rotation.matrix(),
        }
    }

    fn camera_point(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * x + self.se3.translation
    }
}

/// The residual alone (cost evaluation).
#[inline]
fn residual_only(
    k: &StereoIntrinsics,
    pose: &PoseState,
    x: &Vector3<f64>,
    pixel: &Vector2<f64>,
    u_right: Option<f64>,
    viewpoint: &Vector3<f64>,
    min_depth: f64,
) -> Option<Vector3<f64>> {
    let p = pose.camera_point(x) - viewpoint;
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

#[inline]
fn residual_jacobians(
    k: &StereoIntrinsics,
    pose: &PoseState,
    x: &Vector3<f64>,
    pixel: &Vector2<f64>,
    u_right: Option<f64>,
    viewpoint: &Vector3<f64>,
    min_depth: f64,
) -> Option<(Vector3<f64>, M36, Matrix3<f64>)> {
    // The point in the keyframe's camera (q) and as the measuring camera sees it (p).
    let q = pose.camera_point(x);
    let p = q - viewpoint;
    if p.z.partial_cmp(&min_depth) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let iz = 1.0 / p.z;
    // ∂(u_l, v, u_r)/∂P.
    let mut proj = Matrix3::zeros();
    proj[(0, 0)] = k.fx * iz;
    proj[(0, 2)] = -k.fx * p.x * iz * iz;
    proj[(1, 1)] = k.fy * iz;
    proj[(1, 2)] = -k.fy * p.y * iz * iz;
    let mut r = Vector3::new(
        k.fx * p.x * iz + k.cx - pixel.x,
        k.fy * p.y * iz + k.cy - pixel.y,
        0.0,
    );
    if let Some(ur) = u_right {
        proj[(2, 0)] = k.fx * iz;
        proj[(2, 2)] = -k.fx * (p.x - k.baseline) * iz * iz;
        r.z = k.fx * (p.x - k.baseline) * iz + k.cx - ur;
    }
    let mut jp = M36::zeros();
    jp.fixed_view_mut::<3, 3>(0, 0).copy_from(&proj);
    jp.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(-(proj * hat(&q))));
    Some((r, jp, proj * pose.rotation))
}

/// An observation regrouped by point.
#[derive(Clone, Copy, Debug)]
struct Obs {
    keyframe: usize,
    free: Option<usize>,
    pixel: Vector2<f64>,
    u_right: Option<f64>,
    viewpoint: Vector3<f64>,
    /// 1/σ.
    weight: f64,
}

struct StereoBa<'a> {
    k: StereoIntrinsics,
    loss: Loss,
    min_depth: f64,
    stop: Option<&'a AtomicBool>,
    poses: Vec<PoseState>,
    points: Vec<Vector3<f64>>,
    candidate_poses: Vec<PoseState>,
    candidate_points: Vec<Vector3<f64>>,
    free_keyframes: Vec<usize>,
    /// Observations sorted by point (`schur.point_obs`).
    /// (free index, keyframe index, prior) of every free keyframe with a centre prior.
    priors: Vec<(usize, usize, CentrePrior)>,
    obs: Vec<Obs>,
    /// The caller's index of each sorted observation.
    original: Vec<usize>,
    /// The normal equations' blocks, the reduced-system layout and the last step.
    schur: Schur<6>,
    // Linearisation, per sorted observation.
    jp: Vec<M36>,
    residual: Vec<Vector3<f64>>,
}

impl StereoBa<'_> {
    fn cost_of(&self, poses: &[PoseState], points: &[Vector3<f64>]) -> f64 {
        let (k, loss, min_depth) = (&self.k, &self.loss, self.min_depth);
        let (point_obs, obs) = (&self.schur.point_obs, &self.obs);
        0.5 * (0..points.len())
            .into_par_iter()
            .with_min_len(64)
            .map(|j| {
                obs[point_obs[j]..point_obs[j + 1]]
                    .iter()
                    .filter_map(|o| {
                        residual_only(
                            k,
                            &poses[o.keyframe],
                            &points[j],
                            &o.pixel,
                            o.u_right,
                            &o.viewpoint,
                            min_depth,
                        )
                        .map(|r| (r, o.weight))
                    })
                    .map(|(r, w)| loss.evaluate(r.norm_squared() * w * w)[0])
                    .sum::<f64>()
            })
            .sum::<f64>()
            + self
                .priors
                .iter()
                .map(|(_, i, p)| {
                    let r = p.residual(&poses[*i].se3, &poses[*i].rotation);
                    0.5 * r.dot(&(p.information * r))
                })
                .sum::<f64>()
    }
}

impl LeastSquares for StereoBa<'_> {
    fn cost(&mut self) -> f64 {
        self.cost_of(&self.poses, &self.points)
    }

    fn linearize(&mut self) -> f64 {
        let (k, loss, min_depth) = (&self.k, &self.loss, self.min_depth);
        let (poses, points, obs) = (&self.poses, &self.points, &self.obs);
        let schur = &mut self.schur;
        let point_obs = &schur.point_obs;
        // Each point owns a contiguous range of the per-observation arrays.
        split_by_point(&mut self.jp, point_obs)
            .into_par_iter()
            .zip(split_by_point(&mut self.residual, point_obs))
            .zip(split_by_point(&mut schur.wt, point_obs))
            .zip(schur.v.par_iter_mut())
            .zip(schur.gp.par_iter_mut())
            .enumerate()
            .with_min_len(64)
            .for_each(|(j, ((((jp, res), wt), v), gp))| {
                *v = Matrix3::zeros();
                *gp = Vector3::zeros();
                let x = &points[j];
                for (local, o) in obs[point_obs[j]..point_obs[j + 1]].iter().enumerate() {
                    let Some((r, a, b)) = residual_jacobians(
                        k,
                        &poses[o.keyframe],
                        x,
                        &o.pixel,
                        o.u_right,
                        &o.viewpoint,
                        min_depth,
                    ) else {
                        jp[local] = M36::zeros();
                        res[local] = Vector3::zeros();
                        wt[local] = M36::zeros();
                        continue;
                    };
                    // Whitening by 1/σ before the robust correction.
                    let w = o.weight;
                    res[local] = r * w;
                    jp[local] = a * w;
                    wt[local] =
                        add_observation(loss, &mut res[local], &mut jp[local], b * w, v, gp);
                }
            });
        let gmax = schur.accumulate_cameras(&self.jp, &self.residual);
        // Centre priors: J = [−Rᵀ | 0], so U gains R Λ Rᵀ in its translation block and g_c
        // gains −R Λ r.
        let mut gmax_prior: f64 = 0.0;
        for (f, i, p) in &self.priors {
            let (pose, rot) = (&self.poses[*i].se3, &self.poses[*i].rotation);
            let r = p.residual(pose, rot);
            let mut u = schur.u[*f].fixed_view_mut::<3, 3>(0, 0);
            u += rot * p.information * rot.transpose();
            let mut g = schur.gc[*f].fixed_rows_mut::<3>(0);
            g -= rot * (p.information * r);
            gmax_prior = gmax_prior.max(schur.gc[*f].amax());
        }
        gmax.max(gmax_prior)
    }

    fn compute_step(&mut self, mu: f64, lo: f64, hi: f64) -> Option<Step> {
        self.schur.step(mu, lo, hi)
    }

    fn candidate_cost(&mut self) -> f64 {
        self.candidate_poses.copy_from_slice(&self.poses);
        for (f, &i) in self.free_keyframes.iter().enumerate() {
            self.candidate_poses[i] =
                PoseState::new(Se3::exp(&self.schur.step_c[f]) * self.poses[i].se3);
        }
        for ((c, p), d) in self
            .candidate_points
            .iter_mut()
            .zip(&self.points)
            .zip(&self.schur.step_p)
        {
            *c = p + d;
        }
        self.cost_of(&self.candidate_poses, &self.candidate_points)
    }

    fn accept(&mut self) {
        std::mem::swap(&mut self.poses, &mut self.candidate_poses);
        std::mem::swap(&mut self.points, &mut self.candidate_points);
    }

    fn state_norm(&self) -> f64 {
        let c: f64 = self
            .free_keyframes
            .iter()
            .map(|&i| self.poses[i].se3.log().norm_squared())
            .sum();
        let p: f64 = self.points.iter().map(|p| p.norm_squared()).sum();
        (c + p).sqrt()
    }

    fn interrupted(&self) -> bool {
        self.stop.is_some_and(|s| s.load(Ordering::Relaxed))
    }
}

fn check_inputs(
    k: &StereoIntrinsics,
    keyframes: &[BaKeyframe],
    points: &[Vector3<f64>],
    observations: &[BaObservation],
    options: &StereoBaOptions,
) -> Result<()> {
    options.lm.check()?;
    ensure_finite("intrinsics", &[k.fx, k.fy, k.cx, k.cy, k.baseline])?;
    if !(k.fx > 0.0 && k.fy > 0.0) {
        return Err(Error::invalid(
            "intrinsics fx, fy",
            "positive focal lengths",
            format!("{}, {}", k.fx, k.fy),
        ));
    }
    if let Some(s) = options.loss.scale() {
        if !(s.is_finite() && s > 0.0) {
            return Err(Error::invalid("loss scale", "a positive finite number", s));
        }
    }
    ensure_finite("min_depth", &[options.min_depth])?;
    if options.outlier_threshold_sq.is_nan() || options.outlier_threshold_sq < 0.0 {
        return Err(Error::invalid(
            "outlier_threshold_sq",
            "a non-negative number",
            options.outlier_threshold_sq,
        ));
    }
    if observations.is_empty() {
        return Err(Error::invalid("observations", "at least one", 0));
    }
    for (i, kf) in keyframes.iter().enumerate() {
        let t = kf.cam_from_world.translation;
        let q = kf.cam_from_world.rotation.to_quaternion_xyzw();
        ensure_finite(
            &format!("keyframes[{i}].cam_from_world"),
            &[t.x, t.y, t.z, q[0], q[1], q[2], q[3]],
        )?;
    }
    for (i, kf) in keyframes.iter().enumerate() {
        if let Some(p) = kf.prior {
            ensure_finite(&format!("keyframes[{i}].prior.centre"), p.centre.as_slice())?;
            ensure_finite(
                &format!("keyframes[{i}].prior.information"),
                p.information.as_slice(),
            )?;
        }
    }
    for (j, p) in points.iter().enumerate() {
        ensure_finite(&format!("points[{j}]"), p.as_slice())?;
    }
    let (n_kf, n_pt) = (keyframes.len(), points.len());
    for (s, o) in observations.iter().enumerate() {
        if o.keyframe >= n_kf || o.point >= n_pt {
            return Err(Error::invalid(
                format!("observations[{s}]"),
                format!("keyframe < {n_kf} and point < {n_pt}"),
                format!("keyframe {} point {}", o.keyframe, o.point),
            ));
        }
        let ur = o.u_right.unwrap_or(0.0);
        ensure_finite(
            &format!("observations[{s}] (u, v, u_right)"),
            &[o.pixel.x, o.pixel.y, ur],
        )?;
        ensure_finite(
            &format!("observations[{s}].viewpoint"),
            o.viewpoint.as_slice(),
        )?;
        if !(o.sigma.is_finite() && o.sigma > 0.0) {
            return Err(Error::invalid(
                format!("observations[{s}].sigma"),
                "a finite positive number of pixels",
                o.sigma,
            ));
        }
        if o.u_right.is_some() && k.baseline <= 0.0 {
            return Err(Error::invalid(
                "intrinsics baseline",
                "a positive baseline (metres) for stereo observations",
                k.baseline,
            ));
        }
    }
    Ok(())
}

/// Local bundle adjustment: refines the free keyframes' `cam_from_world` and every point
/// (world frame, metres) in place, from rectified-stereo and monocular observations of the
/// rectified left camera `k` (right camera at +`k.baseline` along x).
///
/// `stop`, when given and set (by another thread), ends the solve before its next iteration
/// with [`super::Termination::Interrupted`]; the estimate written back is then the best one
/// reached. Points without observations and free keyframes without observations stay where
/// they are.
pub fn solve_stereo_ba(
    k: &StereoIntrinsics,
    keyframes: &mut [BaKeyframe],
    points: &mut [Vector3<f64>],
    observations: &[BaObservation],
    options: &StereoBaOptions,
    stop: Option<&AtomicBool>,
) -> Result<StereoBaResult> {
    check_inputs(k, keyframes, points, observations, options)?;
    let (n_kf, n_pt, n_obs) = (keyframes.len(), points.len(), observations.len());
    let mut free_index = vec![None; n_kf];
    let mut free_keyframes = Vec::new();
    let mut priors = Vec::new();
    for (i, kf) in keyframes.iter().enumerate() {
        if !kf.fixed {
            if let Some(p) = kf.prior {
                priors.push((free_keyframes.len(), i, p));
            }
            free_index[i] = Some(free_keyframes.len());
            free_keyframes.push(i);
        }
    }
    let n_free = free_keyframes.len();
    // Counting sort of the observations by point.
    let mut point_obs = vec![0usize; n_pt + 1];
    for o in observations {
        point_obs[o.point + 1] += 1;
    }
    for j in 0..n_pt {
        point_obs[j + 1] += point_obs[j];
    }
    let mut fill = point_obs.clone();
    let mut obs = vec![
        Obs {
            keyframe: 0,
            free: None,
            pixel: Vector2::zeros(),
            u_right: None,
            viewpoint: Vector3::zeros(),
            weight: 1.0,
        };
        n_obs
    ];
    let mut original = vec![0usize; n_obs];
    for (s, o) in observations.iter().enumerate() {
        let at = fill[o.point];
        fill[o.point] += 1;
        obs[at] = Obs {
            keyframe: o.keyframe,
            free: free_index[o.keyframe],
            pixel: o.pixel,
            u_right: o.u_right,
            viewpoint: o.viewpoint,
            weight: 1.0 / o.sigma,
        };
        original[at] = s;
    }
    let threads = if options.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        options.threads
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::numerical("thread pool", e.to_string()))?;
    let obs_free = obs.iter().map(|o| o.free).collect();
    let schur = Schur::new(
        point_obs,
        obs_free,
        n_free,
        LinearSolver::Auto,
        threads,
        "stereo bundle adjustment",
    )?;
    let poses: Vec<PoseState> = keyframes
        .iter()
        .map(|kf| PoseState::new(kf.cam_from_world))
        .collect();
    let mut problem = StereoBa {
        k: *k,
        loss: options.loss,
        min_depth: options.min_depth,
        stop,
        candidate_poses: poses.clone(),
        candidate_points: points.to_vec(),
        poses,
        points: points.to_vec(),
        free_keyframes,
        priors,
        obs,
        original,
        schur,
        jp: vec![M36::zeros(); n_obs],
        residual: vec![Vector3::zeros(); n_obs],
    };
    let report = pool.install(|| lm::solve(&mut problem, &options.lm))?;
    for (kf, pose) in keyframes.iter_mut().zip(&problem.poses) {
        kf.cam_from_world = pose.se3;
    }
    points.copy_from_slice(&problem.points);
    let mut inliers = vec![false; n_obs];
    for j in 0..n_pt {
        for s in problem.schur.point_obs[j]..problem.schur.point_obs[j + 1] {
            let o = &problem.obs[s];
            let r = residual_only(
                k,
                &problem.poses[o.keyframe],
                &problem.points[j],
                &o.pixel,
                o.u_right,
                &o.viewpoint,
                options.min_depth,
            );
            let w2 = o.weight * o.weight;
            inliers[problem.original[s]] =
                r.is_some_and(|r| r.norm_squared() * w2 <= options.outlier_threshold_sq);
        }
    }
    Ok(StereoBaResult { report, inliers })
}
