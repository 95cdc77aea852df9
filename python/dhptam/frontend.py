"""The per-frame front-end: events + frames → rectified fused stereo images (issue 5, Fig. 2).

For fusion frame k (time ``t_f^k = t_cam + t_exp / 2``) the pipeline is

1. the events of ``[t_f^(k-1), t_f^k)`` of each event camera (read lazily; frame 0 takes a
   window as long as the next one);
2. moved to their pixels in the **rectified event camera** through a lookup table built once
   (``_core.EventRectifier``: event arrays read in place, GIL released);
3. the E3CT of each side, normalised with per-channel scales shared by left and right;
4. warped into the **rectified frame camera** of the same side (``warp_to_frame``: eq. 5
   with a real perspective divide through a fronto-parallel plane, plus δP_align);
5. exposure recovery of the rectified frame: one that fails the exposure test but holds a
   clean signal is stretched to full contrast (``recover_exposure``, ``[fusion]
   recover_exposure``; ``docs/FUSION.md``);
6. β chosen online from that frame (APS/DVS bias, ``[fusion]``; before step 4) and the blend
   ``(1 − β) C + β D``, done in the warp's pass (``warp_and_fuse``).

Modes: ``fusion`` (the above), ``frames`` (rectified, recovered frames only; no event is read)
and ``events`` (the E3CT intensity alone, β = 1). Mode ``events`` tracks in the rectified
**event cameras** where they are sensors of their own (``[fusion] events_geometry = "auto"``,
the default, or ``"event"``; a DAVIS-like rig, whose events come from the frame cameras'
pixels, stays in the frame geometry under ``"auto"``): steps 4–6 are skipped,
the normalised E3CT keeps its own pixels, with a black border of :data:`EVENT_BORDER_PX` so
that detectors reach the image's edges (ORB ignores a 31-pixel band along the border), and
:attr:`Frontend.tracked_calibration` / :attr:`Frontend.tracked_from_rect` tell the back-end
and the trajectory writers which camera that is. ``events_geometry = "frame"`` warps the
event images into the frame cameras as above.

Illumination floods (``[fusion] flood_*``): a global lighting change makes every event pixel
fire as the light ramps, so a window holds many times the usual event count, almost all of
one polarity, and its E3CT shows the sensor's threshold pattern instead of scene edges.
:func:`is_flood` flags such a window (one polarity's share at least ``flood_polarity`` and its
count above ``flood_ratio`` × its usual count, half the median of the previous
``flood_history`` windows);
:attr:`FrontendFrame.flood` carries the flag, the run then predicts the pose of that frame
instead of tracking it (``flood_predict``) and :meth:`Frontend.bridge_images` spans the flood.
Leaving a DVS-biased segment across a flood, the flood frames and the first clean frame
whose frames are fine are rendered from the frames alone and tracked
(:meth:`Frontend.across_flood`, ``flood_frames``): the flood spoils the events, not the frames.

Quiet windows (``[fusion] quiet_ratio``, ``quiet_structure``): a camera come to rest leaves its
event cameras only sensor noise, whose E3CT still yields keypoints that stereo-match by chance.
Two tests flag such a window (:meth:`Frontend.quiet`): :func:`is_quiet`, fewer events than
``quiet_ratio`` × the median count of the last ``flood_history`` windows that were not quiet,
and :func:`is_noise`, no structure in either event camera (its firing pixels have firing
neighbours no more often than independent noise would, :func:`dhptam.events.activity`), which
needs no history and holds in the dark, where the noise is a larger share of the events.
:attr:`FrontendFrame.quiet` carries the flag, and the run hands it to the tracker, which holds
the pose of a quiet frame it cannot track instead of starting a new map segment on the noise,
and never initialises a map from a quiet frame's event images.

Depth of the warp plane: ``[fusion] plane_depth_m`` (default 0 = infinity, a rotation-only
homography), or ``plane_depth="auto"``: the median scene depth from StereoSGBM on the first
well-exposed frame pair. Infinity is the default because nothing about the scene is known before tracking
starts, and it is exact for distant scenes; its error for a point at depth z is
``f · b / z`` pixels with ``b`` the event-to-frame camera offset (a few cm on TUM-VIE-like
rigs; :attr:`Frontend.warp_parallax_px` is ``f · b``). The caller can set
:attr:`Frontend.plane_depth_m` at any time (the next frame processed uses it), or split a frame
into :meth:`Frontend.prepare` (frames, E3CT: no depth needed) and :meth:`Frontend.finish`
(warp through a given depth, β, blend). ``dhptam run`` with ``[fusion] warp_depth =
"tracked"`` does the latter with the median depth of the map points the previous frame was
tracked with, rounded by :meth:`Frontend.quantised_depth` so the warp maps are reused.

Two background threads run ``prefetch`` frames ahead through bounded queues, one reading the
files (:meth:`Frontend.read`; HDF5 decompression holds the GIL), one running the kernels (which
release it), so the front-end of frame k+1 overlaps the consumer's tracking of frame k.
Exceptions raised in the threads are re-raised in the consumer; :meth:`Frontend.close` stops
and joins them. ``prefetch=0`` runs everything in the consumer's thread.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from . import _core
from ._config import with_setting
from ._prefetch import prefetched
from .datasets import EventWindow, FramePair, Sequence
from .errors import InputError
from .events import Activity, activity, e3ct, shared_scales
from .fusion import choose_beta, fuse, recover_exposure, warp_and_fuse, warp_to_frame
from .geometry import SE3, RectifiedStereo, StereoRig

MODES = ("fusion", "frames", "events")

#: Black border, in pixels, around the event images of mode ``events`` tracked in the event
#: cameras (``[fusion] events_geometry = "event"``): wider than ORB's 31-pixel patch, so that
#: keypoints can lie anywhere in the event camera's view, as they can when the event image is
#: warped into the middle of a frame camera's.
EVENT_BORDER_PX = 32
_U8 = npt.NDArray[np.uint8]
_F32 = npt.NDArray[np.float32]


class RectifiedCalibration(NamedTuple):
    """Rectified left camera intrinsics and stereo baseline (of the frame cameras, or of the
    event cameras where mode ``events`` tracks in them), in the order of
    ``dhptam.StereoCalibration(fx, fy, cx, cy, baseline_m, width, height)``."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float
    width: int
    height: int


