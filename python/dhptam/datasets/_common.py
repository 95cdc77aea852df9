"""Helpers the dataset readers share: YAML files, matrices, exact time parsing, stereo pairing.

Every function raises :mod:`dhptam.errors` exceptions naming the file and the field.
"""

from __future__ import annotations

from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import FileError, InputError, ParseError
from ..geometry import SE3

_NS = 1_000_000_000


def load_yaml(path: Path, what: str) -> dict[str, Any]:
    """A YAML mapping (OpenCV's ``%YAML:1.0`` header line is accepted)."""
    import yaml

    if not path.is_file():
        raise FileError(f"{path}: {what} not found", path=str(path))
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise FileError(f"{path}: cannot read {what} ({err})", path=str(path)) from None
    if text.startswith("%YAML:"):
        # OpenCV writes "%YAML:1.0", which PyYAML rejects as a directive; it carries nothing.
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = None if mark is None else int(mark.line) + 1
        raise ParseError(
            f"{path}{'' if line is None else f':{line}'}: invalid YAML in {what}", path=str(path), line=line
        ) from None
    if not isinstance(doc, dict):
        raise ParseError(f"{path}: {what} must be a YAML mapping", path=str(path))
    return doc


def get_key(doc: Any, key: str, path: Path, field: str) -> Any:
    """``doc[key]``, or a :class:`ParseError` naming ``field.key``."""
    name = f"{field}.{key}" if field else key
    if not isinstance(doc, dict) or key not in doc:
        raise ParseError(f"{path}: {name} is missing", path=str(path), field=name)
    return doc[key]


def numbers(value: Any, count: int | None, path: Path, field: str) -> list[float]:
    """A flat list of finite numbers (``count`` of them when given)."""
    ok = isinstance(value, list) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
    )
    if not ok or (count is not None and len(value) != count):
        want = "numbers" if count is None else f"{count} numbers"
        raise ParseError(
            f"{path}: {field} must be a list of {want}, got {value!r}", path=str(path), field=field
        )
    out = [float(v) for v in value]
    if not all(np.isfinite(out)):
        raise InputError(f"{path}: {field} holds NaN or infinity", path=str(path), field=field)
    return out


def matrix(value: Any, rows: int, cols: int, path: Path, field: str) -> npt.NDArray[np.float64]:
    """A ``rows × cols`` matrix written as nested lists, as one flat row-major list of
    ``rows * cols`` numbers (VECtor's extrinsics files), or as ROS/OpenCV ``{rows, cols, data}``."""
    if isinstance(value, list) and len(value) == rows * cols and not any(isinstance(r, list) for r in value):
        return np.asarray(numbers(value, rows * cols, path, field), np.float64).reshape(rows, cols)
    if isinstance(value, dict):
        r, c = value.get("rows"), value.get("cols")
        if (r, c) != (rows, cols):
            raise ParseError(
                f"{path}: {field} is {r}x{c}, expected {rows}x{cols}", path=str(path), field=field
            )
        flat = numbers(value.get("data"), rows * cols, path, f"{field}.data")
        return np.asarray(flat, np.float64).reshape(rows, cols)
    if isinstance(value, list) and len(value) == rows and all(isinstance(r, list) for r in value):
        return np.asarray([numbers(r, cols, path, f"{field}[{i}]") for i, r in enumerate(value)], np.float64)
    raise ParseError(
        f"{path}: {field} must be a {rows}x{cols} matrix (nested lists or rows/cols/data), got {value!r}",
        path=str(path),
        field=field,
    )


def se3(value: Any, path: Path, field: str) -> SE3:
    """A rigid transform from a 4×4 homogeneous matrix; the rotation must be orthonormal."""
    m = matrix(value, 4, 4, path, field)
    r = m[:3, :3]
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9) or not np.allclose(
        r.T @ r, np.eye(3), atol=1e-4
    ):
        raise InputError(
            f"{path}: {field} is not a rigid transform (last row [0 0 0 1], orthonormal rotation)",
            path=str(path),
            field=field,
        )
    if np.linalg.det(r) < 0:
        raise InputError(f"{path}: {field} has a reflection (det R < 0)", path=str(path), field=field)
    # Re-orthonormalise the rotation printed with a few decimals (SVD: the nearest rotation).
    u, _, vt = np.linalg.svd(r)
    m = m.copy()
    m[:3, :3] = u @ vt
    return SE3.from_matrix(m)


def seconds_to_ns(token: str, path: Path, line: int, field: str) -> int:
    """Exact decimal seconds → integer ns (``Decimal``: nine decimals survive)."""
    try:
        value = Decimal(token)
    except InvalidOperation:
        value = Decimal("NaN")
    if not value.is_finite():
        raise ParseError(
            f"{path}:{line}: {field} {token!r} is not a number of seconds",
            path=str(path),
            line=line,
            field=field,
        )
    return int((value * _NS).to_integral_value())


def check_h5_filters(dataset: Any, path: Path, field: str) -> None:
    """Raise :class:`FileError` naming the file, the dataset and the filter when ``dataset`` is
    compressed with an HDF5 filter this process cannot decode (a plugin that is not installed
    or not registered), instead of failing later on the first read with HDF5's own message."""
    import h5py

    try:
        plist = dataset.id.get_create_plist()
        filters = [plist.get_filter(i) for i in range(plist.get_nfilters())]
    except (AttributeError, OSError, RuntimeError, ValueError):
        return  # not a chunked dataset of a real file: nothing to decode
    for code, _flags, _values, name in filters:
        if not h5py.h5z.filter_avail(code):
            label = name.decode(errors="replace") if isinstance(name, bytes) else str(name)
            raise FileError(
                f"{path}: dataset /{field} is compressed with HDF5 filter {code} "
                f"({label or 'unnamed'}), which is not available here; install or register its "
                "plugin (pip install hdf5plugin covers zstd, Blosc, LZ4 and bitshuffle)",
                path=str(path),
                field=field,
            )


