"""The SLAM back-end (dhptam.System) on synthetic stereo feature sequences."""

from __future__ import annotations

import logging
import re
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from slam_synthetic import CALIB, Frame, ate, generate

import dhptam
import dhptam.logs as dlogs
from dhptam import SE3, features


def run(frames: list[Frame], config: dhptam.Config | None = None) -> dhptam.System:
    system = dhptam.System(CALIB, config, threaded=False)
    for f in frames:
        r = system.track(f.t_ns, f.left, f.right)
        assert r.state in ("initialised", "ok"), f"frame {f.t_ns}: {r.state} ({r.inliers})"
    return system


def positions(system: dhptam.System) -> np.ndarray:
    return system.trajectory()[1][:, :3, 3]


def test_tracks_every_frame_with_noise_and_outliers() -> None:
    frames = generate(frames=200, seed=1)
    system = dhptam.System(CALIB, None, threaded=False)
    created = 0  # keyframes inserted (keyframe culling, on by default, may remove some later)
    for f in frames:
        r = system.track(f.t_ns, f.left, f.right)
        assert r.state in ("initialised", "ok"), f"frame {f.t_ns}: {r.state} ({r.inliers})"
        created += r.keyframe
    t, poses = system.trajectory()
    assert t.tolist() == [f.t_ns for f in frames]
    assert poses.shape == (200, 4, 4)
    truth = np.array([f.world_from_cam[:3, 3] for f in frames])
    error = ate(positions(system), truth)
    assert error < 0.03, error  # 0.5 px noise, 10 % outliers, half a turn of 1 m radius
    kf_t, kf_poses = system.keyframe_trajectory()
    assert 2 < len(kf_t) < 100 and kf_poses.shape == (len(kf_t), 4, 4)
    points = system.map_points()
    assert points.ndim == 2 and points.shape[1] == 3 and len(points) > 500
    # Map points lie on the landmark cylinder (4-7 m from the first camera's axis).
    timing = system.timing()
    assert timing["track"]["count"] == 200 and timing["local_ba"]["count"] == created
    assert len(kf_t) <= created
    # Duplicate fusion and re-finding run once per keyframe, before its bundle adjustment.
    assert timing["fusion"]["count"] == created


def test_written_trajectory_is_smoothed_by_each_frames_covariance() -> None:
    # 1.5 px keypoint noise: the tracked centres scatter; the smoother ([tracking] smoothing_q,
    # on by default) pulls them onto a smooth motion, orientations untouched.
    frames = generate(frames=120, turns=0.25, landmarks=1500, pixel_noise=1.5, seed=3)
    truth = np.array([f.world_from_cam[:3, 3] for f in frames])
    system = run(frames)
    t, smoothed = system.trajectory()
    t_raw, tracked = system.trajectory(smoothed=False)
    assert t.tolist() == t_raw.tolist() == [f.t_ns for f in frames]
    np.testing.assert_array_equal(smoothed[:, :3, :3], tracked[:, :3, :3])
    e_smoothed, e_tracked = ate(smoothed[:, :3, 3], truth), ate(tracked[:, :3, 3], truth)
    assert e_smoothed < 0.8 * e_tracked, (e_smoothed, e_tracked)
    # Off: the written trajectory is the tracked one.
    off = run(frames, dhptam.Config.from_toml("[tracking]\nsmoothing_q = 0"))
    np.testing.assert_array_equal(off.trajectory()[1], off.trajectory(smoothed=False)[1])
    with pytest.raises(dhptam.ConfigError, match="smoothing_q"):
        dhptam.Config.from_toml("[tracking]\nsmoothing_q = -1")


