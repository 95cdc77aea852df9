//! Least-squares solves: BAL bundle adjustment and g2o pose graphs from files, and bundle
//! adjustment of arrays. The GIL is released for the whole solve; the thread count is that of
//! a pool local to the solve.

use dhptam_core::io::{BalObservation, BalProblem, PoseGraph};
use dhptam_core::solver::pose_graph::{solve_pose_graph2, solve_pose_graph3};
use dhptam_core::solver::{
    solve_bal, BundleOptions, LinearSolver, LmOptions, LmReport, Loss, PnpRansacOptions,
    PoseGraphOptions, StereoIntrinsics,
};
use nalgebra::{Vector2, Vector3};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::arrays;
use crate::errors::DetachGuarded;
use crate::errors::{input_error, IntoPyResult};

fn report_dict<'py>(
    py: Python<'py>,
    report: &LmReport,
    threads: usize,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("initial_cost", report.initial_cost)?;
    d.set_item("final_cost", report.final_cost)?;
    d.set_item("iterations", report.iterations)?;
    d.set_item("successful_steps", report.successful_steps)?;
    d.set_item("seconds", report.seconds)?;
    d.set_item("threads", threads)?;
    d.set_item("termination", report.termination.name())?;
    d.set_item("history", report.history.clone())?;
    Ok(d)
}

fn parse_loss(name: &str, scale: f64) -> PyResult<Loss> {
    match name {
        "trivial" => Ok(Loss::Trivial),
        "huber" => Ok(Loss::Huber(scale)),
        "cauchy" => Ok(Loss::Cauchy(scale)),
        "tukey" => Ok(Loss::Tukey(scale)),
        other => Err(input_error(
            "loss",
            "one of trivial, huber, cauchy, tukey",
            other,
        )),
    }
}

fn parse_linear_solver(name: &str) -> PyResult<LinearSolver> {
    match name {
        "auto" => Ok(LinearSolver::Auto),
        "dense" => Ok(LinearSolver::Dense),
        "sparse" => Ok(LinearSolver::Sparse),
        other => Err(input_error(
            "linear_solver",
            "one of auto, dense, sparse",
            other,
        )),
    }
}

fn resolve_threads(threads: usize) -> usize {
    if threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        threads
    }
}

/// Bundle adjustment of a BAL file; writes the optimised problem to `out` when given.
#[pyfunction]
#[pyo3(signature = (path, *, threads=1, linear_solver="auto", loss="trivial", loss_scale=1.0,
    zero_behind_camera=false, max_iterations=50, out=None))]
#[allow(clippy::too_many_arguments)]
pub fn _solve_bal_file<'py>(
    py: Python<'py>,
    path: std::path::PathBuf,
    threads: usize,
    linear_solver: &str,
    loss: &str,
    loss_scale: f64,
    zero_behind_camera: bool,
    max_iterations: usize,
    out: Option<std::path::PathBuf>,
) -> PyResult<Bound<'py, PyDict>> {
    let threads = resolve_threads(threads);
    let options = BundleOptions {
        loss: parse_loss(loss, loss_scale)?,
        linear_solver: parse_linear_solver(linear_solver)?,
        threads,
        zero_behind_camera,
        lm: LmOptions {
            max_iterations,
            ..Default::default()
        },
        ..Default::default()
    };
    let report = py
        .detach_guarded(
            "solver::_solve_bal_file",
            || -> dhptam_core::Result<LmReport> {
                let mut problem = BalProblem::read(&path)?;
                let report = solve_bal(&mut problem, &options)?;
                if let Some(out) = &out {
                    problem.write(out)?;
                }
                Ok(report)
            },
        )?
        .py()?;
    report_dict(py, &report, threads)
}

/// Optimises a g2o pose graph (SE3 or SE2); writes the optimised graph to `out` when given.
#[pyfunction]
#[pyo3(signature = (path, *, threads=1, max_iterations=50, out=None))]
pub fn _solve_pose_graph_file<'py>(
    py: Python<'py>,
    path: std::path::PathBuf,
    threads: usize,
    max_iterations: usize,
    out: Option<std::path::PathBuf>,
) -> PyResult<Bound<'py, PyDict>> {
    let threads = resolve_threads(threads);
    let defaults = PoseGraphOptions::default();
    let options = PoseGraphOptions {
        threads,
        lm: LmOptions {
            max_iterations,
            ..defaults.lm.clone()
        },
        ..defaults
    };
    let (report, kind, vertices, edges) = py
        .detach_guarded(
            "solver::_solve_pose_graph_file",
            || -> dhptam_core::Result<(LmReport, &'static str, usize, usize)> {
                let mut graph = PoseGraph::read(&path)?;
                let (report, kind, v, e) = match &mut graph {
                    PoseGraph::Se3(g) => (
                        solve_pose_graph3(g, &options)?,
                        "se3",
                        g.poses.len(),
                        g.edges.len(),
                    ),
                    PoseGraph::Se2(g) => (
                        solve_pose_graph2(g, &options)?,
                        "se2",
                        g.poses.len(),
                        g.edges.len(),
                    ),
                };
                if let Some(out) = &out {
                    graph.write(out)?;
                }
                Ok((report, kind, v, e))
            },
        )?
        .py()?;
    let d = report_dict(py, &report, threads)?;
    d.set_item("kind", kind)?;
    d.set_item("vertices", vertices)?;
    d.set_item("edges", edges)?;
    Ok(d)
}