def read_table(path: Path, columns: int, what: str) -> list[tuple[int, list[str]]]:
    """Rows ``(line, tokens)`` of a whitespace or comma table (line numbers from 1).

    Blank lines and lines starting with ``#`` or ``%`` are comments; the first other line is
    taken as a header and skipped when its first token is not a number (TUM-VIE, VECtor and
    EuRoC files carry at most one such line). Every data row must hold ``columns`` tokens.
    """
    if not path.is_file():
        raise FileError(f"{path}: {what} file not found", path=str(path))
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise FileError(f"{path}: cannot read {what} file ({err})", path=str(path)) from None
    rows: list[tuple[int, list[str]]] = []
    first = True
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#") or line.startswith("%"):
            continue
        tokens = line.replace(",", " ").split()
        is_first, first = first, False
        if is_first and not _is_number(tokens[0]):
            continue  # the header line, written without '#'
        if len(tokens) != columns:
            raise ParseError(
                f"{path}:{number}: expected {columns} values per line ({what}), found {len(tokens)}",
                path=str(path),
                line=number,
                field=what,
            )
        rows.append((number, tokens))
    return rows


def _is_number(token: str) -> bool:
    try:
        Decimal(token)
    except InvalidOperation:
        return False
    return True


def pose_rows(rows: list[tuple[int, list[str]]], path: Path, first: int) -> npt.NDArray[np.float64]:
    """``(N, 7)`` ``x y z qx qy qz qw`` from the tokens ``first .. first + 6`` of each row, with
    unit quaternions (normalised; a norm far from 1 is an error)."""
    out = np.empty((len(rows), 7), np.float64)
    for k, (line, tok) in enumerate(rows):
        try:
            out[k] = [float(v) for v in tok[first : first + 7]]
        except ValueError:
            raise ParseError(
                f"{path}:{line}: pose values must be numbers", path=str(path), line=line
            ) from None
        if not np.all(np.isfinite(out[k])):
            raise ParseError(
                f"{path}:{line}: pose holds NaN or infinity", path=str(path), line=line, field="pose"
            )
        norm = float(np.linalg.norm(out[k, 3:]))
        if not 0.5 < norm < 2.0:
            raise ParseError(
                f"{path}:{line}: quaternion norm {norm:.3g}, expected a unit quaternion",
                path=str(path),
                line=line,
                field="quaternion",
            )
        out[k, 3:] /= norm
    return out


def check_increasing(
    t_ns: npt.NDArray[np.int64], path: Path, field: str, lines: list[int] | None = None
) -> None:
    """Strictly increasing times, or a :class:`ParseError` naming the first offending entry."""
    bad = np.nonzero(np.diff(t_ns) <= 0)[0]
    if bad.size:
        k = int(bad[0]) + 1
        line = None if lines is None else lines[k]
        where = f"line {line}" if line is not None else f"entry {k}"
        raise ParseError(
            f"{path}: {field} at {where} ({t_ns[k]} ns) is not after the previous one ({t_ns[k - 1]} ns)",
            path=str(path),
            line=line,
            field=field,
        )


def pair_stereo(
    t_left: npt.NDArray[np.int64], t_right: npt.NDArray[np.int64], tolerance_ns: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Indices ``(i_left, i_right)`` of the frames whose stamps differ by at most
    ``tolerance_ns``, each right frame used once: for every left frame, the nearest right one.

    Hardware-triggered stereo cameras stamp a pair within microseconds; a frame dropped on one
    side leaves its partner unpaired rather than shifting every later pair.
    """
    if len(t_left) == 0 or len(t_right) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    j = np.searchsorted(t_right, t_left)
    lo = np.clip(j - 1, 0, len(t_right) - 1)
    hi = np.clip(j, 0, len(t_right) - 1)
    nearest = np.where(np.abs(t_right[lo] - t_left) <= np.abs(t_right[hi] - t_left), lo, hi)
    ok = np.abs(t_right[nearest] - t_left) <= tolerance_ns
    i_left = np.nonzero(ok)[0]
    i_right = nearest[ok]
    # Two left frames closest to the same right frame: keep the first only.
    keep = np.concatenate([[True], np.diff(i_right) > 0]) if i_right.size else np.zeros(0, bool)
    return i_left[keep].astype(np.int64), i_right[keep].astype(np.int64)


def lower_bound(read_t: Any, n: int, v: int, lo: int = 0, block: int = 4096, hint: int | None = None) -> int:
    """First index ``i >= lo`` with ``read_t(i) >= v`` over a sorted length-``n`` sequence.

    ``read_t(i)`` reads one time and ``read_t(slice)`` a block: single reads while the range is
    long, then one block read, so a search costs O(log N) small reads of a file. With ``hint``
    (the expected distance of the answer from ``lo``, e.g. the previous window's event count)
    the search first gallops from ``lo + hint`` by doubling steps, so consecutive windows cost
    O(log window) reads instead of O(log N).
    """
    hi = n
    if hint is not None and hint > block:
        step = int(hint)
        while lo + step < hi:
            if read_t(lo + step) < v:
                lo, step = lo + step + 1, step * 2
            else:
                hi = lo + step
                break
    while hi - lo > block:
        mid = (lo + hi) // 2
        if read_t(mid) < v:
            lo = mid + 1
        else:
            hi = mid
    if hi <= lo:
        return lo
    values = np.asarray(read_t(slice(lo, hi)))
    return lo + int(np.searchsorted(values, v, side="left"))
