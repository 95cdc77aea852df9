"""Keypoints and descriptors for the SLAM front-end: learned (SuperPoint, R2D2) or classical.

One interface for every extractor::

    extractor = dhptam.features.load("r2d2")            # or "superpoint", "orb", "sift"
    left, right = extractor.extract(image_left, image_right)   # uint8 (H, W) grey images

returns two :class:`Features` with ``keypoints`` (N, 2) float32 sub-pixel ``(x, y)``,
``scores`` (N,) float32 and ``descriptors`` (N, D) float32 unit-norm rows or (N, 32) uint8 for
ORB: C-contiguous arrays that the Rust core reads in place. The learned extractors run both
images through the network as one batch, in torch (``pip install dhptam[features]``), on CUDA
when available; ORB and SIFT need neither torch nor weights.

Weights are found by :func:`dhptam.features.weights.resolve`: an explicit path, then
``$DHPTAM_WEIGHTS_DIR``, then the user cache, then a checksum-verified download.

:func:`match` pairs two descriptor sets by mutual nearest neighbour with a ratio test (Rust core).

Example, with the weight-free ORB::

    >>> import numpy as np
    >>> from dhptam import features
    >>> rng = np.random.default_rng(0)
    >>> img = (rng.random((120, 160)) * 255).astype(np.uint8)
    >>> orb = features.load("orb", max_keypoints=200)
    >>> left, right = orb.extract(img, img)
    >>> left.descriptors.dtype, left.descriptors.shape[1], len(left) <= 200
    (dtype('uint8'), 32, True)
    >>> pairs, distances = features.match(left, right)
    >>> bool((distances == 0).all()) and len(pairs) > 0.9 * len(left)
    True
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .. import _core
from ..errors import InputError
from .base import Extractor, Features

__all__ = [
    "EXTRACTORS",
    "KEYPOINT_BUDGET_RANGE",
    "PIXELS_PER_KEYPOINT",
    "Extractor",
    "Features",
    "from_config",
    "keypoint_budget",
    "load",
    "match",
]

#: Names accepted by :func:`load`.
EXTRACTORS = ("superpoint", "r2d2", "orb", "sift")

# The core's per-kind defaults (`MatchOptions::for_kind`): unit-norm float rows by L2
# distance in [0, 2], binary rows by Hamming distance in bits.
_DEFAULT_MAX_DISTANCE = {False: 0.9, True: 64.0}


def load(
    name: str,
    weights: str | os.PathLike[str] | None = None,
    device: str | None = "auto",
    max_keypoints: int = 1000,
    *,
    threads: int | None = None,
    **options: Any,
) -> Extractor:
    """An extractor by name: ``"superpoint"``, ``"r2d2"``, ``"orb"`` or ``"sift"``.

    Parameters
    ----------
    weights
        For the learned extractors: a checkpoint path, or the name of a known weight file
        (``"r2d2_WASF_N16"`` — the default for r2d2 — ``"faster2d2_WASF_N16"``,
        ``"superpoint_v1"`` — the default for superpoint). Must be None for ORB/SIFT.
    device
        ``"auto"`` (CUDA when available, else CPU), ``"cpu"``, ``"cuda"``, ``"cuda:N"``.
    max_keypoints
        Keypoints kept per image, best scores first.
    threads
        CPU threads of torch (``torch.set_num_threads``, process-wide) or OpenCV; None keeps
        the library default.
    options
        Extractor-specific settings, e.g. ``precision="bfloat16"`` (network trunk in reduced
        precision) for the learned extractors, ``scales`` for r2d2, ``nms_radius`` for
        superpoint (see :class:`~dhptam.features.r2d2.R2D2`,
        :class:`~dhptam.features.superpoint.SuperPoint`,
        :class:`~dhptam.features.classical.ORB`, :class:`~dhptam.features.classical.SIFT`).
    """
    key = str(name).lower()
    if key in ("orb", "sift"):
        if weights is not None:
            raise InputError(f"weights: {key} needs no weights, got {weights!r}", field="weights")
        from .classical import ORB, SIFT

        cls = ORB if key == "orb" else SIFT
        return cls(max_keypoints=max_keypoints, threads=threads, **options)
    if key not in ("superpoint", "r2d2"):
        raise InputError(f"name: expected one of {', '.join(EXTRACTORS)}, got {name!r}", field="name")
    from .base import import_torch

    import_torch()  # fails with the install hint before any weight lookup
    path = _weights_path(key, weights)
    if key == "r2d2":
        from .r2d2 import R2D2

        return R2D2(path, max_keypoints=max_keypoints, device=device, threads=threads, **options)
    from .superpoint import SuperPoint

    return SuperPoint(path, max_keypoints=max_keypoints, device=device, threads=threads, **options)


#: Image area per keypoint of :func:`keypoint_budget`, square pixels (one per 16 × 16 block).
PIXELS_PER_KEYPOINT = 256
#: Fewest and most keypoints :func:`keypoint_budget` gives.
KEYPOINT_BUDGET_RANGE = (1000, 8000)


def keypoint_budget(width: int, height: int) -> int:
    """Keypoints per image for ``[features] max_keypoints = 0`` (the default): one per
    :data:`PIXELS_PER_KEYPOINT` square pixels of a ``width`` × ``height`` image, within
    :data:`KEYPOINT_BUDGET_RANGE`; 1000 at 320 × 320 and below, 4096 at TUM-VIE's 1024 × 1024.

    A fixed count spreads thinner as images grow: at 1024 × 1024, 1000 ORB keypoints left every
    mode on five simulated TUM-VIE-size sequences 1.2–19× less accurate than this budget
    (``docs/BENCHMARKS.md``, "Accuracy at TUM-VIE size").
    """
    if width <= 0 or height <= 0:
        raise InputError(f"image size must be positive, got {width}×{height}", field="image_size")
    lo, hi = KEYPOINT_BUDGET_RANGE
    return int(min(max(round(width * height / PIXELS_PER_KEYPOINT), lo), hi))


def from_config(
    config: _core.Config | None = None, *, image_size: tuple[int, int] | None = None, **options: Any
) -> Extractor:
    """The extractor described by the ``[features]`` section of ``config`` (defaults if None).

    ``max_keypoints = 0`` takes :func:`keypoint_budget` of ``image_size`` (width, height), or
    its lower bound (1000) without one. ``precision`` goes to the learned extractors and a
    non-empty ``scales`` to R2D2. ``options`` are passed on to :func:`load`
    (extractor-specific settings) and take precedence over the section.

    >>> from dhptam import Config, features
    >>> features.from_config(Config.from_toml('[features]\\nextractor = "sift"\\nmax_keypoints = 50'))
    SIFT(max_keypoints=50)
    """
    section = (config if config is not None else _core.Config()).to_dict()["features"]
    max_keypoints = int(section["max_keypoints"])
    if max_keypoints == 0:
        max_keypoints = keypoint_budget(*image_size) if image_size is not None else KEYPOINT_BUDGET_RANGE[0]
    # The configuration checked precision and scales against the extractor; ORB and SIFT
    # take neither, so they are passed on only where they apply.
    if section["extractor"] in ("r2d2", "superpoint"):
        options.setdefault("precision", section["precision"])
    if section["scales"]:
        options.setdefault("scales", tuple(float(s) for s in section["scales"]))
    return load(
        section["extractor"],
        options.pop("weights", section["weights"] or None),
        options.pop("device", section["device"]),
        options.pop("max_keypoints", max_keypoints),
        threads=options.pop("threads", int(section["threads"]) or None),
        **options,
    )


def _weights_path(extractor: str, weights: str | os.PathLike[str] | None) -> Path:
    from .weights import WEIGHTS, resolve

    default = {"r2d2": "r2d2_WASF_N16", "superpoint": "superpoint_v1"}[extractor]
    if weights is None:
        return resolve(default)
    text = os.fspath(weights)
    stem = text[:-3] if text.endswith(".pt") else text[:-4] if text.endswith(".pth") else text
    if stem in WEIGHTS and os.sep not in text and not Path(text).is_file():
        return resolve(stem)
    return resolve(default, text)


def match(
    a: Features | npt.NDArray[Any],
    b: Features | npt.NDArray[Any],
    *,
    max_distance: float | None = None,
    ratio: float = 0.8,
    mutual: bool = True,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    """Matches descriptors of ``a`` (query) to ``b`` (train) in the Rust core.

    A pair (i, j) is kept when j is i's nearest neighbour, at distance ≤ ``max_distance``
    (None: 0.9 for unit float rows — L2 in [0, 2] — and 64 bits for binary rows), nearer than
    ``ratio`` × the second-nearest (1.0 turns the test off) and, when ``mutual``, i is also
    j's nearest neighbour. Returns ``pairs`` (M, 2) int64 of (row in a, row in b), sorted by
    the row in a, and ``distances`` (M,) float32. The descriptor arrays are read in place.
    """
    qa = a.descriptors if isinstance(a, Features) else a
    qb = b.descriptors if isinstance(b, Features) else b
    binary = bool(np.asarray(qa).dtype == np.uint8)
    limit = _DEFAULT_MAX_DISTANCE[binary] if max_distance is None else float(max_distance)
    return _core.match_descriptors(qa, qb, limit, float(ratio), bool(mutual))
