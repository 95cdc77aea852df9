"""Milliseconds per stereo pair for each feature extractor on the CPU, against the paper.

The paper (DH-PTAM, CPU) reports per stereo frame: SuperPoint 2.5–3.3 s, R2D2 8.5–8.8 s. Each
row here times ``extractor.extract(left, right)`` — both images, network, detection,
description, the numpy hand-over — at ``max_keypoints=1000`` (the number actually returned is
printed: R2D2's thresholds may stop short of it on a plain image) and gives the paper's time
divided by ours.

Images: scikit-image's astronaut photograph in grey, resized to each size; the right image is
the left one shifted by 8 px (a stereo-like disparity). SuperPoint runs with random weights:
no weights ship with dhptam and its cost does not depend on their values (the NMS sees a few
more or fewer peaks, nothing else). R2D2 uses the official checkpoints from
``../shared/models/r2d2`` (or ``--r2d2-dir``).

    python benches/bench_features.py [--sizes 640x480,1280x1024] [--repeats 3] [--threads 2]
        [--max-keypoints 1000] [--only TEXT]

The int8 row calibrates its trunk on the first pair it sees (the extractor's default), so its
first call (also printed, for every row) includes the calibration.

Prints a markdown table; the figures in docs/BENCHMARKS.md come from it.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch
from skimage import data

from dhptam import features
from dhptam.features.superpoint import SuperPoint, SuperPointNet

PAPER_S = {"superpoint": (2.5, 3.3), "r2d2": (8.5, 8.8)}
REPO = Path(__file__).resolve().parents[1]


def stereo_pair(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    grey = cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2GRAY)
    left = cv2.resize(grey, (width, height), interpolation=cv2.INTER_AREA)
    return left, np.ascontiguousarray(np.roll(left, -8, axis=1))


def configurations(
    r2d2_dir: Path, threads: int, max_keypoints: int
) -> list[tuple[str, str, Callable[[], features.Extractor]]]:
    """(row label, paper family, constructor)."""
    full = r2d2_dir / "r2d2_WASF_N16.pt"
    fast = r2d2_dir / "faster2d2_WASF_N16.pt"
    common = {"device": "cpu", "max_keypoints": max_keypoints, "threads": threads}

    def superpoint(precision: str) -> features.Extractor:
        torch.manual_seed(0)
        return SuperPoint(None, net=SuperPointNet(), precision=precision, **common)  # type: ignore[arg-type]

    return [
        ("orb", "", lambda: features.load("orb", max_keypoints=max_keypoints, threads=threads)),
        ("sift", "", lambda: features.load("sift", max_keypoints=max_keypoints, threads=threads)),
        ("superpoint (random weights)", "superpoint", lambda: superpoint("float32")),
        ("superpoint, bf16 trunk", "superpoint", lambda: superpoint("bfloat16")),
        (
            "r2d2 r2d2_WASF_N16, scales 1/0.75/0.5 (default)",
            "r2d2",
            lambda: features.load("r2d2", full, **common),
        ),
        ("r2d2 faster2d2, scales 1/0.75/0.5", "r2d2", lambda: features.load("r2d2", fast, **common)),
        ("r2d2 faster2d2, scale 1", "r2d2", lambda: features.load("r2d2", fast, scales=(1.0,), **common)),
        (
            "r2d2 faster2d2, scale 1, bf16 trunk",
            "r2d2",
            lambda: features.load("r2d2", fast, scales=(1.0,), precision="bfloat16", **common),
        ),
        (
            "r2d2 faster2d2, scale 1, int8 trunk",
            "r2d2",
            lambda: features.load("r2d2", fast, scales=(1.0,), precision="int8", **common),
        ),
        (
            "r2d2 r2d2_WASF_N16, scales 1/0.75/0.5, int8 trunk",
            "r2d2",
            lambda: features.load("r2d2", full, precision="int8", **common),
        ),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", default="640x480,1280x1024", help="comma-separated WxH list")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per row (after one warm-up)")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--only", default="", help="run only rows whose label contains this text")
    parser.add_argument("--max-keypoints", type=int, default=1000, help="keypoints kept per image")
    parser.add_argument("--r2d2-dir", type=Path, default=REPO.parent / "shared" / "models" / "r2d2")
    args = parser.parse_args()

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    print(f"# {cpu}, {os.cpu_count()} cores, torch {torch.__version__}, OpenCV {cv2.__version__}, ")
    print(f"# threads {args.threads}, load average before: {os.getloadavg()[0]:.2f}\n")
    print(
        "| image | extractor | keypoints (L/R) | ms per stereo pair (median, min) | CPU ms (median) "
        "| first call ms | paper / ours |"
    )
    print("|---|---|---|---|---|---|---|")
    for size in args.sizes.split(","):
        width, height = (int(v) for v in size.lower().split("x"))
        left, right = stereo_pair(width, height)
        for label, family, make in configurations(args.r2d2_dir, args.threads, args.max_keypoints):
            if args.only and args.only not in label:
                continue
            extractor = make()
            start = time.perf_counter()
            fl, fr = extractor.extract(left, right)  # warm-up (allocations, kernel choice, int8 calibration)
            first = time.perf_counter() - start
            times, cpu = [], []
            for _ in range(args.repeats):
                start, start_cpu = time.perf_counter(), time.process_time()
                fl, fr = extractor.extract(left, right)
                times.append(time.perf_counter() - start)
                cpu.append(time.process_time() - start_cpu)
            median = statistics.median(times)
            ratio = ""
            if family:
                low, high = PAPER_S[family]
                ratio = f"{low / median:.1f}–{high / median:.1f}×"
            print(
                f"| {width}×{height} | {label} | {len(fl)}/{len(fr)} | "
                f"{1e3 * median:.0f} ({1e3 * min(times):.0f}) | {1e3 * statistics.median(cpu):.0f} "
                f"| {1e3 * first:.0f} | {ratio} |",
                flush=True,
            )
    print(f"\n# load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
