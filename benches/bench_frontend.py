"""The per-frame front-end (``dhptam.frontend``) and event rectification, timed.

1. ``EventRectifier.apply`` on 1 M events of a 1280×720 kb4 event camera (the TUM-VIE-size
   simulator rig) against the same lookup written as vectorised numpy (fancy indexing into the
   table, boolean mask), in the same run, outputs checked equal.
2. ``Frontend`` per frame in each mode on a simulated sequence (``--sequence DIR``; by default
   0.5 s of the ``desk`` preset is simulated into a temporary folder), synchronous
   (``prefetch=0``), best of ``--repeats`` passes over all frames.

    python benches/bench_frontend.py [--sequence DIR] [--repeats 3]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from dhptam import _core
from dhptam.datasets import load_tumvie
from dhptam.frontend import MODES, Frontend
from dhptam.geometry import RectifiedStereo, StereoRig
from dhptam.sim.presets import RIGS


def bench_rectifier(repeats: int) -> None:
    rig = RIGS["tumvie"]
    cams, poses = rig.cameras(), rig.imu_from_cam()
    right_from_left = poses["event_right"].inverse() @ poses["event_left"]
    rect = RectifiedStereo(StereoRig(cams["event_left"], cams["event_right"], right_from_left))
    t0 = time.perf_counter()
    rectifier = _core.EventRectifier(rect, "left")
    build = time.perf_counter() - t0
    w, h = rectifier.raw_size
    rw, _ = rectifier.rect_size
    rng = np.random.default_rng(0)
    n = 1_000_000
    x = rng.integers(0, w, n).astype(np.uint16)
    y = rng.integers(0, h, n).astype(np.uint16)
    t = np.sort(rng.integers(0, 50_000_000, n)).astype(np.int64)
    p = rng.integers(0, 2, n).astype(np.int8)
    # numpy baseline: the same table (raw pixel → rectified pixel index, -1 outside).
    v, u = np.mgrid[0:h, 0:w]
    rect_px = rectifier.lookup(np.c_[u.ravel(), v.ravel()].astype(np.int64))
    table = np.where(np.isfinite(rect_px[:, 0]), rect_px[:, 1] * rw + rect_px[:, 0], -1).astype(np.int64)

    def numpy_apply() -> tuple[np.ndarray, ...]:
        idx = table[y.astype(np.int64) * w + x]
        keep = idx >= 0
        kept = idx[keep]
        return (kept % rw).astype(np.uint16), (kept // rw).astype(np.uint16), t[keep], p[keep]

    best = {"rust": np.inf, "numpy": np.inf}
    for _ in range(repeats):
        s = time.perf_counter()
        ours = rectifier.apply(x, y, t, p, 0, 50_000_000)
        best["rust"] = min(best["rust"], time.perf_counter() - s)
        s = time.perf_counter()
        ref = numpy_apply()
        best["numpy"] = min(best["numpy"], time.perf_counter() - s)
    assert all(np.array_equal(a, b) for a, b in zip(ours, ref, strict=True))
    print(f"EventRectifier table build (1280×720): {1e3 * build:.1f} ms")
    print(
        f"rectify 1 M events: EventRectifier.apply {1e3 * best['rust']:.1f} ms, "
        f"numpy {1e3 * best['numpy']:.1f} ms "
        f"({best['numpy'] / best['rust']:.2f}×), {len(ours[0])} kept"
    )


def bench_frontend(sequence: Path, repeats: int) -> None:
    with load_tumvie(sequence) as seq:
        cams = seq.calibration.cameras
        print(
            f"sequence {sequence.name}: {len(seq.frames)} frames, frames {cams['frame_left'].width}×"
            f"{cams['frame_left'].height}, events {cams['event_left'].width}×{cams['event_left'].height}, "
            f"{len(seq.events['left'])} + {len(seq.events['right'])} events"
        )
        for mode in MODES:
            fe = Frontend(seq, mode, prefetch=0)
            best = np.inf
            for _ in range(repeats):
                s = time.perf_counter()
                for _frame in fe:
                    pass
                best = min(best, time.perf_counter() - s)
            print(f"Frontend mode {mode:<7}: {1e3 * best / len(fe):.1f} ms per stereo frame")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequence", type=Path, help="TUM-VIE sequence folder (default: simulate one)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    print(f"rayon threads: {_core.thread_count()}")
    bench_rectifier(args.repeats)
    if args.sequence is not None:
        bench_frontend(args.sequence, args.repeats)
        return
    from dhptam.sim import simulate

    with tempfile.TemporaryDirectory() as tmp:
        path = simulate(tmp, preset="desk", duration_s=0.5).path
        bench_frontend(path, args.repeats)


if __name__ == "__main__":
    main()
