"""Baseline solvers for benches/bench_solver.py: Ceres (through pycolmap) on BAL problems and
GTSAM's Levenberg–Marquardt on g2o pose graphs. Each returns the same figures as
``dhptam solve --json``: initial and final cost (½Σ‖r‖², ½Σ‖r‖²_Σ), iterations, seconds."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np


def read_bal(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(cameras N×9, points M×3, observation indices K×2 [camera, point], pixels K×2)."""
    with open(path) as f:
        n_cam, n_pt, n_obs = (int(v) for v in f.readline().split())
        obs = np.loadtxt(f, max_rows=n_obs)
        rest = np.array(f.read().split(), dtype=float)
    cams = rest[: 9 * n_cam].reshape(n_cam, 9)
    pts = rest[9 * n_cam : 9 * n_cam + 3 * n_pt].reshape(n_pt, 3)
    return cams, pts, obs[:, :2].astype(np.int64), obs[:, 2:4]


def _rotation_from_angle_axis(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3)
    k = w / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def ceres_bal(path: Path, linear_solver: str, threads: int) -> dict:
    """Bundle adjustment of a BAL file by Ceres through pycolmap.

    A BAL camera projects p = −P_xy/P_z with y up; COLMAP projects P_xy/P_z with y down.
    Turning each camera by 180° about its x axis (R' = F R, t' = F t, F = diag(1, −1, −1))
    and negating the measured y gives the same residuals, so the costs are identical.
    Cameras are RADIAL (f, cx, cy, k1, k2) with the principal point held at 0.
    """
    import pycolmap

    cams, pts, idx, pix = read_bal(path)
    flip = np.diag([1.0, -1.0, -1.0])
    rec = pycolmap.Reconstruction()
    extent = float(np.abs(pix).max()) + 1.0
    order = np.argsort(idx[:, 0], kind="stable")
    point2d_index = np.empty(len(idx), dtype=np.int64)
    for i, c in enumerate(cams):
        cam = pycolmap.Camera(
            camera_id=i + 1,
            model="RADIAL",
            width=int(2 * extent),
            height=int(2 * extent),
            params=[c[6], 0.0, 0.0, c[7], c[8]],
        )
        rec.add_camera_with_trivial_rig(cam)
    start = 0
    for i, c in enumerate(cams):
        rows = order[start : start + int((idx[:, 0] == i).sum())]
        start += len(rows)
        point2d_index[rows] = np.arange(len(rows))
        keypoints = np.column_stack([pix[rows, 0], -pix[rows, 1]])
        image = pycolmap.Image(name=f"{i}", keypoints=keypoints, camera_id=i + 1, image_id=i + 1)
        rot = flip @ _rotation_from_angle_axis(c[:3])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(rot), flip @ c[3:6])
        rec.add_image_with_trivial_frame(image, pose)
    tracks = [pycolmap.Track() for _ in range(len(pts))]
    for k, (i, j) in enumerate(idx):
        tracks[j].add_element(int(i) + 1, int(point2d_index[k]))
    for j, p in enumerate(pts):
        rec.add_point3D(p, tracks[j])
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.refine_principal_point = False
    ceres = options.ceres
    ceres.auto_select_solver_type = False
    ceres.min_num_residuals_for_cpu_multi_threading = 0
    so = ceres.solver_options
    so.linear_solver_type = getattr(type(so.linear_solver_type), linear_solver)
    so.num_threads = threads
    # Ceres' own defaults for the stopping rules (pycolmap switches the function tolerance off).
    so.function_tolerance = 1e-6
    so.gradient_tolerance = 1e-10
    so.parameter_tolerance = 1e-8
    so.max_num_iterations = 50
    config = pycolmap.BundleAdjustmentConfig()
    for i in range(len(cams)):
        config.add_image(i + 1)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.UNSPECIFIED)
    adjuster = pycolmap.create_default_bundle_adjuster(options, config, rec)
    t0 = time.perf_counter()
    summary = adjuster.solve()
    seconds = time.perf_counter() - t0
    s = summary.ceres_summary
    return {
        "initial_cost": s.initial_cost,
        "final_cost": s.final_cost,
        "iterations": s.num_successful_steps + s.num_unsuccessful_steps,
        "seconds": seconds,
        "solver_seconds": s.total_time_in_seconds,
        "threads": threads,
        "termination": str(s.termination_type),
    }


def gtsam_pose_graph(path: Path) -> dict:
    """GTSAM's Levenberg–Marquardt (default parameters) on a g2o graph.

    The gauge is held by a tight prior on the first pose at its initial value (GTSAM's own
    pose-graph examples do this); the prior's residual starts at zero and stays negligible.
    GTSAM's ``error`` is ½Σ‖r‖²_Σ, the definition dhptam reports.
    """
    import gtsam

    is_3d = "VERTEX_SE3" in Path(path).read_text()[:200]
    graph, initial = gtsam.readG2o(str(path), is_3d)
    first = min(initial.keys())
    if is_3d:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))
        graph.add(gtsam.PriorFactorPose3(first, initial.atPose3(first), noise))
    else:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6))
        graph.add(gtsam.PriorFactorPose2(first, initial.atPose2(first), noise))
    params = gtsam.LevenbergMarquardtParams()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    initial_cost = graph.error(initial)
    t0 = time.perf_counter()
    result = optimizer.optimize()
    seconds = time.perf_counter() - t0
    return {
        "initial_cost": initial_cost,
        "final_cost": graph.error(result),
        "iterations": optimizer.iterations(),
        "seconds": seconds,
        "termination": "gtsam",
    }