@dataclass(frozen=True)
class E3ctStats:
    """Event statistics of one frame's window (``on_left``/``on_right``: ON events among
    ``events_left``/``events_right``; ``hot_left``/``hot_right``: raw pixels whose events were
    dropped as hot pixels, see ``[events] hot_pixel_ratio``; ``activity``: the pixel activity of
    each camera's raw window, left and right, see :func:`dhptam.events.activity`, or ``None``
    where ``[fusion] quiet_structure = 0``)."""

    window_start_ns: int
    window_end_ns: int
    events_left: int
    events_right: int
    rectified_left: int
    rectified_right: int
    scales: tuple[float, ...]
    on_left: int = 0
    on_right: int = 0
    hot_left: int = 0
    hot_right: int = 0
    activity: tuple[Activity, Activity] | None = None


def is_flood(
    count: int, on_count: int, history: npt.ArrayLike, *, ratio: float = 2.5, polarity: float = 0.8
) -> bool:
    """Whether an event window is an illumination flood (a global lighting change).

    ``count`` events of which ``on_count`` are ON; ``history`` the event counts of the
    previous windows. A flood holds at least a ``polarity`` share of one polarity, and more
    events of that polarity than ``ratio`` times its usual count, half the median of
    ``history``: a lighting ramp moves every pixel's log intensity the same way and adds
    events of one polarity only, while scene motion (even fast, with many events) gives both
    polarities in about equal numbers. Comparing the dominant polarity with its own usual
    count, rather than the whole window with the whole median, keeps the other polarity's
    ordinary events from diluting the burst: the start of a ramp, 2.3 × the median count with
    82 % OFF events on the TUM-VIE-size HDR sequence, is a flood (3.8 × the usual OFF count).
    ``ratio = 0`` or an empty history: never.

    >>> is_flood(480_000, 2_000, [30_000] * 10)
    True
    >>> is_flood(300_000, 150_000, [30_000] * 10)  # fast motion: both polarities
    False
    """
    counts = np.asarray(history, np.float64)
    if ratio <= 0.0 or counts.size == 0 or count <= 0:
        return False
    dominant = max(on_count, count - on_count)
    usual = 0.5 * float(np.median(counts))
    return bool(dominant > ratio * usual and dominant >= polarity * count)


def is_quiet(count: int, usual: npt.ArrayLike, *, ratio: float = 0.03) -> bool:
    """Whether an event window of ``count`` events is quiet: fewer than ``ratio`` times the
    median of ``usual``, the event counts of recent windows that were not quiet. A camera at
    rest leaves its event cameras only sensor noise, a small fraction of the count while it
    moves (up to 3 % on the simulator in normal light, 6 % in a dark room); a camera turning
    back keeps about 4 %, which must not count as rest. A window without a single event is
    missing data (a covered lens, a gap in the stream), not a camera at rest, whose sensor
    keeps firing its noise: never quiet. ``ratio = 0`` or no ``usual`` counts: never.

    >>> is_quiet(450, [60_000, 52_000, 41_000])
    True
    >>> is_quiet(2_400, [60_000, 52_000, 41_000])  # turning back: slow, but moving
    False
    """
    counts = np.asarray(usual, np.float64)
    if ratio <= 0.0 or counts.size == 0 or count <= 0:
        return False
    return bool(count < ratio * float(np.median(counts)))


# Above this share of firing pixels a window is busy, never noise: the structure test loses its
# meaning as chance support nears one (at rest the simulator's noise fired 4 % at most).
_NOISE_MAX_ACTIVE = 0.1


def is_noise(activities: tuple[Activity, ...], *, share: float = 0.0025) -> bool:
    """Whether every event camera's window (``activities``, :func:`dhptam.events.activity`)
    shows sensor noise and no scene structure: pixels supported beyond chance
    (:attr:`~dhptam.events.Activity.structured_share`) under ``share`` of the sensor, and
    under 10 % of its pixels active. Noise pixels fire independently, so at rest the share
    stays near zero whatever the noise rate; a moving camera's events line up along edges.
    An empty window is missing data, not noise (see :func:`is_quiet`); ``share = 0`` or no
    windows: never.

    >>> from dhptam.events import Activity
    >>> is_noise((Activity(57_600, 450, 60), Activity(57_600, 440, 55)))
    True
    >>> is_noise((Activity(57_600, 900, 700), Activity(57_600, 450, 60)))  # one sees edges
    False
    """
    if share <= 0.0 or not activities:
        return False
    return all(
        a.active > 0 and a.active_share < _NOISE_MAX_ACTIVE and a.structured_share < share for a in activities
    )


@dataclass(frozen=True)
class FrontendFrame:
    """One processed stereo frame.

    ``left``/``right`` are what the features run on: uint8 ``(H, W)`` images in the rectified
    frame cameras (fused, frames or events according to the mode), or in mode ``events``
    tracked in the event cameras, in those (:attr:`Frontend.tracked_calibration`).
    ``frame_left``/``frame_right`` are the rectified frames alone and ``events_left``/
    ``events_right`` the normalised E3CT in the images' camera (warped into the frame cameras,
    or bordered in the event cameras), ``(H, W, C)`` float32 in [0, 1] (``None`` in mode
    ``frames``), for comparisons and visualisation. ``bias`` is the left camera's β mode
    (``aps``, ``dvs``, ``frames``, ``events``). ``flood``: the event window is an
    illumination flood (:func:`is_flood`; always ``False`` in mode ``frames``). ``quiet``:
    the event window is quiet, the camera likely at rest (:meth:`Frontend.quiet`; always
    ``False`` in mode ``frames``).
    ``warp_depth_m``: depth in metres of the plane the events were warped through (0:
    infinity; 0 in mode ``frames`` and where nothing is warped). ``stretched``: whether the
    left/right frame failed the exposure test and was stretched to full contrast
    (:func:`dhptam.fusion.recover_exposure`; ``frame_left``/``frame_right`` are then the
    stretched frames).
    """

    index: int
    t_ns: int
    left: _U8
    right: _U8
    beta_left: float
    beta_right: float
    bias: str
    bias_right: str
    e3ct_stats: E3ctStats | None
    frame_left: _U8
    frame_right: _U8
    events_left: _F32 | None
    events_right: _F32 | None
    flood: bool = False
    warp_depth_m: float = 0.0
    stretched: tuple[bool, bool] = (False, False)
    quiet: bool = False


@dataclass(frozen=True)
class PreparedFrame:
    """A frame before its event warp (:meth:`Frontend.prepare`): the rectified frames
    ``(left, right)`` and, outside mode ``frames``, the raw E3CTs ``(left, right)`` of its
    window in the rectified event cameras with the window's statistics."""

    index: int
    t_ns: int
    frames: tuple[_U8, _U8]
    tensors: tuple[_F32, _F32] | None
    stats: E3ctStats | None