def test_a_pose_that_jumps_away_from_the_motion_model_is_rejected() -> None:
    # [tracking] max_jump_ratio: a tracked pose farther from the constant-velocity prediction
    # than that fraction of its inliers' median depth goes on to relocalisation instead. The
    # default never fires on ordinary motion; a bound of a micrometre per metre fires on every
    # frame tracked from a valid motion model, and each is relocalised (or starts a segment).
    frames = generate(frames=40, turns=0.1, landmarks=1500, seed=4)
    assert run(frames).tracking_totals()["implausible"] == 0
    strict = dhptam.System(
        CALIB, dhptam.Config.from_toml("[tracking]\nmax_jump_ratio = 1e-6"), threaded=False
    )
    states = [strict.track(f.t_ns, f.left, f.right).state for f in frames]
    totals = strict.tracking_totals()
    assert totals["implausible"] >= 30, totals
    assert totals["implausible"] == totals["relocalisations"] + totals["segments"] + states.count("lost")
    assert len(strict.trajectory()[0]) == len(frames) - states.count("lost")
    with pytest.raises(dhptam.ConfigError, match="max_jump_ratio"):
        dhptam.Config.from_toml("[tracking]\nmax_jump_ratio = -0.5")


def test_debug_log_tells_how_far_each_frame_and_keyframe_moved(caplog, monkeypatch) -> None:
    # At debug level the core logs, for each tracked frame, its camera centre's distance from
    # the motion model's prediction, and after each local bundle adjustment how far it moved
    # each keyframe's centre (the diagnostics of docs/BENCHMARKS.md, "HDR lighting on the real
    # trajectories").
    monkeypatch.delenv(dlogs.ENV_VAR, raising=False)
    levels = {name: logging.getLogger(name).level for name in dlogs.LOGGER_NAMES}
    caplog.set_level(logging.DEBUG, logger="dhptam_core")
    dlogs.configure("debug", handler=logging.NullHandler())
    try:
        frames = generate(frames=40, turns=0.1, landmarks=1500, seed=4)
        system = run(frames)
    finally:
        for name, level in levels.items():
            logging.getLogger(name).setLevel(level)
        dhptam._core._reset_log_cache()
    text = "\n".join(r.getMessage() for r in caplog.records)
    found = re.findall(r"centre ([0-9.]+) mm from the motion model's prediction", text)
    distances = [float(d) for d in found]
    # Every frame after the bootstrap, each a few millimetres off a smooth motion (metres if
    # the distance were taken from anything else, such as the world origin).
    assert len(distances) == len(frames) - 1
    assert 0.0 < np.median(distances) < 10.0, distances
    adjustments = re.findall(r"mapping: keyframe (\d+): keyframe centres moved: (.*)", text)
    keyframes = len(system.keyframe_trajectory()[0])
    assert [int(kf) for kf, _ in adjustments] == list(range(keyframes))
    entries = [m for _, ms in adjustments if ms != "none" for m in ms.split(", ")]
    moved = [re.fullmatch(r"(\d+): ([0-9.]+) mm", m) for m in entries]
    assert moved and all(m is not None and int(m[1]) < keyframes for m in moved), adjustments


def test_binary_descriptors_track() -> None:
    frames = generate(frames=60, turns=0.15, binary=True, seed=2)
    system = run(frames)
    truth = np.array([f.world_from_cam[:3, 3] for f in frames])
    assert ate(positions(system), truth) < 0.03


def test_loop_closure_halves_the_injected_drift() -> None:
    frames = generate(frames=460, turns=1.15, drift_m=0.4, drift_deg=4.0, seed=21)
    truth = np.array([f.world_from_cam[:3, 3] for f in frames])
    off = run(frames, dhptam.Config.from_toml("[loop_closing]\nenabled = false"))
    assert off.loop_closures() == []
    before = ate(positions(off), truth)
    on = run(frames)
    after = ate(positions(on), truth)
    loops = on.loop_closures()
    assert loops, "no loop detected"
    query, matched = loops[0]
    assert query > frames[300].t_ns and matched < frames[100].t_ns
    assert before > 0.04, before
    assert after <= 0.5 * before, (after, before)


