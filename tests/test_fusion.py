"""Online β, blending and the event→frame warp through the Python API."""

from __future__ import annotations

import numpy as np
import pytest

from dhptam import SE3, SO3, Config
from dhptam.errors import ConfigError, InputError
from dhptam.fusion import choose_beta, fuse, recover_exposure, warp_to_frame


def frame(base: float, gradient: float) -> np.ndarray:
    row = np.clip(base + gradient * np.arange(64) / 63.0, 0, 255).astype(np.uint8)
    return np.tile(row, (48, 1))


def test_beta_switches_to_dvs_on_dark_and_bright_frames_and_back():
    normal, dark, bright = frame(40, 180), frame(0, 30), frame(230, 25)
    paper = Config.from_toml("[fusion]\naps_beta_max = 1.0\n")  # min(r, 1 - r) uncapped
    decisions = [choose_beta(f, config=paper) for f in (normal, dark, normal, bright, normal)]
    assert [d.bias for d in decisions] == ["aps", "dvs", "aps", "dvs", "aps"]
    for f, d in zip((normal, dark, normal, bright, normal), decisions, strict=True):
        r = f.mean() / f.max()
        want = min(r, 1 - r) if d.bias == "aps" else max(r, 1 - r)
        assert d.ratio == pytest.approx(r, abs=1e-12) and d.beta == pytest.approx(want, abs=1e-12)
    assert choose_beta(normal, feature_count=10).bias == "dvs"
    capped = Config.from_toml("[fusion]\nbeta_max = 0.3\n")
    assert choose_beta(dark, config=capped).beta == 0.3
    assert choose_beta(dark, config=Config.from_toml('[fusion]\nmode = "frames"\n')).beta == 0.0
    assert choose_beta(normal, config=Config.from_toml('[fusion]\nmode = "events"\n')).bias == "events"
    with pytest.raises(ConfigError):
        Config.from_toml("[fusion]\nmax_clipped_fraction = 1.5\n")


def test_the_default_caps_beta_of_well_exposed_frames_only():
    normal, dark = frame(40, 180), frame(0, 30)
    r = normal.mean() / normal.max()
    assert min(r, 1 - r) > 0.35
    d = choose_beta(normal)
    assert (d.bias, d.beta) == ("aps", 0.3)
    paper = Config.from_toml("[fusion]\naps_beta_max = 1.0\n")
    for f, count in ((dark, None), (normal, 10)):
        capped, plain = choose_beta(f, count), choose_beta(f, count, paper)
        assert capped.bias == plain.bias == "dvs" and capped.beta == plain.beta >= 0.5
    with pytest.raises(ConfigError, match="aps_beta_max"):
        Config.from_toml("[fusion]\naps_beta_max = 1.5\n")


def test_the_dvs_floor_renders_failing_frames_from_their_events():
    normal, dark, bright = frame(40, 180), frame(0, 30), frame(230, 25)
    paper = Config.from_toml("[fusion]\ndvs_beta_min = 0.5\n")
    events_only = Config.from_toml("[fusion]\ndvs_beta_min = 1.0\n")
    for f in (dark, bright):
        r = f.mean() / f.max()
        assert choose_beta(f, config=paper).beta == pytest.approx(max(r, 1 - r), abs=1e-12)
        alone = choose_beta(f, config=events_only)
        assert (alone.bias, alone.beta) == ("dvs", 1.0)
    assert choose_beta(normal, 10, events_only).beta == 1.0  # too few features: DVS-biased
    assert choose_beta(normal, 500, events_only).beta == 0.3  # APS-biased: the APS cap
    with pytest.raises(ConfigError, match="dvs_beta_min"):
        Config.from_toml("[fusion]\ndvs_beta_min = 1.5\n")


