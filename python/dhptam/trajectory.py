"""Trajectories as TUM text files: the one reader and writer every dhptam tool uses.

A TUM trajectory has one pose per line, ``t tx ty tz qx qy qz qw``: ``t`` in seconds,
``world_from_cam`` as a translation (metres) and a unit Hamilton quaternion in ``x y z w``
order. Comment lines start with ``#``. Times are kept as int64 nanoseconds in memory and are
converted exactly at the file boundary (nine decimals are written, so no precision is lost).

Example: write two poses and read them back::

    >>> import tempfile, numpy as np
    >>> from dhptam.trajectory import read_tum, write_tum
    >>> path = tempfile.mkdtemp() + "/traj.tum"
    >>> poses = np.tile(np.eye(4), (2, 1, 1)); poses[1, :3, 3] = [1.0, 2.0, 3.0]
    >>> write_tum(path, [0, 1_500_000_000], poses)
    >>> t_ns, rows = read_tum(path)
    >>> t_ns.tolist(), rows[1].tolist()
    ([0, 1500000000], [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0])
"""

from __future__ import annotations

import os
import tempfile
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ._core import SE3
from .errors import FileError, InputError, ParseError

_NS = 1_000_000_000
_F64 = npt.NDArray[np.float64]


def poses_to_rows(poses: npt.ArrayLike) -> _F64:
    """``(N, 4, 4)`` matrices or ``(N, 7)`` rows → ``(N, 7)`` rows ``x y z qx qy qz qw``."""
    array = np.asarray(poses, dtype=np.float64)
    if array.ndim == 2 and array.shape[1] == 7:
        return np.ascontiguousarray(array)
    if array.ndim == 3 and array.shape[1:] == (4, 4):
        rows = np.empty((array.shape[0], 7), np.float64)
        for i, m in enumerate(array):
            pose = SE3.from_matrix(m)
            rows[i, :3] = pose.translation
            rows[i, 3:] = pose.rotation.quat_xyzw()
        return rows
    raise InputError(
        f"poses must be (N, 4, 4) matrices or (N, 7) rows, got shape {array.shape}", field="poses"
    )


def rows_to_matrices(rows: npt.ArrayLike) -> _F64:
    """``(N, 7)`` rows ``x y z qx qy qz qw`` → ``(N, 4, 4)`` ``world_from_cam`` matrices."""
    array = np.asarray(rows, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 7:
        raise InputError(f"rows must be (N, 7), got shape {array.shape}", field="rows")
    return np.stack([SE3.from_translation_quat_xyzw(r[:3], r[3:]).matrix() for r in array]).reshape(-1, 4, 4)


def _format_seconds(t_ns: int) -> str:
    sign = "-" if t_ns < 0 else ""
    a = abs(t_ns)
    return f"{sign}{a // _NS}.{a % _NS:09d}"


def atomic_write_text(path: str | Path, text: str) -> None:
    """Writes ``text`` to ``path`` through a temporary file in the same folder and a rename,
    so a reader never sees a half-written file and a failure leaves the old file intact."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Binary counterpart of :func:`atomic_write_text`."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_tum(
    path: str | Path,
    t_ns: npt.ArrayLike,
    poses: npt.ArrayLike,
    *,
    header: str = "timestamp[s] tx ty tz qx qy qz qw (world_from_cam)",
) -> None:
    """Writes a TUM trajectory atomically.

    Parameters
    ----------
    path
        The file; its folder is created if needed.
    t_ns
        ``(N,)`` integer nanoseconds, strictly increasing.
    poses
        ``(N, 4, 4)`` ``world_from_cam`` matrices or ``(N, 7)`` rows ``x y z qx qy qz qw``.
    header
        Written as the first line after ``# ``.
    """
    times, rows = _checked(t_ns, poses)
    lines = [f"# {header}"] if header else []
    lines += [
        _format_seconds(int(t)) + " " + " ".join(f"{v:.9f}" for v in row)
        for t, row in zip(times.tolist(), rows, strict=True)
    ]
    atomic_write_text(path, "\n".join(lines) + "\n")


def _parse_seconds(token: str, path: Path, line: int) -> int:
    """Decimal seconds → ns, exactly (``Decimal``, not float: nine decimals survive)."""
    try:
        value = Decimal(token)
    except InvalidOperation:
        value = Decimal("NaN")
    if not value.is_finite():
        raise ParseError(
            f"{path}:{line}: timestamp {token!r} is not a number of seconds",
            path=str(path),
            line=line,
            field="timestamp",
        )
    return int((value * _NS).to_integral_value())


def read_tum(path: str | Path) -> tuple[npt.NDArray[np.int64], _F64]:
    """Reads a TUM trajectory: ``(t_ns (N,) int64, rows (N, 7) float64)``.

    Lines that are empty or start with ``#`` are skipped; a line with a wrong number of
    columns, a value that is not a number, a quaternion far from unit norm or a time not after
    the previous one raises :class:`~dhptam.errors.ParseError` naming the file and line.
    Quaternions are normalised.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileError(f"{p}: trajectory file not found", path=str(p)) from None
    except (OSError, UnicodeDecodeError) as err:
        raise FileError(f"{p}: cannot read the trajectory ({err})", path=str(p)) from None
    times: list[int] = []
    rows: list[list[float]] = []
    previous_line = 0
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.replace(",", " ").split()
        if len(tokens) != 8:
            raise ParseError(
                f"{p}:{number}: expected 8 values (t tx ty tz qx qy qz qw), got {len(tokens)}",
                path=str(p),
                line=number,
                field="columns",
            )
        t = _parse_seconds(tokens[0], p, number)
        try:
            values = [float(v) for v in tokens[1:]]
        except ValueError:
            raise ParseError(
                f"{p}:{number}: a pose value is not a number: {line!r}",
                path=str(p),
                line=number,
                field="pose",
            ) from None
        if not all(np.isfinite(values)):
            raise ParseError(
                f"{p}:{number}: pose values must be finite", path=str(p), line=number, field="pose"
            )
        norm = float(np.linalg.norm(values[3:]))
        if abs(norm - 1.0) > 1e-2:
            raise ParseError(
                f"{p}:{number}: quaternion (qx qy qz qw) has norm {norm:.4f}, expected 1",
                path=str(p),
                line=number,
                field="quaternion",
            )
        if times and t <= times[-1]:
            raise ParseError(
                f"{p}:{number}: timestamp {tokens[0]} is not after the one on line {previous_line}",
                path=str(p),
                line=number,
                field="timestamp",
            )
        values[3:] = [v / norm for v in values[3:]]
        times.append(t)
        rows.append(values)
        previous_line = number
    if not times:
        raise ParseError(f"{p}: no poses in the trajectory", path=str(p), field="poses")
    return np.asarray(times, np.int64), np.asarray(rows, np.float64)


# -- KITTI and EuRoC trajectory files (issue 9) --------------------------------------------------


def _checked(t_ns: npt.ArrayLike, poses: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], _F64]:
    times = np.asarray(t_ns)
    if times.ndim != 1 or (times.size and not np.issubdtype(times.dtype, np.integer)):
        raise InputError(
            f"t_ns must be a 1-D integer array (nanoseconds), got {times.dtype} {times.shape}", field="t_ns"
        )
    rows = poses_to_rows(poses)
    if rows.shape[0] != times.shape[0]:
        raise InputError(f"{times.shape[0]} times but {rows.shape[0]} poses", field="poses")
    if times.size > 1 and np.any(np.diff(times) <= 0):
        k = int(np.argmax(np.diff(times) <= 0)) + 1
        raise InputError(f"t_ns must increase strictly; pose {k} is not after pose {k - 1}", field="t_ns")
    if not np.all(np.isfinite(rows)):
        k = int(np.argmax(~np.all(np.isfinite(rows), axis=1)))
        raise InputError(f"pose {k} is not finite: {rows[k].tolist()}", field="poses")
    return times.astype(np.int64), rows


