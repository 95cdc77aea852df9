"""The per-frame front-end (dhptam.frontend) on a simulated HDR sequence."""

from __future__ import annotations

import itertools
import re
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import PAUSE_S

from dhptam import SE3, SO3, _core
from dhptam.datasets import load_tumvie
from dhptam.errors import ConfigError, InputError
from dhptam.events import Activity
from dhptam.frontend import EVENT_BORDER_PX, MODES, Frontend, _exposed_like, is_flood, is_noise, is_quiet
from dhptam.fusion import choose_beta
from dhptam.sim import simulator_for

_NS = 1_000_000_000
# Mode events with its images warped into the frame cameras, as the fusion mode's are (the
# default tracks them in the event cameras themselves).
WARPED_EVENTS = 'events_geometry = "frame"\n'


@pytest.fixture
def sequence(sim_tiny: Path):  # type: ignore[no-untyped-def]
    with load_tumvie(sim_tiny) as seq:
        yield seq


def _frontend_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name in ("dhptam-frontend", "dhptam-reader")]


@pytest.mark.parametrize("mode", MODES)
def test_images_have_the_rectified_size_and_the_mode_beta(sequence, mode: str) -> None:  # type: ignore[no-untyped-def]
    fe = Frontend(sequence, mode, stop=4)
    calib = fe.tracked_calibration  # the images' camera: in mode events the event cameras
    frames = list(fe)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for f in frames:
        assert f.t_ns == int(sequence.frames.t_mid_ns[f.index])
        for image in (f.left, f.right):
            assert image.shape == (calib.height, calib.width)
            assert image.dtype == np.uint8
        for image in (f.frame_left, f.frame_right):
            assert image.shape == (fe.calibration.height, fe.calibration.width)
            assert image.dtype == np.uint8
        if mode == "frames":
            assert (f.beta_left, f.beta_right, f.bias) == (0.0, 0.0, "frames")
            assert np.array_equal(f.left, f.frame_left)
            assert f.e3ct_stats is None
        elif mode == "events":
            assert (f.beta_left, f.bias) == (1.0, "events")
            assert f.events_left is not None
            assert f.events_left.shape == (calib.height, calib.width, 3)
            intensity = np.round(255.0 * f.events_left.max(axis=2)).astype(np.uint8)
            assert np.abs(f.left.astype(int) - intensity).max() <= 1
        else:
            assert f.bias in ("aps", "dvs")
            assert 0.0 <= f.beta_left <= 1.0
    if mode != "frames":
        # Window k is [t_f^(k-1), t_f^k), frame 0's as long as frame 1's.
        stats = [f.e3ct_stats for f in frames]
        assert stats[1] is not None and stats[0] is not None
        assert stats[1].window_start_ns == frames[0].t_ns
        assert stats[0].window_end_ns - stats[0].window_start_ns == frames[1].t_ns - frames[0].t_ns
        assert stats[2] is not None and 0 < stats[2].rectified_left <= stats[2].events_left


def test_calibration_and_rect_from_cam_describe_the_rectified_left_camera(sequence) -> None:  # type: ignore[no-untyped-def]
    fe = Frontend(sequence, "frames")
    fx, fy, cx, cy, baseline, width, height = fe.calibration
    assert (width, height) == (fe.frame_rect.width, fe.frame_rect.height)
    assert baseline == pytest.approx(0.1, abs=2e-3)  # the rig's frame cameras are 10 cm apart
    cam = sequence.calibration.cameras["frame_left"]
    p_cam = np.array([[0.1, -0.05, 1.5], [-0.3, 0.2, 2.5]])
    # A point seen by the left frame camera lands, through rect_from_cam and the rectified K,
    # where the rectification table sends its raw pixel.
    p_rect = fe.rect_from_cam @ p_cam
    uv = np.c_[fx * p_rect[:, 0] / p_rect[:, 2] + cx, fy * p_rect[:, 1] / p_rect[:, 2] + cy]
    expected = fe.frame_rect.rectify_pixels("left", cam.project(p_cam))
    assert np.allclose(uv, expected, atol=1e-6)
    # Poses of the rectified camera map back: the camera's origin and axes seen from the world.
    world_from_rect = SE3(SO3.exp([0.1, 0.2, -0.3]), [1.0, 2.0, 3.0]).matrix()
    world_from_cam = fe.camera_poses(world_from_rect[None])[0]
    assert np.allclose(
        world_from_cam[:3, :3] @ p_cam[0] + world_from_cam[:3, 3],
        world_from_rect[:3, :3] @ p_rect[0] + world_from_rect[:3, 3],
    )


