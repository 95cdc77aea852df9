"""The sequence model: a calibrated stereo events+frames recording, read lazily.

A :class:`Sequence` holds

* the rig calibration (:class:`RigCalibration`: four cameras, keyed by :data:`CAMERA_KEYS`, and
  their ``imu_from_cam`` extrinsics),
* the stereo frame pairs (:class:`Frames`: timestamps and exposures in memory, images decoded
  from disk only when a pair is accessed),
* one :class:`EventSource` per event camera, which reads the events of a time window from its
  HDF5 file without loading the rest,
* the ground truth of the left frame camera (:class:`GroundTruth`) when the recording has one.

Time is ``int64`` nanoseconds everywhere in this module; files store microseconds, and the
conversion happens where a file is read.

Event windows
-------------
Event files hold ``/events/{x,y,t,p}`` with ``t`` in µs, sorted, and optionally ``/ms_to_idx``
and ``/t_offset`` (µs). Following DSEC (whose layout TUM-VIE reuses), the file's clock is
``t + t_offset`` (``t_offset`` is 0 when absent, as in TUM-VIE), and ``ms_to_idx`` is indexed by
milliseconds of the *stored* ``t`` counted from 0::

    ms_to_idx[k] = the first index i with t[i] >= 1000 * k     (N when no event is that late)

so ``t[ms_to_idx[k] - 1] < 1000 k <= t[ms_to_idx[k]]``. To find the first event at or after a
time ``v`` (µs), the index gives the bracket ``[ms_to_idx[k], ms_to_idx[k + 1]]`` with
``k = floor(v / 1000)``, and a binary search inside the ≤ 1 ms of events of that bracket ends
the search. Without the index (or past its end) a plain binary search over ``/events/t`` reads
single elements, O(log N) reads, until fewer than a few thousand candidates remain. Either way
only the window's own slices of ``x, y, t, p`` are then read, so the memory a window needs is
proportional to its event count, never to the file's.

The index is checked against ``/events/t`` at a handful of entries when the file is opened;
an index that contradicts the definition above is reported as a :class:`~dhptam.errors.ParseError`
rather than silently giving wrong windows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from ..errors import FileError, InputError, ParseError
from ..geometry import SE3, Camera
from ._common import check_h5_filters

CAMERA_KEYS: tuple[str, str, str, str] = ("frame_left", "frame_right", "event_left", "event_right")
"""Camera names, in Basalt's calibration order (indices 0, 1, 2, 3)."""

EVENT_SIDES: tuple[str, str] = ("left", "right")

# Below this many candidates the binary search reads the remaining slice of /events/t at once:
# one read of a few thousand int64 costs about as much as a single-element read of a chunk.
_BISECT_SLICE = 4096
# Number of /ms_to_idx entries checked against /events/t when a file is opened.
_INDEX_SPOT_CHECKS = 9


@dataclass(frozen=True)
class RigCalibration:
    """Intrinsics and extrinsics of the four cameras of a TUM-VIE-like rig.

    ``cameras`` and ``imu_from_cam`` are keyed by :data:`CAMERA_KEYS`; ``imu_from_cam`` is
    Basalt's ``T_imu_cam`` (maps points from the camera frame into the IMU frame).
    """

    cameras: dict[str, Camera]
    imu_from_cam: dict[str, SE3]

    def __post_init__(self) -> None:
        for name, table in (("cameras", self.cameras), ("imu_from_cam", self.imu_from_cam)):
            missing = [k for k in CAMERA_KEYS if k not in table]
            extra = [k for k in table if k not in CAMERA_KEYS]
            if missing or extra:
                raise InputError(
                    f"RigCalibration.{name} must have exactly the keys {list(CAMERA_KEYS)}; "
                    f"missing {missing}, unexpected {extra}",
                    field=name,
                )

    def cam_from_cam(self, target: str, source: str) -> SE3:
        """Transform mapping points of camera ``source`` into camera ``target``."""
        return self.imu_from_cam[target].inverse() @ self.imu_from_cam[source]


