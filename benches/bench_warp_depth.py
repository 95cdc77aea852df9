"""How far warped event edges sit from the frame pixels of the same 3-D points (issue #8).

For each simulated sequence (the ``normal`` suite of ``bench_accuracy_normal.py`` and the HDR
demo of ``bench_accuracy_demo.py``, from the dhptam cache) dhptam first runs in mode
``fusion`` with ``[fusion] warp_depth = "tracked"`` (synchronous back-end), which records in
``frames.csv`` the warp depth each frame used: the median depth of the map points the frame
before it was tracked with, rounded to the inverse-depth bins of ``warp_depth_step_px``.
Then, every ``--step`` frames, the pixels where events fired in each event camera's window are
warped into the rectified frame camera three ways, and compared with where the frame camera
sees the same 3-D point (the simulator's rendered depth of the event camera at the fusion
time, projected by the frame camera and rectified):

* ``infinity``: the plane at infinity (``plane_depth_m = 0``, the warp of ``warp_depth =
  "plane"`` by default);
* ``tracked``: the plane at the depth the run used for that frame;
* ``true median``: a plane at the median true depth of those event pixels (the best a single
  plane can do; an oracle, not available to the system).

Prints a Markdown table (median and 90th percentile of the pixel distance, pooled over both
sides and the sampled frames) and writes it to ``--out/report.md``.

    python benches/bench_warp_depth.py [--normal-duration 4] [--demo-seeds 0] [--step 5]
        [--out bench-warp-depth]
    python benches/bench_warp_depth.py --cost 50 [--demo-seeds 0]   # what the tracked depth costs
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import sys
from pathlib import Path
from typing import Any

import numpy as np
from _accuracy import finish_table

REPO = Path(__file__).resolve().parents[1]


def _warp_depths(sequence: Path, out: Path) -> dict[int, float]:
    """Per frame index, the warp depth a ``fusion`` run with ``warp_depth = "tracked"`` used."""
    from dhptam import _core
    from dhptam.run import run

    config = _core.Config.from_toml('[fusion]\nwarp_depth = "tracked"')
    result = run(sequence, out, mode="fusion", config=config, threaded=False, progress=False)
    with open(result.files["frames"], newline="", encoding="utf-8") as f:
        return {int(r["index"]): float(r["warp_depth_m"]) for r in csv.DictReader(f)}


def _distances(
    seq: Any, fe: Any, sim: Any, index: int, depth_m: float, max_pixels: int
) -> dict[str, list[float]]:
    """Pixel distances between warped event pixels and the truth, per warp, both sides."""
    calib = seq.calibration
    t0, t1 = fe.window_ns(index)
    out: dict[str, list[float]] = {"infinity": [], "tracked": [], "true median": []}
    rng = np.random.default_rng(index)
    for camera, side in ((2, "left"), (3, "right")):
        raw = seq.events[side].window(t0, t1)
        pixels = np.unique(np.c_[np.asarray(raw.x), np.asarray(raw.y)].astype(np.int64), axis=0)
        if len(pixels) > max_pixels:
            pixels = pixels[rng.choice(len(pixels), max_pixels, replace=False)]
        if len(pixels) == 0:
            continue
        cam_e, cam_f = calib.cameras[f"event_{side}"], calib.cameras[f"frame_{side}"]
        depth = sim.render_depth(camera, int(fe.t_f_ns[index]))
        z = depth[pixels[:, 1], pixels[:, 0]].astype(np.float64)
        bearings = cam_e.unproject(pixels.astype(np.float64))
        p_event = bearings * (z / bearings[:, 2])[:, None]
        p_frame = calib.cam_from_cam(f"frame_{side}", f"event_{side}") @ p_event
        truth = fe.frame_rect.rectify_pixels(side, cam_f.project(p_frame))
        rect_e = fe.event_rect.rectify_pixels(side, pixels.astype(np.float64))
        rotation = (
            fe.event_rect.rect_left_from_left if side == "left" else fe.event_rect.rect_right_from_right
        )
        z_rect = (rotation @ p_event)[:, 2]
        ok = np.isfinite(truth).all(axis=1) & np.isfinite(rect_e).all(axis=1) & np.isfinite(z_rect) & (z > 0)
        if not ok.any():
            continue
        for name, d in (
            ("infinity", 0.0),
            ("tracked", depth_m),
            ("true median", float(np.median(z_rect[ok]))),
        ):
            warped = fe.warp_event_pixels(side, rect_e[ok], depth_m=d)
            out[name].extend(np.linalg.norm(warped - truth[ok], axis=1).tolist())
    return out


def _cost(sequence: Path, repeats: int, out: Path) -> list[str]:
    """What the tracked warp depth costs on ``sequence``: ``Frontend.finish`` (warp, β, blend)
    with the warp map cached against a depth that changes bin every call (the map rebuilt),
    and whole threaded ``fusion`` runs with ``warp_depth = "tracked"`` and ``"plane"``,
    interleaved so that other load on the machine hits both alike."""
    import time

    from dhptam import _core
    from dhptam.datasets import load_tumvie
    from dhptam.frontend import Frontend
    from dhptam.run import run

    lines = []
    with load_tumvie(sequence) as seq:
        fe = Frontend(seq, "fusion", prefetch=0)
        prepared = fe.prepare(10)
        step = fe.warp_depth_step_px / fe.warp_parallax_px
        # Three bins in turn: six (depth, side) maps, more than the binding's cache keeps (4).
        bins = [1.0 / (b * step) for b in (4, 5, 6)]
        far = bins[0]
        fe.finish(prepared, far)
        timings: dict[str, list[float]] = {
            "same depth (map cached)": [],
            "new bin every call (map rebuilt)": [],
        }
        for i in range(repeats):
            for name, depth in (
                ("same depth (map cached)", far),
                ("new bin every call (map rebuilt)", bins[1 + i % 2]),
            ):
                if name.startswith("same"):
                    fe.finish(prepared, far)  # make sure the cached map is the one used
                t0 = time.perf_counter()
                fe.finish(prepared, depth)
                timings[name].append(time.perf_counter() - t0)
        size = f"{fe.frame_rect.width}×{fe.frame_rect.height}"
        for name, v in timings.items():
            lines.append(
                f"| {sequence.name} ({size}) | `Frontend.finish`, {name} | {1e3 * np.median(v):.2f} ms |"
            )
    fps: dict[str, list[float]] = {"tracked": [], "plane": []}
    for i in range(repeats // 10 or 1):
        for warp in ("tracked", "plane"):
            config = _core.Config.from_toml(f'[fusion]\nwarp_depth = "{warp}"')
            r = run(sequence, out / f"cost-{warp}-{i}", mode="fusion", config=config, progress=False)
            fps[warp].append(r.fps)
    for warp, v in fps.items():
        lines.append(
            f'| {sequence.name} | threaded `dhptam run`, `warp_depth = "{warp}"` | '
            f"{np.median(v):.1f} fps (runs: {', '.join(f'{x:.1f}' for x in v)}) |"
        )
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--normal-duration", type=float, default=4.0)
    parser.add_argument("--normal-seed", type=int, default=1)
    parser.add_argument("--demo-seeds", default="0", help="demo seeds, comma-separated ('' for none)")
    parser.add_argument("--step", type=int, default=5, help="every this many frames (default 5)")
    parser.add_argument("--max-pixels", type=int, default=3000, help="event pixels per window and side")
    parser.add_argument("--out", type=Path, default=Path("bench-warp-depth"))
    parser.add_argument(
        "--cost",
        type=int,
        default=0,
        metavar="N",
        help="instead: time the warp with and without a map rebuild (N calls each) and N/10 "
        "interleaved threaded runs per setting on the demo sequence of the first --demo-seeds",
    )
    args = parser.parse_args()

    from dhptam.datasets import load_tumvie
    from dhptam.demo import cache_dir, demo_sequence
    from dhptam.frontend import Frontend
    from dhptam.sim import simulator_for

    if args.cost > 0:
        seed = int(args.demo_seeds.split(",")[0] or 0)
        lines = [
            f"{platform.node()}, {os.cpu_count()} CPUs.",
            "",
            "| sequence | what | median |",
            "|---|---|---|",
            *_cost(demo_sequence(seed=seed, progress=False), args.cost, args.out),
        ]
        return finish_table(lines, args.out)
    root = Path(os.environ.get("DHPTAM_SHARED", REPO.parent / "shared")) / "data" / "trajectories"
    jobs: list[tuple[str, Path, Any]] = []
    normal = cache_dir() / "sequences" / f"normal-seed{args.normal_seed}-{args.normal_duration:g}s"
    for path in sorted(p for p in root.iterdir() if p.suffix in (".csv", ".tum", ".txt")):
        if (normal / path.stem).is_dir():
            sim = simulator_for(
                "desk", seed=args.normal_seed, duration_s=args.normal_duration, trajectory=str(path)
            )
            jobs.append((f"normal {args.normal_duration:g} s {path.stem}", normal / path.stem, sim))
    for seed in (int(s) for s in args.demo_seeds.split(",") if s):
        jobs.append(
            (
                f"demo seed {seed}",
                demo_sequence(seed=seed, progress=False),
                simulator_for("demo", seed=seed),
            )
        )

    lines = [
        f"Event pixels of every {args.step}th window (≤ {args.max_pixels} per side), pixel distance "
        f"to the truth in the rectified frame camera; {platform.node()}, {os.cpu_count()} CPUs.",
        "",
        "| sequence | frames | warp depth used [m] (median, range) | true median depth [m] | event pixels "
        "| infinity: median / p90 [px] | tracked: median / p90 [px] | true-median plane: median / p90 [px] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, sequence, sim in jobs:
        print(f"{name}: tracked-depth run", file=sys.stderr)
        depths = _warp_depths(sequence, args.out / name.replace(" ", "-"))
        pooled: dict[str, list[float]] = {"infinity": [], "tracked": [], "true median": []}
        used, true_depths, frames = [], [], 0
        with load_tumvie(sequence) as seq:
            fe = Frontend(seq, "fusion", prefetch=0)
            for k in range(1, len(fe), args.step):
                if k not in depths:
                    continue
                d = _distances(seq, fe, sim, k, depths[k], args.max_pixels)
                if not d["tracked"]:
                    continue
                frames += 1
                used.append(depths[k])
                for key, v in d.items():
                    pooled[key].extend(v)
                z = sim.render_depth(2, int(fe.t_f_ns[k]))
                true_depths.append(float(np.nanmedian(z[np.isfinite(z) & (z > 0)])))

        def cell(v: list[float]) -> str:
            return f"{np.median(v):.2f} / {np.percentile(v, 90):.2f}"

        shown = [u for u in used if u > 0]
        lines.append(
            f"| {name} | {frames} | {np.median(used):.2f} ({min(used):.2f}–{max(used):.2f}; "
            f"{len(used) - len(shown)} at infinity) | {np.median(true_depths):.2f} "
            f"| {len(pooled['tracked'])} | {cell(pooled['infinity'])} | {cell(pooled['tracked'])} "
            f"| {cell(pooled['true median'])} |"
        )
        print(lines[-1], file=sys.stderr)
    return finish_table(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
