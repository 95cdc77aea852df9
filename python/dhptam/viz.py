"""Visualisation sinks of ``dhptam run`` and the ``dhptam view`` command.

A run hands every tracked frame and, at the end, the final map to a :class:`VizSink`. The
default sink does nothing (headless runs pay one no-op method call per frame);
:class:`RerunSink` writes a `rerun <https://rerun.io>`_ recording (``pip install dhptam[viz]``).
The sink sees each frame once and keeps none of its images: they are encoded and handed to
rerun's writer, which streams them to the ``.rrd`` file, so memory stays flat however long the
sequence.

Entities of a recording (timelines ``sensor_time`` — the frame's sensor time — and ``frame``,
the frame index):

======================================  ==========================================================
``world``                               right-down-forward view coordinates (the camera convention)
``world/camera``                        per frame: ``world_from_cam`` of the tracked frame
``world/camera/image``                  the rectified left camera (pinhole) and the fused image
``images/frame``                        per frame: the rectified left frame
``images/e3ct``                         per frame: the left E3CT warped into the frame camera
                                        (first three temporal channels as RGB; not in ``frames``)
``images/stereo``                       per frame: left | right images the features ran on
``images/stereo/keypoints``             per frame: left and right keypoints
``images/stereo/matches``               per frame: left–right descriptor matches on the same
                                        rectified row (±2 px, positive disparity)
``world/trajectory/estimate``           end: the estimated camera path (latest corrections)
``world/trajectory/ground_truth``       end, when known: the reference path, SE(3)-aligned to
                                        the estimate (Kabsch on positions at matching times)
``world/keyframes``                     end: keyframe positions
``world/map``                           end: map points (world frame, metres)
``world/loops``                         end: one segment per accepted loop closure
``plots/beta``, ``plots/mode``          per frame: the fusion weight β and mode of the left
``plots/inliers``, ``plots/keypoints``  camera (0 frames, 1 aps, 2 dvs, 3 events), tracking
                                        inliers, left keypoints
``log/state``                           text: tracking state and fusion mode changes
======================================  ==========================================================

``dhptam view OUT`` opens ``OUT/recording.rrd`` or, when a run was made without ``--viz``,
builds a recording of everything the run's files hold (trajectory, keyframes, map, the
per-frame table of ``frames.csv``, loops and the reference path when found); no images then.
"""

from __future__ import annotations

import csv
import json
import os
import queue
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .errors import FileError, InputError, MissingDependencyError

RECORDING = "recording.rrd"
VIZ_CHOICES = ("none", "rerun", "rerun-spawn")
MODE_CODES = {"frames": 0, "aps": 1, "dvs": 2, "events": 3}
_NS = 1_000_000_000
_F64 = npt.NDArray[np.float64]
# Stereo matches drawn per frame, the nearest rows first; more only clutters the view.
_MAX_MATCHES_DRAWN = 300
_ROW_TOLERANCE_PX = 2.0
_JPEG_QUALITY = 85


def import_rerun() -> Any:
    """The ``rerun`` module, or a :class:`MissingDependencyError` saying how to install it."""
    try:
        import rerun
    except ImportError as e:
        raise MissingDependencyError(
            "visualisation needs the rerun SDK, which is not installed: run "
            "`pip install dhptam[viz]` (or `pip install rerun-sdk`)"
        ) from e
    return rerun


class VizSink:
    """Receives what a run produces; every method is a no-op here (headless default)."""

    def frame(self, frame: Any, left: Any, right: Any, track: Any) -> None:
        """One tracked frame: the front-end's ``FrontendFrame``, the left and right features
        and the tracker's ``TrackResult``."""

    def finish(self, system: Any, reference: tuple[npt.NDArray[np.int64], _F64] | None) -> None:
        """The end of the run: the final trajectory, keyframes, map and loops from ``system``,
        and the reference path ``(t_ns, (N, 7) rows of x y z qx qy qz qw)`` when known."""

    def close(self) -> None:
        """Flushes and releases whatever the sink holds."""


def _duration(t_ns: int) -> np.timedelta64:
    return np.timedelta64(int(t_ns), "ns")