/// Bundle adjustment of arrays: BAL cameras (N, 9), points (M, 3), observations as camera
/// and point indices (K,) and pixels (K, 2). Returns (cameras, points, report).
#[pyfunction]
#[pyo3(signature = (cameras, points, camera_index, point_index, pixels, *, threads=1,
    linear_solver="auto", loss="trivial", loss_scale=1.0, fixed_cameras=Vec::new(), max_iterations=50))]
#[allow(clippy::too_many_arguments)]
pub fn _bundle_adjust<'py>(
    py: Python<'py>,
    cameras: &Bound<'py, PyAny>,
    points: &Bound<'py, PyAny>,
    camera_index: PyReadonlyArray1<'py, i64>,
    point_index: PyReadonlyArray1<'py, i64>,
    pixels: &Bound<'py, PyAny>,
    threads: usize,
    linear_solver: &str,
    loss: &str,
    loss_scale: f64,
    fixed_cameras: Vec<usize>,
    max_iterations: usize,
) -> PyResult<(
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyDict>,
)> {
    let cameras = arrays::rows(cameras, 9, "cameras")?;
    let points = arrays::rows(points, 3, "points")?;
    let pixels = arrays::rows(pixels, 2, "pixels")?;
    let ci = camera_index.as_slice()?;
    let pi = point_index.as_slice()?;
    let k = pixels.shape()[0];
    if ci.len() != k || pi.len() != k {
        return Err(input_error(
            "camera_index, point_index",
            &format!("{k} entries each, one per pixel row"),
            format!("{} and {}", ci.len(), pi.len()),
        ));
    }
    let to_index = |v: i64, what: &str| {
        usize::try_from(v).map_err(|_| input_error(what, "non-negative indices", v))
    };
    let px = pixels.as_slice()?;
    let mut observations = Vec::with_capacity(k);
    for i in 0..k {
        observations.push(BalObservation {
            camera: to_index(ci[i], "camera_index")?,
            point: to_index(pi[i], "point_index")?,
            pixel: [px[2 * i], px[2 * i + 1]],
        });
    }
    let mut problem = BalProblem {
        cameras: cameras
            .as_slice()?
            .chunks_exact(9)
            .map(|c| std::array::from_fn(|i| c[i]))
            .collect(),
        points: points
            .as_slice()?
            .chunks_exact(3)
            .map(|p| [p[0], p[1], p[2]])
            .collect(),
        observations,
    };
    let threads = resolve_threads(threads);
    let options = BundleOptions {
        loss: parse_loss(loss, loss_scale)?,
        linear_solver: parse_linear_solver(linear_solver)?,
        threads,
        fixed_cameras,
        lm: LmOptions {
            max_iterations,
            ..Default::default()
        },
        ..Default::default()
    };
    let report = py
        .detach_guarded("solver::_bundle_adjust", || {
            solve_bal(&mut problem, &options)
        })?
        .py()?;
    let n = problem.cameras.len();
    let m = problem.points.len();
    let cams = Array2::from_shape_fn((n, 9), |(i, c)| problem.cameras[i][c]).into_pyarray(py);
    let pts = Array2::from_shape_fn((m, 3), |(j, c)| problem.points[j][c]).into_pyarray(py);
    Ok((cams, pts, report_dict(py, &report, threads)?))
}

/// RANSAC PnP (P3P + refinement) of a pinhole camera: world points (N, 3) and their pixels
/// (N, 2). Returns (cam_from_world (4, 4), inliers (N,) bool, iterations), or None when no
/// model reaches `min_inliers`.
#[pyfunction]
#[pyo3(signature = (points_world, pixels, fx, fy, cx, cy, *, threshold_px=2.0, confidence=0.999,
    max_iterations=1000, min_inliers=10, seed=0))]
#[allow(clippy::too_many_arguments)]
#[allow(clippy::type_complexity)]
pub fn solve_pnp_ransac<'py>(
    py: Python<'py>,
    points_world: &Bound<'py, PyAny>,
    pixels: &Bound<'py, PyAny>,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    threshold_px: f64,
    confidence: f64,
    max_iterations: usize,
    min_inliers: usize,
    seed: u64,
) -> PyResult<Option<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<bool>>, usize)>> {
    let points = arrays::rows(points_world, 3, "points_world")?;
    let px = arrays::rows(pixels, 2, "pixels")?;
    let points: Vec<Vector3<f64>> = points
        .as_slice()?
        .chunks_exact(3)
        .map(|p| Vector3::new(p[0], p[1], p[2]))
        .collect();
    let px: Vec<Vector2<f64>> = px
        .as_slice()?
        .chunks_exact(2)
        .map(|p| Vector2::new(p[0], p[1]))
        .collect();
    let k = StereoIntrinsics {
        fx,
        fy,
        cx,
        cy,
        baseline: 0.0,
    };
    let options = PnpRansacOptions {
        threshold_px,
        confidence,
        max_iterations,
        min_inliers,
        seed,
    };
    let result = py
        .detach_guarded("solver::solve_pnp_ransac", || {
            dhptam_core::solver::solve_pnp_ransac(&k, &points, &px, &options)
        })?
        .py()?;
    Ok(result.map(|r| {
        let m = r.cam_from_world.matrix();
        let pose = Array2::from_shape_fn((4, 4), |(i, j)| m[(i, j)]).into_pyarray(py);
        let inliers = numpy::ndarray::Array1::from_vec(r.inliers).into_pyarray(py);
        (pose, inliers, r.iterations)
    }))
}
