"""EuRoC MAV (ASL folder layout): stereo frames and ground truth, for the ``frames`` mode.

Layout::

    <seq>/mav0/cam{0,1}/data.csv       "#timestamp [ns],filename"
    <seq>/mav0/cam{0,1}/data/<t>.png   8-bit grayscale
    <seq>/mav0/cam{0,1}/sensor.yaml    T_BS (4x4 body_from_cam, rows/cols/data), resolution
                                       [w, h], camera_model pinhole, intrinsics [fu, fv, cu, cv],
                                       distortion_model radial-tangential, [k1, k2, p1, p2]
    <seq>/mav0/state_groundtruth_estimate0/data.csv
                                       t[ns], p_RS_R xyz [m], q_RS w x y z, then 10 more columns

EuRoC has no event cameras: the sequence's ``events`` is empty and the rig's event cameras are
copies of the frame cameras (so only the ``frames`` mode runs on it). The rig frame is the body
(IMU) frame: ``imu_from_cam = T_BS``. Ground truth ``world_from_cam = T_RS · T_BS(cam0)``; the
quaternion columns are reordered from EuRoC's w-x-y-z to dhptam's x-y-z-w. Frames carry no
exposure time (``exposure_ns = 0``); the left and right stamps of a pair are identical in
EuRoC and are paired exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..errors import FileError, InputError, ParseError
from ..geometry import SE3, Camera
from ._common import check_increasing, get_key, load_yaml, numbers, pair_stereo, pose_rows, read_table, se3
from .sequence import CAMERA_KEYS, Frames, GroundTruth, RigCalibration, Sequence
from .tumvie import compose_poses


def read_euroc_sensor(path: str | Path) -> tuple[Camera, SE3]:
    """``(camera, body_from_cam)`` from a camera ``sensor.yaml``."""
    path = Path(path)
    doc = load_yaml(path, "camera sensor.yaml")
    model = get_key(doc, "camera_model", path, "")
    if model != "pinhole":
        raise InputError(
            f"{path}: camera_model {model!r} is not supported (pinhole)", path=str(path), field="camera_model"
        )
    fx, fy, cx, cy = numbers(get_key(doc, "intrinsics", path, ""), 4, path, "intrinsics")
    dist = get_key(doc, "distortion_model", path, "")
    if dist not in ("radial-tangential", "radtan"):
        raise InputError(
            f"{path}: distortion_model {dist!r} is not supported (radial-tangential)",
            path=str(path),
            field="distortion_model",
        )
    k1, k2, p1, p2 = numbers(
        get_key(doc, "distortion_coefficients", path, ""), 4, path, "distortion_coefficients"
    )
    res = get_key(doc, "resolution", path, "")
    if not (isinstance(res, list) and len(res) == 2 and all(isinstance(v, int) and v > 0 for v in res)):
        raise ParseError(
            f"{path}: resolution must be [width, height], got {res!r}", path=str(path), field="resolution"
        )
    camera = Camera("radtan", [fx, fy, cx, cy, k1, k2, p1, p2, 0.0], res[0], res[1])
    return camera, se3(get_key(doc, "T_BS", path, ""), path, "T_BS")


def _camera_stream(folder: Path) -> tuple[npt.NDArray[np.int64], list[Path]]:
    csv = folder / "data.csv"
    rows = read_table(csv, 2, "image list")
    t_ns = np.empty(len(rows), np.int64)
    paths = []
    for k, (line, tok) in enumerate(rows):
        try:
            t_ns[k] = int(tok[0])
        except ValueError:
            raise ParseError(
                f"{csv}:{line}: timestamp {tok[0]!r} is not integer nanoseconds",
                path=str(csv),
                line=line,
                field="timestamp",
            ) from None
        paths.append(folder / "data" / tok[1])
    check_increasing(t_ns, csv, "timestamp", [line for line, _ in rows])
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise FileError(
            f"{csv}: lists {missing[0]}, which does not exist ({len(missing)} missing)", path=str(missing[0])
        )
    return t_ns, paths


def read_euroc_ground_truth(path: Path) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """``(t_ns, world_from_body rows x y z qx qy qz qw)`` of ``state_groundtruth_estimate0``."""
    rows = read_table(path, 17, "ground-truth state")
    t_ns = np.empty(len(rows), np.int64)
    reordered = []
    for k, (line, tok) in enumerate(rows):
        try:
            t_ns[k] = int(tok[0])
        except ValueError:
            raise ParseError(
                f"{path}:{line}: timestamp {tok[0]!r} is not integer nanoseconds",
                path=str(path),
                line=line,
                field="timestamp",
            ) from None
        # p x y z, q w x y z → x y z qx qy qz qw
        reordered.append((line, [*tok[1:4], *tok[5:8], tok[4]]))
    check_increasing(t_ns, path, "timestamp", [line for line, _ in rows])
    return t_ns, pose_rows(reordered, path, 0)


def load_euroc(path: str | Path) -> Sequence:
    """Open a EuRoC ASL sequence (the folder holding ``mav0/``, or ``mav0`` itself)."""
    root = Path(path)
    mav = root / "mav0" if (root / "mav0").is_dir() else root
    if not (mav / "cam0").is_dir():
        raise FileError(f"{root}: no mav0/cam0 folder (EuRoC ASL layout expected)", path=str(root))
    cams: dict[str, Camera] = {}
    body_from: dict[str, SE3] = {}
    streams = {}
    for side, cam in (("left", "cam0"), ("right", "cam1")):
        folder = mav / cam
        if not folder.is_dir():
            raise FileError(f"{folder}: camera folder not found", path=str(folder))
        cams[side], body_from[side] = read_euroc_sensor(folder / "sensor.yaml")
        streams[side] = _camera_stream(folder)
    i_l, i_r = pair_stereo(streams["left"][0], streams["right"][0], 0)
    rig = RigCalibration(
        cameras={k: cams[k.split("_")[1]] for k in CAMERA_KEYS},
        imu_from_cam={k: body_from[k.split("_")[1]] for k in CAMERA_KEYS},
    )
    frames = Frames(
        streams["left"][0][i_l],
        np.zeros(len(i_l), np.int64),
        [streams["left"][1][i] for i in i_l],
        [streams["right"][1][i] for i in i_r],
        left_size=(cams["left"].width, cams["left"].height),
        right_size=(cams["right"].width, cams["right"].height),
    )
    gt_path = mav / "state_groundtruth_estimate0" / "data.csv"
    ground_truth = None
    if gt_path.exists():
        t_ns, world_from_body = read_euroc_ground_truth(gt_path)
        ground_truth = GroundTruth(
            t_ns=t_ns, world_from_cam=compose_poses(world_from_body, body_from["left"])
        )
    name = root.name if root.name != "mav0" else root.parent.name
    return Sequence(name, root, rig, frames, {}, ground_truth)


__all__ = ["load_euroc", "read_euroc_ground_truth", "read_euroc_sensor"]
