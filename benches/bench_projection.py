"""Projection and unprojection of 1 M points: dhptam's binding against OpenCV, same run.

Compares, per camera model, ``Camera.project`` with ``cv2.projectPoints`` (pinhole, radtan)
or ``cv2.fisheye.projectPoints`` (kb4), and ``Camera.unproject`` with ``cv2.undistortPoints``
/ ``cv2.fisheye.undistortPoints``. Both sides get the same float64 points and are checked to
agree before timing. Prints a Markdown table for docs/BENCHMARKS.md.

    python benches/bench_projection.py [--points 1000000] [--repeats 5] [--threads N]

``--threads`` sets both rayon's (dhptam) and OpenCV's thread count; by default each library
uses its own default.
"""

from __future__ import annotations

import argparse
import os
import platform
import time


def best_of(repeats: int, fn) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()
    if args.threads is not None:
        os.environ["RAYON_NUM_THREADS"] = str(args.threads)  # read by rayon at first use

    import cv2
    import numpy as np

    import dhptam

    if args.threads is not None:
        cv2.setNumThreads(args.threads)

    rng = np.random.default_rng(0)
    cameras = {
        "pinhole": dhptam.Camera("pinhole", [458.0, 457.0, 367.2, 248.4], 752, 480),
        "radtan": dhptam.Camera(
            "radtan", [458.7, 457.3, 367.2, 248.4, -0.2834, 0.0740, 1.9e-4, 1.8e-5, 0.0], 752, 480
        ),
        "kb4": dhptam.Camera(
            "kb4", [747.3, 747.2, 490.8, 506.3, 0.0037, 0.0181, -0.0302, 0.0173], 1024, 1024
        ),
    }
    print(
        f"# {args.points:,} points, best of {args.repeats}; dhptam {dhptam.__version__} "
        f"({dhptam._core.thread_count()} rayon threads), OpenCV {cv2.__version__} "
        f"({cv2.getNumThreads()} threads), {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} CPUs\n"
    )
    print("| model | operation | dhptam [ms] | OpenCV [ms] | OpenCV / dhptam |")
    print("|---|---|---:|---:|---:|")
    for name, camera in cameras.items():
        for row in bench_model(name, camera, args.points, args.repeats, rng):
            print(row)


def bench_model(name, camera, n_points: int, repeats: int, rng) -> list[str]:
    """Table rows comparing dhptam with OpenCV for one camera model."""
    import cv2
    import numpy as np

    zero = np.zeros(3)
    # OpenCV's default undistortion stops after 5 (radtan) or 10 (fisheye) iterations, which
    # leaves ~1e-3 errors in image corners; ask it for the accuracy dhptam delivers.
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-12)
    pixels = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(n_points, 2))
    points = camera.unproject(pixels) * rng.uniform(0.5, 10.0, size=(n_points, 1))
    K = camera.K
    dist = np.array(camera.params[4:])
    pts_cv = points.reshape(-1, 1, 3)
    pix_cv = pixels.reshape(-1, 1, 2)
    if name == "kb4":

        def cv_project():
            return cv2.fisheye.projectPoints(pts_cv, zero, zero, K, dist)[0]

        def cv_unproject():
            return cv2.fisheye.undistortPoints(pix_cv, K, dist, criteria=criteria)

    else:

        def cv_project():
            return cv2.projectPoints(pts_cv, zero, zero, K, dist)[0]

        def cv_unproject():
            return cv2.undistortPoints(pix_cv, K, dist, criteria=criteria)

    # Same answer first: a fast wrong answer is not a result.
    np.testing.assert_allclose(camera.project(points), cv_project().reshape(-1, 2), atol=1e-6)
    bearings = camera.unproject(pixels)
    np.testing.assert_allclose(bearings[:, :2] / bearings[:, 2:], cv_unproject().reshape(-1, 2), atol=1e-8)

    rows = []
    for op, ours, theirs in (
        ("project", lambda: camera.project(points), cv_project),
        ("unproject", lambda: camera.unproject(pixels), cv_unproject),
    ):
        t_ours = best_of(repeats, ours)
        t_cv = best_of(repeats, theirs)
        rows.append(f"| {name} | {op} | {t_ours * 1e3:.1f} | {t_cv * 1e3:.1f} | {t_cv / t_ours:.1f}× |")
    return rows


if __name__ == "__main__":
    main()
