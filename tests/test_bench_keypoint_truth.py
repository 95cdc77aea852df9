"""`benches/bench_keypoint_truth.py` measures keypoints against the simulator's truth: its
geometry (rectified pixels → true 3-D points → the next frame) must put frame keypoints
within a pixel of their matches, or every figure it reports is wrong."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

BENCHES = Path(__file__).resolve().parents[1] / "benches"


def _bench():
    if str(BENCHES) not in sys.path:
        sys.path.insert(0, str(BENCHES))
    return importlib.import_module("bench_keypoint_truth")


def test_frame_keypoints_land_where_the_truth_carries_them(sim_small_desk: Path) -> None:
    from dhptam.sim import simulator_for

    bench = _bench()
    sim = simulator_for("desk", seed=0, duration_s=0.5)
    frames = bench.measure(sim_small_desk, sim, "frames", "orb", step=1)
    events = bench.measure(sim_small_desk, sim, "events", "orb", step=1)

    # Frame keypoints: under a pixel from where the truth carries them, right disparities.
    assert frames["pairs"] >= 5 and frames["matches"] > 200
    assert frames["median"] < 1.0, frames
    assert frames["under1"] > 0.5 and frames["over5"] < 0.05, frames
    assert frames["disparity"] < 0.8 and frames["stereo"] > 500, frames
    # The same measurement sees the event images' keypoints as less precise and fewer.
    assert events["pairs"] >= 5
    assert events["median"] > frames["median"] and events["matches"] < frames["matches"], events


def test_a_wrong_pose_shows_in_the_measurement(sim_small_desk: Path, monkeypatch) -> None:
    """With every other true pose turned by 1° (about 4 px at this focal length), the
    keypoints land that far from where the measurement carries them."""
    import numpy as np

    from dhptam._core import SO3
    from dhptam.sim import simulator_for

    bench = _bench()
    sim = simulator_for("desk", seed=0, duration_s=0.5)
    real = bench._world_from_rect
    turn = np.eye(4)
    turn[:3, :3] = np.asarray(SO3.exp([0.0, np.radians(1.0), 0.0]).matrix())

    def wrong(fe, truth, index):
        pose = real(fe, truth, index)
        return pose @ turn if index % 2 else pose

    monkeypatch.setattr(bench, "_world_from_rect", wrong)
    frames = bench.measure(sim_small_desk, sim, "frames", "orb", step=1)
    assert frames["median"] > 3.0 and frames["under1"] < 0.1, frames
