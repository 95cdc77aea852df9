"""MCAP logs: write a :class:`~dhptam.datasets.Sequence` into one MCAP file and read it back.

The file is dhptam's own recording format (layout in ``dhptam_core::io::mcap``; summary in
``docs/ARCHITECTURE.md``). Every channel is protobuf-encoded with its schema's
``FileDescriptorSet``, so Foxglove shows the frames, calibrations and poses with no plugin:

==========================  ==============================  ====================================
topic                       schema                          content
==========================  ==============================  ====================================
``/events/{left,right}``    ``dhptam.EventBatch``           events in fixed-size batches
``/frames/{left,right}``    ``foxglove.RawImage`` or        ``mono8`` frames, at exposure start
                            ``foxglove.CompressedImage``    (``frame_format="png"``: lossless PNG)
``/calibration/<camera>``   ``foxglove.CameraCalibration``  one per camera of the rig
``/ground_truth``           ``foxglove.PoseInFrame``        ``world_from_cam`` of the left frame
                                                            camera (when the sequence has one)
==========================  ==============================  ====================================

What the Foxglove schemas cannot carry exactly (the camera model and its parameters,
``imu_from_cam``, ``imu_from_marker``, the exposures) is stored in the metadata record
``dhptam.sequence`` as JSON, so :func:`load_mcap` returns a sequence equal to the one written.

Example::

    >>> import tempfile, numpy as np
    >>> from dhptam import SE3, Camera
    >>> from dhptam.datasets import CAMERA_KEYS, RigCalibration, TumVieWriter, load_tumvie
    >>> from dhptam.datasets.mcap import load_mcap, write_sequence
    >>> cam = Camera("kb4", [100.0, 100.0, 31.5, 23.5, 0.0, 0.0, 0.0, 0.0], 64, 48)
    >>> rig = RigCalibration({k: cam for k in CAMERA_KEYS}, {k: SE3() for k in CAMERA_KEYS})
    >>> out = tempfile.mkdtemp()
    >>> with TumVieWriter(out, "demo", rig, SE3()) as w:
    ...     w.add_frame_pair(0, 5_000_000, np.zeros((48, 64), np.uint8), np.zeros((48, 64), np.uint8))
    ...     w.add_events("left", [1, 2, 3], [4, 5, 6], [1_000, 2_500_000, 7_000_000], [1, 0, 1])
    ...     w.add_events("right", [7], [8], [9_000], [0])
    >>> with load_tumvie(f"{out}/demo") as seq:
    ...     _ = write_sequence(seq, f"{out}/demo.mcap", progress=False)
    >>> with load_mcap(f"{out}/demo.mcap") as log:
    ...     len(log.frames), log.events["left"].window(0, 5_000_000).t_ns.tolist()
    (1, [1000, 2500000])
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .._core import McapReader, McapWriter
from ..errors import InputError, ParseError
from ..geometry import SE3, Camera
from .sequence import (
    CAMERA_KEYS,
    EVENT_SIDES,
    EventWindow,
    FramePair,
    Frames,
    GroundTruth,
    RigCalibration,
    Sequence,
    WindowedEvents,
)

EVENTS_TOPIC = "/events/{side}"
FRAMES_TOPIC = "/frames/{side}"
CALIBRATION_TOPIC = "/calibration/{camera}"
GROUND_TRUTH_TOPIC = "/ground_truth"
SEQUENCE_METADATA = "dhptam.sequence"
"""Name of the metadata record holding the exact calibration, exposures and sequence name."""
RAW_IMAGE = "foxglove.RawImage"
COMPRESSED_IMAGE = "foxglove.CompressedImage"
FRAME_FORMATS = ("raw", "png")
"""How frames are written: ``raw`` (``foxglove.RawImage`` mono8) or ``png`` (lossless PNG in a
``foxglove.CompressedImage``: smaller logs, slower to write)."""

# Events handed to the writer per call: bounds the memory write_sequence needs.
_EVENT_BLOCK = 1 << 20

# Camera models and the ROS/Foxglove distortion model names Foxglove's image panels know.
_DISTORTION_MODELS = {"kb4": "kannala_brandt", "radtan": "plumb_bob", "pinhole": "plumb_bob"}


def _pose_row(pose: SE3) -> list[float]:
    t = pose.translation
    q = pose.rotation.quat_xyzw()
    return [float(v) for v in (*t, *q)]


def _pose_from_row(row: Any, path: Path, field: str) -> SE3:
    values = np.asarray(row, dtype=np.float64)
    if values.shape != (7,) or not np.all(np.isfinite(values)):
        raise ParseError(
            f"{path}: metadata {SEQUENCE_METADATA}: {field} must be 7 numbers x y z qx qy qz qw",
            path=str(path),
            field=field,
        )
    return SE3.from_translation_quat_xyzw(values[:3], values[3:])


def _calibration_message(camera: Camera) -> dict[str, Any]:
    """Foxglove's CameraCalibration fields for a camera (ROS CameraInfo conventions)."""
    fx, fy, cx, cy = (float(v) for v in camera.params[:4])
    d = [float(v) for v in camera.params[4:]]
    if camera.model == "radtan" and len(d) == 4:
        d = [*d, 0.0]  # plumb_bob is k1 k2 p1 p2 k3
    return {
        "distortion_model": _DISTORTION_MODELS.get(camera.model, camera.model),
        "d": d,
        "k": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    }


