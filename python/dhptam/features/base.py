"""What every extractor shares: the :class:`Features` record, input checks, torch set-up.

Nothing here imports torch at module level: :func:`import_torch` does it on demand, so that
``import dhptam.features`` stays cheap and ORB/SIFT run on an install without torch.
"""

from __future__ import annotations

import abc
import contextlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from ..errors import InputError, MissingDependencyError

if TYPE_CHECKING:
    import torch

__all__ = [
    "Extractor",
    "Features",
    "TorchExtractor",
    "check_image",
    "import_torch",
    "resolve_device",
]


@dataclass(frozen=True)
class Features:
    """Keypoints of one image with their scores and descriptors.

    Attributes
    ----------
    keypoints
        (N, 2) float32, C-contiguous: sub-pixel ``(x, y)`` = (column, row) in image pixels,
        pixel (0, 0) being the centre of the top-left pixel.
    scores
        (N,) float32, higher is better; the extractor's own detection score (not comparable
        between extractors).
    descriptors
        (N, D) float32 with unit-norm rows (L2 distances in [0, 2]), or (N, 32) uint8 for
        binary ORB descriptors (Hamming distance).
    sigmas
        (N,) float32, finite and positive: each keypoint's location noise σ in pixels, from
        the scale it was detected at (ORB: 1.2^octave, SIFT: 2^octave, R2D2: 1 / pyramid
        scale). The back-end weighs its reprojection residuals by 1/σ (``[tracking]
        keypoint_sigma``). ``None`` at construction (an extractor without scale information)
        gives 1 for every keypoint.

    Every array is C-contiguous with exactly these dtypes, so the Rust core reads them in
    place. Construction checks shapes, dtypes and values and raises
    :class:`~dhptam.errors.InputError` naming the field.
    """

    keypoints: npt.NDArray[np.float32]
    scores: npt.NDArray[np.float32]
    descriptors: npt.NDArray[np.float32] | npt.NDArray[np.uint8]
    sigmas: npt.NDArray[np.float32] = None  # type: ignore[assignment]  # None → ones

    def __post_init__(self) -> None:
        kp, sc, de = self.keypoints, self.scores, self.descriptors
        if not (isinstance(kp, np.ndarray) and kp.dtype == np.float32 and kp.ndim == 2 and kp.shape[1] == 2):
            raise InputError(
                f"keypoints: expected an (N, 2) float32 array, got {_describe(kp)}", field="keypoints"
            )
        n = kp.shape[0]
        if not (isinstance(sc, np.ndarray) and sc.dtype == np.float32 and sc.shape == (n,)):
            raise InputError(f"scores: expected a ({n},) float32 array, got {_describe(sc)}", field="scores")
        if not (
            isinstance(de, np.ndarray)
            and de.dtype in (np.float32, np.uint8)
            and de.ndim == 2
            and de.shape[0] == n
            and de.shape[1] > 0
        ):
            raise InputError(
                f"descriptors: expected an ({n}, D) float32 or uint8 array, got {_describe(de)}",
                field="descriptors",
            )
        si = self.sigmas
        if si is None:
            si = np.ones(n, np.float32)
            object.__setattr__(self, "sigmas", si)
        if not (isinstance(si, np.ndarray) and si.dtype == np.float32 and si.shape == (n,)):
            raise InputError(f"sigmas: expected a ({n},) float32 array, got {_describe(si)}", field="sigmas")
        bad = ~(np.isfinite(si) & (si > 0))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"sigmas: expected finite positive pixels, got {si[i]} at keypoint {i}", field="sigmas"
            )
        for name, array in (("keypoints", kp), ("scores", sc), ("descriptors", de), ("sigmas", si)):
            if not array.flags.c_contiguous:
                raise InputError(f"{name}: expected a C-contiguous array", field=name)

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def binary(self) -> bool:
        """Whether the descriptors are binary (uint8 bit strings compared by Hamming distance)."""
        return bool(self.descriptors.dtype == np.uint8)

    @classmethod
    def empty(cls, width: int, binary: bool = False) -> Features:
        """No keypoints, descriptors of ``width`` floats (or bytes when ``binary``)."""
        dtype = np.uint8 if binary else np.float32
        return cls(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, width), dtype))


