"""Writing evaluation results: JSON, PNG plots (matplotlib Agg), markdown tables.

Every file is written atomically (temporary file + rename), so an interrupted run never
leaves a truncated result next to good ones.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from ..trajectory import atomic_write_bytes, atomic_write_text
from .metrics import EvalResult, SegmentError

_NS = 1_000_000_000


def _figure_bytes(fig: object) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, bbox_inches="tight")  # type: ignore[attr-defined]
    return buffer.getvalue()


def plot_trajectories(result: EvalResult, title: str = "") -> bytes:
    """Top view (x, y) of the reference and the aligned estimate, PNG bytes."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 5.0))
    ax = fig.add_subplot()
    ax.plot(result.reference_xyz[:, 0], result.reference_xyz[:, 1], "k--", lw=1.2, label="reference")
    ax.plot(
        result.estimate_aligned_xyz[:, 0],
        result.estimate_aligned_xyz[:, 1],
        "C0",
        lw=1.2,
        label=f"estimate ({result.align} aligned)",
    )
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title or f"ATE RMSE {result.ate_rmse_m:.4f} m")
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    return _figure_bytes(fig)


def plot_errors(result: EvalResult, title: str = "") -> bytes:
    """Translation error of every matched pose over time, PNG bytes."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.0, 3.0))
    ax = fig.add_subplot()
    t0 = int(result.t_ns[0]) if len(result.t_ns) else 0
    ax.plot((result.t_ns - t0) / _NS, result.errors_m, "C3", lw=1.0)
    ax.axhline(result.ate_rmse_m, color="k", ls=":", lw=1.0, label=f"RMSE {result.ate_rmse_m:.4f} m")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("APE (translation) [m]")
    ax.set_title(title or "absolute position error")
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    return _figure_bytes(fig)


def write_result(
    result: EvalResult,
    out_dir: str | Path,
    name: str = "eval",
    segments: Mapping[str, SegmentError] | None = None,
) -> dict[str, Path]:
    """Writes ``<name>.json``, ``<name>_trajectories.png`` and ``<name>_errors.png``; with
    ``segments`` (:func:`~dhptam.eval.metrics.errors_by_segment`) the JSON also holds
    ``"segments"``: per label its ``poses`` and ``ate_rmse_m`` (NaN without poses)."""
    out = Path(out_dir)
    paths = {
        "json": out / f"{name}.json",
        "trajectories": out / f"{name}_trajectories.png",
        "errors": out / f"{name}_errors.png",
    }
    data = result.to_dict()
    if segments is not None:
        data["segments"] = {k: {"poses": v.poses, "ate_rmse_m": v.rmse_m} for k, v in segments.items()}
    atomic_write_text(paths["json"], json.dumps(data, indent=2, allow_nan=True) + "\n")
    atomic_write_bytes(paths["trajectories"], plot_trajectories(result))
    atomic_write_bytes(paths["errors"], plot_errors(result))
    return paths


def _cell(result: EvalResult | None, min_coverage: float) -> str:
    if result is None:
        return "–"
    text = f"{result.ate_rmse_m:.3f}" if math.isfinite(result.ate_rmse_m) else "nan"
    if result.coverage < min_coverage:
        text += f" ({100.0 * result.coverage:.0f} %)"
    return text


def markdown_table(
    rows: Sequence[str],
    columns: Sequence[str],
    results: dict[tuple[str, str], EvalResult],
    *,
    min_coverage: float = 0.99,
) -> str:
    """A table like the paper's accuracy table: one row per method, one column per
    sequence, ATE RMSE in metres; a coverage below ``min_coverage`` is shown in brackets,
    a missing run as ``–``."""
    header = "| method | " + " | ".join(columns) + " |"
    rule = "|---|" + "---|" * len(columns)
    lines = [header, rule]
    for row in rows:
        cells = [_cell(results.get((row, col)), min_coverage) for col in columns]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


__all__ = ["markdown_table", "plot_errors", "plot_trajectories", "write_result"]
