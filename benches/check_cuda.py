"""Runs each torch extractor on CUDA and compares it with the CPU; times both.

On a machine with a CUDA GPU (figures from an H100 in docs/BENCHMARKS.md, "Feature extractors
on a GPU machine"):

    python benches/check_cuda.py [--device cuda] [--r2d2-dir ../shared/models/r2d2]
        [--sizes 640x480,1024x1024] [--max-keypoints 1000]

For R2D2 (both official checkpoints) and SuperPoint (random weights, seeded), on the first size
of ``--sizes`` (a stereo pair of the astronaut photograph), it checks that the CUDA run finds
the CPU's keypoints (≥ 95 % within 0.5 px, cuDNN's different summation order moves a few
near-ties), with nearly the same descriptors (median cosine ≥ 0.999) and scores (median
relative difference ≤ 1e-3), then prints milliseconds per stereo pair on each device (float32,
and bfloat16/float16 on the GPU), and the device's milliseconds at each further size of
``--sizes`` (1024×1024 is TUM-VIE's frame size). Exits with status 1 when a comparison fails.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from skimage import data

from dhptam import features
from dhptam.features.superpoint import SuperPoint, SuperPointNet

REPO = Path(__file__).resolve().parents[1]


def _pair(width: int = 640, height: int = 480) -> tuple[np.ndarray, np.ndarray]:
    grey = cv2.resize(
        cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2GRAY), (width, height), interpolation=cv2.INTER_AREA
    )
    return grey, np.ascontiguousarray(np.roll(grey, -8, axis=1))


def _make(
    name: str, device: str, r2d2_dir: Path, precision: str = "float32", max_keypoints: int = 1000
) -> features.Extractor:
    if name == "superpoint":
        torch.manual_seed(0)
        net = SuperPointNet()
        return SuperPoint(None, net=net, device=device, max_keypoints=max_keypoints, precision=precision)
    return features.load(
        "r2d2", r2d2_dir / f"{name}.pt", device=device, max_keypoints=max_keypoints, precision=precision
    )


def _ms(extractor: features.Extractor, left: np.ndarray, right: np.ndarray, repeats: int = 5) -> float:
    extractor.extract(left, right)
    times = []
    for _ in range(repeats):
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        start = time.perf_counter()
        extractor.extract(left, right)  # returns numpy arrays: the device work is finished
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def _compare(cpu: features.Features, gpu: features.Features) -> tuple[float, float, float]:
    d = np.linalg.norm(cpu.keypoints[:, None] - gpu.keypoints[None], axis=2)
    nearest = d.argmin(axis=1)
    found = d[np.arange(len(cpu)), nearest] <= 0.5
    cosine = np.einsum("ij,ij->i", cpu.descriptors[found], gpu.descriptors[nearest[found]])
    rel = np.abs(cpu.scores[found] - gpu.scores[nearest[found]]) / np.maximum(cpu.scores[found], 1e-12)
    return float(found.mean()), float(np.median(cosine)), float(np.median(rel))


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--r2d2-dir", type=Path, default=REPO.parent / "shared" / "models" / "r2d2")
    parser.add_argument("--max-keypoints", type=int, default=1000, help="keypoints kept per image")
    parser.add_argument(
        "--sizes", default="640x480,1024x1024", help="WxH list; comparisons at the first, timings at each"
    )
    args = parser.parse_args()
    sizes = [tuple(int(v) for v in size.lower().split("x")) for size in args.sizes.split(",")]
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print("CUDA is not available here", file=sys.stderr)
        return 2
    left, right = _pair(*sizes[0])
    failed = False
    print(f"torch {torch.__version__}, device {args.device}")
    for name in ("r2d2_WASF_N16", "faster2d2_WASF_N16", "superpoint"):
        k = args.max_keypoints
        cpu_ex = _make(name, "cpu", args.r2d2_dir, max_keypoints=k)
        dev_ex = _make(name, args.device, args.r2d2_dir, max_keypoints=k)
        for cpu_f, dev_f, side in zip(
            cpu_ex.extract(left, right), dev_ex.extract(left, right), "LR", strict=True
        ):
            found, cosine, rel = _compare(cpu_f, dev_f)
            ok = found >= 0.95 and cosine >= 0.999 and rel <= 1e-3
            failed |= not ok
            print(
                f"{name} {side}: {len(cpu_f)}/{len(dev_f)} keypoints, {100 * found:.1f} % within 0.5 px, "
                f"median cosine {cosine:.5f}, median score rel. diff {rel:.1e}: {'ok' if ok else 'MISMATCH'}"
            )
        timing = [
            f"cpu {_ms(cpu_ex, left, right, 2):.0f} ms",
            f"{args.device} {_ms(dev_ex, left, right):.1f} ms",
        ]
        for precision in ("bfloat16", "float16") if args.device.startswith("cuda") else ("bfloat16",):
            reduced = _make(name, args.device, args.r2d2_dir, precision, k)
            timing.append(f"{args.device} {precision} {_ms(reduced, left, right):.1f} ms")
        print(f"{name} per stereo pair, {sizes[0][0]}×{sizes[0][1]}: " + ", ".join(timing))
        for width, height in sizes[1:]:
            pair = _pair(width, height)
            precisions = ("float32", "bfloat16", "float16")[: 3 if args.device.startswith("cuda") else 2]
            timing = [
                f"{args.device} {p} {_ms(_make(name, args.device, args.r2d2_dir, p, k), *pair):.1f} ms"
                for p in precisions
            ]
            print(f"{name} per stereo pair, {width}×{height}: " + ", ".join(timing))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
