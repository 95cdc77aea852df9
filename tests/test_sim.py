"""Simulator tests: writer → loader round trip with the hand-eye chain, determinism, the hdr
profile defeating frames but not events, trajectories from files, the CLI."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import PAUSE_S, shared_path

import dhptam
from dhptam import SE3, _core
from dhptam.cli import main
from dhptam.datasets import load_tumvie
from dhptam.errors import InputError, ParseError
from dhptam.frontend import EVENT_BORDER_PX
from dhptam.sim import (
    GROUND_TRUTH_FILE,
    IMU_FROM_MARKER,
    PRESETS,
    RIGS,
    lighting_segments,
    load_photos,
    simulate,
    simulator_for,
)
from dhptam.sim.simulate import _paused

HDR_DURATION_S = 2.0


@pytest.fixture(scope="module")
def hdr_sequence(tmp_path_factory: pytest.TempPathFactory):
    """One 2 s HDR desk sequence at the tiny rig size, shared by the tests below."""
    out = tmp_path_factory.mktemp("sim")
    return simulate(out, preset="tiny", duration_s=HDR_DURATION_S, seed=3)


def _pose(row: np.ndarray) -> SE3:
    return SE3.from_translation_quat_xyzw(row[:3], row[3:])


def _pose_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Translation [m] and rotation [rad] between two x y z qx qy qz qw rows."""
    delta = _pose(a).inverse() @ _pose(b)
    return float(np.linalg.norm(delta.translation)), delta.rotation.angle()


def _expected_world_from_cam(t_ns: np.ndarray, duration_ns: int) -> np.ndarray:
    """The left frame camera's pose, recomputed from the built-in trajectory by SE(3)
    interpolation of its 1 kHz samples and the rig's imu_from_cam (independent of the files)."""
    traj_t, traj_poses = _core.sim_builtin_trajectory("desk_spiral", duration_ns)
    imu_from_cam = RIGS["tiny"].imu_from_cam()["frame_left"]
    rows = []
    for t in t_ns:
        i = int(np.searchsorted(traj_t, t, side="right"))
        i = min(max(i, 1), len(traj_t) - 1)
        s = (t - traj_t[i - 1]) / (traj_t[i] - traj_t[i - 1])
        body = _pose(traj_poses[i - 1]).interpolate(_pose(traj_poses[i]), float(s))
        cam = body @ imu_from_cam
        rows.append(np.concatenate([cam.translation, cam.rotation.quat_xyzw()]))
    return np.array(rows)


def test_round_trip_through_the_tumvie_loader_with_the_hand_eye_chain(hdr_sequence):
    summary = hdr_sequence
    with load_tumvie(summary.path) as seq:
        assert len(seq.frames) == summary.frames == int(HDR_DURATION_S * 20)
        assert np.array_equal(seq.frames.t_ns, np.arange(summary.frames) * 50_000_000)
        assert np.all(seq.frames.exposure_ns >= 1_000_000) and np.all(seq.frames.exposure_ns <= 20_000_000)
        pair = seq.frames[5]
        assert pair.left.shape == (128, 128) and pair.left.dtype == np.uint8
        for side, count in (("left", summary.events_left), ("right", summary.events_right)):
            window = seq.events[side].window(0, summary.duration_ns + 1)
            assert len(window.t_ns) == count > 10_000
            assert np.all(np.diff(window.t_ns) >= 0)
            assert window.x.max() < 128 and window.y.max() < 72
            assert set(np.unique(window.p).tolist()) == {0, 1}
        assert seq.calibration.cameras["event_left"].width == 128

        # Ground truth comes from mocap_data.txt (marker poses) through the hand-eye chain
        # world_from_cam = world_from_marker · inv(imu_from_marker) · imu_from_cam.
        gt = seq.ground_truth
        assert gt is not None and len(gt) == int(HDR_DURATION_S * 120) + 1
        expected = _expected_world_from_cam(gt.t_ns, summary.duration_ns)
        for row, want in zip(gt.world_from_cam, expected, strict=True):
            dt, dr = _pose_error(row, want)
            assert dt < 1e-9 and dr < 1e-9
        # Without the chain (marker poses taken as camera poses) the error is centimetres.
        marker = gt.world_from_cam[10]
        wrong = (_pose(marker) @ IMU_FROM_MARKER).translation
        assert np.linalg.norm(wrong - expected[10][:3]) > 0.05

    # The TUM ground-truth file: seconds, x y z qx qy qz qw, the same camera.
    table = np.loadtxt(summary.path / GROUND_TRUTH_FILE)
    t_ns = np.round(table[:, 0] * 1e9).astype(np.int64)
    assert np.array_equal(t_ns, np.arange(0, summary.duration_ns + 1, 5_000_000))
    expected = _expected_world_from_cam(t_ns[::7], summary.duration_ns)
    for row, want in zip(table[::7, 1:], expected, strict=True):
        dt, dr = _pose_error(row, want)
        assert dt < 1e-8 and dr < 1e-8