def test_events_mode_tracks_in_the_event_cameras_and_maps_poses_to_the_frame_camera(sequence) -> None:  # type: ignore[no-untyped-def]
    fe = Frontend(sequence, "events", prefetch=0)
    # The tiny rig's event cameras are sensors of their own: "auto" (the default) tracks them.
    assert fe.events_geometry == "auto" and not fe.shares_frame_pixels
    assert fe.tracks_event_cameras and not fe.warps_events
    pad = EVENT_BORDER_PX
    fx, fy, cx, cy, baseline, width, height = fe.tracked_calibration
    k = fe.event_rect.K
    assert (fx, fy, cx, cy) == pytest.approx((k[0, 0], k[1, 1], k[0, 2] + pad, k[1, 2] + pad))
    assert (width, height) == (fe.event_rect.width + 2 * pad, fe.event_rect.height + 2 * pad)
    assert baseline == pytest.approx(fe.event_rect.baseline_m)
    # No warp: nothing to correct in the disparities, no depth to warp through.
    assert fe.event_disparity(2.0) == (1.0, 0.0) and fe.event_stereo(2.0) is None
    # The image is the normalised E3CT in its own pixels, inside a black border.
    prepared = fe.prepare(2)
    f = fe.finish(prepared, 1.5)
    assert f.warp_depth_m == 0.0 and f.events_left is not None
    assert f.left.shape == (height, width)
    inner = (slice(pad, height - pad), slice(pad, width - pad))
    assert prepared.tensors is not None and prepared.stats is not None
    scales = np.asarray(prepared.stats.scales, np.float32)
    normalised = np.clip(prepared.tensors[0] / scales, 0.0, 1.0)
    np.testing.assert_allclose(f.events_left[inner], normalised, atol=1e-6)
    border = np.ones((height, width), bool)
    border[inner] = False
    assert f.left[border].max() == 0 and f.left[inner].max() > 0
    # Geometry: a point the left frame camera sees lands, through the tracked camera's pose
    # and intrinsics, where the event camera's rectification sends its raw event pixel.
    calib = sequence.calibration
    p_cam = np.array([[0.1, -0.05, 1.5], [-0.3, 0.2, 2.5]])
    p_tracked = (fe.tracked_from_rect @ fe.rect_from_cam) @ p_cam
    uv = np.c_[fx * p_tracked[:, 0] / p_tracked[:, 2] + cx, fy * p_tracked[:, 1] / p_tracked[:, 2] + cy]
    p_event = calib.cam_from_cam("event_left", "frame_left") @ p_cam
    raw = calib.cameras["event_left"].project(p_event)
    np.testing.assert_allclose(uv, fe.event_rect.rectify_pixels("left", raw) + pad, atol=1e-6)
    # A tracked pose maps to the left frame camera's.
    world_from_tracked = SE3(SO3.exp([0.1, 0.2, -0.3]), [1.0, 2.0, 3.0]).matrix()
    world_from_cam = fe.camera_poses(world_from_tracked[None])[0]
    assert np.allclose(
        world_from_cam[:3, :3] @ p_cam[0] + world_from_cam[:3, 3],
        world_from_tracked[:3, :3] @ p_tracked[0] + world_from_tracked[:3, 3],
    )
    # events_geometry = "frame": the event images warped into the frame cameras, as in fusion.
    warped = Frontend(sequence, "events", _core.Config.from_toml('[fusion]\nevents_geometry = "frame"\n'))
    assert not warped.tracks_event_cameras and warped.warps_events
    assert warped.tracked_calibration == warped.calibration
    assert np.allclose(warped.tracked_from_rect.matrix(), np.eye(4))
    assert warped.process(2).left.shape == (warped.calibration.height, warped.calibration.width)
    # The other modes are never tracked in the event cameras.
    assert not Frontend(sequence, "fusion").tracks_event_cameras


def test_prefetch_gives_the_synchronous_results(sequence) -> None:  # type: ignore[no-untyped-def]
    sync = list(Frontend(sequence, "fusion", prefetch=0, stop=5))
    threaded = list(Frontend(sequence, "fusion", prefetch=2, stop=5))
    assert len(sync) == len(threaded) == 5
    for a, b in zip(sync, threaded, strict=True):
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        assert (a.beta_left, a.bias) == (b.beta_left, b.bias)
    assert not _frontend_threads()


def test_reading_is_split_off_and_the_kernels_touch_no_file(
    sequence, monkeypatch: pytest.MonkeyPatch
) -> None:  # type: ignore[no-untyped-def]
    # Frontend.read(k) is the only step reading the files; prepare(read(k)) gives what
    # prepare(k) gives. From frame 3 the flood test needs earlier windows: read(3) counts them.
    start, stop = 3, 9
    direct = Frontend(sequence, "fusion", prefetch=0, start=start, stop=stop)
    expected = [direct.process(k) for k in range(start, stop)]
    split = Frontend(sequence, "fusion", prefetch=0, start=start, stop=stop)
    raws = [split.read(k) for k in range(start, stop)]
    assert [r.index for r in raws] == list(range(start, stop)) and raws[0].events is not None
    assert Frontend(sequence, "frames", prefetch=0, stop=2).read(0).events is None  # no event read

    def no_reading(*args: object, **kwargs: object) -> None:
        raise AssertionError("a file was read after Frontend.read")

    for side in ("left", "right"):
        monkeypatch.setattr(sequence.events[side], "window", no_reading)
    monkeypatch.setattr(type(sequence.frames), "__getitem__", no_reading)
    got = [split.finish(split.prepare(raw)) for raw in raws]
    for a, b in zip(expected, got, strict=True):
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        assert (a.beta_left, a.bias, a.flood, a.e3ct_stats) == (b.beta_left, b.bias, b.flood, b.e3ct_stats)


def test_worker_exceptions_reach_the_consumer_and_the_thread_is_joined(sequence) -> None:  # type: ignore[no-untyped-def]
    def counter(image: np.ndarray) -> int:
        counter.calls += 1  # type: ignore[attr-defined]
        if counter.calls == 3:  # type: ignore[attr-defined]
            raise RuntimeError("feature counter failed on purpose")
        return 500

    counter.calls = 0  # type: ignore[attr-defined]
    fe = Frontend(sequence, "fusion", prefetch=2, feature_counter=counter)
    seen: list[int] = []

    def consume() -> None:
        for f in fe:
            seen.append(f.index)

    with pytest.raises(RuntimeError, match="on purpose"):
        consume()
    assert seen == [0]  # frame 1's second counter call raised
    assert not _frontend_threads()


