//! The damped Schur-complement step shared by the bundle adjusters ([`super::ba`] for BAL
//! cameras with C = 9 parameters, [`super::stereo_ba`] for SE(3) keyframes with C = 6).
//!
//! With U = Σ J_cᵀJ_c per free camera, V = Σ J_pᵀJ_p per point, W = J_cᵀJ_p per observation
//! and the gradients g_c, g_p, the damped normal equations
//!
//! ```text
//! [U* W ] [δc]     [g_c]        S δc = −g_c + W V*⁻¹ g_p,   S = U* − W V*⁻¹ Wᵀ
//! [Wᵀ V*] [δp] = − [g_p]   ⇒    δp = −V*⁻¹ (g_p + Wᵀ δc)
//! ```
//!
//! eliminate the points (V* is block-diagonal with 3×3 blocks), leaving the reduced camera
//! system S whose block pattern is the covisibility graph of the free cameras, factorised by
//! [`BlockCholesky`]. Damping is Marquardt's: U* = U + μ D_c, V* = V + μ D_p with D the
//! diagonal clamped to [lo, hi]. The solvers fill the blocks in their `linearize` (each point
//! owns a contiguous range of observations, see [`split_by_point`]) and call
//! [`Schur::accumulate_cameras`] and [`Schur::step`].

use nalgebra::{Const, Matrix3, MatrixViewMut, SMatrix, SVector, Vector3};
use rayon::prelude::*;

use super::linear::{BlockCholesky, BlockPattern, LinearSolver};
use super::lm::Step;
use super::robust::Loss;
use crate::error::{Error, Result};

/// The normal-equation blocks and the reduced-system layout of a problem with cameras of `C`
/// parameters and 3-D points, observations grouped by point.
pub(crate) struct Schur<const C: usize> {
    /// Observations sorted by point: `point_obs[j]..point_obs[j + 1]` are point j's.
    pub point_obs: Vec<usize>,
    /// The free-camera index of each sorted observation (`None` for a fixed camera).
    pub obs_free: Vec<Option<usize>>,
    /// Per free camera, its sorted observations.
    camera_obs: Vec<Vec<usize>>,
    /// Per point, the reduced-system slot (and whether the block goes in transposed) of each
    /// ordered pair a ≤ b of its free observations; `pair_start[j]` indexes the first.
    pair_slots: Vec<(usize, bool)>,
    pair_start: Vec<usize>,
    pattern: BlockPattern,
    cholesky: BlockCholesky,
    /// U per free camera (C×C), filled by [`Schur::accumulate_cameras`].
    pub u: Vec<SMatrix<f64, C, C>>,
    /// g_c per free camera.
    pub gc: Vec<SVector<f64, C>>,
    /// V per point (3×3), filled by the solver's linearisation.
    pub v: Vec<Matrix3<f64>>,
    /// g_p per point.
    pub gp: Vec<Vector3<f64>>,
    /// Wᵀ = J_pᵀ J_c per sorted observation (3×C); read only where the camera is free.
    pub wt: Vec<SMatrix<f64, 3, C>>,
    v_inv: Vec<Matrix3<f64>>,
    /// The last step's camera part, per free camera.
    pub step_c: Vec<SVector<f64, C>>,
    /// The last step's point part, per point.
    pub step_p: Vec<Vector3<f64>>,
}

/// `data` cut into the consecutive ranges `offsets[j]..offsets[j + 1]`, one per point.
pub(crate) fn split_by_point<'a, T>(mut data: &'a mut [T], offsets: &[usize]) -> Vec<&'a mut [T]> {
    offsets
        .windows(2)
        .map(|w| {
            let (head, tail) = std::mem::take(&mut data).split_at_mut(w[1] - w[0]);
            data = tail;
            head
        })
        .collect()
}

/// One observation's share of its point's blocks: robust-corrects, in place, the residual `r`
/// and the camera Jacobian `jc` (the caller's storage for them) and the point Jacobian `jp`,
/// adds J_pᵀJ_p to `v` and J_pᵀr to `gp`, and returns Wᵀ = J_pᵀJ_c. Writing in place spares
/// the copies of returning the corrected blocks by value (measurable on the mapping thread's
/// windows).
#[inline]
pub(crate) fn add_observation<const R: usize, const C: usize>(
    loss: &Loss,
    r: &mut SVector<f64, R>,
    jc: &mut SMatrix<f64, R, C>,
    mut jp: SMatrix<f64, R, 3>,
    v: &mut Matrix3<f64>,
    gp: &mut Vector3<f64>,
) -> SMatrix<f64, 3, C> {
    if let Some(corr) = loss.corrector(r.norm_squared()) {
        corr.correct_jacobian(r, jc);
        corr.correct_jacobian(r, &mut jp);
        corr.correct_residual(r);
    }
    let jpt = jp.transpose();
    *v += jpt * jp;
    *gp += jpt * *r;
    jpt * *jc
}

