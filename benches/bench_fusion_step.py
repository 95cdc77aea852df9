"""One stereo fusion step at TUM-VIE resolution, stage by stage (dhptam only, no baseline).

Per side: 1 M raw events at 1280×720 (the event cameras of the TUM-VIE-size simulator rig)
offered to the camera's hot-pixel detector (``HotPixels.update``, which counts one window in
three: its row is the mean over the repeats, use a multiple of 3), moved to their rectified
pixels through the lookup table (``EventRectifier``), their E3CT, the per-channel scales
shared by left and right, each E3CT normalised and warped into its 1024×1024 frame camera
through a plane at 2 m, β chosen from the frame, and the blend. The paper reports 25–30 ms
for the stereo E3CT and 439–521 ms for the fusion on a CPU; the issue's target for the whole
step is ≤ 10 ms on 2 cores. Prints a Markdown table (best of ``--repeats`` per stage and for
the whole step, wall time and the process CPU time of all threads, which a shared machine
inflates less) with the rayon thread count and the load.

The step runs as the front-end runs it: β from each frame first, then one pass per side
that normalises inside the warp (tap by tap) and blends the warped tensor with the frame
while it is in cache (``warp_and_fuse``); the warp's inverse map is built on the first call
for these sizes and reused (the first call's time is printed apart).

``--previous PATH`` also runs the step with another build of ``dhptam._core`` (e.g. the
extension built from main before this work), loaded side by side in the same process, the
way that build's front-end ran it (a build from before the blend moved into the warp, without
``_warp_and_fuse``: scales, β, the warp with the scales, then ``_fuse``); the warped tensors
and the fused images of both are checked
equal bit for bit first, and the table gets the previous build's columns and the ratios from
the same run (the two steps alternate).

    python benches/bench_fusion_step.py [--repeats 7] [--previous OLD/_core.abi3.so]
    RAYON_NUM_THREADS=1 python benches/bench_fusion_step.py
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from types import ModuleType

import numpy as np
from bench_e3ct import SPAN_NS, H, W, load_previous, window

from dhptam import SE3, SO3, _core
from dhptam.geometry import RectifiedStereo, StereoRig
from dhptam.sim.presets import RIGS

FRAME = 1024
Mark = tuple[float, float]  # (wall, process CPU) seconds


def now() -> Mark:
    return time.perf_counter(), time.process_time()


HOT = "2 × hot pixels (mean)"
NAMES = (HOT, "2 × rectify", "2 × e3ct", "scales", "2 × β", "2 × (warp + fuse)", "total")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--previous", help="another build of dhptam._core to run the step with")
    args = ap.parse_args()
    rig = RIGS["tumvie"]
    cams, poses = rig.cameras(), rig.imu_from_cam()
    right_from_left = poses["event_right"].inverse() @ poses["event_left"]
    rect = RectifiedStereo(StereoRig(cams["event_left"], cams["event_right"], right_from_left))
    rw, rh = rect.width, rect.height
    sides = [window(1_000_000, seed) for seed in (1, 2)]
    frames = [np.random.default_rng(s).integers(20, 230, (FRAME, FRAME), dtype=np.uint8) for s in (3, 4)]
    k = rect.K
    k_event, k_frame = [k[0, 0], k[1, 1], k[0, 2], k[1, 2]], [750.0, 750.0, 511.5, 511.5]
    frame_from_event = SE3(SO3.exp([0.01, -0.015, 0.004]), [0.02, 0.03, 0.0])

    def step(m: ModuleType, fused_blend: bool) -> Callable[[], tuple[list[Mark], list[np.ndarray]]]:
        """The step with module ``m``: returns the stage marks and the warped tensors + fused images
        (``fused_blend``: the blend inside the warp, ``_warp_and_fuse``; else warp, then fuse)."""
        # The same rig rebuilt with the module's own classes (another build's types differ).
        cam = [
            m.Camera(c.model, list(c.params), c.width, c.height)
            for c in (cams["event_left"], cams["event_right"])
        ]
        rig_m = m.StereoRig(cam[0], cam[1], m.SE3.from_matrix(right_from_left.matrix()))
        rect_m = m.RectifiedStereo(rig_m)
        rectifiers = [m.EventRectifier(rect_m, side) for side in ("left", "right")]
        assert all(r.raw_size == (W, H) for r in rectifiers)
        # The hot-pixel detectors' update (builds from before them: no such stage). They keep
        # their state across repeats, as across a run's windows.
        hot = [m.HotPixels(W, H) for _ in sides] if hasattr(m, "HotPixels") else []
        pose = (
            m.SE3(m.SO3.exp([0.01, -0.015, 0.004]), [0.02, 0.03, 0.0]) if m is not _core else frame_from_event
        )

        def warp_fuse(
            image: np.ndarray, scales: list[float], frame: np.ndarray, beta: float
        ) -> list[np.ndarray]:
            if fused_blend:
                args = (image, k_event, k_frame, pose, 2.0, (0.0, 0.0), frame, beta, scales)
                return list(m._warp_and_fuse(*args))
            warped = m._warp_to_frame(
                image, k_event, k_frame, pose, 2.0, (0.0, 0.0), FRAME, FRAME, None, scales
            )[0]
            return [warped, m._fuse(frame, warped, beta)]

        def run() -> tuple[list[Mark], list[np.ndarray]]:
            th = now()
            for detector, s in zip(hot, sides, strict=False):
                detector.update(s[0], s[1], SPAN_NS * 1e-9)
            t0 = now()
            rectified = [r.apply(*s, 0, SPAN_NS) for r, s in zip(rectifiers, sides, strict=True)]
            t1 = now()
            raw = [m._e3ct(*s, rw, rh, 0, SPAN_NS, 0.5, 30.0, 3, "both") for s in rectified]
            t2 = now()
            scales = m._e3ct_scales(raw, 99.0)
            t3 = now()
            betas = [m._choose_beta(f, None, None)[1] for f in frames]
            t4 = now()
            out = [warp_fuse(t, scales, f, b) for t, f, b in zip(raw, frames, betas, strict=True)]
            t5 = now()
            return [th, t0, t1, t2, t3, t4, t5], [a for pair in out for a in pair]

        return run

    def timed(
        runs: list[Callable[[], tuple[list[Mark], list[np.ndarray]]]],
    ) -> list[dict[str, tuple[float, float]]]:
        """Best wall and best CPU time [ms] of each stage of each run over the repeats; the runs
        alternate, so that a change of the machine's load reaches all of them alike."""
        wall: list[dict[str, list[float]]] = [{k: [] for k in NAMES} for _ in runs]
        cpu: list[dict[str, list[float]]] = [{k: [] for k in NAMES} for _ in runs]
        for _ in range(args.repeats):
            for w, c, run in zip(wall, cpu, runs, strict=True):
                marks, _ = run()
                pairs = [(marks[i], marks[i + 1]) for i in range(6)] + [(marks[0], marks[6])]
                for key, (a, b) in zip(NAMES, pairs, strict=True):
                    w[key].append((b[0] - a[0]) * 1e3)
                    c[key].append((b[1] - a[1]) * 1e3)

        def figure(values: dict[str, list[float]], key: str) -> float:
            # The hot-pixel detector counts one window in three (it samples): its mean over the
            # repeats is its cost per window; the total is the best of the other stages' sum
            # plus that mean.
            hot = float(np.mean(values[HOT]))
            if key == HOT:
                return hot
            if key == "total":
                return min(t - h for t, h in zip(values["total"], values[HOT], strict=True)) + hot
            return min(values[key])

        return [
            {key: (figure(w, key), figure(c, key)) for key in NAMES} for w, c in zip(wall, cpu, strict=True)
        ]

    ours = step(_core, True)
    t_first = time.perf_counter()
    marks, mine = ours()
    first_warp = (marks[6][0] - marks[5][0]) * 1e3
    t_first = time.perf_counter() - t_first
    rectifiers = [_core.EventRectifier(rect, side) for side in ("left", "right")]
    kept = [len(r.apply(*s, 0, SPAN_NS)[0]) for r, s in zip(rectifiers, sides, strict=True)]
    runs, names = [ours], ["dhptam"]
    if args.previous:
        previous = load_previous(args.previous)
        theirs = step(previous, hasattr(previous, "_warp_and_fuse"))
        _, want = theirs()
        for a, b in zip(mine, want, strict=True):
            np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))
        runs.append(theirs)
        names.append("previous")
    columns = list(zip(names, timed(runs), strict=True))
    print(
        f"stereo fusion step, events 2 × 1 M at {W}×{H} (kept after rectification: {kept[0]} + {kept[1]}, "
        f"rectified {rw}×{rh}), frames {FRAME}×{FRAME}, rayon threads {_core.thread_count()}, load average "
        f"{os.getloadavg()[0]:.1f}; best of {args.repeats}; "
        f"first step (2 warp maps built) {t_first * 1e3:.1f} ms, "
        f"of which 2 × warp {first_warp:.1f} ms"
        + (
            "; warped tensors and fused images equal to the previous build's bit for bit"
            if args.previous
            else ""
        )
    )
    head = " | ".join(f"{name} wall / CPU [ms]" for name, _ in columns)
    ratio = " | previous / dhptam (wall / CPU)" if args.previous else ""
    print(f"| stage | {head}{ratio} |")
    print("|---|" + "---:|" * (len(columns) + (1 if args.previous else 0)))
    for key in NAMES:
        cells = " | ".join(f"{t[key][0]:.1f} / {t[key][1]:.1f}" for _, t in columns)
        if args.previous:
            (w0, c0), (w1, c1) = columns[0][1][key], columns[1][1][key]
            cells += f" | {w1 / w0:.1f}× / {c1 / max(c0, 1e-9):.1f}×"
        print(f"| {key} | {cells} |")


if __name__ == "__main__":
    main()