def test_stopping_early_joins_the_prefetch_thread(sequence) -> None:  # type: ignore[no-untyped-def]
    fe = Frontend(sequence, "fusion", prefetch=2)
    it = iter(fe)
    assert next(it).index == 0
    assert {t.name for t in _frontend_threads()} == {"dhptam-frontend", "dhptam-reader"}
    it.close()  # type: ignore[attr-defined]
    assert not _frontend_threads()


def test_bad_arguments_are_errors(sequence) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InputError, match="mode"):
        Frontend(sequence, "stereo")
    with pytest.raises(InputError, match="prefetch"):
        Frontend(sequence, prefetch=-1)


@pytest.mark.parametrize("side", ["left", "right"])
def test_event_to_frame_warp_with_true_depth_lands_on_the_same_3d_point(sequence, side: str) -> None:  # type: ignore[no-untyped-def]
    """Issue 5: with ground-truth depth and δP_align = 0, event pixels land within 0.5 px of
    the frame pixels of the same 3-D point (both in the rectified cameras)."""
    fe = Frontend(sequence, "fusion")
    sim = simulator_for("tiny")
    calib = sequence.calibration
    cam_e, cam_f = calib.cameras[f"event_{side}"], calib.cameras[f"frame_{side}"]
    t_ns = int(sequence.frames.t_mid_ns[5])
    depth = sim.render_depth(2 if side == "left" else 3, t_ns)
    v, u = np.mgrid[4 : cam_e.height - 4 : 5, 4 : cam_e.width - 4 : 5]
    raw = np.c_[u.ravel(), v.ravel()].astype(np.float64)
    z = depth[v.ravel(), u.ravel()].astype(np.float64)
    bearings = cam_e.unproject(raw)
    p_event = bearings * (z / bearings[:, 2])[:, None]
    # Truth: the 3-D point projected by the frame camera, then rectified.
    p_frame = calib.cam_from_cam(f"frame_{side}", f"event_{side}") @ p_event
    truth = fe.frame_rect.rectify_pixels(side, cam_f.project(p_frame))
    # Warp: the event pixel rectified, through the plane at the point's rectified depth.
    rect_e = fe.event_rect.rectify_pixels(side, raw)
    rotation = fe.event_rect.rect_left_from_left if side == "left" else fe.event_rect.rect_right_from_right
    z_rect = (rotation @ p_event)[:, 2]
    ok = np.isfinite(truth).all(axis=1) & np.isfinite(rect_e).all(axis=1) & np.isfinite(z_rect)
    assert ok.sum() > 100
    warped = np.array(
        [fe.warp_event_pixels(side, rect_e[i], depth_m=z_rect[i])[0] for i in np.flatnonzero(ok)]
    )
    error = np.linalg.norm(warped - truth[ok], axis=1)
    assert error.max() < 0.5, error.max()
    # The scene is 1–3 m away and the cameras a few cm apart: the warp at infinity misses by
    # about a pixel at this resolution, so the depth really mattered.
    at_infinity = np.array(
        [fe.warp_event_pixels(side, rect_e[i], depth_m=0.0)[0] for i in np.flatnonzero(ok)]
    )
    assert np.median(np.linalg.norm(at_infinity - truth[ok], axis=1)) > 0.5
    # The lookup table rounds to the nearest rectified event pixel (≤ 0.71 px there, scaled by
    # f_frame / f_event here); its median error stays under half a pixel too.
    table = fe._rectifiers[side].lookup(raw.astype(np.int64))
    ok_t = ok & np.isfinite(table).all(axis=1)
    warped_t = np.array(
        [fe.warp_event_pixels(side, table[i], depth_m=z_rect[i])[0] for i in np.flatnonzero(ok_t)]
    )
    assert np.median(np.linalg.norm(warped_t - truth[ok_t], axis=1)) < 0.5


def _orb_count(image: np.ndarray) -> int:
    # 128-pixel images: a small border and patch so that ORB can use most of the image.
    orb = cv2.ORB_create(nfeatures=2000, edgeThreshold=8, patchSize=15, fastThreshold=10)
    return len(orb.detect(image, None))


def test_hdr_beta_switches_to_dvs_in_dark_and_bright_segments_and_fusion_adds_features(sequence) -> None:  # type: ignore[no-untyped-def]
    """Issue 5: on the ``hdr`` profile β is DVS-biased in the dark and bright segments and
    APS-biased again afterwards; there the fused image has more ORB features than the frame.
    The paper's β on the frames as they come: exposure recovery off (see the next test)."""
    raw_frames = _core.Config.from_toml("[fusion]\nrecover_exposure = false\n")
    frames = list(Frontend(sequence, "fusion", raw_frames))
    duration_s = 1.0  # the tiny preset
    segments = _core.sim_profile_segments("hdr")
    checked = {"dark": 0, "bright": 0, "after": 0}
    last_normal_start = segments[-1][1] * duration_s
    for f in frames:
        t = f.t_ns / _NS
        kind = next((name for name, a, b in segments if a * duration_s <= t < b * duration_s), None)
        if kind in ("dark", "bright"):
            assert f.bias == "dvs" and f.bias_right == "dvs", (f.index, t, kind)
            assert f.beta_left >= 0.5
            fused, frame = _orb_count(f.left), _orb_count(f.frame_left)
            assert fused > frame, (f.index, kind, fused, frame)
            checked[kind] += 1
        elif t >= last_normal_start:
            assert f.bias == "aps", (f.index, t)
            assert f.beta_left <= 0.5
            checked["after"] += 1
    assert checked["dark"] >= 3 and checked["bright"] >= 2 and checked["after"] >= 2, checked


