"""One entry point for every dataset format: ``load(format, path, **options)``.

=============  ==========================================  ======================================
format         path                                        reader
=============  ==========================================  ======================================
``tum-vie``    sequence folder                             :func:`~dhptam.datasets.load_tumvie`
``vector``     folder with ``<seq>.synced.*``               :func:`~dhptam.datasets.load_vector`
``vector-bag`` VECtor ROS1 ``.bag``                        :func:`~dhptam.datasets.rosbag.load_vector_bag`
``mvsec``      ``<seq>_data.hdf5`` or its folder           :func:`~dhptam.datasets.load_mvsec`
``euroc``      ASL folder (``mav0/``)                       :func:`~dhptam.datasets.load_euroc`
=============  ==========================================  ======================================

``calibration`` is accepted by every format except EuRoC (whose calibration is in the folder);
other keyword options go to the reader unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import InputError
from .sequence import Sequence


def _tumvie(path: Path, **kw: Any) -> Sequence:
    from .tumvie import load_tumvie

    return load_tumvie(path, **kw)


def _vector(path: Path, **kw: Any) -> Sequence:
    from .vector import load_vector

    return load_vector(path, **kw)


def _vector_bag(path: Path, **kw: Any) -> Sequence:
    from .rosbag import load_vector_bag

    return load_vector_bag(path, **kw)


def _mvsec(path: Path, **kw: Any) -> Sequence:
    from .mvsec import load_mvsec

    return load_mvsec(path, **kw)


def _euroc(path: Path, **kw: Any) -> Sequence:
    from .euroc import load_euroc

    if kw.pop("calibration", None) is not None:
        raise InputError(
            "EuRoC sequences carry their calibration (mav0/cam*/sensor.yaml)", field="calibration"
        )
    return load_euroc(path, **kw)


def _mcap(path: Path, **kw: Any) -> Sequence:
    from .mcap import load_mcap

    if kw.pop("calibration", None) is not None:
        raise InputError(
            "MCAP logs carry their calibration (metadata 'dhptam.sequence')", field="calibration"
        )
    return load_mcap(path, **kw)


FORMATS: dict[str, Callable[..., Sequence]] = {
    "tum-vie": _tumvie,
    "vector": _vector,
    "vector-bag": _vector_bag,
    "mvsec": _mvsec,
    "euroc": _euroc,
    "mcap": _mcap,
}
"""Reader of each format name."""


def load(format: str, path: str | Path, **options: Any) -> Sequence:
    """Open a sequence of the named format; ``options`` go to the reader.

    ``calibration=None`` is dropped so that each reader looks for its own default.
    """
    reader = FORMATS.get(format)
    if reader is None:
        raise InputError(
            f"unknown sequence format {format!r}; choose one of {', '.join(FORMATS)}", field="format"
        )
    if options.get("calibration") is None:
        options.pop("calibration", None)
    return reader(Path(path), **options)


__all__ = ["FORMATS", "load"]