def test_save_load_continue_gives_the_same_poses(tmp_path: Path) -> None:
    frames = generate(frames=100, seed=3)
    reference = dhptam.System(CALIB, threaded=False)
    expected = [reference.track(f.t_ns, f.left, f.right) for f in frames]
    first = dhptam.System(CALIB, threaded=False)
    for f in frames[:50]:
        first.track(f.t_ns, f.left, f.right)
    first.save_map(tmp_path / "map.bin")
    second = dhptam.System(CALIB, threaded=False)
    second.load_map(tmp_path / "map.bin")
    assert len(second.trajectory()[0]) == 50
    for f, e in zip(frames[50:], expected[50:], strict=True):
        r = second.track(f.t_ns, f.left, f.right)
        assert (r.state, r.keyframe) == (e.state, e.keyframe)
        np.testing.assert_allclose(r.pose, e.pose, atol=1e-9)
    with pytest.raises(dhptam.FileError, match=r"missing\.bin"):
        second.load_map(tmp_path / "missing.bin")
    (tmp_path / "junk.bin").write_bytes(b"not a map")
    with pytest.raises(dhptam.DhptamError, match=r"junk\.bin"):
        second.load_map(tmp_path / "junk.bin")


def test_threaded_stress_and_prompt_shutdown() -> None:
    frames = generate(frames=2000, turns=2.0, landmarks=700, seed=4)
    system = dhptam.System(CALIB, threaded=True)
    results: list[dhptam.TrackResult] = []
    errors: list[Exception] = []

    def feed() -> None:
        for f in frames:
            try:
                results.append(system.track(f.t_ns, f.left, f.right))
            except dhptam.DhptamError as e:  # raised once shut down
                errors.append(e)
                return

    worker = threading.Thread(target=feed)
    worker.start()
    while len(results) < 1500 and worker.is_alive():
        time.sleep(0.01)
    system.shutdown()
    worker.join(timeout=60)
    assert not worker.is_alive(), "tracking did not stop after shutdown"
    assert errors and len(results) < len(frames)
    assert all(r.state in ("initialised", "ok") for r in results)
    t, poses = system.trajectory()
    assert t.tolist() == [r.t_ns for r in results]
    assert np.all(np.isfinite(poses))
    truth = np.array([f.world_from_cam[:3, 3] for f in frames[: len(t)]])
    assert ate(poses[:, :3, 3], truth) < 0.1


def test_bad_input_is_refused_with_names() -> None:
    f = generate(frames=1, seed=5)[0]
    system = dhptam.System(CALIB, threaded=False)
    bad = type(f.left)(f.left.keypoints, f.left.descriptors.astype(np.float64))
    with pytest.raises(dhptam.InputError, match=r"left\.descriptors"):
        system.track(0, bad, f.right)
    bad = type(f.left)(f.left.keypoints[:, :1].copy(), f.left.descriptors)
    with pytest.raises(dhptam.InputError, match=r"left\.keypoints"):
        system.track(0, bad, f.right)
    short = type(f.left)(f.left.keypoints[:-1].copy(), f.left.descriptors)
    with pytest.raises(dhptam.InputError, match=r"left\.keypoints"):
        system.track(0, short, f.right)
    with pytest.raises(dhptam.InputError, match="baseline"):
        dhptam.System(dhptam.StereoCalibration(400, 400, 320, 240, -0.1, 640, 480))
    system.track(0, f.left, f.right)
    binary = type(f.left)(f.left.keypoints, np.zeros((len(f.left.keypoints), 32), np.uint8))
    with pytest.raises(dhptam.InputError, match="descriptors"):
        system.track(1, binary, f.right)


