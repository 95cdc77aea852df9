"""VECtor (Gao et al. 2022): the synced HDF5 + PNG release, and its calibration files.

Layout of a sequence folder (SPEC-NOTES §7; names as the VECtor release and the public
loaders written against it use them)::

    <seq>.synced.left_event.hdf5    /events/{x,y} u16, /events/p u8 (0/1), /events/t u32 µs after
    <seq>.synced.right_event.hdf5   /t_offset (i64 µs), /ms_to_idx; zstd (read via hdf5plugin)
    <seq>.synced.left_camera/       PNG images and timestamp.txt: two comment lines, then
    <seq>.synced.right_camera/      "start end" of each exposure in seconds
    <seq>.synced.gt.txt             timestamp[s] tx ty tz qx qy qz qw: world_from_body

The images are named by their time (``1643091527.996090.png``) in the release; any names work
here, taken in order of (length, name), which is time order for such names and for numbered
ones (``000000.png``); their count must match ``timestamp.txt``.

The event files follow the DSEC convention that :class:`~dhptam.datasets.EventSource` reads
(``t + t_offset`` on the sequence clock). A frame's stamp is the start of its exposure and
``exposure = end - start``; both are parsed exactly from decimal seconds.

Calibration (a folder; by default the first of the sequence folder, its ``calibration/`` or
``0_calib/``, its parent, or the parent's ``calibration/`` or ``0_calib/`` — the release keeps
the calibration files in ``0_calib/`` beside the sequence folders — that holds the left frame
camera's intrinsics):

* ROS ``camera_info`` YAML intrinsics per camera, found by name:
  ``*left_regular_camera*.yaml`` (frame_left, ``left_regular_camera_intrinsic_results.yaml``
  in the release), ``*right_regular_camera*.yaml``, ``*left_event_camera*.yaml``,
  ``*right_event_camera*.yaml``, each with ``image_width``, ``image_height``,
  ``camera_matrix`` (3x3), ``distortion_model: plumb_bob`` and ``distortion_coefficients``
  ``[k1, k2, p1, p2, k3]``;
* the joint extrinsics ``*joint*extrinsic*.yaml``: ``camN: {T_cam0_camN: 4x4}`` =
  ``cam0_from_camN``; ``camera_order`` says which rig camera each ``camN`` is (default
  cam0..cam3 = frame_left, frame_right, event_left, event_right). The release has one file
  per rig set-up, ``small_scale_joint_camera_extrinsic_results.yaml`` and
  ``large_scale_...``; when a folder holds both, pass the one of the sequence as
  ``joint_extrinsics=``;
* the camera–body transform: ``*mocap*extrinsic*.yaml`` (the release's
  ``camera_mocap_extrinsic_results1.yaml``, ``cam0: {T_body_cam, T_cam_body}``) or a
  ``*body*.yaml`` with ``T_body_cam0`` at the top level; either key of the release
  (``T_body_cam`` = ``body_from_cam0``, or ``T_cam_body``, its inverse) is read, or
  ``body_from_cam0=`` is given directly.

4x4 matrices may be nested lists, one flat row-major list of 16 numbers (as the release
writes them) or ``{rows, cols, data}``.

The rig frame of the resulting :class:`~dhptam.datasets.RigCalibration` is ``cam0``
(``imu_from_cam[k] = cam0_from_k``). Ground truth of the left frame camera:
``world_from_cam = world_from_body · body_from_cam0 · cam0_from_frame_left``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..errors import FileError, InputError, ParseError
from ..geometry import SE3, Camera
from ._common import (
    check_increasing,
    get_key,
    load_yaml,
    matrix,
    numbers,
    pair_stereo,
    pose_rows,
    read_table,
    se3,
    seconds_to_ns,
)
from .sequence import CAMERA_KEYS, EventSource, EventStream, Frames, GroundTruth, RigCalibration, Sequence
from .tumvie import compose_poses

INTRINSICS_GLOBS: dict[str, str] = {
    "frame_left": "*left_regular_camera*.yaml",
    "frame_right": "*right_regular_camera*.yaml",
    "event_left": "*left_event_camera*.yaml",
    "event_right": "*right_event_camera*.yaml",
}
"""File-name patterns of the four intrinsics files inside a calibration folder."""
EXTRINSICS_GLOB = "*joint*extrinsic*.yaml"
BODY_GLOBS = ("*mocap*extrinsic*.yaml", "*body*.yaml")
CALIBRATION_FOLDERS = ("", "calibration", "0_calib")
"""Sub-folders of the sequence folder, then of its parent, searched for the calibration."""
DEFAULT_ORDER: tuple[str, str, str, str] = CAMERA_KEYS


def read_ros_camera_yaml(path: str | Path) -> Camera:
    """A ROS ``camera_info`` YAML with the ``plumb_bob`` model → ``Camera("radtan", ...)``."""
    path = Path(path)
    doc = load_yaml(path, "camera intrinsics")
    width = get_key(doc, "image_width", path, "")
    height = get_key(doc, "image_height", path, "")
    for name, v in (("image_width", width), ("image_height", height)):
        if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
            raise ParseError(
                f"{path}: {name} must be a positive integer, got {v!r}", path=str(path), field=name
            )
    k = matrix(get_key(doc, "camera_matrix", path, ""), 3, 3, path, "camera_matrix")
    model = get_key(doc, "distortion_model", path, "")
    if model != "plumb_bob":
        raise InputError(
            f"{path}: distortion_model {model!r} is not supported (plumb_bob)",
            path=str(path),
            field="distortion_model",
        )
    raw = get_key(doc, "distortion_coefficients", path, "")
    coeffs = numbers(
        raw.get("data") if isinstance(raw, dict) else raw, 5, path, "distortion_coefficients.data"
    )
    k1, k2, p1, p2, k3 = coeffs
    try:
        return Camera("radtan", [k[0, 0], k[1, 1], k[0, 2], k[1, 2], k1, k2, p1, p2, k3], width, height)
    except ValueError as err:
        raise InputError(f"{path}: {err}", path=str(path), field="camera_matrix") from None


def read_joint_extrinsics(path: str | Path) -> dict[str, SE3]:
    """``{"cam0": identity, "camN": cam0_from_camN}`` from a VECtor joint extrinsics file."""
    path = Path(path)
    doc = load_yaml(path, "joint extrinsics")
    out: dict[str, SE3] = {}
    n = 0
    while f"cam{n}" in doc:
        name = f"cam{n}"
        entry = doc[name]
        key = f"T_cam0_{name}"
        if n == 0 and (not isinstance(entry, dict) or key not in entry):
            out[name] = SE3()
        else:
            out[name] = se3(get_key(entry, key, path, name), path, f"{name}.{key}")
        n += 1
    if n < 2:
        raise ParseError(
            f"{path}: needs cam0, cam1, ... entries with T_cam0_camN", path=str(path), field="cam1"
        )
    return out


def _glob_one(folder: Path, pattern: str, what: str, choose: str | None = None) -> Path:
    found = sorted(folder.glob(pattern))
    if len(found) != 1:
        raise FileError(
            f"{folder}: expected one {what} file matching {pattern!r}, found {len(found)}"
            + (f" ({', '.join(p.name for p in found)})" if found else "")
            + (f"; pass {choose} to choose" if choose and len(found) > 1 else ""),
            path=str(folder),
            field=what,
        )
    return found[0]


def read_vector_calibration(
    folder: str | Path,
    camera_order: tuple[str, ...] = DEFAULT_ORDER,
    joint_extrinsics: str | Path | None = None,
) -> RigCalibration:
    """The rig from a VECtor calibration folder (module docstring); rig frame = ``cam0``.

    ``joint_extrinsics`` picks the joint extrinsics file (default: the folder's only
    ``*joint*extrinsic*.yaml``)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileError(f"{folder}: calibration folder not found", path=str(folder))
    cameras = {
        k: read_ros_camera_yaml(_glob_one(folder, INTRINSICS_GLOBS[k], f"{k} intrinsics"))
        for k in CAMERA_KEYS
    }
    ext_path = (
        Path(joint_extrinsics)
        if joint_extrinsics is not None
        else _glob_one(folder, EXTRINSICS_GLOB, "joint extrinsics", "joint_extrinsics=")
    )
    cam0_from = read_joint_extrinsics(ext_path)
    if sorted(camera_order) != sorted(CAMERA_KEYS):
        raise InputError(f"camera_order must be a permutation of {list(CAMERA_KEYS)}", field="camera_order")
    imu_from_cam = {}
    for n, key in enumerate(camera_order):
        name = f"cam{n}"
        if name not in cam0_from:
            raise ParseError(
                f"{ext_path}: {name}.T_cam0_{name} is missing (the {key} camera)",
                path=str(ext_path),
                field=f"{name}.T_cam0_{name}",
            )
        imu_from_cam[key] = cam0_from[name]
    return RigCalibration(cameras=cameras, imu_from_cam=imu_from_cam)


