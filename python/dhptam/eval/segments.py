"""Labelled time spans of a sequence, for splitting a trajectory's error by condition.

A segments file is CSV text, one span per line: ``label,start_s,end_s`` (seconds on the
trajectories' clock, start included, end excluded; several spans may share a label). Lines
starting with ``#`` and blank lines are skipped; a first line ``label,start_s,end_s`` is a
header. The simulator writes one into every sequence it makes (``lighting.csv``: the spans lit
at one level, see :func:`dhptam.sim.lighting_segments`); for real data write your own, e.g.
the dark and the bright parts of a recording, and pass it to ``dhptam eval --segments``.

    >>> import tempfile, pathlib
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "spans.csv"
    >>> write_segments(path, [("dark", 1_000_000_000, 2_500_000_000)])
    >>> read_segments(path)
    [('dark', 1000000000, 2500000000)]
"""

from __future__ import annotations

from collections.abc import Sequence
from decimal import Decimal, InvalidOperation
from pathlib import Path

from ..errors import FileError, InputError, ParseError
from ..trajectory import _format_seconds, atomic_write_text

HEADER = "label,start_s,end_s"
#: The file the simulator writes into each sequence folder.
LIGHTING_FILE = "lighting.csv"

_NS = 1_000_000_000


def _seconds_to_ns(text: str, path: Path, line: int, what: str) -> int:
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise ParseError(
            f"{path}:{line}: {what} must be a number of seconds, got {text.strip()!r}",
            path=str(path),
            line=line,
            field=what,
        ) from None
    if not value.is_finite():
        raise ParseError(
            f"{path}:{line}: {what} must be finite, got {text.strip()!r}", path=str(path), line=line
        )
    return int((value * _NS).to_integral_value())


def read_segments(path: str | Path) -> list[tuple[str, int, int]]:
    """The spans ``(label, start_ns, end_ns)`` of a segments file, in file order."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileError(f"{p}: segments file not found", path=str(p)) from None
    except (OSError, UnicodeDecodeError) as error:
        raise FileError(f"{p}: cannot read the segments file ({error})", path=str(p)) from None
    spans: list[tuple[str, int, int]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#") or (not spans and line.replace(" ", "") == HEADER):
            continue
        fields = line.split(",")
        if len(fields) != 3 or not fields[0].strip():
            raise ParseError(
                f"{p}:{number}: expected 'label,start_s,end_s', got {line!r}", path=str(p), line=number
            )
        label = fields[0].strip()
        start = _seconds_to_ns(fields[1], p, number, "start_s")
        end = _seconds_to_ns(fields[2], p, number, "end_s")
        if end <= start:
            raise ParseError(
                f"{p}:{number}: span {label!r} must end after it starts ({fields[1].strip()} s to "
                f"{fields[2].strip()} s)",
                path=str(p),
                line=number,
            )
        spans.append((label, start, end))
    if not spans:
        raise ParseError(
            f"{p}: no span in the segments file (expected lines 'label,start_s,end_s')", path=str(p)
        )
    return spans


def write_segments(path: str | Path, segments: Sequence[tuple[str, int, int]]) -> None:
    """Writes ``segments`` (``(label, start_ns, end_ns)``) as a segments file, atomically."""
    atomic_write_text(Path(path), segments_text(segments))


def segments_text(segments: Sequence[tuple[str, int, int]]) -> str:
    """The text of a segments file (exact: nanoseconds written as decimal seconds)."""
    lines = [HEADER]
    for label, start, end in segments:
        if "," in label or "\n" in label or not label.strip() or int(end) <= int(start):
            raise InputError(
                "a span needs a label without commas and an end after its start, "
                f"got {(label, start, end)!r}",
                field="segments",
            )
        lines.append(f"{label},{_format_seconds(int(start))},{_format_seconds(int(end))}")
    return "\n".join(lines) + "\n"
