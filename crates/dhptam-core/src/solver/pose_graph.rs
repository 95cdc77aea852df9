//! Pose-graph optimisation on SE(3) and SE(2) with full information matrices.
//!
//! An edge (i, j) with measurement Z = i_from_j and information Ω contributes ½ eᵀΩe with
//!
//! ```text
//! SE(3):  e = Log(Z⁻¹ T_i⁻¹ T_j) ∈ [ρ, φ],  T ← T exp(δ):
//!         ∂e/∂δ_j = J_r⁻¹(e),   ∂e/∂δ_i = −J_r⁻¹(e) Ad(T_j⁻¹ T_i)
//! SE(2):  E = Z⁻¹ T_i⁻¹ T_j,  e = (E_x, E_y, wrap(E_θ)),  (x, y, θ) ← (x, y, θ) + δ:
//!         e_xy = R_zᵀ (R_iᵀ (t_j − t_i) − t_z),  e_θ = θ_j − θ_i − θ_z
//! ```
//!
//! which are GTSAM's `BetweenFactor` errors for `Pose3` (exponential chart) and `Pose2`, so the
//! reported costs compare with it. The error is whitened by Ω = L Lᵀ (e ↦ Lᵀe). The gauge is
//! fixed by holding vertices constant: the file's `FIX` vertices, or else the first one. The
//! normal equations are block-sparse (one block per vertex, one per edge) and factorised by
//! sparse Cholesky whose symbolic analysis is done once per solve.

use nalgebra::{Matrix2, SMatrix, SVector, Vector2, Vector3, Vector6};
use rayon::prelude::*;

use super::linear::{BlockCholesky, BlockPattern, LinearSolver};
use super::lm::{self, LeastSquares, LmOptions, LmReport, Step};
use super::robust::Loss;
use crate::error::{Error, Result};
use crate::geometry::Se3;
use crate::io::g2o::{Pose2, PoseGraph2, PoseGraph3};

/// Options of the pose-graph solvers.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseGraphOptions {
    /// Loss on each edge's whitened squared error (loop closures may be wrong).
    pub loss: Loss,
    /// How the normal equations are factorised.
    pub linear_solver: LinearSolver,
    /// Worker threads (0: one per available core).
    pub threads: usize,
    /// The LM loop's options.
    pub lm: LmOptions,
}

impl Default for PoseGraphOptions {
    fn default() -> Self {
        Self {
            loss: Loss::Trivial,
            linear_solver: LinearSolver::Sparse,
            threads: 1,
            // A nearly Gauss–Newton start (damping 1e-10 of the diagonal), like GTSAM's
            // λ₀ = 1e-5: pose graphs have weak global bending modes that a heavier initial
            // damping takes several extra iterations to release.
            lm: LmOptions {
                initial_trust_radius: 1e10,
                ..LmOptions::default()
            },
        }
    }
}

/// A pose type a graph can hold, with D degrees of freedom.
pub trait GraphPose<const D: usize>: Copy + Send + Sync {
    /// The pose moved by a tangent increment, as the solver updates it.
    fn plus(&self, delta: &SVector<f64, D>) -> Self;
    /// The edge error e(T_i, T_j; Z).
    fn between_error(ti: &Self, tj: &Self, z: &Self) -> SVector<f64, D>;
    /// The edge error with its Jacobians with respect to δ_i and δ_j.
    fn between_error_jacobians(
        ti: &Self,
        tj: &Self,
        z: &Self,
    ) -> (SVector<f64, D>, SMatrix<f64, D, D>, SMatrix<f64, D, D>);
    /// Squared norm of the pose's coordinates (for the step tolerance).
    fn norm_squared(&self) -> f64;
}

impl GraphPose<6> for Se3 {
    fn plus(&self, delta: &Vector6<f64>) -> Self {
        *self * Se3::exp(delta)
    }

    fn between_error(ti: &Self, tj: &Self, z: &Self) -> Vector6<f64> {
        (z.inverse() * ti.inverse() * *tj).log()
    }