def _fast_corners(image: np.ndarray) -> int:
    return len(cv2.FastFeatureDetector_create(threshold=15).detect(image))


def test_hdr_profile_defeats_frames_while_event_rates_stay_informative(hdr_sequence):
    summary = hdr_sequence
    duration = summary.duration_ns
    segments = _core.sim_profile_segments("hdr")
    with load_tumvie(summary.path) as seq:
        mids = seq.frames.t_mid_ns / duration
        corners = np.array([_fast_corners(pair.left) for pair in seq.frames])
        means = np.array([pair.left.mean() for pair in seq.frames])

        def frames_in(label: str) -> np.ndarray:
            return np.concatenate(
                [np.nonzero((mids >= a) & (mids < b))[0] for name, a, b in segments if name == label]
            )

        normal, dark, bright = frames_in("normal"), frames_in("dark"), frames_in("bright")
        # The first frames let auto-exposure settle.
        normal = normal[normal >= 3]
        assert len(normal) >= 5 and len(dark) >= 5 and len(bright) >= 2
        # Frames: features collapse in the dark (even at the longest exposure) and the bright
        # segment saturates (even at the shortest).
        assert np.median(corners[normal]) >= 20
        assert np.median(corners[dark]) <= 0.1 * np.median(corners[normal])
        assert np.median(means[dark]) < 20
        assert np.median(means[bright]) > 200
        assert np.median(corners[bright]) <= 0.3 * np.median(corners[normal])

        # Events: the dark segment fires at a rate comparable to normal light, far above what
        # background activity alone could produce there.
        def rate(label: str) -> float:
            count, span = 0, 0.0
            for name, a, b in segments:
                if name == label:
                    t0, t1 = int(a * duration), int(b * duration)
                    count += len(seq.events["left"].window(t0, t1).t_ns)
                    span += (t1 - t0) * 1e-9
            return count / span

        normal_rate, dark_rate = rate("normal"), rate("dark")
        assert dark_rate > 0.3 * normal_rate, (dark_rate, normal_rate)
        # Expected background activity in the dark, from the pixels' true intensities.
        assert dark_rate > 3 * _expected_noise_rate(duration, segments), dark_rate


def _expected_noise_rate(duration_ns: int, segments: list[tuple[str, float, float]]) -> float:
    """Background events/s of event_left over the dark segment: Σ_pixels r·min(30, √(I_ref/I))."""
    config = dhptam.Config().to_dict()["sim"]
    rig = RIGS["tiny"]
    cams, imu = rig.cameras(), rig.imu_from_cam()
    keys = ("frame_left", "frame_right", "event_left", "event_right")
    t, poses = _core.sim_builtin_trajectory("desk_spiral", duration_ns)
    # The same scene as the fixture's sequence (photos, procedural textures from seed 3).
    photos = load_photos()
    sim = _core.Simulator(
        [cams[k] for k in keys], [imu[k] for k in keys], photos, t, poses, "hdr", duration_ns, 3
    )
    (a, b) = next((a, b) for name, a, b in segments if name == "dark")
    rates = []
    for s in np.linspace(a, b, 5):
        t_ns = int(s * duration_ns)
        intensity = sim.illumination(t_ns) * sim.render(2, t_ns).astype(np.float64)
        gain = np.minimum(30.0, np.sqrt(config["noise_reference_intensity"] / np.maximum(intensity, 1e-12)))
        rates.append(config["noise_rate_hz"] * gain.sum())
    return float(np.mean(rates))