@dataclass(frozen=True)
class FramePair:
    """One stereo frame pair; ``t_ns`` is the start of exposure (the camera's stamp)."""

    index: int
    t_ns: int
    exposure_ns: int
    left: npt.NDArray[np.uint8]
    right: npt.NDArray[np.uint8]

    @property
    def t_mid_ns(self) -> int:
        """Middle of the exposure, the fusion time t_f = t_cam + t_exp / 2 (SPEC-NOTES §2)."""
        return self.t_ns + self.exposure_ns // 2


@dataclass(frozen=True)
class EventWindow:
    """The events of one camera in a half-open time window, sorted by time."""

    x: npt.NDArray[np.uint16]
    y: npt.NDArray[np.uint16]
    t_ns: npt.NDArray[np.int64]
    p: npt.NDArray[np.int8]

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True)
class GroundTruth:
    """Poses of the left frame camera: ``world_from_cam`` rows are ``x y z qx qy qz qw``."""

    t_ns: npt.NDArray[np.int64]
    world_from_cam: npt.NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@runtime_checkable
class EventStream(Protocol):
    """What a :class:`Sequence` needs from the events of one camera, whatever the file format.

    :class:`EventSource` (DSEC/TUM-VIE/VECtor HDF5) implements it, and so do the MVSEC and ROS
    bag readers of :mod:`dhptam.datasets`. Times are ``int64`` ns on the sequence's clock;
    windows are half-open ``[t0, t1)`` and sorted by time; indices count events in file order.
    Implementations keep memory proportional to the window read, never to the recording.
    """

    def __len__(self) -> int: ...

    @property
    def t_range_ns(self) -> tuple[int, int]:
        """``[first, last + 1)`` of the event times; ``(0, 0)`` when there are none."""
        ...

    def window(self, t0_ns: int, t1_ns: int) -> EventWindow:
        """The events with ``t0_ns <= t < t1_ns``."""
        ...

    def index_range(self, t0_ns: int, t1_ns: int) -> tuple[int, int]:
        """Indices ``[i0, i1)`` of the events with ``t0_ns <= t < t1_ns``."""
        ...

    def slice(self, i0: int, i1: int) -> EventWindow:
        """Events ``i0 .. i1 - 1`` in file order."""
        ...

    def iter_windows(
        self, step_ns: int, t0_ns: int | None = None, t1_ns: int | None = None
    ) -> Iterator[EventWindow]:
        """Consecutive windows of ``step_ns`` covering ``[t0_ns, t1_ns)`` (default: all)."""
        ...

    def close(self) -> None:
        """Release the file."""
        ...

    def __enter__(self) -> EventStream: ...

    def __exit__(self, *exc: object) -> None: ...


class WindowedEvents:
    """Shared part of the readers whose windows come from :meth:`window`: consecutive windows
    and the context manager. A subclass provides ``t_range_ns``, ``window`` and ``close``."""

    def iter_windows(
        self, step_ns: int, t0_ns: int | None = None, t1_ns: int | None = None
    ) -> Iterator[EventWindow]:
        """Consecutive windows ``[t0 + k step, t0 + (k + 1) step)`` covering ``[t0, t1)``
        (default: the stream's time range)."""
        if step_ns <= 0:
            raise InputError(f"step_ns must be positive, got {step_ns}", field="step_ns")
        lo, hi = self.t_range_ns  # type: ignore[attr-defined]
        t = lo if t0_ns is None else int(t0_ns)
        end = hi if t1_ns is None else int(t1_ns)
        while t < end:
            t_next = min(t + step_ns, end)
            yield self.window(t, t_next)  # type: ignore[attr-defined]
            t = t_next

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()  # type: ignore[attr-defined]


