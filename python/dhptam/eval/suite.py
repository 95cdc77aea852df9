"""Batch evaluation over a suite file, giving a comparison table like the paper's.

A suite is a TOML file; relative paths are relative to the suite file's folder::

    align = "se3"              # default alignment of every run ("se3" or "sim3")
    min_coverage = 0.99        # below this, the table shows the coverage next to the ATE

    [[run]]
    method = "fusion"          # table row
    sequence = "hdr-demo"      # table column
    estimate = "runs/fusion/trajectory.tum"
    reference = "data/demo/groundtruth_frame_left.txt"
    # optional: reference_format = "tum" | "tum-vie-mocap", mocap_calibration = "…",
    #           calibration = "…", align = "sim3"

Unknown keys are errors that name the suite file and the run.
"""

from __future__ import annotations

import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import ConfigError, FileError
from ..trajectory import atomic_write_text
from .metrics import ALIGNMENTS, REFERENCE_FORMATS, EvalResult, evaluate, load_trajectory
from .report import markdown_table, write_result

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

_TOP_KEYS = {"align", "min_coverage", "run"}
_RUN_KEYS = {
    "method",
    "sequence",
    "estimate",
    "reference",
    "reference_format",
    "mocap_calibration",
    "calibration",
    "align",
}


@dataclass(frozen=True)
class SuiteRun:
    """One estimate/reference pair of a suite."""

    method: str
    sequence: str
    estimate: Path
    reference: Path
    reference_format: str
    mocap_calibration: Path | None
    calibration: Path | None
    align: str


@dataclass(frozen=True)
class Suite:
    """A parsed suite file."""

    path: Path
    runs: list[SuiteRun]
    min_coverage: float


def _text(run: dict[str, Any], key: str, where: str, path: Path, default: str | None = None) -> str:
    value = run.get(key, default)
    if not isinstance(value, str) or not value:
        raise ConfigError(
            f"{path}: {where}.{key} must be a non-empty string", path=str(path), field=f"{where}.{key}"
        )
    return value


def read_suite(path: str | Path) -> Suite:
    """Parses and checks a suite file (see the module docstring)."""
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileError(f"{p}: suite file not found", path=str(p)) from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML ({err})", path=str(p)) from None
    unknown = sorted(set(doc) - _TOP_KEYS)
    if unknown:
        raise ConfigError(
            f"{p}: unknown keys {unknown}; allowed: {sorted(_TOP_KEYS)}", path=str(p), field=unknown[0]
        )
    default_align = doc.get("align", "se3")
    if default_align not in ALIGNMENTS:
        raise ConfigError(
            f"{p}: align must be one of {ALIGNMENTS}, got {default_align!r}", path=str(p), field="align"
        )
    min_coverage = doc.get("min_coverage", 0.99)
    if not isinstance(min_coverage, (int, float)) or not 0.0 <= float(min_coverage) <= 1.0:
        raise ConfigError(f"{p}: min_coverage must be a number in [0, 1]", path=str(p), field="min_coverage")
    entries = doc.get("run", [])
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{p}: the suite needs at least one [[run]] table", path=str(p), field="run")
    base = p.parent
    runs = []
    for i, entry in enumerate(entries):
        where = f"run[{i}]"
        bad = sorted(set(entry) - _RUN_KEYS)
        if bad:
            raise ConfigError(
                f"{p}: {where} has unknown keys {bad}; allowed: {sorted(_RUN_KEYS)}",
                path=str(p),
                field=f"{where}.{bad[0]}",
            )
        fmt = _text(entry, "reference_format", where, p, "tum")
        if fmt not in REFERENCE_FORMATS:
            raise ConfigError(
                f"{p}: {where}.reference_format must be one of {REFERENCE_FORMATS}",
                path=str(p),
                field=f"{where}.reference_format",
            )
        align = _text(entry, "align", where, p, default_align)
        if align not in ALIGNMENTS:
            raise ConfigError(
                f"{p}: {where}.align must be one of {ALIGNMENTS}", path=str(p), field=f"{where}.align"
            )
        optional = {
            k: base / _text(entry, k, where, p) if k in entry else None
            for k in ("mocap_calibration", "calibration")
        }
        runs.append(
            SuiteRun(
                method=_text(entry, "method", where, p),
                sequence=_text(entry, "sequence", where, p),
                estimate=base / _text(entry, "estimate", where, p),
                reference=base / _text(entry, "reference", where, p),
                reference_format=fmt,
                mocap_calibration=optional["mocap_calibration"],
                calibration=optional["calibration"],
                align=align,
            )
        )
    return Suite(p, runs, float(min_coverage))


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text)


def run_suite(path: str | Path, out_dir: str | Path) -> tuple[str, dict[tuple[str, str], EvalResult]]:
    """Evaluates every run of a suite; writes per-run JSON/PNGs, ``summary.json`` and
    ``table.md`` into ``out_dir``; returns the markdown table and the results."""
    suite = read_suite(path)
    out = Path(out_dir)
    results: dict[tuple[str, str], EvalResult] = {}
    for run in suite.runs:
        estimate = load_trajectory(run.estimate, "tum")
        reference = load_trajectory(
            run.reference,
            run.reference_format,
            mocap_calibration=run.mocap_calibration,
            calibration=run.calibration,
        )
        result = evaluate(estimate, reference, align=run.align)
        write_result(result, out, f"{_slug(run.method)}__{_slug(run.sequence)}")
        results[(run.method, run.sequence)] = result
    rows = list(dict.fromkeys(r.method for r in suite.runs))
    columns = list(dict.fromkeys(r.sequence for r in suite.runs))
    table = markdown_table(rows, columns, results, min_coverage=suite.min_coverage)
    summary = [{"method": m, "sequence": s, **r.to_dict()} for (m, s), r in results.items()]
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    atomic_write_text(out / "table.md", "ATE RMSE [m] (coverage when below 100 %)\n\n" + table)
    return table, results


__all__ = ["Suite", "SuiteRun", "read_suite", "run_suite"]
