"""Event representations: the E3CT of DH-PTAM, ablation baselines, fusion windows.

The kernels run in the Rust core (``dhptam._core``) with the GIL released. Event arrays are
read in place when they already have the dtypes of :class:`dhptam.datasets.EventWindow`
(``x``, ``y`` uint16, ``t_ns`` int64, ``p`` int8) and are C-contiguous; anything else is
converted once, after checking that the values fit those dtypes.

Bad events are errors, never skipped: a pixel outside the image, a polarity other than 0/1,
a time outside ``[t_start_ns, t_end_ns)`` or a time smaller than the previous event's raises
:class:`dhptam.errors.InputError` whose ``field`` names the first offending event (e.g.
``"event 12 (x, y)"``). Each of these means the window was cut wrongly or the calibration does
not match the events, which dropping events would hide.

The exact E3CT formula and the reasoning behind it are in ``docs/E3CT.md``.

Example: one event at the centre of the decay kernel lands, with weight 1, in channel 1::

    >>> import numpy as np
    >>> from dhptam.events import e3ct
    >>> ms = 1_000_000
    >>> img = e3ct([2], [1], [15 * ms], [1], width=4, height=3, t_start_ns=0, t_end_ns=30 * ms)
    >>> img.shape, img.dtype, img[1, 2].tolist()
    ((3, 4, 3), dtype('float32'), [0.0, 1.0, 0.0])
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from . import _core
from .errors import InputError

if TYPE_CHECKING:
    from .datasets import EventSource, EventWindow, FramePair, Frames

_F32 = npt.NDArray[np.float32]


def _typed(values: Any, dtype: type[np.generic], name: str) -> npt.NDArray[Any]:
    """``values`` as a C-contiguous array of ``dtype``: the array itself when it already is one."""
    if isinstance(values, np.ndarray) and values.dtype == dtype and values.flags.c_contiguous:
        if values.ndim != 1:
            raise InputError(f"{name} must be 1-D, got shape {values.shape}", field=name)
        return values
    array = np.asarray(values)
    if array.ndim != 1:
        raise InputError(f"{name} must be 1-D, got shape {array.shape}", field=name)
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise InputError(f"{name} must hold integers, got dtype {array.dtype}", field=name)
    if array.size:
        info = np.iinfo(dtype)
        lo, hi = int(array.min()), int(array.max())
        if lo < info.min or hi > info.max:
            raise InputError(
                f"{name} must fit {np.dtype(dtype).name} ([{info.min}, {info.max}]), "
                f"got values in [{lo}, {hi}]",
                field=name,
            )
    return np.ascontiguousarray(array, dtype=dtype)


def _window(x: Any, y: Any, t_ns: Any, p: Any) -> tuple[npt.NDArray[Any], ...]:
    return (
        _typed(x, np.uint16, "x"),
        _typed(y, np.uint16, "y"),
        _typed(t_ns, np.int64, "t_ns"),
        _typed(p, np.int8, "p"),
    )


def e3ct(
    x: npt.ArrayLike,
    y: npt.ArrayLike,
    t_ns: npt.ArrayLike,
    p: npt.ArrayLike,
    *,
    width: int,
    height: int,
    t_start_ns: int,
    t_end_ns: int,
    alpha: float = 0.5,
    eta_ms: float = 30.0,
    channels: int = 3,
    polarity: str = "both",
) -> _F32:
    """Event 3-Channel Tensor of the window ``[t_start_ns, t_end_ns)``, not normalised.

    Each event adds ``V1 = exp(-alpha ((a - eta/2) / (eta/6))^2)``, with ``a`` its age in ms
    at ``t_end_ns``, to the two temporal channels around ``tau (channels - 1)``, ``tau`` its
    normalised time in the window, split linearly (tent voting).

    Parameters
    ----------
    x, y, t_ns, p
        The events, sorted by time (see the module docstring for dtypes and errors).
    width, height
        Image size in pixels.
    t_start_ns, t_end_ns
        The window; every event must lie in it.
    alpha, eta_ms
        Decay kernel sharpness and span (the paper: 0.5 and 30 ms).
    channels
        Temporal channels (3: a synthetic RGB image).
    polarity
        ``"both"`` (ON and OFF share the channels) or ``"split"`` (ON in the first
        ``channels`` channels, OFF in the next ``channels``).

    Returns
    -------
    numpy.ndarray
        ``(height, width, C)`` float32, ``C = channels`` or ``2 channels``; zeros for an
        empty window. Normalise left and right together with :func:`normalise`.
    """
    return _core._e3ct(
        *_window(x, y, t_ns, p),
        int(width),
        int(height),
        int(t_start_ns),
        int(t_end_ns),
        float(alpha),
        float(eta_ms),
        int(channels),
        polarity,
    )


def count_image(
    x: npt.ArrayLike,
    y: npt.ArrayLike,
    t_ns: npt.ArrayLike,
    p: npt.ArrayLike,
    *,
    width: int,
    height: int,
    t_start_ns: int,
    t_end_ns: int,
    polarity: str = "both",
) -> _F32:
    """Events per pixel, ``(H, W, 1)`` or, with ``polarity="split"``, ``(H, W, 2)`` (ON, OFF)."""
    return _core._count_image(
        *_window(x, y, t_ns, p), int(width), int(height), int(t_start_ns), int(t_end_ns), polarity
    )


@dataclass(frozen=True)
class Activity:
    """Pixel activity of one event window on one sensor (:func:`activity`): ``pixels`` of the
    sensor, ``active`` pixels (at least one event) and ``supported`` ones (an active pixel
    among their eight neighbours)."""

    pixels: int
    active: int
    supported: int

    @property
    def active_share(self) -> float:
        """Share of the sensor's pixels that are active."""
        return self.active / self.pixels if self.pixels else 0.0

    @property
    def structured_share(self) -> float:
        """Active pixels supported beyond chance, as a share of the sensor's pixels:
        ``(supported - active * chance) / pixels``, with ``chance = 1 - (1 - active_share)**8``
        the support independent pixels would get at that density. About zero for sensor noise
        alone, whatever its rate; about the share of pixels on moving edges for a moving
        camera; meaningless when most pixels are active."""
        if not self.pixels:
            return 0.0
        chance = 1.0 - (1.0 - self.active_share) ** 8
        return (self.supported - self.active * chance) / self.pixels


