"""dhptam's RANSAC PnP against OpenCV's ``cv2.solvePnPRansac`` (P3P minimal solver, same
threshold, confidence and iteration cap), same machine, same run, same correspondences.

    python benches/bench_pnp.py [--repeat R] [--threads N]

Scenes: N world points 1–12 m in front of a random pose, 0.5 px Gaussian pixel noise, a
fraction replaced by uniform random pixels (outliers). Both solvers get a 2 px threshold,
99.9 % confidence and at most 1000 iterations. Printed per scene: median wall-clock time over
R runs of each solver, their ratio (OpenCV / dhptam), iterations, inliers and the pose errors
against the truth. OpenCV runs with ``cv2.setNumThreads(N)``; dhptam's PnP is single-threaded.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_pnp import CX, CY, FX, FY, K, pose_error, scene

from dhptam import solver

T = TypeVar("T")


def _time(fn: Callable[[], T], repeat: int) -> tuple[float, T]:
    out = fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def bench_scene(n: int, outliers: float, seed: int, repeat: int) -> str:
    """One table row: both solvers on one scene."""
    world, pixels, _, truth = scene(n, outliers, 0.5, seed)

    def ours() -> solver.PnpResult | None:
        return solver.solve_pnp_ransac(
            world, pixels, FX, FY, CX, CY, threshold_px=2.0, confidence=0.999, seed=seed
        )

    def opencv() -> tuple:
        return cv2.solvePnPRansac(
            world,
            pixels,
            K,
            None,
            iterationsCount=1000,
            reprojectionError=2.0,
            confidence=0.999,
            flags=cv2.SOLVEPNP_P3P,
        )

    t_ours, r = _time(ours, repeat)
    t_cv, (ok, rvec, tvec, inl) = _time(opencv, repeat)
    assert r is not None and ok
    cv_pose = np.eye(4)
    cv_pose[:3, :3], _ = cv2.Rodrigues(rvec)
    cv_pose[:3, 3] = tvec.ravel()
    e_ours = pose_error(r.cam_from_world, truth)
    e_cv = pose_error(cv_pose, truth)
    return (
        f"| {n} | {outliers:.0%} | {t_ours * 1e3:.3f} ms | {t_cv * 1e3:.3f} ms "
        f"| {t_cv / t_ours:.2f}× | {r.iterations} | {r.inlier_count} / {len(inl)} "
        f"| {e_ours[0] * 100:.2f}, {e_ours[1] * 1e3:.2f} / {e_cv[0] * 100:.2f}, "
        f"{e_cv[1] * 1e3:.2f} |"
    )


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeat", type=int, default=50)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    cv2.setNumThreads(args.threads)
    print(
        "| N | outliers | dhptam | OpenCV | OpenCV / dhptam | iterations (dhptam) "
        "| inliers dhptam / OpenCV | pose error dhptam / OpenCV (cm, mrad) |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---|")
    for n, outliers, seed in [(100, 0.3, 1), (500, 0.3, 2), (500, 0.5, 3), (2000, 0.5, 4)]:
        print(bench_scene(n, outliers, seed, args.repeat))
    return 0


if __name__ == "__main__":
    sys.exit(main())
