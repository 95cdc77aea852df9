//! Bundle adjustment of BAL problems with the Schur complement.
//!
//! Unknowns: per camera c = [δφ, δt, δf, δk1, δk2] (rotation updated on the left,
//! R ← exp(δφ) R), per point δX. With U = Σ J_cᵀJ_c, V = Σ J_pᵀJ_p, W = J_cᵀJ_p and gradients
//! g_c, g_p, the damped normal equations
//!
//! ```text
//! [U* W ] [δc]     [g_c]        S δc = −g_c + W V*⁻¹ g_p,   S = U* − W V*⁻¹ Wᵀ
//! [Wᵀ V*] [δp] = − [g_p]   ⇒    δp = −V*⁻¹ (g_p + Wᵀ δc)
//! ```
//!
//! eliminate the points (V* is block-diagonal with 3×3 blocks), leaving the reduced camera
//! system S whose block pattern is the camera covisibility graph. S is factorised densely for
//! small windows and by sparse Cholesky (symbolic analysis once per solve) for large ones.
//! Residuals, Jacobians and the elimination run in parallel with rayon on a local pool.

use nalgebra::{Matrix2x3, Matrix3, SMatrix, SVector, Vector2, Vector3};
use rayon::prelude::*;

use super::linear::{BlockCholesky, BlockPattern, LinearSolver};
use super::lm::{self, LeastSquares, LmOptions, LmReport, Step};
use super::robust::{Corrector, Loss};
use crate::error::{Error, Result};
use crate::geometry::so3::hat;
use crate::geometry::So3;
use crate::io::BalProblem;

type M29 = SMatrix<f64, 2, 9>;
type M93 = SMatrix<f64, 9, 3>;
type M99 = SMatrix<f64, 9, 9>;
type V9 = SVector<f64, 9>;

/// Options of [`BundleAdjustment`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BundleOptions {
    /// Loss on each observation's squared pixel error.
    pub loss: Loss,
    /// How the reduced camera system is factorised.
    pub linear_solver: LinearSolver,
    /// Worker threads (0: one per available core).
    pub threads: usize,
    /// Cameras held fixed (indices into the problem's cameras).
    pub fixed_cameras: Vec<usize>,
    /// Observations whose point lies behind the camera (depth below machine epsilon)
    /// contribute no residual, as COLMAP's reprojection cost does; off, every observation
    /// counts, as in the plain BAL cost.
    pub zero_behind_camera: bool,
    /// The LM loop's options.
    pub lm: LmOptions,
}

/// A BAL camera with its rotation matrix cached.
#[derive(Clone, Copy, Debug)]
struct CameraState {
    rotation: So3,
    matrix: Matrix3<f64>,
    translation: Vector3<f64>,
    focal: f64,
    k1: f64,
    k2: f64,
}

impl CameraState {
    fn from_bal(c: &[f64; 9]) -> Self {
        let rotation = So3::exp(&Vector3::new(c[0], c[1], c[2]));
        Self {
            rotation,
            matrix: rotation.matrix(),
            translation: Vector3::new(c[3], c[4], c[5]),
            focal: c[6],
            k1: c[7],
            k2: c[8],
        }
    }

    fn to_bal(self) -> [f64; 9] {
        let w = self.rotation.log();
        let t = self.translation;
        [w.x, w.y, w.z, t.x, t.y, t.z, self.focal, self.k1, self.k2]
    }

    fn plus(&self, d: &V9) -> Self {
        let rotation = So3::exp(&Vector3::new(d[0], d[1], d[2])) * self.rotation;
        Self {
            rotation,
            matrix: rotation.matrix(),
            translation: self.translation + Vector3::new(d[3], d[4], d[5]),
            focal: self.focal + d[6],
            k1: self.k1 + d[7],
            k2: self.k2 + d[8],
        }
    }

    /// Whether `x` is in front of the camera (BAL cameras look down −z).
    fn sees(&self, x: &Vector3<f64>) -> bool {
        -(self.matrix.row(2) * x)[0] - self.translation.z >= f64::EPSILON
    }

