"""The SLAM back-end: stereo features in, poses and a map out (issue 7, SPEC-NOTES §5).

Input per frame: features of the RECTIFIED left and right images (pinhole, no distortion,
the right camera at +baseline along the left x axis), as produced by ``dhptam.features``:
anything with ``.keypoints`` ((N, 2) float32, x = column, y = row) and ``.descriptors``
((N, D) float32 unit rows or (N, B) uint8) arrays, and optionally ``.sigmas`` ((N,) float32,
each keypoint's location noise in pixels; the left image's weigh its residuals by 1/σ with
``[tracking] keypoint_sigma = "octave"``). All are read in place by the Rust core,
which tracks with the GIL released; mapping runs on its own thread unless ``threaded=False``
(then inline and deterministic). Poses are ``world_from_cam`` 4×4 matrices of the rectified
left camera; the world frame is the first keyframe's camera frame.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._core import Config
from .errors import InputError

TrackState = Literal["initialised", "ok", "lost", "relocalised", "predicted", "held"]


class FeatureSet(Protocol):
    """What ``System.track`` reads from each image's features."""

    @property
    def keypoints(self) -> NDArray[np.float32]: ...

    @property
    def descriptors(self) -> NDArray[np.float32] | NDArray[np.uint8]: ...


def _sigmas(features: FeatureSet) -> NDArray[np.float32] | None:
    """The features' per-keypoint σ, or ``None`` (1 px each) when they carry none."""
    return getattr(features, "sigmas", None)


def _viewpoint(centre: ArrayLike) -> tuple[float, float, float]:
    """A camera centre ``(x, y, z)`` in metres as the binding takes it."""
    c = np.asarray(centre, np.float64)
    if c.shape != (3,):
        raise InputError(f"viewpoint: expected (x, y, z) in metres, got shape {c.shape}", field="viewpoint")
    return (float(c[0]), float(c[1]), float(c[2]))


def _disparity(correction: tuple[float, float]) -> tuple[float, float]:
    """A ``(scale, offset_px)`` disparity correction as the binding takes it."""
    scale, offset = correction
    return float(scale), float(offset)


@dataclass(frozen=True)
class StereoCalibration:
    """Rectified stereo calibration: left intrinsics (pixels), baseline (metres), image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float
    width: int
    height: int


@dataclass(frozen=True)
class TrackResult:
    """The result of tracking one frame."""

    t_ns: int
    pose: NDArray[np.float64]
    """(4, 4) world_from_cam; for a lost frame the constant-velocity prediction."""
    state: TrackState
    inliers: int
    keyframe: bool


def _track_result(t_ns: int, core: tuple[NDArray[np.float64], str, int, bool]) -> TrackResult:
    """A :class:`TrackResult` from the core's (pose, state, inliers, keyframe) tuple."""
    pose, state, inliers, keyframe = core
    return TrackResult(
        t_ns=int(t_ns),
        pose=pose,
        state=state,  # type: ignore[arg-type]
        inliers=inliers,
        keyframe=keyframe,
    )


@dataclass(frozen=True)
class BridgeResult:
    """A bridge keyframe (:meth:`System.bridge`): its id, the map points re-matched by the
    tracked image and the new points from the other image's stereo matches."""

    keyframe: int
    linked: int
    other_points: int


