"""TUM-VIE: read the real dataset layout, and write it (for simulated sequences).

Layout of a sequence folder ``<seq>/`` (SPEC-NOTES §7, as the dataset is distributed)::

    <seq>-events_left.h5, <seq>-events_right.h5   /events/{x,y} u16, /events/p i8 (0/1),
                                                   /events/t i64 µs, /ms_to_idx u64; Blosc
    left_images/00000.jpg ...                      8-bit grayscale frames, 5-digit index
    left_images/image_timestamps_left.txt          '#' header line, then µs (start of exposure)
    left_images/image_exposures_left.txt           '#' header line, then µs
    right_images/...                               the same for the right camera
    mocap_data.txt                                 '# mocap poses: time(us) px py pz qx qy qz qw'
    camera-calibration{A,B}.json                   Basalt calibration (here or in the parent)
    mocap-imu-calibration{A,B}.json                Basalt mocap calibration, value0.T_imu_marker

Timestamps in the text files may carry fractions of a microsecond; they are converted to
integer nanoseconds exactly (decimal arithmetic, no float rounding).

Basalt calibration: ``value0.T_imu_cam[i]`` ``{px, py, pz, qx, qy, qz, qw}`` (imu_from_cam),
``value0.intrinsics[i]`` ``{camera_type, intrinsics: {...}}`` and ``value0.resolution[i]``
``[width, height]``, with i = 0, 1, 2, 3 for the left/right frame and left/right event camera
(:data:`~dhptam.datasets.sequence.CAMERA_KEYS`). Camera types read and written:

* ``kb4`` ↔ ``Camera("kb4", [fx, fy, cx, cy, k1, k2, k3, k4])`` (TUM-VIE uses it throughout),
* ``pinhole`` ↔ ``Camera("pinhole", [fx, fy, cx, cy])``,
* ``pinhole-radtan8`` ↔ ``Camera("radtan", [fx, fy, cx, cy, k1, k2, p1, p2, k3])``: Basalt's
  rational model with its denominator coefficients ``k4 = k5 = k6 = 0`` is OpenCV's 5-term
  plumb-bob; a file with non-zero ``k4..k6`` is refused, since dhptam has no rational model.

Ground truth: mocap gives ``world_from_marker``; the left frame camera's pose is
``world_from_cam = world_from_marker · inv(T_imu_marker) · T_imu_cam[0]``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from decimal import Decimal, InvalidOperation
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import FileError, InputError, ParseError
from ..geometry import SE3, Camera
from ._common import read_table
from .sequence import (
    CAMERA_KEYS,
    EVENT_SIDES,
    EventSource,
    Frames,
    GroundTruth,
    RigCalibration,
    Sequence,
)

TIMESTAMPS_HEADER = "# timestamps [us]"
EXPOSURES_HEADER = "# exposures [us]"
MOCAP_HEADER = "# mocap poses: time(us) px py pz qx qy qz qw"
IMAGE_DIGITS = 5
JPEG_QUALITY = 95
"""JPEG quality of written frames (OpenCV scale 0–100)."""
EVENT_CHUNK = 1 << 15
"""Events per HDF5 chunk: 32768 (256 KiB of ``t``), small enough that the single-element reads
of a binary search decompress little, large enough for Blosc to compress well."""


# ---------------------------------------------------------------------------------------------
# text files
# ---------------------------------------------------------------------------------------------


def _us_to_ns(token: str, path: Path, line: int, field: str) -> int:
    """Exact conversion of a decimal µs string (possibly with a fraction) to integer ns."""
    try:
        value = Decimal(token)
    except InvalidOperation:
        raise ParseError(
            f"{path}:{line}: {field} {token!r} is not a number (µs expected)",
            path=str(path),
            line=line,
            field=field,
        ) from None
    if not value.is_finite():
        raise ParseError(f"{path}:{line}: {field} is {token}", path=str(path), line=line, field=field)
    return int((value * 1000).to_integral_value())


def _read_times_us(path: Path, what: str, *, strictly_increasing: bool) -> npt.NDArray[np.int64]:
    rows = read_table(path, 1, what)
    values = np.array([_us_to_ns(tok[0], path, line, what) for line, tok in rows], dtype=np.int64)
    if strictly_increasing:
        _check_increasing(values, [line for line, _ in rows], path, what)
    return values


def _check_increasing(values: npt.NDArray[np.int64], lines: list[int], path: Path, what: str) -> None:
    bad = np.nonzero(np.diff(values) <= 0)[0]
    if bad.size:
        k = int(bad[0]) + 1
        kind = "duplicated" if values[k] == values[k - 1] else "unsorted"
        raise ParseError(
            f"{path}:{lines[k]}: {kind} {what}: {values[k] / 1000} µs after {values[k - 1] / 1000} µs "
            f"(strictly increasing times expected)",
            path=str(path),
            line=lines[k],
            field=what,
        )


def _format_us(t_ns: int) -> str:
    """Exact µs decimal for an integer ns time (``1234567`` → ``'1234.567'``)."""
    t_ns = int(t_ns)
    sign = "-" if t_ns < 0 else ""
    whole, frac = divmod(abs(t_ns), 1000)
    return f"{sign}{whole}" if frac == 0 else f"{sign}{whole}.{frac:03d}"


# ---------------------------------------------------------------------------------------------
# Basalt JSON
# ---------------------------------------------------------------------------------------------


def _load_json(path: Path, what: str) -> dict[str, Any]:
    if not path.is_file():
        raise FileError(f"{path}: {what} not found", path=str(path))
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as err:
        raise FileError(f"{path}: cannot read {what} ({err})", path=str(path)) from None
    except json.JSONDecodeError as err:
        raise ParseError(
            f"{path}:{err.lineno}: invalid JSON in {what}: {err.msg}", path=str(path), line=err.lineno
        ) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("value0"), dict):
        raise ParseError(
            f"{path}: {what} must be an object with a 'value0' object", path=str(path), field="value0"
        )
    return doc["value0"]


def _number(obj: Any, key: str, path: Path, field: str) -> float:
    if not isinstance(obj, dict) or key not in obj:
        raise ParseError(f"{path}: {field}.{key} is missing", path=str(path), field=f"{field}.{key}")
    value = obj[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParseError(
            f"{path}: {field}.{key} must be a number, got {value!r}", path=str(path), field=f"{field}.{key}"
        )
    value = float(value)
    if not np.isfinite(value):
        raise InputError(f"{path}: {field}.{key} is {value}", path=str(path), field=f"{field}.{key}")
    return value


def _pose_from_json(obj: Any, path: Path, field: str) -> SE3:
    t = [_number(obj, k, path, field) for k in ("px", "py", "pz")]
    q = np.array([_number(obj, k, path, field) for k in ("qx", "qy", "qz", "qw")])
    norm = float(np.linalg.norm(q))
    if not 0.5 < norm < 2.0:
        raise InputError(
            f"{path}: {field} quaternion has norm {norm:.3g}, expected a unit quaternion",
            path=str(path),
            field=field,
        )
    return SE3.from_translation_quat_xyzw(t, q / norm)


def _pose_to_json(pose: SE3) -> dict[str, float]:
    t = pose.translation
    q = pose.rotation.quat_xyzw()
    return {
        "px": float(t[0]),
        "py": float(t[1]),
        "pz": float(t[2]),
        "qx": float(q[0]),
        "qy": float(q[1]),
        "qz": float(q[2]),
        "qw": float(q[3]),
    }


def _camera_from_json(intr: Any, res: Any, path: Path, i: int) -> Camera:
    field = f"value0.intrinsics[{i}]"
    if not isinstance(intr, dict) or not isinstance(intr.get("intrinsics"), dict):
        raise ParseError(
            f"{path}: {field} must hold 'camera_type' and 'intrinsics'", path=str(path), field=field
        )
    kind = intr.get("camera_type")
    p = intr["intrinsics"]
    sub = f"{field}.intrinsics"

    def get(*keys: str) -> list[float]:
        return [_number(p, k, path, sub) for k in keys]

    if kind == "kb4":
        model, params = "kb4", get("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    elif kind == "pinhole":
        model, params = "pinhole", get("fx", "fy", "cx", "cy")
    elif kind == "pinhole-radtan8":
        fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = get(
            "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"
        )
        if (k4, k5, k6) != (0.0, 0.0, 0.0):
            raise InputError(
                f"{path}: {sub} has rational coefficients k4..k6 = {(k4, k5, k6)}; dhptam's radtan model "
                "is the 5-term plumb-bob (k4 = k5 = k6 = 0)",
                path=str(path),
                field=sub,
            )
        model, params = "radtan", [fx, fy, cx, cy, k1, k2, p1, p2, k3]
    else:
        raise InputError(
            f"{path}: {field}.camera_type {kind!r} is not supported (kb4, pinhole, pinhole-radtan8)",
            path=str(path),
            field=f"{field}.camera_type",
        )
    rfield = f"value0.resolution[{i}]"
    if (
        not isinstance(res, list)
        or len(res) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in res)
    ):
        raise ParseError(
            f"{path}: {rfield} must be [width, height] positive integers, got {res!r}",
            path=str(path),
            field=rfield,
        )
    try:
        return Camera(model, params, res[0], res[1])
    except ValueError as err:
        raise InputError(f"{path}: {field}: {err}", path=str(path), field=field) from None


def _camera_to_json(cam: Camera, key: str) -> dict[str, Any]:
    p = [float(v) for v in cam.params]
    names = ("fx", "fy", "cx", "cy")
    if cam.model == "kb4":
        return {
            "camera_type": "kb4",
            "intrinsics": dict(zip((*names, "k1", "k2", "k3", "k4"), p, strict=True)),
        }
    if cam.model == "pinhole":
        return {"camera_type": "pinhole", "intrinsics": dict(zip(names, p, strict=True))}
    if cam.model == "radtan":
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = p
        values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "k1": k1, "k2": k2, "p1": p1, "p2": p2}
        values.update({"k3": k3, "k4": 0.0, "k5": 0.0, "k6": 0.0})
        return {"camera_type": "pinhole-radtan8", "intrinsics": values}
    raise InputError(f"camera {key}: model {cam.model!r} has no Basalt equivalent", field=key)


def read_basalt_calibration(path: str | Path) -> RigCalibration:
    """Read a Basalt ``camera-calibration*.json`` holding the four TUM-VIE cameras."""
    path = Path(path)
    doc = _load_json(path, "camera calibration")
    lists = {}
    for key in ("T_imu_cam", "intrinsics", "resolution"):
        value = doc.get(key)
        if not isinstance(value, list):
            raise ParseError(f"{path}: value0.{key} must be a list", path=str(path), field=f"value0.{key}")
        if len(value) < len(CAMERA_KEYS):
            raise InputError(
                f"{path}: value0.{key} has {len(value)} entries; TUM-VIE needs 4 cameras "
                f"({', '.join(CAMERA_KEYS)}), so {', '.join(CAMERA_KEYS[len(value) :])} is missing",
                path=str(path),
                field=f"value0.{key}",
            )
        lists[key] = value
    cameras = {}
    imu_from_cam = {}
    for i, key in enumerate(CAMERA_KEYS):
        imu_from_cam[key] = _pose_from_json(lists["T_imu_cam"][i], path, f"value0.T_imu_cam[{i}]")
        cameras[key] = _camera_from_json(lists["intrinsics"][i], lists["resolution"][i], path, i)
    return RigCalibration(cameras=cameras, imu_from_cam=imu_from_cam)


def read_mocap_calibration(path: str | Path) -> SE3:
    """Read ``value0.T_imu_marker`` (imu_from_marker) of a Basalt ``mocap-imu-calibration*.json``."""
    path = Path(path)
    doc = _load_json(path, "mocap calibration")
    if "T_imu_marker" not in doc:
        raise ParseError(
            f"{path}: value0.T_imu_marker is missing", path=str(path), field="value0.T_imu_marker"
        )
    return _pose_from_json(doc["T_imu_marker"], path, "value0.T_imu_marker")


def _find_calibration(seq_dir: Path, stem: str) -> Path | None:
    """``<stem>{A,B,}.json`` next to the sequence, else in its parent; ambiguity is an error."""
    for folder in (seq_dir, seq_dir.parent):
        found = sorted(p for p in (folder / f"{stem}{s}.json" for s in ("A", "B", "")) if p.is_file())
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise InputError(
                f"{folder}: several calibrations ({', '.join(p.name for p in found)}); pass the one this "
                "sequence was recorded with explicitly",
                path=str(folder),
                field=stem,
            )
    return None


# ---------------------------------------------------------------------------------------------
# reader
# ---------------------------------------------------------------------------------------------


def _image_list(folder: Path, count: int, ts_path: Path) -> list[Path]:
    if not folder.is_dir():
        raise FileError(f"{folder}: image folder not found", path=str(folder))
    images = sorted(folder.glob("*.jpg"), key=lambda p: (len(p.stem), p.stem))
    if len(images) != count:
        raise InputError(
            f"{folder}: {len(images)} images but {ts_path} lists {count} timestamps",
            path=str(folder),
            field="images",
        )
    return images


def _read_mocap(path: Path) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    rows = read_table(path, 8, "mocap pose")
    t_ns = np.array([_us_to_ns(tok[0], path, line, "mocap time") for line, tok in rows], dtype=np.int64)
    _check_increasing(t_ns, [line for line, _ in rows], path, "mocap time")
    poses = np.empty((len(rows), 7), dtype=np.float64)
    for k, (line, tok) in enumerate(rows):
        try:
            poses[k] = [float(v) for v in tok[1:]]
        except ValueError:
            raise ParseError(
                f"{path}:{line}: pose values must be numbers", path=str(path), line=line
            ) from None
        if not np.all(np.isfinite(poses[k])):
            raise ParseError(
                f"{path}:{line}: pose holds NaN or infinity", path=str(path), line=line, field="pose"
            )
        norm = np.linalg.norm(poses[k, 3:])
        if not 0.5 < norm < 2.0:
            raise ParseError(
                f"{path}:{line}: quaternion norm {norm:.3g}, expected a unit quaternion",
                path=str(path),
                line=line,
                field="pose",
            )
        poses[k, 3:] /= norm
    return t_ns, poses


def compose_poses(a_from_b: npt.NDArray[np.float64], b_from_c: SE3) -> npt.NDArray[np.float64]:
    """``a_from_b[i] · b_from_c`` for (N, 7) rows ``x y z qx qy qz qw`` and one constant SE3."""
    a_from_b = np.asarray(a_from_b, dtype=np.float64).reshape(-1, 7)
    out = np.empty_like(a_from_b)
    t_bc = b_from_c.translation
    q_bc = b_from_c.rotation.quat_xyzw()
    q = a_from_b[:, 3:]
    # t = t_ab + R_ab t_bc, with R_ab v = v + 2 w (u × v) + 2 u × (u × v) for q = (u, w).
    u, w = q[:, :3], q[:, 3:4]
    uv = np.cross(u, t_bc)
    out[:, :3] = a_from_b[:, :3] + t_bc + 2.0 * w * uv + 2.0 * np.cross(u, uv)
    # Hamilton product q_ab ⊗ q_bc in (x, y, z, w) order.
    x1, y1, z1, w1 = q.T
    x2, y2, z2, w2 = q_bc
    out[:, 3] = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
    out[:, 4] = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
    out[:, 5] = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2
    out[:, 6] = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    return out


def load_tumvie(
    path: str | Path,
    *,
    calibration: str | Path | RigCalibration | None = None,
    mocap_calibration: str | Path | SE3 | None = None,
) -> Sequence:
    """Open a TUM-VIE sequence folder (real or written by :class:`TumVieWriter`).

    Parameters
    ----------
    path
        The sequence folder ``<seq>/``; its name is the sequence name.
    calibration
        A ``camera-calibration*.json`` file or a :class:`RigCalibration`. By default the one
        ``camera-calibration{A,B}.json`` found in the folder or its parent.
    mocap_calibration
        A ``mocap-imu-calibration*.json`` file or ``imu_from_marker`` itself; found like
        ``calibration`` by default. Needed only when the folder has ``mocap_data.txt``.

    Raises
    ------
    FileError
        A file is missing, unreadable, or an HDF5 file is corrupt or truncated.
    ParseError
        A file does not have the documented structure (line, dtype, dataset, sorting).
    InputError
        Values are inconsistent (image and timestamp counts, unsupported camera model, NaN).
    """
    seq_dir = Path(path)
    if not seq_dir.is_dir():
        raise FileError(f"{seq_dir}: sequence folder not found", path=str(seq_dir))
    name = seq_dir.name

    if isinstance(calibration, RigCalibration):
        rig = calibration
    else:
        calib_path = (
            Path(calibration) if calibration is not None else _find_calibration(seq_dir, "camera-calibration")
        )
        if calib_path is None:
            raise FileError(
                f"{seq_dir}: no camera-calibration{{A,B}}.json in the folder or its parent; "
                "pass calibration=",
                path=str(seq_dir),
                field="calibration",
            )
        rig = read_basalt_calibration(calib_path)

    frames = _load_frames(seq_dir, rig)

    events: dict[str, EventSource] = {}
    try:
        for side in EVENT_SIDES:
            events[side] = EventSource(seq_dir / f"{name}-events_{side}.h5")
            _check_event_overlap(events[side], seq_dir / f"{name}-events_{side}.h5", frames)
        ground_truth, imu_from_marker = _load_ground_truth(seq_dir, rig, mocap_calibration)
    except BaseException:
        for source in events.values():
            source.close()
        raise
    return Sequence(name, seq_dir, rig, frames, events, ground_truth, imu_from_marker)


def _check_event_overlap(source: EventSource, path: Path, frames: Frames) -> None:
    """Events and frames share one clock: an event stream entirely outside the frames' span
    (e.g. written in ns or s where µs belong, or from another recording) is refused rather
    than giving empty event windows for every frame. An empty event file is allowed."""
    if len(source) == 0 or len(frames) == 0:
        return
    lo, hi = source.t_range_ns
    f_lo = int(frames.t_ns[0])
    f_hi = int(frames.t_ns[-1] + frames.exposure_ns[-1])
    if hi <= f_lo or lo > f_hi:
        raise InputError(
            f"{path}: the events span [{lo / 1e9:.6f}, {hi / 1e9:.6f}] s but the frames span "
            f"[{f_lo / 1e9:.6f}, {f_hi / 1e9:.6f}] s; both must share one clock "
            "(events/t in microseconds expected)",
            path=str(path),
            field="events/t",
        )


def _load_frames(seq_dir: Path, rig: RigCalibration) -> Frames:
    t: dict[str, npt.NDArray[np.int64]] = {}
    exposure: dict[str, npt.NDArray[np.int64]] = {}
    images: dict[str, list[Path]] = {}
    ts_paths: dict[str, Path] = {}
    for side in ("left", "right"):
        folder = seq_dir / f"{side}_images"
        ts_paths[side] = folder / f"image_timestamps_{side}.txt"
        exp_path = folder / f"image_exposures_{side}.txt"
        t[side] = _read_times_us(ts_paths[side], "image timestamp", strictly_increasing=True)
        exposure[side] = _read_times_us(exp_path, "exposure", strictly_increasing=False)
        if len(exposure[side]) != len(t[side]):
            raise InputError(
                f"{exp_path}: {len(exposure[side])} exposures but {ts_paths[side]} lists "
                f"{len(t[side])} timestamps",
                path=str(exp_path),
                field="exposure",
            )
        if np.any(exposure[side] < 0):
            raise InputError(f"{exp_path}: negative exposure time", path=str(exp_path), field="exposure")
        images[side] = _image_list(folder, len(t[side]), ts_paths[side])
    # Both cameras are triggered together: a pair needs the same start of exposure on both.
    if len(t["left"]) != len(t["right"]):
        raise InputError(
            f"stereo frames do not pair up: {ts_paths['left']} lists {len(t['left'])} frames, "
            f"{ts_paths['right']} lists {len(t['right'])}",
            path=str(ts_paths["left"]),
            field="image timestamp",
        )
    mismatch = np.nonzero(t["left"] != t["right"])[0]
    if mismatch.size:
        k = int(mismatch[0])
        raise InputError(
            f"stereo frames do not pair up: frame {k} starts at {t['left'][k] / 1000} µs in "
            f"{ts_paths['left']} but at {t['right'][k] / 1000} µs in {ts_paths['right']}",
            path=str(ts_paths["right"]),
            field="image timestamp",
        )
    left, right = rig.cameras["frame_left"], rig.cameras["frame_right"]
    return Frames(
        t["left"],
        exposure["left"],
        images["left"],
        images["right"],
        left_size=(left.width, left.height),
        right_size=(right.width, right.height),
    )


def _load_ground_truth(
    seq_dir: Path, rig: RigCalibration, mocap_calibration: str | Path | SE3 | None
) -> tuple[GroundTruth | None, SE3 | None]:
    mocap_path = seq_dir / "mocap_data.txt"
    if isinstance(mocap_calibration, SE3):
        imu_from_marker: SE3 | None = mocap_calibration
    else:
        found = (
            Path(mocap_calibration)
            if mocap_calibration is not None
            else _find_calibration(seq_dir, "mocap-imu-calibration")
        )
        imu_from_marker = None if found is None else read_mocap_calibration(found)
    if not mocap_path.exists():
        return None, imu_from_marker
    if imu_from_marker is None:
        raise FileError(
            f"{mocap_path} needs the mocap-to-IMU calibration: no mocap-imu-calibration{{A,B}}.json "
            f"in {seq_dir} or its parent; pass mocap_calibration=",
            path=str(mocap_path),
            field="mocap_calibration",
        )
    t_ns, world_from_marker = _read_mocap(mocap_path)
    marker_from_cam = imu_from_marker.inverse() @ rig.imu_from_cam["frame_left"]
    return GroundTruth(
        t_ns=t_ns, world_from_cam=compose_poses(world_from_marker, marker_from_cam)
    ), imu_from_marker


# ---------------------------------------------------------------------------------------------
# writer
# ---------------------------------------------------------------------------------------------


class _EventFileWriter:
    """Appends sorted event chunks to one HDF5 file and keeps ``/ms_to_idx`` up to date."""

    def __init__(self, path: Path, width: int, height: int, t_offset_us: int = 0) -> None:
        import h5py
        import hdf5plugin

        self.path = path
        # DSEC's /t_offset: stored times are t - t_offset, so that /ms_to_idx, which counts ms
        # from stored t = 0, stays short for recordings stamped in Unix time.
        self.t_offset_us = int(t_offset_us)
        self.width, self.height = width, height
        self.file: Any = h5py.File(path, "w")
        compression = hdf5plugin.Blosc(cname="zstd", clevel=1, shuffle=hdf5plugin.Blosc.SHUFFLE)
        group = self.file.create_group("events")
        self.dsets = {}
        for name, dtype in (("x", np.uint16), ("y", np.uint16), ("t", np.int64), ("p", np.int8)):
            self.dsets[name] = group.create_dataset(
                name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(EVENT_CHUNK,), **compression
            )
        if self.t_offset_us:
            self.file.create_dataset("t_offset", data=np.int64(self.t_offset_us))
        self.index = self.file.create_dataset(
            "ms_to_idx", shape=(0,), maxshape=(None,), dtype=np.uint64, chunks=(EVENT_CHUNK,), **compression
        )
        self.count = 0
        self.next_ms = 0  # first ms whose index entry is not written yet
        self.last_t_us = 0

    def append(self, x: Any, y: Any, t_ns: Any, p: Any, side: str) -> None:
        x = np.asarray(x)
        y = np.asarray(y)
        t_ns = np.asarray(t_ns)
        p = np.asarray(p)
        n = t_ns.shape[0] if t_ns.ndim == 1 else -1
        if any(a.ndim != 1 or a.shape[0] != n for a in (x, y, t_ns, p)):
            raise InputError(
                f"add_events({side!r}): x, y, t_ns and p must be 1-D arrays of one length, got shapes "
                f"{x.shape}, {y.shape}, {t_ns.shape}, {p.shape}",
                field="events",
            )
        if n == 0:
            return
        for name, a in (("x", x), ("y", y), ("t_ns", t_ns), ("p", p)):
            if a.dtype.kind not in ("iu" if name == "t_ns" else "iub"):
                raise InputError(f"add_events({side!r}): {name} must be integers, got {a.dtype}", field=name)
        for name, a, limit in (("x", x, self.width), ("y", y, self.height)):
            if int(a.min()) < 0 or int(a.max()) >= limit:
                raise InputError(
                    f"add_events({side!r}): {name} outside [0, {limit}) of the event_{side} camera",
                    field=name,
                )
        if not np.all((p == 0) | (p == 1)):
            raise InputError(f"add_events({side!r}): p must be 0 or 1", field="p")
        # Whole µs, rounded down: a monotone map, so sorted input stays sorted.
        t_us = t_ns.astype(np.int64) // 1000 - self.t_offset_us
        if t_us[0] < 0:
            raise InputError(
                f"add_events({side!r}): time {int(t_ns[0])} ns is before the file's t_offset "
                f"{self.t_offset_us} µs (/ms_to_idx counts ms from stored t = 0)",
                field="t_ns",
            )
        if np.any(np.diff(t_ns.astype(np.int64)) < 0) or (self.count and t_us[0] < self.last_t_us):
            raise InputError(
                f"add_events({side!r}): t_ns must be sorted, within and across calls", field="t_ns"
            )
        start = self.count
        end = start + n
        for name, values, dtype in (
            ("x", x, np.uint16),
            ("y", y, np.uint16),
            ("t", t_us, np.int64),
            ("p", p, np.int8),
        ):
            dset = self.dsets[name]
            dset.resize((end,))
            dset[start:end] = values.astype(dtype, copy=False)
        # Entries of every ms k with 1000 k <= last time are now known: later events are later.
        last_ms = int(t_us[-1]) // 1000
        if last_ms >= self.next_ms:
            bounds = 1000 * np.arange(self.next_ms, last_ms + 1, dtype=np.int64)
            self._append_index(start + np.searchsorted(t_us, bounds, side="left"))
            self.next_ms = last_ms + 1
        self.count = end
        self.last_t_us = int(t_us[-1])

    def _append_index(self, values: npt.NDArray[np.int64]) -> None:
        old = self.index.shape[0]
        self.index.resize((old + len(values),))
        self.index[old:] = values.astype(np.uint64)

    def finish(self) -> None:
        # One entry past the last event's ms, pointing at N, so the index brackets every event.
        self._append_index(np.array([self.count], dtype=np.int64))
        self.file.close()


class TumVieWriter:
    """Write a sequence in the real TUM-VIE layout, atomically.

    Everything goes to a hidden temporary folder next to ``out_dir / name``, which
    :meth:`close` renames into place; if the writer is used as a context manager and the body
    raises, or :meth:`abort` is called, the temporary folder is deleted and nothing is left.

    Parameters
    ----------
    out_dir
        Parent folder of the sequence; created if needed.
    name
        Sequence name: the folder ``out_dir / name`` and the event files ``<name>-events_*.h5``.
    calibration
        The rig. Written as ``camera-calibrationA.json`` (Basalt format: kb4, pinhole, and radtan
        as ``pinhole-radtan8`` with ``k4 = k5 = k6 = 0``); images and events are checked
        against its resolutions.
    imu_from_marker
        Written as ``value0.T_imu_marker`` of ``mocap-imu-calibrationA.json``, with
        ``T_mocap_world`` the identity (mocap poses are given in the world frame).
    overwrite
        Replace an existing ``out_dir / name`` on :meth:`close` (otherwise an error, raised now).
    event_t_offset_us
        Written as ``/t_offset`` of the event files (DSEC convention, read back by
        :class:`~dhptam.datasets.EventSource`); events are stored as ``t - t_offset``. Use a
        whole second near the first event for recordings stamped in Unix time. Default 0.

    Notes
    -----
    Timestamps are integer ns. Frame, exposure and mocap times are written as exact decimal µs;
    event times are stored as whole µs, rounded down (the format's resolution), and must be
    non-negative because ``/ms_to_idx`` counts milliseconds from t = 0.
    """

    def __init__(
        self,
        out_dir: str | Path,
        name: str,
        calibration: RigCalibration,
        imu_from_marker: SE3,
        *,
        overwrite: bool = False,
        event_t_offset_us: int = 0,
    ) -> None:
        if not name or "/" in name or os.sep in name or name.startswith("."):
            raise InputError(f"invalid sequence name {name!r}", field="name")
        self.out_dir = Path(out_dir)
        self.name = name
        self.final_dir = self.out_dir / name
        self.overwrite = overwrite
        self.calibration = calibration
        self.imu_from_marker = imu_from_marker
        if self.final_dir.exists() and not overwrite:
            raise FileError(
                f"{self.final_dir} already exists (pass overwrite=True)", path=str(self.final_dir)
            )
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self.tmp_dir = Path(tempfile.mkdtemp(prefix=f".{name}.partial-", dir=self.out_dir))
        except OSError as err:
            raise FileError(
                f"{self.out_dir}: cannot create the output folder ({err})", path=str(self.out_dir)
            ) from None
        self._closed = False
        self._t_ns: list[int] = []
        self._exposure_ns: list[int] = []
        self._mocap: tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]] | None = None
        self._events: dict[str, _EventFileWriter] = {}
        try:
            for side in ("left", "right"):
                (self.tmp_dir / f"{side}_images").mkdir()
            for side in EVENT_SIDES:
                cam = calibration.cameras[f"event_{side}"]
                self._events[side] = _EventFileWriter(
                    self.tmp_dir / f"{name}-events_{side}.h5", cam.width, cam.height, event_t_offset_us
                )
        except BaseException:
            self.abort()
            raise

    def _check_open(self) -> None:
        if self._closed:
            raise InputError(
                f"TumVieWriter for {self.final_dir} is already closed or aborted", field="writer"
            )

    def add_frame_pair(self, t_ns: int, exposure_ns: int, left: Any, right: Any) -> None:
        """Write one stereo pair (8-bit grayscale, the frame cameras' resolutions) as JPEG."""
        self._check_open()
        t_ns, exposure_ns = int(t_ns), int(exposure_ns)
        if self._t_ns and t_ns <= self._t_ns[-1]:
            raise InputError(f"frame times must increase: {t_ns} ns after {self._t_ns[-1]} ns", field="t_ns")
        if exposure_ns < 0:
            raise InputError(f"negative exposure {exposure_ns} ns", field="exposure_ns")
        import cv2

        index = len(self._t_ns)
        for side, image in (("left", left), ("right", right)):
            cam = self.calibration.cameras[f"frame_{side}"]
            image = np.asarray(image)
            if image.dtype != np.uint8 or image.shape != (cam.height, cam.width):
                raise InputError(
                    f"{side} image must be uint8 of shape ({cam.height}, {cam.width}), "
                    f"got {image.dtype} {image.shape}",
                    field=side,
                )
            target = self.tmp_dir / f"{side}_images" / f"{index:0{IMAGE_DIGITS}d}.jpg"
            if not cv2.imwrite(str(target), image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
                raise FileError(f"{target}: cannot write the image", path=str(target))
        self._t_ns.append(t_ns)
        self._exposure_ns.append(exposure_ns)

    def add_events(self, side: str, x: Any, y: Any, t_ns: Any, p: Any) -> None:
        """Append a chunk of events of the ``"left"`` or ``"right"`` event camera.

        Chunks must be sorted in time, within and across calls; they are written to disk at
        once, so a long simulation never holds more than one chunk.
        """
        self._check_open()
        if side not in self._events:
            raise InputError(f"side must be 'left' or 'right', got {side!r}", field="side")
        writer = self._events[side]
        try:
            writer.append(x, y, t_ns, p, side)
        except OSError as err:
            raise FileError(f"{writer.path}: writing events failed ({err})", path=str(writer.path)) from None

    def set_mocap(self, t_ns: Any, world_from_marker: Any) -> None:
        """Mocap marker poses: ``(N,)`` ns times and ``(N, 7)`` rows ``x y z qx qy qz qw``."""
        self._check_open()
        t = np.asarray(t_ns)
        poses = np.asarray(world_from_marker, dtype=np.float64)
        if t.ndim != 1 or t.dtype.kind not in "iu" or poses.shape != (t.shape[0], 7):
            raise InputError(
                f"set_mocap: t_ns must be (N,) integers and world_from_marker (N, 7), got "
                f"{t.dtype} {t.shape} and {poses.shape}",
                field="world_from_marker",
            )
        if np.any(np.diff(t.astype(np.int64)) <= 0):
            raise InputError("set_mocap: t_ns must be strictly increasing", field="t_ns")
        if not np.all(np.isfinite(poses)):
            raise InputError("set_mocap: poses hold NaN or infinity", field="world_from_marker")
        self._mocap = (t.astype(np.int64), poses.copy())

    def add_text_file(self, relative_path: str, text: str) -> None:
        """Write an extra text file into the sequence folder (e.g. a TUM ground-truth
        trajectory), so that it appears atomically with the rest on :meth:`close`."""
        self._check_open()
        target = (self.tmp_dir / relative_path).resolve()
        if self.tmp_dir.resolve() not in target.parents:
            raise InputError(
                f"{relative_path!r} is not a path inside the sequence folder", field="relative_path"
            )
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(text, encoding="utf-8")
        except OSError as err:
            raise FileError(f"{target}: cannot write ({err})", path=str(target)) from None

    def close(self) -> Path:
        """Finish every file and move the sequence into place; returns its folder."""
        self._check_open()
        try:
            for writer in self._events.values():
                writer.finish()
            self._write_text_files()
            if self.final_dir.exists():
                if not self.overwrite:
                    raise FileError(f"{self.final_dir} already exists", path=str(self.final_dir))
                trash = Path(tempfile.mkdtemp(prefix=f".{self.name}.old-", dir=self.out_dir))
                os.replace(self.final_dir, trash / self.name)
                os.replace(self.tmp_dir, self.final_dir)
                shutil.rmtree(trash, ignore_errors=True)
            else:
                os.replace(self.tmp_dir, self.final_dir)
        except OSError as err:
            self.abort()
            raise FileError(
                f"{self.final_dir}: finishing the sequence failed ({err})", path=str(self.final_dir)
            ) from None
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.final_dir

    def abort(self) -> None:
        """Discard everything written so far."""
        for writer in self._events.values():
            # The half-written file is deleted next; a failure to close it changes nothing.
            with contextlib.suppress(Exception):
                writer.file.close()
        shutil.rmtree(self.tmp_dir, ignore_errors=True)
        self._closed = True

    def __enter__(self) -> TumVieWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is not None:
            if not self._closed:
                self.abort()
        elif not self._closed:
            self.close()

    def _write_text_files(self) -> None:
        d = self.tmp_dir
        for side in ("left", "right"):
            folder = d / f"{side}_images"
            _write_lines(
                folder / f"image_timestamps_{side}.txt", TIMESTAMPS_HEADER, map(_format_us, self._t_ns)
            )
            _write_lines(
                folder / f"image_exposures_{side}.txt", EXPOSURES_HEADER, map(_format_us, self._exposure_ns)
            )
        rig = self.calibration
        calib = {
            "value0": {
                "T_imu_cam": [_pose_to_json(rig.imu_from_cam[k]) for k in CAMERA_KEYS],
                "intrinsics": [_camera_to_json(rig.cameras[k], k) for k in CAMERA_KEYS],
                "resolution": [[rig.cameras[k].width, rig.cameras[k].height] for k in CAMERA_KEYS],
                "cam_time_offset_ns": 0,
                "vignette": [],
            }
        }
        (d / "camera-calibrationA.json").write_text(json.dumps(calib, indent=4) + "\n", encoding="utf-8")
        mocap_calib = {
            "value0": {
                "T_imu_marker": _pose_to_json(self.imu_from_marker),
                "T_mocap_world": _pose_to_json(SE3()),
            }
        }
        (d / "mocap-imu-calibrationA.json").write_text(
            json.dumps(mocap_calib, indent=4) + "\n", encoding="utf-8"
        )
        if self._mocap is not None:
            t, poses = self._mocap
            rows = (
                _format_us(int(ti)) + " " + " ".join(repr(float(v)) for v in row)
                for ti, row in zip(t, poses, strict=True)
            )
            _write_lines(d / "mocap_data.txt", MOCAP_HEADER, rows)


def _write_lines(path: Path, header: str, lines: Any) -> None:
    with path.open("w", encoding="utf-8") as f:
        f.write(header + "\n")
        for line in lines:
            f.write(line + "\n")


__all__ = [
    "TumVieWriter",
    "compose_poses",
    "load_tumvie",
    "read_basalt_calibration",
    "read_mocap_calibration",
]