def activity(x: npt.ArrayLike, y: npt.ArrayLike, *, width: int, height: int) -> Activity:
    """How much of a window with events at pixels ``(x, y)`` of a ``width × height`` sensor is
    scene structure rather than sensor noise (:class:`Activity`). A moving camera's events
    line up along edges, so an active pixel mostly has an active neighbour; noise pixels fire
    independently. An event outside the sensor raises :class:`dhptam.errors.InputError`.

    >>> a = activity([10, 11, 12, 50], [5, 5, 5, 40], width=64, height=48)
    >>> (a.active, a.supported)
    (4, 3)
    """
    xs, ys = _typed(x, np.uint16, "x"), _typed(y, np.uint16, "y")
    return Activity(*_core._event_activity(xs, ys, int(width), int(height)))


def time_surface(
    x: npt.ArrayLike,
    y: npt.ArrayLike,
    t_ns: npt.ArrayLike,
    p: npt.ArrayLike,
    *,
    width: int,
    height: int,
    t_start_ns: int,
    t_end_ns: int,
    tau_ms: float = 30.0,
) -> _F32:
    """``(H, W, 2)`` (ON, OFF): ``exp(-(t_end - t_last) / tau)`` of each pixel's latest event, 0 if none."""
    return _core._time_surface(
        *_window(x, y, t_ns, p),
        int(width),
        int(height),
        int(t_start_ns),
        int(t_end_ns),
        float(tau_ms),
    )


def voxel_grid(
    x: npt.ArrayLike,
    y: npt.ArrayLike,
    t_ns: npt.ArrayLike,
    p: npt.ArrayLike,
    *,
    width: int,
    height: int,
    t_start_ns: int,
    t_end_ns: int,
    bins: int = 5,
) -> _F32:
    """``(H, W, bins)``: signed polarities (+1 ON, -1 OFF) tent-voted into temporal bins, no decay."""
    return _core._voxel_grid(
        *_window(x, y, t_ns, p), int(width), int(height), int(t_start_ns), int(t_end_ns), int(bins)
    )


def normalise(
    *tensors: npt.NDArray[np.float32],
    percentile: float = 99.0,
    scales: Sequence[float] | None = None,
) -> tuple[list[_F32], npt.NDArray[np.float32]]:
    """Divides each channel by a shared scale and clips to [0, 1].

    The scale of a channel is the ``percentile``-th percentile (nearest rank) of its non-zero
    values pooled over all ``tensors``, unless ``scales`` are given. Passing the left and right
    E3CT of one stereo window together gives both the same colours for the same scene.

    Returns the normalised copies and the scales used.

    >>> import numpy as np
    >>> a = np.zeros((1, 2, 1), np.float32); a[0, 0, 0] = 4.0
    >>> b = np.zeros((1, 2, 1), np.float32); b[0, 1, 0] = 2.0
    >>> (na, nb), s = normalise(a, b, percentile=100.0)
    >>> s.tolist(), na.ravel().tolist(), nb.ravel().tolist()
    ([4.0], [1.0, 0.0], [0.0, 0.5])
    """
    if not tensors:
        raise InputError("normalise needs at least one tensor", field="tensors")
    arrays = [np.ascontiguousarray(t, dtype=np.float32) for t in tensors]
    used = shared_scales(*arrays, percentile=percentile) if scales is None else [float(s) for s in scales]
    return [_core._e3ct_apply_scales(a, used) for a in arrays], np.asarray(used, np.float32)