@dataclass(frozen=True)
class RawFrame:
    """What :meth:`Frontend.read` takes from the sequence for frame ``index``: the stereo
    frames as decoded (before rectification) and, outside mode ``frames``, the raw event
    windows ``(left, right)`` of its window ``[t0_ns, t1_ns)``."""

    index: int
    pair: FramePair
    window_ns: tuple[int, int]
    events: tuple[EventWindow, EventWindow] | None


@dataclass(frozen=True)
class BridgeImages:
    """The raw data of one frame blended with its neighbour's β, at a fusion-mode switch.

    When the β mode of frame k differs from frame k−1's (``aps`` ↔ ``dvs``), the frame whose
    raw frame is usable (the APS-biased one: k−1 when entering a dark or saturated segment, k
    when leaving it) is blended again with the other frame's β, its frame first given the
    other frame's exposure (mean and contrast), so that the tracker can see
    the same instant both ways and insert a bridge keyframe (``dhptam.System.bridge``).
    ``index``/``t_ns`` name that frame; ``bias`` and ``beta_left``/``beta_right`` are the
    mode and β of this blend (the neighbour's); ``warp_depth_m`` the depth of the plane its
    events were warped through (0: infinity).
    """

    index: int
    t_ns: int
    left: _U8
    right: _U8
    bias: str
    beta_left: float
    beta_right: float
    warp_depth_m: float = 0.0


def _exposed_like(frame: _U8, like: _U8) -> _U8:
    """``frame`` with the mean and contrast (standard deviation) of ``like``.

    A bridge re-renders the frame with usable raw data in the neighbouring DVS-biased mode;
    the neighbour's own frame is dark or saturated, so in its blend the frame part is nearly
    flat. Giving the bridge's frame the neighbour's exposure statistics makes the bridge look
    like the neighbour (events on a nearly flat background) instead of carrying texture the
    neighbour cannot show.
    """
    f = frame.astype(np.float32)
    g = like.astype(np.float32)
    out = float(g.mean()) + (f - float(f.mean())) * (float(g.std()) / max(float(f.std()), 1e-3))
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _with_mode(config: _core.Config, mode: str) -> _core.Config:
    """``config`` with ``[fusion] mode`` replaced."""
    return with_setting(config, "fusion", "mode", mode)


