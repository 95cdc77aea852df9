//! Bundle adjustment of BAL problems with the Schur complement.
//!
//! Unknowns: per camera c = [δφ, δt, δf, δk1, δk2] (rotation updated on the left,
//! R ← exp(δφ) R), per point δX. The points are eliminated with the Schur complement of
//! [`super::schur`], leaving the reduced camera system whose block pattern is the camera
//! covisibility graph; it is factorised densely for small windows and by sparse Cholesky
//! (symbolic analysis once per solve) for large ones. Residuals, Jacobians and the elimination
//! run in parallel with rayon on a local pool.

use nalgebra::{Matrix2x3, Matrix3, SMatrix, SVector, Vector2, Vector3};
use rayon::prelude::*;

use super::linear::LinearSolver;
use super::lm::{self, LeastSquares, LmOptions, LmReport, Step};
use super::robust::Loss;
use super::schur::{add_observation, split_by_point, Schur};
use crate::error::{Error, Result};
use crate::geometry::so3::hat;
use crate::geometry::So3;
use crate::io::BalProblem;

type M29 = SMatrix<f64, 2, 9>;
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
    /// Camera and pixel of each observation, sorted by point (`schur.point_obs`).
    obs_camera: Vec<usize>,
    obs_pixel: Vec<Vector2<f64>>,
    /// Each camera's index among the free ones (`None`: held fixed).
    free_index: Vec<Option<usize>>,
    /// The normal equations' blocks, the reduced-system layout and the last step.
    schur: Schur<9>,
    // Linearisation, per sorted observation.
    jc: Vec<M29>,
    residual: Vec<Vector2<f64>>,
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
        let obs_free = obs_camera.iter().map(|&c| free_index[c]).collect();
        let schur = pool.install(|| {
            Schur::new(
                point_obs,
                obs_free,
                n_free,
                options.linear_solver,
                threads,
                "bundle adjustment",
            )
        })?;
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
            obs_camera,
            obs_pixel,
            free_index,
            schur,
            jc: vec![M29::zeros(); n_obs],
            residual: vec![Vector2::zeros(); n_obs],
        })
    }

    /// Worker threads in use.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Whether the reduced camera system is factorised densely.
    pub fn uses_dense_solver(&self) -> bool {
        self.schur.is_dense()
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
                &self.schur.point_obs,
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

impl LeastSquares for BundleAdjustment {
    fn cost(&mut self) -> f64 {
        total_cost(
            &self.cameras,
            &self.points,
            &self.schur.point_obs,
            &self.obs_camera,
            &self.obs_pixel,
            &self.loss,
            self.zero_behind_camera,
        )
    }

    fn linearize(&mut self) -> f64 {
        let (cameras, points, loss) = (&self.cameras, &self.points, &self.loss);
        let (obs_camera, obs_pixel) = (&self.obs_camera, &self.obs_pixel);
        let zero_behind_camera = self.zero_behind_camera;
        let schur = &mut self.schur;
        let point_obs = &schur.point_obs;
        // Residuals and Jacobians per point (each point owns a contiguous range).
        split_by_point(&mut self.jc, point_obs)
            .into_par_iter()
            .zip(split_by_point(&mut self.residual, point_obs))
            .zip(split_by_point(&mut schur.wt, point_obs))
            .zip(schur.v.par_iter_mut())
            .zip(schur.gp.par_iter_mut())
            .enumerate()
            .with_min_len(64)
            .for_each(|(j, ((((jc, res), wt), v), gp))| {
                *v = Matrix3::zeros();
                *gp = Vector3::zeros();
                for (local, k) in (point_obs[j]..point_obs[j + 1]).enumerate() {
                    let cam = &cameras[obs_camera[k]];
                    if zero_behind_camera && !cam.sees(&points[j]) {
                        wt[local] = SMatrix::zeros();
                        jc[local] = M29::zeros();
                        res[local] = Vector2::zeros();
                        continue;
                    }
                    let (pix, a, b) = cam.project_with_jacobians(&points[j]);
                    res[local] = pix - obs_pixel[k];
                    jc[local] = a;
                    wt[local] = add_observation(loss, &mut res[local], &mut jc[local], b, v, gp);
                }
            });
        schur.accumulate_cameras(&self.jc, &self.residual)
    }

    fn compute_step(&mut self, mu: f64, lo: f64, hi: f64) -> Option<Step> {
        self.schur.step(mu, lo, hi)
    }

    fn candidate_cost(&mut self) -> f64 {
        for (i, cam) in self.cameras.iter().enumerate() {
            self.candidate_cameras[i] = match self.free_index[i] {
                Some(f) => cam.plus(&self.schur.step_c[f]),
                None => *cam,
            };
        }
        let step_p = &self.schur.step_p;
        self.candidate_points
            .par_iter_mut()
            .zip(self.points.par_iter())
            .enumerate()
            .for_each(|(j, (c, p))| *c = p + step_p[j]);
        total_cost(
            &self.candidate_cameras,
            &self.candidate_points,
            &self.schur.point_obs,
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