def shared_scales(*tensors: npt.NDArray[np.float32], percentile: float = 99.0) -> npt.NDArray[np.float32]:
    """The per-channel scales :func:`normalise` would use, without the normalised copies.

    For the fusion step, which normalises inside the warp
    (``dhptam.fusion.warp_to_frame(raw, ..., scales=shared_scales(left, right))``).

    >>> import numpy as np
    >>> a = np.zeros((1, 2, 1), np.float32); a[0, 0, 0] = 4.0
    >>> shared_scales(a, percentile=100.0).tolist()
    [4.0]
    """
    if not tensors:
        raise InputError("shared_scales needs at least one tensor", field="tensors")
    arrays = [np.ascontiguousarray(t, dtype=np.float32) for t in tensors]
    return np.asarray(_core._e3ct_scales(arrays, float(percentile)), np.float32)


def stereo_e3ct(
    left: EventWindow,
    right: EventWindow,
    *,
    width: int,
    height: int,
    t_start_ns: int,
    t_end_ns: int,
    config: _core.Config | None = None,
) -> tuple[_F32, _F32, npt.NDArray[np.float32]]:
    """Normalised E3CT of a stereo window with scales shared by both sides.

    ``config`` supplies ``[events]`` (alpha, eta_ms, channels, polarity,
    normalise_percentile); defaults otherwise. Returns ``(left, right, scales)``.
    """
    section = (config or _core.Config()).to_dict()["events"]
    raw = [
        e3ct(
            w.x,
            w.y,
            w.t_ns,
            w.p,
            width=width,
            height=height,
            t_start_ns=t_start_ns,
            t_end_ns=t_end_ns,
            alpha=section["alpha"],
            eta_ms=section["eta_ms"],
            channels=section["channels"],
            polarity=section["polarity"],
        )
        for w in (left, right)
    ]
    (out_left, out_right), scales = normalise(*raw, percentile=section["normalise_percentile"])
    return out_left, out_right, scales


def fusion_times_ns(frames: Frames) -> npt.NDArray[np.int64]:
    """Fusion frame times t_f = t_cam + t_exp / 2 (paper eq. 2), one per frame pair."""
    return np.asarray(frames.t_mid_ns, dtype=np.int64)


def fusion_windows(
    frames: Frames,
    left: EventSource,
    right: EventSource,
    *,
    first_window_ns: int | None = None,
) -> Iterator[tuple[FramePair, EventWindow, EventWindow, int, int]]:
    """Yields ``(pair, left_events, right_events, t_start_ns, t_end_ns)`` per frame pair.

    Frame pair k gets the events of ``[t_f^(k-1), t_f^k)`` (paper eq. 2, SPEC-NOTES §2), with
    ``t_f = t_cam + t_exp / 2``. Frame pair 0 has no predecessor: its window ends at
    ``t_f^0`` and lasts ``first_window_ns``, by default as long as the next window
    (``t_f^1 - t_f^0``). Windows are read lazily, one pair at a time.
    """
    t_f = fusion_times_ns(frames)
    if t_f.size == 0:
        return
    if np.any(np.diff(t_f) <= 0):
        k = int(np.argmax(np.diff(t_f) <= 0)) + 1
        raise InputError(f"fusion times must increase; frame {k} is not after frame {k - 1}", field="frames")
    if first_window_ns is None:
        if t_f.size < 2:
            raise InputError(
                "a single frame pair needs first_window_ns (no next frame to take the window length from)",
                field="first_window_ns",
            )
        first_window_ns = int(t_f[1] - t_f[0])
    if first_window_ns <= 0:
        raise InputError(f"first_window_ns must be positive, got {first_window_ns}", field="first_window_ns")
    for k in range(t_f.size):
        t1 = int(t_f[k])
        t0 = t1 - first_window_ns if k == 0 else int(t_f[k - 1])
        yield frames[k], left.window(t0, t1), right.window(t0, t1), t0, t1