@pytest.mark.parametrize("mode", ["fusion", "frames"])
def test_dark_frames_are_stretched_before_beta_and_features_and_others_are_not(sequence, mode: str) -> None:  # type: ignore[no-untyped-def]
    """Issue 8: the dark frames of the ``hdr`` profile hold the scene in a few grey levels with
    little noise; they are stretched to full contrast (``[fusion] recover_exposure``), become
    APS-biased and give ORB many more features. Saturated frames stay DVS-biased; well-exposed
    frames are passed on untouched; a strict noise test leaves every frame as it is."""
    fe = Frontend(sequence, mode, prefetch=0)
    strict = Frontend(sequence, mode, _core.Config.from_toml("[fusion]\nrecover_min_snr = 1e6\n"), prefetch=0)
    segments = _core.sim_profile_segments("hdr")
    duration_s = 1.0  # the tiny preset
    checked = {"dark": 0, "bright": 0, "normal": 0}
    for k in range(len(fe)):
        f = fe.process(k)
        raw = fe._rectify_frame(sequence.frames[k].left, "left")
        t = f.t_ns / _NS
        kind = next((name for name, a, b in segments if a * duration_s <= t < b * duration_s), "normal")
        if kind == "dark" and f.stretched == (True, True):
            assert int(f.frame_left.max()) == 255 and int(raw.max()) < 60, (k, int(raw.max()))
            assert _orb_count(f.frame_left) > 3 * max(_orb_count(raw), 10), k
            assert f.bias == ("aps" if mode == "fusion" else "frames"), (k, f.bias)
            if mode == "fusion":
                assert f.beta_left <= 0.3
            checked["dark"] += 1
        elif kind == "bright" and mode == "fusion":
            assert f.bias == "dvs", k  # stretching does not unclip a saturated frame
            checked["bright"] += 1
        if choose_beta(raw).bias == "aps":  # well exposed (the auto-exposure lags the light)
            assert f.stretched[0] is False and np.array_equal(f.frame_left, raw), k
            checked["normal"] += 1
        g = strict.process(k)
        assert g.stretched == (False, False) and np.array_equal(g.frame_left, raw), k
    assert checked["dark"] >= 3 and checked["normal"] >= 3, checked
    assert mode == "frames" or checked["bright"] >= 2, checked


def test_auto_plane_depth_is_the_median_scene_depth(sequence) -> None:  # type: ignore[no-untyped-def]
    fe = Frontend(sequence, "fusion", plane_depth="auto", prefetch=0)
    sim = simulator_for("tiny")
    truth = float(np.nanmedian(sim.render_depth(0, int(sequence.frames.t_mid_ns[0]))))
    assert fe.plane_depth_m == pytest.approx(truth, rel=0.15), (fe.plane_depth_m, truth)
    # The events mode measures the same depth (its β is always 1, the exposure test is not).
    assert Frontend(sequence, "events", plane_depth="auto", prefetch=0).plane_depth_m == fe.plane_depth_m
    assert Frontend(sequence, "fusion", plane_depth=1.5).plane_depth_m == 1.5
    assert Frontend(sequence, "fusion").plane_depth_m == 0.0  # the config's default: infinity
    with pytest.raises(InputError, match="plane_depth"):
        Frontend(sequence, "fusion", plane_depth="near")


def test_bridge_images_blend_the_usable_frame_with_the_neighbours_beta(sequence) -> None:  # type: ignore[no-untyped-def]
    """Issue 8: at every APS↔DVS switch of the HDR profile the bridge renders the APS-biased
    frame of the pair (the previous one entering a dark/bright segment, the current one
    leaving it) with the other frame's β; between frames of one mode there is none."""
    from dhptam.fusion import fuse

    frontend = Frontend(sequence, "fusion", prefetch=0)
    frames = [frontend.process(k) for k in range(len(frontend))]
    # Flood frames are predicted, not tracked: a bridge spans them, between the clean frames
    # on either side, and never involves a flood frame.
    clean = [f for f in frames if not f.flood]
    switches = {"in": 0, "out": 0, "out across a flood": 0}
    for previous, current in itertools.pairwise(frames):
        if previous.flood or current.flood:
            assert frontend.bridge_images(previous, current) is None, current.index
    for previous, current in itertools.pairwise(clean):
        bridge = frontend.bridge_images(previous, current)
        if previous.bias == current.bias:
            assert bridge is None, current.index
            continue
        source, neighbour = (previous, current) if previous.bias == "aps" else (current, previous)
        if source is current and current.index > previous.index + 1:
            # Leaving a DVS-biased segment across a flood: no bridge, the frame's own image.
            assert bridge is None, current.index
            switches["out across a flood"] += 1
            continue
        assert bridge is not None, current.index
        switches["in" if source is previous else "out"] += 1
        assert (bridge.index, bridge.t_ns, bridge.bias) == (source.index, source.t_ns, neighbour.bias)
        assert bridge.beta_left == neighbour.beta_left and bridge.beta_right == neighbour.beta_right
        for side in ("left", "right"):
            beta = getattr(neighbour, f"beta_{side}")
            # The source frame is first given the neighbour's exposure (mean and contrast).
            frame = _exposed_like(getattr(source, f"frame_{side}"), getattr(neighbour, f"frame_{side}"))
            expected = fuse(frame, getattr(source, f"events_{side}"), beta)
            assert np.array_equal(getattr(bridge, side), expected), side
        assert not np.array_equal(bridge.left, source.left)
    assert switches["in"] >= 1 and switches["out"] >= 1 and switches["out across a flood"] >= 1, switches
    # Switched off, or outside the fusion mode: no bridge.
    off = Frontend(sequence, "fusion", _core.Config.from_toml("[fusion]\nbridge = false"), prefetch=0)
    pair = next((a, b) for a, b in itertools.pairwise(frames) if a.bias != b.bias)
    assert off.bridge_images(*pair) is None
    events = Frontend(sequence, "events", prefetch=0)
    assert events.bridge_images(events.process(pair[0].index), events.process(pair[1].index)) is None


