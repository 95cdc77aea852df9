"""Writes TUM-VIE sequences in the real layout with h5py, OpenCV and plain text, for the tests.

Deliberately independent of :class:`dhptam.datasets.TumVieWriter`: the reader is checked
against the format as the dataset ships it, not against our own writer. Every value written is
returned in a :class:`Layout` so that tests can compare what the loader reads with the truth.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import h5py
import hdf5plugin
import numpy as np

# A TUM-VIE-like rig, scaled down: two kb4 frame cameras and two kb4 event cameras.
INTRINSICS = [
    [180.5, 181.0, 63.2, 47.9, 0.021, -0.004, 0.0012, -0.0003],
    [179.8, 180.1, 64.1, 48.3, 0.019, -0.002, 0.0009, -0.0002],
    [150.0, 150.2, 79.5, 44.6, -0.011, -0.006, 0.0021, -0.0023],
    [149.1, 149.3, 81.2, 44.1, -0.012, 0.006, 0.0035, -0.0088],
]
RESOLUTIONS = [[128, 96], [128, 96], [160, 90], [160, 90]]
# imu_from_cam per camera: translation and (x, y, z, w) quaternion, like TUM-VIE's values.
T_IMU_CAM = [
    ([0.0096, 0.0539, -0.0265], [-0.7073312, 0.7068683, -0.0015069, -0.0041801]),
    ([0.0093, -0.0554, -0.0264], [-0.7073932, 0.7068137, 0.0024961, -0.0017015]),
    ([-0.0348, 0.0597, -0.0369], [-0.7015384, 0.7125976, 0.0065161, 0.0024332]),
    ([-0.0351, -0.0587, -0.0362], [-0.7005187, 0.7135042, 0.0094333, -0.0098071]),
]
T_IMU_MARKER = ([0.012, -0.034, 0.051], [0.1, -0.2, 0.05, 0.97])


def unit(q: list[float]) -> list[float]:
    a = np.asarray(q, dtype=np.float64)
    return list(a / np.linalg.norm(a))


def pose_json(t: list[float], q: list[float]) -> dict[str, float]:
    qn = unit(q)
    return dict(px=t[0], py=t[1], pz=t[2], qx=qn[0], qy=qn[1], qz=qn[2], qw=qn[3])


def calibration_json() -> dict[str, Any]:
    keys = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    return {
        "value0": {
            "T_imu_cam": [pose_json(t, q) for t, q in T_IMU_CAM],
            "intrinsics": [
                {"camera_type": "kb4", "intrinsics": dict(zip(keys, p, strict=True))} for p in INTRINSICS
            ],
            "resolution": RESOLUTIONS,
            "calib_accel_bias": [0.0] * 9,
            "calib_gyro_bias": [0.0] * 12,
            "imu_update_rate": 200.0,
            "cam_time_offset_ns": 0,
            "vignette": [],
        }
    }


def mocap_calibration_json() -> dict[str, Any]:
    return {
        "value0": {
            "T_imu_marker": pose_json(*T_IMU_MARKER),
            "T_mocap_world": pose_json([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
            "mocap_time_offset_ns": 0,
        }
    }


def ms_to_idx(t_us: np.ndarray) -> np.ndarray:
    """The DSEC index computed by brute force: one entry per ms up to one past the last event."""
    last_ms = int(t_us[-1]) // 1000 if len(t_us) else 0
    return np.searchsorted(t_us, 1000 * np.arange(last_ms + 2, dtype=np.int64), side="left").astype(np.uint64)


def write_event_file(
    path: Path,
    x: np.ndarray,
    y: np.ndarray,
    t_us: np.ndarray,
    p: np.ndarray,
    *,
    index: np.ndarray | bool | None = True,
    t_offset_us: int | None = None,
    dtypes: dict[str, Any] | None = None,
    chunk: int = 8192,
) -> None:
    """An event file as TUM-VIE/DSEC ship it (Blosc zstd); ``index=True`` computes /ms_to_idx."""
    dt = {"x": np.uint16, "y": np.uint16, "t": np.int64, "p": np.int8}
    dt.update(dtypes or {})
    blosc = hdf5plugin.Blosc(cname="zstd", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE)
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        for name, values in (("x", x), ("y", y), ("t", t_us), ("p", p)):
            data = np.asarray(values).astype(dt[name])
            g.create_dataset(name, data=data, maxshape=(None,), chunks=(chunk,), **blosc)
        if index is True:
            index = ms_to_idx(np.asarray(t_us))
        if index is not None and index is not False:
            f.create_dataset("ms_to_idx", data=index)
        if t_offset_us is not None:
            f.create_dataset("t_offset", data=np.int64(t_offset_us))


def random_events(
    rng: np.random.Generator, n: int, t_first_us: int, t_last_us: int, width: int, height: int
) -> tuple[np.ndarray, ...]:
    """Sorted events with bursts, quiet gaps and many equal timestamps (as real sensors give)."""
    t = np.sort(rng.integers(t_first_us, t_last_us + 1, n)).astype(np.int64)
    # Collapse runs to the same µs and carve a silent 30 ms gap, so windows meet both cases.
    t[n // 3 : n // 3 + 200] = t[n // 3]
    gap_start = t_first_us + (t_last_us - t_first_us) // 2
    t[(t >= gap_start) & (t < gap_start + 30_000)] = gap_start + 30_000
    t = np.sort(t)
    x = rng.integers(0, width, n).astype(np.uint16)
    y = rng.integers(0, height, n).astype(np.uint16)
    p = rng.integers(0, 2, n).astype(np.int8)
    return x, y, t, p


@dataclass
class Layout:
    """What was written, in the units a loader must return (ns)."""

    root: Path
    name: str
    seq_dir: Path
    frame_t_ns: np.ndarray
    exposure_ns: np.ndarray
    images: dict[str, list[np.ndarray]]
    events: dict[str, tuple[np.ndarray, ...]] = field(default_factory=dict)
    mocap_t_ns: np.ndarray | None = None
    world_from_marker: np.ndarray | None = None


def write_sequence(
    root: Path,
    rng: np.random.Generator,
    *,
    name: str = "mocap-desk",
    n_frames: int = 6,
    n_events: int = 20_000,
    calibration_in_parent: bool = True,
) -> Layout:
    """A complete sequence folder ``root / name`` in the real TUM-VIE layout."""
    seq = root / name
    seq.mkdir(parents=True)
    calib_dir = root if calibration_in_parent else seq
    (calib_dir / "camera-calibrationA.json").write_text(json.dumps(calibration_json(), indent=4))
    (calib_dir / "mocap-imu-calibrationA.json").write_text(json.dumps(mocap_calibration_json(), indent=4))

    # Frames at 20 Hz with sub-µs fractions in the stamps, as the real files have.
    t0_us = 1_625_000
    frame_us = [f"{t0_us + 50_000 * k}.{(137 * k) % 1000:03d}" for k in range(n_frames)]
    exposure_us = [f"{2000 + 311 * k}.{(71 * k) % 1000:03d}" for k in range(n_frames)]
    frame_t_ns = np.array([int(s.replace(".", "")) for s in frame_us], dtype=np.int64)
    exposure_ns = np.array([int(s.replace(".", "")) for s in exposure_us], dtype=np.int64)
    images: dict[str, list[np.ndarray]] = {"left": [], "right": []}
    w, h = RESOLUTIONS[0]
    yy, xx = np.mgrid[0:h, 0:w]
    for side in ("left", "right"):
        folder = seq / f"{side}_images"
        folder.mkdir()
        (folder / f"image_timestamps_{side}.txt").write_text(
            "# timestamps [us]\n" + "\n".join(frame_us) + "\n"
        )
        (folder / f"image_exposures_{side}.txt").write_text(
            "# exposures [us]\n" + "\n".join(exposure_us) + "\n"
        )
        for k in range(n_frames):
            # Smooth content, so JPEG keeps it to within a few grey levels.
            image = (127 + 100 * np.sin(xx / 9.0 + k) * np.cos(yy / 13.0 - (side == "right"))).astype(
                np.uint8
            )
            cv2.imwrite(str(folder / f"{k:05d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 95])
            images[side].append(image)

    layout = Layout(root, name, seq, frame_t_ns, exposure_ns, images)
    for side, res in (("left", RESOLUTIONS[2]), ("right", RESOLUTIONS[3])):
        x, y, t, p = random_events(rng, n_events, t0_us - 5_000, t0_us + 50_000 * n_frames, *res)
        write_event_file(seq / f"{name}-events_{side}.h5", x, y, t, p)
        layout.events[side] = (x, y, t, p)

    # Mocap at 120 Hz: marker poses with unit quaternions.
    n_mocap = 40
    mocap_t_us = t0_us - 20_000 + (np.arange(n_mocap) * 1e6 / 120).astype(np.int64)
    poses = np.empty((n_mocap, 7))
    poses[:, :3] = rng.normal(size=(n_mocap, 3))
    q = rng.normal(size=(n_mocap, 4))
    poses[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    lines = [f"{t} " + " ".join(f"{v:.17g}" for v in row) for t, row in zip(mocap_t_us, poses, strict=True)]
    (seq / "mocap_data.txt").write_text(
        "# mocap poses: time(us) px py pz qx qy qz qw\n" + "\n".join(lines) + "\n"
    )
    layout.mocap_t_ns = mocap_t_us * 1000
    layout.world_from_marker = poses
    return layout