def _noisy_ramp(low: float, high: float, sigma: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ramp = np.linspace(low, high, 160)[None, :] + sigma * rng.standard_normal((120, 160))
    return np.clip(np.rint(ramp), 0, 255).astype(np.uint8)


def test_dark_frames_with_a_signal_are_stretched_and_noise_and_good_frames_are_not():
    dark = _noisy_ramp(1, 15, 0.3, 0)  # a clean signal over 15 grey levels
    r = recover_exposure(dark)
    assert r.failed and r.stretched and r.snr >= 20.0, r
    assert (int(r.image.min()), int(r.image.max())) == (0, 255)
    assert r.image.shape == dark.shape and r.image.dtype == np.uint8
    assert int(dark.max()) <= 16  # the input is not modified
    # Column means keep their order: a stretch, not a reshuffle.
    means = r.image.mean(axis=0)
    assert means[10] + 100 < means[80] < means[150] - 100
    # Afterwards the frame is usable: β leaves the DVS-biased mode.
    assert choose_beta(dark).bias == "dvs" and choose_beta(r.image).bias == "aps"

    noise = _noisy_ramp(4, 10, 2.5, 1)  # 12 levels of range over a noise of 2.5
    r = recover_exposure(noise)
    assert r.failed and not r.stretched and r.image is noise  # returned as it is
    assert r.noise == pytest.approx(2.5, rel=0.2) and r.snr < 20.0

    good = _noisy_ramp(30, 220, 2.0, 2)
    r = recover_exposure(good)
    assert not r.failed and not r.stretched and np.array_equal(r.image, good) and r.snr == 0.0

    saturated = _noisy_ramp(120, 600, 0.5, 3)  # 70 % of the pixels at 255
    r = recover_exposure(saturated)
    assert r.failed and r.stretched and choose_beta(r.image).bias == "dvs"
    # The DVS switch has its own threshold: above the clipped share, the stretched frame stays
    # APS-biased, while the exposure test (and so the stretch) is unchanged.
    lenient = Config.from_toml("[fusion]\ndvs_clipped_fraction = 0.9\n")
    r2 = recover_exposure(saturated, lenient)
    assert r2.failed and r2.stretched and np.array_equal(r2.image, r.image)
    assert choose_beta(r.image, config=lenient).bias == "aps"
    with pytest.raises(ConfigError, match="dvs_clipped_fraction"):
        Config.from_toml("[fusion]\ndvs_clipped_fraction = -0.1\n")

    off = Config.from_toml("[fusion]\nrecover_exposure = false\n")
    assert not recover_exposure(dark, off).stretched
    strict = Config.from_toml("[fusion]\nrecover_min_snr = 1000.0\n")
    assert not recover_exposure(dark, strict).stretched
    with pytest.raises(InputError, match="frame"):
        recover_exposure(dark.astype(np.float32))
    with pytest.raises(InputError, match="frame"):
        recover_exposure(dark[None])
    with pytest.raises(ConfigError, match="recover_min_snr"):
        Config.from_toml("[fusion]\nrecover_min_snr = -1.0\n")


def test_fuse_blends_frame_and_event_intensity():
    c = np.array([[100, 200, 0]], np.uint8)
    d = np.array([[[0.2, 0.9, 0.1], [0, 0, 0], [1.0, 0.5, 0]]], np.float32)
    assert fuse(c, d, 0.0).tolist() == c.tolist()
    assert fuse(c, d, 0.25).tolist() == [[132, 150, 64]]
    with pytest.raises(InputError):
        fuse(c, d[:, :2], 0.5)
    with pytest.raises(InputError):
        fuse(c, d, 1.5)


def test_warp_moves_event_pixels_onto_the_frame_pixel_of_the_same_point():
    k_event = np.array([500.0, 500.0, 31.5, 23.5])
    k_frame = np.array([600.0, 600.0, 40.0, 30.0])
    frame_from_event = SE3(SO3.exp([0.0, 0.02, 0.01]), [0.05, -0.01, 0.0])
    depth = 2.0
    image = np.zeros((48, 64, 1), np.float32)
    image[15, 20, 0] = 1.0
    # The 3-D point seen at event pixel (20, 15) on the plane z = 2 m, and its frame pixel.
    x_d = depth * np.array([(20 - 31.5) / 500.0, (15 - 23.5) / 500.0, 1.0])
    x_c = frame_from_event @ x_d
    want = np.array([600.0 * x_c[0] / x_c[2] + 40.0, 600.0 * x_c[1] / x_c[2] + 30.0])
    out, uv = warp_to_frame(
        image, k_event, k_frame, frame_from_event, width=80, height=60, depth_m=depth, pixels=[[20.0, 15.0]]
    )
    assert out.shape == (60, 80, 1) and uv is not None
    assert np.linalg.norm(uv[0] - want) < 0.5
    assert np.linalg.norm(uv[0] - want) < 1e-9
    peak = np.unravel_index(np.argmax(out[..., 0]), out.shape[:2])
    assert np.hypot(peak[1] - want[0], peak[0] - want[1]) <= 1.0
    # Warping at infinity ignores the 5 cm offset: pixels off by several pixels at 2 m.
    _, uv_inf = warp_to_frame(
        image, k_event, k_frame, frame_from_event, width=80, height=60, pixels=[[20.0, 15.0]]
    )
    assert uv_inf is not None and np.linalg.norm(uv_inf[0] - want) > 5.0
    # δP_align shifts the result by exactly itself.
    _, uv_shift = warp_to_frame(
        image,
        k_event,
        k_frame,
        frame_from_event,
        width=80,
        height=60,
        depth_m=depth,
        align_px=[1.0, -2.0],
        pixels=[[20.0, 15.0]],
    )
    assert uv_shift is not None and np.allclose(uv_shift[0] - uv[0], [1.0, -2.0])
    with pytest.raises(InputError):
        warp_to_frame(image, k_event, k_frame, frame_from_event, width=80, height=60, depth_m=-1.0)


def test_fused_dark_frame_yields_more_features_than_the_frame_alone():
    import cv2

    from dhptam.events import e3ct, normalise

    # A nearly black frame with squares 3 grey levels brighter: too faint for FAST.
    dark = np.full((120, 160), 4, np.uint8)
    squares = [(20, 20), (20, 90), (70, 40), (70, 110)]
    for r, c in squares:
        dark[r : r + 30, c : c + 30] = 7
    # Events fire along the squares' edges over a 50 ms window (an edge sweeping the sensor).
    ys, xs = [], []
    for r, c in squares:
        for k in range(30):
            ys += [r, r + 29, r + k, r + k]
            xs += [c + k, c + k, c, c + 29]
    n = len(xs)
    t = np.linspace(0, 49_000_000, n).astype(np.int64)
    order = np.random.default_rng(1).permutation(n)
    img = e3ct(
        np.array(xs)[order],
        np.array(ys)[order],
        t,
        np.ones(n, np.int8),
        width=160,
        height=120,
        t_start_ns=0,
        t_end_ns=50_000_000,
        eta_ms=100.0,
    )
    (events,), _ = normalise(img)
    decision = choose_beta(dark)
    assert decision.bias == "dvs"
    fused = fuse(dark, events, decision.beta)
    fast = cv2.FastFeatureDetector_create(threshold=20)
    on_frame = len(fast.detect(dark))
    on_fused = len(fast.detect(fused))
    assert on_frame == 0 and on_fused >= 4 * len(squares), (on_frame, on_fused)
