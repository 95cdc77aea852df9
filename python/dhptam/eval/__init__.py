"""Trajectory evaluation (issue 8): evo APE/RPE with SE(3)/Sim(3) alignment, coverage,
JSON + PNG reports and suite tables. Needs the ``eval`` extra (evo, matplotlib).

Example: an exact copy of a trajectory has zero ATE and full coverage::

    >>> import numpy as np
    >>> from dhptam.eval import Trajectory, evaluate
    >>> t = np.arange(10, dtype=np.int64) * 100_000_000
    >>> rows = np.zeros((10, 7)); rows[:, 6] = 1.0
    >>> rows[:, 0], rows[:, 1] = np.cos(np.arange(10)), np.sin(np.arange(10))
    >>> ref = Trajectory(t, rows)
    >>> r = evaluate(Trajectory(t, rows.copy()), ref)
    >>> round(r.ate_rmse_m, 9), r.coverage
    (0.0, 1.0)
"""

from __future__ import annotations

from .metrics import (
    ALIGNMENTS,
    REFERENCE_FORMATS,
    EvalResult,
    SegmentError,
    Trajectory,
    coverage,
    errors_by_segment,
    evaluate,
    interpolate,
    load_trajectory,
)
from .report import markdown_table, plot_errors, plot_trajectories, write_result
from .segments import LIGHTING_FILE, read_segments, write_segments
from .suite import Suite, SuiteRun, read_suite, run_suite

__all__ = [
    "ALIGNMENTS",
    "LIGHTING_FILE",
    "REFERENCE_FORMATS",
    "EvalResult",
    "SegmentError",
    "Suite",
    "SuiteRun",
    "Trajectory",
    "coverage",
    "errors_by_segment",
    "evaluate",
    "interpolate",
    "load_trajectory",
    "markdown_table",
    "plot_errors",
    "plot_trajectories",
    "read_segments",
    "read_suite",
    "run_suite",
    "write_result",
    "write_segments",
]