    /// The predicted pixel.
    fn project(&self, x: &Vector3<f64>) -> Vector2<f64> {
        let pc = self.matrix * x + self.translation;
        let p = Vector2::new(-pc.x / pc.z, -pc.y / pc.z);
        let r2 = p.norm_squared();
        p * (self.focal * (1.0 + r2 * (self.k1 + self.k2 * r2)))
    }

    /// The predicted pixel with its Jacobians with respect to the camera update and the point.
    fn project_with_jacobians(&self, x: &Vector3<f64>) -> (Vector2<f64>, M29, Matrix2x3<f64>) {
        let rx = self.matrix * x;
        let pc = rx + self.translation;
        let iz = 1.0 / pc.z;
        let p = Vector2::new(-pc.x * iz, -pc.y * iz);
        let r2 = p.norm_squared();
        let d = 1.0 + r2 * (self.k1 + self.k2 * r2);
        let f = self.focal;
        // ∂p/∂P for p = −P_xy / P_z.
        let dp_dpc = Matrix2x3::new(-iz, 0.0, -p.x * iz, 0.0, -iz, -p.y * iz);
        // ∂pixel/∂p = f (d I + 2 (k1 + 2 k2 r²) p pᵀ).
        let dd = 2.0 * (self.k1 + 2.0 * self.k2 * r2);
        let dpix_dp = nalgebra::Matrix2::new(
            d + dd * p.x * p.x,
            dd * p.x * p.y,
            dd * p.x * p.y,
            d + dd * p.y * p.y,
        ) * f;
        let a = dpix_dp * dp_dpc;
        let mut jc = M29::zeros();
        // P = R X + t with R ← exp(δφ) R: ∂P/∂δφ = −[R X]×, ∂P/∂δt = I.
        jc.fixed_view_mut::<2, 3>(0, 0).copy_from(&(-a * hat(&rx)));
        jc.fixed_view_mut::<2, 3>(0, 3).copy_from(&a);
        jc.set_column(6, &(p * d));
        jc.set_column(7, &(p * (f * r2)));
        jc.set_column(8, &(p * (f * r2 * r2)));
        (p * (f * d), jc, a * self.matrix)
    }
}

/// Bundle adjustment of one BAL problem. Build it with [`BundleAdjustment::new`], run
/// [`BundleAdjustment::solve`], read the result with [`BundleAdjustment::cameras`] and
/// [`BundleAdjustment::points`] or [`BundleAdjustment::write_back`].
pub struct BundleAdjustment {
    loss: Loss,
    zero_behind_camera: bool,
    lm: LmOptions,
    pool: rayon::ThreadPool,
    threads: usize,
    cameras: Vec<CameraState>,
    points: Vec<Vector3<f64>>,
    candidate_cameras: Vec<CameraState>,
    candidate_points: Vec<Vector3<f64>>,
    /// Observations sorted by point: `point_obs[j]..point_obs[j + 1]`.
    point_obs: Vec<usize>,
    obs_camera: Vec<usize>,
    obs_pixel: Vec<Vector2<f64>>,
    /// Original observation order, to map back.
    free_index: Vec<Option<usize>>,
    /// For each free camera, its observations.
    camera_obs: Vec<Vec<usize>>,
    /// Per point, the reduced-system slots of its free observation pairs (a ≤ b in local
    /// order), flattened; `pair_start[j]` indexes the first.
    pair_slots: Vec<(usize, bool)>,
    pair_start: Vec<usize>,
    pattern: BlockPattern,
    cholesky: BlockCholesky,
    // Linearisation.
    jc: Vec<M29>,
    residual: Vec<Vector2<f64>>,
    w: Vec<M93>,
    u: Vec<M99>,
    gc: Vec<V9>,
    v: Vec<Matrix3<f64>>,
    gp: Vec<Vector3<f64>>,
    // Step.
    step_c: Vec<V9>,
    step_p: Vec<Vector3<f64>>,
}