def test_frames_leaving_the_dvs_bias_across_a_flood_are_rendered_from_their_frames(sequence) -> None:  # type: ignore[no-untyped-def]
    """Issue 8: leaving a DVS-biased segment across a flood (the last clean frame was
    DVS-biased), the flood frames and the first clean frame after them whose two frames pass
    the exposure test are rendered from the frames alone (β 0, bias ``frames``). Such a flood
    frame is tracked when it has ``[fusion] min_features`` features, the clean one always;
    every other flood frame is left as it was and predicted, every other clean frame untouched.
    """
    frontend = Frontend(sequence, "fusion", prefetch=0)
    no_frames = _core.Config.from_toml("[fusion]\nflood_frames = false")
    strict = Frontend(sequence, "fusion", no_frames, prefetch=0)
    previous = None
    leaving = {"flood": 0, "clean": 0}
    for k in range(len(frontend)):
        frame = frontend.process(k)
        rendered = frontend.across_flood(previous, frame)
        assert strict.across_flood(previous, frame) is frame
        across = previous is not None and (frame.flood or frame.index > previous.index + 1)
        if across and previous.bias == "dvs" and (frame.bias, frame.bias_right) == ("aps", "aps"):
            leaving["flood" if frame.flood else "clean"] += 1
            assert (rendered.bias, rendered.bias_right, rendered.beta_left, rendered.beta_right) == (
                "frames", "frames", 0.0, 0.0,
            )  # fmt: skip
            assert np.array_equal(rendered.left, frame.frame_left)
            assert np.array_equal(rendered.right, frame.frame_right)
            assert not np.array_equal(frame.left, frame.frame_left)  # the events were blended in
            if frame.flood:
                assert not frontend.predicts(rendered, frontend.min_features)
                assert frontend.predicts(rendered, frontend.min_features - 1)  # too few features
                assert strict.predicts(frame, 10_000)
            else:
                assert not frontend.predicts(rendered, 0)  # a clean frame is always tracked
        else:
            assert rendered is frame, k
            assert frontend.predicts(frame, 10_000) == frame.flood, k
        if not frame.flood:
            previous = rendered
    assert leaving["flood"] >= 1 and leaving["clean"] >= 1, leaving
    # Outside the fusion mode nothing is re-rendered.
    events = Frontend(sequence, "events", prefetch=0)
    flood = next(events.process(k) for k in range(len(events)) if events.process(k).flood)
    assert events.across_flood(flood, flood) is flood and events.predicts(flood, 10_000)


# -- illumination floods (issue 8, accuracy) -----------------------------------------------------


def test_is_flood_needs_a_burst_of_one_polarity() -> None:
    history = [30_000] * 10
    assert is_flood(480_000, 1_000, history)  # a darkening ramp: OFF events only
    assert is_flood(480_000, 479_000, history)  # a brightening one: ON only
    assert not is_flood(480_000, 240_000, history)  # fast motion: as many ON as OFF
    # One polarity but no burst: OFF events at 2.4x their usual count (half the median).
    assert not is_flood(36_000, 0, history)
    assert is_flood(90_000, 0, history, ratio=2.5) and not is_flood(90_000, 0, history, ratio=7.0)
    # The start of a darkening ramp as measured at TUM-VIE size (demo rig `tumvie`, frame 66 of
    # the HDR sequence): 2.3x the median count, 82 % OFF. The OFF events alone are 3.8x their
    # usual count; the whole window against the whole median would not have been a flood.
    ramp = [2_700_000, 14_100_000, 14_400_000, 6_980_000] + [2_825_000] * 6
    assert is_flood(6_603_633, 1_188_654, ramp)
    assert not is_flood(6_603_633, 3_301_816, ramp)  # as many events, both polarities: motion
    assert not is_flood(480_000, 1_000, history, ratio=0.0)  # detection off
    assert not is_flood(480_000, 1_000, [])  # nothing to compare with (frame 0)
    # The median, not the mean: earlier floods in the history do not hide the next one.
    assert is_flood(480_000, 1_000, [30_000] * 7 + [500_000] * 3)