def _e3ct_rgb(events: npt.NDArray[np.float32]) -> npt.NDArray[np.uint8]:
    """(H, W, C) float in [0, 1] → (H, W, 3) uint8: the first three channels (oldest to newest
    window slices), or the one channel repeated."""
    rgb = events[..., :3] if events.shape[-1] >= 3 else np.repeat(events[..., :1], 3, axis=-1)
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def stereo_matches(
    left: Any, right: Any, *, ratio: float = 0.8, limit: int | None = _MAX_MATCHES_DRAWN
) -> npt.NDArray[np.int64]:
    """Pairs (row in left, row in right) of descriptor matches (:func:`dhptam.features.match`
    with ``ratio``) that lie on the same rectified row (±2 px) with a positive disparity,
    nearest rows first (at most ``limit``; ``None``: all)."""
    from .features import match

    kl, kr = np.asarray(left.keypoints), np.asarray(right.keypoints)
    if len(kl) == 0 or len(kr) == 0:
        return np.empty((0, 2), np.int64)
    pairs, _ = match(left, right, ratio=ratio)
    if len(pairs) == 0:
        return pairs
    a, b = kl[pairs[:, 0]], kr[pairs[:, 1]]
    dy = np.abs(a[:, 1] - b[:, 1])
    keep = (dy <= _ROW_TOLERANCE_PX) & (a[:, 0] - b[:, 0] > 0)
    pairs, dy = pairs[keep], dy[keep]
    return pairs[np.argsort(dy, kind="stable")[:limit]]


