"""Fusion of events and frames (DH-PTAM eqs. 5–6): online β, blending, event→frame warp.

All three run in the Rust core with the GIL released.

* :func:`choose_beta`: with ``r = mean(C) / max(C)``, APS-biased
  ``beta = min(r, 1 - r, aps_beta_max)`` when the frame is usable (``[fusion] aps_beta_max``,
  0.3; 1 gives the paper's uncapped form), DVS-biased ``beta = max(r, 1 - r, dvs_beta_min)``
  (``dvs_beta_min`` 0.5: the paper's form) when more than
  ``[fusion] dvs_clipped_fraction`` of its pixels are under/over-exposed or fewer than
  ``min_features`` features were found on it; both capped at ``beta_max``; modes ``frames``
  (beta = 0) and ``events`` (beta = 1). See ``docs/FUSION.md``.
* :func:`recover_exposure`: a frame that fails the exposure test (too dark or too bright) has
  its grey levels between the 1st and 99th percentile stretched over 0–255 when that range
  holds at least ``[fusion] recover_min_snr`` deviations of the frame's noise; the front-end
  does this before choosing β (``[fusion] recover_exposure``).
* :func:`fuse`: ``(1 - beta) C + beta * 255 * D`` with ``D`` the per-pixel maximum of the
  normalised, warped E3CT channels.
* :func:`warp_to_frame`: the rectified E3CT resampled into the rectified frame camera through
  a plane at ``depth_m`` (0: infinity) with a real perspective divide, plus ``align_px``.

Example: a dark frame switches to the DVS-biased mode::

    >>> import numpy as np
    >>> from dhptam.fusion import choose_beta
    >>> dark = np.full((48, 64), 5, np.uint8); dark[0, 0] = 200
    >>> d = choose_beta(dark)
    >>> d.bias, round(d.beta, 3)
    ('dvs', 0.975)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from . import _core
from .errors import InputError
from .geometry import SE3


@dataclass(frozen=True)
class BetaDecision:
    """The β of one frame: ``bias`` is ``"aps"``, ``"dvs"``, ``"frames"`` or ``"events"``."""

    bias: str
    beta: float
    ratio: float
    clipped_fraction: float


def choose_beta(
    frame: npt.NDArray[np.uint8], feature_count: int | None = None, config: _core.Config | None = None
) -> BetaDecision:
    """β for an 8-bit grayscale frame (``[fusion]`` of ``config``, defaults otherwise)."""
    image = np.ascontiguousarray(frame, dtype=np.uint8)
    return BetaDecision(*_core._choose_beta(image, feature_count, config))


@dataclass(frozen=True)
class ExposureRecovery:
    """What :func:`recover_exposure` found: ``image`` is the frame to use (the stretched copy,
    or the input itself when it was not stretched); ``failed``: the exposure test failed
    (``clipped_fraction`` above ``[fusion] max_clipped_fraction``); ``low``/``high``: the grey
    levels at the 1st/99th percentile; ``noise``: the noise deviation in grey levels (0 when
    the frame passed and it was not estimated)."""

    image: npt.NDArray[np.uint8]
    failed: bool
    stretched: bool
    low: int
    high: int
    noise: float
    clipped_fraction: float

    @property
    def snr(self) -> float:
        """``(high - low) / noise``: noise deviations in the stretched range (inf without
        noise, 0 when not estimated)."""
        span = float(self.high - self.low)
        if self.noise > 0.0:
            return span / self.noise
        return float("inf") if self.failed and span > 0 else 0.0


def recover_exposure(frame: npt.NDArray[np.uint8], config: _core.Config | None = None) -> ExposureRecovery:
    """Stretches an under- or over-exposed 8-bit frame (H, W) to full contrast when its signal
    is well above its noise (``[fusion] recover_exposure``, ``recover_min_snr``; see
    ``docs/FUSION.md``). The input is never modified.

    >>> import numpy as np
    >>> from dhptam.fusion import recover_exposure
    >>> dark = np.tile(np.arange(16, dtype=np.uint8), (32, 4))  # a clean ramp over 0..15
    >>> r = recover_exposure(dark)
    >>> r.failed, r.stretched, int(r.image.min()), int(r.image.max())
    (True, True, 0, 255)
    """
    image = np.asarray(frame)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise InputError(
            f"frame must be a (H, W) uint8 image, got {image.dtype} {image.shape}", field="frame"
        )
    image = np.ascontiguousarray(image)
    stretched, failed, low, high, noise, clipped = _core._recover_exposure(image, config)
    return ExposureRecovery(
        image=image if stretched is None else stretched,
        failed=bool(failed),
        stretched=stretched is not None,
        low=int(low),
        high=int(high),
        noise=float(noise),
        clipped_fraction=float(clipped),
    )


def fuse(frame: npt.NDArray[np.uint8], e3ct: npt.NDArray[np.float32], beta: float) -> npt.NDArray[np.uint8]:
    """Blends an 8-bit frame (H, W) with a normalised E3CT (H, W, C) already in its pixels."""
    return _core._fuse(
        np.ascontiguousarray(frame, dtype=np.uint8), np.ascontiguousarray(e3ct, dtype=np.float32), float(beta)
    )


def _scale_list(scales: npt.ArrayLike | None) -> list[float] | None:
    """Per-channel normalisation scales as the binding takes them (float32 values)."""
    return None if scales is None else [float(s) for s in np.asarray(scales, np.float32).ravel()]


def warp_to_frame(
    image: npt.NDArray[np.float32],
    k_event: npt.ArrayLike,
    k_frame: npt.ArrayLike,
    frame_from_event: SE3,
    *,
    width: int,
    height: int,
    depth_m: float = 0.0,
    align_px: npt.ArrayLike = (0.0, 0.0),
    pixels: npt.ArrayLike | None = None,
    scales: npt.ArrayLike | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float64] | None]:
    """Resamples a rectified event image (H, W, C) into a ``height × width`` frame image.

    ``k_event`` and ``k_frame`` are ``[fx, fy, cx, cy]`` of the rectified cameras,
    ``frame_from_event`` maps rectified event-camera points to rectified frame-camera points.
    When ``pixels`` (N, 2) of the event image are given, their frame pixels are returned too
    (NaN behind the camera). With ``scales`` (one per channel, e.g. from
    :func:`dhptam.events.shared_scales`) a raw E3CT is normalised inside the warp, tap by tap:
    the same values as warping ``normalise(image, scales=scales)``, without that copy. The
    warp's inverse map is computed once per (warp, sizes) and reused by later calls.
    """
    return _core._warp_to_frame(
        np.ascontiguousarray(image, dtype=np.float32),
        k_event,
        k_frame,
        frame_from_event,
        float(depth_m),
        align_px,
        int(width),
        int(height),
        pixels,
        _scale_list(scales),
    )


def warp_and_fuse(
    image: npt.NDArray[np.float32],
    k_event: npt.ArrayLike,
    k_frame: npt.ArrayLike,
    frame_from_event: SE3,
    frame: npt.NDArray[np.uint8],
    beta: float,
    *,
    depth_m: float = 0.0,
    align_px: npt.ArrayLike = (0.0, 0.0),
    scales: npt.ArrayLike | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint8]]:
    """:func:`warp_to_frame` into the frame camera of ``frame`` (its size) and :func:`fuse` of
    the result with ``frame`` at ``beta``, in one pass: returns ``(warped, fused)``, the same
    values as the two calls, without reading the warped tensor back from memory. ``beta``
    comes from :func:`choose_beta` of the frame, before the warp.
    """
    return _core._warp_and_fuse(
        np.ascontiguousarray(image, dtype=np.float32),
        k_event,
        k_frame,
        frame_from_event,
        float(depth_m),
        align_px,
        np.ascontiguousarray(frame, dtype=np.uint8),
        float(beta),
        _scale_list(scales),
    )


__all__ = [
    "BetaDecision",
    "ExposureRecovery",
    "choose_beta",
    "fuse",
    "recover_exposure",
    "warp_and_fuse",
    "warp_to_frame",
]
