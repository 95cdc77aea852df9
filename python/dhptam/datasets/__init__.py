"""Datasets: the sequence model and the TUM-VIE reader and writer.

A :class:`Sequence` bundles a rig calibration, stereo frame pairs (decoded lazily), one
:class:`EventSource` per event camera (random access by time window) and the left frame
camera's ground truth. :func:`load_tumvie` reads the real TUM-VIE layout; :class:`TumVieWriter`
writes it (the simulator's output format). :func:`load` opens any supported format by name
(:data:`FORMATS`: TUM-VIE, VECtor folders and ROS bags, MVSEC, EuRoC); Kalibr camchain files
give a :class:`RigCalibration` through :func:`rig_from_kalibr`.

Example: write a tiny sequence and read an event window back::

    >>> import tempfile, numpy as np
    >>> from dhptam import SE3, Camera
    >>> from dhptam.datasets import CAMERA_KEYS, RigCalibration, TumVieWriter, load_tumvie
    >>> cam = Camera("kb4", [100.0, 100.0, 31.5, 23.5, 0.0, 0.0, 0.0, 0.0], 64, 48)
    >>> rig = RigCalibration({k: cam for k in CAMERA_KEYS}, {k: SE3() for k in CAMERA_KEYS})
    >>> out = tempfile.mkdtemp()
    >>> with TumVieWriter(out, "demo", rig, SE3()) as w:
    ...     w.add_frame_pair(0, 5_000_000, np.zeros((48, 64), np.uint8), np.zeros((48, 64), np.uint8))
    ...     w.add_events("left", [1, 2, 3], [4, 5, 6], [1_000, 2_500_000, 7_000_000], [1, 0, 1])
    >>> with load_tumvie(f"{out}/demo") as seq:
    ...     window = seq.events["left"].window(0, 5_000_000)
    ...     len(seq.frames), window.x.tolist(), window.t_ns.tolist()
    (1, [1, 2], [1000, 2500000])
"""

from __future__ import annotations

# -- other datasets (issue 9) -------------------------------------------------------------------
from .euroc import load_euroc
from .kalibr import KalibrCamera, read_kalibr_camchain, rig_from_kalibr
from .loaders import FORMATS, load
from .mvsec import load_mvsec
from .sequence import (
    CAMERA_KEYS,
    EVENT_SIDES,
    EventSource,
    EventStream,
    EventWindow,
    FramePair,
    Frames,
    GroundTruth,
    RigCalibration,
    Sequence,
)
from .tumvie import TumVieWriter, compose_poses, load_tumvie, read_basalt_calibration, read_mocap_calibration
from .vector import load_vector, read_vector_calibration

__all__ = [
    "CAMERA_KEYS",
    "EVENT_SIDES",
    "FORMATS",
    "EventSource",
    "EventStream",
    "EventWindow",
    "FramePair",
    "Frames",
    "GroundTruth",
    "KalibrCamera",
    "RigCalibration",
    "Sequence",
    "TumVieWriter",
    "compose_poses",
    "load",
    "load_euroc",
    "load_mvsec",
    "load_tumvie",
    "load_vector",
    "read_basalt_calibration",
    "read_kalibr_camchain",
    "read_mocap_calibration",
    "read_vector_calibration",
    "rig_from_kalibr",
]