    fn between_error_jacobians(
        ti: &Self,
        tj: &Self,
        z: &Self,
    ) -> (Vector6<f64>, SMatrix<f64, 6, 6>, SMatrix<f64, 6, 6>) {
        let e = Self::between_error(ti, tj, z);
        let jr_inv = Se3::right_jacobian_inverse(&e);
        let ji = -jr_inv * (tj.inverse() * *ti).adjoint();
        (e, ji, jr_inv)
    }

    fn norm_squared(&self) -> f64 {
        self.translation.norm_squared() + self.rotation.log().norm_squared()
    }
}

/// Wraps an angle to (−π, π].
fn wrap_angle(a: f64) -> f64 {
    let w = a.sin().atan2(a.cos());
    if w <= -std::f64::consts::PI {
        w + 2.0 * std::f64::consts::PI
    } else {
        w
    }
}

/// V(θ)⁻¹ of the SE(2) exponential, t = V(θ) v: with a = sin θ/θ and b = (1 − cos θ)/θ,
/// V = [[a, −b], [b, a]] and V⁻¹ = [[a, b], [−b, a]] / (a² + b²); series near θ = 0.
fn se2_v_inverse(theta: f64) -> Matrix2<f64> {
    let (a, b) = if theta.abs() < 1e-6 {
        let t2 = theta * theta;
        (1.0 - t2 / 6.0, theta / 2.0 - theta * t2 / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / theta)
    };
    Matrix2::new(a, b, -b, a) / (a * a + b * b)
}

/// Log of the SE(2) pose (t, θ): (V(θ)⁻¹ t, θ), with its 3×3 Jacobian with respect to (t, θ)
/// (the θ column of V⁻¹ t by a central difference; V⁻¹ is smooth on (−2π, 2π)).
fn se2_log_with_jacobian(t: &Vector2<f64>, theta: f64) -> (Vector3<f64>, SMatrix<f64, 3, 3>) {
    let vinv = se2_v_inverse(theta);
    let v = vinv * t;
    let h = 1e-6;
    let dv = (se2_v_inverse(theta + h) * t - se2_v_inverse(theta - h) * t) / (2.0 * h);
    let mut j = SMatrix::<f64, 3, 3>::zeros();
    j.fixed_view_mut::<2, 2>(0, 0).copy_from(&vinv);
    j[(0, 2)] = dv.x;
    j[(1, 2)] = dv.y;
    j[(2, 2)] = 1.0;
    (Vector3::new(v.x, v.y, theta), j)
}

fn rot2(theta: f64) -> Matrix2<f64> {
    let (s, c) = theta.sin_cos();
    Matrix2::new(c, -s, s, c)
}

impl GraphPose<3> for Pose2 {
    fn plus(&self, d: &Vector3<f64>) -> Self {
        Pose2 {
            x: self.x + d.x,
            y: self.y + d.y,
            theta: wrap_angle(self.theta + d.z),
        }
    }

    fn between_error(ti: &Self, tj: &Self, z: &Self) -> Vector3<f64> {
        Self::between_error_jacobians(ti, tj, z).0
    }

    fn between_error_jacobians(
        ti: &Self,
        tj: &Self,
        z: &Self,
    ) -> (Vector3<f64>, SMatrix<f64, 3, 3>, SMatrix<f64, 3, 3>) {
        let rzt = rot2(z.theta).transpose();
        let rit = rot2(ti.theta).transpose();
        let dt = Vector2::new(tj.x - ti.x, tj.y - ti.y);
        // The error pose E = z⁻¹·(Tᵢ⁻¹Tⱼ) as (t, θ), then its logarithm (V(θ)⁻¹ t, θ), as GTSAM's
        // Pose2 BetweenFactor; the Jacobians below are those of (t, θ), chained through the
        // logarithm's at the end.
        let exy = rzt * (rit * dt - Vector2::new(z.x, z.y));
        let theta = wrap_angle(tj.theta - ti.theta - z.theta);
        // ∂R(θ)ᵀ/∂θ = [[−s, c], [−c, −s]].
        let (s, c) = ti.theta.sin_cos();
        let drit = Matrix2::new(-s, c, -c, -s);
        let a = rzt * rit;
        let mut ji = SMatrix::<f64, 3, 3>::zeros();
        let mut jj = SMatrix::<f64, 3, 3>::zeros();
        ji.fixed_view_mut::<2, 2>(0, 0).copy_from(&(-a));
        ji.fixed_view_mut::<2, 1>(0, 2)
            .copy_from(&(rzt * drit * dt));
        ji[(2, 2)] = -1.0;
        jj.fixed_view_mut::<2, 2>(0, 0).copy_from(&a);
        jj[(2, 2)] = 1.0;
        let (log, dlog) = se2_log_with_jacobian(&exy, theta);
        (log, dlog * ji, dlog * jj)
    }

