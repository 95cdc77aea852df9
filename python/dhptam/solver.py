"""Nonlinear least squares: bundle adjustment (BAL problems), pose graphs (g2o files) and
RANSAC PnP.

The solves run in Rust with the GIL released, on a thread pool local to each call. Costs are
½Σρ(‖r‖²) — Ceres' definition for bundle adjustment, ½Σ‖r‖²_Σ (GTSAM's) for pose graphs.

Example: a two-vertex planar pose graph written, solved and written back::

    >>> import tempfile, pathlib
    >>> from dhptam.solver import solve_pose_graph
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "g.g2o").write_text(
    ...     "VERTEX_SE2 0 0 0 0\\nVERTEX_SE2 1 0.5 0.2 0.1\\n"
    ...     "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\\n")
    >>> report = solve_pose_graph(d / "g.g2o", out=d / "opt.g2o")
    >>> report.initial_cost > 0.1, report.final_cost < 1e-12
    (True, True)
    >>> [round(float(v), 6) for v in (d / "opt.g2o").read_text().splitlines()[1].split()[2:]]
    [1.0, 0.0, 0.0]
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core

LinearSolver = Literal["auto", "dense", "sparse"]
LossName = Literal["trivial", "huber", "cauchy", "tukey"]


@dataclass(frozen=True)
class SolveReport:
    """What one solve did.

    Attributes
    ----------
    initial_cost, final_cost:
        ½Σρ(‖r‖²) before and after.
    iterations:
        Levenberg–Marquardt iterations, taken and rejected steps together.
    successful_steps:
        Steps taken.
    seconds:
        Wall-clock time of the solve (reading and writing files excluded).
    threads:
        Worker threads used.
    termination:
        ``function_tolerance``, ``gradient_tolerance``, ``parameter_tolerance``,
        ``max_iterations``, ``no_decrease`` or ``interrupted``.
    history:
        (cost, seconds since the start) after each taken step, the initial cost first.
    extra:
        Solver-specific facts (for pose graphs: ``kind``, ``vertices``, ``edges``).
    """

    initial_cost: float
    final_cost: float
    iterations: int
    successful_steps: int
    seconds: float
    threads: int
    termination: str
    history: list[tuple[float, float]] = field(repr=False)
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def _from_dict(cls, d: dict[str, Any]) -> SolveReport:
        keys = {
            "initial_cost",
            "final_cost",
            "iterations",
            "successful_steps",
            "seconds",
            "threads",
            "termination",
            "history",
        }
        return cls(
            **{k: d[k] for k in keys},
            extra={k: v for k, v in d.items() if k not in keys},
        )

    def seconds_to_cost(self, target: float) -> float | None:
        """Seconds until the cost first reached ``target``; None if it never did."""
        return next((s for c, s in self.history if c <= target), None)

    def to_json_dict(self) -> dict[str, Any]:
        """The summary the ``dhptam solve --json`` command prints."""
        return {
            "initial_cost": self.initial_cost,
            "final_cost": self.final_cost,
            "iterations": self.iterations,
            "seconds": self.seconds,
            "threads": self.threads,
            "termination": self.termination,
            **self.extra,
        }


def solve_bal(
    path: str | os.PathLike[str],
    *,
    threads: int = 1,
    linear_solver: LinearSolver = "auto",
    loss: LossName = "trivial",
    loss_scale: float = 1.0,
    zero_behind_camera: bool = False,
    max_iterations: int = 50,
    out: str | os.PathLike[str] | None = None,
) -> SolveReport:
    """Bundle adjustment of a BAL file (``problem-*.txt``).

    ``threads=0`` uses every core. ``zero_behind_camera`` drops the residuals of points behind
    their camera, as COLMAP does (the plain BAL cost counts them). ``out`` receives the
    optimised problem in BAL format.
    """
    d = _core._solve_bal_file(
        Path(path),
        threads=threads,
        linear_solver=linear_solver,
        loss=loss,
        loss_scale=loss_scale,
        zero_behind_camera=zero_behind_camera,
        max_iterations=max_iterations,
        out=None if out is None else Path(out),
    )
    return SolveReport._from_dict(d)


def solve_pose_graph(
    path: str | os.PathLike[str],
    *,
    threads: int = 1,
    max_iterations: int = 50,
    out: str | os.PathLike[str] | None = None,
) -> SolveReport:
    """Optimises a g2o pose graph (SE3 or SE2); ``out`` receives the optimised graph.

    The gauge is fixed by the file's ``FIX`` vertices, or else by the first vertex.
    """
    d = _core._solve_pose_graph_file(
        Path(path),
        threads=threads,
        max_iterations=max_iterations,
        out=None if out is None else Path(out),
    )
    return SolveReport._from_dict(d)


def bundle_adjust(
    cameras: ArrayLike,
    points: ArrayLike,
    camera_index: ArrayLike,
    point_index: ArrayLike,
    pixels: ArrayLike,
    *,
    threads: int = 1,
    linear_solver: LinearSolver = "auto",
    loss: LossName = "trivial",
    loss_scale: float = 1.0,
    fixed_cameras: list[int] | None = None,
    max_iterations: int = 50,
) -> tuple[NDArray[np.float64], NDArray[np.float64], SolveReport]:
    """Bundle adjustment of BAL-model cameras (N, 9: angle-axis, t, f, k1, k2) and points
    (M, 3) from observations (camera index, point index, pixel). Returns the optimised
    cameras, points and the report; the inputs are not modified."""
    cams, pts, d = _core._bundle_adjust(
        cameras,
        points,
        np.ascontiguousarray(camera_index, dtype=np.int64),
        np.ascontiguousarray(point_index, dtype=np.int64),
        pixels,
        threads=threads,
        linear_solver=linear_solver,
        loss=loss,
        loss_scale=loss_scale,
        fixed_cameras=list(fixed_cameras or []),
        max_iterations=max_iterations,
    )
    return cams, pts, SolveReport._from_dict(d)


@dataclass(frozen=True)
class PnpResult:
    """A camera pose found by :func:`solve_pnp_ransac`.

    Attributes
    ----------
    cam_from_world:
        (4, 4) float64 transform mapping world points into the camera frame.
    inliers:
        (N,) bool: in front of the camera with a reprojection error ≤ ``threshold_px``.
    inlier_count:
        Number of inliers.
    iterations:
        RANSAC iterations run.
    """

    cam_from_world: NDArray[np.float64]
    inliers: NDArray[np.bool_]
    inlier_count: int
    iterations: int


def solve_pnp_ransac(
    points_world: ArrayLike,
    pixels: ArrayLike,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    *,
    threshold_px: float = 2.0,
    confidence: float = 0.999,
    max_iterations: int = 1000,
    min_inliers: int = 10,
    seed: int = 0,
) -> PnpResult | None:
    """RANSAC PnP of an undistorted pinhole camera: P3P samples drawn by a seeded generator,
    an adaptive iteration count for ``confidence``, then Levenberg–Marquardt refinement on the
    inliers and re-scoring.

    ``points_world`` (N, 3) in metres, ``pixels`` (N, 2) as (column, row). Returns ``None``
    when no pose has ``min_inliers`` inliers; raises :class:`dhptam.errors.InputError`
    for mismatched lengths, fewer than 4 correspondences or non-finite values.

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> cam = rng.uniform([-1, -1, 2], [1, 1, 6], (20, 3))   # identity pose: world = camera
    >>> px = cam[:, :2] / cam[:, 2:] * 400.0 + 320.0
    >>> r = solve_pnp_ransac(cam, px, 400.0, 400.0, 320.0, 320.0)
    >>> r.inlier_count, bool(np.allclose(r.cam_from_world, np.eye(4), atol=1e-9))
    (20, True)
    """
    out = _core.solve_pnp_ransac(
        points_world,
        pixels,
        fx,
        fy,
        cx,
        cy,
        threshold_px=threshold_px,
        confidence=confidence,
        max_iterations=max_iterations,
        min_inliers=min_inliers,
        seed=seed,
    )
    if out is None:
        return None
    pose, inliers, iterations = out
    return PnpResult(pose, inliers, int(inliers.sum()), iterations)