def read_body_from_cam0(path: str | Path) -> SE3:
    """``body_from_cam0`` of a VECtor camera–body calibration YAML: ``cam0.T_body_cam`` or the
    inverse of ``cam0.T_cam_body`` (the release's ``camera_mocap_extrinsic_results*.yaml``), or
    a top-level ``T_body_cam0``."""
    path = Path(path)
    doc = load_yaml(path, "camera-body calibration")
    if "T_body_cam0" in doc:
        return se3(doc["T_body_cam0"], path, "T_body_cam0")
    cam0 = get_key(doc, "cam0", path, "")
    if isinstance(cam0, dict) and "T_body_cam" in cam0:
        return se3(cam0["T_body_cam"], path, "cam0.T_body_cam")
    if isinstance(cam0, dict) and "T_cam_body" in cam0:
        return se3(cam0["T_cam_body"], path, "cam0.T_cam_body").inverse()
    raise ParseError(
        f"{path}: cam0 has neither T_body_cam nor T_cam_body (and there is no T_body_cam0)",
        path=str(path),
        field="cam0.T_body_cam",
    )


def _calibration_folder(seq_dir: Path) -> Path:
    for base in (seq_dir, seq_dir.parent):
        for sub in CALIBRATION_FOLDERS:
            folder = base / sub if sub else base
            if folder.is_dir() and any(folder.glob(INTRINSICS_GLOBS["frame_left"])):
                return folder
    raise FileError(
        f"{seq_dir}: no VECtor calibration ({INTRINSICS_GLOBS['frame_left']}) in the folder, its "
        "calibration/ or 0_calib/, its parent or the parent's calibration/ or 0_calib/; pass "
        "calibration=",
        path=str(seq_dir),
        field="calibration",
    )