def _progress(total: int, enabled: bool, desc: str) -> Any:
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=desc, unit="msg", leave=False)


def _check_frame_format(frame_format: str) -> None:
    if frame_format not in FRAME_FORMATS:
        raise InputError(
            f"frame_format must be one of {', '.join(FRAME_FORMATS)}, got {frame_format!r}",
            field="frame_format",
        )


def _add_frame(
    writer: McapWriter, side: str, t_ns: int, image: npt.NDArray[np.uint8], frame_format: str
) -> None:
    """Write one frame of ``side`` as a RawImage or a PNG CompressedImage."""
    topic, frame_id = FRAMES_TOPIC.format(side=side), f"frame_{side}"
    if frame_format == "raw":
        writer.add_image(topic, frame_id, t_ns, image)
        return
    import cv2

    ok, png = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise InputError(f"{topic}: frame at {t_ns} ns could not be encoded as PNG", field=topic)
    writer.add_compressed_image(topic, frame_id, t_ns, png.tobytes(), "png")


def sequence_start_ns(sequence: Sequence) -> int:
    """The earliest frame or event time of ``sequence`` (0 when it has neither): the origin of
    :func:`write_sequence`'s ``start_s``."""
    starts = [int(sequence.frames.t_ns[0])] if len(sequence.frames) else []
    starts += [source.t_range_ns[0] for source in sequence.events.values() if len(source)]
    return min(starts, default=0)