def _describe(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"shape {value.shape} dtype {value.dtype}"
    return type(value).__name__


def check_image(image: Any, name: str) -> npt.NDArray[np.uint8]:
    """An 8-bit grayscale (H, W) image as a C-contiguous uint8 array (a view when possible).

    (H, W, 1) is accepted and squeezed; colour images are refused rather than guessed at.
    """
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    if array.dtype != np.uint8 or array.ndim != 2:
        raise InputError(
            f"{name}: expected an 8-bit grayscale (H, W) uint8 image, got {_describe(array)}", field=name
        )
    if array.shape[0] < 16 or array.shape[1] < 16:
        raise InputError(f"{name}: expected an image of at least 16×16 pixels, got {array.shape}", field=name)
    return np.ascontiguousarray(array)


class Extractor(abc.ABC):
    """A keypoint detector and descriptor; build one with :func:`dhptam.features.load`."""

    #: Name given to :func:`dhptam.features.load`.
    name: str = ""
    #: Descriptor width: floats per row, or bytes per row for binary descriptors.
    descriptor_width: int = 0
    #: Whether descriptors are binary (uint8, Hamming).
    binary: bool = False

    def __init__(self, max_keypoints: int) -> None:
        if int(max_keypoints) < 1:
            raise InputError(
                f"max_keypoints: expected a positive count, got {max_keypoints}", field="max_keypoints"
            )
        self.max_keypoints = int(max_keypoints)

    def extract(self, image_left: Any, image_right: Any) -> tuple[Features, Features]:
        """Features of a stereo pair of 8-bit grayscale images of the same size."""
        left = check_image(image_left, "image_left")
        right = check_image(image_right, "image_right")
        if left.shape != right.shape:
            raise InputError(
                f"image_right: expected the size of image_left {left.shape}, got {right.shape}",
                field="image_right",
            )
        return self._extract_pair(left, right)

    def extract_one(self, image: Any) -> Features:
        """Features of a single 8-bit grayscale image."""
        return self._extract_single(check_image(image, "image"))

    @abc.abstractmethod
    def _extract_pair(
        self, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8]
    ) -> tuple[Features, Features]: ...

    @abc.abstractmethod
    def _extract_single(self, image: npt.NDArray[np.uint8]) -> Features: ...

    def __repr__(self) -> str:
        return f"{type(self).__name__}(max_keypoints={self.max_keypoints})"


def import_torch() -> Any:
    """The ``torch`` module, or a :class:`MissingDependencyError` saying how to install it."""
    try:
        import torch
    except ImportError as e:
        raise MissingDependencyError(
            "the learned feature extractors (superpoint, r2d2) need PyTorch, which is not installed: "
            "run `pip install dhptam[features]` (or `pip install torch`); "
            "the classical extractors 'orb' and 'sift' work without it"
        ) from e
    return torch


def resolve_device(device: str | None) -> torch.device:
    """``"auto"`` (or None) → CUDA when available, else CPU; otherwise the named torch device."""
    torch = import_torch()
    name = "auto" if device is None else str(device)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(name)
    except (RuntimeError, ValueError) as e:
        raise InputError(
            f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {name!r}", field="device"
        ) from e
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device: {name!r} was asked for but CUDA is not available", field="device")
    return resolved


_PRECISIONS = ("float32", "bfloat16", "float16")


class TorchExtractor(Extractor):
    """An extractor whose network runs in torch on ``device`` under ``torch.inference_mode``.

    ``threads`` (> 0) sets ``torch.set_num_threads``, a process-wide torch setting; None or 0
    leaves torch's default (one thread per core). ``precision`` is ``"float32"`` (default),
    ``"bfloat16"`` or, on CUDA, ``"float16"`` for the network's forward pass (see
    :meth:`autocast`); a subclass may accept more in :attr:`extra_precisions` (R2D2: ``"int8"``),
    for which :meth:`autocast` does nothing and the subclass runs its own network.
    """

    #: Precisions this extractor accepts besides float32, bfloat16 and float16.
    extra_precisions: tuple[str, ...] = ()

    def __init__(
        self,
        max_keypoints: int,
        device: str | None = "auto",
        threads: int | None = None,
        precision: str = "float32",
    ) -> None:
        super().__init__(max_keypoints)
        self._torch = import_torch()
        self.device = resolve_device(device)
        allowed = _PRECISIONS + self.extra_precisions
        if precision not in allowed:
            raise InputError(
                f"precision: expected one of {', '.join(allowed)}, got {precision!r}", field="precision"
            )
        if precision == "float16" and self.device.type != "cuda":
            raise InputError(
                "precision: float16 needs a CUDA device; use bfloat16 on the CPU", field="precision"
            )
        self.precision = precision
        if threads is not None and int(threads) < 0:
            raise InputError(
                f"threads: expected 0 (torch's default) or a positive count, got {threads}", field="threads"
            )
        if threads:
            self._torch.set_num_threads(int(threads))

    def autocast(self) -> contextlib.AbstractContextManager[Any]:
        """The context the network runs in: nothing for float32, else torch autocast.

        bfloat16 uses the CPU's AMX/AVX-512 BF16 units where present (about 2–4× faster on a
        Sapphire Rapids core) at the cost of ~3 significant digits in the network's
        activations; everything after the network (NMS, sampling, normalisation) stays float32.
        """
        if self.precision not in ("bfloat16", "float16"):
            return contextlib.nullcontext()
        dtype = getattr(self._torch, self.precision)
        return self._torch.autocast(device_type=self.device.type, dtype=dtype)

    def _extract_single(self, image: npt.NDArray[np.uint8]) -> Features:
        return self._run_batch([image])[0]

    def _extract_pair(
        self, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8]
    ) -> tuple[Features, Features]:
        first, second = self._run_batch([left, right])
        return first, second

    @abc.abstractmethod
    def _run_batch(self, images: list[npt.NDArray[np.uint8]]) -> list[Features]:
        """Features of images of one size, computed in one batched forward pass."""

    def _to_tensor(self, images: list[npt.NDArray[np.uint8]]) -> torch.Tensor:
        """(B, 1, H, W) float32 in [0, 1] on the device."""
        torch = self._torch
        batch = torch.from_numpy(np.stack(images)).to(self.device)
        return batch.unsqueeze(1).float().div_(255.0)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(max_keypoints={self.max_keypoints}, device={self.device})"


