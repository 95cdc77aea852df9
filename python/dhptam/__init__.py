"""dhptam: stereo events+frames SLAM (DH-PTAM), with a Rust core.

Quick look::

    >>> import numpy as np, dhptam
    >>> cam = dhptam.Camera("pinhole", [500.0, 500.0, 320.0, 240.0], 640, 480)
    >>> cam.project(np.array([[0.0, 0.0, 2.0]]))
    array([[320., 240.]])

Modules: :mod:`dhptam.geometry` (Lie groups, cameras, rectification, triangulation),
:mod:`dhptam.errors` (exceptions), :mod:`dhptam.logs` (logging), :mod:`dhptam.cli` (the
``dhptam`` command), :mod:`dhptam.datasets` (sequences, TUM-VIE reader and writer; imported
on its own, as it loads h5py), :mod:`dhptam.events` (E3CT, baseline event images, fusion
windows).
"""

from __future__ import annotations

from . import _core
from ._core import Config
from .errors import (
    ConfigError,
    DhptamError,
    FileError,
    InputError,
    NumericalError,
    ParseError,
)
from .geometry import SE3, SO3, Camera, RectifiedStereo, StereoRig, Triangulation, triangulate

# ``dhptam.run(...)`` -> ``RunResult``: the function behind ``dhptam run`` (issue 8). It takes
# the name of its module on the package, so ``import dhptam.run`` followed by ``dhptam.run``
# gives the function; the module itself is ``sys.modules["dhptam.run"]``.
from .run import RunResult, run
from .system import StereoCalibration, System, TrackResult

__version__: str = _core.__version__

__all__ = [
    "SE3",
    "SO3",
    "Camera",
    "Config",
    "ConfigError",
    "DhptamError",
    "FileError",
    "InputError",
    "NumericalError",
    "ParseError",
    "RectifiedStereo",
    "RunResult",
    "StereoCalibration",
    "StereoRig",
    "System",
    "TrackResult",
    "Triangulation",
    "__version__",
    "run",
    "triangulate",
]
