"""VECtor's ROS1 bags, read directly with ``rosbags`` (no ROS installation).

Topics (SPEC-NOTES §7)::

    /prophesee/left/events, /prophesee/right/events   EventArray (dvs_msgs or prophesee_event_msgs:
                                                      header, height, width, events[] of
                                                      {uint16 x, uint16 y, time ts, bool polarity})
    /camera/left/image_mono, /camera/right/image_mono sensor_msgs/Image, mono8
    /gt/pose                                          geometry_msgs/PoseStamped, world_from_body

Events are decoded straight from the serialized message with one numpy structured view
(13 bytes per event) after the bag's own message definition has been checked to have exactly
that layout; a definition that differs is refused (naming the topic and field) rather than
misread. Opening the bag reads each event message once to index it (bag time, first and last
event time, count: 32 bytes per message); a window then reads only the messages it overlaps,
so memory is proportional to the window. Frames are decoded on access. Known cost: rosbags'
``Reader.messages(start=...)`` walks its in-memory index from the beginning on every call, so a
window late in a bag with very many messages pays one comparison per earlier message.

Frame stamps are the image headers' ``stamp``, taken as the start of exposure; the bag has no
exposure time, so ``exposure_ns`` (default 0) is an argument. Ground truth and calibration are
as for the synced release (:mod:`dhptam.datasets.vector`).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import FileError, InputError, ParseError
from ..geometry import SE3
from ._common import pair_stereo
from .sequence import EventStream, EventWindow, Frames, GroundTruth, RigCalibration, Sequence, WindowedEvents
from .tumvie import compose_poses

EVENT_TOPICS = {"left": "/prophesee/left/events", "right": "/prophesee/right/events"}
IMAGE_TOPICS = {"left": "/camera/left/image_mono", "right": "/camera/right/image_mono"}
GT_TOPIC = "/gt/pose"

EVENT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"), ("p", "u1")])
"""One serialized ROS1 event: x, y, ts (sec, nsec), polarity."""
_EVENT_FIELDS = [
    ("x", "uint16"),
    ("y", "uint16"),
    ("ts", "builtin_interfaces/msg/Time"),
    ("polarity", "bool"),
]


def _missing_rosbags() -> Exception:
    from ..errors import MissingDependencyError

    return MissingDependencyError("reading ROS bags needs rosbags: pip install 'dhptam[datasets]'")


class BagFile:
    """An open ROS1 bag with a lock (the frontend reads frames and events from two threads)."""

    def __init__(self, path: str | Path) -> None:
        try:
            from rosbags.rosbag1 import Reader, ReaderError
            from rosbags.typesys import Stores, get_typestore
        except ImportError:
            raise _missing_rosbags() from None
        self.path = Path(path)
        if not self.path.is_file():
            raise FileError(f"{self.path}: bag not found", path=str(self.path))
        self._error = ReaderError
        self.reader = Reader(self.path)
        try:
            self.reader.open()
        except ReaderError as err:
            hint = " (run `rosbag reindex` on it)" if "not indexed" in str(err) else ""
            raise FileError(
                f"{self.path}: cannot read the bag: {err}{hint}", path=str(self.path), field="index"
            ) from None
        self.typestore = get_typestore(Stores.ROS1_NOETIC)
        self.lock = threading.Lock()

    def connection(self, topic: str, msgtypes: tuple[str, ...] | None = None) -> Any:
        found = [c for c in self.reader.connections if c.topic == topic]
        if not found:
            have = sorted({c.topic for c in self.reader.connections})
            raise ParseError(
                f"{self.path}: topic {topic} is missing (the bag has {', '.join(have) or 'no topics'})",
                path=str(self.path),
                field=topic,
            )
        conn = found[0]
        if msgtypes is not None and conn.msgtype not in msgtypes:
            raise ParseError(
                f"{self.path}: topic {topic} has type {conn.msgtype}, expected {' or '.join(msgtypes)}",
                path=str(self.path),
                field=topic,
            )
        return conn

    def messages(
        self, conn: Any, start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[int, bytes]]:
        try:
            for _, t, raw in self.reader.messages(connections=[conn], start=start, stop=stop):
                yield t, raw
        except self._error as err:
            raise FileError(
                f"{self.path}: reading {conn.topic} failed: {err}", path=str(self.path), field=conn.topic
            ) from None

    def close(self) -> None:
        self.reader.close()


def _describe(fields: list[tuple[str, Any]]) -> list[tuple[str, str]]:
    """``(name, type)`` pairs of a parsed rosbags field list (sequences as ``type[]``)."""
    out = []
    for name, desc in fields:
        kind = desc[0].name
        if kind == "BASE":
            out.append((name, str(desc[1][0])))
        elif kind == "SEQUENCE":
            inner = desc[1][0]
            out.append((name, (str(inner[1][0]) if inner[0].name == "BASE" else str(inner[1])) + "[]"))
        else:
            out.append((name, str(desc[1])))
    return out


def _check_event_definition(bag: BagFile, conn: Any) -> None:
    """The topic must be (Header header, uint32 height, uint32 width, Event[] events) with
    Event = (uint16 x, uint16 y, time ts, bool polarity): the layout :func:`decode_events` reads."""
    from rosbags.typesys import get_types_from_msg

    try:
        types = get_types_from_msg(conn.msgdef.data, conn.msgtype)
    except Exception as err:  # rosbags raises several parser errors
        raise ParseError(
            f"{bag.path}: cannot parse the message definition of {conn.topic} ({err})",
            path=str(bag.path),
            field=conn.topic,
        ) from None
    array = _describe(types[conn.msgtype][1]) if conn.msgtype in types else []
    event_type = array[3][1][:-2] if len(array) == 4 else ""
    want = [
        ("header", "std_msgs/msg/Header"),
        ("height", "uint32"),
        ("width", "uint32"),
        ("events", f"{event_type}[]"),
    ]
    got = [*array, *(_describe(types[event_type][1]) if event_type in types else [])]
    if got != [*want, *_EVENT_FIELDS]:
        raise ParseError(
            f"{bag.path}: {conn.topic} ({conn.msgtype}) must be an EventArray {want} of events "
            f"{_EVENT_FIELDS} (dvs_msgs/prophesee_event_msgs layout); the bag defines {got}",
            path=str(bag.path),
            field=f"{conn.topic}.events",
        )


def _skip_header(raw: bytes | memoryview, path: Path, topic: str) -> int:
    """Byte offset after std_msgs/Header (seq u32, stamp 2×u32, frame_id string)."""
    if len(raw) < 16:
        raise ParseError(f"{path}: a {topic} message is truncated", path=str(path), field=topic)
    n = int(np.frombuffer(raw, "<u4", 1, 12)[0])
    return 16 + n


def decode_events(raw: bytes | memoryview, path: Path, topic: str) -> npt.NDArray[np.void]:
    """The events of one serialized EventArray as a structured array (no copy)."""
    off = _skip_header(raw, path, topic) + 8  # height, width
    if len(raw) < off + 4:
        raise ParseError(f"{path}: a {topic} message is truncated", path=str(path), field=topic)
    n = int(np.frombuffer(raw, "<u4", 1, off)[0])
    if len(raw) != off + 4 + n * EVENT_DTYPE.itemsize:
        raise ParseError(
            f"{path}: a {topic} message holds {len(raw) - off - 4} bytes of events, expected "
            f"{n} × {EVENT_DTYPE.itemsize}",
            path=str(path),
            field=topic,
        )
    return np.frombuffer(raw, EVENT_DTYPE, n, off + 4)


def _ns(ev: npt.NDArray[np.void]) -> npt.NDArray[np.int64]:
    return ev["sec"].astype(np.int64) * 1_000_000_000 + ev["nsec"].astype(np.int64)


class BagEventStream(WindowedEvents):
    """Events of one topic of a bag, by time window (an :class:`~dhptam.datasets.EventStream`)."""

    def __init__(self, bag: BagFile, topic: str) -> None:
        self.bag = bag
        self.topic = topic
        self.conn = bag.connection(topic)
        _check_event_definition(bag, self.conn)
        bag_t, first, last, count = [], [], [], []
        with bag.lock:
            for t, raw in bag.messages(self.conn):
                ev = decode_events(raw, bag.path, topic)
                if ev.size == 0:
                    continue
                ts = _ns(ev[[0, -1]])
                bag_t.append(t)
                first.append(int(ts[0]))
                last.append(int(ts[1]))
                count.append(ev.size)
        self._bag_t = np.asarray(bag_t, np.int64)
        self._first = np.asarray(first, np.int64)
        self._last = np.asarray(last, np.int64)
        if np.any(self._last < self._first) or np.any(self._first[1:] < self._last[:-1]):
            raise ParseError(
                f"{bag.path}: {topic} events are not in time order across messages",
                path=str(bag.path),
                field=topic,
            )
        self._start = np.concatenate([[0], np.cumsum(np.asarray(count, np.int64))])
        # Messages sharing a bag time with an earlier one: skipped when reading from that time.
        same = np.concatenate([[False], np.diff(self._bag_t) == 0]) if len(bag_t) else np.zeros(0, bool)
        run_start = np.maximum.accumulate(np.where(~same, np.arange(len(bag_t)), 0)) if len(bag_t) else same
        self._dup_before = np.arange(len(bag_t)) - run_start
        if np.any(np.diff(self._bag_t) < 0):
            raise ParseError(
                f"{bag.path}: {topic} messages are not in bag-time order", path=str(bag.path), field=topic
            )

    def __len__(self) -> int:
        return int(self._start[-1])

    @property
    def t_range_ns(self) -> tuple[int, int]:
        """``[first, last + 1)`` in ns."""
        return (0, 0) if len(self._first) == 0 else (int(self._first[0]), int(self._last[-1]) + 1)

    def _messages(self, k0: int, k1: int) -> npt.NDArray[np.void]:
        """Events of messages ``k0 .. k1 - 1`` concatenated."""
        if k1 <= k0:
            return np.empty(0, EVENT_DTYPE)
        parts = []
        skip = int(self._dup_before[k0])
        want = k1 - k0
        with self.bag.lock:
            for _, raw in self.bag.messages(
                self.conn, start=int(self._bag_t[k0]), stop=int(self._bag_t[k1 - 1]) + 1
            ):
                ev = decode_events(raw, self.bag.path, self.topic)
                if ev.size == 0:
                    continue  # not indexed
                if skip:
                    skip -= 1
                    continue
                parts.append(ev)
                if len(parts) == want:
                    break
        return np.concatenate(parts) if parts else np.empty(0, EVENT_DTYPE)

    def _lower(self, t_ns: int) -> int:
        """Global index of the first event with t >= t_ns."""
        k = int(np.searchsorted(self._last, t_ns, side="left"))  # first message reaching t_ns
        if k >= len(self._last):
            return len(self)
        if self._first[k] >= t_ns:
            return int(self._start[k])
        ev = self._messages(k, k + 1)
        return int(self._start[k]) + int(np.searchsorted(_ns(ev), t_ns, side="left"))

    def index_range(self, t0_ns: int, t1_ns: int) -> tuple[int, int]:
        """Indices ``[i0, i1)`` of the events with ``t0_ns <= t < t1_ns``."""
        if int(t1_ns) <= int(t0_ns):
            return (0, 0)
        return (self._lower(int(t0_ns)), self._lower(int(t1_ns)))

    def window(self, t0_ns: int, t1_ns: int) -> EventWindow:
        """The events with ``t0_ns <= t < t1_ns``."""
        return self.slice(*self.index_range(t0_ns, t1_ns))

    def slice(self, i0: int, i1: int) -> EventWindow:
        """Events ``i0 .. i1 - 1`` in bag order."""
        i0, i1 = max(0, int(i0)), min(len(self), int(i1))
        if i1 <= i0:
            ev = np.empty(0, EVENT_DTYPE)
        else:
            k0 = int(np.searchsorted(self._start, i0, side="right")) - 1
            k1 = int(np.searchsorted(self._start, i1, side="left"))
            base = int(self._start[k0])
            ev = self._messages(k0, k1)[i0 - base : i1 - base]
        t_ns = _ns(ev)
        if t_ns.size > 1 and np.any(t_ns[1:] < t_ns[:-1]):
            raise ParseError(
                f"{self.bag.path}: {self.topic} events are not sorted",
                path=str(self.bag.path),
                field=self.topic,
            )
        return EventWindow(x=ev["x"].copy(), y=ev["y"].copy(), t_ns=t_ns, p=(ev["p"] != 0).astype(np.int8))

    def close(self) -> None:
        """The bag is closed by its sequence."""


class BagFrames(Frames):
    """Stereo frames of two image topics, decoded from the bag on access."""

    def __init__(
        self,
        bag: BagFile,
        conns: dict[str, Any],
        bag_t: dict[str, npt.NDArray[np.int64]],
        t_ns: npt.NDArray[np.int64],
        exposure_ns: npt.NDArray[np.int64],
        sizes: dict[str, tuple[int, int]],
    ) -> None:
        refs = {s: [Path(f"{bag.path}#{conns[s].topic}@{int(t)}") for t in bag_t[s]] for s in bag_t}
        super().__init__(t_ns, exposure_ns, refs["left"], refs["right"], sizes["left"], sizes["right"])
        self._bag = bag
        self._conns = conns
        self._bag_t = bag_t

    def _image(self, i: int, side: str) -> npt.NDArray[np.uint8]:
        conn = self._conns[side]
        t = int(self._bag_t[side][i])
        with self._bag.lock:
            raw = next(iter(self._bag.messages(conn, start=t, stop=t + 1)), None)
        if raw is None:
            raise FileError(
                f"{self._bag.path}: {conn.topic} message at {t} ns vanished", path=str(self._bag.path)
            )
        msg: Any = self._bag.typestore.deserialize_ros1(raw[1], "sensor_msgs/msg/Image")
        if msg.encoding not in ("mono8", "8UC1"):
            raise InputError(
                f"{self._bag.path}: {conn.topic} has encoding {msg.encoding!r}, expected mono8",
                path=str(self._bag.path),
                field=f"{conn.topic}.encoding",
            )
        h, w, step = int(msg.height), int(msg.width), int(msg.step)
        data = np.asarray(msg.data, np.uint8)
        if step < w or data.size != h * step:
            raise ParseError(
                f"{self._bag.path}: {conn.topic} image of {w}x{h} has {data.size} bytes with step {step}",
                path=str(self._bag.path),
                field=f"{conn.topic}.data",
            )
        size = self._sizes[side]
        if size is not None and (w, h) != size:
            raise InputError(
                f"{self._bag.path}: {conn.topic} images are {w}x{h} but the calibration says "
                f"{size[0]}x{size[1]}",
                path=str(self._bag.path),
                field="resolution",
            )
        return np.ascontiguousarray(data.reshape(h, step)[:, :w])


def _image_stamps(bag: BagFile, conn: Any) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    bag_t, stamp = [], []
    with bag.lock:
        for t, raw in bag.messages(conn):
            _skip_header(raw, bag.path, conn.topic)
            sec, nsec = np.frombuffer(raw, "<u4", 2, 4)
            bag_t.append(t)
            stamp.append(int(sec) * 1_000_000_000 + int(nsec))
    return np.asarray(bag_t, np.int64), np.asarray(stamp, np.int64)


def _ground_truth(bag: BagFile, body_from_left: SE3) -> GroundTruth:
    conn = bag.connection(GT_TOPIC, ("geometry_msgs/msg/PoseStamped",))
    t_ns, rows = [], []
    with bag.lock:
        for _, raw in bag.messages(conn):
            msg: Any = bag.typestore.deserialize_ros1(raw, "geometry_msgs/msg/PoseStamped")
            p, q = msg.pose.position, msg.pose.orientation
            t_ns.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
            rows.append([p.x, p.y, p.z, q.x, q.y, q.z, q.w])
    t = np.asarray(t_ns, np.int64)
    world_from_body = np.asarray(rows, np.float64).reshape(-1, 7)
    if np.any(np.diff(t) <= 0):
        raise ParseError(
            f"{bag.path}: {GT_TOPIC} stamps are not strictly increasing", path=str(bag.path), field=GT_TOPIC
        )
    norms = np.linalg.norm(world_from_body[:, 3:], axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-2) or not np.all(np.isfinite(world_from_body)):
        raise InputError(
            f"{bag.path}: {GT_TOPIC} holds a non-unit quaternion or NaN", path=str(bag.path), field=GT_TOPIC
        )
    world_from_body[:, 3:] /= norms[:, None]
    return GroundTruth(t_ns=t, world_from_cam=compose_poses(world_from_body, body_from_left))


def load_vector_bag(
    path: str | Path,
    *,
    calibration: str | Path | RigCalibration | None = None,
    body_from_cam0: str | Path | SE3 | None = None,
    exposure_ns: int = 0,
    pair_tolerance_ns: int = 1_000_000,
) -> Sequence:
    """Open a VECtor ROS1 bag as a :class:`~dhptam.datasets.Sequence`.

    ``calibration`` and ``body_from_cam0`` are as in :func:`~dhptam.datasets.load_vector`
    (the calibration folder is looked for beside the bag by default); ground truth is read when
    the bag has ``/gt/pose``.
    """
    from .vector import _body_from_cam0, _calibration_folder, read_vector_calibration

    bag_path = Path(path)
    calib_dir: Path | None = None
    if isinstance(calibration, RigCalibration):
        rig = calibration
    else:
        calib_dir = Path(calibration) if calibration is not None else _calibration_folder(bag_path.parent)
        rig = read_vector_calibration(calib_dir)
    bag = BagFile(bag_path)
    try:
        conns = {s: bag.connection(IMAGE_TOPICS[s], ("sensor_msgs/msg/Image",)) for s in ("left", "right")}
        stamps = {s: _image_stamps(bag, conns[s]) for s in ("left", "right")}
        for s in ("left", "right"):
            if np.any(np.diff(stamps[s][1]) <= 0):
                raise ParseError(
                    f"{bag_path}: {IMAGE_TOPICS[s]} header stamps are not strictly increasing",
                    path=str(bag_path),
                    field=IMAGE_TOPICS[s],
                )
        i_l, i_r = pair_stereo(stamps["left"][1], stamps["right"][1], pair_tolerance_ns)
        sizes = {
            s: (rig.cameras[f"frame_{s}"].width, rig.cameras[f"frame_{s}"].height) for s in ("left", "right")
        }
        frames = BagFrames(
            bag,
            conns,
            {"left": stamps["left"][0][i_l], "right": stamps["right"][0][i_r]},
            stamps["left"][1][i_l],
            np.full(len(i_l), int(exposure_ns), np.int64),
            sizes,
        )
        events: dict[str, EventStream] = {s: BagEventStream(bag, EVENT_TOPICS[s]) for s in ("left", "right")}
        ground_truth = None
        if any(c.topic == GT_TOPIC for c in bag.reader.connections):
            body = _body_from_cam0(body_from_cam0, calib_dir, bag_path)
            ground_truth = _ground_truth(bag, body @ rig.imu_from_cam["frame_left"])
    except BaseException:
        bag.close()
        raise
    return Sequence(bag_path.stem, bag_path, rig, frames, events, ground_truth, on_close=bag.close)


__all__ = ["EVENT_DTYPE", "BagEventStream", "BagFile", "BagFrames", "decode_events", "load_vector_bag"]
