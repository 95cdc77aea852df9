"""The event→frame warp depth from the tracked map points (``[fusion] warp_depth``, issue 8)."""

from __future__ import annotations

import csv
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import dhptam
from dhptam import _core
from dhptam.datasets import load_tumvie
from dhptam.frontend import Frontend
from dhptam.run import _DepthFeed, run
from dhptam.sim import simulator_for


def _frames_csv(out: Path) -> list[dict[str, str]]:
    with open(out / "frames.csv", newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def _edge_distances(seq: Any, fe: Frontend, sim: _core.Simulator, index: int, depth_m: float) -> Any:
    """Pixel distances, in the rectified left frame camera, between the event pixels of frame
    ``index``'s window warped through the plane at ``depth_m`` and the frame pixels of the same
    3-D points (the simulator's depth of the left event camera)."""
    calib = seq.calibration
    t0, t1 = fe.window_ns(index)
    raw = seq.events["left"].window(t0, t1)
    pixels = np.unique(np.c_[np.asarray(raw.x), np.asarray(raw.y)].astype(np.int64), axis=0)[::3]
    z = sim.render_depth(2, int(fe.t_f_ns[index]))[pixels[:, 1], pixels[:, 0]].astype(np.float64)
    bearings = calib.cameras["event_left"].unproject(pixels.astype(np.float64))
    p_event = bearings * (z / bearings[:, 2])[:, None]
    p_frame = calib.cam_from_cam("frame_left", "event_left") @ p_event
    truth = fe.frame_rect.rectify_pixels("left", calib.cameras["frame_left"].project(p_frame))
    rect_e = fe.event_rect.rectify_pixels("left", pixels.astype(np.float64))
    ok = np.isfinite(truth).all(axis=1) & np.isfinite(rect_e).all(axis=1) & (z > 0)
    warped = fe.warp_event_pixels("left", rect_e[ok], depth_m=depth_m)
    return np.linalg.norm(warped - truth[ok], axis=1)


def test_tracked_warp_depth_puts_event_edges_closer_to_frame_edges_than_infinity(
    sim_desk_run: Path, tmp_path: Path
) -> None:
    """A run with ``warp_depth = "tracked"`` records per frame the depth it warped through: the
    configured plane (infinity) for the first frame, then the median depth of the map points the
    frame before was tracked with. That depth is the scene's, and the event pixels warped through
    it land nearer the frame pixels of the same 3-D points than through infinity."""
    config = _core.Config.from_toml('[fusion]\nwarp_depth = "tracked"')
    result = run(sim_desk_run, tmp_path, mode="fusion", config=config, progress=False, threaded=False)
    rows = _frames_csv(tmp_path)
    assert result.frames == len(rows) == 24
    depths = [float(r["warp_depth_m"]) for r in rows]
    assert depths[0] == 0.0  # nothing tracked yet: the configured plane, at infinity
    assert all(d > 0.0 for d in depths[1:]), depths
    sim = simulator_for("desk", seed=1, duration_s=1.2)
    with load_tumvie(sim_desk_run) as seq:
        fe = Frontend(seq, "fusion", prefetch=0)
        checked = 0
        for k in range(2, len(rows), 4):
            z = sim.render_depth(0, int(fe.t_f_ns[k]))
            true_median = float(np.median(z[np.isfinite(z) & (z > 0)]))
            # The depth is the scene's: its parallax within 1 px of the true median depth's
            # (measured 2026-11-27: 0.07-0.49 px; infinity is 2.8-3.1 px off here).
            off_px = abs(fe.warp_parallax_px / depths[k] - fe.warp_parallax_px / true_median)
            assert off_px < 1.0, (k, depths[k], true_median)
            tracked = _edge_distances(seq, fe, sim, k, depths[k])
            infinity = _edge_distances(seq, fe, sim, k, 0.0)
            assert len(tracked) > 100
            # Measured 2026-11-27 (frames 2-22): median 0.28-0.61 px against 2.70-2.88 px.
            assert np.median(tracked) < 0.5 * np.median(infinity), (
                k,
                np.median(tracked),
                np.median(infinity),
            )
            checked += 1
        assert checked >= 5
        # The frame images really are warped through the recorded depth.
        frame = fe.finish(fe.prepare(5), depths[5])
        assert frame.warp_depth_m == depths[5]
        assert not np.array_equal(frame.events_left, fe.finish(fe.prepare(5), 0.0).events_left)


def test_plane_warp_depth_is_recorded_as_the_configured_plane(sim_desk_run: Path, tmp_path: Path) -> None:
    config = _core.Config.from_toml('[fusion]\nwarp_depth = "plane"\nplane_depth_m = 2.5')
    run(sim_desk_run, tmp_path, mode="fusion", config=config, progress=False, threaded=False, max_frames=6)
    assert [float(r["warp_depth_m"]) for r in _frames_csv(tmp_path)] == [2.5] * 6


def test_bad_warp_depth_settings_are_config_errors() -> None:
    with pytest.raises(dhptam.ConfigError, match=r"fusion\.warp_depth"):
        _core.Config.from_toml('[fusion]\nwarp_depth = "nearest"')
    with pytest.raises(dhptam.ConfigError, match=r"fusion\.warp_depth_step_px"):
        _core.Config.from_toml("[fusion]\nwarp_depth_step_px = -1.0")
    assert _core.Config().to_dict()["fusion"]["warp_depth"] == "plane"  # chosen by measurement


def test_quantised_depth_rounds_inverse_depth_to_bins_of_parallax(sim_tiny: Path) -> None:
    with load_tumvie(sim_tiny) as seq:
        fe = Frontend(seq, "fusion", prefetch=0)
        parallax = fe.warp_parallax_px  # px · m
        assert 0.5 < parallax < 50.0, parallax  # a few cm at a few hundred pixels of focal length
        step = fe.warp_depth_step_px
        assert fe.quantised_depth(None) == fe.plane_depth_m == 0.0
        assert fe.quantised_depth(float("nan")) == 0.0
        assert fe.quantised_depth(1e6) == 0.0  # less than half a bin of parallax: infinity
        depths = np.linspace(0.3, 6.0, 400)
        rounded = np.array([fe.quantised_depth(float(d)) for d in depths])
        # The rounding moves a warped pixel by at most half a bin of parallax ...
        moved = np.abs(parallax / depths - parallax / rounded)
        assert moved.max() <= step / 2 + 1e-9, moved.max()
        # ... and a slowly drifting depth keeps its bin (so the warp map is reused).
        assert len(np.unique(rounded)) < len(depths) / 4
        # Hysteresis: the previous frame's depth is kept while the new one is within one bin.
        current = fe.quantised_depth(2.0)
        within = 1.0 / (1.0 / current + 0.9 * step / parallax)  # 0.9 bin of parallax nearer
        beyond = 1.0 / (1.0 / current + 1.6 * step / parallax)
        assert fe.quantised_depth(within) != current  # rounds to the next bin on its own ...
        assert fe.quantised_depth(within, current) == current  # ... but is held
        assert fe.quantised_depth(beyond, current) == fe.quantised_depth(beyond) < current
        assert fe.quantised_depth(None, current) == fe.plane_depth_m  # lost: the configured plane
        fe.warp_depth_step_px = 0.0
        assert fe.quantised_depth(1.234) == 1.234
        frames = Frontend(seq, "frames", prefetch=0)
        assert frames.warp_parallax_px == 0.0
        assert frames.finish(frames.prepare(0), 1.0).warp_depth_m == 0.0


def test_depth_feed_hands_frame_k_the_depth_tracked_at_frame_k_minus_1() -> None:
    feed = _DepthFeed(start=3, tracked=True)
    assert feed.wait(3) is None  # the first frame does not wait
    got: list[float | None] = []
    waiter = threading.Thread(target=lambda: got.append(feed.wait(5)))
    waiter.start()
    feed.publish(3, 1.5)
    waiter.join(0.2)
    assert waiter.is_alive()  # frame 5 waits for frame 4
    feed.publish(4, 2.0)
    waiter.join(5.0)
    assert got == [2.0]
    feed.publish(5, None)  # lost: the front-end falls back to the configured plane
    assert feed.wait(6) is None
    feed.close()
    with pytest.raises(RuntimeError, match="tracking loop ended"):
        feed.wait(9)
    assert _DepthFeed(start=0, tracked=False).wait(7) is None
