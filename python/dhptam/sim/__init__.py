"""The stereo events+frames simulator (``dhptam simulate``).

A textured room with a desk (photographs from scikit-image and procedural textures) is ray
cast per pixel in Rust for four cameras — stereo frame cameras and stereo event cameras, a
TUM-VIE-like rig — moving along a built-in or recorded trajectory. Frames get exposure, motion
blur, a lagging auto-exposure, noise and saturation; events follow the ESIM model (optionally
with hot pixels, :class:`HotPixelSource`). The output
is the TUM-VIE layout, written through :class:`dhptam.datasets.TumVieWriter`, plus the left
frame camera's ground truth as a TUM trajectory.

Example::

    >>> import tempfile
    >>> from dhptam.datasets import load_tumvie
    >>> from dhptam.sim import simulate
    >>> out = simulate(tempfile.mkdtemp(), preset="tiny", duration_s=0.2, seed=1)
    >>> with load_tumvie(out.path) as seq:
    ...     len(seq.frames), seq.frames[0].left.shape, len(seq.ground_truth) > 0
    (4, (128, 128), True)
"""

from __future__ import annotations

from .presets import (
    DEFAULT_PRESET,
    IMU_FROM_MARKER,
    MOTIONS,
    PRESETS,
    PROFILES,
    RIGS,
    Preset,
    RigSpec,
    lighting_segments,
)
from .simulate import GROUND_TRUTH_FILE, HotPixelSource, SimulationSummary, simulate, simulator_for
from .textures import PHOTO_NAMES, load_photos

__all__ = [
    "DEFAULT_PRESET",
    "GROUND_TRUTH_FILE",
    "IMU_FROM_MARKER",
    "MOTIONS",
    "PHOTO_NAMES",
    "PRESETS",
    "PROFILES",
    "RIGS",
    "HotPixelSource",
    "Preset",
    "RigSpec",
    "SimulationSummary",
    "lighting_segments",
    "load_photos",
    "simulate",
    "simulator_for",
]