def postprocess(
    image: npt.NDArray[np.float32],
    *,
    denoise: float = 0.0,
    median: int = 0,
    stretch: bool = False,
    threshold: float | None = None,
) -> _F32:
    """Frame-style post-processing of a normalised E3CT (values in [0, 1]), with OpenCV.

    Applied in this order: non-local-means ``denoise`` of strength ``denoise`` (0: off;
    3-channel images only), ``median`` filter of that odd aperture (0: off; 3 or 5), per-channel
    contrast ``stretch`` of [min, max] to [0, 1], and a binary ``threshold`` (values above it
    become 1, the rest 0). The paper's Fig. 4 uses a median filter followed by a threshold.
    """
    import cv2

    out = np.ascontiguousarray(image, dtype=np.float32)
    if out.ndim != 3:
        raise InputError(f"image must be (H, W, C), got shape {out.shape}", field="image")
    if denoise > 0.0:
        if out.shape[2] != 3:
            raise InputError("denoise needs a 3-channel image", field="denoise")
        u8 = np.clip(out * 255.0 + 0.5, 0, 255).astype(np.uint8)
        out = (
            cv2.fastNlMeansDenoisingColored(u8, None, float(denoise), float(denoise)).astype(np.float32)
            / 255.0
        )
    if median:
        if median not in (3, 5):
            raise InputError(f"median aperture must be 3 or 5 for float images, got {median}", field="median")
        out = cv2.medianBlur(out, median).reshape(out.shape)
    if stretch:
        lo = out.min(axis=(0, 1), keepdims=True)
        hi = out.max(axis=(0, 1), keepdims=True)
        out = np.where(hi > lo, (out - lo) / np.where(hi > lo, hi - lo, 1.0), 0.0).astype(np.float32)
    if threshold is not None:
        out = (out > threshold).astype(np.float32)
    return out


class HotPixels:
    """The running hot-pixel detector of one event camera (raw sensor pixels).

    A hot pixel fires on its own, whatever the scene does: a bright dot at a fixed place in
    every event image. :meth:`update` offers one window; the detector counts one whenever an
    eighth of ``time_constant_s`` has passed since the last one it counted (hot pixels fire
    steadily, so sampling loses nothing; the other windows cost nothing). A pixel is hot while
    it fires at least ``min_rate_hz`` and ``ratio`` times more than each of its 8 neighbours
    (rates over the last few ``time_constant_s``), and has fired in three counted windows in a
    row (a burst of a real pixel on a passing detail does not). The rule and its reasons:
    ``docs/E3CT.md``, "Hot pixels".
    :class:`dhptam.frontend.Frontend` keeps one per camera (``[events] hot_pixel_*``) and
    drops their events before the E3CT.

    Example: a pixel firing 400 times a second alone in the dark::

        >>> import numpy as np
        >>> from dhptam.events import HotPixels
        >>> detector = HotPixels(width=8, height=6)
        >>> [detector.update(x=[3] * 20, y=[4] * 20, duration_s=0.05) for _ in range(7)]
        [False, False, False, False, False, False, True]
        >>> detector.pixels().tolist(), 4 * 8 + 3
        ([35], 35)
    """

    def __init__(
        self,
        width: int,
        height: int,
        *,
        ratio: float | None = None,
        min_rate_hz: float | None = None,
        time_constant_s: float | None = None,
    ) -> None:
        """A detector for a ``width × height`` sensor; a parameter left out (``None``) takes
        its ``[events] hot_pixel_*`` default (``dhptam.Config().to_dict()["events"]``)."""
        self._inner = _core.HotPixels(
            int(width), int(height), ratio=ratio, min_rate_hz=min_rate_hz, time_constant_s=time_constant_s
        )

    def update(self, x: npt.ArrayLike, y: npt.ArrayLike, duration_s: float) -> bool:
        """Offers a window of ``duration_s`` seconds with events at raw pixels ``(x, y)``;
        returns whether the set of hot pixels changed (always ``False`` for a window the
        detector does not count). A pixel outside the sensor raises
        :class:`dhptam.errors.InputError` naming the event, and changes nothing."""
        return bool(
            self._inner.update(_typed(x, np.uint16, "x"), _typed(y, np.uint16, "y"), float(duration_s))
        )

    def pixels(self) -> npt.NDArray[np.uint32]:
        """The hot pixels, raw indices ``y * width + x`` (uint32, ascending)."""
        return self._inner.pixels()

    def __len__(self) -> int:
        return len(self._inner)


__all__ = [
    "Activity",
    "HotPixels",
    "activity",
    "count_image",
    "e3ct",
    "fusion_times_ns",
    "fusion_windows",
    "normalise",
    "postprocess",
    "shared_scales",
    "stereo_e3ct",
    "time_surface",
    "voxel_grid",
]
