"""Accuracy across the simulator's presets: lighting, motion, rig and lens models (issue #8).

The defaults must hold on data they were not tuned on. This bench runs dhptam with its default
configuration in every mode on the first ``--duration`` seconds of each simulator preset named
in ``--presets``: normal light (``desk``), radial-tangential frame lenses with pinhole event
lenses (``desk-mixed``), a 40× darker room (``dark``), exposure flicker (``desk-flicker``),
back-and-forth translation (``1d-trans``), fast six-degree-of-freedom shaking (``6dof``) and a
closed loop around the room (``loop``). Each sequence is simulated once into the dhptam cache
(``$DHPTAM_CACHE_DIR`` or ``~/.cache/dhptam``, under ``sequences/presets-seed<S>-<D>s/``) and
reused; every run is evaluated against the simulator's ground truth (evo, SE(3) alignment, left
frame camera). Prints a Markdown table for docs/BENCHMARKS.md (and, for presets lit at
several levels, each run's error per lighting level) and writes the runs, ``eval.json`` files
and ``report.md`` under ``--out``.

    python benches/bench_accuracy_presets.py [--presets desk,dark,...] [--duration 4]
        [--seed 3] [--modes fusion,frames,events] [--features orb] [--out bench-presets] [--sync]
        [--keypoint-sigma octave|unit]

``--keypoint-sigma octave|unit`` overrides ``[tracking] keypoint_sigma`` (before/after tables).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

from _accuracy import (
    TABLE_HEAD,
    add_config_option,
    bench_config,
    choices,
    evaluated_run,
    finish_table,
    keypoint_sigma_toml,
    table_row,
)

DEFAULT_PRESETS = "desk,desk-mixed,dark,desk-flicker,1d-trans,6dof,loop"


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--presets", default=DEFAULT_PRESETS, help=f"default {DEFAULT_PRESETS}")
    parser.add_argument("--duration", type=float, default=4.0, help="seconds of each preset (default 4)")
    parser.add_argument("--seed", type=int, default=3, help="simulator seed (default 3)")
    parser.add_argument("--modes", default="fusion,frames,events")
    parser.add_argument("--features", default="orb", help="orb, sift, r2d2 or superpoint (default orb)")
    parser.add_argument("--out", type=Path, default=Path("bench-presets"))
    add_config_option(parser)
    parser.add_argument("--sync", action="store_true", help="mapping inline (deterministic runs)")
    parser.add_argument(
        "--keypoint-sigma",
        choices=("octave", "unit"),
        default=None,
        help="[tracking] keypoint_sigma (default: the configuration's)",
    )
    args = parser.parse_args()

    from dhptam.demo import GROUND_TRUTH, cache_dir, lighting_of
    from dhptam.eval import errors_by_segment, load_trajectory
    from dhptam.run import MODES
    from dhptam.sim import PRESETS, simulate

    modes = choices(parser, args.modes, MODES, "mode")
    presets = choices(parser, args.presets, PRESETS, "preset")

    root = cache_dir() / "sequences" / f"presets-seed{args.seed}-{args.duration:g}s"
    lines = [
        f"Sequences: first {args.duration:g} s of each preset, seed {args.seed}, features "
        f"{args.features}, configuration {args.config or 'default'}, "
        f"keypoint σ {args.keypoint_sigma or 'default'}; "
        f"{'synchronous' if args.sync else 'threaded'} mapping; "
        f"{platform.node()}, {os.cpu_count()} CPUs.",
        "",
        *TABLE_HEAD,
    ]
    config = bench_config(args.config, keypoint_sigma_toml(args.keypoint_sigma))
    # Presets lit at several levels (hdr): each run's ATE per level, in a second table.
    by_light = [
        "",
        "ATE RMSE [mm] per lighting level (presets lit at several levels; the whole run's alignment):",
        "",
        "| sequence | mode | normal | dark | bright |",
        "|---|---|---|---|---|",
    ]
    split = False
    for preset in presets:
        sequence = root / preset
        if not (sequence / GROUND_TRUTH).is_file():
            print(f"simulating {preset} into {sequence} (once; cached)", file=sys.stderr)
            simulate(root, preset=preset, seed=args.seed, duration_s=args.duration, overwrite=True)
        reference = load_trajectory(sequence / GROUND_TRUTH)
        for mode in modes:
            result, ev = evaluated_run(
                sequence,
                args.out / preset / mode,
                reference,
                mode=mode,
                features=args.features,
                config=config,
                threaded=not args.sync,
            )
            lines.append(table_row(preset, mode, result, ev))
            lighting = lighting_of(sequence, preset, reference)
            if lighting and ev is not None:
                parts = errors_by_segment(ev, lighting)
                cells = [
                    f"{1000 * parts[k].rmse_m:.1f}" if k in parts and parts[k].poses else "–"
                    for k in ("normal", "dark", "bright")
                ]
                by_light.append(f"| {preset} | {mode} | " + " | ".join(cells) + " |")
                split = True
    return finish_table(lines + (by_light if split else []), args.out)


if __name__ == "__main__":
    raise SystemExit(main())