def write_sequence(
    sequence: Sequence,
    path: str | Path,
    *,
    start_s: float | None = None,
    duration_s: float | None = None,
    progress: bool = True,
    compression: str = "zstd",
    frame_format: str = "raw",
) -> Path:
    """Write ``sequence`` (or a time slice of it) into the MCAP log ``path``.

    Parameters
    ----------
    sequence
        Any :class:`Sequence` (TUM-VIE, simulated, or read from another log).
    path
        The log to create. It is written to a temporary file beside it and renamed at the end,
        so ``path`` never holds a partial log (an error or an interrupt leaves it untouched).
    start_s, duration_s
        Keep only ``[t0 + start_s, t0 + start_s + duration_s)``, ``t0`` being the sequence's
        earliest frame or event time; ``None`` keeps from the start / to the end.
    progress
        Show a tqdm bar on stderr (when tqdm is installed).
    compression
        Chunk compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
    frame_format
        ``"raw"`` (default): frames as ``foxglove.RawImage``; ``"png"``: as lossless PNG in
        ``foxglove.CompressedImage`` (read back identical).

    Returns
    -------
    The path of the written log.
    """
    path = Path(path)
    _check_frame_format(frame_format)
    ends = [int(sequence.frames.t_ns[-1]) + 1] if len(sequence.frames) else []
    ends += [source.t_range_ns[1] for source in sequence.events.values() if len(source)]
    t_first = sequence_start_ns(sequence)
    t0 = t_first + (0 if start_s is None else round(float(start_s) * 1e9))
    t1 = max(ends, default=0) if duration_s is None else t0 + round(float(duration_s) * 1e9)
    if duration_s is not None and duration_s <= 0:
        raise InputError(f"duration_s must be positive, got {duration_s}", field="duration_s")
    if t0 < 0:
        raise InputError(f"start_s places the slice before time 0 ({t0} ns)", field="start_s")

    frames = sequence.frames
    frame_ids = [i for i in range(len(frames)) if t0 <= int(frames.t_ns[i]) < t1]
    ranges = {side: src.index_range(t0, t1) for side, src in sequence.events.items()}
    blocks = sum(-(-(b - a) // _EVENT_BLOCK) for a, b in ranges.values())
    bar = _progress(len(frame_ids) + blocks, progress, f"mcap {path.name}")

    writer = McapWriter(path, compression=compression)
    try:
        _write_calibration(writer, sequence, t0)
        for side, src in sequence.events.items():
            a, b = ranges[side]
            for i in range(a, b, _EVENT_BLOCK):
                w = src.slice(i, min(i + _EVENT_BLOCK, b))
                writer.add_events(EVENTS_TOPIC.format(side=side), f"event_{side}", w.x, w.y, w.t_ns, w.p)
                if bar is not None:
                    bar.update(1)
        for i in frame_ids:
            pair = frames[i]
            _add_frame(writer, "left", pair.t_ns, pair.left, frame_format)
            _add_frame(writer, "right", pair.t_ns, pair.right, frame_format)
            if bar is not None:
                bar.update(1)
        gt = sequence.ground_truth
        if gt is not None:
            # Without a slice, every pose is kept (ground truth may outlast frames and events).
            keep = np.ones(len(gt), bool)
            if start_s is not None:
                keep &= gt.t_ns >= t0
            if duration_s is not None:
                keep &= gt.t_ns < t1
            writer.add_poses(GROUND_TRUTH_TOPIC, "world", gt.t_ns[keep], gt.world_from_cam[keep])
        exposures = [int(frames.exposure_ns[i]) for i in frame_ids]
        writer.add_metadata(SEQUENCE_METADATA, _sequence_metadata(sequence, exposures))
        writer.finish()
    except BaseException:
        writer.abort()
        raise
    finally:
        if bar is not None:
            bar.close()
    return path


def _write_calibration(writer: McapWriter, sequence: Sequence, t_ns: int) -> None:
    for key in CAMERA_KEYS:
        cam = sequence.calibration.cameras[key]
        m = _calibration_message(cam)
        writer.add_calibration(
            CALIBRATION_TOPIC.format(camera=key),
            key,
            t_ns,
            cam.width,
            cam.height,
            m["distortion_model"],
            m["d"],
            m["k"],
            m["r"],
            m["p"],
        )


def _sequence_metadata(sequence: Sequence, exposures: list[int]) -> dict[str, str]:
    rig = sequence.calibration
    cameras = {
        k: {
            "model": rig.cameras[k].model,
            "params": [float(v) for v in rig.cameras[k].params],
            "width": rig.cameras[k].width,
            "height": rig.cameras[k].height,
        }
        for k in CAMERA_KEYS
    }
    return {
        "format": "1",
        "name": sequence.name,
        "cameras": json.dumps(cameras),
        "imu_from_cam": json.dumps({k: _pose_row(rig.imu_from_cam[k]) for k in CAMERA_KEYS}),
        "imu_from_marker": json.dumps(
            None if sequence.imu_from_marker is None else _pose_row(sequence.imu_from_marker)
        ),
        "exposure_ns": json.dumps(exposures),
    }


class McapFrames(Frames):
    """Stereo frame pairs of an MCAP log; images are decoded from the log on access, from
    ``foxglove.RawImage`` (mono8) or ``foxglove.CompressedImage`` (PNG or JPEG) messages."""

    def __init__(
        self,
        reader: McapReader,
        t_ns: npt.NDArray[np.int64],
        exposure_ns: npt.NDArray[np.int64],
        sizes: dict[str, tuple[int, int]],
        schemas: dict[str, str] | None = None,
    ) -> None:
        n = len(t_ns)
        path = Path(reader.path)
        super().__init__(t_ns, exposure_ns, [path] * n, [path] * n, sizes["left"], sizes["right"])
        self._reader = reader
        self._schemas = schemas or {"left": RAW_IMAGE, "right": RAW_IMAGE}

    def __getitem__(self, index: int) -> FramePair:
        n = len(self)
        i = int(index)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame index {index} out of range for {n} frames")
        images = {side: self._image(side, i) for side in ("left", "right")}
        return FramePair(
            index=i,
            t_ns=int(self.t_ns[i]),
            exposure_ns=int(self.exposure_ns[i]),
            left=images["left"],
            right=images["right"],
        )

    def _image(self, side: str, i: int) -> npt.NDArray[np.uint8]:
        topic = FRAMES_TOPIC.format(side=side)
        if self._schemas[side] == COMPRESSED_IMAGE:
            image = self._decode(topic, i)
        else:
            ((_, _, image),) = self._reader.images(topic, i, i + 1)
        size = self._sizes[side]
        if (
            image.ndim != 2
            or image.dtype != np.uint8
            or (size is not None and (image.shape[1], image.shape[0]) != size)
        ):
            raise ParseError(
                f"{self._reader.path}: {topic} frame {i} is {image.shape} ({image.dtype}); the "
                f"calibration of the {side} frame camera says mono8 {size}",
                path=str(self._reader.path),
                field=topic,
            )
        return np.asarray(image, dtype=np.uint8)

    def _decode(self, topic: str, i: int) -> npt.NDArray[Any]:
        import cv2

        ((_, _, fmt, data),) = self._reader.compressed_images(topic, i, i + 1)
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ParseError(
                f"{self._reader.path}: {topic} frame {i}: its {len(data)} bytes of format {fmt!r} do "
                "not decode as an image",
                path=str(self._reader.path),
                field=topic,
            )
        return np.asarray(image)


class McapEventSource(WindowedEvents):
    """Random access by time window to the events of one camera in an MCAP log.

    Same public interface as :class:`~dhptam.datasets.EventSource`; windows are located through
    the log's message index (one batch decoded per bound) and only the chunks holding a
    window's batches are decompressed. The arrays a window returns own the decoded buffers
    (no copy between Rust and numpy).
    """

    def __init__(self, reader: McapReader, side: str) -> None:
        self.path = Path(reader.path)
        self.topic = EVENTS_TOPIC.format(side=side)
        self._reader: McapReader | None = reader
        self._n = reader.event_count(self.topic)
        self._t_range = reader.event_time_range(self.topic)

    def _open(self) -> McapReader:
        if self._reader is None:
            raise InputError(f"{self.path}: {self.topic}: the event source is closed", field=self.topic)
        return self._reader

    def __len__(self) -> int:
        return self._n

    @property
    def has_index(self) -> bool:
        """Always true: MCAP logs carry message indexes."""
        return True

    @property
    def t_range_ns(self) -> tuple[int, int]:
        """Half-open ``[first, last + 1)`` span of the events; ``(0, 0)`` when empty."""
        return (int(self._t_range[0]), int(self._t_range[1]))

    def window(self, t0_ns: int, t1_ns: int) -> EventWindow:
        """The events with ``t0_ns <= t < t1_ns`` (empty when ``t1_ns <= t0_ns``)."""
        i0, i1 = self.index_range(t0_ns, t1_ns)
        return self.slice(i0, i1)

    def index_range(self, t0_ns: int, t1_ns: int) -> tuple[int, int]:
        """Indices ``[i0, i1)`` of the events with ``t0_ns <= t < t1_ns``."""
        t0, t1 = int(t0_ns), int(t1_ns)
        if t1 <= t0 or self._n == 0:
            return (0, 0)
        # Log times are unsigned: clamp instead of passing negative times through.
        i0, i1 = self._open().event_index_range(self.topic, max(t0, 0), max(t1, 0))
        return (int(i0), int(i1))

    def slice(self, i0: int, i1: int) -> EventWindow:
        """Events ``i0 .. i1 - 1`` in log order."""
        i0, i1 = max(0, int(i0)), min(self._n, int(i1))
        if i1 <= i0:
            return EventWindow(
                x=np.empty(0, np.uint16),
                y=np.empty(0, np.uint16),
                t_ns=np.empty(0, np.int64),
                p=np.empty(0, np.int8),
            )
        x, y, t, p = self._open().event_slice(self.topic, i0, i1)
        return EventWindow(x=x, y=y, t_ns=t, p=p)

    def close(self) -> None:
        """Release the log (windows can no longer be read)."""
        self._reader = None

    def __repr__(self) -> str:
        return f"McapEventSource({str(self.path)!r}, {self.topic}, events={self._n})"


def _json_field(meta: dict[str, str], key: str, path: Path) -> Any:
    if key not in meta:
        raise ParseError(
            f"{path}: metadata {SEQUENCE_METADATA} lacks the entry {key!r}",
            path=str(path),
            field=f"{SEQUENCE_METADATA}.{key}",
        )
    try:
        return json.loads(meta[key])
    except json.JSONDecodeError as err:
        raise ParseError(
            f"{path}: metadata {SEQUENCE_METADATA}.{key} is not valid JSON ({err})",
            path=str(path),
            field=f"{SEQUENCE_METADATA}.{key}",
        ) from None


def _read_calibration(meta: dict[str, str], path: Path) -> RigCalibration:
    cameras_json = _json_field(meta, "cameras", path)
    poses_json = _json_field(meta, "imu_from_cam", path)
    cameras: dict[str, Camera] = {}
    imu_from_cam: dict[str, SE3] = {}
    for key in CAMERA_KEYS:
        try:
            c = cameras_json[key]
            cameras[key] = Camera(
                str(c["model"]), [float(v) for v in c["params"]], int(c["width"]), int(c["height"])
            )
        except (KeyError, TypeError, ValueError) as err:
            raise ParseError(
                f"{path}: metadata {SEQUENCE_METADATA}.cameras[{key!r}] is incomplete or invalid ({err})",
                path=str(path),
                field=f"{SEQUENCE_METADATA}.cameras.{key}",
            ) from None
        if key not in poses_json:
            raise ParseError(
                f"{path}: metadata {SEQUENCE_METADATA}.imu_from_cam lacks {key!r}",
                path=str(path),
                field=f"{SEQUENCE_METADATA}.imu_from_cam.{key}",
            )
        imu_from_cam[key] = _pose_from_row(poses_json[key], path, f"{SEQUENCE_METADATA}.imu_from_cam.{key}")
    return RigCalibration(cameras, imu_from_cam)


def _frame_schema(reader: McapReader, side: str, path: Path) -> str:
    """The schema of a frame channel: RawImage or CompressedImage, else a ParseError."""
    topic = FRAMES_TOPIC.format(side=side)
    info = reader.topics().get(topic)
    if info is None:
        raise ParseError(
            f"{path}: channel {topic} is missing (the log has {sorted(reader.topics())})",
            path=str(path),
            field=topic,
        )
    schema = str(info["schema_name"])
    if schema not in (RAW_IMAGE, COMPRESSED_IMAGE):
        raise ParseError(
            f"{path}: channel {topic} carries {schema!r} messages; expected {RAW_IMAGE} or "
            f"{COMPRESSED_IMAGE}",
            path=str(path),
            field=topic,
        )
    return schema


def load_mcap(path: str | Path) -> Sequence:
    """Read a log written by :func:`write_sequence` (or ``dhptam run --record``) as a sequence.

    Raises :class:`~dhptam.errors.ParseError` naming the file and the channel (or metadata
    entry) when the log is damaged or lacks one, and :class:`~dhptam.errors.FileError` when it
    cannot be opened.
    """
    path = Path(path)
    reader = McapReader(path)
    meta = reader.metadata(SEQUENCE_METADATA)
    if meta is None:
        raise ParseError(
            f"{path}: metadata record {SEQUENCE_METADATA!r} is missing; the log was not written by "
            "dhptam.datasets.mcap.write_sequence",
            path=str(path),
            field=SEQUENCE_METADATA,
        )
    calibration = _read_calibration(meta, path)
    schemas = {side: _frame_schema(reader, side, path) for side in ("left", "right")}
    times = {
        side: np.asarray(reader.log_times(FRAMES_TOPIC.format(side=side), schemas[side]), np.int64)
        for side in ("left", "right")
    }
    if not np.array_equal(times["left"], times["right"]):
        raise ParseError(
            f"{path}: /frames/left and /frames/right disagree: {len(times['left'])} and "
            f"{len(times['right'])} frames, or different timestamps",
            path=str(path),
            field="/frames/right",
        )
    exposure = np.asarray(_json_field(meta, "exposure_ns", path), dtype=np.int64)
    if exposure.shape != times["left"].shape:
        raise ParseError(
            f"{path}: metadata {SEQUENCE_METADATA}.exposure_ns has {exposure.size} entries for "
            f"{len(times['left'])} frames",
            path=str(path),
            field=f"{SEQUENCE_METADATA}.exposure_ns",
        )
    cams = calibration.cameras
    sizes = {side: (cams[f"frame_{side}"].width, cams[f"frame_{side}"].height) for side in ("left", "right")}
    frames = McapFrames(reader, times["left"], exposure, sizes, schemas)
    events = {side: McapEventSource(reader, side) for side in EVENT_SIDES}
    ground_truth = None
    if GROUND_TRUTH_TOPIC in reader.topics():
        t_ns, poses, _ = reader.poses(GROUND_TRUTH_TOPIC)
        ground_truth = GroundTruth(t_ns=t_ns, world_from_cam=poses)
    marker = _json_field(meta, "imu_from_marker", path)
    imu_from_marker = None if marker is None else _pose_from_row(marker, path, "imu_from_marker")
    return Sequence(
        name=str(meta.get("name", path.stem)),
        path=path,
        calibration=calibration,
        frames=frames,
        events=events,
        ground_truth=ground_truth,
        imu_from_marker=imu_from_marker,
    )


def _pose_rows(matrices: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(N, 4, 4) transforms as (N, 7) rows ``x y z qx qy qz qw``."""
    rows = np.empty((len(matrices), 7))
    for i, m in enumerate(matrices):
        rows[i] = _pose_row(SE3.from_matrix(m))
    return rows


class McapRecorder:
    """Records a run's inputs and outputs into one MCAP log (``dhptam run --record``).

    Inputs, as the run reads them: the calibration, every processed frame pair and the raw
    events up to each frame's fusion time (so the events of consecutive frames tile the time
    line), and the ground truth over the recorded span. Outputs, at :meth:`finish`: the frame
    trajectory (``/slam/world_from_frame_left``, the left frame camera, comparable with
    ``/ground_truth``), the keyframes (``/slam/keyframes``, left rectified frame camera) and
    the final map (``/slam/map``). The log is also a sequence: :func:`load_mcap` reads it back.
    ``frame_format`` is as in :func:`write_sequence`.
    """

    def __init__(
        self, path: str | Path, sequence: Sequence, *, compression: str = "zstd", frame_format: str = "raw"
    ) -> None:
        _check_frame_format(frame_format)
        self.path = Path(path)
        self._seq = sequence
        self._frame_format = frame_format
        self._writer = McapWriter(self.path, compression=compression)
        self._t_events: int | None = None
        self._frames: list[int] = []
        try:
            _write_calibration(self._writer, sequence, 0)
        except BaseException:
            self._writer.abort()
            raise

    def add_frame(self, index: int) -> None:
        """Record frame pair ``index`` and the events up to its fusion time."""
        pair = self._seq.frames[index]
        t_mid = pair.t_mid_ns
        if self._t_events is None:
            starts = [src.t_range_ns[0] for src in self._seq.events.values() if len(src)]
            previous = self._seq.frames.t_mid_ns[index - 1] if index > 0 else min(starts, default=t_mid)
            self._t_events = int(previous)
        for side, src in self._seq.events.items():
            w = src.window(self._t_events, t_mid)
            self._writer.add_events(EVENTS_TOPIC.format(side=side), f"event_{side}", w.x, w.y, w.t_ns, w.p)
        self._t_events = max(self._t_events, t_mid)
        _add_frame(self._writer, "left", pair.t_ns, pair.left, self._frame_format)
        _add_frame(self._writer, "right", pair.t_ns, pair.right, self._frame_format)
        self._frames.append(pair.index)

    def finish(
        self,
        trajectory: tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]],
        keyframes: tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]],
        map_points: npt.NDArray[np.float64],
    ) -> Path:
        """Write the outputs (``world_from_cam`` (N, 4, 4) trajectories, (M, 3) map points) and
        close the log."""
        w = self._writer
        try:
            t, poses = trajectory
            w.add_poses("/slam/world_from_frame_left", "world", np.asarray(t, np.int64), _pose_rows(poses))
            kt, kposes = keyframes
            w.add_poses("/slam/keyframes", "world", np.asarray(kt, np.int64), _pose_rows(kposes))
            frames = self._seq.frames
            t_end = int(frames.t_ns[self._frames[-1]]) if self._frames else 0
            w.add_point_cloud("/slam/map", "world", t_end, np.asarray(map_points, np.float64).reshape(-1, 3))
            gt = self._seq.ground_truth
            if gt is not None and self._frames:
                t0 = int(frames.t_ns[self._frames[0]])
                keep = (gt.t_ns >= t0) & (gt.t_ns <= t_end)
                w.add_poses(GROUND_TRUTH_TOPIC, "world", gt.t_ns[keep], gt.world_from_cam[keep])
            exposures = [int(frames.exposure_ns[i]) for i in self._frames]
            w.add_metadata(SEQUENCE_METADATA, _sequence_metadata(self._seq, exposures))
            w.finish()
        except BaseException:
            w.abort()
            raise
        return self.path

    def abort(self) -> None:
        """Drop the recording (nothing is left at ``path``)."""
        self._writer.abort()


__all__ = [
    "CALIBRATION_TOPIC",
    "COMPRESSED_IMAGE",
    "EVENTS_TOPIC",
    "FRAMES_TOPIC",
    "FRAME_FORMATS",
    "GROUND_TRUTH_TOPIC",
    "RAW_IMAGE",
    "SEQUENCE_METADATA",
    "McapEventSource",
    "McapFrames",
    "McapRecorder",
    "load_mcap",
    "sequence_start_ns",
    "write_sequence",
]
