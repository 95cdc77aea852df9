"""Estimating δP_align, the constant event→frame pixel offset of eq. 5 (``dhptam calibrate-align``).

After the event→frame warp (rectified event camera → rectified frame camera through the
plane of ``[fusion] plane_depth_m``), a constant residual offset remains from calibration
errors; the paper adds it as δP_align. We estimate it from the sequence itself:

1. For every usable frame (APS-biased: neither under- nor over-exposed), the events of a
   short window **centred** on the fusion time, ``[t_f − h, t_f + h)``, are rectified and
   accumulated into a count image, and warped into the rectified frame camera with the
   current warp (δP_align = the configured value). A centred window matters: the E3CT's
   window ends at ``t_f`` and its content lags the frame by the camera motion, which would
   bias the estimate along the direction of motion.
2. Matches: around strong corners of the frame (``goodFeaturesToTrack``) a patch of the
   frame's gradient magnitude (edges, what events see) is searched for by normalised
   cross-correlation in the blurred event image, ±``max_shift_px``; a match is kept when the
   correlation peak is high (``min_score``) and the patch holds events. ORB/SIFT keypoints
   were tried first but sparse event images give almost none (1–4 per 128-px frame on the
   simulator), so the matches are patch correlations, refined to sub-pixel by a parabola
   through the peak.
3. A RANSAC on the 2-D translation (one match per hypothesis, inliers within
   ``inlier_px``) over all matches of all frames rejects mismatches; the residual is the
   median of the inliers' offsets (frame pixel − event pixel), and the new δP_align is the
   configured one plus that residual.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from . import _core
from .errors import InputError, NumericalError
from .events import count_image
from .frontend import Frontend
from .fusion import choose_beta, warp_to_frame
from .trajectory import atomic_write_text

_F32 = npt.NDArray[np.float32]
_F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class AlignEstimate:
    """Result of :func:`calibrate_align`: ``align_px`` is the δP_align to configure."""

    align_px: tuple[float, float]
    residual_px: tuple[float, float]
    previous_px: tuple[float, float]
    matches: int
    inliers: int
    frames_used: int
    spread_px: float


def _edges(image: npt.NDArray[np.uint8]) -> _F32:
    import cv2

    smooth = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 1.0)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
    return np.asarray(cv2.magnitude(gx, gy), np.float32)


def _parabola(c_minus: float, c0: float, c_plus: float) -> float:
    denom = c_minus - 2.0 * c0 + c_plus
    return 0.0 if denom >= 0.0 else float(np.clip(0.5 * (c_minus - c_plus) / denom, -0.5, 0.5))


def patch_matches(
    frame: npt.NDArray[np.uint8],
    events: _F32,
    *,
    patch: int = 15,
    max_shift_px: int = 6,
    min_score: float = 0.6,
    max_corners: int = 200,
) -> _F64:
    """High-confidence patch matches between a rectified frame and an event image in the same
    pixels (see the module): rows ``(u, v, dx, dy)``, the frame pixel and the offset
    frame pixel − event pixel."""
    import cv2

    edges = _edges(frame)
    blurred = cv2.GaussianBlur(np.asarray(events, np.float32), (0, 0), 1.0)
    h, w = frame.shape
    r = patch // 2
    margin = r + max_shift_px + 1
    corners = cv2.goodFeaturesToTrack(frame, max_corners, 0.01, patch / 2)
    offsets = []
    if corners is None:
        return np.empty((0, 4))
    for u, v in corners.reshape(-1, 2).round().astype(int):
        if not (margin <= u < w - margin and margin <= v < h - margin):
            continue
        template = edges[v - r : v + r + 1, u - r : u + r + 1]
        region = blurred[
            v - r - max_shift_px : v + r + max_shift_px + 1, u - r - max_shift_px : u + r + max_shift_px + 1
        ]
        if template.std() < 1e-6 or np.count_nonzero(region) < patch * 2 or region.std() < 1e-9:
            continue
        score = cv2.matchTemplate(region, template, cv2.TM_CCOEFF_NORMED)
        iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
        best = float(score[iy, ix])
        if best < min_score or not (0 < ix < score.shape[1] - 1 and 0 < iy < score.shape[0] - 1):
            continue
        dx = ix - max_shift_px + _parabola(score[iy, ix - 1], best, score[iy, ix + 1])
        dy = iy - max_shift_px + _parabola(score[iy - 1, ix], best, score[iy + 1, ix])
        # The frame's content at (u, v) is found in the event image at (u + dx, v + dy).
        offsets.append((u, v, -dx, -dy))
    return np.asarray(offsets, np.float64).reshape(-1, 4)


def _compensate_parallax(
    fe: Frontend, side: str, frame: npt.NDArray[np.uint8], other: npt.NDArray[np.uint8], matches: _F64
) -> _F64:
    """Removes from each match the parallax of its 3-D point with respect to the warp plane.

    The warp maps event pixels through the plane of ``plane_depth_m``; a point at another
    depth lands ``Δ = q − W_plane(p_event)`` pixels away from its frame pixel ``q`` even with a
    perfect calibration. With the point's depth from StereoSGBM on the rectified frame pair
    (median over the patch), ``p_event`` is its projection into the rectified event camera and
    Δ is subtracted, so the estimate does not depend on the plane depth. Matches without a
    valid depth are dropped.
    """
    from .depth import sgbm

    calib = fe.calibration
    if side == "left":
        inverse = sgbm(frame, other, calib)
    else:
        # SGBM matches left against right; mirrored images turn the right view into a left one.
        inverse = np.ascontiguousarray(
            np.fliplr(sgbm(np.fliplr(frame).copy(), np.fliplr(other).copy(), calib))
        )
    kf, ke = fe.frame_rect.K, fe.event_rect.K
    frame_from_event = fe.frame_from_event[side].matrix()
    event_from_frame = np.linalg.inv(frame_from_event)
    depth_m = fe.plane_depth_m
    # Plane homography event → frame: K_f (R + t nᵀ / d) K_e⁻¹ with n = (0, 0, 1); at infinity K_f R K_e⁻¹.
    plane = frame_from_event[:3, :3].copy()
    if depth_m > 0:
        plane[:, 2] += frame_from_event[:3, 3] / depth_m
    h_plane = kf @ plane @ np.linalg.inv(ke)
    kept = []
    for u, v, dx, dy in matches:
        iu, iv = int(u), int(v)
        rho = inverse[max(iv - 3, 0) : iv + 4, max(iu - 3, 0) : iu + 4]
        rho = rho[np.isfinite(rho)]
        if rho.size < 5:
            continue
        z = 1.0 / float(np.median(rho))
        p_frame = z * np.linalg.solve(kf, [u, v, 1.0])
        p_event = event_from_frame[:3, :3] @ p_frame + event_from_frame[:3, 3]
        if p_event[2] <= 0:
            continue
        q_event = ke @ (p_event / p_event[2])
        q_plane = h_plane @ q_event
        delta = np.array([u, v]) - q_plane[:2] / q_plane[2]
        kept.append((u, v, dx - delta[0], dy - delta[1]))
    return np.asarray(kept, np.float64).reshape(-1, 4)


def ransac_translation(offsets: _F64, inlier_px: float = 1.0) -> tuple[_F64, npt.NDArray[np.bool_]]:
    """Median translation of the largest consensus set (every offset is tried as the model;
    deterministic) and the inlier mask."""
    if offsets.shape[0] == 0:
        raise NumericalError("no matches to estimate a translation from", field="matches")
    best = np.zeros(offsets.shape[0], bool)
    for candidate in offsets:
        inliers = np.linalg.norm(offsets - candidate, axis=1) <= inlier_px
        if inliers.sum() > best.sum():
            best = inliers
    return np.median(offsets[best], axis=0), best


def calibrate_align(
    sequence: object,
    config: _core.Config | None = None,
    *,
    side: str = "left",
    half_window_ms: float = 10.0,
    max_frames: int | None = None,
    min_matches: int = 20,
    inlier_px: float = 1.0,
    depth_compensation: bool = True,
) -> AlignEstimate:
    """Estimates δP_align of ``side`` on a :class:`~dhptam.datasets.Sequence` (see the module)."""
    if half_window_ms <= 0:
        raise InputError(f"half_window_ms must be positive, got {half_window_ms}", field="half_window_ms")
    fe = Frontend(sequence, "fusion", config, prefetch=0)  # type: ignore[arg-type]
    if side not in ("left", "right"):
        raise InputError(f'side must be "left" or "right", got {side!r}', field="side")
    ke, kf = fe.event_rect.K, fe.frame_rect.K
    k_event = [ke[0, 0], ke[1, 1], ke[0, 2], ke[1, 2]]
    k_frame = [kf[0, 0], kf[1, 1], kf[0, 2], kf[1, 2]]
    ew, eh = int(fe.event_rect.width), int(fe.event_rect.height)
    half_ns = round(half_window_ms * 1e6)
    indices = np.arange(len(fe.t_f_ns))
    if max_frames is not None and max_frames < len(indices):
        indices = np.unique(np.linspace(0, len(indices) - 1, max_frames).round().astype(int))
    all_offsets = []
    frames_used = 0
    for k in indices.tolist():
        pair = fe.sequence.frames[k]
        frame = fe._rectify_frame(pair.left if side == "left" else pair.right, side)
        if choose_beta(frame, None, fe.config).bias != "aps":
            continue
        t = int(fe.t_f_ns[k])
        t0, t1 = t - half_ns, t + half_ns
        window, _ = fe._rectified_events(side, t0, t1)
        counts = count_image(
            window.x, window.y, window.t_ns, window.p, width=ew, height=eh, t_start_ns=t0, t_end_ns=t1
        )
        warped, _ = warp_to_frame(
            counts,
            k_event,
            k_frame,
            fe.frame_from_event[side],
            width=frame.shape[1],
            height=frame.shape[0],
            depth_m=fe.plane_depth_m,
            align_px=fe.align_px,
        )
        matches = patch_matches(frame, warped[:, :, 0])
        if depth_compensation and matches.shape[0]:
            other = fe._rectify_frame(
                pair.right if side == "left" else pair.left, "right" if side == "left" else "left"
            )
            matches = _compensate_parallax(fe, side, frame, other, matches)
        if matches.shape[0]:
            frames_used += 1
            all_offsets.append(matches[:, 2:])
    stacked = np.vstack(all_offsets) if all_offsets else np.empty((0, 2))
    if stacked.shape[0] < min_matches:
        raise NumericalError(
            f"only {stacked.shape[0]} high-confidence event/frame matches (need {min_matches}); "
            "use a sequence with well-exposed, textured frames and camera motion",
            field="matches",
        )
    residual, inliers = ransac_translation(stacked, inlier_px)
    previous = fe.align_px
    spread = float(np.median(np.linalg.norm(stacked[inliers] - residual, axis=1)))
    return AlignEstimate(
        align_px=(previous[0] + float(residual[0]), previous[1] + float(residual[1])),
        residual_px=(float(residual[0]), float(residual[1])),
        previous_px=previous,
        matches=int(stacked.shape[0]),
        inliers=int(inliers.sum()),
        frames_used=frames_used,
        spread_px=spread,
    )


def write_align_config(
    base: _core.Config | None, align_px: tuple[float, float], out: str | Path
) -> _core.Config:
    """Writes ``base`` (defaults when None) with ``[fusion] align_px`` replaced, as documented
    TOML, atomically; returns the new configuration (validated by parsing it back)."""
    text = (base or _core.Config()).to_toml()
    head, sep, tail = text.partition("[fusion]")
    if not sep:
        raise InputError("the configuration has no [fusion] section", field="fusion")
    value = f"align_px = [{align_px[0]:.4f}, {align_px[1]:.4f}]"
    tail, n = re.subn(r"(?m)^align_px = \[.*\]$", value, tail, count=1)
    if n != 1:
        raise InputError("the [fusion] section has no align_px key", field="fusion.align_px")
    config = _core.Config.from_toml(head + sep + tail, str(out))
    atomic_write_text(out, config.to_commented_toml())
    return config


__all__ = ["AlignEstimate", "calibrate_align", "patch_matches", "ransac_translation", "write_align_config"]