def _heteroscedastic(seed: int, frames: int = 80) -> list[tuple[Frame, features.Features]]:
    """Frames whose left keypoints have 0.3 px noise, except a random half with 3 px more
    along x; each keypoint's σ says which (0.3 or 3 px)."""
    rng = np.random.default_rng(100 + seed)
    out = []
    for f in generate(frames=frames, turns=0.2, seed=seed, pixel_noise=0.3, outliers=0.0):
        kp = f.left.keypoints.copy()
        vague = rng.random(len(kp)) < 0.5
        kp[vague, 0] += 3.0 * rng.standard_normal(int(vague.sum()))
        sigmas = np.where(vague, 3.0, 0.3).astype(np.float32)
        scores = np.zeros(len(kp), np.float32)
        out.append((f, features.Features(np.ascontiguousarray(kp), scores, f.left.descriptors, sigmas)))
    return out


def test_keypoint_sigmas_weigh_tracking_and_mapping(tmp_path: Path) -> None:
    frames = _heteroscedastic(seed=3)
    truth = np.array([f.world_from_cam[:3, 3] for f, _ in frames])
    errors = {}
    for mode in ("octave", "unit"):
        config = dhptam.Config.from_toml(f'[tracking]\nkeypoint_sigma = "{mode}"')
        system = dhptam.System(CALIB, config, threaded=False)
        for f, left in frames:
            assert system.track(f.t_ns, left, f.right).state in ("initialised", "ok")
        errors[mode] = ate(positions(system), truth)
    # Weighting by 1/σ trusts the precise half: measured 1.9 mm against 5.3 mm.
    assert errors["octave"] < 0.6 * errors["unit"], errors
    # "unit" is the old behaviour: the same poses as the same keypoints without σ.
    unit = dhptam.System(
        CALIB, dhptam.Config.from_toml('[tracking]\nkeypoint_sigma = "unit"'), threaded=False
    )
    plain = dhptam.System(CALIB, threaded=False)
    for f, left in frames[:30]:
        r = unit.track(f.t_ns, left, f.right)
        p = plain.track(f.t_ns, type(f.left)(left.keypoints, left.descriptors), f.right)
        np.testing.assert_array_equal(r.pose, p.pose)
    # The σ travel with the keyframes through a saved map (format version 3 on).
    octave = dhptam.Config.from_toml('[tracking]\nkeypoint_sigma = "octave"')
    reference = dhptam.System(CALIB, octave, threaded=False)
    expected = [reference.track(f.t_ns, left, f.right) for f, left in frames[:40]]
    first = dhptam.System(CALIB, octave, threaded=False)
    for f, left in frames[:20]:
        first.track(f.t_ns, left, f.right)
    first.save_map(tmp_path / "map.bin")
    second = dhptam.System(CALIB, octave, threaded=False)
    second.load_map(tmp_path / "map.bin")
    for (f, left), e in zip(frames[20:40], expected[20:], strict=True):
        np.testing.assert_allclose(second.track(f.t_ns, left, f.right).pose, e.pose, atol=1e-9)


def test_bad_keypoint_sigmas_are_refused_with_names() -> None:
    f = generate(frames=1, seed=5)[0]
    system = dhptam.System(CALIB, threaded=False)
    n = len(f.left.keypoints)
    with_nan = np.ones(n, np.float32)
    with_nan[5] = np.nan
    for bad, name in (
        (np.ones(n - 1, np.float32), "left.sigmas"),
        (np.zeros(n, np.float32), "left.sigmas[0]"),
        (with_nan, "left.sigmas[5]"),
    ):
        with pytest.raises(dhptam.InputError, match=re.escape(name)):
            system._core.track(
                0, f.left.keypoints, f.left.descriptors, f.right.keypoints, f.right.descriptors, bad
            )
    for scale in (0.0, -1.0, float("nan")):
        with pytest.raises(dhptam.InputError, match=re.escape("left.sigma_scale")):
            system.track(0, f.left, f.right, sigma_scale=scale)
    for disparity in ((0.0, 0.0), (-1.0, 0.0), (1.0, float("inf"))):
        with pytest.raises(dhptam.InputError, match=re.escape("left.disparity")):
            system.track(0, f.left, f.right, disparity=disparity)
    # A viewpoint is (x, y, z) in metres, finite; nothing is tracked when it is not.
    with pytest.raises(dhptam.InputError, match=re.escape("viewpoint")):
        system.track(0, f.left, f.right, viewpoint=(0.0, 0.03))
    with pytest.raises(dhptam.InputError, match=re.escape("left.viewpoint[1]")):
        system.track(0, f.left, f.right, viewpoint=(0.0, float("nan"), 0.0))
    assert system.trajectory()[0].size == 0