def test_floods_are_flagged_at_the_lighting_transitions_of_the_hdr_profile(sequence) -> None:  # type: ignore[no-untyped-def]
    """Every change of light of the ``hdr`` profile floods the event cameras (all pixels fire,
    one polarity); those windows and only those are flagged: none inside a segment, at least
    one at each transition. The frames mode reads no events and flags nothing."""
    fe = Frontend(sequence, "fusion", prefetch=0)
    frames = [fe.process(k) for k in range(len(fe))]
    duration_s = 1.0  # the tiny preset
    transitions = [b * duration_s for _, _, b in _core.sim_profile_segments("hdr")][:-1]
    period = (frames[1].t_ns - frames[0].t_ns) / _NS
    for t_change in transitions:
        near = [f for f in frames if abs(f.t_ns / _NS - t_change) < 2.5 * period]
        assert any(f.flood for f in near), (t_change, [(f.index, f.flood) for f in near])
    for f in frames:
        if f.flood:
            assert min(abs(f.t_ns / _NS - t) for t in transitions) < 2.5 * period, f.index
            stats = f.e3ct_stats
            assert stats is not None
            share_on = (stats.on_left + stats.on_right) / (stats.events_left + stats.events_right)
            assert max(share_on, 1.0 - share_on) >= 0.8, f.index
    # The flag does not depend on the order frames are processed in.
    last_flood = max(f.index for f in frames if f.flood)
    assert Frontend(sequence, "fusion", prefetch=0).process(last_flood).flood
    off = Frontend(sequence, "fusion", _core.Config.from_toml("[fusion]\nflood_ratio = 0"), prefetch=0)
    assert not off.process(last_flood).flood
    assert not any(f.flood for f in Frontend(sequence, "frames", prefetch=0))


def test_is_quiet_compares_with_the_median_of_the_usual_counts() -> None:
    usual = [60_000, 52_000, 41_000, 900_000]  # the median, not the mean: 56 000
    assert is_quiet(450, usual) and is_quiet(1_600, usual)
    assert not is_quiet(1_800, usual)  # 3.2 % of the median
    assert is_quiet(1_800, usual, ratio=0.05) and not is_quiet(450, usual, ratio=0.0)
    assert not is_quiet(10, [])  # nothing to compare with (frame 0)
    assert not is_quiet(0, usual)  # no event at all: missing data (a covered lens), not rest


def test_is_noise_needs_every_camera_without_structure() -> None:
    noise, edges = Activity(57_600, 450, 60), Activity(57_600, 2_000, 1_500)
    assert is_noise((noise, noise))
    assert not is_noise((noise, edges)) and not is_noise((edges, edges))
    assert not is_noise((noise, noise), share=0.0)  # off
    assert not is_noise((noise, Activity(57_600, 0, 0)))  # a covered lens: missing data
    busy = Activity(57_600, 7_000, 900)  # 12 % of the pixels fired: busy, never noise
    assert busy.structured_share < 0.0025 and not is_noise((busy, busy))
    assert not is_noise(())


def test_quiet_windows_are_those_of_a_camera_at_rest(sim_tiny_pause: Path) -> None:
    """Issue 8: on a real trajectory with a rest inserted, exactly the event windows that lie
    inside the rest are flagged quiet, and frame 0's, which ends a few milliseconds into the
    recording; none while the camera moves, none in mode frames or with both tests off. Each
    test finds the rest on its own: the count (``[fusion] quiet_ratio``) against the windows
    before, the structure (``quiet_structure``) with no history at all, which also flags
    frame 0. A window tested on its own (no history of this front-end) gets the same flag."""

    def flags(fe: Frontend) -> list[bool]:
        return [fe.process(k).quiet for k in range(len(fe))]

    with load_tumvie(sim_tiny_pause) as seq:
        fe = Frontend(seq, "events", prefetch=0)
        frames = [fe.process(k) for k in range(len(fe))]
        windows = [fe.window_ns(k) for k in range(len(fe))]
        rest = (PAUSE_S[0] * _NS, (PAUSE_S[0] + PAUSE_S[1]) * _NS)
        inside = [rest[0] <= t0 and t1 <= rest[1] for t0, t1 in windows]
        outside = [k > 0 and (t1 <= rest[0] or t0 >= rest[1]) for k, (t0, t1) in enumerate(windows)]
        assert sum(inside) >= 8 and sum(outside) >= 14, (inside, outside)
        for k, f in enumerate(frames):
            if inside[k] or outside[k]:
                assert f.quiet == inside[k], (k, f.quiet, f.e3ct_stats)
        assert frames[0].quiet
        stats = frames[inside.index(True)].e3ct_stats
        assert stats is not None and stats.activity is not None
        assert all(a.structured_share < 0.0025 for a in stats.activity), stats.activity
        first = inside.index(True)
        assert Frontend(seq, "events", prefetch=0).process(first).quiet
        by_count = flags(
            Frontend(seq, "events", _core.Config.from_toml("[fusion]\nquiet_structure = 0"), prefetch=0)
        )
        by_structure = flags(
            Frontend(seq, "events", _core.Config.from_toml("[fusion]\nquiet_ratio = 0"), prefetch=0)
        )
        for k in range(1, len(fe)):
            if inside[k] or outside[k]:
                assert by_count[k] == by_structure[k] == inside[k], (k, by_count[k], by_structure[k])
        assert by_structure[0] and not by_count[0]  # frame 0 has no history to count against
        off = Frontend(
            seq,
            "events",
            _core.Config.from_toml("[fusion]\nquiet_ratio = 0\nquiet_structure = 0"),
            prefetch=0,
        )
        assert not any(flags(off))
        assert not any(f.quiet for f in Frontend(seq, "frames", prefetch=0))