class Frames:
    """Stereo frame pairs in time order; images are decoded from disk on access.

    ``t_ns`` (start of exposure) and ``exposure_ns`` are arrays in memory; indexing returns a
    :class:`FramePair` whose images were read with OpenCV as 8-bit grayscale.
    """

    def __init__(
        self,
        t_ns: npt.NDArray[np.int64],
        exposure_ns: npt.NDArray[np.int64],
        left_paths: list[Path],
        right_paths: list[Path],
        left_size: tuple[int, int] | None = None,
        right_size: tuple[int, int] | None = None,
    ) -> None:
        n = len(t_ns)
        if not (len(exposure_ns) == len(left_paths) == len(right_paths) == n):
            raise InputError(
                f"frame arrays disagree in length: {n} timestamps, {len(exposure_ns)} exposures, "
                f"{len(left_paths)} left and {len(right_paths)} right images",
                field="frames",
            )
        self.t_ns = np.asarray(t_ns, dtype=np.int64)
        self.exposure_ns = np.asarray(exposure_ns, dtype=np.int64)
        self.left_paths = list(left_paths)
        self.right_paths = list(right_paths)
        # (width, height) each image must have, from the calibration; None skips the check.
        self._sizes = {"left": left_size, "right": right_size}

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def t_mid_ns(self) -> npt.NDArray[np.int64]:
        """Middle of every exposure (fusion times)."""
        return self.t_ns + self.exposure_ns // 2

    def __getitem__(self, index: int) -> FramePair:
        n = len(self)
        i = int(index)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame index {index} out of range for {n} frames")
        return FramePair(
            index=i,
            t_ns=int(self.t_ns[i]),
            exposure_ns=int(self.exposure_ns[i]),
            left=self._image(i, "left"),
            right=self._image(i, "right"),
        )

    def __iter__(self) -> Iterator[FramePair]:
        for i in range(len(self)):
            yield self[i]

    def _image(self, i: int, side: str) -> npt.NDArray[np.uint8]:
        """Image ``i`` of one side; readers whose images are not files (ROS bags) override it."""
        return self._read((self.left_paths if side == "left" else self.right_paths)[i], side)

    def _read(self, path: Path, side: str) -> npt.NDArray[np.uint8]:
        import cv2

        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise FileError(f"{path}: cannot read or decode the image", path=str(path), field="image")
        size = self._sizes[side]
        if size is not None and (image.shape[1], image.shape[0]) != size:
            raise InputError(
                f"{path}: image is {image.shape[1]}x{image.shape[0]} but the calibration of the "
                f"{side} frame camera says {size[0]}x{size[1]}",
                path=str(path),
                field="resolution",
            )
        # IMREAD_GRAYSCALE always decodes to 8 bits; this only tells the type checker.
        return np.asarray(image, dtype=np.uint8)


def _h5_error(path: Path, what: str, err: BaseException) -> FileError:
    return FileError(f"{path}: {what} failed ({err}); the HDF5 file is corrupt or truncated", path=str(path))


