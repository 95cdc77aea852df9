"""MVSEC: the DAVIS stereo recordings of Zhu et al. (2018), read from their HDF5 files.

Layout (SPEC-NOTES §7)::

    <seq>_data.hdf5   davis/{left,right}/events       (N, 4) float64: x, y, t [s], p (-1/+1)
                      davis/{left,right}/image_raw    (M, H, W) uint8 APS frames
                      davis/{left,right}/image_raw_ts (M,) float64 [s]
    <seq>_gt.hdf5     davis/left/pose                 (K, 4, 4) world_from_cam of the left DAVIS
                      davis/left/pose_ts              (K,) float64 [s]

Calibration is MVSEC's Kalibr ``camchain-imucam-<scene>.yaml`` (cam0/cam1: left/right DAVIS,
``equidistant`` distortion), passed as ``calibration=``; a DAVIS gives frames and events from one
pixel array, so the frame and event cameras of the rig are the same camera.

Times are float64 seconds of Unix time (≈1.5e9 s), resolved to ~0.2 µs by the float; they are
rounded to whole microseconds (the DAVIS clock's resolution) and held as int64 ns. Polarity
``-1/+1`` becomes ``0/1``. APS frames carry no exposure time in these files: ``exposure_ns`` is 0,
so a frame's stamp is also its fusion time. The left and right frames are paired by nearest
stamp within ``pair_tolerance_ns``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import FileError, InputError, ParseError
from ..trajectory import poses_to_rows
from ._common import check_h5_filters, check_increasing, lower_bound, pair_stereo
from .kalibr import rig_from_kalibr
from .sequence import EventWindow, Frames, GroundTruth, RigCalibration, Sequence


def seconds_to_ns(t_s: npt.NDArray[np.float64]) -> npt.NDArray[np.int64]:
    """Float seconds → int64 ns, rounded to the microsecond (the DAVIS clock's resolution)."""
    return np.rint(np.asarray(t_s, np.float64) * 1e6).astype(np.int64) * 1000


def _open_h5(path: Path) -> Any:
    import h5py
    import hdf5plugin  # noqa: F401  (registers the compression filters)

    if not path.is_file():
        raise FileError(f"{path}: file not found", path=str(path))
    try:
        # A 32 MiB chunk cache: the binary searches read single rows, and each row read would
        # otherwise decompress its whole chunk again when the window's slice is read next.
        return h5py.File(path, "r", rdcc_nbytes=32 << 20, rdcc_nslots=10007)
    except OSError as err:
        raise FileError(
            f"{path}: cannot open as HDF5 ({err}); corrupt or truncated", path=str(path)
        ) from None


def _dataset(f: Any, key: str, path: Path, shape_tail: tuple[int, ...], ndim: int) -> Any:
    try:
        d = f[key]
    except (KeyError, OSError):
        raise ParseError(f"{path}: dataset /{key} is missing", path=str(path), field=key) from None
    if not hasattr(d, "dtype") or d.ndim != ndim or (shape_tail and tuple(d.shape[1:]) != shape_tail):
        want = f"{ndim}-D" + (f" (N, {', '.join(map(str, shape_tail))})" if shape_tail else "")
        raise ParseError(
            f"{path}: /{key} must be a {want} dataset, got shape {getattr(d, 'shape', 'a group')}",
            path=str(path),
            field=key,
        )
    check_h5_filters(d, path, key)
    return d


class MvsecEventSource:
    """Time-window access to one DAVIS's ``(N, 4)`` event dataset (an
    :class:`~dhptam.datasets.EventStream`); only the rows of a window are read."""

    def __init__(self, path: str | Path, side: str, *, file: Any = None) -> None:
        self.path = Path(path)
        self.key = f"davis/{side}/events"
        self._owns = file is None
        self._file = _open_h5(self.path) if file is None else file
        try:
            self._d = _dataset(self._file, self.key, self.path, (4,), 2)
            if self._d.dtype.kind != "f":
                raise ParseError(
                    f"{self.path}: /{self.key} has dtype {self._d.dtype}, expected float64 "
                    "(x, y, t in seconds, p)",
                    path=str(self.path),
                    field=self.key,
                )
            self._n = int(self._d.shape[0])
            if self._n:
                self._first_ns = int(seconds_to_ns(np.array([self._read(0)]))[0])
                self._last_ns = int(seconds_to_ns(np.array([self._read(self._n - 1)]))[0])
                if self._last_ns < self._first_ns:
                    raise ParseError(
                        f"{self.path}: /{self.key} times are not sorted (first after last)",
                        path=str(self.path),
                        field=self.key,
                    )
        except BaseException:
            self.close()
            raise

    def _read(self, i: int | slice) -> Any:
        try:
            return self._d[i, 2]
        except (OSError, RuntimeError, ValueError) as err:
            raise FileError(f"{self.path}: reading /{self.key} failed ({err})", path=str(self.path)) from None

    def _lower(self, t_ns: int, lo: int = 0, hint: int | None = None) -> int:
        # Compare in the stored unit: the smallest µs-rounded time >= t_ns.
        if self._n == 0:
            return 0
        if t_ns <= self._first_ns:
            return lo
        if t_ns > self._last_ns:
            return self._n

        def read_ns(i: int | slice) -> Any:
            return (
                seconds_to_ns(np.atleast_1d(self._read(i)))
                if isinstance(i, slice)
                else int(seconds_to_ns(np.array([self._read(i)]))[0])
            )

        return lower_bound(read_ns, self._n, t_ns, lo, hint=hint)

    def __len__(self) -> int:
        return self._n

    @property
    def t_range_ns(self) -> tuple[int, int]:
        """``[first, last + 1)`` in ns."""
        return (0, 0) if self._n == 0 else (self._first_ns, self._last_ns + 1)

    def index_range(self, t0_ns: int, t1_ns: int) -> tuple[int, int]:
        """Rows ``[i0, i1)`` with ``t0_ns <= t < t1_ns``."""
        if int(t1_ns) <= int(t0_ns):
            return (0, 0)
        i0 = self._lower(int(t0_ns))
        return (i0, self._lower(int(t1_ns), i0))

    def window(self, t0_ns: int, t1_ns: int) -> EventWindow:
        """The events with ``t0_ns <= t < t1_ns``."""
        return self.slice(*self.index_range(t0_ns, t1_ns))

    def slice(self, i0: int, i1: int) -> EventWindow:
        """Rows ``i0 .. i1 - 1``."""
        i0, i1 = max(0, int(i0)), min(self._n, int(i1))
        if i1 <= i0:
            block = np.empty((0, 4), np.float64)
        else:
            try:
                block = np.asarray(self._d[i0:i1])
            except (OSError, RuntimeError, ValueError) as err:
                raise FileError(
                    f"{self.path}: reading /{self.key} rows {i0}..{i1} failed ({err})", path=str(self.path)
                ) from None
        p = block[:, 3]
        if p.size and not np.all((p == 1.0) | (p == -1.0)):
            raise ParseError(
                f"{self.path}: /{self.key} polarity column holds values other than -1/+1",
                path=str(self.path),
                field=self.key,
            )
        t_ns = seconds_to_ns(block[:, 2])
        if t_ns.size > 1 and np.any(t_ns[1:] < t_ns[:-1]):
            raise ParseError(
                f"{self.path}: /{self.key} times are not sorted between rows {i0} and {i1}",
                path=str(self.path),
                field=self.key,
            )
        return EventWindow(
            x=block[:, 0].astype(np.uint16),
            y=block[:, 1].astype(np.uint16),
            t_ns=t_ns,
            p=(p > 0).astype(np.int8),
        )

    def iter_windows(
        self, step_ns: int, t0_ns: int | None = None, t1_ns: int | None = None
    ) -> Iterator[EventWindow]:
        """Consecutive windows of ``step_ns`` over ``[t0_ns, t1_ns)``."""
        if step_ns <= 0:
            raise InputError(f"step_ns must be positive, got {step_ns}", field="step_ns")
        lo, hi = self.t_range_ns
        t = lo if t0_ns is None else int(t0_ns)
        end = hi if t1_ns is None else int(t1_ns)
        i = self._lower(t)
        count = None  # the previous window's size: where to start looking for the next bound
        while t < end:
            t_next = min(t + step_ns, end)
            j = self._lower(t_next, i, hint=count)
            yield self.slice(i, j)
            count = j - i
            i, t = j, t_next

    def close(self) -> None:
        """Close the file if this source opened it."""
        if self._owns and self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> MvsecEventSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class HdfFrames(Frames):
    """Frames stored as ``(M, H, W)`` uint8 HDF5 datasets; image ``i`` is read on access."""

    def __init__(
        self,
        datasets: dict[str, Any],
        index: dict[str, npt.NDArray[np.int64]],
        t_ns: npt.NDArray[np.int64],
        exposure_ns: npt.NDArray[np.int64],
        path: Path,
        sizes: dict[str, tuple[int, int]],
    ) -> None:
        refs = {
            s: [Path(f"{path}#/{datasets[s].name.lstrip('/')}[{int(i)}]") for i in index[s]] for s in index
        }
        super().__init__(t_ns, exposure_ns, refs["left"], refs["right"], sizes["left"], sizes["right"])
        self._datasets = datasets
        self._index = index
        self._path = path

    def _image(self, i: int, side: str) -> npt.NDArray[np.uint8]:
        d = self._datasets[side]
        try:
            image = np.asarray(d[int(self._index[side][i])])
        except (OSError, RuntimeError, ValueError) as err:
            raise FileError(
                f"{self._path}: reading {d.name}[{i}] failed ({err})", path=str(self._path)
            ) from None
        size = self._sizes[side]
        if size is not None and (image.shape[1], image.shape[0]) != size:
            raise InputError(
                f"{self._path}: {d.name} frames are {image.shape[1]}x{image.shape[0]} but the calibration "
                f"says {size[0]}x{size[1]}",
                path=str(self._path),
                field="resolution",
            )
        return image.astype(np.uint8, copy=False)


def load_mvsec(
    path: str | Path,
    *,
    calibration: str | Path | RigCalibration | None = None,
    pair_tolerance_ns: int = 2_000_000,
) -> Sequence:
    """Open an MVSEC sequence.

    Parameters
    ----------
    path
        ``<seq>_data.hdf5``, or the folder holding exactly one ``*_data.hdf5``.
        ``<seq>_gt.hdf5`` next to it is read when present.
    calibration
        MVSEC's Kalibr ``camchain-imucam-*.yaml`` (or a rig); by default the one
        ``camchain*.yaml`` beside the data file.
    pair_tolerance_ns
        Largest stamp difference of a left/right frame pair.
    """
    data_path = _data_file(Path(path))
    seq_name = data_path.name[: -len("_data.hdf5")]
    if isinstance(calibration, RigCalibration):
        rig = calibration
    else:
        calib_path = Path(calibration) if calibration is not None else _find_camchain(data_path.parent)
        rig, _ = rig_from_kalibr(calib_path)
    f = _open_h5(data_path)
    try:
        frames = _frames(f, data_path, rig, pair_tolerance_ns)
        events = {side: MvsecEventSource(data_path, side, file=f) for side in ("left", "right")}
        gt_path = data_path.with_name(f"{seq_name}_gt.hdf5")
        ground_truth = _ground_truth(gt_path) if gt_path.exists() else None
    except BaseException:
        f.close()
        raise
    return Sequence(seq_name, data_path, rig, frames, events, ground_truth, on_close=f.close)


def _data_file(path: Path) -> Path:
    if path.is_dir():
        found = sorted(path.glob("*_data.hdf5"))
        if len(found) != 1:
            raise FileError(
                f"{path}: expected one <seq>_data.hdf5, found {len(found)}"
                + (f" ({', '.join(p.name for p in found)}); pass the file" if found else ""),
                path=str(path),
            )
        return found[0]
    if not path.name.endswith("_data.hdf5"):
        raise InputError(f"{path}: an MVSEC data file is named <seq>_data.hdf5", path=str(path), field="path")
    if not path.is_file():
        raise FileError(f"{path}: file not found", path=str(path))
    return path


def _find_camchain(folder: Path) -> Path:
    found = sorted(folder.glob("camchain*.yaml"))
    if len(found) != 1:
        raise FileError(
            f"{folder}: expected one Kalibr camchain*.yaml beside the data, found {len(found)}; "
            "pass calibration=",
            path=str(folder),
            field="calibration",
        )
    return found[0]


def _frames(f: Any, path: Path, rig: RigCalibration, tolerance_ns: int) -> HdfFrames:
    images: dict[str, Any] = {}
    stamps: dict[str, npt.NDArray[np.int64]] = {}
    for side in ("left", "right"):
        images[side] = _dataset(f, f"davis/{side}/image_raw", path, (), 3)
        ts = _dataset(f, f"davis/{side}/image_raw_ts", path, (), 1)
        if ts.shape[0] != images[side].shape[0]:
            raise ParseError(
                f"{path}: /davis/{side}/image_raw has {images[side].shape[0]} frames but image_raw_ts "
                f"{ts.shape[0]} stamps",
                path=str(path),
                field=f"davis/{side}/image_raw_ts",
            )
        stamps[side] = seconds_to_ns(ts[:])
        check_increasing(stamps[side], path, f"davis/{side}/image_raw_ts")
    i_left, i_right = pair_stereo(stamps["left"], stamps["right"], tolerance_ns)
    sizes = {
        s: (rig.cameras[f"frame_{s}"].width, rig.cameras[f"frame_{s}"].height) for s in ("left", "right")
    }
    return HdfFrames(
        images,
        {"left": i_left, "right": i_right},
        stamps["left"][i_left],
        np.zeros(len(i_left), np.int64),
        path,
        sizes,
    )


def _ground_truth(path: Path) -> GroundTruth:
    f = _open_h5(path)
    try:
        poses = _dataset(f, "davis/left/pose", path, (4, 4), 3)[:]
        ts = _dataset(f, "davis/left/pose_ts", path, (), 1)[:]
    finally:
        f.close()
    if len(poses) != len(ts):
        raise ParseError(
            f"{path}: /davis/left/pose has {len(poses)} poses but pose_ts {len(ts)} stamps",
            path=str(path),
            field="davis/left/pose_ts",
        )
    t_ns = seconds_to_ns(ts)
    check_increasing(t_ns, path, "davis/left/pose_ts")
    if not np.all(np.isfinite(poses)):
        raise InputError(
            f"{path}: /davis/left/pose holds NaN or infinity", path=str(path), field="davis/left/pose"
        )
    return GroundTruth(t_ns=t_ns, world_from_cam=poses_to_rows(np.asarray(poses, np.float64)))


__all__ = ["HdfFrames", "MvsecEventSource", "load_mvsec", "seconds_to_ns"]