    fn norm_squared(&self) -> f64 {
        self.x * self.x + self.y * self.y + self.theta * self.theta
    }
}

struct Edge<P, const D: usize> {
    from: usize,
    to: usize,
    measurement: P,
    /// Lᵀ with Ω = L Lᵀ.
    whitener: SMatrix<f64, D, D>,
}

/// Levenberg–Marquardt on a graph of poses `P` with D degrees of freedom.
pub struct PoseGraphSolver<P: GraphPose<D>, const D: usize> {
    loss: Loss,
    lm: LmOptions,
    threads: usize,
    pool: Option<rayon::ThreadPool>,
    poses: Vec<P>,
    candidate: Vec<P>,
    edges: Vec<Edge<P, D>>,
    free_index: Vec<Option<usize>>,
    edge_slot: Vec<Option<usize>>,
    pattern: BlockPattern,
    cholesky: BlockCholesky,
    // Linearisation: whitened, loss-corrected error and Jacobians per edge.
    lin: Vec<(SVector<f64, D>, SMatrix<f64, D, D>, SMatrix<f64, D, D>)>,
    hessian: Vec<f64>,
    gradient: Vec<f64>,
    step: Vec<f64>,
}

/// The SE(3) pose-graph solver.
pub type PoseGraphSe3 = PoseGraphSolver<Se3, 6>;
/// The SE(2) pose-graph solver.
pub type PoseGraphSe2 = PoseGraphSolver<Pose2, 3>;