class Frontend:
    """Iterates :class:`FrontendFrame` over a :class:`~dhptam.datasets.Sequence`.

    Parameters
    ----------
    sequence
        A loaded sequence (``load_tumvie``); it must stay open while iterating.
    mode
        ``fusion``, ``frames`` or ``events`` (see the module docstring).
    config
        Supplies ``[rectification]``, ``[events]`` and ``[fusion]``; defaults otherwise.
        ``mode`` overrides ``[fusion] mode``.
    prefetch
        Frames computed ahead in a background thread (0: none, synchronous).
    feature_counter
        Optional ``f(rectified_frame) -> int`` giving the feature yield of a frame, fed to β
        (fewer than ``[fusion] min_features`` switches to the DVS bias). Without it β uses the
        exposure statistics only.
    plane_depth
        Depth in metres of the warp plane, ``"auto"`` for the median scene depth measured by
        StereoSGBM on the first well-exposed frame pair of the range (see
        :meth:`median_scene_depth`), or ``None`` for ``[fusion] plane_depth_m`` (0: infinity).
    start, stop
        Frame index range ``[start, stop)`` to iterate (default: all).
    """

    def __init__(
        self,
        sequence: Sequence,
        mode: str = "fusion",
        config: _core.Config | None = None,
        prefetch: int = 2,
        *,
        feature_counter: Callable[[_U8], int] | None = None,
        plane_depth: float | str | None = None,
        start: int = 0,
        stop: int | None = None,
    ) -> None:
        if mode not in MODES:
            raise InputError(f"mode must be one of {', '.join(MODES)}, got {mode!r}", field="mode")
        if prefetch < 0:
            raise InputError(f"prefetch must be >= 0, got {prefetch}", field="prefetch")
        self.sequence = sequence
        self.mode = mode
        self.config = _with_mode(config or _core.Config(), mode)
        self.prefetch = int(prefetch)
        self.feature_counter = feature_counter
        n = len(sequence.frames)
        self.start = int(start)
        self.stop = n if stop is None else min(int(stop), n)
        if not 0 <= self.start <= self.stop:
            raise InputError(f"frame range [{start}, {stop}) is not inside [0, {n})", field="start")
        settings = self.config.to_dict()
        self._events_cfg: dict[str, Any] = settings["events"]
        fusion_cfg = settings["fusion"]
        self.plane_depth_m: float = float(fusion_cfg["plane_depth_m"])
        self.bridge_enabled: bool = bool(fusion_cfg["bridge"])
        self.flood_ratio: float = float(fusion_cfg["flood_ratio"])
        self.flood_polarity: float = float(fusion_cfg["flood_polarity"])
        self.flood_history: int = int(fusion_cfg["flood_history"])
        self.flood_predict: bool = bool(fusion_cfg["flood_predict"])
        self.flood_frames: bool = bool(fusion_cfg["flood_frames"])
        self.quiet_ratio: float = float(fusion_cfg["quiet_ratio"])
        self.quiet_structure: float = float(fusion_cfg["quiet_structure"])
        self.min_features: int = int(fusion_cfg["min_features"])
        self.warp_depth: str = str(fusion_cfg["warp_depth"])
        self.warp_depth_step_px: float = float(fusion_cfg["warp_depth_step_px"])
        self.event_disparity_enabled: bool = bool(fusion_cfg["event_disparity"])
        self.event_stereo_reading: str = str(fusion_cfg["event_stereo"])
        self.event_viewpoint_enabled: bool = bool(fusion_cfg["event_viewpoint"])
        self.events_geometry: str = str(fusion_cfg["events_geometry"])
        #: Whether the event images are tracked in the rectified event cameras themselves
        #: (mode ``events`` with ``[fusion] events_geometry = "event"``, or ``"auto"`` on a
        #: rig whose event cameras are not its frame cameras): no warp, no β. Set below.
        self.tracks_event_cameras = False
        self._event_stereo: dict[float, _core.EventStereo] = {}
        # Event counts (left + right) of the windows seen, by frame index (flood reference).
        self._window_counts: dict[int, int] = {}
        # The quiet test's state: the counts of the last windows that were not quiet, and the
        # index of the last window tested.
        self._usual_counts: list[int] = []
        self._quiet_index: int | None = None
        self.align_px: tuple[float, float] = (
            float(fusion_cfg["align_px"][0]),
            float(fusion_cfg["align_px"][1]),
        )

        calib = sequence.calibration
        cams = calib.cameras
        self.frame_rect = RectifiedStereo(
            StereoRig(
                cams["frame_left"], cams["frame_right"], calib.cam_from_cam("frame_right", "frame_left")
            ),
            self.config,
        )
        self._maps = {side: self.frame_rect.remap_tables(side) for side in ("left", "right")}
        self.t_f_ns = np.asarray(sequence.frames.t_mid_ns, np.int64)
        if np.any(np.diff(self.t_f_ns) <= 0):
            k = int(np.argmax(np.diff(self.t_f_ns) <= 0)) + 1
            raise InputError(
                f"fusion times must increase; frame {k} is not after frame {k - 1}", field="frames"
            )
        self._hot: dict[str, _core.HotPixels] = {}
        if mode != "frames":
            self.event_rect = RectifiedStereo(
                StereoRig(
                    cams["event_left"], cams["event_right"], calib.cam_from_cam("event_right", "event_left")
                ),
                self.config,
            )
            self._rectifiers = {
                side: _core.EventRectifier(self.event_rect, side) for side in ("left", "right")
            }
            # Hot pixels (firing on their own) found as the windows come and masked in the
            # rectification tables, so that their events reach no representation.
            ev = self._events_cfg
            self._hot = {
                side: _core.HotPixels(
                    cams[f"event_{side}"].width,
                    cams[f"event_{side}"].height,
                    ratio=ev["hot_pixel_ratio"],
                    min_rate_hz=ev["hot_pixel_min_rate_hz"],
                    time_constant_s=ev["hot_pixel_time_s"],
                )
                for side in ("left", "right")
                if ev["hot_pixel_ratio"] > 0.0
            }
            # Rectified frame camera ← rectified event camera, per side:
            # rect_f ← f (rectifying rotation) ← e (rig extrinsics) ← rect_e (inverse rotation).
            self.frame_from_event = {
                side: SE3(self._rect_rotation(self.frame_rect, side))
                @ calib.cam_from_cam(f"frame_{side}", f"event_{side}")
                @ SE3(self._rect_rotation(self.event_rect, side)).inverse()
                for side in ("left", "right")
            }
            if mode == "events" and self.events_geometry != "frame":
                self.tracks_event_cameras = self.events_geometry == "event" or not self.shares_frame_pixels
        if plane_depth == "auto":
            if mode != "frames":
                self.plane_depth_m = self.median_scene_depth()
        elif plane_depth is not None:
            if isinstance(plane_depth, str) or not float(plane_depth) >= 0.0:
                raise InputError(
                    'plane_depth must be a depth in metres (>= 0, 0: infinity), "auto" or None, '
                    f"got {plane_depth!r}",
                    field="plane_depth",
                )
            self.plane_depth_m = float(plane_depth)
        self._prefetch: Generator[Any, None, None] | None = None

    @staticmethod
    def _rect_rotation(rect: RectifiedStereo, side: str) -> _core.SO3:
        return rect.rect_left_from_left if side == "left" else rect.rect_right_from_right

    # -- geometry the back-end needs ------------------------------------------------------------

    @property
    def calibration(self) -> RectifiedCalibration:
        """Rectified left frame camera intrinsics and baseline (what the SLAM back-end takes)."""
        k = self.frame_rect.K
        return RectifiedCalibration(
            float(k[0, 0]),
            float(k[1, 1]),
            float(k[0, 2]),
            float(k[1, 2]),
            float(self.frame_rect.baseline_m),
            int(self.frame_rect.width),
            int(self.frame_rect.height),
        )

    @property
    def shares_frame_pixels(self) -> bool:
        """Whether the rectified event cameras are the rectified frame cameras (same pose,
        intrinsics and size on both sides, as on a DAVIS sensor): warping the events into the
        frame cameras is then the identity. ``False`` in mode ``frames``."""
        if self.mode == "frames":
            return False
        same_pose = all(
            float(np.linalg.norm(self.frame_from_event[side].translation)) < 1e-6
            and float(self.frame_from_event[side].rotation.angle()) < 1e-6
            for side in ("left", "right")
        )
        return (
            same_pose
            and (self.event_rect.width, self.event_rect.height)
            == (self.frame_rect.width, self.frame_rect.height)
            and bool(np.allclose(self.event_rect.K, self.frame_rect.K, rtol=0.0, atol=1e-6))
        )

    @property
    def warps_events(self) -> bool:
        """Whether the event images are warped into the frame cameras (modes ``fusion`` and,
        with ``[fusion] events_geometry = "frame"``, ``events``)."""
        return self.mode != "frames" and not self.tracks_event_cameras

    @property
    def tracked_calibration(self) -> RectifiedCalibration:
        """The rectified camera the images of :class:`FrontendFrame` are in (what the SLAM
        back-end takes): :attr:`calibration`, except in mode ``events`` tracked in the event
        cameras, where it is the rectified left event camera with the principal point and size
        grown by the border of :data:`EVENT_BORDER_PX`, and the event cameras' baseline."""
        if not self.tracks_event_cameras:
            return self.calibration
        k, pad = self.event_rect.K, EVENT_BORDER_PX
        return RectifiedCalibration(
            float(k[0, 0]),
            float(k[1, 1]),
            float(k[0, 2]) + pad,
            float(k[1, 2]) + pad,
            float(self.event_rect.baseline_m),
            int(self.event_rect.width) + 2 * pad,
            int(self.event_rect.height) + 2 * pad,
        )

    @property
    def tracked_from_rect(self) -> SE3:
        """Tracked camera ← rectified left frame camera: the identity, except in mode
        ``events`` tracked in the event cameras (the rectified left event camera ← the
        rectified left frame camera). The back-end's ``world_from_tracked`` poses give the
        rectified frame camera as ``world_from_tracked @ tracked_from_rect``; the world frame
        stays the first keyframe's tracked camera."""
        if not self.tracks_event_cameras:
            return SE3()
        return self.frame_from_event["left"].inverse()

    @property
    def rect_from_cam(self) -> SE3:
        """Rectified left frame camera ← left frame camera (a pure rotation). A trajectory of
        the rectified camera maps back with ``world_from_cam = world_from_rect @ rect_from_cam``."""
        return SE3(self.frame_rect.rect_left_from_left)

    def median_scene_depth(self, max_tries: int = 10) -> float:
        """Median depth (m) of the scene seen by the rectified left frame camera: StereoSGBM on
        the first APS-biased (well-exposed) frame pair among the first ``max_tries`` of the
        range; 0 (infinity) when none has enough valid disparities."""
        from .depth import sgbm

        # Exposure test of the fusion mode whatever this front-end's mode: in mode "events"
        # choose_beta would answer "events" for every frame and no depth would ever be measured.
        exposure_config = _with_mode(self.config, "fusion")
        for k in range(self.start, min(self.stop, self.start + max_tries)):
            pair = self.sequence.frames[k]
            left, right = self._rectify_frame(pair.left, "left"), self._rectify_frame(pair.right, "right")
            if choose_beta(left, None, exposure_config).bias != "aps":
                continue
            inverse = sgbm(left, right, self.calibration)
            valid = inverse[np.isfinite(inverse)]
            if valid.size > 0.1 * inverse.size:
                return float(1.0 / np.median(valid))
        return 0.0

    def camera_poses(self, world_from_tracked: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """``world_from_cam`` (N, 4, 4) of the left frame camera from the tracker's
        ``world_from_tracked`` (N, 4, 4) poses of the tracked camera (the rectified left frame
        camera, or the rectified left event camera: :attr:`tracked_from_rect`)."""
        poses = np.asarray(world_from_tracked, np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise InputError(
                f"world_from_tracked must be (N, 4, 4), got {poses.shape}", field="world_from_tracked"
            )
        return poses @ (self.tracked_from_rect @ self.rect_from_cam).matrix()

    def __len__(self) -> int:
        return self.stop - self.start

    def warp_event_pixels(
        self,
        side: str,
        pixels: npt.ArrayLike,
        depth_m: float | None = None,
        align_px: tuple[float, float] | None = None,
    ) -> npt.NDArray[np.float64]:
        """Rectified frame-camera pixels ``(N, 2)`` of rectified event-camera ``pixels``
        through the front-end's warp (plane at ``depth_m``, default :attr:`plane_depth_m`;
        ``align_px`` default the configured δP_align); NaN behind the camera."""
        if self.mode == "frames":
            raise InputError("mode 'frames' has no event cameras set up", field="mode")
        if side not in ("left", "right"):
            raise InputError(f'side must be "left" or "right", got {side!r}', field="side")
        ke, kf = self.event_rect.K, self.frame_rect.K
        _, out = warp_to_frame(
            np.zeros((1, 1, 1), np.float32),
            [ke[0, 0], ke[1, 1], ke[0, 2], ke[1, 2]],
            [kf[0, 0], kf[1, 1], kf[0, 2], kf[1, 2]],
            self.frame_from_event[side],
            width=1,
            height=1,
            depth_m=self.plane_depth_m if depth_m is None else float(depth_m),
            align_px=self.align_px if align_px is None else align_px,
            pixels=np.asarray(pixels, np.float64).reshape(-1, 2),
        )
        assert out is not None
        return out

    # -- one frame ---------------------------------------------------------------------------

    def window_ns(self, index: int) -> tuple[int, int]:
        """Event window ``[t_f^(k-1), t_f^k)`` of frame ``index`` (frame 0: as long as the next)."""
        t1 = int(self.t_f_ns[index])
        if index > 0:
            return int(self.t_f_ns[index - 1]), t1
        if len(self.t_f_ns) < 2:
            raise InputError("a one-frame sequence has no window length for its events", field="frames")
        return t1 - int(self.t_f_ns[1] - self.t_f_ns[0]), t1

    def _rectify_frame(self, image: _U8, side: str) -> _U8:
        import cv2

        map_x, map_y = self._maps[side]
        return np.asarray(
            cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT), np.uint8
        )

    def _rectified_events(self, side: str, t0: int, t1: int) -> tuple[EventWindow, int]:
        window, count, _ = self._rectified_events_counted(side, t0, t1)
        return window, count

    def _rectified_events_counted(
        self, side: str, t0: int, t1: int, raw: EventWindow | None = None
    ) -> tuple[EventWindow, int, int]:
        """The rectified window, its raw event count and its raw ON-event count (``raw``: the
        window already read, else it is read here). The window first updates the camera's
        hot-pixel detector, and the events of its hot pixels are dropped."""
        if raw is None:
            raw = self.sequence.events[side].window(t0, t1)
        hot = self._hot.get(side)
        if hot is not None and hot.update(raw.x, raw.y, (t1 - t0) * 1e-9):
            self._rectifiers[side].set_masked(hot.pixels())
        x, y, t, p = self._rectifiers[side].apply(raw.x, raw.y, raw.t_ns, raw.p, t0, t1)
        return EventWindow(x=x, y=y, t_ns=t, p=p), len(raw), int(np.count_nonzero(raw.p))

    def _window_count(self, index: int) -> int:
        """Raw events (left + right) in the window of frame ``index``, read once."""
        count = self._window_counts.get(index)
        if count is None:
            t0, t1 = self.window_ns(index)
            count = sum(len(self.sequence.events[side].window(t0, t1)) for side in ("left", "right"))
            self._window_counts[index] = count
        return count

    def flood(self, index: int, stats: E3ctStats) -> bool:
        """Whether frame ``index``'s window (``stats``) is an illumination flood, against the
        previous ``[fusion] flood_history`` windows (:func:`is_flood`; frame 0 never is)."""
        count = stats.events_left + stats.events_right
        self._window_counts[index] = count
        # Bounded memory on long runs: keep the counts a later window can still ask for.
        for old in [k for k in self._window_counts if k < index - 2 * self.flood_history]:
            del self._window_counts[old]
        if self.flood_ratio <= 0.0:
            return False
        history = [self._window_count(k) for k in range(max(0, index - self.flood_history), index)]
        return is_flood(
            count,
            stats.on_left + stats.on_right,
            history,
            ratio=self.flood_ratio,
            polarity=self.flood_polarity,
        )

    def quiet(self, index: int, stats: E3ctStats) -> bool:
        """Whether frame ``index``'s window (``stats``) is quiet: by its count against the last
        ``flood_history`` windows that were not (:func:`is_quiet`, ``[fusion] quiet_ratio``),
        or by the lack of structure in both event cameras (:func:`is_noise`, ``[fusion]
        quiet_structure``), which needs no history. Windows are meant to come in order; when
        ``index`` does not follow the last window tested (the first one, or a jump), the
        usual count restarts from the windows just before it, all taken as moving. Empty
        windows (no data) are never quiet and stay out of the usual count."""
        if self.quiet_ratio <= 0.0 and self.quiet_structure <= 0.0:
            return False
        if self._quiet_index is None or index != self._quiet_index + 1:
            first = max(0, index - self.flood_history)
            self._usual_counts = [c for k in range(first, index) if (c := self._window_count(k)) > 0]
        count = stats.events_left + stats.events_right
        quiet = is_quiet(count, self._usual_counts, ratio=self.quiet_ratio) or (
            stats.activity is not None and is_noise(stats.activity, share=self.quiet_structure)
        )
        if not quiet and count > 0:
            self._usual_counts = [*self._usual_counts, count][-self.flood_history :]
        self._quiet_index = index
        return quiet

    def _event_tensors(
        self, t0: int, t1: int, raw: tuple[EventWindow, EventWindow] | None = None
    ) -> tuple[list[_F32], E3ctStats]:
        """The raw E3CT of each event camera (left, right) for ``[t0, t1)`` and the window's
        statistics (its shared normalisation scales included); ``raw``: the windows already
        read (left, right), else they are read here."""
        cfg = self._events_cfg
        w, h = int(self.event_rect.width), int(self.event_rect.height)
        raw_counts: dict[str, int] = {}
        on_counts: dict[str, int] = {}
        tensors = []
        rect_counts: dict[str, int] = {}
        activities: list[Activity] = []
        for k, side in enumerate(("left", "right")):
            raw_window = self.sequence.events[side].window(t0, t1) if raw is None else raw[k]
            if self.quiet_structure > 0.0:
                # On the sensor's own pixels, whose neighbours are those noise is independent of.
                cam = self.sequence.calibration.cameras[f"event_{side}"]
                activities.append(activity(raw_window.x, raw_window.y, width=cam.width, height=cam.height))
            window, raw_counts[side], on_counts[side] = self._rectified_events_counted(
                side, t0, t1, raw_window
            )
            rect_counts[side] = len(window)
            tensors.append(
                e3ct(
                    window.x,
                    window.y,
                    window.t_ns,
                    window.p,
                    width=w,
                    height=h,
                    t_start_ns=t0,
                    t_end_ns=t1,
                    alpha=cfg["alpha"],
                    eta_ms=cfg["eta_ms"],
                    channels=cfg["channels"],
                    polarity=cfg["polarity"],
                )
            )
        scales = shared_scales(*tensors, percentile=cfg["normalise_percentile"])
        stats = E3ctStats(
            window_start_ns=t0,
            window_end_ns=t1,
            events_left=raw_counts["left"],
            events_right=raw_counts["right"],
            rectified_left=rect_counts["left"],
            rectified_right=rect_counts["right"],
            scales=tuple(float(s) for s in scales),
            on_left=on_counts["left"],
            on_right=on_counts["right"],
            hot_left=self._rectifiers["left"].masked_count,
            hot_right=self._rectifiers["right"].masked_count,
            activity=(activities[0], activities[1]) if activities else None,
        )
        return tensors, stats

    def _warp_tensors(
        self,
        tensors: list[_F32],
        scales: tuple[float, ...],
        depth_m: float,
        frames: dict[str, _U8],
        betas: dict[str, tuple[str, float]],
    ) -> tuple[dict[str, _F32], dict[str, _U8]]:
        """The raw E3CTs (left, right) normalised with ``scales`` inside the warp (tap by tap,
        the same values as normalise() then warp), warped through the plane at ``depth_m``, and
        their blend with ``frames`` at ``betas`` done in the same pass. Tracked in the event
        cameras (:attr:`tracks_event_cameras`), the same pass copies each normalised E3CT
        into the middle of a black image :data:`EVENT_BORDER_PX` wider on every side (the
        identity map: every tap on a pixel centre), β = 1."""
        k_event = self.event_rect.K
        ke = [k_event[0, 0], k_event[1, 1], k_event[0, 2], k_event[1, 2]]
        if self.tracks_event_cameras:
            calib = self.tracked_calibration
            kf = [calib.fx, calib.fy, calib.cx, calib.cy]
            blank = np.zeros((calib.height, calib.width), np.uint8)
            targets = {"left": blank, "right": blank}
            frame_from_event = {"left": SE3(), "right": SE3()}
            depth_m, align_px = 0.0, (0.0, 0.0)
        else:
            k_frame = self.frame_rect.K
            kf = [k_frame[0, 0], k_frame[1, 1], k_frame[0, 2], k_frame[1, 2]]
            targets, frame_from_event, align_px = frames, self.frame_from_event, self.align_px
        out: dict[str, _F32] = {}
        fused: dict[str, _U8] = {}
        for side, tensor in zip(("left", "right"), tensors, strict=True):
            # fuse() takes the per-pixel largest channel as the event intensity D.
            out[side], fused[side] = warp_and_fuse(
                tensor,
                ke,
                kf,
                frame_from_event[side],
                targets[side],
                betas[side][1],
                depth_m=depth_m,
                align_px=align_px,
                scales=scales,
            )
        return out, fused

    # -- warp depth from the tracker (``[fusion] warp_depth``) ---------------------------------

    @property
    def warp_parallax_px(self) -> float:
        """Parallax in frame pixels per unit of inverse depth (px · m) between the rectified
        event and frame cameras: ``f_frame · |t_xy|`` of the larger of the two sides' offsets.
        A point at depth z warped through infinity lands ``warp_parallax_px / z`` pixels from
        where the frame camera sees it (0 in mode ``frames``)."""
        if self.mode == "frames":
            return 0.0
        f = float(self.frame_rect.K[0, 0])
        return max(
            f * float(np.linalg.norm(self.frame_from_event[side].translation[:2]))
            for side in ("left", "right")
        )

    def event_disparity(self, depth_m: float = 0.0) -> tuple[float, float]:
        """``(scale, offset_px)`` that map the stereo disparity ``d`` of the event images
        warped into the frame cameras through the plane at ``depth_m`` (0: infinity) to the
        frame cameras' disparity ``scale · d + offset_px`` (``System.track``'s
        ``disparity``). The identity when the event cameras themselves are tracked
        (:attr:`tracks_event_cameras`).

        A warped event pair keeps the event cameras' parallax: a point at depth ``Z`` shows
        ``f b_e / Z − f (b_e − b_f) / D`` through the plane at ``D``, with ``b_e`` and
        ``b_f`` the event and frame baselines along the rectified rows (the event cameras'
        centres in the rectified frame cameras) and ``f`` the frame focal length. Hence
        ``scale = b_f / b_e`` and ``offset_px = scale · f (b_e − b_f) / D``. Identity in mode
        ``frames``, with ``[fusion] event_disparity = false``, or when the event cameras
        share the frame cameras' centres."""
        if not self.warps_events or not self.event_disparity_enabled:
            return (1.0, 0.0)
        b_f = float(self.frame_rect.baseline_m)
        left = np.asarray(self.frame_from_event["left"].translation, np.float64)
        right = np.asarray(self.frame_from_event["right"].translation, np.float64)
        b_e = float(right[0] + b_f - left[0])
        if not (b_e > 0.0 and b_f > 0.0) or abs(b_e - b_f) <= 1e-9 * b_f:
            return (1.0, 0.0)
        scale = b_f / b_e
        depth = float(depth_m)
        offset = scale * float(self.frame_rect.K[0, 0]) * (b_e - b_f) / depth if depth > 0.0 else 0.0
        return (scale, offset)

    def event_viewpoint(self, depth_m: float = 0.0) -> tuple[float, float, float]:
        """The viewpoint (``System.track``'s ``viewpoint``) of the event images warped into
        the frame cameras through the plane at ``depth_m`` (0: infinity): the rectified left
        event camera's centre in the rectified left frame camera's axes, metres. Through the
        plane at infinity a warped event image is exactly the event cameras' view with the
        frame cameras' orientation. Zero (the frame cameras' own view) through a plane at
        finite depth, without ``[fusion] event_viewpoint`` or ``event_disparity``, with
        ``event_stereo = "exact"`` (which moves the keypoints itself), in mode ``frames`` and
        when the event cameras themselves are tracked."""
        if (
            not self.warps_events
            or not self.event_viewpoint_enabled
            or not self.event_disparity_enabled
            or self.event_stereo_reading == "exact"
            or float(depth_m) > 0.0
        ):
            return (0.0, 0.0, 0.0)
        c = np.asarray(self.frame_from_event["left"].translation, np.float64)
        return (float(c[0]), float(c[1]), float(c[2]))

    def event_stereo(self, depth_m: float = 0.0) -> _core.EventStereo | None:
        """The :class:`dhptam._core.EventStereo` that reads the stereo matches of the event
        images warped through the plane at ``depth_m`` (0: infinity) as the frame cameras
        would have measured them (``System.track``'s ``event_stereo``): both pixels unwarped
        into the rectified event cameras, triangulated with the event pair, projected into
        the rectified frame cameras. ``None`` in mode ``frames``, with ``[fusion]
        event_disparity = false`` or ``event_stereo = "disparity"`` (then
        :meth:`event_disparity` applies), and when the event cameras themselves are tracked.
        Built once per depth."""
        if not self.warps_events or not self.event_disparity_enabled or self.event_stereo_reading != "exact":
            return None
        depth = float(depth_m)
        reading = self._event_stereo.get(depth)
        if reading is None:
            ke, kf = self.event_rect.K, self.frame_rect.K
            reading = _core.EventStereo(
                [ke[0, 0], ke[1, 1], ke[0, 2], ke[1, 2]],
                float(self.event_rect.baseline_m),
                [kf[0, 0], kf[1, 1], kf[0, 2], kf[1, 2]],
                float(self.frame_rect.baseline_m),
                self.frame_from_event["left"],
                self.frame_from_event["right"],
                depth,
                self.align_px,
            )
            self._event_stereo[depth] = reading
        return reading

    def quantised_depth(self, depth_m: float | None, current: float | None = None) -> float:
        """``depth_m`` rounded to the inverse-depth bins of ``[fusion] warp_depth_step_px``
        (bin width ``step_px / warp_parallax_px`` in 1/m), so consecutive frames share a warp
        map while the scene depth drifts; ``None``, 0 or a non-finite depth give the
        configured ``plane_depth_m``. Depths beyond ``2 · warp_parallax_px / step_px`` metres
        round to bin 0: infinity (their parallax is under half a bin).

        With ``current`` (the depth the previous frame was warped through, > 0) the warp
        keeps ``current`` while ``depth_m``'s parallax is within one bin of it: a tracked
        depth wavering at a bin edge does not make the event image jump back and forth."""
        if depth_m is None or not np.isfinite(depth_m) or depth_m <= 0.0:
            return self.plane_depth_m
        parallax = self.warp_parallax_px
        if self.warp_depth_step_px <= 0.0 or parallax <= 0.0:
            return float(depth_m)
        if (
            current is not None
            and current > 0.0
            and abs(parallax / depth_m - parallax / current) <= self.warp_depth_step_px
        ):
            return float(current)
        step = self.warp_depth_step_px / parallax  # inverse-depth bin width, 1/m
        bins = round((1.0 / depth_m) / step)
        return 0.0 if bins == 0 else float(1.0 / (bins * step))

    # -- one frame ------------------------------------------------------------------------------

    def read(self, index: int) -> RawFrame:
        """Frame ``index``'s input as stored: the decoded stereo frames and, outside mode
        ``frames``, both raw event windows. Only this step touches the sequence's files (HDF5
        decompression holds the GIL), so ``dhptam run`` runs it on a thread of its own, ahead
        of :meth:`prepare`, whose kernels release the GIL. One thread at a time may read."""
        pair = self.sequence.frames[index]
        window = self.window_ns(index)
        if self.mode == "frames":
            return RawFrame(index, pair, window, None)
        left, right = (self.sequence.events[side].window(*window) for side in ("left", "right"))
        if index == self.start and self.flood_ratio > 0.0:
            # The flood test of the first frames compares with windows before the first frame:
            # counted here, on the reading thread, so that no other thread reads the files.
            for k in range(max(0, index - self.flood_history), index):
                self._window_count(k)
        return RawFrame(index, pair, window, (left, right))

    def prepare(self, index: int | RawFrame) -> PreparedFrame:
        """The part of :meth:`process` that does not depend on the warp depth: the rectified
        frames and, outside mode ``frames``, the raw E3CTs of frame ``index``'s window
        (``index`` may be what :meth:`read` returned for it). :meth:`finish` completes it;
        ``process(k) == finish(prepare(k)) == finish(prepare(read(k)))``."""
        raw = index if isinstance(index, RawFrame) else self.read(int(index))
        k, pair = raw.index, raw.pair
        frames = (self._rectify_frame(pair.left, "left"), self._rectify_frame(pair.right, "right"))
        if self.mode == "frames" or raw.events is None:
            return PreparedFrame(k, int(self.t_f_ns[k]), frames, None, None)
        tensors, stats = self._event_tensors(*raw.window_ns, raw.events)
        return PreparedFrame(k, int(self.t_f_ns[k]), frames, (tensors[0], tensors[1]), stats)

    def finish(self, prepared: PreparedFrame, depth_m: float | None = None) -> FrontendFrame:
        """Warps ``prepared``'s events through the plane at ``depth_m`` (default
        :attr:`plane_depth_m`; 0: infinity), chooses β and blends (see :meth:`process`)."""
        index, t_ns = prepared.index, prepared.t_ns
        frames = {"left": prepared.frames[0], "right": prepared.frames[1]}
        stretched = (False, False)
        if self.mode != "events":
            # Failed frames with a good signal get their contrast back before β and features.
            recovered = [recover_exposure(frames[side], self.config) for side in ("left", "right")]
            frames = {"left": recovered[0].image, "right": recovered[1].image}
            stretched = (recovered[0].stretched, recovered[1].stretched)
        if prepared.tensors is None or prepared.stats is None:
            return FrontendFrame(
                index, t_ns, frames["left"], frames["right"], 0.0, 0.0, "frames", "frames", None,
                frames["left"], frames["right"], None, None, stretched=stretched,
            )  # fmt: skip
        depth = self.plane_depth_m if depth_m is None else float(depth_m)
        if not (np.isfinite(depth) and depth >= 0.0):
            raise InputError(f"depth_m must be >= 0 (0: infinity), got {depth_m!r}", field="depth_m")
        if self.tracks_event_cameras:
            depth = 0.0  # nothing is warped
        stats = prepared.stats
        betas: dict[str, tuple[str, float]] = {}
        for side in ("left", "right"):
            if self.mode == "events":
                betas[side] = ("events", 1.0)
            else:
                count = None if self.feature_counter is None else int(self.feature_counter(frames[side]))
                d = choose_beta(frames[side], count, self.config)
                betas[side] = (d.bias, d.beta)
        # β depends on the frame only, so the blend happens inside the warp (warp_and_fuse).
        events, images = self._warp_tensors(list(prepared.tensors), stats.scales, depth, frames, betas)
        return FrontendFrame(
            index=index,
            t_ns=t_ns,
            left=images["left"],
            right=images["right"],
            beta_left=betas["left"][1],
            beta_right=betas["right"][1],
            bias=betas["left"][0],
            bias_right=betas["right"][0],
            e3ct_stats=stats,
            frame_left=frames["left"],
            frame_right=frames["right"],
            events_left=events["left"],
            events_right=events["right"],
            flood=self.flood(index, stats),
            warp_depth_m=depth,
            stretched=stretched,
            quiet=self.quiet(index, stats),
        )

    def process(self, index: int) -> FrontendFrame:
        """Runs the pipeline on frame ``index`` in the calling thread, warping through
        :attr:`plane_depth_m`."""
        return self.finish(self.prepare(index))

    def across_flood(self, previous: FrontendFrame | None, current: FrontendFrame) -> FrontendFrame:
        """``current`` as the run tracks it after ``previous``, the last frame that was not a
        flood: leaving a DVS-biased segment across a flood (``previous.bias == "dvs"``, and
        ``current`` a flood frame or the first clean frame after the flood), a frame whose two
        frames pass the exposure test (APS-biased) is rendered from its frames alone (β = 0,
        bias ``frames``; ``[fusion] flood_frames``). A flood frame's events are the flood's
        threshold pattern, and leaving a DVS-biased segment across a flood there is no bridge
        (:meth:`bridge_images`); the first clean frame, blended with its events at the
        APS-biased β while the auto-exposure is still catching up (a dark frame: mostly event
        edges on a flat background), matched the map of the segment's event-dominated
        keyframes with a fifth of the inliers its frames alone give. Entering a DVS-biased
        segment the flood frames stay predicted: the bridge needs the clean events of the last
        frame before them. Any other frame is returned unchanged."""
        if (
            self.mode != "fusion"
            or not (self.flood_predict and self.flood_frames)
            or previous is None
            or not (current.flood or current.index > previous.index + 1)
            or previous.bias != "dvs"
            or (current.bias, current.bias_right) != ("aps", "aps")
        ):
            return current
        return replace(
            current,
            left=current.frame_left,
            right=current.frame_right,
            beta_left=0.0,
            beta_right=0.0,
            bias="frames",
            bias_right="frames",
        )

    def predicts(self, frame: FrontendFrame, features: int) -> bool:
        """Whether the run predicts ``frame``'s pose instead of tracking it: a flood frame
        (``[fusion] flood_predict``), unless :meth:`across_flood` rendered it from its frames
        alone and ``features`` (the fewer of its two images') reach ``[fusion] min_features``."""
        if not (frame.flood and self.flood_predict):
            return False
        return not (frame.bias == "frames" and features >= self.min_features)

    def bridge_images(self, previous: FrontendFrame, current: FrontendFrame) -> BridgeImages | None:
        """The bridge rendering at a switch between frames ``previous`` and ``current`` (see
        :class:`BridgeImages`): consecutive ones, or, entering a DVS-biased segment, the last
        clean frame before a flood and the first after it when flood frames are predicted
        (``[fusion] flood_predict``; leaving one across a flood there is no bridge);
        ``None`` without a switch, when either is a predicted flood frame, outside the
        ``fusion`` mode or with ``[fusion] bridge = false``."""
        if (
            self.mode != "fusion"
            or not self.bridge_enabled
            or (self.flood_predict and (previous.flood or current.flood))
            or current.index <= previous.index
            or {previous.bias, current.bias} != {"aps", "dvs"}
        ):
            return None
        source, neighbour = (previous, current) if previous.bias == "aps" else (current, previous)
        if source is current and current.index > previous.index + 1:
            # Leaving a DVS-biased segment across a flood: the first clean frame is tracked with
            # its own (APS-biased) image. Its old-mode rendering, after several predicted
            # frames, locked onto a wrong pose on the repetitive event edges (70-90 mm off on
            # both demo seeds), worse than a new map segment that loop closing joins.
            return None
        if source.events_left is None or source.events_right is None:
            return None
        return BridgeImages(
            index=source.index,
            t_ns=source.t_ns,
            left=fuse(
                _exposed_like(source.frame_left, neighbour.frame_left),
                source.events_left,
                neighbour.beta_left,
            ),
            right=fuse(
                _exposed_like(source.frame_right, neighbour.frame_right),
                source.events_right,
                neighbour.beta_right,
            ),
            bias=neighbour.bias,
            beta_left=neighbour.beta_left,
            beta_right=neighbour.beta_right,
            warp_depth_m=source.warp_depth_m,
        )

    # -- iteration with prefetch ---------------------------------------------------------------

    def __iter__(self) -> Iterator[FrontendFrame]:
        if self.prefetch == 0:
            for k in range(self.start, self.stop):
                yield self.process(k)
            return
        self.close()
        # The files are read on a thread of their own (HDF5 holds the GIL), the kernels on another.
        raw = prefetched(iter(range(self.start, self.stop)), self.read, "reader", self.prefetch)
        self._prefetch = prefetched(raw, lambda r: self.finish(self.prepare(r)), "frontend", self.prefetch)
        try:
            yield from self._prefetch
        finally:
            self.close()

    def close(self) -> None:
        """Stops the prefetch threads (if any) and joins them."""
        stage, self._prefetch = self._prefetch, None
        if stage is not None:
            stage.close()

    def __enter__(self) -> Frontend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = [
    "MODES",
    "BridgeImages",
    "E3ctStats",
    "Frontend",
    "FrontendFrame",
    "PreparedFrame",
    "RectifiedCalibration",
    "is_flood",
]