@pytest.mark.parametrize("depth_m", [0.0, 2.0])
def test_event_disparity_gives_the_frame_disparity_of_warped_event_pairs(sequence, depth_m: float) -> None:  # type: ignore[no-untyped-def]
    """Issue 8: a point seen by both event cameras and warped into the frame cameras through
    the plane at ``depth_m`` keeps the event rig's parallax; the correction maps its
    disparity to the frame cameras' ``f b / Z``, at every depth."""
    fe = Frontend(sequence, "events", _core.Config.from_toml("[fusion]\n" + WARPED_EVENTS))
    f, b = float(fe.frame_rect.K[0, 0]), float(fe.frame_rect.baseline_m)
    ke = fe.event_rect.K
    rng = np.random.default_rng(3)
    z = rng.uniform(0.8, 4.0, 200)
    p_left = np.c_[rng.uniform(-0.3, 0.3, 200) * z, rng.uniform(-0.15, 0.15, 200) * z, z]
    pixels = {}
    for side, p_frame in (("left", p_left), ("right", p_left - [b, 0.0, 0.0])):
        p_event = (fe.frame_from_event[side].inverse().matrix() @ np.c_[p_frame, np.ones(200)].T).T[:, :3]
        rect = (ke @ (p_event / p_event[:, 2:3]).T).T[:, :2]
        pixels[side] = fe.warp_event_pixels(side, rect, depth_m=depth_m)
    measured = pixels["left"][:, 0] - pixels["right"][:, 0]
    assert np.abs(pixels["left"][:, 1] - pixels["right"][:, 1]).max() < 0.1  # rows still align
    scale, offset = fe.event_disparity(depth_m)
    truth = f * b / z
    # (The event cameras sit 1-2 mm off the frame cameras along the optical axis too; the
    # correction leaves that out, a few hundredths of a pixel here.)
    corrected = np.abs(scale * measured + offset - truth).max()
    assert corrected < 0.05
    # Read as frame disparities, the event pair puts near points over 0.3 px off (b_e / b_f = 1.1).
    assert np.abs(measured - truth).max() > max(0.3, 10 * corrected)
    assert 0.85 < scale < 0.95
    # Frames, or the correction turned off: identity.
    assert Frontend(sequence, "frames").event_disparity(depth_m) == (1.0, 0.0)
    off = _core.Config.from_toml("[fusion]\nevent_disparity = false\n" + WARPED_EVENTS)
    assert Frontend(sequence, "events", off).event_disparity(depth_m) == (1.0, 0.0)


def test_event_viewpoint_is_where_warped_event_images_are_seen_from(sequence) -> None:  # type: ignore[no-untyped-def]
    """Issue 8: through the plane at infinity a warped event image is the left event camera's
    view with the frame camera's orientation, so a point X lands at ``K π(X − c)`` for the
    viewpoint ``c`` the front-end hands the tracker (``[fusion] event_viewpoint``)."""
    on = _core.Config.from_toml("[fusion]\nevent_viewpoint = true\n" + WARPED_EVENTS)
    fe = Frontend(sequence, "events", on)
    c = np.array(fe.event_viewpoint(0.0))
    assert np.allclose(c, fe.frame_from_event["left"].translation) and np.linalg.norm(c) > 0.01
    kf, ke = fe.frame_rect.K, fe.event_rect.K
    rng = np.random.default_rng(4)
    z = rng.uniform(0.8, 4.0, 200)
    p_frame = np.c_[rng.uniform(-0.3, 0.3, 200) * z, rng.uniform(-0.15, 0.15, 200) * z, z]
    p_event = (fe.frame_from_event["left"].inverse().matrix() @ np.c_[p_frame, np.ones(200)].T).T[:, :3]
    warped = fe.warp_event_pixels("left", (ke @ (p_event / p_event[:, 2:3]).T).T[:, :2], depth_m=0.0)

    def project(p: np.ndarray) -> np.ndarray:
        return (kf @ (p / p[:, 2:3]).T).T[:, :2]

    from_viewpoint = np.abs(warped - project(p_frame - c)).max()
    assert from_viewpoint < 0.05
    # Read as the frame camera's own pixels they are pixels off.
    assert np.abs(warped - project(p_frame)).max() > max(1.0, 20 * from_viewpoint)
    # Zero through a finite plane, in mode frames, and by default.
    assert fe.event_viewpoint(2.0) == (0.0, 0.0, 0.0)
    assert Frontend(sequence, "frames", on).event_viewpoint(0.0) == (0.0, 0.0, 0.0)
    plain = _core.Config.from_toml("[fusion]\n" + WARPED_EVENTS)
    assert Frontend(sequence, "events", plain).event_viewpoint(0.0) == (0.0, 0.0, 0.0)


