"""Classical extractors through OpenCV, needing no weights and no torch: ORB and SIFT.

* ORB: oriented FAST corners on an 8-level pyramid (scale 1.2) with rotated BRIEF, binary
  descriptors of 32 bytes compared by Hamming distance; the score is OpenCV's Harris response.
* SIFT: difference-of-Gaussians keypoints with 128-D gradient histograms, L2-normalised to unit
  rows (distances in [0, 2], like the learned descriptors); the score is the DoG response.

Keypoints come from OpenCV with sub-pixel positions (SIFT interpolates its extrema; ORB's
positions at coarser pyramid levels are scaled back), already in the pixel-centre convention
used by dhptam. Each keypoint's location noise ``sigmas`` is the pixel size of the pyramid
level it was found at: ORB ``1.2^octave``, SIFT ``2^octave`` (octave −1, the doubled image,
counted as 1 px: upsampling adds no information). At most ``max_keypoints`` are kept, best
score first. The two images of a stereo pair are processed one after the other (OpenCV
parallelises inside each call).
"""

from __future__ import annotations

import abc
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ..errors import InputError
from .base import Extractor, Features

__all__ = ["ORB", "SIFT"]


class _OpenCVExtractor(Extractor):
    def __init__(self, max_keypoints: int, threads: int | None) -> None:
        super().__init__(max_keypoints)
        if threads is not None and int(threads) < 0:
            raise InputError(
                f"threads: expected 0 (OpenCV's default) or a positive count, got {threads}", field="threads"
            )
        if threads:
            cv2.setNumThreads(int(threads))
        self._detector = self._create()

    @abc.abstractmethod
    def _create(self) -> Any:
        """The OpenCV detector-descriptor object (ORB or SIFT) this extractor runs."""

    def _descriptors(self, raw: npt.NDArray[Any]) -> npt.NDArray[Any]:
        return raw

    @abc.abstractmethod
    def _sigmas(self, keypoints: Any) -> npt.NDArray[np.float32]:
        """Location noise (pixels) of OpenCV keypoints, from the pyramid level of each."""

    def _extract_single(self, image: npt.NDArray[np.uint8]) -> Features:
        keypoints, raw = self._detector.detectAndCompute(image, None)
        if raw is None or len(keypoints) == 0:
            return Features.empty(self.descriptor_width, binary=self.binary)
        xy = np.array([kp.pt for kp in keypoints], dtype=np.float32).reshape(-1, 2)
        scores = np.array([kp.response for kp in keypoints], dtype=np.float32)
        order = np.argsort(-scores, kind="stable")[: self.max_keypoints]
        descriptors = self._descriptors(raw[order])
        sigmas = self._sigmas(keypoints)[order]
        return Features(
            np.ascontiguousarray(xy[order]),
            np.ascontiguousarray(scores[order]),
            descriptors,
            np.ascontiguousarray(sigmas),
        )

    def _extract_pair(
        self, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8]
    ) -> tuple[Features, Features]:
        return self._extract_single(left), self._extract_single(right)


class ORB(_OpenCVExtractor):
    """OpenCV ORB: (N, 32) uint8 binary descriptors."""

    name = "orb"
    descriptor_width = 32
    binary = True

    def __init__(
        self,
        *,
        max_keypoints: int = 1000,
        threads: int | None = None,
        fast_threshold: int = 20,
        levels: int = 8,
    ) -> None:
        self.fast_threshold = int(fast_threshold)
        self.levels = int(levels)
        super().__init__(max_keypoints, threads)

    #: Ratio between ORB's pyramid levels (OpenCV's default, used at creation).
    scale_factor = 1.2

    def _create(self) -> Any:
        return cv2.ORB_create(
            nfeatures=self.max_keypoints,
            scaleFactor=self.scale_factor,
            nlevels=self.levels,
            fastThreshold=self.fast_threshold,
        )

    def _sigmas(self, keypoints: Any) -> npt.NDArray[np.float32]:
        octave = np.array([kp.octave for kp in keypoints], dtype=np.float32)
        return np.power(np.float32(self.scale_factor), octave).astype(np.float32)

    def _descriptors(self, raw: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
        return np.ascontiguousarray(raw, dtype=np.uint8)


class SIFT(_OpenCVExtractor):
    """OpenCV SIFT: (N, 128) float32 unit-norm descriptors."""

    name = "sift"
    descriptor_width = 128

    def __init__(
        self, *, max_keypoints: int = 1000, threads: int | None = None, contrast_threshold: float = 0.04
    ) -> None:
        self.contrast_threshold = float(contrast_threshold)
        super().__init__(max_keypoints, threads)

    def _create(self) -> Any:
        return cv2.SIFT_create(nfeatures=self.max_keypoints, contrastThreshold=self.contrast_threshold)

    def _sigmas(self, keypoints: Any) -> npt.NDArray[np.float32]:
        # OpenCV packs the octave into the low byte as a signed number (−1: doubled image).
        octave = np.array([kp.octave & 255 for kp in keypoints], dtype=np.int32)
        octave = np.where(octave >= 128, octave - 256, octave)
        return np.power(np.float32(2.0), np.maximum(octave, 0)).astype(np.float32)

    def _descriptors(self, raw: npt.NDArray[Any]) -> npt.NDArray[np.float32]:
        d = np.asarray(raw, dtype=np.float32)
        norms = np.linalg.norm(d, axis=1, keepdims=True)
        return np.ascontiguousarray(d / np.maximum(norms, 1e-12), dtype=np.float32)