impl BundleAdjustment {
    /// Prepares the solver: checks indices, groups observations, analyses the pattern.
    pub fn new(problem: &BalProblem, options: &BundleOptions) -> Result<Self> {
        options.lm.check()?;
        let n_cam = problem.cameras.len();
        let n_pt = problem.points.len();
        for (k, o) in problem.observations.iter().enumerate() {
            if o.camera >= n_cam || o.point >= n_pt {
                return Err(Error::invalid(
                    format!("observations[{k}]"),
                    format!("camera < {n_cam} and point < {n_pt}"),
                    format!("camera {} point {}", o.camera, o.point),
                ));
            }
        }
        for (i, c) in problem.cameras.iter().enumerate() {
            crate::error::ensure_finite(&format!("cameras[{i}]"), c)?;
        }
        for (j, p) in problem.points.iter().enumerate() {
            crate::error::ensure_finite(&format!("points[{j}]"), p)?;
        }
        if let Some(s) = options.loss.scale() {
            if !(s.is_finite() && s > 0.0) {
                return Err(Error::invalid("loss scale", "a positive finite number", s));
            }
        }
        let mut fixed = vec![false; n_cam];
        for &c in &options.fixed_cameras {
            if c >= n_cam {
                return Err(Error::invalid(
                    "fixed_cameras",
                    format!("indices below {n_cam}"),
                    c,
                ));
            }
            fixed[c] = true;
        }
        let mut free_index = vec![None; n_cam];
        let mut n_free = 0;
        for (i, f) in fixed.iter().enumerate() {
            if !f {
                free_index[i] = Some(n_free);
                n_free += 1;
            }
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

        // Counting sort of the observations by point.
        let mut point_obs = vec![0usize; n_pt + 1];
        for o in &problem.observations {
            point_obs[o.point + 1] += 1;
        }
        for j in 0..n_pt {
            point_obs[j + 1] += point_obs[j];
        }
        let mut fill = point_obs.clone();
        let n_obs = problem.observations.len();
        let mut obs_camera = vec![0; n_obs];
        let mut obs_pixel = vec![Vector2::zeros(); n_obs];
        for o in &problem.observations {
            let k = fill[o.point];
            fill[o.point] += 1;
            obs_camera[k] = o.camera;
            obs_pixel[k] = Vector2::new(o.pixel[0], o.pixel[1]);
        }
        let mut camera_obs = vec![Vec::new(); n_free];
        for (k, &c) in obs_camera.iter().enumerate() {
            if let Some(f) = free_index[c] {
                camera_obs[f].push(k);
            }
        }
        let mut pairs = Vec::new();
        for j in 0..n_pt {
            let cams: Vec<usize> = (point_obs[j]..point_obs[j + 1])
                .filter_map(|k| free_index[obs_camera[k]])
                .collect();
            for (a, &ca) in cams.iter().enumerate() {
                for &cb in &cams[a + 1..] {
                    if ca != cb {
                        pairs.push((ca, cb));
                    }
                }
            }
        }
        let pattern = BlockPattern::new(n_free, 9, pairs);
        let mut pair_slots = Vec::new();
        let mut pair_start = Vec::with_capacity(n_pt + 1);
        for j in 0..n_pt {
            pair_start.push(pair_slots.len());
            let cams: Vec<usize> = (point_obs[j]..point_obs[j + 1])
                .filter_map(|k| free_index[obs_camera[k]])
                .collect();
            for (a, &ca) in cams.iter().enumerate() {
                for &cb in &cams[a..] {
                    let (lo, hi) = (ca.min(cb), ca.max(cb));
                    let slot = pattern.slot(lo, hi).ok_or_else(|| {
                        Error::numerical("bundle adjustment", "covisibility pattern incomplete")
                    })?;
                    pair_slots.push((slot, ca > cb));
                }
            }
        }
        pair_start.push(pair_slots.len());
        let cholesky =
            pool.install(|| BlockCholesky::new(&pattern, options.linear_solver, threads))?;
        let cameras: Vec<CameraState> = problem.cameras.iter().map(CameraState::from_bal).collect();
        let points: Vec<Vector3<f64>> = problem.points.iter().map(|p| Vector3::from(*p)).collect();
        Ok(Self {
            loss: options.loss,
            zero_behind_camera: options.zero_behind_camera,
            lm: options.lm.clone(),
            pool,
            threads,
            candidate_cameras: cameras.clone(),
            candidate_points: points.clone(),
            cameras,
            points,
            point_obs,
            obs_camera,
            obs_pixel,
            free_index,
            camera_obs,
            pair_slots,
            pair_start,
            pattern,
            cholesky,
            jc: vec![M29::zeros(); n_obs],
            residual: vec![Vector2::zeros(); n_obs],
            w: vec![M93::zeros(); n_obs],
            u: vec![M99::zeros(); n_free],
            gc: vec![V9::zeros(); n_free],
            v: vec![Matrix3::zeros(); n_pt],
            gp: vec![Vector3::zeros(); n_pt],
            step_c: vec![V9::zeros(); n_free],
            step_p: vec![Vector3::zeros(); n_pt],
        })
    }

    /// Worker threads in use.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Whether the reduced camera system is factorised densely.
    pub fn uses_dense_solver(&self) -> bool {
        self.cholesky.is_dense()
    }

    /// Runs Levenberg–Marquardt from the current estimate.
    pub fn solve(&mut self) -> Result<LmReport> {
        let options = self.lm.clone();
        let pool = std::mem::replace(
            &mut self.pool,
            rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .build()
                .map_err(|e| Error::numerical("thread pool", e.to_string()))?,
        );
        let report = pool.install(|| lm::solve(self, &options));
        self.pool = pool;
        report
    }

    /// ½Σρ(‖r‖²) at the current estimate.
    pub fn current_cost(&mut self) -> f64 {
        let pool = &self.pool;
        pool.install(|| {
            total_cost(
                &self.cameras,
                &self.points,
                &self.point_obs,
                &self.obs_camera,
                &self.obs_pixel,
                &self.loss,
                self.zero_behind_camera,
            )
        })
    }

    /// Cameras in BAL layout.
    pub fn cameras(&self) -> Vec<[f64; 9]> {
        self.cameras.iter().map(|c| c.to_bal()).collect()
    }

    /// Points.
    pub fn points(&self) -> Vec<[f64; 3]> {
        self.points.iter().map(|p| [p.x, p.y, p.z]).collect()
    }

    /// Copies the estimate into `problem` (which must be the problem this was built from).
    pub fn write_back(&self, problem: &mut BalProblem) {
        problem.cameras = self.cameras();
        problem.points = self.points();
    }
}

fn total_cost(
    cameras: &[CameraState],
    points: &[Vector3<f64>],
    point_obs: &[usize],
    obs_camera: &[usize],
    obs_pixel: &[Vector2<f64>],
    loss: &Loss,
    zero_behind_camera: bool,
) -> f64 {
    0.5 * (0..points.len())
        .into_par_iter()
        .map(|j| {
            (point_obs[j]..point_obs[j + 1])
                .map(|k| {
                    let cam = &cameras[obs_camera[k]];
                    if zero_behind_camera && !cam.sees(&points[j]) {
                        return 0.0;
                    }
                    let r = cam.project(&points[j]) - obs_pixel[k];
                    loss.evaluate(r.norm_squared())[0]
                })
                .sum::<f64>()
        })
        .sum::<f64>()
}

/// clamp(diag(m), lo, hi).
fn clamped_diagonal<const N: usize>(m: &SMatrix<f64, N, N>, lo: f64, hi: f64) -> SVector<f64, N> {
    SVector::<f64, N>::from_fn(|i, _| m[(i, i)].clamp(lo, hi))
}

impl LeastSquares for BundleAdjustment {
    fn cost(&mut self) -> f64 {
        total_cost(
            &self.cameras,
            &self.points,
            &self.point_obs,
            &self.obs_camera,
            &self.obs_pixel,
            &self.loss,
            self.zero_behind_camera,
        )
    }