impl<P: GraphPose<D>, const D: usize> PoseGraphSolver<P, D> {
    /// Prepares a solve: `edges` are (i, j, i_from_j, Ω); `fixed` vertices are held (the first
    /// vertex when empty).
    pub fn new(
        poses: &[P],
        edges: impl IntoIterator<Item = (usize, usize, P, SMatrix<f64, D, D>)>,
        fixed: &[usize],
        options: &PoseGraphOptions,
    ) -> Result<Self> {
        options.lm.check()?;
        let n = poses.len();
        if n == 0 {
            return Err(Error::invalid("poses", "at least one vertex", 0));
        }
        let mut is_fixed = vec![false; n];
        if fixed.is_empty() {
            is_fixed[0] = true;
        }
        for &f in fixed {
            if f >= n {
                return Err(Error::invalid("fixed", format!("indices below {n}"), f));
            }
            is_fixed[f] = true;
        }
        let mut free_index = vec![None; n];
        let mut n_free = 0;
        for (i, f) in is_fixed.iter().enumerate() {
            if !f {
                free_index[i] = Some(n_free);
                n_free += 1;
            }
        }
        let mut list = Vec::new();
        for (k, (from, to, measurement, information)) in edges.into_iter().enumerate() {
            if from >= n || to >= n || from == to {
                return Err(Error::invalid(
                    format!("edges[{k}]"),
                    format!("two different vertices below {n}"),
                    format!("({from}, {to})"),
                ));
            }
            let chol = information.cholesky().ok_or_else(|| {
                Error::invalid(
                    format!("edges[{k}].information"),
                    "a symmetric positive-definite matrix",
                    "a matrix without Cholesky factor",
                )
            })?;
            list.push(Edge {
                from,
                to,
                measurement,
                whitener: chol.l().transpose(),
            });
        }
        let pairs: Vec<(usize, usize)> = list
            .iter()
            .filter_map(|e| Some((free_index[e.from]?, free_index[e.to]?)))
            .collect();
        let pattern = BlockPattern::new(n_free, D, pairs);
        let edge_slot = list
            .iter()
            .map(|e| {
                let (a, b) = (free_index[e.from]?, free_index[e.to]?);
                pattern.slot(a.min(b), a.max(b))
            })
            .collect();
        let threads = if options.threads == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        } else {
            options.threads
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| Error::numerical("thread pool", e.to_string()))?;
        let cholesky =
            pool.install(|| BlockCholesky::new(&pattern, options.linear_solver, threads))?;
        let n_edges = list.len();
        Ok(Self {
            loss: options.loss,
            lm: options.lm.clone(),
            threads,
            pool: Some(pool),
            poses: poses.to_vec(),
            candidate: poses.to_vec(),
            edges: list,
            free_index,
            edge_slot,
            hessian: pattern.zeros(),
            gradient: vec![0.0; pattern.dim()],
            step: vec![0.0; pattern.dim()],
            pattern,
            cholesky,
            lin: vec![(SVector::zeros(), SMatrix::zeros(), SMatrix::zeros()); n_edges],
        })
    }

    /// Worker threads in use.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Runs Levenberg–Marquardt from the current estimate.
    pub fn solve(&mut self) -> Result<LmReport> {
        let options = self.lm.clone();
        let pool = self
            .pool
            .take()
            .ok_or_else(|| Error::numerical("pose graph", "solver re-entered"))?;
        let report = pool.install(|| lm::solve(self, &options));
        self.pool = Some(pool);
        report
    }

    /// The current estimate.
    pub fn poses(&self) -> &[P] {
        &self.poses
    }

    fn total_cost(&self, poses: &[P]) -> f64 {
        let loss = self.loss;
        0.5 * self
            .edges
            .par_iter()
            .map(|e| {
                let r = e.whitener * P::between_error(&poses[e.from], &poses[e.to], &e.measurement);
                loss.evaluate(r.norm_squared())[0]
            })
            .sum::<f64>()
    }
}

fn add_block<const D: usize>(dst: &mut [f64], m: &SMatrix<f64, D, D>) {
    for (x, y) in dst.iter_mut().zip(m.iter()) {
        *x += y;
    }
}

impl<P: GraphPose<D>, const D: usize> LeastSquares for PoseGraphSolver<P, D> {
    fn cost(&mut self) -> f64 {
        self.total_cost(&self.poses)
    }

    fn linearize(&mut self) -> f64 {
        let (poses, loss) = (&self.poses, self.loss);
        self.lin
            .par_iter_mut()
            .zip(self.edges.par_iter())
            .for_each(|(lin, e)| {
                let (r, ji, jj) =
                    P::between_error_jacobians(&poses[e.from], &poses[e.to], &e.measurement);
                let (mut r, mut ji, mut jj) = (e.whitener * r, e.whitener * ji, e.whitener * jj);
                if let Some(corr) = loss.corrector(r.norm_squared()) {
                    corr.correct_jacobian(&r, &mut ji);
                    corr.correct_jacobian(&r, &mut jj);
                    corr.correct_residual(&mut r);
                }
                *lin = (r, ji, jj);
            });
        self.hessian.iter_mut().for_each(|x| *x = 0.0);
        self.gradient.iter_mut().for_each(|x| *x = 0.0);
        let dd = D * D;
        for ((e, (r, ji, jj)), slot) in self.edges.iter().zip(&self.lin).zip(&self.edge_slot) {
            let (fi, fj) = (self.free_index[e.from], self.free_index[e.to]);
            if let Some(a) = fi {
                let s = self.pattern.diagonal_slot(a);
                add_block(
                    &mut self.hessian[s * dd..(s + 1) * dd],
                    &(ji.transpose() * ji),
                );
                let g = ji.transpose() * r;
                for (x, y) in self.gradient[a * D..(a + 1) * D].iter_mut().zip(g.iter()) {
                    *x += y;
                }
            }
            if let Some(b) = fj {
                let s = self.pattern.diagonal_slot(b);
                add_block(
                    &mut self.hessian[s * dd..(s + 1) * dd],
                    &(jj.transpose() * jj),
                );
                let g = jj.transpose() * r;
                for (x, y) in self.gradient[b * D..(b + 1) * D].iter_mut().zip(g.iter()) {
                    *x += y;
                }
            }
            if let (Some(a), Some(b), Some(s)) = (fi, fj, slot) {
                // Block (min, max): rows of the smaller free index.
                let block = if a < b {
                    ji.transpose() * jj
                } else {
                    jj.transpose() * ji
                };
                add_block(&mut self.hessian[s * dd..(s + 1) * dd], &block);
            }
        }
        self.gradient.iter().fold(0.0, |m, g| m.max(g.abs()))
    }

