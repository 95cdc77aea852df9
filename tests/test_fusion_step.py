"""The stereo fusion step's fused stages equal the stage-by-stage pipeline bit for bit.

``warp_to_frame(raw, scales=...)`` (each bilinear tap normalised inside the warp, the warp's
inverse map computed once and reused) against ``normalise`` → ``warp_to_frame``, and
``warp_and_fuse`` (the blend inside the warp) against ``warp_to_frame`` → ``fuse``.
"""

from __future__ import annotations

import numpy as np
import pytest

from dhptam import SE3, SO3
from dhptam.errors import InputError
from dhptam.events import normalise, shared_scales
from dhptam.fusion import fuse, warp_and_fuse, warp_to_frame

K_EVENT, K_FRAME = [500.0, 500.0, 63.5, 47.5], [560.0, 560.0, 90.0, 70.0]
FRAME_FROM_EVENT = SE3(SO3.exp([0.01, -0.02, 0.005]), [0.03, 0.01, 0.0])


def _raw(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.where(rng.random((96, 128, 3)) < 0.3, rng.uniform(0, 3, (96, 128, 3)), 0).astype(np.float32)


def _warp(image: np.ndarray, depth_m: float, align: tuple[float, float], **kw: object) -> np.ndarray:
    out, _ = warp_to_frame(
        image,
        K_EVENT,
        K_FRAME,
        FRAME_FROM_EVENT,
        width=180,
        height=140,
        depth_m=depth_m,
        align_px=align,
        **kw,
    )
    return out


def test_warp_with_scales_equals_warp_of_the_normalised_tensor() -> None:
    left, right = _raw(4), _raw(5)
    (n_left, _), scales = normalise(left, right)
    np.testing.assert_array_equal(shared_scales(left, right), scales)
    for depth_m, align in ((1.5, (0.7, -1.2)), (0.0, (0.0, 0.0)), (1.5, (0.7, -1.2))):
        want = _warp(n_left, depth_m, align)
        got = _warp(left, depth_m, align, scales=scales)
        assert got.shape == (140, 180, 3) and got.dtype == np.float32
        np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
        # Events show through, some raw values exceed their scale (clipped), and frame
        # pixels beyond the event image stay 0.
        assert np.count_nonzero(got) > got.size // 6
        assert (left > scales).any() and float(got.max()) <= 1.0
        assert not got[0].any() and not got[:, 0].any()
    # The cached map of one warp is not reused for another: a different plane moves pixels.
    assert not np.array_equal(
        _warp(left, 1.5, (0.7, -1.2), scales=scales), _warp(left, 0.4, (0.7, -1.2), scales=scales)
    )


def test_warp_with_bad_scales_is_an_input_error() -> None:
    raw = _raw(6)
    with pytest.raises(InputError, match="scales"):
        _warp(raw, 1.5, (0.0, 0.0), scales=[1.0, 1.0])
    with pytest.raises(InputError, match=r"scales\[1\]"):
        _warp(raw, 1.5, (0.0, 0.0), scales=[1.0, 0.0, 1.0])


def test_warp_and_fuse_equals_warp_then_fuse() -> None:
    left, right = _raw(7), _raw(8)
    scales = shared_scales(left, right)
    frame = np.random.default_rng(9).integers(0, 256, (140, 180), dtype=np.uint8)
    for depth_m, align in ((1.5, (0.7, -1.2)), (0.0, (0.0, 0.0))):
        want = _warp(left, depth_m, align, scales=scales)
        for beta in (0.0, 0.37, 1.0):
            warped, fused = warp_and_fuse(
                left,
                K_EVENT,
                K_FRAME,
                FRAME_FROM_EVENT,
                frame,
                beta,
                depth_m=depth_m,
                align_px=align,
                scales=scales,
            )
            np.testing.assert_array_equal(warped.view(np.uint32), want.view(np.uint32))
            assert fused.shape == (140, 180) and fused.dtype == np.uint8
            np.testing.assert_array_equal(fused, fuse(frame, want, beta))
        # The frame's size is the warp's output size.
        small, _ = warp_and_fuse(left, K_EVENT, K_FRAME, FRAME_FROM_EVENT, frame[:100, :120], 0.5)
        assert small.shape == (100, 120, 3)
        # β = 1: the event intensity alone, black beyond the event image.
        assert fused.max() > 200 and not fused[0].any()
    with pytest.raises(InputError, match="beta"):
        warp_and_fuse(left, K_EVENT, K_FRAME, FRAME_FROM_EVENT, frame, 1.5, scales=scales)