    fn linearize(&mut self) -> f64 {
        let (cameras, points) = (&self.cameras, &self.points);
        let (point_obs, obs_camera, obs_pixel, loss) = (
            &self.point_obs,
            &self.obs_camera,
            &self.obs_pixel,
            &self.loss,
        );
        let free_index = &self.free_index;
        let zero_behind_camera = self.zero_behind_camera;
        // Residuals and Jacobians per point (each point owns a contiguous range).
        type PointSlices<'a> = (&'a mut [M29], &'a mut [Vector2<f64>], &'a mut [M93]);
        let mut per_point: Vec<PointSlices> = Vec::with_capacity(points.len());
        {
            let (mut jc, mut res, mut w) =
                (&mut self.jc[..], &mut self.residual[..], &mut self.w[..]);
            for j in 0..points.len() {
                let m = point_obs[j + 1] - point_obs[j];
                let (a, b) = jc.split_at_mut(m);
                let (e, f) = res.split_at_mut(m);
                let (g, h) = w.split_at_mut(m);
                per_point.push((a, e, g));
                jc = b;
                res = f;
                w = h;
            }
        }
        per_point
            .into_par_iter()
            .zip(self.v.par_iter_mut())
            .zip(self.gp.par_iter_mut())
            .enumerate()
            .for_each(|(j, (((jc, res, w), v), gp))| {
                *v = Matrix3::zeros();
                *gp = Vector3::zeros();
                for (local, k) in (point_obs[j]..point_obs[j + 1]).enumerate() {
                    let cam = &cameras[obs_camera[k]];
                    if zero_behind_camera && !cam.sees(&points[j]) {
                        w[local] = M93::zeros();
                        jc[local] = M29::zeros();
                        res[local] = Vector2::zeros();
                        continue;
                    }
                    let (pix, mut a, mut b) = cam.project_with_jacobians(&points[j]);
                    let mut r = pix - obs_pixel[k];
                    if *loss != Loss::Trivial {
                        let corr = Corrector::new(loss, r.norm_squared());
                        if !corr.is_scalar() {
                            let rr = r * r.transpose() * corr.alpha_over_s;
                            a -= rr * a;
                            b -= rr * b;
                        }
                        a *= corr.sqrt_rho1;
                        b *= corr.sqrt_rho1;
                        r *= corr.residual_scale;
                    }
                    *v += b.transpose() * b;
                    *gp += b.transpose() * r;
                    if free_index[obs_camera[k]].is_some() {
                        w[local] = a.transpose() * b;
                    }
                    jc[local] = a;
                    res[local] = r;
                }
            });
        let (jc, residual) = (&self.jc, &self.residual);
        self.u
            .par_iter_mut()
            .zip(self.gc.par_iter_mut())
            .zip(self.camera_obs.par_iter())
            .for_each(|((u, g), obs)| {
                *u = M99::zeros();
                *g = V9::zeros();
                for &k in obs {
                    *u += jc[k].transpose() * jc[k];
                    *g += jc[k].transpose() * residual[k];
                }
            });
        let gmax_c = self.gc.iter().map(|g| g.amax()).fold(0.0, f64::max);
        let gmax_p = self.gp.iter().map(|g| g.amax()).fold(0.0, f64::max);
        gmax_c.max(gmax_p)
    }

