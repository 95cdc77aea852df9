"""Hot pixels: what they cost the event modes, and what the detector gives back.

The demo's HDR desk sequence (``demo`` preset, 4 s) is simulated with a fraction of each event
camera's pixels hot (``dhptam simulate --hot-pixels``: each fires on its own, periodically, at
20 Hz to 2 kHz), once per seed and fraction, into the dhptam cache (``$DHPTAM_CACHE_DIR`` or
``~/.cache/dhptam``, under ``sequences/hot-<fraction>-seed<S>/``). dhptam then runs on it in
the event modes with the hot-pixel detector on (the default ``[events] hot_pixel_ratio``) and
off (``hot_pixel_ratio = 0``), ``--sync`` unless ``--threaded``, and each run is evaluated
against the simulator's ground truth (evo, SE(3), left frame camera). ``frames`` does not read
events and is left out. Prints a Markdown table for docs/BENCHMARKS.md and writes the runs
and ``report.md`` under ``--out``.

    python benches/bench_hot_pixels.py [--seeds 0,1,2] [--fractions 0.003,0.01]
        [--modes fusion,events] [--features orb] [--out bench-hot-pixels] [--threaded]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

from _accuracy import add_config_option, bench_config, choices, evaluated_run, finish_table


def hot_sequence(seed: int, fraction: float) -> Path:
    """The demo sequence with ``fraction`` hot pixels, simulated once into the cache."""
    from dhptam.demo import cache_dir
    from dhptam.sim import simulate

    parent = cache_dir() / "sequences" / f"hot-{fraction:g}-seed{seed}"
    path = parent / "demo"
    if not (path / "groundtruth_frame_left.txt").exists():
        print(f"simulating {path} ...", file=sys.stderr)
        simulate(parent, preset="demo", seed=seed, hot_pixels=fraction, overwrite=True, progress=True)
    return path


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", default="0,1,2", help="simulator seeds (default 0,1,2)")
    parser.add_argument("--fractions", default="0.003,0.01", help="hot fractions of the pixels")
    parser.add_argument("--modes", default="fusion,events", help="fusion and/or events")
    parser.add_argument("--features", default="orb")
    parser.add_argument("--out", type=Path, default=Path("bench-hot-pixels"))
    parser.add_argument("--threaded", action="store_true", help="threaded back-end (default: --sync)")
    add_config_option(parser)
    args = parser.parse_args()

    from dhptam.demo import GROUND_TRUTH
    from dhptam.eval import load_trajectory

    modes = choices(parser, args.modes, ("fusion", "events"), "mode")
    lines = [
        f"`demo` preset with hot pixels, features {args.features}, "
        f"{'threaded' if args.threaded else 'sync'}; {platform.node()}, {os.cpu_count()} CPUs.",
        "",
        "| seed | hot fraction | mode | detector | tracked | predicted | hot pixels masked (last frame) "
        "| ATE RMSE [m] | ATE [% of path] | new segments |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for seed in (int(s) for s in args.seeds.split(",") if s):
        for fraction in (float(f) for f in args.fractions.split(",") if f):
            sequence = hot_sequence(seed, fraction)
            reference = load_trajectory(sequence / GROUND_TRUTH)
            for mode in modes:
                for detector in ("on", "off"):
                    config = bench_config(
                        args.config, "" if detector == "on" else "[events]\nhot_pixel_ratio = 0.0"
                    )
                    out = args.out / f"hot-{fraction:g}-seed{seed}" / f"{mode}-{detector}"
                    result, ev = evaluated_run(
                        sequence, out, reference, mode=mode, features=args.features, config=config,
                        threaded=args.threaded,
                    )  # fmt: skip
                    rows = (out / "frames.csv").read_text().splitlines()
                    masked = (
                        rows[-1].split(",")[rows[0].split(",").index("hot_pixels")] if len(rows) > 1 else "–"
                    )
                    t = result.tracking
                    ate = "– | –" if ev is None else f"{ev.ate_rmse_m:.4f} | {ev.ate_percent_of_path:.2f}"
                    lines.append(
                        f"| {seed} | {fraction:g} | {mode} | {detector} "
                        f"| {result.tracked} of {result.frames} | {t.get('predicted', 0)} | {masked} | {ate} "
                        f"| {t.get('segments', 0)} |"
                    )
                    print(lines[-1], file=sys.stderr)
    return finish_table(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
