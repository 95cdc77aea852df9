"""Writes VECtor, MVSEC, EuRoC and Kalibr files in their real on-disk layouts, for the tests.

Written with h5py/hdf5plugin (zstd, as VECtor ships), rosbags' own writer, OpenCV and plain
text, independently of dhptam's readers; every value written is returned so tests compare what
the readers give with the truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import h5py
import hdf5plugin
import numpy as np

W, H = 64, 48
# Four plumb-bob cameras: frame left/right, event left/right (cam0..cam3).
K = [
    [120.5, 121.0, 31.2, 23.9],
    [119.8, 120.1, 32.1, 24.3],
    [100.0, 100.2, 31.5, 22.6],
    [99.1, 99.3, 32.2, 24.1],
]
D = [
    [0.01, -0.002, 0.0003, -0.0001, 0.0],
    [0.02, -0.001, 0.0002, 0.0001, 0.0],
    [-0.03, 0.004, -0.0001, 0.0002, 0.001],
    [-0.02, 0.003, 0.0001, -0.0002, 0.0],
]


def rot(axis: list[float], angle: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def transform(axis: list[float], angle: float, t: list[float]) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rot(axis, angle)
    m[:3, 3] = t
    return m


# cam0_from_camN of the joint extrinsics (cam0 = frame_left).
CAM0_FROM = [
    np.eye(4),
    transform([0, 1, 0], 0.01, [0.12, 0.0, 0.001]),
    transform([1, 0, 0], -0.02, [0.01, 0.03, -0.002]),
    transform([0, 0, 1], 0.015, [0.13, 0.031, 0.0]),
]
BODY_FROM_CAM0 = transform([0.3, 1, -0.2], 0.4, [0.05, -0.02, 0.1])


def quat_xyzw(r: np.ndarray) -> list[float]:
    """Rotation matrix → unit quaternion (x, y, z, w), w >= 0 (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
        q = [0.0, 0.0, 0.0, (r[k, j] - r[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (r[j, i] + r[i, j]) / s
        q[k] = (r[k, i] + r[i, k]) / s
    q = np.asarray(q)
    return list(q if q[3] >= 0 else -q)


def matrix_from_row(row: np.ndarray) -> np.ndarray:
    x, y, z, w = row[3:]
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = row[:3]
    return m


def body_poses(n: int, t0_ns: int, step_ns: int) -> tuple[np.ndarray, list[np.ndarray]]:
    t = t0_ns + step_ns * np.arange(n, dtype=np.int64)
    poses = [transform([0.2, 1.0, 0.1 * k], 0.05 * k, [0.1 * k, -0.05 * k, 1.0 + 0.01 * k]) for k in range(n)]
    return t, poses


def random_events(rng: np.random.Generator, n: int, t0_us: int, span_us: int) -> dict[str, np.ndarray]:
    t = np.sort(rng.integers(t0_us, t0_us + span_us, n)).astype(np.int64)
    return {
        "x": rng.integers(0, W, n).astype(np.uint16),
        "y": rng.integers(0, H, n).astype(np.uint16),
        "t": t,
        "p": rng.integers(0, 2, n).astype(np.uint8),
    }


def images(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    return [rng.integers(0, 256, (H, W), dtype=np.uint8) for _ in range(n)]


def ros_camera_yaml(k: list[float], d: list[float], name: str) -> str:
    fx, fy, cx, cy = k
    return (
        f"image_width: {W}\nimage_height: {H}\ncamera_name: {name}\n"
        f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: [{fx}, 0.0, {cx}, 0.0, {fy}, {cy}, 0.0, 0.0, 1.0]\n"
        "distortion_model: plumb_bob\n"
        f"distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: {list(d)}\n"
        "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
    )


def matrix_yaml(m: np.ndarray, indent: str) -> str:
    return "".join(f"{indent}- [{', '.join(repr(float(v)) for v in row)}]\n" for row in m)


def write_vector_calibration(folder: Path, *, drop_cam: int | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    names = ["left_regular_camera", "right_regular_camera", "left_event_camera", "right_event_camera"]
    for i, name in enumerate(names):
        (folder / f"{name}_intrinsic_results.yaml").write_text(ros_camera_yaml(K[i], D[i], name))
    text = ""
    for n in range(4):
        if n == drop_cam:
            continue
        text += f"cam{n}:\n  T_cam0_cam{n}:\n" + matrix_yaml(CAM0_FROM[n], "    ")
    (folder / "large_scale_joint_camera_extrinsic_results.yaml").write_text(text)
    (folder / "camera_body_extrinsic_results.yaml").write_text(
        "T_body_cam0:\n" + matrix_yaml(BODY_FROM_CAM0, "  ")
    )


@dataclass
class VectorTruth:
    folder: Path
    name: str
    t_offset_us: int
    events: dict[str, dict[str, np.ndarray]]
    frame_start_s: list[str]
    frame_end_s: list[str]
    images: dict[str, list[np.ndarray]]
    gt_t_ns: np.ndarray
    world_from_body: list[np.ndarray]
    extra: dict[str, Any] = field(default_factory=dict)


def write_vector(
    root: Path, rng: np.random.Generator, name: str = "corner_slow1", n_events: int = 20000
) -> VectorTruth:
    """A VECtor synced sequence: zstd HDF5 events, PNG frames, timestamp.txt, gt.txt."""
    root.mkdir(parents=True, exist_ok=True)
    t_offset_us = 1_643_091_527_000_000  # a Unix time in µs, as VECtor stores
    events = {}
    for side in ("left", "right"):
        ev = random_events(rng, n_events, 0, 2_000_000)
        events[side] = ev
        with h5py.File(root / f"{name}.synced.{side}_event.hdf5", "w") as f:
            zstd = hdf5plugin.Zstd()
            f.create_dataset("events/x", data=ev["x"], chunks=(min(4096, n_events),), **zstd)
            f.create_dataset("events/y", data=ev["y"], chunks=(min(4096, n_events),), **zstd)
            f.create_dataset("events/p", data=ev["p"], chunks=(min(4096, n_events),), **zstd)
            f.create_dataset(
                "events/t", data=ev["t"].astype(np.uint32), chunks=(min(4096, n_events),), **zstd
            )
            f.create_dataset("t_offset", data=np.int64(t_offset_us))
            ms = np.searchsorted(ev["t"], 1000 * np.arange(2001), side="left").astype(np.uint64)
            f.create_dataset("ms_to_idx", data=ms, **zstd)
    # 10 frames at 10 Hz; exposure 3250.5 µs; stamps in decimal seconds (ends with 7 decimals).
    starts = [
        f"{t_offset_us // 1_000_000}.{(t_offset_us % 1_000_000) + 50_000 + 100_000 * k:06d}"
        for k in range(10)
    ]
    ends = []
    for s in starts:
        whole, frac = s.split(".")
        us = int(frac) + 3250
        ends.append(f"{whole}.{us:06d}5")  # + 3250.5 µs
    imgs = {}
    for side in ("left", "right"):
        folder = root / f"{name}.synced.{side}_camera"
        folder.mkdir()
        imgs[side] = images(rng, 10)
        for k, im in enumerate(imgs[side]):
            cv2.imwrite(str(folder / f"{k:06d}.png"), im)
        lines = ["# timestamps of the regular camera", "# exposure start [s] exposure end [s]"]
        lines += [f"{a} {b}" for a, b in zip(starts, ends, strict=True)]
        (folder / "timestamp.txt").write_text("\n".join(lines) + "\n")
    gt_t, world_from_body = body_poses(20, t_offset_us * 1000, 100_000_000)
    rows = ["# timestamp tx ty tz qx qy qz qw"]
    for t, m in zip(gt_t, world_from_body, strict=True):
        q = quat_xyzw(m[:3, :3])
        rows.append(f"{t // 10**9}.{t % 10**9:09d} " + " ".join(repr(float(v)) for v in [*m[:3, 3], *q]))
    (root / f"{name}.synced.gt.txt").write_text("\n".join(rows) + "\n")
    write_vector_calibration(root / "calibration")
    return VectorTruth(root, name, t_offset_us, events, starts, ends, imgs, gt_t, world_from_body)


# -- ROS bags -------------------------------------------------------------------------------------

EVENT_ARRAY = "std_msgs/Header header\nuint32 height\nuint32 width\ndvs_msgs/Event[] events\n"
EVENT = "uint16 x\nuint16 y\ntime ts\nbool polarity\n"
BAD_EVENT = "int32 x\nuint16 y\ntime ts\nbool polarity\n"


def typestore(event_def: str = EVENT) -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    types = {}
    types.update(get_types_from_msg(EVENT_ARRAY, "dvs_msgs/msg/EventArray"))
    types.update(get_types_from_msg(event_def, "dvs_msgs/msg/Event"))
    store.register(types)
    return store


def write_vector_bag(
    path: Path,
    truth: VectorTruth,
    *,
    per_message: int = 1500,
    skip_topics: tuple[str, ...] = (),
    event_def: str = EVENT,
    compress: bool = True,
) -> None:
    """The same recording as a VECtor ROS1 bag (events split into EventArray messages)."""
    from rosbags.rosbag1 import Writer

    store = typestore(event_def)
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = store.types["std_msgs/msg/Header"]
    Event = store.types["dvs_msgs/msg/Event"]
    EventArray = store.types["dvs_msgs/msg/EventArray"]
    Image = store.types["sensor_msgs/msg/Image"]
    PoseStamped = store.types["geometry_msgs/msg/PoseStamped"]
    Pose = store.types["geometry_msgs/msg/Pose"]
    Point = store.types["geometry_msgs/msg/Point"]
    Quaternion = store.types["geometry_msgs/msg/Quaternion"]

    def stamp(t_ns: int) -> Any:
        return Time(sec=int(t_ns // 10**9), nanosec=int(t_ns % 10**9))

    writer = Writer(path)
    if compress:
        writer.set_compression(Writer.CompressionFormat.LZ4)
    with writer:
        for side in ("left", "right"):
            topic = f"/prophesee/{side}/events"
            if topic in skip_topics:
                continue
            conn = writer.add_connection(topic, "dvs_msgs/msg/EventArray", typestore=store)
            ev = truth.events[side]
            t_ns = (ev["t"] + truth.t_offset_us) * 1000
            for k, a in enumerate(range(0, len(t_ns), per_message)):
                b = min(a + per_message, len(t_ns))
                items = [
                    Event(
                        x=int(ev["x"][i]),
                        y=int(ev["y"][i]),
                        ts=stamp(int(t_ns[i])),
                        polarity=bool(ev["p"][i]),
                    )
                    for i in range(a, b)
                ]
                msg = EventArray(
                    header=Header(seq=k, stamp=stamp(int(t_ns[b - 1])), frame_id=side),
                    height=H,
                    width=W,
                    events=items,
                )
                writer.write(
                    conn, int(t_ns[b - 1]) + 1000, store.serialize_ros1(msg, "dvs_msgs/msg/EventArray")
                )
        for side in ("left", "right"):
            topic = f"/camera/{side}/image_mono"
            if topic in skip_topics:
                continue
            conn = writer.add_connection(topic, "sensor_msgs/msg/Image", typestore=store)
            for k, (s, im) in enumerate(zip(truth.frame_start_s, truth.images[side], strict=True)):
                whole, frac = s.split(".")
                t = int(whole) * 10**9 + int(frac) * 1000
                msg = Image(
                    header=Header(seq=k, stamp=stamp(t), frame_id=side),
                    height=H,
                    width=W,
                    encoding="mono8",
                    is_bigendian=0,
                    step=W,
                    data=im.reshape(-1).copy(),
                )
                writer.write(conn, t + 5_000_000, store.serialize_ros1(msg, "sensor_msgs/msg/Image"))
        if "/gt/pose" not in skip_topics:
            conn = writer.add_connection("/gt/pose", "geometry_msgs/msg/PoseStamped", typestore=store)
            for k, (t, m) in enumerate(zip(truth.gt_t_ns, truth.world_from_body, strict=True)):
                q = quat_xyzw(m[:3, :3])
                msg = PoseStamped(
                    header=Header(seq=k, stamp=stamp(int(t)), frame_id="world"),
                    pose=Pose(
                        position=Point(x=m[0, 3], y=m[1, 3], z=m[2, 3]),
                        orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
                    ),
                )
                writer.write(conn, int(t), store.serialize_ros1(msg, "geometry_msgs/msg/PoseStamped"))


# -- MVSEC ----------------------------------------------------------------------------------------


def kalibr_camchain(with_imu: bool = True, model: str = "equidistant") -> str:
    coeffs = [[-0.048, 0.012, -0.024, 0.008], [-0.047, 0.009, -0.019, 0.005]]
    text = ""
    cam_from_imu = [np.linalg.inv(CAM0_FROM[0]) @ np.linalg.inv(BODY_FROM_CAM0), None]
    cam_from_imu[1] = np.linalg.inv(CAM0_FROM[1]) @ cam_from_imu[0]
    for n in range(2):
        fx, fy, cx, cy = K[n]
        text += f"cam{n}:\n"
        if with_imu:
            text += "  T_cam_imu:\n" + matrix_yaml(cam_from_imu[n], "  ")
        if n == 1:
            text += "  T_cn_cnm1:\n" + matrix_yaml(np.linalg.inv(CAM0_FROM[1]), "  ")
        text += (
            f"  cam_overlaps: [{1 - n}]\n  camera_model: pinhole\n  distortion_coeffs: {coeffs[n]}\n"
            f"  distortion_model: {model}\n  intrinsics: [{fx}, {fy}, {cx}, {cy}]\n"
            f"  resolution: [{W}, {H}]\n  rostopic: /davis/{('left', 'right')[n]}/image_raw\n"
        )
    return text


@dataclass
class MvsecTruth:
    data: Path
    events: dict[str, np.ndarray]
    image_ts: dict[str, np.ndarray]
    images: dict[str, np.ndarray]
    pose_ts: np.ndarray
    poses: np.ndarray


def write_mvsec(root: Path, rng: np.random.Generator, seq: str = "indoor_flying1") -> MvsecTruth:
    root.mkdir(parents=True, exist_ok=True)
    t0 = 1_506_117_898.0
    events, ts, ims = {}, {}, {}
    data = root / f"{seq}_data.hdf5"
    with h5py.File(data, "w") as f:
        for side, shift in (("left", 0.0), ("right", 7e-6)):
            n = 15000
            t_us = np.sort(rng.integers(0, 1_000_000, n))
            ev = np.column_stack(
                [rng.integers(0, W, n), rng.integers(0, H, n), t0 + t_us * 1e-6, rng.choice([-1.0, 1.0], n)]
            ).astype(np.float64)
            events[side] = ev
            f.create_dataset(f"davis/{side}/events", data=ev, chunks=(4096, 4), **hdf5plugin.Blosc())
            ts[side] = t0 + 0.05 * np.arange(12) + shift
            ims[side] = rng.integers(0, 256, (12, H, W), dtype=np.uint8)
            f.create_dataset(f"davis/{side}/image_raw_ts", data=ts[side])
            f.create_dataset(f"davis/{side}/image_raw", data=ims[side], chunks=(1, H, W))
    _, poses = body_poses(8, 0, 1)
    pose_ts = t0 + 0.1 * np.arange(8)
    with h5py.File(root / f"{seq}_gt.hdf5", "w") as f:
        f.create_dataset("davis/left/pose", data=np.stack(poses))
        f.create_dataset("davis/left/pose_ts", data=pose_ts)
    (root / "camchain-imucam-indoor_flying.yaml").write_text(kalibr_camchain())
    return MvsecTruth(data, events, ts, ims, pose_ts, np.stack(poses))


# -- EuRoC ----------------------------------------------------------------------------------------


def write_euroc(root: Path, rng: np.random.Generator) -> dict[str, Any]:
    mav = root / "mav0"
    t = 1_403_636_579_763_555_584 + 50_000_000 * np.arange(6, dtype=np.int64)
    ims = {}
    for n, side in enumerate(("left", "right")):
        folder = mav / f"cam{n}"
        (folder / "data").mkdir(parents=True)
        ims[side] = images(rng, len(t))
        lines = ["#timestamp [ns],filename"]
        for ti, im in zip(t, ims[side], strict=True):
            cv2.imwrite(str(folder / "data" / f"{ti}.png"), im)
            lines.append(f"{ti},{ti}.png")
        (folder / "data.csv").write_text("\n".join(lines) + "\n")
        fx, fy, cx, cy = K[n]
        body_from_cam = BODY_FROM_CAM0 @ CAM0_FROM[n]
        (folder / "sensor.yaml").write_text(
            "sensor_type: camera\ncomment: VI-Sensor cam\nT_BS:\n  cols: 4\n  rows: 4\n"
            f"  data: [{', '.join(repr(float(v)) for v in body_from_cam.reshape(-1))}]\n"
            f"rate_hz: 20\nresolution: [{W}, {H}]\ncamera_model: pinhole\n"
            f"intrinsics: [{fx}, {fy}, {cx}, {cy}]\ndistortion_model: radial-tangential\n"
            f"distortion_coefficients: {D[n][:4]}\n"
        )
    gt_t, poses = body_poses(10, int(t[0]), 25_000_000)
    gt = mav / "state_groundtruth_estimate0"
    gt.mkdir()
    lines = [
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
        "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
        "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
        "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
    ]
    for ti, m in zip(gt_t, poses, strict=True):
        x, y, z, w = quat_xyzw(m[:3, :3])
        vals = [*m[:3, 3], w, x, y, z, *([0.0] * 9)]
        lines.append(f"{ti}," + ",".join(repr(float(v)) for v in vals))
    (gt / "data.csv").write_text("\n".join(lines) + "\n")
    return {"t": t, "images": ims, "gt_t": gt_t, "world_from_body": poses}