    fn compute_step(&mut self, mu: f64, lo: f64, hi: f64) -> Option<Step> {
        let n_free = self.u.len();
        let dim = self.pattern.dim();
        // Damped, inverted point blocks.
        let v_inv: Vec<Option<Matrix3<f64>>> = self
            .v
            .par_iter()
            .map(|v| {
                let d = clamped_diagonal(v, lo, hi);
                (v + Matrix3::from_diagonal(&(d * mu)))
                    .cholesky()
                    .map(|c| c.inverse())
            })
            .collect();
        if v_inv.iter().any(Option::is_none) {
            return None;
        }
        let n_values = self.pattern.stored_blocks() * 81;
        let (point_obs, obs_camera, free_index) =
            (&self.point_obs, &self.obs_camera, &self.free_index);
        let (w, gp, pair_slots, pair_start) =
            (&self.w, &self.gp, &self.pair_slots, &self.pair_start);
        // S = −Σ W V*⁻¹ Wᵀ off the camera diagonal terms, rhs = Σ W V*⁻¹ g_p, accumulated
        // per thread and summed.
        let (mut values, mut rhs) = (0..self.points.len())
            .into_par_iter()
            .fold(
                || (vec![0.0; n_values], vec![0.0; dim]),
                |(mut values, mut rhs), j| {
                    let Some(vi) = v_inv[j] else {
                        return (values, rhs);
                    };
                    let free: Vec<(usize, usize)> = (point_obs[j]..point_obs[j + 1])
                        .filter_map(|k| free_index[obs_camera[k]].map(|c| (k, c)))
                        .collect();
                    let mut slot = pair_start[j];
                    for (a, &(ka, ca)) in free.iter().enumerate() {
                        let wv = w[ka] * vi;
                        let b = wv * gp[j];
                        for (x, y) in rhs[ca * 9..ca * 9 + 9].iter_mut().zip(b.iter()) {
                            *x += y;
                        }
                        for &(kb, _) in &free[a..] {
                            let (s, transposed) = pair_slots[slot];
                            slot += 1;
                            let block = wv * w[kb].transpose();
                            let dst = &mut values[s * 81..s * 81 + 81];
                            if transposed {
                                let bt = block.transpose();
                                for (x, y) in dst.iter_mut().zip(bt.iter()) {
                                    *x -= y;
                                }
                            } else {
                                for (x, y) in dst.iter_mut().zip(block.iter()) {
                                    *x -= y;
                                }
                            }
                            // A point seen twice by one camera lands on a diagonal block
                            // through two ordered pairs; the symmetric half is added here.
                            if ka != kb && free_index[obs_camera[ka]] == free_index[obs_camera[kb]]
                            {
                                let bt = block.transpose();
                                for (x, y) in dst.iter_mut().zip(bt.iter()) {
                                    *x -= y;
                                }
                            }
                        }
                    }
                    (values, rhs)
                },
            )
            .reduce(
                || (vec![0.0; n_values], vec![0.0; dim]),
                |(mut va, mut ra), (vb, rb)| {
                    va.iter_mut().zip(&vb).for_each(|(x, y)| *x += y);
                    ra.iter_mut().zip(&rb).for_each(|(x, y)| *x += y);
                    (va, ra)
                },
            );
        let mut camera_diag = Vec::with_capacity(n_free);
        for i in 0..n_free {
            let d = clamped_diagonal(&self.u[i], lo, hi);
            let ud = self.u[i] + M99::from_diagonal(&(d * mu));
            let s = self.pattern.diagonal_slot(i);
            for (x, y) in values[s * 81..s * 81 + 81].iter_mut().zip(ud.iter()) {
                *x += y;
            }
            for (x, y) in rhs[i * 9..i * 9 + 9].iter_mut().zip(self.gc[i].iter()) {
                *x -= y;
            }
            camera_diag.push(d);
        }
        if !self.cholesky.solve(&self.pattern, &values, &mut rhs) {
            return None;
        }
        if rhs.iter().any(|x| !x.is_finite()) {
            return None;
        }
        for (i, s) in self.step_c.iter_mut().enumerate() {
            *s = V9::from_column_slice(&rhs[i * 9..i * 9 + 9]);
        }
        let step_c = &self.step_c;
        let v = &self.v;
        // Back-substitution δp = −V*⁻¹ (g_p + Σ Wᵀ δc), and the model decrease terms.
        let point_terms: (f64, f64, f64) = self
            .step_p
            .par_iter_mut()
            .enumerate()
            .map(|(j, dp)| {
                let mut b = gp[j];
                for k in point_obs[j]..point_obs[j + 1] {
                    if let Some(c) = free_index[obs_camera[k]] {
                        b += w[k].transpose() * step_c[c];
                    }
                }
                let vi = v_inv[j].unwrap_or_else(Matrix3::zeros);
                *dp = -(vi * b);
                let d = clamped_diagonal(&v[j], lo, hi);
                (
                    -gp[j].dot(dp),
                    dp.component_mul(dp).dot(&d),
                    dp.norm_squared(),
                )
            })
            .reduce(|| (0.0, 0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
        let mut neg_g_dot = point_terms.0;
        let mut d_dot = point_terms.1;
        let mut norm2 = point_terms.2;
        for ((dc, g), d) in self.step_c.iter().zip(&self.gc).zip(&camera_diag) {
            neg_g_dot -= g.dot(dc);
            d_dot += dc.component_mul(dc).dot(d);
            norm2 += dc.norm_squared();
        }
        Some(Step {
            model_decrease: 0.5 * (neg_g_dot + mu * d_dot),
            norm: norm2.sqrt(),
        })
    }

    fn candidate_cost(&mut self) -> f64 {
        for (i, cam) in self.cameras.iter().enumerate() {
            self.candidate_cameras[i] = match self.free_index[i] {
                Some(f) => cam.plus(&self.step_c[f]),
                None => *cam,
            };
        }
        let step_p = &self.step_p;
        self.candidate_points
            .par_iter_mut()
            .zip(self.points.par_iter())
            .enumerate()
            .for_each(|(j, (c, p))| *c = p + step_p[j]);
        total_cost(
            &self.candidate_cameras,
            &self.candidate_points,
            &self.point_obs,
            &self.obs_camera,
            &self.obs_pixel,
            &self.loss,
            self.zero_behind_camera,
        )
    }

    fn accept(&mut self) {
        std::mem::swap(&mut self.cameras, &mut self.candidate_cameras);
        std::mem::swap(&mut self.points, &mut self.candidate_points);
    }

    fn state_norm(&self) -> f64 {
        let c: f64 = self
            .cameras
            .iter()
            .map(|c| c.to_bal().iter().map(|x| x * x).sum::<f64>())
            .sum();
        let p: f64 = self.points.iter().map(|p| p.norm_squared()).sum();
        (c + p).sqrt()
    }
}

/// Solves a BAL problem in place and returns the report; its times include the setup
/// (grouping observations, pattern analysis, symbolic factorisation).
pub fn solve_bal(problem: &mut BalProblem, options: &BundleOptions) -> Result<LmReport> {
    let start = std::time::Instant::now();
    let mut ba = BundleAdjustment::new(problem, options)?;
    let setup = start.elapsed().as_secs_f64();
    let mut report = ba.solve()?;
    report.include_setup(setup);
    ba.write_back(problem);
    Ok(report)
}

/// The pixel a BAL camera predicts for a world point (for tests and tools).
pub fn bal_project(camera: &[f64; 9], point: &[f64; 3]) -> [f64; 2] {
    let p = CameraState::from_bal(camera).project(&Vector3::from(*point));
    [p.x, p.y]
}

/// The BAL residual (predicted − measured pixel) and its Jacobians with respect to the
/// camera update [δφ (left), δt, δf, δk1, δk2] (2×9, row-major) and the point (2×3,
/// row-major), as the solver linearises them.
pub fn bal_residual_jacobians(
    camera: &[f64; 9],
    point: &[f64; 3],
    pixel: &[f64; 2],
) -> ([f64; 2], [f64; 18], [f64; 6]) {
    let (p, jc, jp) = CameraState::from_bal(camera).project_with_jacobians(&Vector3::from(*point));
    let mut a = [0.0; 18];
    let mut b = [0.0; 6];
    for r in 0..2 {
        for c in 0..9 {
            a[r * 9 + c] = jc[(r, c)];
        }
        for c in 0..3 {
            b[r * 3 + c] = jp[(r, c)];
        }
    }
    ([p.x - pixel[0], p.y - pixel[1]], a, b)
}

/// Applies a camera update [δφ, δt, δf, δk1, δk2] the way the solver does (for tests).
pub fn bal_camera_plus(camera: &[f64; 9], delta: &[f64; 9]) -> [f64; 9] {
    CameraState::from_bal(camera)
        .plus(&V9::from_column_slice(delta))
        .to_bal()
}