def align_positions(source: _F64, target: _F64) -> tuple[_F64, _F64]:
    """Rotation ``R`` and translation ``t`` minimising Σ‖R·source + t − target‖² (Kabsch, no
    scale) over (N, 3) positions, N ≥ 3."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    h = (source - mu_s).T @ (target - mu_t)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rotation, mu_t - rotation @ mu_s


def aligned_reference(
    reference: tuple[npt.NDArray[np.int64], _F64], t_ns: npt.NDArray[np.int64], positions: _F64
) -> _F64 | None:
    """The reference positions in the estimate's world: interpolated at the estimate's times,
    aligned by :func:`align_positions`; ``None`` with fewer than 3 common times."""
    ref_t, ref_rows = reference
    if len(ref_t) < 2 or len(t_ns) < 3:
        return None
    inside = (t_ns >= ref_t[0]) & (t_ns <= ref_t[-1])
    if inside.sum() < 3:
        return None
    tq = t_ns[inside].astype(np.float64)
    rt = ref_t.astype(np.float64)
    ref_at = np.stack([np.interp(tq, rt, ref_rows[:, k]) for k in range(3)], axis=1)
    rotation, translation = align_positions(ref_at, positions[inside])
    return np.asarray(ref_rows[:, :3] @ rotation.T + translation, np.float64)


class RerunSink(VizSink):
    """Writes a rerun recording to ``path`` (and streams it to a spawned viewer with ``spawn``).

    ``calibration`` is the rectified left camera ``(fx, fy, cx, cy, baseline_m, width, height)``.
    Frames are encoded and logged on a thread of the sink's own, up to ``depth`` frames behind
    the caller (which waits when it is that far ahead, so memory stays bounded); an error there
    is raised by the next :meth:`frame`, :meth:`finish` or :meth:`close`.
    """

    def __init__(
        self,
        path: str | os.PathLike[str] | None,
        calibration: Sequence[float],
        *,
        spawn: bool = False,
        name: str = "dhptam",
        depth: int = 4,
    ) -> None:
        rr = import_rerun()
        self._rr = rr
        self.path = None if path is None else Path(path)
        self.rec = rr.RecordingStream("dhptam", recording_id=name)
        sinks: list[Any] = []
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(self.path)))
        if spawn:
            rr.spawn(connect=False)
            sinks.append(rr.GrpcSink())
        if not sinks:
            raise InputError("a rerun sink needs a file to write or a viewer to spawn", field="path")
        self.rec.set_sinks(*sinks)
        fx, fy, cx, cy, _, width, height = (float(v) for v in calibration)
        self.width, self.height = int(width), int(height)
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self.rec.log(
            "world/camera/image",
            rr.Pinhole(focal_length=[fx, fy], principal_point=[cx, cy], resolution=[width, height]),
            static=True,
        )
        self._state: tuple[str, str] | None = None
        self._closed = False
        self._queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(maxsize=max(1, int(depth)))
        self._error: BaseException | None = None
        self._worker = threading.Thread(target=self._work, name="dhptam-viz", daemon=True)
        self._worker.start()

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._error is None:
                try:
                    self._log_frame(*item)
                except BaseException as error:  # re-raised on the caller's thread
                    self._error = error

    def _raise_pending(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def _drain(self) -> None:
        """Waits until every queued frame is logged and stops the worker."""
        if self._worker.is_alive():
            self._queue.put(None)
            self._worker.join()

    def _time(self, t_ns: int, index: int | None = None) -> None:
        self.rec.set_time("sensor_time", duration=_duration(t_ns))
        if index is not None:
            self.rec.set_time("frame", sequence=int(index))

    def _image(self, entity: str, image: npt.NDArray[np.uint8]) -> None:
        rr = self._rr
        self.rec.log(entity, rr.Image(np.ascontiguousarray(image)).compress(jpeg_quality=_JPEG_QUALITY))

    def frame(self, frame: Any, left: Any, right: Any, track: Any) -> None:
        self._raise_pending()
        self._queue.put((frame, left, right, track))

    def _log_frame(self, frame: Any, left: Any, right: Any, track: Any) -> None:
        rr, rec = self._rr, self.rec
        self._time(frame.t_ns, frame.index)
        pose = np.asarray(track.pose, np.float64)
        rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        self._image("world/camera/image/fused", frame.left)
        self._image("images/frame", frame.frame_left)
        if frame.events_left is not None:
            self._image("images/e3ct", _e3ct_rgb(frame.events_left))
        self._image("images/stereo", np.hstack([frame.left, frame.right]))
        kl = np.asarray(left.keypoints, np.float32).reshape(-1, 2)
        # Right keypoints drawn in the right half of the stereo image.
        kr = np.asarray(right.keypoints, np.float32).reshape(-1, 2) + np.array(
            [frame.left.shape[1], 0], np.float32
        )
        colours = np.vstack([np.tile([0, 200, 255], (len(kl), 1)), np.tile([255, 160, 0], (len(kr), 1))])
        rec.log("images/stereo/keypoints", rr.Points2D(np.vstack([kl, kr]), colors=colours, radii=1.5))
        pairs = stereo_matches(left, right)
        strips = np.stack([kl[pairs[:, 0]], kr[pairs[:, 1]]], axis=1) if len(pairs) else np.empty((0, 2, 2))
        rec.log("images/stereo/matches", rr.LineStrips2D(strips, colors=[80, 255, 80], radii=0.5))
        rec.log("plots/beta", rr.Scalars(float(frame.beta_left)))
        rec.log("plots/mode", rr.Scalars(float(MODE_CODES.get(frame.bias, -1))))
        rec.log("plots/inliers", rr.Scalars(float(track.inliers)))
        rec.log("plots/keypoints", rr.Scalars(float(len(kl))))
        state = (str(track.state), str(frame.bias))
        if state != self._state:
            rec.log("log/state", rr.TextLog(f"tracking {state[0]}, fusion mode {state[1]}"))
            self._state = state

    def finish(self, system: Any, reference: tuple[npt.NDArray[np.int64], _F64] | None) -> None:
        self._drain()
        self._raise_pending()
        t_ns, poses = system.trajectory()
        kt, kposes = system.keyframe_trajectory()
        log_final(
            self.rec,
            np.asarray(t_ns, np.int64),
            np.asarray(poses, np.float64)[:, :3, 3] if len(poses) else np.empty((0, 3)),
            np.asarray(kt, np.int64),
            np.asarray(kposes, np.float64)[:, :3, 3] if len(kposes) else np.empty((0, 3)),
            np.asarray(system.map_points(), np.float64),
            list(system.loop_closures()),
            reference,
        )

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._drain()
            self.rec.flush()
            self.rec.disconnect()
            self._raise_pending()


def log_final(
    rec: Any,
    t_ns: npt.NDArray[np.int64],
    positions: _F64,
    keyframe_t_ns: npt.NDArray[np.int64],
    keyframe_positions: _F64,
    map_points: _F64,
    loops: list[tuple[int, int]],
    reference: tuple[npt.NDArray[np.int64], _F64] | None,
) -> None:
    """Logs the end-of-run entities (trajectories, keyframes, map, loops) at the last sensor
    time, so that scrubbing back in time shows the per-frame state and the end shows the
    result."""
    rr = import_rerun()
    if len(t_ns):
        rec.set_time("sensor_time", duration=_duration(int(t_ns[-1])))
    rec.log("world/trajectory/estimate", rr.LineStrips3D([positions], colors=[40, 120, 255], radii=0.004))
    if reference is not None:
        gt = aligned_reference(reference, t_ns, positions)
        if gt is not None:
            rec.log("world/trajectory/ground_truth", rr.LineStrips3D([gt], colors=[255, 80, 80], radii=0.004))
    rec.log("world/keyframes", rr.Points3D(keyframe_positions, colors=[255, 220, 0], radii=0.012))
    rec.log("world/map", rr.Points3D(map_points, colors=[200, 200, 200], radii=0.004))
    where = {int(t): keyframe_positions[i] for i, t in enumerate(keyframe_t_ns)}
    segments = [[where[a], where[b]] for a, b in loops if a in where and b in where]
    rec.log(
        "world/loops",
        rr.LineStrips3D(np.asarray(segments).reshape(-1, 2, 3), colors=[255, 0, 255], radii=0.006),
    )


# -- dhptam view -------------------------------------------------------------------------------


def read_ply_points(path: Path) -> _F64:
    """The (N, 3) vertex positions of a binary little-endian PLY written by
    :func:`dhptam.depth.write_ply` (float x y z, optional uchar colours)."""
    try:
        data = path.read_bytes()
    except OSError as err:
        raise FileError(f"{path}: cannot read the map ({err})", path=str(path)) from None
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' ... 'end_header')", field="header")
    header = data[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise InputError(f"{path}: only binary little-endian PLY is read", field="format")
    sizes = {"float": ("<f4", 4), "uchar": ("u1", 1), "double": ("<f8", 8)}
    count, fields = 0, []
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            count = int(parts[2])
        elif parts[:1] == ["property"] and len(parts) == 3 and parts[1] in sizes:
            fields.append((parts[2], sizes[parts[1]][0]))
        elif parts[:1] == ["property"]:
            raise InputError(f"{path}: unsupported PLY property {line!r}", field="property")
    dtype = np.dtype(fields)
    body = data[end + len(b"end_header\n") :]
    if len(body) < count * dtype.itemsize or not {"x", "y", "z"} <= set(dtype.names or ()):
        raise InputError(
            f"{path}: expected {count} vertices with x y z ({count * dtype.itemsize} bytes), "
            f"got {len(body)} bytes",
            field="vertex",
        )
    records = np.frombuffer(body, dtype=dtype, count=count)
    return np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.float64)


def _reference_for(out: Path, meta: dict[str, Any], reference: str | Path | None) -> Any:
    from .trajectory import read_tum

    if reference is not None:
        return read_tum(reference)
    sequence = meta.get("sequence")
    if sequence:
        candidate = Path(sequence) / "groundtruth_frame_left.txt"
        if candidate.is_file():
            return read_tum(candidate)
    return None


def recording_from_files(out: str | Path, path: str | Path, *, reference: str | Path | None = None) -> Path:
    """Writes a recording of a run folder's files into ``path`` (no images: those are only in
    a recording made during the run) and returns ``path``.

    Read: ``trajectory.tum`` (required), ``keyframes.tum``, ``map.ply``, ``frames.csv`` (β,
    mode, inliers, keypoints over time) and ``timing.json`` (loop closures, the sequence
    folder); the reference path is ``reference`` (TUM) or else the sequence's
    ``groundtruth_frame_left.txt`` when there is one.
    """
    from .trajectory import read_tum

    out = Path(out)
    rr = import_rerun()
    meta: dict[str, Any] = {}
    if (out / "timing.json").is_file():
        meta = json.loads((out / "timing.json").read_text(encoding="utf-8"))
    t_ns, rows = read_tum(out / "trajectory.tum")
    kt, krows = np.empty(0, np.int64), np.empty((0, 7))
    if (out / "keyframes.tum").is_file():
        kt, krows = read_tum(out / "keyframes.tum")
    points = read_ply_points(out / "map.ply") if (out / "map.ply").is_file() else np.empty((0, 3))
    rec = rr.RecordingStream("dhptam", recording_id=f"view:{out.name}")
    rec.set_sinks(rr.FileSink(str(path)))
    rec.log("world", rr.ViewCoordinates.RDF, static=True)
    for index, row in enumerate(_frames_table(out / "frames.csv")):
        rec.set_time("sensor_time", duration=_duration(round(float(row["t_s"]) * _NS)))
        rec.set_time("frame", sequence=int(row.get("index", index)))
        rec.log("plots/beta", rr.Scalars(float(row.get("beta_left", "nan"))))
        rec.log("plots/mode", rr.Scalars(float(MODE_CODES.get(row.get("bias", ""), -1))))
        rec.log("plots/inliers", rr.Scalars(float(row.get("inliers", "nan"))))
        rec.log("plots/keypoints", rr.Scalars(float(row.get("keypoints_left", "nan"))))
    from .trajectory import rows_to_matrices

    for t, pose in zip(t_ns, rows_to_matrices(rows), strict=True):
        rec.set_time("sensor_time", duration=_duration(int(t)))
        rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
    loops = [(round(a * _NS), round(b * _NS)) for a, b in meta.get("loops_s", [])]
    # Keyframe times in keyframes.tum are rounded to the file's precision; match loops to them
    # by the nearest keyframe.
    if len(kt) and loops:
        loops = [(int(kt[np.abs(kt - a).argmin()]), int(kt[np.abs(kt - b).argmin()])) for a, b in loops]
    log_final(
        rec,
        t_ns,
        rows[:, :3],
        kt,
        krows[:, :3],
        points,
        loops,
        _reference_for(out, meta, reference),
    )
    rec.flush()
    rec.disconnect()
    return Path(path)


def _frames_table(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def has_display() -> bool:
    """Whether a viewer window can open here (an X11/Wayland display, or macOS/Windows)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def spawn_viewer(path: str | Path) -> None:
    """Opens the rerun viewer on a recording file, detached from this process."""
    import subprocess

    import_rerun()
    subprocess.Popen(  # the viewer outlives the command, like rerun's own spawn
        [sys.executable, "-m", "rerun", str(path)],
        stdin=subprocess.DEVNULL,
        start_new_session=True,
    )


