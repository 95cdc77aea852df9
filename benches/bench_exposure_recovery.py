"""Exposure recovery on and off: dark and saturated frames stretched before β (issue #8).

Runs dhptam twice on each sequence, with the default ``[fusion] recover_exposure = true`` and
with it off, in the modes that use frames (``--modes``, default ``fusion,frames``), and prints
one Markdown table with both runs side by side. The sequences, each simulated once into the
dhptam cache (``$DHPTAM_CACHE_DIR`` or ``~/.cache/dhptam``) and reused:

- the HDR demo sequence, ``--demo-seeds`` (default 0-5; ``sequences/seed<S>/demo``, the
  cache of ``dhptam demo`` and ``bench_accuracy_demo.py``);
- the ``dark`` and ``desk-flicker`` presets, ``--preset-seed`` (3), first 4 s
  (``sequences/presets-seed<S>-4s``, the cache of ``bench_accuracy_presets.py``);
- the ``dark`` preset again with a noisier frame sensor, ``[sim] read_noise_e`` set to each of
  ``--read-noise`` (default 250,600 electrons against the default 5; ``sequences/
  presets-seed<S>-4s-read-noise-<N>/dark``): frames whose range holds fewer than ``[fusion]
  recover_min_snr`` noise deviations must be left as they are. These rows also run with that
  guard off (``recover_min_snr = 0``: every failed frame stretched), to show what it prevents.

Every run is synchronous (deterministic) and evaluated against the simulator's ground truth
(evo, SE(3) alignment, left frame camera); ``stretched`` counts the frames of the run that were
stretched (left camera). Writes the runs and ``report.md`` under ``--out``.

    python benches/bench_exposure_recovery.py [--demo-seeds 0,1,2,3,4,5] [--preset-seed 3]
        [--read-noise 250,600] [--modes fusion,frames] [--features orb] [--out bench-exposure]
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import sys
from pathlib import Path
from typing import Any

from _accuracy import add_config_option, bench_config, choices, evaluated_run, finish_table

DURATION_S = 4.0


def _sequences(args: argparse.Namespace) -> list[tuple[str, Path]]:
    """``(name, folder)`` of every sequence, simulated into the cache when missing."""
    from dhptam import _core
    from dhptam.demo import GROUND_TRUTH, cache_dir, demo_sequence
    from dhptam.sim import simulate

    out = [(f"demo seed {s}", demo_sequence(seed=s, progress=False)) for s in args.demo_seeds]
    presets = cache_dir() / "sequences" / f"presets-seed{args.preset_seed}-{DURATION_S:g}s"
    for preset in ("dark", "desk-flicker"):
        if not (presets / preset / GROUND_TRUTH).is_file():
            print(f"simulating {preset} into {presets} (once; cached)", file=sys.stderr)
            simulate(presets, preset=preset, seed=args.preset_seed, duration_s=DURATION_S, overwrite=True)
        out.append((preset, presets / preset))
    for noise in args.read_noise:
        root = Path(f"{presets}-read-noise-{noise:g}")
        if not (root / "dark" / GROUND_TRUTH).is_file():
            print(f"simulating dark, read noise {noise:g} e-, into {root} (once; cached)", file=sys.stderr)
            sensor = _core.Config.from_toml(f"[sim]\nread_noise_e = {noise!r}\n", "<bench>")
            simulate(
                root,
                preset="dark",
                seed=args.preset_seed,
                duration_s=DURATION_S,
                config=sensor,
                overwrite=True,
            )
        out.append((f"dark, read noise {noise:g} e-", root / "dark"))
    return out


def _is_noisy(sequence: Path) -> bool:
    """A sequence of the noisy-sensor rows (the guard's third column is run on them)."""
    return "-read-noise-" in sequence.parent.name


def _cell(result: Any, ev: Any, out: Path) -> str:
    """``ATE % (tracked/frames, stretched N)`` of one run; a dash for a run without poses."""
    with (out / "frames.csv").open() as f:
        stretched = sum(int(r["stretched"]) > 0 for r in csv.DictReader(f))
    tracked = f"{result.tracked}/{result.frames}"
    if ev is None:
        return f"– ({tracked}, stretched {stretched})"
    return f"{ev.ate_percent_of_path:.2f} ({tracked}, stretched {stretched})"


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--demo-seeds", default="0,1,2,3,4,5", help="demo seeds (default 0-5)")
    parser.add_argument("--preset-seed", type=int, default=3, help="seed of the presets (default 3)")
    parser.add_argument("--read-noise", default="250,600", help="read noise of the noisy dark runs, e-")
    parser.add_argument("--modes", default="fusion,frames")
    parser.add_argument("--features", default="orb", help="orb, sift, r2d2 or superpoint (default orb)")
    parser.add_argument("--out", type=Path, default=Path("bench-exposure"))
    add_config_option(parser)
    args = parser.parse_args()
    args.demo_seeds = [int(s) for s in args.demo_seeds.split(",") if s]
    args.read_noise = [float(s) for s in args.read_noise.split(",") if s]

    from dhptam.demo import GROUND_TRUTH
    from dhptam.eval import load_trajectory
    from dhptam.run import MODES

    modes = choices(parser, args.modes, MODES, "mode")
    settings = {
        "on": "recover_exposure = true",
        "off": "recover_exposure = false",
        "unguarded": "recover_exposure = true\nrecover_min_snr = 0.0",
    }
    lines = [
        f"Features {args.features}, configuration {args.config or 'default'}, synchronous runs; "
        f"{platform.node()}, {os.cpu_count()} CPUs. Cells: ATE % of the path (tracked frames, "
        "frames stretched).",
        "",
        "| sequence | mode | recovery on (default) | recovery off | on, no noise guard "
        "(`recover_min_snr = 0`; noisy sensors only) |",
        "|---|---|---|---|---|",
    ]
    for name, sequence in _sequences(args):
        reference = load_trajectory(sequence / GROUND_TRUTH)
        for mode in modes:
            cells = []
            for key, toml in settings.items():
                if key == "unguarded" and not _is_noisy(sequence):
                    cells.append("not run")
                    continue
                out = args.out / sequence.parent.name / sequence.name / f"{mode}-{key}"
                result, ev = evaluated_run(
                    sequence,
                    out,
                    reference,
                    mode=mode,
                    features=args.features,
                    config=bench_config(args.config, f"[fusion]\n{toml}\n"),
                    threaded=False,
                )
                cells.append(_cell(result, ev, out))
            row = f"| {name} | {mode} | {' | '.join(cells)} |"
            print(row, file=sys.stderr)
            lines.append(row)
    return finish_table(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