def test_hot_pixels_are_found_and_their_events_dropped(tmp_path: Path, sequence) -> None:  # type: ignore[no-untyped-def]
    from dhptam.sim import HotPixelSource, simulate

    # The clean HDR sequence (floods, dark and bright segments) has no hot pixel at any time.
    with Frontend(sequence, "events", prefetch=0) as fe:
        stats = [fe.prepare(k).stats for k in range(len(fe))]
    assert all(s is not None and s.hot_left == s.hot_right == 0 for s in stats)

    out = simulate(tmp_path, preset="tiny", seed=0, hot_pixels=0.01)
    width = 128
    with load_tumvie(out.path) as seq, Frontend(seq, "events", prefetch=0) as fe:
        plain = _core.EventRectifier(fe.event_rect, "left")
        masked = []
        for k in range(len(fe)):
            t0, t1 = fe.window_ns(k)
            window, _ = fe._rectified_events("left", t0, t1)
            found = fe._hot["left"].pixels().astype(np.int64)
            masked.append(len(found))
            # The window lost exactly the events of the pixels found hot (inside the view).
            raw = seq.events["left"].window(t0, t1)
            kept = plain.apply(raw.x, raw.y, raw.t_ns, raw.p, t0, t1)[0]
            raw_pixels = np.stack([raw.x, raw.y], axis=1).astype(np.int64)
            in_view = np.isfinite(plain.lookup(raw_pixels)[:, 0])
            at_hot = np.isin(raw_pixels[:, 1] * width + raw_pixels[:, 0], found)
            assert len(window) == len(kept) - np.count_nonzero(at_hot & in_view)
        source = HotPixelSource(width, 72, 0.01, 0, "left")
        index = source.y.astype(np.int64) * width + source.x.astype(np.int64)
        truth = set(index.tolist())
        # The tiny sensor sees the whole textured room: its pixels fire ~400 Hz on average,
        # so a hot pixel stands out from its neighbours from about 500 Hz.
        fast = set(index[1e9 / source.period_ns >= 500.0].tolist())
        found_set = set(found.tolist())
        assert masked[0] == 0  # no decision before three counted windows in a row
        assert max(masked) > 0 and found_set <= truth  # nothing but hot pixels
        assert len(found_set & fast) >= 0.8 * len(fast) > 10  # and most of the busy ones
    off = _core.Config.from_toml("[events]\nhot_pixel_ratio = 0.0\n", "test")
    with load_tumvie(out.path) as seq, Frontend(seq, "events", off, prefetch=0) as fe:
        assert all(fe.prepare(k).stats.hot_left == 0 for k in range(len(fe)))


@pytest.mark.parametrize("depth_m", [0.0, 2.0])
def test_event_stereo_reads_warped_event_matches_as_frame_pixels(sequence, depth_m: float) -> None:  # type: ignore[no-untyped-def]
    """Issue 8: a point seen by both event cameras and warped into the frame cameras lands
    pixels away from where the frame cameras see it (the event cameras' centres differ);
    ``Frontend.event_stereo`` reads the warped match back as the frame cameras' ``(u, v)`` and
    ``u_right``, at every depth and through any warp plane (``[fusion] event_stereo =
    "exact"``)."""
    exact = _core.Config.from_toml('[fusion]\nevent_stereo = "exact"\n' + WARPED_EVENTS)
    fe = Frontend(sequence, "events", exact)
    k, b = fe.frame_rect.K, float(fe.frame_rect.baseline_m)
    ke = fe.event_rect.K
    rng = np.random.default_rng(4)
    n = 200
    z = rng.uniform(0.5, 4.0, n)
    p_left = np.c_[rng.uniform(-0.3, 0.3, n) * z, rng.uniform(-0.15, 0.15, n) * z, z]
    pixels = {}
    for side, p_frame in (("left", p_left), ("right", p_left - [b, 0.0, 0.0])):
        p_event = (fe.frame_from_event[side].inverse().matrix() @ np.c_[p_frame, np.ones(n)].T).T[:, :3]
        rect = (ke @ (p_event / p_event[:, 2:3]).T).T[:, :2]
        pixels[side] = fe.warp_event_pixels(side, rect, depth_m=depth_m)
    matches = np.c_[pixels["left"], pixels["right"][:, 0]].astype(np.float32)
    truth = np.c_[
        k[0, 0] * p_left[:, 0] / z + k[0, 2],
        k[1, 1] * p_left[:, 1] / z + k[1, 2],
        k[0, 0] * (p_left[:, 0] - b) / z + k[0, 2],
    ]
    reading = fe.event_stereo(depth_m)
    assert reading is not None
    read = reading.frame_readings(matches)
    # float32 pixels and the right row taken from the left: a few hundredths of a pixel.
    assert np.abs(read - truth).max() < 0.05
    # As the warp leaves them, near points are pixels off (mostly in v: the event cameras sit
    # 3 cm below the frame cameras).
    assert np.abs(matches[:, 1] - truth[:, 1]).max() > 2.0
    assert fe.event_stereo(depth_m) is reading  # built once per depth
    # Frames, the correction turned off, or the disparity-only correction (the default): none.
    assert Frontend(sequence, "frames", exact).event_stereo(depth_m) is None
    warped = _core.Config.from_toml("[fusion]\n" + WARPED_EVENTS)
    assert Frontend(sequence, "events", warped).event_stereo(depth_m) is None
    off = _core.Config.from_toml(
        '[fusion]\nevent_disparity = false\nevent_stereo = "exact"\n' + WARPED_EVENTS
    )
    assert Frontend(sequence, "events", off).event_stereo(depth_m) is None
    with pytest.raises(ConfigError, match=re.escape("fusion.event_stereo")):
        _core.Config.from_toml('[fusion]\nevent_stereo = "nearest"')
    # A match without positive disparity in the event cameras cannot be read.
    swapped = np.c_[pixels["right"][:1], pixels["left"][:1, 0]].astype(np.float32)
    assert np.isnan(reading.frame_readings(swapped)).all()