def read_vector_frame_times(path: Path) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """``(start_ns, exposure_ns)`` from a VECtor ``timestamp.txt`` (start and end in s)."""
    rows = read_table(path, 2, "exposure start and end")
    lines = [line for line, _ in rows]
    start = np.array([seconds_to_ns(t[0], path, ln, "exposure start") for ln, t in rows], np.int64)
    end = np.array([seconds_to_ns(t[1], path, ln, "exposure end") for ln, t in rows], np.int64)
    check_increasing(start, path, "exposure start", lines)
    bad = np.nonzero(end < start)[0]
    if bad.size:
        ln = lines[int(bad[0])]
        raise ParseError(
            f"{path}:{ln}: exposure ends before it starts", path=str(path), line=ln, field="exposure end"
        )
    return start, end - start


def read_vector_ground_truth(path: Path) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """``(t_ns, world_from_body rows)`` of ``<seq>.synced.gt.txt``."""
    rows = read_table(path, 8, "ground-truth pose")
    lines = [line for line, _ in rows]
    t_ns = np.array([seconds_to_ns(t[0], path, ln, "timestamp") for ln, t in rows], np.int64)
    check_increasing(t_ns, path, "timestamp", lines)
    return t_ns, pose_rows(rows, path, 1)


def _sequence_name(seq_dir: Path) -> str:
    names = sorted({p.name.split(".synced.")[0] for p in seq_dir.glob("*.synced.*")})
    if len(names) != 1:
        raise FileError(
            f"{seq_dir}: expected the files of one VECtor sequence (<seq>.synced.*), found "
            + (", ".join(names) if names else "none"),
            path=str(seq_dir),
        )
    return names[0]


