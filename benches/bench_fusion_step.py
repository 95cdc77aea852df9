"""One stereo fusion step at TUM-VIE resolution, stage by stage (dhptam only, no baseline).

Per side: 1 M raw events at 1280×720 (the event cameras of the TUM-VIE-size simulator rig)
moved to their rectified pixels through the lookup table (``EventRectifier``), their E3CT,
the left and right tensors normalised with shared scales, each warped into its 1024×1024
frame camera through a plane at 2 m, β chosen from the frame, and the blend. The paper
reports 25–30 ms for the stereo E3CT and 439–521 ms for the fusion on a CPU; the issue's
target for the whole step is ≤ 10 ms on 2 cores. Prints a Markdown table (best of
``--repeats`` per stage and for the whole step, wall time and the process CPU time of all
threads, which a shared machine inflates less) with the rayon thread count and the load.

A second table times the same step with the one-pass stages, checked equal to the staged
pipeline's fused images first: rectification inside the E3CT pass (``EventRectifier.e3ct``),
the shared scales only (``_e3ct_scales``), and normalise + warp + blend in one pass over the
frame pixels (``_fuse_frame``); ``staged / one-pass`` is the ratio of the whole steps.

    python benches/bench_fusion_step.py [--repeats 7]
    RAYON_NUM_THREADS=1 python benches/bench_fusion_step.py
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from bench_e3ct import SPAN_NS, H, W, window

from dhptam import SE3, SO3, _core
from dhptam.events import e3ct, normalise
from dhptam.fusion import choose_beta, fuse, warp_to_frame
from dhptam.geometry import RectifiedStereo, StereoRig
from dhptam.sim.presets import RIGS

FRAME = 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    rig = RIGS["tumvie"]
    cams, poses = rig.cameras(), rig.imu_from_cam()
    right_from_left = poses["event_right"].inverse() @ poses["event_left"]
    rect = RectifiedStereo(StereoRig(cams["event_left"], cams["event_right"], right_from_left))
    rectifiers = [_core.EventRectifier(rect, side) for side in ("left", "right")]
    assert all(r.raw_size == (W, H) for r in rectifiers)
    rw, rh = rect.width, rect.height
    sides = [window(1_000_000, seed) for seed in (1, 2)]
    frames = [np.random.default_rng(s).integers(20, 230, (FRAME, FRAME), dtype=np.uint8) for s in (3, 4)]
    k = rect.K
    k_event, k_frame = [k[0, 0], k[1, 1], k[0, 2], k[1, 2]], [750.0, 750.0, 511.5, 511.5]
    frame_from_event = SE3(SO3.exp([0.01, -0.015, 0.004]), [0.02, 0.03, 0.0])
    names = ("2 × rectify", "2 × e3ct", "normalise", "2 × warp", "2 × (β + fuse)", "total")
    stages: dict[str, list[float]] = {k: [] for k in names}
    cpu: dict[str, list[float]] = {k: [] for k in names}

    def now() -> tuple[float, float]:
        return time.perf_counter(), time.process_time()

    fused_staged: list[np.ndarray] = []
    for _ in range(args.repeats):
        t0 = now()
        rectified = [r.apply(*s, 0, SPAN_NS) for r, s in zip(rectifiers, sides, strict=True)]
        t1 = now()
        raw = [e3ct(*s, width=rw, height=rh, t_start_ns=0, t_end_ns=SPAN_NS) for s in rectified]
        t2 = now()
        tensors, _ = normalise(*raw)
        t3 = now()
        warped = [
            warp_to_frame(t, k_event, k_frame, frame_from_event, width=FRAME, height=FRAME, depth_m=2.0)[0]
            for t in tensors
        ]
        t4 = now()
        fused_staged = [fuse(f, d, choose_beta(f).beta) for f, d in zip(frames, warped, strict=True)]
        t5 = now()
        marks = (t0, t1, t2, t3, t4, t5)
        spans = [(marks[k], marks[k + 1]) for k in range(5)] + [(t0, t5)]
        for key, (a, b) in zip(names, spans, strict=True):
            stages[key].append(b[0] - a[0])
            cpu[key].append(b[1] - a[1])
    print(
        f"stereo fusion step, events 2 × 1 M at {W}×{H} (kept after rectification: "
        f"{len(rectified[0][0])} + {len(rectified[1][0])}, rectified {rw}×{rh}), frames {FRAME}×{FRAME}, "
        f"rayon threads {_core.thread_count()}, load average {os.getloadavg()[0]:.1f}; best of {args.repeats}"
    )
    print("| stage | wall [ms] | CPU, all threads [ms] |")
    print("|---|---:|---:|")
    for key in names:
        print(f"| {key} | {min(stages[key]) * 1e3:.1f} | {min(cpu[key]) * 1e3:.1f} |")

    one_pass = ("2 × (rectify + e3ct)", "scales", "2 × (β + normalise + warp + fuse)", "total")
    o_wall: dict[str, list[float]] = {k: [] for k in one_pass}
    o_cpu: dict[str, list[float]] = {k: [] for k in one_pass}
    for _ in range(args.repeats):
        t0 = now()
        raw = [r.e3ct(*s, 0, SPAN_NS) for r, s in zip(rectifiers, sides, strict=True)]
        t1 = now()
        scales = _core._e3ct_scales(raw, 99.0)
        t2 = now()
        fused = [
            _core._fuse_frame(
                f, d, scales, k_event, k_frame, frame_from_event, 2.0, (0.0, 0.0), choose_beta(f).beta
            )
            for f, d in zip(frames, raw, strict=True)
        ]
        t3 = now()
        marks = (t0, t1, t2, t3)
        spans = [(marks[k], marks[k + 1]) for k in range(3)] + [(t0, t3)]
        for key, (a, b) in zip(one_pass, spans, strict=True):
            o_wall[key].append(b[0] - a[0])
            o_cpu[key].append(b[1] - a[1])
    for a, b in zip(fused, fused_staged, strict=True):
        np.testing.assert_array_equal(a, b)
    print()
    print(f"one-pass stages, fused images equal to the staged ones; load average {os.getloadavg()[0]:.1f}")
    print("| stage | wall [ms] | CPU, all threads [ms] |")
    print("|---|---:|---:|")
    for key in one_pass:
        print(f"| {key} | {min(o_wall[key]) * 1e3:.1f} | {min(o_cpu[key]) * 1e3:.1f} |")
    ratio_wall = min(stages["total"]) / min(o_wall["total"])
    ratio_cpu = min(cpu["total"]) / min(o_cpu["total"])
    print(f"| staged / one-pass (whole step) | {ratio_wall:.1f}× | {ratio_cpu:.1f}× |")


if __name__ == "__main__":
    main()