class System:
    """Stereo SLAM over per-frame features; see the module documentation."""

    def __init__(
        self,
        calibration: StereoCalibration,
        config: Config | None = None,
        threaded: bool = True,
    ) -> None:
        c = calibration
        self.calibration = calibration
        self._core = _core.PySystem(c.fx, c.fy, c.cx, c.cy, c.baseline_m, c.width, c.height, config, threaded)

    def track(
        self,
        t_ns: int,
        left: FeatureSet,
        right: FeatureSet,
        sigma_scale: float = 1.0,
        disparity: tuple[float, float] = (1.0, 0.0),
        event_stereo: _core.EventStereo | None = None,
        viewpoint: tuple[float, float, float] = (0.0, 0.0, 0.0),
        dvs_biased: bool = False,
        quiet: bool = False,
    ) -> TrackResult:
        """Tracks one rectified stereo frame taken at ``t_ns`` nanoseconds; ``sigma_scale``
        multiplies every keypoint σ of the frame (e.g. an event-dominated image).
        ``disparity`` ``(scale, offset_px)`` maps each stereo match's disparity ``d`` to the
        frame cameras' ``scale · d + offset_px``: identity for frames, and
        :meth:`dhptam.frontend.Frontend.event_disparity` for event images warped into the
        frame cameras (their disparity follows the event cameras' baseline).
        ``event_stereo`` (:meth:`dhptam.frontend.Frontend.event_stereo`) reads such a pair's
        stereo matches exactly instead: each match is triangulated with the event cameras
        and its left keypoint and right column moved to where the frame cameras see the
        point; ``disparity`` must then stay the identity. ``viewpoint`` is the centre, in
        metres in the rectified left frame camera's axes, of the cameras whose view the
        images are: zero for the frame cameras' own, and for event images warped into the
        frame cameras through the plane at infinity the left event camera's
        (:meth:`dhptam.frontend.Frontend.event_viewpoint`), so that tracking, new map points
        and bundle adjustment model their keypoints from there. ``dvs_biased`` marks the
        fusion's DVS-biased (event-dominated) rendering: such a frame becomes a keyframe under
        ``[tracking] dvs_keyframe_min_tracked`` tracked points instead of
        ``keyframe_min_tracked``. ``quiet`` marks a quiet event window
        (:meth:`dhptam.frontend.Frontend.quiet`: the camera likely at rest, its event images
        sensor noise): when such a frame cannot be tracked it keeps the last pose (state
        ``held``, the motion model restarting from rest) instead of being relocalised or
        starting a new map segment on the noise."""
        return _track_result(
            t_ns,
            self._core.track(
                int(t_ns),
                left.keypoints,
                left.descriptors,
                right.keypoints,
                right.descriptors,
                _sigmas(left),
                float(sigma_scale),
                _disparity(disparity),
                event_stereo,
                _viewpoint(viewpoint),
                bool(dvs_biased),
                bool(quiet),
            ),
        )

    def predict(self, t_ns: int) -> TrackResult:
        """Moves the pose on to ``t_ns`` with the constant-velocity model instead of tracking
        a frame whose images carry no usable measurement (an event window flooded by a
        lighting change). The pose is recorded in the trajectory with state ``predicted``;
        the map and the motion model are unchanged, so the next frame is tracked against the
        map from an extrapolated prediction (and a bridge keyframe may still be inserted at
        the last tracked frame). ``lost`` (nothing recorded) before initialisation or after a
        lost frame."""
        return _track_result(t_ns, self._core.predict(int(t_ns)))

    def bridge(
        self,
        t_ns: int,
        primary: tuple[FeatureSet, FeatureSet],
        other: tuple[FeatureSet, FeatureSet],
        sigma_scales: tuple[float, float] = (1.0, 1.0),
        disparities: tuple[tuple[float, float], tuple[float, float]] = ((1.0, 0.0), (1.0, 0.0)),
        event_stereo: tuple[_core.EventStereo | None, _core.EventStereo | None] = (None, None),
        viewpoints: tuple[tuple[float, float, float], tuple[float, float, float]] = (
            (0.0, 0.0, 0.0),
            (0.0, 0.0, 0.0),
        ),
    ) -> BridgeResult | None:
        """Inserts a bridge keyframe at the last tracked frame (taken at ``t_ns``) across a
        change of image appearance, e.g. the fusion switching between frame- and
        event-dominated images.

        ``primary`` are the (left, right) features of the image that frame was tracked with,
        ``other`` those of the same sensor data rendered the other way (e.g. blended with the
        other fusion mode's β). The primary features are matched against the map again at
        the frame's pose; the keyframe holds both images' features, observes the re-matched
        map points and adds the other image's stereo points, so the next frames, which look
        like ``other``, track against it and the map stays one piece. ``None`` when refused:
        the last frame is not at ``t_ns``, was lost, or too few primary features matched.
        ``sigma_scales`` multiply the keypoint σ of ``primary`` and ``other``;
        ``disparities`` are their disparity corrections, ``event_stereo`` their
        event-stereo readings and ``viewpoints`` their viewpoints (see :meth:`track`).
        """
        (pl, pr), (ol, orr) = primary, other
        r = self._core.bridge(
            int(t_ns),
            pl.keypoints, pl.descriptors, pr.keypoints, pr.descriptors,
            ol.keypoints, ol.descriptors, orr.keypoints, orr.descriptors,
            _sigmas(pl), _sigmas(ol), float(sigma_scales[0]), float(sigma_scales[1]),
            _disparity(disparities[0]), _disparity(disparities[1]),
            event_stereo[0], event_stereo[1],
            _viewpoint(viewpoints[0]), _viewpoint(viewpoints[1]),
        )  # fmt: skip
        if r is None:
            return None
        return BridgeResult(keyframe=r[0], linked=r[1], other_points=r[2])

    def tracking_totals(self) -> dict[str, int]:
        """Since the start: ``bridges`` inserted, ``bridges_refused``, new map ``segments``
        (started at the constant-velocity pose), ``relocalisations``, ``predicted`` frames
        (:meth:`predict`), quiet frames ``held`` at rest (:meth:`track`) and ``implausible``
        tracked poses, rejected for jumping away from the
        motion model's prediction (``[tracking] max_jump_ratio``)."""
        return self._core.tracking_totals()

    def tracked_depth(self) -> float | None:
        """Median depth in metres (rectified left camera) of the map points the last
        :meth:`track` measured its pose with (after a bootstrap: the points it created);
        ``None`` before the first frame, after a lost frame or without such points.
        :meth:`predict` leaves it unchanged."""
        return self._core.tracked_depth()

    def trajectory(self, smoothed: bool = True) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """(t_ns (N,), poses (N, 4, 4)) of every tracked frame, with the latest corrections;
        with ``[tracking] smoothing_q`` > 0 and ``smoothed`` the camera centres are those of
        the trajectory smoother (each frame weighted by its own measured covariance), else
        as tracked."""
        return self._core.trajectory(smoothed)

    def keyframe_trajectory(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """(t_ns (K,), poses (K, 4, 4)) of the keyframes."""
        return self._core.keyframe_trajectory()

    def map_points(self) -> NDArray[np.float64]:
        """(N, 3) map point positions, world frame, metres."""
        return self._core.map_points()

    def loop_closures(self) -> list[tuple[int, int]]:
        """Accepted loops as (query keyframe t_ns, matched keyframe t_ns)."""
        return self._core.loop_closures()

    def timing(self) -> dict[str, dict[str, float]]:
        """Per stage: count, total_s, mean_s, max_s of wall time."""
        return self._core.timing()

    def save_map(self, path: str | os.PathLike[str]) -> None:
        """Writes the map and the tracker state (binary, atomically)."""
        self._core.save_map(path)

    def load_map(self, path: str | os.PathLike[str]) -> None:
        """Replaces the map and tracker state with a saved one (same calibration)."""
        self._core.load_map(path)

    def refine_map(self, iterations: int = 20) -> dict[str, int]:
        """Bundle adjustment of the whole map after the last frame: every keyframe and map
        point, the first keyframe of each map segment held fixed, ``iterations``
        Levenberg–Marquardt iterations; outlier observations are removed. The trajectory
        (stored relative to keyframes) follows. Returns the counts ``optimised`` and
        ``fixed`` keyframes, ``points``, ``outliers_removed`` and ``culled`` points. Best
        called after :meth:`shutdown` (with mapping still running, a loop correction made
        meanwhile discards the result)."""
        return self._core.refine_map(int(iterations))

    def shutdown(self) -> None:
        """Stops mapping (queued keyframes are dropped); later ``track`` calls raise."""
        self._core.shutdown()

    def __enter__(self) -> System:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()