def load_vector(
    path: str | Path,
    *,
    calibration: str | Path | RigCalibration | None = None,
    body_from_cam0: str | Path | SE3 | None = None,
    camera_order: tuple[str, ...] = DEFAULT_ORDER,
    pair_tolerance_ns: int = 1_000_000,
    joint_extrinsics: str | Path | None = None,
) -> Sequence:
    """Open a VECtor sequence folder (synced HDF5/PNG release).

    Parameters
    ----------
    path
        The folder holding ``<seq>.synced.*``.
    calibration
        A calibration folder, or a rig whose frame is ``cam0`` (``imu_from_cam`` =
        ``cam0_from_cam``, as the ground-truth chain assumes); default: found as the module
        docstring says.
    body_from_cam0
        ``T_body_cam0`` as a YAML file or an SE3; by default the ``*body*.yaml`` of the
        calibration folder. Needed only when the folder has ``<seq>.synced.gt.txt``.
    camera_order
        The rig camera of cam0, cam1, cam2, cam3 in the joint extrinsics.
    pair_tolerance_ns
        Largest start-of-exposure difference of a left/right frame pair.
    joint_extrinsics
        The joint extrinsics file, when the calibration folder holds several (the release's
        ``small_scale_...`` and ``large_scale_joint_camera_extrinsic_results.yaml``).
    """
    seq_dir = Path(path)
    if not seq_dir.is_dir():
        raise FileError(f"{seq_dir}: sequence folder not found", path=str(seq_dir))
    name = _sequence_name(seq_dir)
    calib_dir: Path | None = None
    if isinstance(calibration, RigCalibration):
        rig = calibration
    else:
        calib_dir = Path(calibration) if calibration is not None else _calibration_folder(seq_dir)
        rig = read_vector_calibration(calib_dir, camera_order, joint_extrinsics)

    times: dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]] = {}
    images: dict[str, list[Path]] = {}
    for side in ("left", "right"):
        folder = seq_dir / f"{name}.synced.{side}_camera"
        if not folder.is_dir():
            raise FileError(f"{folder}: frame folder not found", path=str(folder))
        ts_path = folder / "timestamp.txt"
        times[side] = read_vector_frame_times(ts_path)
        images[side] = sorted(folder.glob("*.png"), key=lambda p: (len(p.stem), p.stem))
        if len(images[side]) != len(times[side][0]):
            raise InputError(
                f"{folder}: {len(images[side])} PNG images but {ts_path} lists "
                f"{len(times[side][0])} exposures",
                path=str(folder),
                field="images",
            )
    i_l, i_r = pair_stereo(times["left"][0], times["right"][0], pair_tolerance_ns)
    left, right = rig.cameras["frame_left"], rig.cameras["frame_right"]
    frames = Frames(
        times["left"][0][i_l],
        times["left"][1][i_l],
        [images["left"][i] for i in i_l],
        [images["right"][i] for i in i_r],
        left_size=(left.width, left.height),
        right_size=(right.width, right.height),
    )

    events: dict[str, EventStream] = {}
    try:
        for side in ("left", "right"):
            events[side] = EventSource(seq_dir / f"{name}.synced.{side}_event.hdf5")
        ground_truth = None
        gt_path = seq_dir / f"{name}.synced.gt.txt"
        if gt_path.exists():
            body = _body_from_cam0(body_from_cam0, calib_dir, gt_path)
            t_ns, world_from_body = read_vector_ground_truth(gt_path)
            body_from_left = body @ rig.imu_from_cam["frame_left"]
            ground_truth = GroundTruth(
                t_ns=t_ns, world_from_cam=compose_poses(world_from_body, body_from_left)
            )
    except BaseException:
        for source in events.values():
            source.close()
        raise
    return Sequence(name, seq_dir, rig, frames, events, ground_truth)


def _body_from_cam0(value: str | Path | SE3 | None, calib_dir: Path | None, gt_path: Path) -> SE3:
    if isinstance(value, SE3):
        return value
    if value is not None:
        return read_body_from_cam0(value)
    if calib_dir is not None:
        for pattern in BODY_GLOBS:
            found = sorted(calib_dir.glob(pattern))
            if len(found) == 1:
                return read_body_from_cam0(found[0])
            if len(found) > 1:
                raise FileError(
                    f"{calib_dir}: several camera-body calibrations match {pattern!r} ("
                    f"{', '.join(p.name for p in found)}); pass body_from_cam0= (the file of "
                    f"{gt_path.name}'s session)",
                    path=str(calib_dir),
                    field="T_body_cam0",
                )
    raise FileError(
        f"{gt_path} holds body poses and needs the camera-body transform T_body_cam0: no "
        f"{' or '.join(BODY_GLOBS)} in the calibration folder; pass body_from_cam0=",
        path=str(gt_path),
        field="T_body_cam0",
    )


__all__ = [
    "load_vector",
    "read_body_from_cam0",
    "read_joint_extrinsics",
    "read_ros_camera_yaml",
    "read_vector_calibration",
    "read_vector_frame_times",
    "read_vector_ground_truth",
]