class EventSource:
    """Random access by time window to the events of one camera in an HDF5 file.

    The file stays open until :meth:`close`; only the slices a window needs are read.

    Parameters
    ----------
    path
        The ``*.h5`` file (DSEC/TUM-VIE layout; see the module docstring).
    use_index
        Use ``/ms_to_idx`` when the file has one (default). ``False`` forces the plain binary
        search, which the tests use to check both paths against each other.
    """

    def __init__(self, path: str | Path, *, use_index: bool = True) -> None:
        import h5py
        import hdf5plugin  # noqa: F401  (registers the Blosc filter with HDF5)

        self.path = Path(path)
        if not self.path.is_file():
            raise FileError(f"{self.path}: event file not found", path=str(self.path))
        try:
            self._file: Any = h5py.File(self.path, "r")
        except OSError as err:
            raise FileError(
                f"{self.path}: cannot open as HDF5 ({err}); the file is corrupt or truncated",
                path=str(self.path),
            ) from None
        try:
            self._open(use_index)
        except BaseException:
            self._file.close()
            raise

    def _open(self, use_index: bool) -> None:
        f = self._file
        self._d = {}
        for name in ("x", "y", "t", "p"):
            key = f"events/{name}"
            try:
                dset = f[key]
            except (KeyError, OSError):
                raise ParseError(
                    f"{self.path}: dataset /{key} is missing", path=str(self.path), field=key
                ) from None
            if not hasattr(dset, "dtype") or dset.ndim != 1:
                raise ParseError(f"{self.path}: /{key} must be a 1-D dataset", path=str(self.path), field=key)
            check_h5_filters(dset, self.path, key)
            if dset.dtype.kind not in "iu" and not (name == "p" and dset.dtype.kind == "b"):
                raise ParseError(
                    f"{self.path}: /{key} has dtype {dset.dtype}, expected integers"
                    + (" (µs timestamps)" if name == "t" else ""),
                    path=str(self.path),
                    field=key,
                )
            self._d[name] = dset
        lengths = {name: d.shape[0] for name, d in self._d.items()}
        if len(set(lengths.values())) != 1:
            raise ParseError(
                f"{self.path}: /events datasets differ in length: {lengths}",
                path=str(self.path),
                field="events",
            )
        self._n = lengths["t"]
        self._offset_us = 0
        if "t_offset" in f:
            node = f["t_offset"]
            arr = (
                np.asarray(self._read(lambda: node[()], "reading /t_offset"))
                if hasattr(node, "dtype")
                else None
            )
            if arr is None or arr.size != 1 or arr.dtype.kind not in "iu":
                raise ParseError(
                    f"{self.path}: /t_offset must be one integer (µs), got "
                    + ("a group" if arr is None else f"{arr.dtype} of shape {arr.shape}"),
                    path=str(self.path),
                    field="t_offset",
                )
            self._offset_us = int(arr.reshape(()))
        self._index: npt.NDArray[np.int64] | None = None
        if use_index and "ms_to_idx" in f:
            self._index = self._load_index()
        if self._n:
            first, last = self._read(
                lambda: (int(self._d["t"][0]), int(self._d["t"][-1])), "reading /events/t"
            )
            if last < first:
                raise ParseError(
                    f"{self.path}: /events/t is not sorted (first {first} µs > last {last} µs)",
                    path=str(self.path),
                    field="events/t",
                )
            self._t_first_us, self._t_last_us = first, last

    def _read(self, fn: Any, what: str) -> Any:
        try:
            return fn()
        except (OSError, RuntimeError, ValueError) as err:
            raise _h5_error(self.path, what, err) from None

    def _load_index(self) -> npt.NDArray[np.int64]:
        dset = self._file["ms_to_idx"]
        if not hasattr(dset, "dtype") or dset.ndim != 1 or dset.dtype.kind not in "iu" or dset.shape[0] == 0:
            raise ParseError(
                f"{self.path}: /ms_to_idx must be a non-empty 1-D integer dataset, "
                f"got {getattr(dset, 'dtype', 'a group')} of shape {getattr(dset, 'shape', None)}",
                path=str(self.path),
                field="ms_to_idx",
            )
        # One int64 per millisecond: 4.8 MB for a 10-minute recording, so it is kept in memory.
        index = np.asarray(self._read(lambda: dset[:], "reading /ms_to_idx")).astype(np.int64)
        bad = "entries must be non-decreasing and within [0, N]"
        if index[0] < 0 or index[-1] > self._n or np.any(np.diff(index) < 0):
            raise ParseError(f"{self.path}: /ms_to_idx {bad}", path=str(self.path), field="ms_to_idx")
        t = self._d["t"]
        for k in np.unique(np.linspace(0, len(index) - 1, _INDEX_SPOT_CHECKS).astype(np.int64)):
            i = int(index[k])
            bound = 1000 * int(k)
            after_ok = i == self._n or self._read(lambda i=i: int(t[i]), "reading /events/t") >= bound
            before_ok = i == 0 or self._read(lambda i=i: int(t[i - 1]), "reading /events/t") < bound
            if not (after_ok and before_ok):
                raise ParseError(
                    f"{self.path}: /ms_to_idx[{k}] = {i} contradicts /events/t: expected the first "
                    f"index with t >= {bound} µs (DSEC convention, ms counted from t = 0)",
                    path=str(self.path),
                    field="ms_to_idx",
                )
        return index

    # -- public API ----------------------------------------------------------------------------

    def __len__(self) -> int:
        return int(self._n)

    @property
    def has_index(self) -> bool:
        """Whether windows are located through ``/ms_to_idx``."""
        return self._index is not None

    @property
    def t_range_ns(self) -> tuple[int, int]:
        """Half-open ``[first, last + 1)`` time span of the events, so that
        ``window(*t_range_ns)`` returns every event; ``(0, 0)`` for an empty file."""
        if self._n == 0:
            return (0, 0)
        off = self._offset_us
        return ((self._t_first_us + off) * 1000, (self._t_last_us + off) * 1000 + 1)

    def window(self, t0_ns: int, t1_ns: int) -> EventWindow:
        """The events with ``t0_ns <= t < t1_ns`` (empty when ``t1_ns <= t0_ns``)."""
        i0, i1 = self.index_range(t0_ns, t1_ns)
        return self.slice(i0, i1)

    def index_range(self, t0_ns: int, t1_ns: int) -> tuple[int, int]:
        """Indices ``[i0, i1)`` of the events with ``t0_ns <= t < t1_ns``."""
        t0_ns, t1_ns = int(t0_ns), int(t1_ns)
        if t1_ns <= t0_ns or self._n == 0:
            return (0, 0)
        # An event at stored time u (µs) is at (u + offset) * 1000 ns, so
        # (u + offset) * 1000 >= t  <=>  u >= ceil(t / 1000) - offset.
        a_us = -((-t0_ns) // 1000) - self._offset_us
        b_us = -((-t1_ns) // 1000) - self._offset_us
        i0 = self._lower_bound(a_us)
        i1 = self._lower_bound(b_us, lo=i0)
        return (i0, i1)

    def slice(self, i0: int, i1: int) -> EventWindow:
        """Events ``i0 .. i1 - 1`` in file order."""
        i0, i1 = max(0, int(i0)), min(self._n, int(i1))
        if i1 <= i0:
            return _empty_window()

        def read() -> tuple[Any, ...]:
            return tuple(self._d[k][i0:i1] for k in ("x", "y", "t", "p"))

        x, y, t, p = self._read(read, f"reading events {i0}..{i1}")
        if t.shape[0] > 1 and np.any(t[1:] < t[:-1]):
            raise ParseError(
                f"{self.path}: /events/t is not sorted between indices {i0} and {i1}",
                path=str(self.path),
                field="events/t",
            )
        # In place on the freshly read array: a window can hold millions of events.
        t_ns = t.astype(np.int64, copy=False)
        if self._offset_us:
            t_ns += self._offset_us
        t_ns *= 1000
        return EventWindow(
            x=x.astype(np.uint16, copy=False),
            y=y.astype(np.uint16, copy=False),
            t_ns=t_ns,
            p=p.astype(np.int8, copy=False),
        )

    def iter_windows(
        self, step_ns: int, t0_ns: int | None = None, t1_ns: int | None = None
    ) -> Iterator[EventWindow]:
        """Consecutive windows ``[t0 + k step, t0 + (k + 1) step)`` covering ``[t0, t1)``.

        Memory stays proportional to one window's events, whatever the file's length.
        """
        if step_ns <= 0:
            raise InputError(f"step_ns must be positive, got {step_ns}", field="step_ns")
        lo, hi = self.t_range_ns
        t = lo if t0_ns is None else int(t0_ns)
        end = hi if t1_ns is None else int(t1_ns)
        i = self._lower_bound_ns(t)
        while t < end:
            t_next = min(t + step_ns, end)
            j = self._lower_bound_ns(t_next, lo=i)
            yield self.slice(i, j)
            i, t = j, t_next

    def close(self) -> None:
        """Close the HDF5 file (windows can no longer be read)."""
        self._file.close()

    def __enter__(self) -> EventSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"EventSource({str(self.path)!r}, events={self._n}, index={self.has_index})"

    # -- search --------------------------------------------------------------------------------

    def _lower_bound_ns(self, t_ns: int, lo: int = 0) -> int:
        return self._lower_bound(-((-int(t_ns)) // 1000) - self._offset_us, lo=lo)

    def _lower_bound(self, v_us: int, lo: int = 0) -> int:
        """First index ``i >= lo`` with ``t[i] >= v_us`` (stored µs), or N."""
        n = self._n
        if n == 0:
            return 0
        if v_us <= self._t_first_us:
            return max(lo, 0)
        if v_us > self._t_last_us:
            return n
        hi = n
        index = self._index
        if index is not None:
            k = v_us // 1000  # floor: 1000 k <= v < 1000 (k + 1)
            if k < 0:
                hi = min(hi, int(index[0]))
            elif k < len(index):
                lo = max(lo, int(index[k]))
                if k + 1 < len(index):
                    hi = min(hi, int(index[k + 1]))
            else:
                lo = max(lo, int(index[-1]))
        return self._bisect(v_us, lo, max(lo, hi))

    def _bisect(self, v_us: int, lo: int, hi: int) -> int:
        """Binary search for ``v_us`` in ``t[lo:hi]``, reading single elements until the
        remaining range is short enough to read at once."""
        t = self._d["t"]
        while hi - lo > _BISECT_SLICE:
            mid = (lo + hi) // 2
            if self._read(lambda mid=mid: int(t[mid]), "reading /events/t") < v_us:
                lo = mid + 1
            else:
                hi = mid
        if hi <= lo:
            return lo
        block = self._read(lambda: t[lo:hi], "reading /events/t")
        return lo + int(np.searchsorted(block, v_us, side="left"))


def _empty_window() -> EventWindow:
    return EventWindow(
        x=np.empty(0, np.uint16), y=np.empty(0, np.uint16), t_ns=np.empty(0, np.int64), p=np.empty(0, np.int8)
    )


class Sequence:
    """A recording: calibration, stereo frames, event streams and optional ground truth.

    ``events`` maps ``"left"``/``"right"`` to any :class:`EventStream`; it is empty for a
    frames-only recording (EuRoC), which only the ``frames`` mode can run.

    Close it (or use it as a context manager) to release the event files.
    """

    def __init__(
        self,
        name: str,
        path: Path,
        calibration: RigCalibration,
        frames: Frames,
        events: Mapping[str, EventStream],
        ground_truth: GroundTruth | None,
        imu_from_marker: SE3 | None = None,
        *,
        on_close: Callable[[], None] | None = None,
    ) -> None:
        self.name = name
        self.path = path
        self.calibration = calibration
        self.frames = frames
        self.events: dict[str, EventStream] = dict(events)
        self.ground_truth = ground_truth
        self.imu_from_marker = imu_from_marker
        # Releases what the reader holds besides the event streams (a shared HDF5 file, a bag).
        self._on_close = on_close

    def close(self) -> None:
        """Close the event files (and whatever else the reader keeps open)."""
        for source in self.events.values():
            source.close()
        if self._on_close is not None:
            self._on_close()
            self._on_close = None

    def __enter__(self) -> Sequence:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        gt = "none" if self.ground_truth is None else f"{len(self.ground_truth)} poses"
        counts = ", ".join(f"{k}: {len(v)}" for k, v in self.events.items())
        return (
            f"Sequence({self.name!r}, {len(self.frames)} frame pairs, events {{{counts}}}, ground truth {gt})"
        )


__all__ = [
    "CAMERA_KEYS",
    "EVENT_SIDES",
    "EventSource",
    "EventStream",
    "EventWindow",
    "FramePair",
    "Frames",
    "GroundTruth",
    "RigCalibration",
    "Sequence",
    "WindowedEvents",
]
