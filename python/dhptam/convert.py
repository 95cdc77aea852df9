"""``dhptam convert``: rewrite a sequence of any readable format in another format.

Readers are :data:`dhptam.datasets.FORMATS`; writers are the :data:`WRITERS` table, keyed by
format name, each ``writer(sequence, dst, t0_ns, t1_ns, progress) -> Path``. Output is atomic:
a writer builds a hidden temporary folder or file next to ``dst`` and renames it into place
only when everything is written, so an error or Ctrl-C leaves nothing behind.

``start`` and ``duration`` (seconds) cut the window ``[t_begin + start, t_begin + start +
duration)``, where ``t_begin`` is the first frame's stamp (the first event's time when the
sequence has no frames); frames are kept by their stamp, events and ground truth by their time.

Writing TUM-VIE
---------------
The rig is written as Basalt JSON; ground truth becomes ``mocap_data.txt`` with the left frame
camera as the "marker" (``T_imu_marker = T_imu_cam[frame_left]``), so that reading it back gives
the same ``world_from_cam``. Event times are stored in whole microseconds (TUM-VIE's unit),
rounded down, relative to a ``/t_offset`` of whole seconds (DSEC convention) so that
``/ms_to_idx`` stays short for Unix-time stamps; frames are re-encoded as JPEG (quality
:data:`~dhptam.datasets.tumvie.JPEG_QUALITY`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError

EVENT_CHUNK_NS = 50_000_000
"""Events are copied in windows of 50 ms: memory stays bounded by one window's events."""


def _window(sequence: Any, start_s: float | None, duration_s: float | None) -> tuple[int, int]:
    if len(sequence.frames):
        t_begin = int(sequence.frames.t_ns[0])
    else:
        ranges = [s.t_range_ns for s in sequence.events.values() if len(s)]
        if not ranges:
            raise InputError(f"{sequence.path}: the sequence has neither frames nor events", field="path")
        t_begin = min(r[0] for r in ranges)
    for name, value in (("start", start_s), ("duration", duration_s)):
        if value is not None and not (np.isfinite(value) and value >= 0):
            raise InputError(f"--{name} must be a non-negative number of seconds, got {value}", field=name)
    t0 = t_begin + round((start_s or 0.0) * 1e9)
    t1 = np.iinfo(np.int64).max if duration_s is None else t0 + round(duration_s * 1e9)
    return t0, int(t1)


def _bar(enabled: bool, total: int, desc: str) -> Any:
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step")


def _write_tumvie(sequence: Any, dst: Path, t0: int, t1: int, progress: bool) -> Path:
    bar = _bar(progress, _steps(sequence, t0, t1), f"convert → tum-vie {dst.name}")
    try:
        return _write_tumvie_steps(sequence, dst, t0, t1, bar)
    finally:
        if bar is not None:
            bar.close()


def _write_tumvie_steps(sequence: Any, dst: Path, t0: int, t1: int, progress: Any) -> Path:
    from .datasets import TumVieWriter

    rig = sequence.calibration
    frames = sequence.frames
    keep = np.nonzero((frames.t_ns >= t0) & (frames.t_ns < t1))[0]
    streams = {side: sequence.events[side] for side in ("left", "right") if side in sequence.events}
    starts = [max(s.t_range_ns[0], t0) for s in streams.values() if len(s)]
    # Whole seconds before the first event written: stored event times stay small (module doc).
    offset_us = max(0, min(starts) // 1_000_000_000 * 1_000_000) if starts else 0
    with TumVieWriter(
        dst.parent, dst.name, rig, rig.imu_from_cam["frame_left"], event_t_offset_us=offset_us
    ) as writer:
        for k in keep:
            pair = frames[int(k)]
            writer.add_frame_pair(pair.t_ns, pair.exposure_ns, pair.left, pair.right)
            if progress is not None:
                progress.update(1)
        for side, stream in streams.items():
            lo, hi = stream.t_range_ns
            a, b = max(lo, t0), min(hi, t1)
            if b <= a:
                continue
            for window in stream.iter_windows(EVENT_CHUNK_NS, a, b):
                if len(window):
                    writer.add_events(side, window.x, window.y, window.t_ns, window.p)
                if progress is not None:
                    progress.update(1)
        gt = sequence.ground_truth
        if gt is not None:
            sel = (gt.t_ns >= t0) & (gt.t_ns < t1)
            if np.any(sel):
                writer.set_mocap(gt.t_ns[sel], gt.world_from_cam[sel])
    return dst


def _steps(sequence: Any, t0: int, t1: int) -> int:
    frames = int(np.count_nonzero((sequence.frames.t_ns >= t0) & (sequence.frames.t_ns < t1)))
    chunks = 0
    for stream in sequence.events.values():
        lo, hi = stream.t_range_ns
        a, b = max(lo, t0), min(hi, t1)
        if b > a:
            chunks += -(-(b - a) // EVENT_CHUNK_NS)
    return frames + chunks


def _write_mcap(sequence: Any, dst: Path, t0: int, t1: int, progress: bool) -> Path:
    from .datasets.mcap import sequence_start_ns, write_sequence

    origin = sequence_start_ns(sequence)
    duration = None if t1 == np.iinfo(np.int64).max else (t1 - t0) / 1e9
    return write_sequence(sequence, dst, start_s=(t0 - origin) / 1e9, duration_s=duration, progress=progress)


WRITERS: dict[str, Callable[[Any, Path, int, int, bool], Path]] = {
    "tum-vie": _write_tumvie,
    "mcap": _write_mcap,
}
"""Writer of each output format: ``(sequence, dst, t0_ns, t1_ns, progress) -> dst``, atomic."""


def convert(
    src: str | Path,
    dst: str | Path,
    *,
    from_format: str,
    to_format: str = "tum-vie",
    start_s: float | None = None,
    duration_s: float | None = None,
    calibration: str | Path | None = None,
    progress: bool = False,
) -> Path:
    """Read ``src`` as ``from_format`` and write ``dst`` as ``to_format``; returns ``dst``.

    Examples
    --------
    ``convert("vector/corridors_walk1", "out/corridors_walk1", from_format="vector",
    start_s=5, duration_s=10)`` writes ten seconds as a TUM-VIE folder.
    """
    from .datasets import load

    writer = WRITERS.get(to_format)
    if writer is None:
        raise InputError(f"cannot write {to_format!r}; choose one of {', '.join(WRITERS)}", field="to")
    dst = Path(dst)
    if dst.exists():
        raise InputError(f"{dst} already exists; choose a new destination", field="dst")
    with load(from_format, src, calibration=calibration) as sequence:
        t0, t1 = _window(sequence, start_s, duration_s)
        return writer(sequence, dst, t0, t1, progress)


__all__ = ["EVENT_CHUNK_NS", "WRITERS", "convert"]