def view(
    out: str | Path,
    *,
    save: str | Path | None = None,
    reference: str | Path | None = None,
    spawn: bool | None = None,
) -> tuple[Path, bool]:
    """``dhptam view``: shows a run folder's recording. Returns ``(recording file, viewer
    opened)``.

    The recording is ``OUT/recording.rrd`` (written by ``dhptam run --viz rerun``); a run without
    one gets a recording built from its files (no images), written to ``save`` or else to
    ``OUT/view.rrd``. With ``save`` an existing recording is copied there. The viewer opens
    when ``spawn`` is True, or when it is None, ``save`` is not given and there is a display.
    """
    out_dir = Path(out)
    if not out_dir.is_dir():
        raise FileError(
            f"{out_dir}: run folder not found (expected the --out folder of dhptam run)", path=str(out_dir)
        )
    existing = out_dir / RECORDING
    if not existing.is_file() and not (out_dir / "trajectory.tum").is_file():
        raise FileError(
            f"{out_dir}: neither {RECORDING} nor trajectory.tum found; is this a dhptam run folder?",
            path=str(out_dir),
        )
    import_rerun()
    show = (save is None and has_display()) if spawn is None else spawn
    if existing.is_file():
        target = existing if save is None else Path(save)
        if target.resolve() != existing.resolve():
            import shutil

            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(existing, target)
    else:
        target = out_dir / "view.rrd" if save is None else Path(save)
        target.parent.mkdir(parents=True, exist_ok=True)
        recording_from_files(out_dir, target, reference=reference)
    if show:
        spawn_viewer(target)
    return target, show


__all__ = [
    "RECORDING",
    "VIZ_CHOICES",
    "RerunSink",
    "VizSink",
    "align_positions",
    "import_rerun",
    "read_ply_points",
    "recording_from_files",
    "spawn_viewer",
    "stereo_matches",
    "view",
]