def _switch_appearance(frames: list[Frame], at: int, seed: int = 7) -> list[Frame]:
    """From frame ``at`` on, every descriptor is turned by one fixed random rotation, as when
    the fusion swaps frame-dominated for event-dominated images: landmarks stay recognisable
    among the new frames (distances between them are kept) but not against the old map."""
    dim = frames[0].left.descriptors.shape[1]
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(dim, dim)))

    def turned(v: Any) -> Any:
        d = np.ascontiguousarray(np.asarray(v.descriptors, np.float64) @ q.T, dtype=np.float32)
        return type(v)(v.keypoints, d)

    return frames[:at] + [
        Frame(f.t_ns, f.world_from_cam, turned(f.left), turned(f.right)) for f in frames[at:]
    ]


def test_an_abrupt_change_of_appearance_starts_a_new_map_segment_and_tracking_goes_on() -> None:
    frames = _switch_appearance(generate(frames=80, seed=3), at=40)
    truth = np.array([f.world_from_cam[:3, 3] for f in frames])
    system = dhptam.System(CALIB, None, threaded=False)
    states = [system.track(f.t_ns, f.left, f.right).state for f in frames]
    assert "lost" not in states
    assert states[40] == "initialised", states[35:45]
    t, _ = system.trajectory()
    assert len(t) == 80
    assert ate(positions(system), truth) < 0.05
    # Without re-initialisation the same sequence is lost after the switch.
    off = dhptam.System(CALIB, dhptam.Config.from_toml("[tracking]\nreinitialise = false"), threaded=False)
    states_off = [off.track(f.t_ns, f.left, f.right).state for f in frames]
    assert states_off[41:].count("lost") > 30, states_off[40:]


# -- bridge keyframes across appearance switches (issue 8, accuracy) ----------------------------


def test_bridge_keyframes_keep_one_map_across_an_appearance_switch() -> None:
    """Frames 40-59 look the other way. Entering, the last normal frame is bridged to its
    other rendering; leaving, the first normal frame is tracked with its other rendering and
    bridged to its own: no new map segment, one covisible map, the ATE of an unswitched run."""
    plain = generate(frames=80, seed=3)
    other = _switch_appearance(plain, at=0)  # every frame rendered the other way
    truth = np.array([f.world_from_cam[:3, 3] for f in plain])
    system = dhptam.System(CALIB, None, threaded=False)
    states = []
    bridges = []
    for i, (f, g) in enumerate(zip(plain, other, strict=True)):
        if i == 60:
            states.append(system.track(g.t_ns, g.left, g.right).state)
            bridges.append(system.bridge(f.t_ns, (g.left, g.right), (f.left, f.right)))
            continue
        seen = g if 40 <= i < 60 else f
        states.append(system.track(seen.t_ns, seen.left, seen.right).state)
        if i == 39:
            bridges.append(system.bridge(f.t_ns, (f.left, f.right), (g.left, g.right)))
    assert all(b is not None and b.linked >= 50 and b.other_points >= 50 for b in bridges), bridges
    assert states[1:].count("initialised") == 0, states
    assert "lost" not in states
    totals = system.tracking_totals()
    assert totals == {
        "bridges": 2,
        "bridges_refused": 0,
        "segments": 0,
        "relocalisations": 0,
        "predicted": 0,
        "held": 0,
        "implausible": 0,
    }
    assert ate(positions(system), truth) < 0.03
    # The same switches without bridges start two new segments.
    off = dhptam.System(CALIB, None, threaded=False)
    for i, (f, g) in enumerate(zip(plain, other, strict=True)):
        seen = g if 40 <= i < 60 else f
        off.track(seen.t_ns, seen.left, seen.right)
    assert off.tracking_totals()["segments"] == 2


