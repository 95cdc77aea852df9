"""The ``dhptam`` command.

Every subcommand listed by ``dhptam --help`` works; new ones arrive with the features they
drive. Exit codes: 0 on success, 2 for usage and input errors (bad arguments, files, values),
1 for anything unexpected.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from . import __version__, _core, logs
from .errors import DhptamError, InputError, InternalError

EXIT_USAGE = 2
EXIT_FAILURE = 1


def _config_command(args: argparse.Namespace) -> int:
    if args.check is not None:
        config = _core.Config.from_file(Path(args.check))
        sys.stdout.write(f"# {args.check}: valid; resolved configuration follows\n")
        sys.stdout.write(config.to_commented_toml())
    else:
        sys.stdout.write(_core.Config.defaults_toml())
    return 0


def _simulate_command(args: argparse.Namespace) -> int:
    from .sim import simulate

    config = _core.Config.from_file(Path(args.config)) if args.config else None
    summary = simulate(
        args.out,
        preset=args.preset,
        name=args.name,
        seed=args.seed,
        duration_s=args.duration,
        profile=args.profile,
        trajectory=args.trajectory,
        config=config,
        overwrite=args.overwrite,
        progress=not args.quiet,
        blackout=_span(args.blackout, "blackout"),
        shake=_span(args.shake, "shake"),
        hot_pixels=args.hot_pixels,
        pause=_span(args.pause, "pause"),
    )
    sys.stdout.write(
        f"{summary.path}: {summary.frames} frame pairs, {summary.events_left} + {summary.events_right} "
        f"events, {summary.duration_ns / 1e9:.2f} s simulated in {summary.seconds:.1f} s\n"
    )
    return 0


def _span(text: str | None, field: str) -> tuple[float, float] | None:
    """``START:DURATION`` in seconds."""
    if text is None:
        return None
    try:
        start, duration = (float(v) for v in text.split(":"))
    except ValueError:
        raise InputError(f"--{field} expects START:DURATION in seconds, got {text!r}", field=field) from None
    return start, duration


def _add_simulate_command(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from .sim.presets import DEFAULT_PRESET, MOTIONS, PRESETS, PROFILES, describe_presets

    simulate = sub.add_parser(
        "simulate",
        help="simulate a stereo events+frames sequence with ground truth (TUM-VIE layout)",
        description=(
            "Ray-cast a textured desk room for a TUM-VIE-like rig (stereo frames + stereo events) "
            "and write the sequence in the TUM-VIE layout with its ground truth."
        ),
        epilog="presets:\n" + describe_presets(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    simulate.add_argument("--preset", default=DEFAULT_PRESET, choices=list(PRESETS), help="what to simulate")
    simulate.add_argument("--out", required=True, metavar="DIR", help="parent folder of the sequence")
    simulate.add_argument("--name", help="sequence name (default: the preset's)")
    simulate.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    simulate.add_argument("--duration", type=float, metavar="S", help="duration in seconds")
    simulate.add_argument("--profile", choices=list(PROFILES), help="lighting profile")
    simulate.add_argument(
        "--trajectory",
        metavar="MOTION|FILE",
        help=f"built-in motion ({', '.join(MOTIONS)}) or a TUM/CSV trajectory file",
    )
    simulate.add_argument("--config", metavar="FILE", help="TOML configuration ([sim] section)")
    simulate.add_argument("--overwrite", action="store_true", help="replace an existing sequence")
    simulate.add_argument("--quiet", action="store_true", help="no progress bar")
    simulate.add_argument(
        "--blackout",
        metavar="START:DURATION",
        help="cover the lenses over this span in seconds: black frames, no events",
    )
    simulate.add_argument(
        "--shake", metavar="START:DURATION", help="add a violent hand shake over this span in seconds"
    )
    simulate.add_argument(
        "--pause",
        metavar="START:DURATION",
        help="hold the camera still from START for DURATION seconds, then go on along the motion",
    )
    simulate.add_argument(
        "--hot-pixels",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="fraction of each event camera's pixels that fire on their own, 20 Hz-2 kHz (default 0)",
    )
    simulate.set_defaults(func=_simulate_command)


def _solve_command(args: argparse.Namespace) -> int:
    import json

    from . import solver

    if args.problem == "bal":
        report = solver.solve_bal(
            Path(args.file),
            threads=args.threads,
            linear_solver=args.linear_solver,
            zero_behind_camera=args.zero_behind_camera,
            max_iterations=args.max_iterations,
            out=args.out,
        )
    else:
        report = solver.solve_pose_graph(
            Path(args.file), threads=args.threads, max_iterations=args.max_iterations, out=args.out
        )
    if args.json:
        sys.stdout.write(json.dumps(report.to_json_dict()) + "\n")
    else:
        sys.stdout.write(
            f"{args.file}: cost {report.initial_cost:.6e} -> {report.final_cost:.6e} in "
            f"{report.iterations} iterations, {report.seconds:.3f} s on {report.threads} thread(s) "
            f"({report.termination})\n"
        )
    return 0


def _add_solve_parser(sub: Any) -> None:
    solve = sub.add_parser(
        "solve",
        help="solve a bundle-adjustment (BAL) or pose-graph (g2o) problem file",
        description="Levenberg-Marquardt on a BAL problem or a g2o pose graph, reporting costs.",
    )
    kinds = solve.add_subparsers(dest="problem", metavar="PROBLEM", required=True)
    bal = kinds.add_parser("bal", help="bundle adjustment of a BAL problem-*.txt file")
    bal.add_argument(
        "--linear-solver", choices=["auto", "dense", "sparse"], default="auto", help="reduced camera system"
    )
    bal.add_argument(
        "--zero-behind-camera",
        action="store_true",
        help="drop residuals of points behind their camera (COLMAP's cost)",
    )
    graph = kinds.add_parser("pose-graph", help="optimise a g2o pose graph (SE3 or SE2)")
    outputs = ((bal, "write the optimised BAL problem here"), (graph, "write the optimised graph here"))
    for p, out_help in outputs:
        p.add_argument("file", metavar="FILE")
        p.add_argument("--threads", type=int, default=1, help="worker threads (0: all cores)")
        p.add_argument("--max-iterations", type=int, default=50, help="Levenberg-Marquardt iteration limit")
        p.add_argument("--out", metavar="OUT", help=out_help)
        p.add_argument("--json", action="store_true", help="print the report as one JSON object")
        p.set_defaults(func=_solve_command)


# -- dhptam eval (issue 8) ---------------------------------------------------------------------


def _eval_command(args: argparse.Namespace) -> int:
    from .eval import errors_by_segment, evaluate, load_trajectory, read_segments, run_suite, write_result

    if args.suite:
        table, _ = run_suite(args.suite, args.out)
        sys.stdout.write(table)
        sys.stdout.write(f"wrote {Path(args.out) / 'table.md'} and per-run results\n")
        return 0
    if not (args.estimate and args.reference):
        raise InputError("give --estimate and --reference, or --suite", field="estimate")
    estimate = load_trajectory(args.estimate, "tum")
    reference = load_trajectory(
        args.reference,
        args.reference_format,
        mocap_calibration=args.mocap_calibration,
        calibration=args.calibration,
    )
    # Read before the evaluation: a bad segments file fails before anything is written.
    spans = read_segments(args.segments) if args.segments else None
    result = evaluate(estimate, reference, align=args.align, rpe_delta=args.rpe_delta)
    parts = errors_by_segment(result, spans) if spans is not None else None
    paths = write_result(result, args.out, segments=parts)
    sys.stdout.write(
        f"ATE RMSE {result.ate_rmse_m:.4f} m "
        f"({result.ate_percent_of_path:.2f} % of {result.path_length_m:.2f} m), "
        f"RPE RMSE {result.rpe.get('rmse', float('nan')):.4f} m, coverage {100 * result.coverage:.1f} %, "
        f"{result.poses_matched}/{result.poses_estimate} poses, {args.align} alignment "
        f"by the {result.aligned_by} (scale {result.scale:.4f})\n"
    )
    for part in (parts or {}).values():
        figure = f"ATE RMSE {part.rmse_m:.4f} m over {part.poses} poses" if part.poses else "no pose"
        sys.stdout.write(f"  {part.label}: {figure}\n")
    sys.stdout.write(f"wrote {paths['json']}\n")
    return 0


def _add_eval_command(sub: Any) -> None:
    from .eval import ALIGNMENTS, REFERENCE_FORMATS

    ev = sub.add_parser(
        "eval",
        help="trajectory accuracy (evo APE/RPE, coverage) with JSON and plots",
        description=(
            "Evaluate an estimated TUM trajectory against a reference with evo: APE (ATE RMSE) and "
            "RPE after SE(3) or Sim(3) Umeyama alignment, coverage of the reference time span; "
            "writes eval.json and PNG plots into --out. With --suite, evaluates every run of a "
            "suite TOML and prints a markdown comparison table (also written to OUT/table.md)."
        ),
    )
    ev.add_argument("--estimate", metavar="FILE", help="estimated trajectory (TUM)")
    ev.add_argument(
        "--reference", metavar="FILE", help="reference trajectory (TUM, or TUM-VIE mocap_data.txt)"
    )
    ev.add_argument("--reference-format", choices=list(REFERENCE_FORMATS), default="tum")
    ev.add_argument("--mocap-calibration", metavar="FILE", help="mocap-imu-calibration*.json (tum-vie-mocap)")
    ev.add_argument("--calibration", metavar="FILE", help="camera-calibration*.json (tum-vie-mocap)")
    ev.add_argument(
        "--align", choices=list(ALIGNMENTS), default="se3", help="Umeyama alignment (default se3)"
    )
    ev.add_argument("--rpe-delta", type=int, default=1, metavar="FRAMES", help="RPE pose distance in frames")
    ev.add_argument(
        "--segments",
        metavar="FILE",
        help=(
            "labelled time spans (CSV lines 'label,start_s,end_s'; a simulated sequence's "
            "lighting.csv is one): also report the ATE RMSE over the poses of each label"
        ),
    )
    ev.add_argument("--suite", metavar="FILE", help="evaluate every run of a suite TOML instead")
    ev.add_argument("--out", required=True, metavar="DIR", help="output folder")
    ev.set_defaults(func=_eval_command)


# -- dhptam calibrate-align (issue 5) -------------------------------------------------------------


def _calibrate_align_command(args: argparse.Namespace) -> int:
    from .align import calibrate_align, write_align_config
    from .datasets import load_tumvie

    base = _core.Config.from_file(Path(args.config)) if args.config else None
    out = Path(args.out) if args.out else (Path(args.config) if args.config else None)
    if out is None:
        raise InputError("give --out FILE (or --config FILE to update it in place)", field="out")
    with load_tumvie(args.sequence, calibration=args.calibration) as sequence:
        estimate = calibrate_align(
            sequence,
            base,
            side=args.side,
            half_window_ms=args.half_window_ms,
            max_frames=args.max_frames,
            depth_compensation=not args.no_depth_compensation,
        )
    write_align_config(base, estimate.align_px, out)
    sys.stdout.write(
        f"δP_align ({args.side}) = [{estimate.align_px[0]:.3f}, {estimate.align_px[1]:.3f}] px "
        f"(was [{estimate.previous_px[0]:.3f}, {estimate.previous_px[1]:.3f}]; {estimate.inliers} of "
        f"{estimate.matches} matches agree, median spread {estimate.spread_px:.2f} px, "
        f"{estimate.frames_used} frames); wrote {out}\n"
    )
    return 0


def _add_calibrate_align_command(sub: Any) -> None:
    cal = sub.add_parser(
        "calibrate-align",
        help="estimate the event→frame offset δP_align from a sequence and write it to a config",
        description=(
            "Match warped event images against the frames of a sequence (patch correlation on "
            "well-exposed frames, parallax removed with StereoSGBM depth, RANSAC translation, "
            "median) and write [fusion] align_px into a configuration TOML."
        ),
    )
    cal.add_argument("--sequence", required=True, metavar="DIR", help="TUM-VIE sequence folder")
    cal.add_argument("--calibration", metavar="FILE", help="camera-calibration*.json (default: found)")
    cal.add_argument("--config", metavar="FILE", help="base configuration (updated in place without --out)")
    cal.add_argument("--out", metavar="FILE", help="configuration TOML to write")
    cal.add_argument("--side", choices=["left", "right"], default="left")
    cal.add_argument("--half-window-ms", type=float, default=10.0, help="events within ± this of each frame")
    cal.add_argument("--max-frames", type=int, help="use at most this many frames, spread evenly")
    cal.add_argument("--no-depth-compensation", action="store_true", help="skip the SGBM parallax removal")
    cal.set_defaults(func=_calibrate_align_command)


# -- dhptam run / demo (issue 8) ---------------------------------------------------------------


def _run_command(args: argparse.Namespace) -> int:
    from .run import run

    result = run(
        args.sequence,
        args.out,
        fmt=args.format,
        calibration=args.calibration,
        mode=args.mode,
        features=args.features,
        weights=args.weights,
        config=args.config,
        realtime=args.realtime,
        progress=not args.quiet,
        max_frames=args.max_frames,
        threaded=not args.sync,
        trajectory_formats=tuple(args.trajectory_format or ()),
        viz=args.viz,
        record=args.record,
        record_frames=args.record_frames,
    )
    states = ", ".join(f"{n} {s}" for s, n in sorted(result.states.items()))
    tracking = result.tracking
    sys.stdout.write(
        f"{result.out}: {result.frames} frames ({states}) in {result.seconds:.1f} s ({result.fps:.1f} fps), "
        f"{result.keyframes} keyframes, {result.map_points} map points, {result.loop_closures} loop closures"
        # Issue 8 (accuracy): how the map stayed in one piece across fusion-mode switches.
        + f", {tracking.get('bridges', 0)} bridge keyframes, {tracking.get('segments', 0)} new map segments"
        + (" [interrupted]" if result.interrupted else "")
        + "\n"
    )
    return 130 if result.interrupted else 0


def _add_run_command(sub: Any) -> None:
    from .run import FEATURES, FORMATS, MODES

    p = sub.add_parser(
        "run",
        help="run the SLAM system on a sequence and write trajectory, map and timing",
        description=(
            "Run dhptam on a sequence: front-end (events, E3CT, fusion), features, tracking, "
            "mapping and loop closing. Writes OUT/trajectory.tum (every frame, left rectified "
            "frame camera; centres smoothed by each frame's measured covariance, see [tracking] "
            "smoothing_q), trajectory_frame_left.tum, keyframes.tum, map.ply, frames.csv, "
            "timing.json, config.toml and run.log. Ctrl-C stops cleanly and keeps what was done."
        ),
    )
    p.add_argument("--format", choices=list(FORMATS), default="tum-vie", help="sequence format")
    p.add_argument("--sequence", required=True, metavar="DIR", help="sequence folder")
    p.add_argument(
        "--calibration", metavar="FILE", help="calibration file (default: found beside the sequence)"
    )
    p.add_argument("--mode", choices=list(MODES), default="fusion", help="input images (default fusion)")
    p.add_argument(
        "--features", choices=list(FEATURES), default="orb", help="keypoint extractor (default orb)"
    )
    p.add_argument("--weights", metavar="PATH", help="weights of a learned extractor")
    p.add_argument("--config", metavar="FILE", help="configuration TOML (see dhptam config --defaults)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--realtime", action="store_true", help="play the sequence back at sensor rate")
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    p.add_argument("--sync", action="store_true", help="mapping and loop closing inline (deterministic)")
    p.add_argument(
        "--trajectory-format",
        action="append",
        choices=["kitti", "euroc"],
        help="also write the trajectories as KITTI (*.kitti) or EuRoC CSV (*.csv); repeatable",
    )
    p.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="also record inputs and outputs (frames, events, poses, keyframes, map) into one MCAP log",
    )
    p.add_argument(
        "--record-frames",
        choices=["raw", "png"],
        default="raw",
        help="how --record stores frames: raw (foxglove.RawImage, default) or png (lossless, smaller)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--viz",
        choices=["none", "rerun", "rerun-spawn"],
        default="none",
        help="rerun: write OUT/recording.rrd; rerun-spawn: also open a live viewer (needs dhptam[viz])",
    )
    p.set_defaults(func=_run_command)


def _demo_command(args: argparse.Namespace) -> int:
    from .demo import demo

    demo(
        args.out,
        features=args.features,
        modes=tuple(args.modes.split(",")),
        preset=args.preset,
        seed=args.seed,
        weights=args.weights,
        config=args.config,
        progress=not args.quiet,
    )
    return 0


def _add_demo_command(sub: Any) -> None:
    from .run import FEATURES

    p = sub.add_parser(
        "demo",
        help="simulate the HDR demo sequence, run fusion/frames/events, evaluate, write a report",
        description=(
            "The main job: simulates (once, then cached) the default HDR desk sequence, runs "
            "dhptam in the fusion, frames and events modes, evaluates each against ground truth "
            "and writes OUT/report.md with a table and plots."
        ),
    )
    p.add_argument("--out", default="dhptam-demo", metavar="DIR", help="output folder (default dhptam-demo)")
    p.add_argument(
        "--features", choices=list(FEATURES), default="orb", help="keypoint extractor (default orb)"
    )
    p.add_argument("--weights", metavar="PATH", help="weights of a learned extractor")
    p.add_argument("--modes", default="fusion,frames,events", help="comma-separated modes to run")
    p.add_argument(
        "--config", metavar="FILE", help="configuration TOML every run starts from (see dhptam run --config)"
    )
    p.add_argument("--preset", default="demo", help="simulator preset (default demo)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_demo_command)


# -- dhptam convert (issue 9) -------------------------------------------------------------------


def _convert_command(args: argparse.Namespace) -> int:
    from .convert import convert

    out = convert(
        args.src,
        args.dst,
        from_format=args.from_format,
        to_format=args.to_format,
        start_s=args.start,
        duration_s=args.duration,
        calibration=args.calibration,
        progress=not args.quiet,
    )
    sys.stdout.write(f"{out}\n")
    return 0


def _add_convert_command(sub: Any) -> None:
    from .convert import WRITERS
    from .datasets.loaders import FORMATS

    p = sub.add_parser(
        "convert",
        help="convert a sequence between formats (VECtor, MVSEC, EuRoC, ROS bag → TUM-VIE, ...)",
        description="Read SRC in the --from format and write DST in the --to format, atomically.",
    )
    p.add_argument("--from", dest="from_format", required=True, choices=list(FORMATS), help="input format")
    p.add_argument("--to", dest="to_format", default="tum-vie", choices=list(WRITERS), help="output format")
    p.add_argument("src", metavar="SRC", help="input sequence (folder or file)")
    p.add_argument("dst", metavar="DST", help="output path (must not exist)")
    p.add_argument("--start", type=float, metavar="S", help="skip S seconds after the first frame")
    p.add_argument("--duration", type=float, metavar="S", help="keep S seconds")
    p.add_argument("--calibration", metavar="PATH", help="calibration file or folder of the input")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_convert_command)


# -- dhptam view (issue 8) ---------------------------------------------------------------------


def _view_command(args: argparse.Namespace) -> int:
    from .viz import view

    spawn = True if args.spawn else (False if args.no_spawn else None)
    path, shown = view(args.out, save=args.save, reference=args.reference, spawn=spawn)
    sys.stdout.write(f"recording: {path}" + (" (viewer opened)" if shown else "") + "\n")
    return 0


def _add_view_command(sub: Any) -> None:
    p = sub.add_parser(
        "view",
        help="open a run's rerun recording (or build one from its files) in the rerun viewer",
        description=(
            "Show OUT/recording.rrd (written by dhptam run --viz rerun) in the rerun viewer. For a "
            "run made without --viz, a recording is built from its files (trajectory, keyframes, "
            "map, frames.csv, loops, ground truth when found) into OUT/view.rrd or --save FILE. "
            "The viewer opens when there is a display and no --save is given."
        ),
    )
    p.add_argument("out", metavar="OUT", help="output folder of dhptam run")
    p.add_argument("--save", metavar="FILE.rrd", help="write the recording here (no viewer unless --spawn)")
    p.add_argument("--reference", metavar="FILE", help="reference trajectory (TUM) to draw, aligned")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--spawn", action="store_true", help="open the viewer even with --save")
    group.add_argument("--no-spawn", action="store_true", help="never open the viewer")
    p.set_defaults(func=_view_command)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``dhptam`` command."""
    parser = argparse.ArgumentParser(
        prog="dhptam",
        description="Stereo events+frames SLAM (DH-PTAM) with a Rust core.",
    )
    parser.add_argument("--version", action="version", version=f"dhptam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    config = sub.add_parser(
        "config",
        help="print the default configuration or check a configuration file",
        description=(
            "Print the full default configuration as documented TOML (--defaults, the default "
            "action), or validate a TOML file and print it resolved with the defaults (--check)."
        ),
    )
    group = config.add_mutually_exclusive_group()
    group.add_argument(
        "--defaults", action="store_true", help="print every key with its default and its meaning"
    )
    group.add_argument("--check", metavar="FILE", help="validate FILE and print the resolved configuration")
    config.set_defaults(func=_config_command)
    _add_demo_command(sub)
    _add_run_command(sub)
    _add_simulate_command(sub)
    _add_solve_parser(sub)
    _add_eval_command(sub)
    _add_calibrate_align_command(sub)
    _add_convert_command(sub)
    _add_view_command(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        if os.environ.get(logs.ENV_VAR):
            # Asked for by name: the console shows that level too (run.log gets it either way).
            logs.configure()
        return int(args.func(args))
    except InternalError as error:
        print(f"dhptam {args.command}: {error}", file=sys.stderr)
        return EXIT_FAILURE
    except DhptamError as error:
        print(f"dhptam {args.command}: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as error:
        # A file the user named could not be read or written (missing, a folder, no
        # permission, disk full): an input problem, reported without a traceback.
        print(f"dhptam {args.command}: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"dhptam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover - exercised through the console script
    sys.exit(main())
