"""``dhptam demo``: the paper's claim, shown on data made here.

Simulates the default HDR desk sequence (once; it is cached), runs dhptam on it in the three
input modes — ``fusion``, ``frames`` and ``events`` — evaluates each against the simulator's
ground truth, prints a table and writes ``report.md`` with plots: trajectories against ground
truth, the position error over time, and β with the fusion bias over time. On a sequence lit at
several levels (the ``hdr`` profile) a second table splits each mode's error by lighting
segment (normal, dark, bright), which is where the three modes differ.
"""

from __future__ import annotations

import csv
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import FileError, InputError
from .run import MODES, RunResult, run

log = logging.getLogger(__name__)

_NS = 1_000_000_000
GROUND_TRUTH = "groundtruth_frame_left.txt"


def cache_dir() -> Path:
    """``$DHPTAM_CACHE_DIR`` or the user cache folder (``$XDG_CACHE_HOME/dhptam``)."""
    env = os.environ.get("DHPTAM_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "dhptam"


@dataclass
class DemoRow:
    """One mode's outcome."""

    mode: str
    run: RunResult
    evaluation: Any | None
    note: str = ""


def demo_sequence(preset: str = "demo", seed: int = 0, *, progress: bool = True) -> Path:
    """The simulated sequence of ``preset``, generated into the cache on first use."""
    from .sim import simulate

    root = cache_dir() / "sequences" / f"seed{seed}"
    name = preset
    path = root / name
    if (path / GROUND_TRUTH).is_file():
        log.info("reusing the cached sequence %s", path)
        return path
    log.info("simulating the %s sequence into %s (once; it is cached)", preset, path)
    simulate(root, preset=preset, name=name, seed=seed, overwrite=True, progress=progress)
    return path


def _read_frames_csv(path: Path) -> dict[str, list[str]]:
    with path.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    return {k: [r[k] for r in rows] for k in (rows[0] if rows else {})}


def _plot_overview(
    rows: list[DemoRow], reference: Any, path: Path, segments: list[tuple[str, int, int]] | None = None
) -> None:
    """Top view of every mode's aligned trajectory against ground truth, their errors over
    time (dark and bright ``segments`` shaded), and β / fusion bias over time (fusion mode; a
    band where the frame was stretched by exposure recovery)."""
    from matplotlib.figure import Figure

    from .trajectory import atomic_write_bytes

    fig = Figure(figsize=(12, 8.5))
    grid = fig.add_gridspec(2, 2, height_ratios=(1.3, 1.0))
    top = fig.add_subplot(grid[0, 0])
    err = fig.add_subplot(grid[0, 1])
    beta = fig.add_subplot(grid[1, :])
    top.plot(reference.rows[:, 0], reference.rows[:, 1], "k--", lw=1.2, label="ground truth")
    t0 = int(reference.t_ns[0])
    for i, row in enumerate(rows):
        ev = row.evaluation
        if ev is None:
            continue
        top.plot(
            ev.estimate_aligned_xyz[:, 0], ev.estimate_aligned_xyz[:, 1], f"C{i}", lw=1.1, label=row.mode
        )
        err.plot(
            (ev.t_ns - t0) / _NS,
            ev.errors_m,
            f"C{i}",
            lw=1.0,
            label=f"{row.mode} (RMSE {ev.ate_rmse_m:.3f} m)",
        )
    shaded: set[str] = set()
    for label, start, end in segments or []:
        if label in _SHADES:
            err.axvspan(
                (start - t0) / _NS,
                (end - t0) / _NS,
                color=_SHADES[label],
                alpha=0.25,
                lw=0,
                label=None if label in shaded else f"{label} lighting",
            )
            shaded.add(label)
    top.set(xlabel="x [m]", ylabel="y [m]", title="trajectories (SE(3)-aligned), top view")
    top.set_aspect("equal", adjustable="datalim")
    err.set(xlabel="time [s]", ylabel="position error [m]", title="error over time")
    for ax in (top, err):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    for i, row in enumerate(rows):
        frames = row.run.files.get("frames")
        if frames is None or not frames.is_file():
            continue
        data = _read_frames_csv(frames)
        if not data:
            continue
        t = (np.asarray(data["t_s"], float) * _NS - t0) / _NS
        if row.mode == "fusion":
            b = np.asarray(data["beta_left"], float)
            beta.plot(t, b, "C0", lw=1.2, label="β (left, fusion)")
            dvs = np.asarray([x == "dvs" for x in data["bias"]])
            beta.fill_between(t, 0, 1, where=dvs, color="C1", alpha=0.15, step="mid", label="DVS-biased")
            if "stretched" in data:  # frames.csv of runs before exposure recovery lack it
                stretched = np.asarray([int(x) > 0 for x in data["stretched"]])
                beta.fill_between(
                    t, 0, 0.05, where=stretched, color="C2", alpha=0.6, step="mid", label="frame stretched"
                )
        lost = np.asarray([s == "lost" for s in data["state"]])
        if lost.any():
            beta.plot(
                t[lost],
                np.full(lost.sum(), 1.02 + 0.03 * i),
                "|",
                color=f"C{i}",
                ms=8,
                label=f"{row.mode}: lost",
            )
    beta.set(xlabel="time [s]", ylabel="β", ylim=(0, 1.15), title="fusion weight β and tracking losses")
    beta.grid(alpha=0.3)
    if beta.get_legend_handles_labels()[0]:
        beta.legend(fontsize=8, loc="upper right", ncol=3)
    else:  # only frames/events modes, none of them lost a frame
        beta.text(0.5, 0.5, "no fusion run, no frame lost", ha="center", transform=beta.transAxes)
    buffer = __import__("io").BytesIO()
    fig.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    atomic_write_bytes(path, buffer.getvalue())


#: Colours of the lighting segments shaded in the error plot (normal light is left clear).
_SHADES = {"dark": "0.45", "bright": "gold"}


def lighting_of(sequence: str | Path, preset: str, reference: Any) -> list[tuple[str, int, int]]:
    """The lighting segments of a simulated ``sequence``: its ``lighting.csv`` (written by the
    simulator, :func:`dhptam.eval.read_segments`), else, for a sequence simulated before that
    file existed, :func:`dhptam.sim.lighting_segments` of ``preset``'s profile over
    ``reference``'s span (the simulator's ground truth spans the sequence); empty when the
    sequence is lit at a single level or ``preset`` is unknown."""
    from .eval import LIGHTING_FILE, read_segments
    from .sim import PRESETS, lighting_segments

    path = Path(sequence) / LIGHTING_FILE
    if path.is_file():
        segments = read_segments(path)
    else:
        spec = PRESETS.get(preset)
        if spec is None or len(reference.t_ns) < 2:
            return []
        t0 = int(reference.t_ns[0])
        segments = [
            (label, t0 + start, t0 + end)
            for label, start, end in lighting_segments(spec.profile, (int(reference.t_ns[-1]) - t0) / _NS)
        ]
    return segments if len({label for label, _, _ in segments}) > 1 else []


def _segment_table(rows: list[DemoRow], segments: list[tuple[str, int, int]]) -> str:
    """Each mode's ATE RMSE per lighting segment, in millimetres (poses in brackets)."""
    from .eval import errors_by_segment

    labels = list(dict.fromkeys(label for label, _, _ in segments))
    lines = [
        "| mode | " + " | ".join(f"{label} [mm]" for label in labels) + " |",
        "|---|" + "---|" * len(labels),
    ]
    for r in rows:
        if r.evaluation is None:
            lines.append(f"| {r.mode} | " + " | ".join("–" for _ in labels) + " |")
            continue
        parts = errors_by_segment(r.evaluation, segments)
        cells = [
            f"{1000 * parts[label].rmse_m:.1f} ({parts[label].poses})" if parts[label].poses else "–"
            for label in labels
        ]
        lines.append(f"| {r.mode} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _table(rows: list[DemoRow]) -> str:
    lines = [
        "| mode | frames | tracked | lost | coverage | ATE RMSE [m] | ATE [% of path] | keyframes "
        "| bridges / new map segments | fps |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ev = r.evaluation
        lost = r.run.states.get("lost", 0)
        cells = [
            r.mode,
            str(r.run.frames),
            # Flood frames whose pose the motion model predicted (issue 8) and quiet frames held
            # at rest are not "tracked".
            str(r.run.tracked)
            + (f" + {r.run.tracking['predicted']} predicted" if r.run.tracking.get("predicted") else "")
            + (f" + {r.run.tracking['held']} held" if r.run.tracking.get("held") else ""),
            str(lost),
            f"{100 * ev.coverage:.0f} %" if ev else "–",
            f"{ev.ate_rmse_m:.4f}" if ev else "–",
            f"{ev.ate_percent_of_path:.2f}" if ev else "–",
            str(r.run.keyframes),
            f"{r.run.tracking.get('bridges', 0)} / {r.run.tracking.get('segments', 0)}",
            f"{r.run.fps:.1f}",
        ]
        lines.append("| " + " | ".join(cells) + " |" + (f" {r.note}" if r.note else ""))
    return "\n".join(lines) + "\n"


def demo(
    out: str | Path = "dhptam-demo",
    *,
    features: str = "orb",
    modes: tuple[str, ...] = MODES,
    preset: str = "demo",
    seed: int = 0,
    weights: str | Path | None = None,
    config: str | Path | None = None,
    progress: bool = True,
) -> list[DemoRow]:
    """Runs the demo and writes ``out/report.md``; returns one row per mode.

    ``config`` is a configuration file every run starts from (``dhptam run --config``), e.g.
    ``configs/r2d2-cpu.toml`` with ``features="r2d2"``.
    """
    from .eval import evaluate, load_trajectory, write_result
    from .trajectory import atomic_write_text

    for m in modes:
        if m not in MODES:
            raise InputError(f"unknown mode {m!r}; choose from {', '.join(MODES)}", field="modes")
    out_dir = Path(out)
    sequence = demo_sequence(preset, seed, progress=progress)
    reference = load_trajectory(sequence / GROUND_TRUTH)
    rows: list[DemoRow] = []
    for mode in modes:
        result = run(
            sequence,
            out_dir / mode,
            mode=mode,
            features=features,
            weights=weights,
            config=config,
            progress=progress,
        )
        evaluation, note = None, ""
        try:
            estimate = load_trajectory(result.files["trajectory_frame_left"])
            evaluation = evaluate(estimate, reference, align="se3")
            write_result(evaluation, out_dir / mode, name="eval")
        except InputError as error:
            note = f"(not evaluated: {error})"
        rows.append(DemoRow(mode, result, evaluation, note))
    try:
        segments = lighting_of(sequence, preset, reference)
    except (InputError, FileError) as error:  # a damaged lighting.csv costs the table, not the report
        log.warning("no table by lighting level: %s", error)
        segments = []
    _plot_overview(rows, reference, out_dir / "overview.png", segments)
    table = _table(rows)
    by_lighting = (
        "ATE RMSE [mm] over the frames of each lighting level (poses in brackets; the ramps between\n"
        "levels belong to none; the alignment is the whole run's, as above):\n\n"
        + _segment_table(rows, segments)
        if segments
        else ""
    )
    report = [
        f"# dhptam demo: `{preset}` sequence (seed {seed}), features `{features}`",
        "",
        f"Configuration: `{config}` (resolved: `<mode>/config.toml`)."
        if config is not None
        else "Configuration: defaults (resolved: `<mode>/config.toml`).",
        "",
        f"Sequence: `{sequence}`; ground truth: `{GROUND_TRUTH}` (left frame camera).",
        "ATE after SE(3) alignment (evo); coverage = share of the ground-truth time span tracked.",
        "",
        table,
        *([by_lighting] if by_lighting else []),
        "![overview](overview.png)",
        "",
        "Per mode: `<mode>/trajectory.tum`, `<mode>/eval.json`, `<mode>/eval_trajectories.png`,",
        "`<mode>/eval_errors.png`, `<mode>/timing.json`, `<mode>/frames.csv`, `<mode>/run.log`.",
        "",
    ]
    atomic_write_text(out_dir / "report.md", "\n".join(report))
    sys.stdout.write(table)
    if by_lighting:
        sys.stdout.write("\n" + by_lighting)
    sys.stdout.write(f"report: {out_dir / 'report.md'}\n")
    return rows