def write_kitti(path: str | Path, poses: npt.ArrayLike) -> None:
    """Writes a KITTI odometry trajectory atomically: one line per pose, the top 3x4 of the
    ``world_from_cam`` matrix row-major (12 numbers), no times and no comments (KITTI has
    neither; pair it with the TUM or EuRoC file for times)."""
    rows = poses_to_rows(poses)
    if not np.all(np.isfinite(rows)):
        raise InputError("poses hold NaN or infinity", field="poses")
    mats = rows_to_matrices(rows) if rows.shape[0] else np.empty((0, 4, 4))
    lines = [" ".join(f"{v:.9e}" for v in m[:3].reshape(-1)) for m in mats]
    atomic_write_text(path, "\n".join(lines) + ("\n" if lines else ""))


EUROC_HEADER = (
    "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
)
"""Header of a EuRoC ground-truth style CSV (quaternion w first, as EuRoC writes it)."""


def write_euroc(path: str | Path, t_ns: npt.ArrayLike, poses: npt.ArrayLike) -> None:
    """Writes a EuRoC CSV trajectory atomically: integer ns, position, quaternion **w x y z**
    (EuRoC's order; dhptam's rows are x y z w and are reordered here)."""
    times, rows = _checked(t_ns, poses)
    lines = [EUROC_HEADER]
    for t, r in zip(times.tolist(), rows, strict=True):
        values = (r[0], r[1], r[2], r[6], r[3], r[4], r[5])
        lines.append(f"{t}," + ",".join(f"{v:.9f}" for v in values))
    atomic_write_text(path, "\n".join(lines) + "\n")


TRAJECTORY_FORMATS = ("tum", "kitti", "euroc")
"""Formats :func:`write_trajectory` writes (and evo reads: ``evo_traj tum|kitti|euroc``)."""


def write_trajectory(path: str | Path, fmt: str, t_ns: npt.ArrayLike, poses: npt.ArrayLike) -> None:
    """Writes a frame or keyframe trajectory in one of :data:`TRAJECTORY_FORMATS`."""
    if fmt == "tum":
        write_tum(path, t_ns, poses)
    elif fmt == "kitti":
        _checked(t_ns, poses)
        write_kitti(path, poses)
    elif fmt == "euroc":
        write_euroc(path, t_ns, poses)
    else:
        raise InputError(
            f"unknown trajectory format {fmt!r}; choose one of {', '.join(TRAJECTORY_FORMATS)}",
            field="format",
        )


__all__ = [
    "EUROC_HEADER",
    "TRAJECTORY_FORMATS",
    "atomic_write_bytes",
    "atomic_write_text",
    "poses_to_rows",
    "read_tum",
    "rows_to_matrices",
    "write_euroc",
    "write_kitti",
    "write_trajectory",
    "write_tum",
]
