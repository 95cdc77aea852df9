"""Rigs and presets of the simulator.

A rig is four cameras in the TUM-VIE / Basalt order (``frame_left``, ``frame_right``,
``event_left``, ``event_right``) with their ``imu_from_cam`` poses: frame cameras 10 cm apart,
each event camera 5.5 cm from the centre and 3 cm below, all looking forward with small
mounting rotations, like the TUM-VIE head. Cameras are Kannala–Brandt (kb4), the model of the
TUM-VIE calibration files, except in the ``*-mixed`` rigs (radtan frame cameras, pinhole
event cameras); the full-size rig has TUM-VIE's resolutions (1024×1024 frames, 1280×720
events), the smaller ones scale the intrinsics with the resolution. The ``*davis`` rigs are a
stereo pair of DAVIS-like sensors instead (as MVSEC's): each sensor reads frames and events
from the same pixels, so an event camera is its frame camera (same intrinsics, size and pose).
"""

from __future__ import annotations

from dataclasses import dataclass

from .._core import SE3, SO3, Camera

# kb4 distortion of the rigs (the same for every size: it is a function of the ray angle).
_KB4_FRAME = (0.0194, 0.0023, -0.0027, 0.0009)
_KB4_EVENT = (-0.0308, 0.0151, -0.0139, 0.0040)
# TUM-VIE-like intrinsics at full size: (fx, fy, cx, cy, width, height).
# Radial-tangential distortion [k1, k2, p1, p2, k3] of the mixed rigs' frame cameras.
_RADTAN_FRAME = (-0.12, 0.03, 2e-4, -3e-4, 0.0)
_FRAME_FULL = (747.3, 747.4, 490.8, 506.1, 1024, 1024)
# A DAVIS346-like sensor (346×260 pixels, about 75° across) with a mild equidistant (kb4) lens.
_DAVIS_FULL = (226.0, 226.0, 172.5, 129.5, 346, 260)
_KB4_DAVIS = (-0.045, 0.010, -0.030, 0.010)
_EVENT_FULL = (1049.1, 1049.2, 634.3, 363.0, 1280, 720)

CAMERA_ORDER = ("frame_left", "frame_right", "event_left", "event_right")

# Where the mocap marker sits on the rig (arbitrary but not trivial, so that the hand-eye
# chain world_from_cam = world_from_marker · inv(imu_from_marker) · imu_from_cam is exercised).
IMU_FROM_MARKER = SE3(SO3.exp([0.1, -0.2, 0.3]), [0.02, -0.08, 0.05])


@dataclass(frozen=True)
class RigSpec:
    """A rig size: the frame and event resolutions; ``shared_sensor``: frames and events come
    from the same pixels (DAVIS-like sensors), the event cameras are the frame cameras."""

    name: str
    frame_size: tuple[int, int]
    event_size: tuple[int, int]
    mixed_models: bool = False
    shared_sensor: bool = False

    def cameras(self) -> dict[str, Camera]:
        """The four cameras, intrinsics scaled from the full-size rig."""

        def scaled(
            model: str,
            full: tuple[float, float, float, float, int, int],
            size: tuple[int, int],
            k: tuple[float, ...],
        ) -> Camera:
            fx, fy, cx, cy, w, h = full
            sx, sy = size[0] / w, size[1] / h
            # Pixel centres at integers: scale the image about its corner at (−½, −½).
            params = [fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5, *k]
            return Camera(model, params, size[0], size[1])

        if self.shared_sensor:
            if self.frame_size != self.event_size:
                raise ValueError(f"rig {self.name}: a shared sensor has one resolution")
            sensor = scaled("kb4", _DAVIS_FULL, self.frame_size, _KB4_DAVIS)
            return {name: sensor for name in CAMERA_ORDER}
        if self.mixed_models:
            frame = scaled("radtan", _FRAME_FULL, self.frame_size, _RADTAN_FRAME)
            event = scaled("pinhole", _EVENT_FULL, self.event_size, ())
        else:
            frame = scaled("kb4", _FRAME_FULL, self.frame_size, _KB4_FRAME)
            event = scaled("kb4", _EVENT_FULL, self.event_size, _KB4_EVENT)
        return {"frame_left": frame, "frame_right": frame, "event_left": event, "event_right": event}

    def imu_from_cam(self) -> dict[str, SE3]:
        """Camera poses on the rig (metres; camera axes roughly along the IMU's)."""
        left = SE3(SO3.exp([0.004, 0.006, -0.002]), [-0.05, 0.0, 0.0])
        right = SE3(SO3.exp([-0.003, -0.005, 0.001]), [0.05, 0.001, 0.0])
        if self.shared_sensor:
            return {"frame_left": left, "frame_right": right, "event_left": left, "event_right": right}
        return {
            "frame_left": left,
            "frame_right": right,
            "event_left": SE3(SO3.exp([0.006, 0.002, 0.003]), [-0.055, 0.03, 0.002]),
            "event_right": SE3(SO3.exp([-0.002, -0.004, -0.002]), [0.055, 0.031, 0.001]),
        }


