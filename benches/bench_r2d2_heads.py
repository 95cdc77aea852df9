"""R2D2 on the CPU: the fused Rust heads against torch's upsampling + heads, same extractor.

Since the fused path, the CPU extractor never builds the full-resolution 128-channel map: the
Rust core (``_core._r2d2_heads``) interpolates each pixel's descriptor from the network's
low-resolution output, squares it and takes the heads' dot products in registers, and the
descriptors are interpolated at the keypoints only. The baseline is the same extractor with
``_heads`` replaced by the torch path (``F.interpolate`` + ``R2D2Net.heads``, what runs on a
GPU), so the rows differ in that step alone. Each row: ``extractor.extract(left, right)`` on
the astronaut photograph in grey (right image shifted by 8 px), ``max_keypoints=1000``, the
best of ``--repeats`` runs after a warm-up, process CPU time (all threads) and wall time.

    python benches/bench_r2d2_heads.py [--sizes 640x480,1280x1024] [--threads 2] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812 - torch's usual name
from skimage import data

from dhptam.features.r2d2 import R2D2

REPO = Path(__file__).resolve().parents[1]


class TorchHeads(R2D2):
    """The same extractor with the heads run by torch on the upsampled map (the GPU path)."""

    def _heads(self, low: torch.Tensor, upsample: int) -> tuple[torch.Tensor, torch.Tensor]:
        low = low.float()
        if upsample > 1:
            low = F.interpolate(low, scale_factor=upsample, mode="bilinear", align_corners=False)
        _, rel, rep = self.net.heads(low)
        return rel, rep


def best_of(extractor: R2D2, left: np.ndarray, right: np.ndarray, repeats: int) -> tuple[float, float, int]:
    extractor.extract(left, right)
    cpu, wall, count = [], [], 0
    for _ in range(repeats):
        c, w = time.process_time(), time.perf_counter()
        first, _ = extractor.extract(left, right)
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
        count = len(first.keypoints)
    return min(cpu), min(wall), count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="640x480,1280x1024")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--r2d2-dir", type=Path, default=REPO.parent / "shared" / "models" / "r2d2")
    args = parser.parse_args()
    grey = cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2GRAY)
    settings = [
        ("faster2d2_WASF_N16", "bfloat16", (1.0,)),
        ("faster2d2_WASF_N16", "float32", (1.0,)),
        ("r2d2_WASF_N16", "bfloat16", (1.0,)),
        ("r2d2_WASF_N16", "float32", (1.0, 0.75, 0.5)),
    ]
    print(f"torch {torch.__version__}, {args.threads} threads, load average {os.getloadavg()[0]:.1f}")
    print(
        "| image | weights | precision | scales "
        "| torch heads: CPU / wall s | fused: CPU / wall s | CPU ratio |"
    )
    print("|---|---|---|---|---:|---:|---:|")
    for size in args.sizes.split(","):
        w, h = (int(v) for v in size.split("x"))
        left = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA)
        right = np.ascontiguousarray(np.roll(left, -8, axis=1))
        for weights, precision, scales in settings:
            kw = dict(
                device="cpu", threads=args.threads, precision=precision, scales=scales, max_keypoints=1000
            )
            path = args.r2d2_dir / f"{weights}.pt"
            base = best_of(TorchHeads(path, **kw), left, right, args.repeats)
            fused = best_of(R2D2(path, **kw), left, right, args.repeats)
            print(
                f"| {size} | {weights} | {precision} | {'/'.join(map(str, scales))} "
                f"| {base[0]:.2f} / {base[1]:.2f} | {fused[0]:.2f} / {fused[1]:.2f} "
                f"| {base[0] / fused[0]:.2f}× |",
                flush=True,
            )
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