def test_bridge_is_refused_unless_it_is_the_last_tracked_frame() -> None:
    frames = generate(frames=4, seed=5)
    system = dhptam.System(CALIB, None, threaded=False)
    f0 = frames[0]
    assert system.bridge(f0.t_ns, (f0.left, f0.right), (f0.left, f0.right)) is None  # nothing tracked
    for f in frames[:3]:
        system.track(f.t_ns, f.left, f.right)
    assert system.bridge(frames[1].t_ns, (f0.left, f0.right), (f0.left, f0.right)) is None
    assert system.tracking_totals()["bridges_refused"] == 2
    bad = type(f0.left)(np.zeros((3, 3), np.float32), f0.left.descriptors[:3])
    with pytest.raises(dhptam.DhptamError, match="keypoints"):
        system.bridge(frames[2].t_ns, (bad, f0.right), (f0.left, f0.right))


# -- predicted frames across illumination floods (issue 8, accuracy) ----------------------------


def test_predicted_frames_extrapolate_the_motion_and_leave_the_map_alone(tmp_path: Path) -> None:
    frames = generate(frames=120, seed=1)
    truth = np.array([f.world_from_cam[:3, 3] for f in frames])
    # The placement of predicted frames as tracked: the trajectory smoother off.
    unsmoothed = dhptam.Config.from_toml("[tracking]\nsmoothing_q = 0")
    system = dhptam.System(CALIB, unsmoothed, threaded=False)
    first = system.predict(frames[0].t_ns)
    assert first.state == "lost" and len(system.trajectory()[0]) == 0  # nothing to predict from
    for f in frames[:60]:
        system.track(f.t_ns, f.left, f.right)
    keyframes, points = len(system.keyframe_trajectory()[0]), len(system.map_points())
    predicted = [system.predict(f.t_ns) for f in frames[60:63]]
    assert [r.state for r in predicted] == ["predicted"] * 3
    assert all(r.inliers == 0 and not r.keyframe for r in predicted)
    assert (len(system.keyframe_trajectory()[0]), len(system.map_points())) == (keyframes, points)
    # Each predicted pose is the last tracked one moved on by the mean motion of the last
    # `[tracking] predict_velocity_frames` (4) steps, (cam_from_world(59) world_from_cam(55))^(1/4).
    t, poses = system.trajectory()
    assert t.tolist() == [f.t_ns for f in frames[:63]]
    assert all(np.allclose(poses[60 + k], r.pose) for k, r in enumerate(predicted))
    step = SE3.exp(SE3.from_matrix(np.linalg.inv(poses[59]) @ poses[55]).log() / 4.0).matrix()
    for k in range(3):
        expected = poses[59] @ np.linalg.matrix_power(np.linalg.inv(step), k + 1)
        assert np.allclose(poses[60 + k], expected, atol=1e-9), k
    # Tracking resumes against the map after the predicted frames; the camera moves along a
    # circle at a constant rate, so the predicted frames keep the ATE of a fully tracked run.
    states = [system.track(f.t_ns, f.left, f.right).state for f in frames[63:]]
    assert states == ["ok"] * len(states), states
    assert system.tracking_totals()["predicted"] == 3
    assert ate(positions(system), truth) < 0.03
    # Once frame 63 is measured, the written trajectory places the predicted frames on the
    # geodesic between frames 59 and 63, by time, instead of the extrapolation.
    t, poses = system.trajectory()
    between = SE3.from_matrix(np.linalg.inv(poses[59]) @ poses[63]).log()
    for k in range(60, 63):
        s = (t[k] - t[59]) / (t[63] - t[59])
        assert np.allclose(poses[k], poses[59] @ SE3.exp(s * between).matrix(), atol=1e-9), k
    assert not np.allclose(poses[62], predicted[2].pose, atol=1e-6)
    # The predicted flags travel through a saved map (format version 5) ...
    system.save_map(tmp_path / "map.bin")
    loaded = dhptam.System(CALIB, unsmoothed, threaded=False)
    loaded.load_map(tmp_path / "map.bin")
    assert np.allclose(loaded.trajectory()[1], poses, atol=1e-12)
    # ... and a version-3 map (the same file without them) reads every record as measured:
    # the stored predictions come back (moved with their keyframe by bundle adjustment since
    # they were made, by under a millimetre here). A record is t (8), keyframe (8), pose (56),
    # the predicted flag (1), the covariance flag (1) and, when set, the covariance's upper
    # triangle (48); the records follow their count, the segment-start count and ids (none
    # here) follow them.
    data = bytearray((tmp_path / "map.bin").read_bytes())
    n = len(t)
    assert int.from_bytes(data[8:12], "little") == 5 and data[-8:] == bytes(8)
    start = data.index(n.to_bytes(8, "little") + int(t[0]).to_bytes(8, "little")) + 8
    records, at, with_covariance = [], start, 0
    for _ in range(n):
        records.append(bytes(data[at : at + 72]))
        with_covariance += data[at + 73]
        at += 74 + 48 * data[at + 73]
    assert at == len(data) - 8 and with_covariance > n // 2, (at, len(data), with_covariance)
    v3 = data[:8] + (3).to_bytes(4, "little") + data[12:start] + b"".join(records) + data[-8:]
    (tmp_path / "v3.bin").write_bytes(bytes(v3))
    old = dhptam.System(CALIB, unsmoothed, threaded=False)
    old.load_map(tmp_path / "v3.bin")
    old_poses = old.trajectory()[1]
    assert np.allclose(old_poses[60:63], [r.pose for r in predicted], atol=2e-3)
    assert not np.allclose(old_poses[62], poses[62], atol=1e-6)
    assert np.allclose(
        np.delete(old_poses, [60, 61, 62], axis=0), np.delete(poses, [60, 61, 62], axis=0), atol=1e-12
    )


