"""Accuracy on the default HDR demo sequence, per mode, seed and back-end mode (issue #8).

For every ``--seeds`` the ``demo`` preset is simulated once into the dhptam cache (``dhptam
demo`` reuses the same files), then dhptam runs in every mode, threaded and/or synchronous,
and is evaluated against the simulator's ground truth (evo, SE(3) alignment, left frame
camera). ``--bridge both`` also runs ``fusion`` with ``[fusion] bridge = false``, to measure
the bridge keyframes against new map segments; ``--flood both`` also runs ``fusion`` and
``events`` with ``[fusion] flood_predict = false`` (flood frames tracked like any other),
to measure the prediction across illumination floods; ``--flood-frames both`` also runs
``fusion`` with ``[fusion] flood_frames = false`` (every flood frame predicted, also those
leaving a DVS-biased segment with good frames, and the first clean frame after them blended
with its events). Prints a Markdown table (with the error per lighting level, the bridges,
new map segments and relocalisations of each run) and writes the runs under ``--out``.

    python benches/bench_accuracy_demo.py [--seeds 0,2] [--modes fusion,frames,events]
        [--backend threaded,sync] [--bridge on|off|both] [--flood on|off|both]
        [--flood-frames on|off|both]
        [--warp-depth plane|tracked|both] [--keypoint-sigma octave|unit]
        [--out bench-accuracy-demo]

``--warp-depth both`` runs the event modes with ``[fusion] warp_depth = "tracked"`` and
``"plane"`` (the default) in the same invocation.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

from _accuracy import (
    add_config_option,
    bench_config,
    choices,
    evaluated_run,
    finish_table,
    keypoint_sigma_toml,
)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", default="0,2", help="simulator seeds, comma-separated (default 0,2)")
    parser.add_argument("--modes", default="fusion,frames,events")
    parser.add_argument("--backend", default="threaded,sync", help="threaded and/or sync")
    parser.add_argument("--bridge", choices=("on", "off", "both"), default="on")
    parser.add_argument("--flood", choices=("on", "off", "both"), default="on", help="flood_predict")
    parser.add_argument(
        "--flood-frames", choices=("on", "off", "both"), default="on", help="[fusion] flood_frames"
    )
    parser.add_argument("--features", default="orb")
    parser.add_argument(
        "--warp-depth", choices=("tracked", "plane", "both"), default="plane", help="[fusion] warp_depth"
    )
    parser.add_argument(
        "--keypoint-sigma",
        choices=("octave", "unit"),
        default=None,
        help="[tracking] keypoint_sigma (default: the configuration's)",
    )
    parser.add_argument("--out", type=Path, default=Path("bench-accuracy-demo"))
    add_config_option(parser)
    args = parser.parse_args()

    from dhptam.demo import GROUND_TRUTH, demo_sequence, lighting_of
    from dhptam.eval import errors_by_segment, load_trajectory
    from dhptam.run import MODES

    modes = choices(parser, args.modes, MODES, "mode")
    backends = choices(parser, args.backend, ("threaded", "sync"), "back-end")
    bridges = {"on": [True], "off": [False], "both": [True, False]}[args.bridge]
    floods = {"on": [True], "off": [False], "both": [True, False]}[args.flood]
    flood_frames = {"on": [True], "off": [False], "both": [True, False]}[args.flood_frames]
    warps = {"tracked": ["tracked"], "plane": ["plane"], "both": ["tracked", "plane"]}[args.warp_depth]
    lines = [
        f"`demo` preset (HDR desk spiral, 4 s, 80 frames), features {args.features}, "
        f"keypoint σ {args.keypoint_sigma or 'default'}; "
        f"{platform.node()}, {os.cpu_count()} CPUs.",
        "",
        "| seed | mode | bridge | flood predict | flood frames | warp depth | back-end | frames | tracked "
        "| predicted | ATE RMSE [m] | ATE [% of path] | normal / dark / bright light [mm] "
        "| bridges | new segments | relocalisations |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for seed in (int(s) for s in args.seeds.split(",") if s):
        sequence = demo_sequence(seed=seed, progress=False)
        reference = load_trajectory(sequence / GROUND_TRUTH)
        lighting = lighting_of(sequence, "demo", reference)
        for mode in modes:
            variants = [
                (bridge, flood, frames_across, warp)
                for bridge in (bridges if mode == "fusion" else [True])
                for flood in (floods if mode != "frames" else [True])
                for frames_across in (flood_frames if mode == "fusion" and flood else [True])
                for warp in (warps if mode != "frames" else warps[:1])
            ]
            for bridge, flood, frames_across, warp in variants:
                config = bench_config(
                    args.config,
                    f"[fusion]\nbridge = {str(bridge).lower()}\nflood_predict = {str(flood).lower()}"
                    f"\nflood_frames = {str(frames_across).lower()}"
                    f'\nwarp_depth = "{warp}"' + keypoint_sigma_toml(args.keypoint_sigma),
                )
                for backend in backends:
                    tag = ("" if bridge else "-nobridge") + ("" if flood else "-noflood")
                    tag += "" if frames_across else "-nofloodframes"
                    tag += f"-{warp}" if len(warps) > 1 else ""
                    out = args.out / f"seed{seed}" / f"{mode}{tag}-{backend}"
                    result, ev = evaluated_run(
                        sequence, out, reference, mode=mode, features=args.features, config=config,
                        threaded=backend == "threaded",
                    )  # fmt: skip
                    t = result.tracking
                    parts = errors_by_segment(ev, lighting).values()
                    by_light = " / ".join(f"{1000 * p.rmse_m:.1f}" if p.poses else "–" for p in parts)
                    shown = ("on" if bridge else "off") if mode == "fusion" else "–"
                    shown_flood = ("on" if flood else "off") if mode != "frames" else "–"
                    shown_frames = ("on" if frames_across else "off") if mode == "fusion" and flood else "–"
                    shown_warp = warp if mode != "frames" else "–"
                    lines.append(
                        f"| {seed} | {mode} | {shown} | {shown_flood} | {shown_frames} | {shown_warp} "
                        f"| {backend} | {result.frames} "
                        f"| {result.tracked} | {t.get('predicted', 0)} "
                        f"| {ev.ate_rmse_m:.4f} | {ev.ate_percent_of_path:.2f} | {by_light} "
                        f"| {t.get('bridges', 0)} "
                        f"| {t.get('segments', 0)} | {t.get('relocalisations', 0)} |"
                    )
                    print(lines[-1], file=sys.stderr)
    return finish_table(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