RIGS = {
    "tumvie": RigSpec("tumvie", (1024, 1024), (1280, 720)),
    "small": RigSpec("small", (320, 320), (320, 180)),
    "tiny": RigSpec("tiny", (128, 128), (128, 72)),
    "small-mixed": RigSpec("small-mixed", (320, 320), (320, 180), mixed_models=True),
    "tiny-mixed": RigSpec("tiny-mixed", (128, 128), (128, 72), mixed_models=True),
    "davis": RigSpec("davis", (346, 260), (346, 260), shared_sensor=True),
    "tiny-davis": RigSpec("tiny-davis", (128, 96), (128, 96), shared_sensor=True),
}


@dataclass(frozen=True)
class Preset:
    """What ``dhptam simulate --preset NAME`` generates."""

    name: str
    rig: str
    motion: str
    profile: str
    duration_s: float
    description: str


PRESETS = {
    p.name: p
    for p in (
        Preset(
            "demo", "small", "desk_spiral", "hdr", 4.0, "the demo's data: short HDR desk sequence (default)"
        ),
        Preset("desk", "small", "desk_spiral", "normal", 10.0, "desk spiral, normal lighting"),
        Preset(
            "desk-flicker",
            "small",
            "desk_spiral",
            "flicker",
            6.0,
            "desk spiral, exposure flicker at the start",
        ),
        Preset("dark", "small", "desk_spiral", "dark", 6.0, "desk spiral in a 40× darker room"),
        Preset("1d-trans", "small", "translation_1d", "normal", 8.0, "back and forth along x"),
        Preset("6dof", "small", "shake_6dof", "normal", 6.0, "fast shaking in six degrees of freedom"),
        Preset("loop", "small", "closed_loop", "normal", 12.0, "one loop around the room, back to the start"),
        Preset(
            "tumvie-desk", "tumvie", "desk_spiral", "normal", 10.0, "desk spiral at full TUM-VIE resolution"
        ),
        Preset(
            "tumvie-hdr", "tumvie", "desk_spiral", "hdr", 10.0, "HDR desk sequence at full TUM-VIE resolution"
        ),
        Preset(
            "desk-mixed",
            "small-mixed",
            "desk_spiral",
            "normal",
            10.0,
            "desk spiral, radtan frames, pinhole events",
        ),
        Preset("tiny", "tiny", "desk_spiral", "hdr", 1.0, "a 1 s 128-pixel sequence for tests"),
        Preset(
            "tiny-mixed", "tiny-mixed", "desk_spiral", "normal", 1.0, "tiny, radtan frames, pinhole events"
        ),
        Preset(
            "davis-hdr",
            "davis",
            "desk_spiral",
            "hdr",
            4.0,
            "HDR desk sequence on a DAVIS346-like stereo pair (frames and events from the same pixels)",
        ),
        Preset(
            "tiny-davis",
            "tiny-davis",
            "desk_spiral",
            "normal",
            1.0,
            "tiny, frames and events from the same pixels",
        ),
    )
}

DEFAULT_PRESET = "demo"
MOTIONS = ("desk_spiral", "translation_1d", "shake_6dof", "closed_loop")
PROFILES = ("normal", "hdr", "flicker", "dark")


def lighting_segments(profile: str, duration_s: float) -> list[tuple[str, int, int]]:
    """The spans of a simulated sequence of ``duration_s`` seconds lit at one level under
    ``profile``: ``(label, start_ns, end_ns)`` in the sequence's time (which starts at 0), label
    ``normal``, ``dark`` or ``bright``, in time order. The ramps between two levels belong to
    no span. ``hdr`` gives normal, dark, normal, bright, normal; the other profiles one span.

    >>> [(label, start / 1e9, end / 1e9) for label, start, end in lighting_segments("hdr", 4.0)][:2]
    [('normal', 0.0, 1.2), ('dark', 1.32, 2.08)]
    """
    from .. import _core
    from ..errors import InputError

    # The core checks the profile's name (InputError, field "lighting profile").
    if not duration_s > 0:
        raise InputError(f"duration must be positive, got {duration_s}", field="duration")
    return [
        (label, round(start * duration_s * 1e9), round(end * duration_s * 1e9))
        for label, start, end in _core.sim_profile_segments(profile)
    ]


def describe_presets() -> str:
    """One line per preset, for ``--help``."""
    lines = []
    for p in PRESETS.values():
        w, h = RIGS[p.rig].frame_size
        ew, eh = RIGS[p.rig].event_size
        lines.append(
            f"  {p.name:<13} {p.description} [{p.motion}, {p.profile}, {p.duration_s:g} s, "
            f"frames {w}×{h}, events {ew}×{eh}{', radtan/pinhole' if RIGS[p.rig].mixed_models else ''}]"
        )
    return "\n".join(lines)
