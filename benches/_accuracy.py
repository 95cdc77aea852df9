"""Shared steps of the accuracy benches: one evaluated run, and the report table."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any


def evaluated_run(sequence: Path, out: Path, reference: Any, **run_args: Any) -> tuple[Any, Any]:
    """``dhptam.run`` on ``sequence`` into ``out``, then the SE(3)-aligned evaluation of its
    left-frame-camera trajectory against ``reference`` (also written into ``out``); the
    evaluation is ``None`` when the run has no pose at all (no usable input, e.g. `frames` in
    the dark)."""
    from dhptam.eval import evaluate, load_trajectory, write_result
    from dhptam.run import run

    result = run(sequence, out, progress=False, **run_args)
    if result.tracked == 0:
        return result, None
    ev = evaluate(load_trajectory(result.files["trajectory_frame_left"]), reference, align="se3")
    write_result(ev, out, name="eval")
    return result, ev


def bench_config(base: Path | None, overrides: str = "") -> Any:
    """The configuration of a bench run: the TOML file ``base`` (``--config``; ``None``: the
    defaults) with the tables of ``overrides`` (TOML text, the bench's own options) merged
    over it, key by key."""
    import json

    import tomllib

    from dhptam import _core

    merged: dict[str, Any] = tomllib.loads(base.read_text()) if base is not None else {}
    for table, values in tomllib.loads(overrides).items():
        merged.setdefault(table, {}).update(values)

    def literal(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, list):
            return "[" + ", ".join(literal(x) for x in v) + "]"
        return json.dumps(v) if isinstance(v, str) else repr(v)

    text = "\n".join(
        f"[{table}]\n" + "".join(f"{k} = {literal(v)}\n" for k, v in values.items())
        for table, values in merged.items()
    )
    return _core.Config.from_toml(text, str(base) if base is not None else "<bench>")


def add_config_option(parser: Any) -> None:
    """``--config FILE``: the configuration the bench's runs start from."""
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="configuration TOML the runs start from (the bench's own options override it)",
    )


def keypoint_sigma_toml(keypoint_sigma: str | None) -> str:
    """A ``[tracking] keypoint_sigma`` table for ``--keypoint-sigma`` (empty for ``None``: the
    configuration's default)."""
    return "" if keypoint_sigma is None else f'\n[tracking]\nkeypoint_sigma = "{keypoint_sigma}"\n'


def choices(parser: Any, text: str, allowed: Any, what: str) -> list[str]:
    """The comma-separated items of ``text``, each checked against ``allowed`` (an argparse
    error naming ``what`` otherwise)."""
    items = [item for item in text.split(",") if item]
    for item in items:
        if item not in allowed:
            parser.error(f"unknown {what} {item!r}; choose from {', '.join(allowed)}")
    return items


TABLE_HEAD = [
    "| sequence | mode | frames | tracked | coverage | path [m] | ATE RMSE [m] | ATE [% of path] |",
    "|---|---|---|---|---|---|---|---|",
]


def table_row(name: str, mode: str, result: Any, ev: Any) -> str:
    """One row under :data:`TABLE_HEAD` for a run and its evaluation (also echoed to stderr,
    so a long bench shows its progress); dashes for a run without poses."""
    if ev is None:
        row = f"| {name} | {mode} | {result.frames} | 0 | 0 % | – | – | – |"
        print(row, file=sys.stderr)
        return row
    row = (
        f"| {name} | {mode} | {result.frames} | {result.tracked} | {100 * ev.coverage:.0f} % "
        f"| {ev.path_length_m:.3f} | {ev.ate_rmse_m:.4f} | {ev.ate_percent_of_path:.2f} |"
    )
    print(row, file=sys.stderr)
    return row


def finish_table(lines: list[str], out: Path) -> int:
    """Writes the table atomically to ``out/report.md`` and to stdout; the exit status."""
    from dhptam.trajectory import atomic_write_text

    table = "\n".join(lines) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "report.md", table)
    sys.stdout.write(table)
    return 0