def test_quiet_frames_that_cannot_be_tracked_are_held_at_rest() -> None:
    """Issue 8: a camera at rest in front of event cameras sees sensor noise, whose features
    stereo-match by chance but match nothing else. Flagged ``quiet``, such frames keep the
    last pose (state ``held``) and the camera moving on is tracked against the same map;
    unflagged, each starts a new map segment of noise points."""
    frames = generate(frames=80, seed=3)
    stop, rest = 39, 8
    period = frames[1].t_ns - frames[0].t_ns
    rng = np.random.default_rng(5)

    def noise(k: int) -> Frame:
        # Frame 39's view at a later time, its descriptors turned by a fresh random rotation
        # (the same in both views): stereo pairs match, nothing matches across frames.
        q, _ = np.linalg.qr(rng.normal(size=(frames[0].left.descriptors.shape[1],) * 2))
        f = frames[stop]

        def turned(v: Any) -> Any:
            return type(v)(v.keypoints, np.ascontiguousarray(np.asarray(v.descriptors) @ q.T, np.float32))

        return Frame(f.t_ns + k * period, f.world_from_cam, turned(f.left), turned(f.right))

    at_rest = [noise(k) for k in range(1, rest + 1)]
    moving = [Frame(f.t_ns + rest * period, f.world_from_cam, f.left, f.right) for f in frames[stop + 1 :]]

    def play(quiet: bool) -> tuple[dhptam.System, list[Any]]:
        system = dhptam.System(CALIB, None, threaded=False)
        results = [system.track(f.t_ns, f.left, f.right) for f in frames[: stop + 1]]
        results += [system.track(f.t_ns, f.left, f.right, quiet=quiet) for f in at_rest]
        results += [system.track(f.t_ns, f.left, f.right) for f in moving]
        return system, results

    system, results = play(True)
    states = [r.state for r in results]
    assert states[stop + 1 : stop + 1 + rest] == ["held"] * rest, states
    held = results[stop + 1 : stop + 1 + rest]
    assert all(np.allclose(r.pose, results[stop].pose, atol=1e-9) for r in held)
    assert states[stop + 1 + rest :] == ["ok"] * len(moving), states
    totals = system.tracking_totals()
    assert (totals["held"], totals["segments"], totals["relocalisations"]) == (rest, 0, 0), totals
    truth = np.array([f.world_from_cam[:3, 3] for f in frames[: stop + 1] + at_rest + moving])
    assert ate(positions(system), truth) < 0.03
    plain, results = play(False)
    assert plain.tracking_totals()["segments"] >= 2, [r.state for r in results]