    fn compute_step(&mut self, mu: f64, lo: f64, hi: f64) -> Option<Step> {
        let dd = D * D;
        let mut values = self.hessian.clone();
        let n = self.pattern.block_count();
        let mut diag = vec![0.0; n * D];
        for i in 0..n {
            let s = self.pattern.diagonal_slot(i);
            for c in 0..D {
                let k = s * dd + c * D + c;
                let d = self.hessian[k].clamp(lo, hi);
                diag[i * D + c] = d;
                values[k] += mu * d;
            }
        }
        for (x, g) in self.step.iter_mut().zip(&self.gradient) {
            *x = -g;
        }
        if !self.cholesky.solve(&self.pattern, &values, &mut self.step) {
            return None;
        }
        if self.step.iter().any(|x| !x.is_finite()) {
            return None;
        }
        let mut neg_g_dot = 0.0;
        let mut d_dot = 0.0;
        let mut norm2 = 0.0;
        for ((x, g), d) in self.step.iter().zip(&self.gradient).zip(&diag) {
            neg_g_dot -= g * x;
            d_dot += d * x * x;
            norm2 += x * x;
        }
        Some(Step {
            model_decrease: 0.5 * (neg_g_dot + mu * d_dot),
            norm: norm2.sqrt(),
        })
    }

    fn candidate_cost(&mut self) -> f64 {
        for (i, p) in self.poses.iter().enumerate() {
            self.candidate[i] = match self.free_index[i] {
                Some(f) => p.plus(&SVector::<f64, D>::from_column_slice(
                    &self.step[f * D..(f + 1) * D],
                )),
                None => *p,
            };
        }
        self.total_cost(&self.candidate)
    }

    fn accept(&mut self) {
        std::mem::swap(&mut self.poses, &mut self.candidate);
    }

    fn state_norm(&self) -> f64 {
        self.poses
            .iter()
            .map(|p| p.norm_squared())
            .sum::<f64>()
            .sqrt()
    }
}

/// Optimises a 3-D graph in place. The report's times include the setup (pattern analysis
/// and symbolic factorisation).
pub fn solve_pose_graph3(graph: &mut PoseGraph3, options: &PoseGraphOptions) -> Result<LmReport> {
    let edges = graph
        .edges
        .iter()
        .map(|e| (e.from, e.to, e.measurement, e.information));
    let start = std::time::Instant::now();
    let mut solver = PoseGraphSe3::new(&graph.poses, edges, &graph.fixed, options)?;
    let setup = start.elapsed().as_secs_f64();
    let mut report = solver.solve()?;
    report.include_setup(setup);
    graph.poses.copy_from_slice(solver.poses());
    Ok(report)
}

/// Optimises a planar graph in place. The report's times include the setup.
pub fn solve_pose_graph2(graph: &mut PoseGraph2, options: &PoseGraphOptions) -> Result<LmReport> {
    let edges = graph
        .edges
        .iter()
        .map(|e| (e.from, e.to, e.measurement, e.information));
    let start = std::time::Instant::now();
    let mut solver = PoseGraphSe2::new(&graph.poses, edges, &graph.fixed, options)?;
    let setup = start.elapsed().as_secs_f64();
    let mut report = solver.solve()?;
    report.include_setup(setup);
    graph.poses.copy_from_slice(solver.poses());
    Ok(report)
}
