"""Tracking loss through ``dhptam.run`` (issue 10): a 1 s blackout of frames and events (lens
covered) and a violent shake, on simulated desk sequences with exact ground truth.

The system must come back after the loss, by relocalising against the map or by starting a
new map segment, and the final trajectory must cover the sequence outside the loss.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from dhptam.eval import evaluate, load_trajectory
from dhptam.run import run
from dhptam.sim import simulate
from dhptam.sim.simulate import shake_offsets
from dhptam.trajectory import read_tum

_NS = 1_000_000_000
BLACKOUT = (1.0, 1.0)  # start, duration [s]
SHAKE = (1.0, 0.8)


@pytest.fixture(scope="module")
def blackout_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 s of the desk preset (320-pixel frames, normal light) with the lenses covered over
    [1 s, 2 s)."""
    return simulate(
        tmp_path_factory.mktemp("loss"),
        preset="desk",
        name="blackout",
        duration_s=3.0,
        seed=3,
        blackout=BLACKOUT,
    ).path


@pytest.fixture(scope="module")
def shake_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2.4 s of the desk preset with a violent shake over [1 s, 1.8 s)."""
    return simulate(
        tmp_path_factory.mktemp("loss"), preset="desk", name="shake", duration_s=2.4, seed=4, shake=SHAKE
    ).path


def _frames_csv(out: Path) -> tuple[np.ndarray, list[str]]:
    rows = (out / "frames.csv").read_text().splitlines()
    header = rows[0].split(",")
    cells = [r.split(",") for r in rows[1:]]
    t_s = np.array([float(c[header.index("t_s")]) for c in cells])
    return t_s, [c[header.index("state")] for c in cells]


def test_the_blackout_is_black_and_silent(blackout_sequence: Path) -> None:
    """The simulator option itself: no event and only black frames inside the span."""
    from dhptam.datasets import load_tumvie

    start, end = (round(v * _NS) for v in (BLACKOUT[0], BLACKOUT[0] + BLACKOUT[1]))
    for side in ("left", "right"):
        with h5py.File(blackout_sequence / f"blackout-events_{side}.h5", "r") as f:
            t_us = f["events/t"][:]
        assert not np.any((t_us * 1000 >= start) & (t_us * 1000 < end))
        assert np.any(t_us * 1000 < start) and np.any(t_us * 1000 >= end)
    with load_tumvie(blackout_sequence) as seq:
        for k in range(len(seq.frames)):
            pair = seq.frames[k]
            inside = start <= pair.t_ns < end
            assert (pair.left.max() == 0 and pair.right.max() == 0) == inside, k


def test_shake_offsets_are_violent_and_vanish_outside_the_span() -> None:
    t = np.linspace(0.0, SHAKE[1], 2001)
    w = shake_offsets(t, SHAKE[1])
    assert np.abs(w[[0, -1]]).max() < 1e-9
    angle = np.linalg.norm(w[:, :3], axis=1)
    assert angle.max() > 0.3  # rad
    rate = np.linalg.norm(np.diff(w[:, :3], axis=0), axis=1).max() / (t[1] - t[0])
    assert rate > 15.0  # rad/s
    assert np.abs(w[:, 3:]).max() > 0.02  # m


@pytest.mark.parametrize("mode", ["frames", "fusion"])
def test_tracking_comes_back_after_a_one_second_blackout(
    blackout_sequence: Path, tmp_path: Path, mode: str
) -> None:
    result = run(blackout_sequence, tmp_path, mode=mode, features="orb", progress=False, threaded=False)
    t_s, states = _frames_csv(tmp_path)
    before = t_s < BLACKOUT[0]
    after = t_s >= BLACKOUT[0] + BLACKOUT[1]
    lost = np.array([s == "lost" for s in states])
    assert result.frames == len(t_s) == 60
    # Tracking is lost in the dark and comes back soon after the lens is uncovered.
    assert lost[~before & ~after].mean() > 0.8, states
    assert not lost[before].any(), states
    assert lost[after].sum() <= 3, states
    # The trajectory covers every frame outside the blackout that was tracked, in one frame.
    traj_t, _ = read_tum(tmp_path / "trajectory_frame_left.tum")
    outside = (traj_t < BLACKOUT[0] * _NS) | (traj_t >= (BLACKOUT[0] + BLACKOUT[1]) * _NS)
    assert outside.sum() >= 0.9 * (before.sum() + after.sum())
    ev = evaluate(
        load_trajectory(tmp_path / "trajectory_frame_left.tum"),
        load_trajectory(blackout_sequence / "groundtruth_frame_left.txt"),
    )
    # One SE(3) alignment for before and after: a segment left in its own frame (not merged)
    # would be off by the drift of the constant-velocity guess over 1 s (tens of cm).
    assert ev.ate_rmse_m < 0.05, ev.to_dict()


@pytest.mark.parametrize("mode", ["frames", "fusion"])
def test_tracking_survives_a_violent_shake(shake_sequence: Path, tmp_path: Path, mode: str) -> None:
    result = run(shake_sequence, tmp_path, mode=mode, features="orb", progress=False, threaded=False)
    t_s, states = _frames_csv(tmp_path)
    outside = (t_s < SHAKE[0]) | (t_s >= SHAKE[0] + SHAKE[1] + 0.2)
    lost = np.array([s == "lost" for s in states])
    assert result.frames == len(t_s) == 48
    assert lost[outside].sum() <= 3, states
    ev = evaluate(
        load_trajectory(tmp_path / "trajectory_frame_left.tum"),
        load_trajectory(shake_sequence / "groundtruth_frame_left.txt"),
    )
    assert ev.coverage > 0.9
    # Measured (seed 4, ORB, synchronous, 2-core box): ATE 6.3 cm in fusion mode, under 5 cm in
    # frames mode; a tracker that lost the map through the shake is off by decimetres.
    assert ev.ate_rmse_m < 0.10, ev.to_dict()