def test_same_seed_gives_identical_output_and_another_seed_does_not(tmp_path: Path):
    runs = {}
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        summary = simulate(tmp_path, preset="tiny", name=name, duration_s=0.25, seed=seed, profile="normal")
        with load_tumvie(summary.path) as seq:
            window = seq.events["left"].window(0, summary.duration_ns + 1)
            runs[name] = (
                [pair.left.copy() for pair in seq.frames],
                window.x.copy(),
                window.t_ns.copy(),
                window.p.copy(),
            )
    a, b, c = runs["a"], runs["b"], runs["c"]
    assert all(np.array_equal(x, y) for x, y in zip(a[0], b[0], strict=True))
    assert all(np.array_equal(x, y) for x, y in zip(a[1:], b[1:], strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(a[0], c[0], strict=True))
    assert not (len(a[2]) == len(c[2]) and np.array_equal(a[2], c[2]))


def test_rendered_radiance_is_finite_and_textured_for_every_camera():
    rig = RIGS["tiny"]
    cams, imu = rig.cameras(), rig.imu_from_cam()
    keys = ("frame_left", "frame_right", "event_left", "event_right")
    t, poses = _core.sim_builtin_trajectory("closed_loop", 1_000_000_000)
    sim = _core.Simulator([cams[k] for k in keys], [imu[k] for k in keys], [], t, poses, "normal", 10**9, 0)
    for index, key in enumerate(keys):
        image = sim.render(index, 400_000_000)
        assert image.shape == (cams[key].height, cams[key].width) and image.dtype == np.float32
        assert np.all(np.isfinite(image)) and image.min() > 0.0 and image.std() > 0.05


def test_file_trajectories_are_fitted_into_the_room(tmp_path: Path):
    region_min, region_max = np.array([-1.4, -1.4, 0.95]), np.array([1.4, 0.6, 1.8])
    for name in ("ecd_poster_6dof.csv", "esim_quadrotor_circles.csv"):
        t, poses = _core.sim_file_trajectory(str(shared_path("data", "trajectories", name)), "csv")
        assert t[0] == 0 and np.all(np.diff(t) > 0)
        assert np.all(poses[:, :3] >= region_min - 1e-9) and np.all(poses[:, :3] <= region_max + 1e-9)
    # A TUM file (seconds) gives the same motion as the CSV it was converted from.
    csv_path = shared_path("data", "trajectories", "esim_quadrotor_circles.csv")
    rows = np.loadtxt(csv_path, delimiter=",", comments="#")[:200]
    tum = tmp_path / "traj.txt"
    np.savetxt(tum, np.column_stack([rows[:, 0] * 1e-9, rows[:, 1:]]), fmt="%.9f")
    csv_small = tmp_path / "traj.csv"
    np.savetxt(csv_small, rows, delimiter=",", fmt=["%d"] + ["%.14f"] * 7)
    t_tum, p_tum = _core.sim_file_trajectory(str(tum), "tum")
    t_csv, p_csv = _core.sim_file_trajectory(str(csv_small), "csv")
    assert np.abs(t_tum - t_csv).max() <= 1 and np.abs(p_tum - p_csv).max() < 1e-6
    bad = tmp_path / "bad.txt"
    bad.write_text("# t x y z qx qy qz qw\n0 0 0 0 0 0 0 1\n0.1 0 0 zero 0 0 0 1\n")
    with pytest.raises(ParseError) as err:
        _core.sim_file_trajectory(str(bad), "tum")
    assert err.value.line == 3 and err.value.path == str(bad)


def test_a_pause_holds_the_camera_still_and_shifts_the_rest_of_the_motion(sim_tiny_pause: Path) -> None:
    """``simulate(pause=(start, duration))``: the ground truth stays at the pose of the last
    trajectory sample before ``start`` for ``duration`` seconds, and from then on is the
    unpaused motion ``duration`` later."""
    (start, duration), ns = PAUSE_S, 1e9
    truth = np.loadtxt(sim_tiny_pause / GROUND_TRUTH_FILE)
    t = truth[:, 0]
    still = truth[(t >= start) & (t < start + duration - 0.005)]  # the held sample may precede start
    assert len(still) >= 9 and np.abs(still[:, 1:] - still[0, 1:]).max() < 1e-9
    trajectory = str(shared_path("data", "trajectories", "ecd_poster_6dof.csv"))
    unpaused = simulator_for("tiny-mixed", duration_s=1.3, trajectory=trajectory)
    after = t > start + duration + 0.01
    t_ns = np.round((t[after] - duration) * ns).astype(np.int64)
    assert after.sum() >= 5 and np.allclose(unpaused.world_from_cam(0, t_ns), truth[after, 1:], atol=1e-6)
    before = t < start - 0.01
    t_ns = np.round(t[before] * ns).astype(np.int64)
    assert np.allclose(unpaused.world_from_cam(0, t_ns), truth[before, 1:], atol=1e-8)
    # The samples: the held one repeated after the pause, the later ones shifted; a pause
    # past the last sample changes nothing.
    t_s, poses = np.array([0, 10, 20, 30]), np.arange(28.0).reshape(4, 7)
    t2, p2 = _paused(t_s, poses, (15, 115))
    assert t2.tolist() == [0, 10, 110, 120, 130] and np.array_equal(p2[[1, 2]], poses[[1, 1]])
    assert _paused(t_s, poses, (40, 50))[0] is t_s


def test_simulator_for_rebuilds_the_simulator_that_wrote_a_sequence(tmp_path: Path):
    trajectory = str(shared_path("data", "trajectories", "esim_quadrotor_circles.csv"))
    summary = simulate(tmp_path, preset="tiny", duration_s=0.3, seed=4, trajectory=trajectory)
    sim = simulator_for("tiny", seed=4, duration_s=0.3, trajectory=trajectory)
    other = simulator_for("tiny", seed=4, duration_s=0.3)
    with load_tumvie(summary.path) as seq:
        first = seq.frames[0]
    # The first frame pair (later ones depend on the auto-exposure's history) up to the JPEG
    # compression of the written images; the built-in motion sees another view.
    for simulator, most, least in ((sim, 3.0, 0.0), (other, np.inf, 15.0)):
        _, left, right = simulator.frame_pair(first.t_ns)
        for image, written in ((left, first.left), (right, first.right)):
            assert least <= np.abs(image.astype(np.float64) - written).mean() <= most
    truth = np.loadtxt(summary.path / GROUND_TRUTH_FILE)
    t_ns = np.round(truth[:, 0] * 1e9).astype(np.int64)
    assert np.allclose(sim.world_from_cam(0, t_ns), truth[:, 1:], atol=1e-8)
    assert not np.allclose(other.world_from_cam(0, t_ns), truth[:, 1:], atol=1e-3)
    with pytest.raises(InputError, match="preset"):
        simulator_for("nope")


def test_bad_arguments_raise_input_errors(tmp_path: Path):
    with pytest.raises(InputError, match="preset"):
        simulate(tmp_path, preset="nope")
    with pytest.raises(InputError, match="profile"):
        simulate(tmp_path, preset="tiny", profile="disco")
    with pytest.raises(InputError, match="trajectory"):
        simulate(tmp_path, preset="tiny", trajectory="no_such_motion")


def test_cli_lists_presets_and_simulates(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    help_text = capsys.readouterr().out
    assert all(name in help_text for name in PRESETS) and "--profile" in help_text
    code = main(
        [
            "simulate",
            "--preset",
            "tiny",
            "--out",
            str(tmp_path),
            "--duration",
            "0.1",
            "--seed",
            "2",
            "--quiet",
        ]
    )
    assert code == 0
    assert "2 frame pairs" in capsys.readouterr().out
    assert (tmp_path / "tiny" / "tiny-events_left.h5").exists()
    # An existing sequence is not overwritten without --overwrite.
    code = main(["simulate", "--preset", "tiny", "--out", str(tmp_path), "--duration", "0.1", "--quiet"])
    assert code == 2


def test_mixed_camera_models_round_trip(tmp_path: Path):
    summary = simulate(tmp_path, preset="tiny-mixed", duration_s=0.1, seed=1)
    with load_tumvie(summary.path) as seq:
        models = {k: cam.model for k, cam in seq.calibration.cameras.items()}
        assert models == {
            "frame_left": "radtan",
            "frame_right": "radtan",
            "event_left": "pinhole",
            "event_right": "pinhole",
        }
        expected = RIGS["tiny-mixed"].cameras()
        for key, cam in seq.calibration.cameras.items():
            assert np.allclose(cam.params, expected[key].params)
        assert len(seq.frames) == 2 and seq.frames[1].left.std() > 5


def test_a_shared_sensor_rig_reads_frames_and_events_from_the_same_pixels(tmp_path: Path):
    """The DAVIS-like rigs (MVSEC's kind of sensor): each event camera is its frame camera, so
    the front-end's event→frame warp is the identity, the event images need no disparity
    correction, and a run goes through end to end."""
    from dhptam.frontend import Frontend
    from dhptam.run import run

    assert not RIGS["tiny"].shared_sensor and RIGS["davis"].shared_sensor
    assert PRESETS["davis-hdr"].rig == "davis"
    summary = simulate(tmp_path, preset="tiny-davis", duration_s=0.3, seed=1)
    with load_tumvie(summary.path) as seq:
        cams = seq.calibration.cameras
        for side in ("left", "right"):
            frame, event = cams[f"frame_{side}"], cams[f"event_{side}"]
            assert (event.model, event.width, event.height) == (frame.model, 128, 96) == ("kb4", 128, 96)
            assert np.array_equal(event.params, frame.params)
            pose_f = seq.calibration.imu_from_cam[f"frame_{side}"].matrix()
            pose_e = seq.calibration.imu_from_cam[f"event_{side}"].matrix()
            assert np.allclose(pose_f, pose_e, atol=1e-12)
        fe = Frontend(seq, "fusion", prefetch=0)
        pixels = np.array([[10.0, 20.0], [64.0, 48.0], [120.5, 90.25]])
        for depth in (0.0, 0.7, 3.0):
            assert np.allclose(fe.warp_event_pixels("left", pixels, depth_m=depth), pixels, atol=1e-6)
            assert np.allclose(fe.warp_event_pixels("right", pixels, depth_m=depth), pixels, atol=1e-6)
        assert fe.event_disparity(2.0) == (1.0, 0.0)
        frame = fe.process(3)
        assert frame.left.shape == (96, 128) and frame.events_left is not None
        assert frame.events_left.shape[:2] == (96, 128)
        # Mode events stays in these shared pixels under [fusion] events_geometry = "auto"
        # (the default); "event" still tracks the same pixels with the detectors' border.
        events = Frontend(seq, "events", prefetch=0)
        assert events.shares_frame_pixels and not events.tracks_event_cameras
        assert events.tracked_calibration == events.calibration
        forced = Frontend(seq, "events", _core.Config.from_toml('[fusion]\nevents_geometry = "event"\n'))
        assert forced.tracks_event_cameras and forced.tracked_calibration.width == 128 + 2 * EVENT_BORDER_PX
    result = run(
        summary.path, tmp_path / "out", mode="fusion", features="orb", progress=False, threaded=False
    )
    assert result.frames == 6 and (tmp_path / "out" / "trajectory.tum").is_file()


def test_hot_pixels_add_their_periodic_events_and_leave_the_scene_events_alone(tmp_path: Path) -> None:
    from dhptam.sim import HotPixelSource

    clean = simulate(tmp_path, preset="tiny", duration_s=0.3, seed=4, name="clean")
    hot = simulate(tmp_path, preset="tiny", duration_s=0.3, seed=4, name="hot", hot_pixels=0.01)
    width, height = RIGS["tiny"].event_size
    with load_tumvie(clean.path) as a, load_tumvie(hot.path) as b:
        for side in ("left", "right"):
            source = HotPixelSource(width, height, 0.01, 4, side)
            assert len(source) == round(0.01 * width * height)
            t0, t1 = 0, clean.duration_ns
            ea, eb = a.events[side].window(t0, t1 + 1), b.events[side].window(t0, t1 + 1)
            hx, hy, ht, _ = source.events(t0, t1)
            assert len(eb) == len(ea) + len(ht) and len(ht) > 0
            # The stream is the clean one plus the hot pixels' events (as multisets of
            # (µs, x, y)), sorted by time.
            assert np.all(np.diff(eb.t_ns) >= 0)
            expected = np.concatenate(
                [np.stack([ea.t_ns // 1000, ea.x, ea.y], axis=1), np.stack([ht // 1000, hx, hy], axis=1)]
            ).astype(np.int64)
            got = np.stack([eb.t_ns // 1000, eb.x, eb.y], axis=1).astype(np.int64)
            assert np.array_equal(expected[np.lexsort(expected.T[::-1])], got[np.lexsort(got.T[::-1])])
            # Each hot pixel fires at its own rate, 20 Hz to 2 kHz.
            rates = 1e9 / source.period_ns
            assert rates.min() >= 20.0 - 1e-6 and rates.max() <= 2000.0 + 1e-6
            busiest = int(np.argmax(rates))
            fired = np.count_nonzero((hx == source.x[busiest]) & (hy == source.y[busiest]))
            assert abs(fired - rates[busiest] * 0.3) <= 1
    # Split spans give the events of the whole span, once each.
    source = HotPixelSource(width, height, 0.01, 4, "left")
    whole = source.events(0, 300_000_000)[2]
    parts = np.concatenate([source.events(k * 50_000_000, (k + 1) * 50_000_000)[2] for k in range(6)])
    assert np.array_equal(np.sort(whole), np.sort(parts))
    with pytest.raises(InputError, match="hot_pixels"):
        simulate(tmp_path, preset="tiny", duration_s=0.1, name="bad", hot_pixels=0.5)


def test_lighting_segments_put_the_profile_on_the_sequence_clock(sim_tiny: Path) -> None:
    """The spans lit at one level, in nanoseconds of a sequence of the given duration, in
    time order, the ramps between levels in none of them; bad input names its field. Every
    simulated sequence carries its own as ``lighting.csv``."""
    from dhptam.eval import read_segments

    assert read_segments(sim_tiny / "lighting.csv") == lighting_segments("hdr", 1.0)
    assert lighting_segments("normal", 2.0) == [("normal", 0, 2_000_000_000)]
    hdr = lighting_segments("hdr", 10.0)
    assert [label for label, _, _ in hdr] == ["normal", "dark", "normal", "bright", "normal"]
    assert hdr[0][1] == 0 and hdr[-1][2] == 10_000_000_000
    ends = [t for _, start, end in hdr for t in (start, end)]
    assert all(a < b for a, b in zip(ends[1:-1:2], ends[2::2], strict=True)), "ramps between spans"
    assert [(s * 4, e * 4) for _, s, e in lighting_segments("hdr", 2.5)] == [(s, e) for _, s, e in hdr]
    with pytest.raises(InputError, match="profile"):
        lighting_segments("sunny", 1.0)
    with pytest.raises(InputError, match="duration"):
        lighting_segments("hdr", 0.0)
