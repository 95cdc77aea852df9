"""Accuracy on simulator sequences driven by real trajectories (issue #8).

For every trajectory file (``*.csv`` / ``*.tum``) of the folder ``--trajectories`` (default:
``$DHPTAM_SHARED/data/trajectories``, else ``../shared/data/trajectories`` beside the
repository) the simulator renders the first ``--duration`` seconds of the trajectory (all of
it when the file is shorter: ``--duration 60`` simulates both shipped trajectories whole), fitted
into the desk room, with the small rig (320×320 frames, 320×180 events) under normal lighting
(the ``desk`` preset with the file's motion; ``--preset tumvie-desk`` for the TUM-VIE-size rig,
1024×1024 frames and 1280×720 events). ``--lighting hdr`` lights the same motion like the HDR
demo instead (normal, dark, normal, saturated, normal, stretched over the duration, with the
lighting floods between: the ``demo`` preset, or ``tumvie-hdr`` with ``--preset tumvie-desk``),
and the table also gives each run's error per lighting level. Each sequence is generated once
into the dhptam cache (``$DHPTAM_CACHE_DIR`` or ``~/.cache/dhptam``, under
``sequences/<lighting>-seed<S>-<D>s/``, or ``sequences/<lighting>-<preset>-seed<S>-<D>s/`` for
another preset) and reused. dhptam then runs on it in every mode and is evaluated against the
simulator's ground truth (evo, SE(3) alignment, left frame camera). Prints a Markdown table for
docs/BENCHMARKS.md and writes the runs, ``eval.json`` files and ``report.md`` under ``--out``.

    python benches/bench_accuracy_normal.py [--duration 4] [--seed 1] [--modes fusion,frames,events]
        [--features orb] [--preset desk|tumvie-desk] [--lighting normal|hdr]
        [--out bench-accuracy] [--sync] [--warp-depth plane|tracked|both]
        [--keypoint-sigma octave|unit] [--pause START:DURATION]

``--pause START:DURATION`` holds the camera still over that span of every sequence (the
simulator's ``pause``: the motion goes on after it, the sequence keeps its duration), for
stop-and-go runs: an event camera at rest sees only its noise.

``--warp-depth both`` runs the event modes with ``[fusion] warp_depth = "tracked"`` and
``"plane"`` in the same invocation (before/after figures from one run of the same code); the
default is the configuration's default, ``plane``.
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

REPO = Path(__file__).resolve().parents[1]


def default_trajectories() -> Path:
    """``$DHPTAM_SHARED/data/trajectories``, else ``../shared/data/trajectories``."""
    root = Path(os.environ.get("DHPTAM_SHARED", REPO.parent / "shared"))
    return root / "data" / "trajectories"


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--trajectories", type=Path, default=default_trajectories())
    parser.add_argument(
        "--duration",
        type=float,
        default=4.0,
        help="seconds of each trajectory (default 4; a trajectory shorter than this is simulated whole)",
    )
    parser.add_argument("--seed", type=int, default=1, help="simulator seed (default 1)")
    parser.add_argument(
        "--preset",
        choices=("desk", "tumvie-desk"),
        default="desk",
        help="rig: desk (320-pixel, default) or tumvie-desk (TUM-VIE size)",
    )
    parser.add_argument(
        "--lighting",
        choices=("normal", "hdr"),
        default="normal",
        help="normal (default) or hdr: the HDR demo's lighting profile over the duration",
    )
    parser.add_argument(
        "--pause",
        metavar="START:DURATION",
        default=None,
        help="hold the camera still over this span in seconds (stop-and-go; default none)",
    )
    parser.add_argument("--modes", default="fusion,frames,events")
    parser.add_argument("--features", default="orb", help="orb, sift, r2d2 or superpoint (default orb)")
    parser.add_argument("--out", type=Path, default=Path("bench-accuracy"))
    add_config_option(parser)
    parser.add_argument("--sync", action="store_true", help="mapping inline (deterministic runs)")
    parser.add_argument(
        "--warp-depth",
        default="plane",
        help='[fusion] warp_depth: "tracked", "plane" or "both" (the two in the same run)',
    )
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
    from dhptam.sim import simulate

    modes = choices(parser, args.modes, MODES, "mode")
    warps = choices(
        parser, args.warp_depth.replace("both", "tracked,plane"), ("tracked", "plane"), "warp depth"
    )
    if not args.trajectories.is_dir():
        parser.error(f"trajectory folder {args.trajectories} does not exist (set DHPTAM_SHARED)")
    files = sorted(p for p in args.trajectories.iterdir() if p.suffix in (".csv", ".tum", ".txt"))
    if not files:
        parser.error(f"no .csv/.tum/.txt trajectory in {args.trajectories}")

    pause = None
    if args.pause is not None:
        try:
            pause = tuple(float(v) for v in args.pause.split(":"))
        except ValueError:
            parser.error(f"--pause expects START:DURATION in seconds, got {args.pause!r}")
        if len(pause) != 2:
            parser.error(f"--pause expects START:DURATION in seconds, got {args.pause!r}")
    kind = "" if args.preset == "desk" else f"{args.preset}-"
    paused = "" if pause is None else f"-pause{pause[0]:g}+{pause[1]:g}"
    root = cache_dir() / "sequences" / f"{args.lighting}-{kind}seed{args.seed}-{args.duration:g}s{paused}"
    hdr = args.lighting == "hdr"
    preset = {"desk": "demo", "tumvie-desk": "tumvie-hdr"}[args.preset] if hdr else args.preset
    head = TABLE_HEAD
    if hdr:
        head = [TABLE_HEAD[0] + " normal / dark / bright light [mm] |", TABLE_HEAD[1] + "---|"]
    lines = [
        f"Sequences: first {args.duration:g} s of each trajectory (all of it where it is shorter), "
        + ("" if pause is None else f"the camera still for {pause[1]:g} s from {pause[0]:g} s, ")
        + f"`{preset}` preset ({args.lighting} "
        f"lighting), seed {args.seed}, features {args.features}, "
        f"configuration {args.config or 'default'}, "
        f"keypoint σ {args.keypoint_sigma or 'default'}; "
        f"{'synchronous' if args.sync else 'threaded'} mapping; "
        f"{platform.node()}, {os.cpu_count()} CPUs.",
        "",
        *head,
    ]
    for path in files:
        name = path.stem
        sequence = root / name
        if not (sequence / GROUND_TRUTH).is_file():
            print(f"simulating {name} into {sequence} (once; cached)", file=sys.stderr)
            simulate(
                root,
                preset=preset,
                name=name,
                seed=args.seed,
                duration_s=args.duration,
                trajectory=str(path),
                overwrite=True,
                pause=pause,
            )
        reference = load_trajectory(sequence / GROUND_TRUTH)
        lighting = lighting_of(sequence, preset, reference) if hdr else []
        for mode in modes:
            # The warp depth only matters where events are warped.
            for warp in warps if mode != "frames" else warps[:1]:
                config = bench_config(
                    args.config, f'[fusion]\nwarp_depth = "{warp}"' + keypoint_sigma_toml(args.keypoint_sigma)
                )
                compared = len(warps) > 1 and mode != "frames"
                out = args.out / name / (f"{mode}-{warp}" if compared else mode)
                result, ev = evaluated_run(
                    sequence,
                    out,
                    reference,
                    mode=mode,
                    features=args.features,
                    config=config,
                    threaded=not args.sync,
                )
                row = table_row(f"{name}, warp {warp}" if compared else name, mode, result, ev)
                if hdr:
                    parts = errors_by_segment(ev, lighting).values() if ev is not None else []
                    split = " / ".join(f"{1000 * p.rmse_m:.1f}" if p.poses else "–" for p in parts)
                    row += f" {split or '–'} |"
                lines.append(row)
    return finish_table(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