/// clamp(diag(m), lo, hi).
pub(crate) fn clamped_diagonal<const N: usize>(
    m: &SMatrix<f64, N, N>,
    lo: f64,
    hi: f64,
) -> SVector<f64, N> {
    SVector::<f64, N>::from_fn(|i, _| m[(i, i)].clamp(lo, hi))
}

impl<const C: usize> Schur<C> {
    /// The layout for observations sorted by point (`point_obs`, as offsets) whose cameras
    /// are `obs_free` (free-camera index or `None`), with `n_free` free cameras; analyses the
    /// reduced system's pattern once. `what` names the solver in errors.
    pub fn new(
        point_obs: Vec<usize>,
        obs_free: Vec<Option<usize>>,
        n_free: usize,
        solver: LinearSolver,
        threads: usize,
        what: &'static str,
    ) -> Result<Self> {
        let n_pt = point_obs.len().saturating_sub(1);
        let n_obs = obs_free.len();
        let mut camera_obs = vec![Vec::new(); n_free];
        for (s, f) in obs_free.iter().enumerate() {
            if let Some(f) = *f {
                camera_obs[f].push(s);
            }
        }
        let free_of = |j: usize| obs_free[point_obs[j]..point_obs[j + 1]].iter().flatten();
        let mut pairs = Vec::new();
        for j in 0..n_pt {
            for (a, &ca) in free_of(j).enumerate() {
                pairs.extend(
                    free_of(j)
                        .skip(a + 1)
                        .filter(|&&cb| cb != ca)
                        .map(|&cb| (ca, cb)),
                );
            }
        }
        let pattern = BlockPattern::new(n_free, C, pairs);
        let mut pair_slots = Vec::new();
        let mut pair_start = Vec::with_capacity(n_pt + 1);
        for j in 0..n_pt {
            pair_start.push(pair_slots.len());
            for (a, &ca) in free_of(j).enumerate() {
                for &cb in free_of(j).skip(a) {
                    let slot = pattern
                        .slot(ca.min(cb), ca.max(cb))
                        .ok_or_else(|| Error::numerical(what, "covisibility pattern incomplete"))?;
                    pair_slots.push((slot, ca > cb));
                }
            }
        }
        pair_start.push(pair_slots.len());
        let cholesky = BlockCholesky::new(&pattern, solver, threads)?;
        Ok(Self {
            point_obs,
            obs_free,
            camera_obs,
            pair_slots,
            pair_start,
            pattern,
            cholesky,
            u: vec![SMatrix::zeros(); n_free],
            gc: vec![SVector::zeros(); n_free],
            v: vec![Matrix3::zeros(); n_pt],
            gp: vec![Vector3::zeros(); n_pt],
            wt: vec![SMatrix::zeros(); n_obs],
            v_inv: vec![Matrix3::zeros(); n_pt],
            step_c: vec![SVector::zeros(); n_free],
            step_p: vec![Vector3::zeros(); n_pt],
        })
    }

    /// Whether the reduced camera system is factorised densely.
    pub fn is_dense(&self) -> bool {
        self.cholesky.is_dense()
    }

    /// U and g_c of every free camera from the per-observation camera Jacobians `jc` and
    /// residuals `residual` (robust correction already applied; rows of zeros for
    /// observations that contribute nothing). Returns max |g| over cameras and points.
    pub fn accumulate_cameras<const R: usize>(
        &mut self,
        jc: &[SMatrix<f64, R, C>],
        residual: &[SVector<f64, R>],
    ) -> f64 {
        self.u
            .par_iter_mut()
            .zip(self.gc.par_iter_mut())
            .zip(self.camera_obs.par_iter())
            .for_each(|((u, g), list)| {
                *u = SMatrix::zeros();
                *g = SVector::zeros();
                for &s in list {
                    u.gemm_tr(1.0, &jc[s], &jc[s], 1.0);
                    g.gemv_tr(1.0, &jc[s], &residual[s], 1.0);
                }
            });
        let gmax_c = self.gc.iter().map(|g| g.amax()).fold(0.0, f64::max);
        let gmax_p = self.gp.iter().map(|g| g.amax()).fold(0.0, f64::max);
        gmax_c.max(gmax_p)
    }