def to_features(
    keypoints: torch.Tensor,
    scores: torch.Tensor,
    descriptors: torch.Tensor,
    sigmas: torch.Tensor | None = None,
) -> Features:
    """Features from torch tensors on any device, as float32 C-contiguous numpy arrays
    (``sigmas`` ``None``: 1 px each)."""
    kp, sc, de = (t.detach().float().cpu().contiguous().numpy() for t in (keypoints, scores, descriptors))
    arrays = (np.ascontiguousarray(kp), np.ascontiguousarray(sc), np.ascontiguousarray(de))
    if sigmas is None:
        return Features(*arrays)
    return Features(*arrays, np.ascontiguousarray(sigmas.detach().float().cpu().numpy()))


def refine_subpixel(
    score_map: torch.Tensor, batch: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor
) -> torch.Tensor:
    """Sub-pixel offsets ``(dx, dy)`` of local maxima, from a parabola through 3 samples per axis.

    ``score_map`` is (B, 1, H, W); the maxima are at the integer positions ``(batch, ys, xs)``.
    Along x, the parabola through s(x−1), s(x), s(x+1) peaks at
    ``dx = (s(x+1) − s(x−1)) / (2 (2 s(x) − s(x−1) − s(x+1)))``, and likewise along y. Offsets
    are clamped to [−0.5, 0.5] (a larger one would mean the sample is not the maximum) and are 0
    on the image border, where a neighbour is missing. Returns an (N, 2) tensor.
    """
    torch = import_torch()
    h, w = score_map.shape[-2:]
    s = score_map[:, 0]
    centre = s[batch, ys, xs]
    left = s[batch, ys, (xs - 1).clamp(min=0)]
    right = s[batch, ys, (xs + 1).clamp(max=w - 1)]
    up = s[batch, (ys - 1).clamp(min=0), xs]
    down = s[batch, (ys + 1).clamp(max=h - 1), xs]
    den_x = 2.0 * (2.0 * centre - left - right)
    den_y = 2.0 * (2.0 * centre - up - down)
    inside_x = (den_x > 1e-12) & (xs > 0) & (xs < w - 1)
    inside_y = (den_y > 1e-12) & (ys > 0) & (ys < h - 1)
    dx = torch.where(inside_x, (right - left) / torch.where(inside_x, den_x, 1.0), 0.0).clamp(-0.5, 0.5)
    dy = torch.where(inside_y, (down - up) / torch.where(inside_y, den_y, 1.0), 0.0).clamp(-0.5, 0.5)
    return torch.stack([dx, dy], dim=1)


def window_max(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Maximum over the (2r+1)×(2r+1) window around each pixel of (B, C, H, W), −∞ outside.

    Equal to ``F.max_pool2d(x, 2r+1, stride=1, padding=r)``, but computed separably (rows,
    then columns) by doubling: after j steps each entry holds the maximum of 2^j consecutive
    samples, and two overlapping power-of-two windows cover any width. That is a few
    element-wise maxima per pixel instead of (2r+1)² comparisons: ~20× faster than
    ``max_pool2d`` for r = 4 on the CPU.
    """
    if radius == 0:
        return x
    torch = import_torch()
    F = torch.nn.functional
    k = 2 * radius + 1
    for dim, pad in ((3, (radius, radius, 0, 0)), (2, (0, 0, radius, radius))):
        n = x.shape[dim]
        cur = F.pad(x, pad, value=float("-inf"))
        span = 1
        while 2 * span <= k:
            m = cur.shape[dim]
            cur = torch.maximum(cur.narrow(dim, 0, m - span), cur.narrow(dim, span, m - span))
            span *= 2
        x = torch.maximum(cur.narrow(dim, 0, n), cur.narrow(dim, k - span, n))
    return x
