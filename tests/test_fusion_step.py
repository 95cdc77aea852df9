"""The one-pass stages of the stereo fusion step equal the stage-by-stage pipeline bit for bit.

``EventRectifier.e3ct`` (rectification inside the E3CT pass) against ``e3ct`` of
``EventRectifier.apply``; ``_core._fuse_frame`` (normalise, warp and blend per frame pixel)
against ``normalise`` → ``warp_to_frame`` → ``fuse``.
"""

from __future__ import annotations

import numpy as np
import pytest

from dhptam import SE3, SO3, _core
from dhptam.errors import InputError
from dhptam.events import e3ct, normalise
from dhptam.fusion import fuse, warp_to_frame
from dhptam.geometry import RectifiedStereo, StereoRig
from dhptam.sim.presets import RIGS

MS = 1_000_000


def _raw_window(n: int, w: int, h: int, span_ns: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span_ns // 1000, n)).astype(np.int64) * 1000
    return (
        rng.integers(0, w, n).astype(np.uint16),
        rng.integers(0, h, n).astype(np.uint16),
        t,
        rng.integers(0, 2, n).astype(np.int8),
    )


@pytest.fixture(scope="module")
def rectifier() -> _core.EventRectifier:
    rig = RIGS["tumvie"]
    cams, poses = rig.cameras(), rig.imu_from_cam()
    right_from_left = poses["event_right"].inverse() @ poses["event_left"]
    rect = RectifiedStereo(StereoRig(cams["event_left"], cams["event_right"], right_from_left))
    return _core.EventRectifier(rect, "left")


def test_rectified_e3ct_in_one_pass_equals_e3ct_of_the_rectified_events(
    rectifier: _core.EventRectifier,
) -> None:
    w, h = rectifier.raw_size
    rw, rh = rectifier.rect_size
    x, y, t, p = _raw_window(200_000, w, h, 50 * MS, 3)
    rx, ry, rt, rp = rectifier.apply(x, y, t, p, 0, 50 * MS)
    assert 0 < len(rt) < len(t)  # some events leave the rectified view
    want = e3ct(rx, ry, rt, rp, width=rw, height=rh, t_start_ns=0, t_end_ns=50 * MS)
    got = rectifier.e3ct(x, y, t, p, 0, 50 * MS)
    assert got.shape == (rh, rw, 3) and got.dtype == np.float32
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
    assert float(got.sum()) > 1000.0
    split = rectifier.e3ct(x, y, t, p, 0, 50 * MS, channels=2, polarity="split")
    assert split.shape == (rh, rw, 4)
    x[5] = w  # outside the raw image: an error naming the event, as in apply
    with pytest.raises(InputError, match="event 5"):
        rectifier.e3ct(x, y, t, p, 0, 50 * MS)


def test_one_pass_frame_fusion_equals_normalise_warp_and_blend() -> None:
    rng = np.random.default_rng(4)
    raw = np.where(rng.random((96, 128, 3)) < 0.3, rng.uniform(0, 3, (96, 128, 3)), 0).astype(np.float32)
    frame = rng.integers(0, 256, (80, 100), dtype=np.uint8)
    k_event, k_frame = [500.0, 500.0, 63.5, 47.5], [560.0, 560.0, 50.0, 40.0]
    frame_from_event = SE3(SO3.exp([0.01, -0.02, 0.005]), [0.03, 0.01, 0.0])
    (normalised,), scales = normalise(raw)
    for depth_m, align in ((1.5, (0.7, -1.2)), (0.0, (0.0, 0.0))):
        warped, _ = warp_to_frame(
            normalised,
            k_event,
            k_frame,
            frame_from_event,
            width=100,
            height=80,
            depth_m=depth_m,
            align_px=align,
        )
        for beta in (0.0, 0.35, 1.0):
            want = fuse(frame, warped, beta)
            got = _core._fuse_frame(
                frame, raw, scales, k_event, k_frame, frame_from_event, depth_m, align, beta
            )
            np.testing.assert_array_equal(got, want)
        events_only = _core._fuse_frame(
            frame, raw, scales, k_event, k_frame, frame_from_event, depth_m, align, 1.0
        )
        assert np.count_nonzero(events_only) > events_only.size // 4
    with pytest.raises(InputError, match="scales"):
        _core._fuse_frame(frame, raw, [1.0, 1.0], k_event, k_frame, frame_from_event, 1.5, (0, 0), 0.5)