    /// The damped step for `mu` (into [`Schur::step_c`], [`Schur::step_p`]) and its model
    /// decrease; `None` when a damped block or the reduced system is not positive definite
    /// or the step is not finite.
    pub fn step(&mut self, mu: f64, lo: f64, hi: f64) -> Option<Step> {
        let n_free = self.u.len();
        let dim = self.pattern.dim();
        let ok = self
            .v_inv
            .par_iter_mut()
            .zip(self.v.par_iter())
            .with_min_len(256)
            .all(|(vi, v)| {
                let d = clamped_diagonal(v, lo, hi);
                // V* = V + μD is positive definite for μ > 0 (V is a sum of JᵀJ, D ≥ lo > 0):
                // the closed-form 3×3 inverse suffices; a singular or non-finite one refuses
                // the step.
                match (v + Matrix3::from_diagonal(&(d * mu))).try_inverse() {
                    Some(inv) if inv.iter().all(|x| x.is_finite()) => {
                        *vi = inv;
                        true
                    }
                    _ => false,
                }
            });
        if !ok {
            return None;
        }
        let cc = C * C;
        let n_values = self.pattern.stored_blocks() * cc;
        let (point_obs, obs_free, wt, gp, v_inv) = (
            &self.point_obs,
            &self.obs_free,
            &self.wt,
            &self.gp,
            &self.v_inv,
        );
        let (pair_slots, pair_start) = (&self.pair_slots, &self.pair_start);
        // −Σ W V*⁻¹ Wᵀ into the blocks and Σ W V*⁻¹ g_p into the right-hand side, accumulated
        // per worker and summed.
        let (mut values, mut rhs) = (0..self.v.len())
            .into_par_iter()
            .with_min_len(128)
            .fold(
                || (vec![0.0; n_values], vec![0.0; dim]),
                |(mut values, mut rhs), j| {
                    let vi = &v_inv[j];
                    let range = point_obs[j]..point_obs[j + 1];
                    let mut slot = pair_start[j];
                    for a in range.clone() {
                        let Some(ca) = obs_free[a] else { continue };
                        // (W_a V*⁻¹)ᵀ = V*⁻¹ W_aᵀ, 3×C.
                        let vwt = vi * wt[a];
                        let mut r = MatrixViewMut::<f64, Const<C>, Const<1>>::from_slice(
                            &mut rhs[ca * C..ca * C + C],
                        );
                        r.gemv_tr(1.0, &vwt, &gp[j], 1.0);
                        for b in a..range.end {
                            let Some(cb) = obs_free[b] else { continue };
                            let (s, transposed) = pair_slots[slot];
                            slot += 1;
                            // Block (ca, cb) −= W_a V*⁻¹ W_bᵀ, written in place (or its
                            // transpose into (cb, ca)).
                            let mut dst = MatrixViewMut::<f64, Const<C>, Const<C>>::from_slice(
                                &mut values[s * cc..s * cc + cc],
                            );
                            if transposed {
                                dst.gemm_tr(-1.0, &wt[b], &vwt, 1.0);
                            } else {
                                dst.gemm_tr(-1.0, &vwt, &wt[b], 1.0);
                            }
                            // Two observations of one point by one camera meet on a diagonal
                            // block through both orders; add the other half here.
                            if b != a && ca == cb {
                                if transposed {
                                    dst.gemm_tr(-1.0, &vwt, &wt[b], 1.0);
                                } else {
                                    dst.gemm_tr(-1.0, &wt[b], &vwt, 1.0);
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
            let ud = self.u[i] + SMatrix::<f64, C, C>::from_diagonal(&(d * mu));
            let s = self.pattern.diagonal_slot(i);
            values[s * cc..s * cc + cc]
                .iter_mut()
                .zip(ud.iter())
                .for_each(|(x, y)| *x += y);
            rhs[i * C..i * C + C]
                .iter_mut()
                .zip(self.gc[i].iter())
                .for_each(|(x, y)| *x -= y);
            camera_diag.push(d);
        }
        if n_free > 0 && !self.cholesky.solve(&self.pattern, &values, &mut rhs) {
            return None;
        }
        if rhs.iter().any(|x| !x.is_finite()) {
            return None;
        }
        for (i, s) in self.step_c.iter_mut().enumerate() {
            *s = SVector::<f64, C>::from_column_slice(&rhs[i * C..i * C + C]);
        }
        let (step_c, v) = (&self.step_c, &self.v);
        // Back-substitution δp = −V*⁻¹ (g_p + Σ Wᵀ δc) and the model-decrease terms.
        let (mut neg_g_dot, mut d_dot, mut norm2) = self
            .step_p
            .par_iter_mut()
            .enumerate()
            .with_min_len(256)
            .map(|(j, dp)| {
                let mut b = gp[j];
                for s in point_obs[j]..point_obs[j + 1] {
                    if let Some(c) = obs_free[s] {
                        b.gemv(1.0, &wt[s], &step_c[c], 1.0);
                    }
                }
                *dp = -(v_inv[j] * b);
                let d = clamped_diagonal(&v[j], lo, hi);
                (
                    -gp[j].dot(dp),
                    dp.component_mul(dp).dot(&d),
                    dp.norm_squared(),
                )
            })
            .reduce(|| (0.0, 0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
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
}
