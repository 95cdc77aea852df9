"""Shared steps of the accuracy benches: one evaluated run, and the report table."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any


def evaluated_run(sequence: Path, out: Path, reference: Any, **run_args: Any) -> tuple[Any, Any]:
    """``dhptam.run`` on ``sequence`` into ``out``, then the SE(3)-aligned evaluation of its
    left-frame-camera trajectory against ``reference`` (also written into ``out``)."""
    from dhptam.eval import evaluate, load_trajectory, write_result
    from dhptam.run import run

    result = run(sequence, out, progress=False, **run_args)
    ev = evaluate(load_trajectory(result.files["trajectory_frame_left"]), reference, align="se3")
    write_result(ev, out, name="eval")
    return result, ev


def finish_table(lines: list[str], out: Path) -> int:
    """Writes the table atomically to ``out/report.md`` and to stdout; the exit status."""
    from dhptam.trajectory import atomic_write_text

    table = "\n".join(lines) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "report.md", table)
    sys.stdout.write(table)
    return 0