def test_a_bridge_spans_predicted_frames_between_two_appearances() -> None:
    """Frames 40-42 are a flood (predicted), frames 43-59 look the other way. The bridge from
    the last tracked frame (39) is inserted after the flood, at frame 39's pose: one map, no
    new segment, the ATE of an unswitched run; without the bridge a new segment starts."""
    plain = generate(frames=80, seed=3)
    other = _switch_appearance(plain, at=0)
    truth = np.array([f.world_from_cam[:3, 3] for f in plain])

    def run_with_flood(bridge: bool) -> tuple[dhptam.System, list[str], list[Any]]:
        system = dhptam.System(CALIB, None, threaded=False)
        states: list[str] = []
        bridges: list[Any] = []
        for i, (f, g) in enumerate(zip(plain, other, strict=True)):
            if 40 <= i < 43:
                states.append(system.predict(f.t_ns).state)
                continue
            if i == 43 and bridge:
                bridges.append(system.bridge(plain[39].t_ns, (plain[39].left, plain[39].right),
                                             (other[39].left, other[39].right)))  # fmt: skip
            if i == 60 and bridge:
                states.append(system.track(g.t_ns, g.left, g.right).state)
                bridges.append(system.bridge(f.t_ns, (g.left, g.right), (f.left, f.right)))
                continue
            seen = g if 43 <= i < 60 else f
            states.append(system.track(seen.t_ns, seen.left, seen.right).state)
        return system, states, bridges

    system, states, bridges = run_with_flood(True)
    assert all(b is not None and b.linked >= 50 for b in bridges), bridges
    assert states[40:43] == ["predicted"] * 3
    assert states[1:].count("initialised") == 0 and "lost" not in states, states
    totals = system.tracking_totals()
    assert totals == {
        "bridges": 2,
        "bridges_refused": 0,
        "segments": 0,
        "relocalisations": 0,
        "predicted": 3,
        "held": 0,
        "implausible": 0,
    }
    assert len(system.trajectory()[0]) == 80
    assert ate(positions(system), truth) < 0.03
    # The bridge keyframe sits at frame 39's pose, not at the last predicted frame's (three
    # steps of about 4 cm on).
    kf_t, kf_poses = system.keyframe_trajectory()
    _, poses = system.trajectory()
    bridge_position = kf_poses[kf_t.tolist().index(plain[39].t_ns)][:3, 3]
    assert np.linalg.norm(bridge_position - poses[39][:3, 3]) < 0.005
    assert np.linalg.norm(bridge_position - poses[42][:3, 3]) > 0.05
    # A bridge from a frame before the last measured one is refused.
    assert (
        system.bridge(plain[50].t_ns, (plain[50].left, plain[50].right), (other[50].left, other[50].right))
        is None
    )
    off, _, _ = run_with_flood(False)
    assert off.tracking_totals()["segments"] >= 1
