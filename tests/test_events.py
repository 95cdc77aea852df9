"""E3CT and baseline event representations through the Python API, and fusion windows."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys

import numpy as np
import pytest

from dhptam import SE3, Camera, Config
from dhptam.errors import InputError
from dhptam.events import (
    _typed,
    count_image,
    e3ct,
    fusion_windows,
    normalise,
    postprocess,
    stereo_e3ct,
    time_surface,
    voxel_grid,
)

MS = 1_000_000


def random_window(n, w, h, span_ns, seed):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span_ns // 1000, n)) * 1000
    return (
        rng.integers(0, w, n).astype(np.uint16),
        rng.integers(0, h, n).astype(np.uint16),
        t.astype(np.int64),
        rng.integers(0, 2, n).astype(np.int8),
    )


def reference_e3ct(x, y, t, p, w, h, t0, t1, alpha=0.5, eta_ms=30.0, b=3):
    """The formula of docs/E3CT.md in float64 numpy, one event at a time in vector form."""
    age_ms = (t1 - t) * 1e-6
    v1 = np.exp(-alpha * ((age_ms - eta_ms / 2) / (eta_ms / 6)) ** 2)
    s = (t - t0) / (t1 - t0) * (b - 1)
    out = np.zeros((h, w, b))
    for j in range(b):
        np.add.at(out, (y, x, j), v1 * np.maximum(0.0, 1.0 - np.abs(s - j)))
    return out


def test_hand_computed_values():
    # Window [0, 30 ms): an event 15 ms old has V1 = 1 and tau = 1/2 (all in channel 1); one
    # 10 ms old has V1 = e^-1/2 and s = 4/3 (2/3 to channel 1, 1/3 to channel 2); one at the
    # window start has V1 = e^-4.5, all in channel 0.
    img = e3ct(
        [3, 3, 0],
        [1, 1, 2],
        [0, 15 * MS, 20 * MS],
        [0, 1, 1],
        width=4,
        height=3,
        t_start_ns=0,
        t_end_ns=30 * MS,
    )
    assert img.shape == (3, 4, 3) and img.dtype == np.float32
    np.testing.assert_allclose(img[1, 3], [np.exp(-4.5), 1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(img[2, 0], [0.0, np.exp(-0.5) * 2 / 3, np.exp(-0.5) / 3], atol=1e-6)
    assert np.count_nonzero(img) == 4
    split = e3ct(
        [3, 3],
        [1, 1],
        [0, 15 * MS],
        [0, 1],
        width=4,
        height=3,
        t_start_ns=0,
        t_end_ns=30 * MS,
        polarity="split",
    )
    np.testing.assert_allclose(split[1, 3], [0, 1, 0, np.exp(-4.5), 0, 0], atol=1e-6)


def test_matches_the_formula_on_a_random_window():
    x, y, t, p = random_window(20_000, 64, 48, 50 * MS, seed=3)
    for alpha, eta in [(0.5, 30.0), (1.0, 80.0)]:
        got = e3ct(x, y, t, p, width=64, height=48, t_start_ns=0, t_end_ns=50 * MS, alpha=alpha, eta_ms=eta)
        want = reference_e3ct(x, y, t, p, 64, 48, 0, 50 * MS, alpha, eta)
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_early_events_fill_channel_zero_and_late_ones_channel_two():
    kw = dict(width=2, height=2, t_start_ns=0, t_end_ns=30 * MS, eta_ms=60.0)
    early = e3ct([1, 1], [1, 1], [1 * MS, 2 * MS], [1, 0], **kw)[1, 1]
    late = e3ct([1, 1], [1, 1], [28 * MS, 29 * MS], [1, 0], **kw)[1, 1]
    assert early.argmax() == 0 and early[2] == 0.0
    assert late.argmax() == 2 and late[0] == 0.0


def test_identical_streams_give_identical_normalised_tensors():
    from dhptam.datasets import EventWindow

    x, y, t, p = random_window(5_000, 64, 48, 50 * MS, seed=4)
    window = EventWindow(x=x, y=y, t_ns=t, p=p)
    left, right, scales = stereo_e3ct(window, window, width=64, height=48, t_start_ns=0, t_end_ns=50 * MS)
    assert np.array_equal(left, right)
    assert left.max() == 1.0 and left.min() == 0.0 and np.all(scales > 0)
    # A right window with half the events keeps the left's scales: colours stay comparable.
    half = EventWindow(x=x[::2], y=y[::2], t_ns=t[::2], p=p[::2])
    cfg = Config.from_toml("[events]\nnormalise_percentile = 90.0\n")
    _, r2, s2 = stereo_e3ct(window, half, width=64, height=48, t_start_ns=0, t_end_ns=50 * MS, config=cfg)
    raw_l = e3ct(x, y, t, p, width=64, height=48, t_start_ns=0, t_end_ns=50 * MS)
    raw_r = e3ct(x[::2], y[::2], t[::2], p[::2], width=64, height=48, t_start_ns=0, t_end_ns=50 * MS)
    for c in range(3):
        pooled = np.sort(np.concatenate([raw_l[..., c][raw_l[..., c] > 0], raw_r[..., c][raw_r[..., c] > 0]]))
        assert s2[c] == pooled[int(np.ceil(0.9 * pooled.size)) - 1]
    np.testing.assert_allclose(r2, np.clip(raw_r / s2, 0, 1), atol=1e-6)


def test_empty_window_gives_zeros():
    for fn in (e3ct, count_image, time_surface, voxel_grid):
        img = fn([], [], [], [], width=5, height=4, t_start_ns=0, t_end_ns=MS)
        assert img.shape[:2] == (4, 5) and not img.any()
    (n,), s = normalise(np.zeros((4, 5, 3), np.float32))
    assert not n.any() and s.tolist() == [1.0, 1.0, 1.0]


@pytest.mark.parametrize(
    ("events", "field"),
    [
        (([0, 4], [0, 0], [0, 1], [1, 1]), "event 1 (x, y)"),
        (([0, 0], [0, 3], [0, 1], [1, 1]), "event 1 (x, y)"),
        (([0, 0], [0, 0], [5, 4], [1, 1]), "event 1 t_ns"),
        (([0, 0], [0, 0], [0, 10 * MS], [1, 1]), "event 1 t_ns"),
        (([0, 0], [0, 0], [0, 1], [1, -1]), "event 1 p"),
        (([0, 70_000], [0, 0], [0, 1], [1, 1]), "x"),
        (([0, 0], [0, 0.5], [0, 1], [1, 1]), "y"),
        (([0], [0, 0], [0, 1], [1, 1]), "x"),
    ],
)
def test_bad_events_raise_naming_the_event(events, field):
    for fn in (e3ct, count_image, voxel_grid):
        with pytest.raises(InputError) as info:
            fn(*events, width=4, height=3, t_start_ns=0, t_end_ns=10 * MS)
        assert info.value.field == field, str(info.value)


def test_unsorted_input_is_an_error_not_resorted():
    with pytest.raises(InputError, match="non-decreasing"):
        e3ct([0, 1], [0, 0], [2 * MS, MS], [1, 1], width=4, height=3, t_start_ns=0, t_end_ns=10 * MS)


def test_event_arrays_of_the_window_dtypes_are_used_in_place():
    x = np.arange(5, dtype=np.uint16)
    assert _typed(x, np.uint16, "x") is x
    assert _typed(x[::2], np.uint16, "x") is not x
    assert _typed([1, 2], np.int64, "t_ns").dtype == np.int64


def test_bit_identical_across_thread_counts():
    code = (
        "import hashlib, numpy as np, sys; sys.path.insert(0, 'tests');"
        "from test_events import random_window; from dhptam.events import e3ct;"
        "w = random_window(400_000, 320, 240, 50_000_000, 9);"
        "img = e3ct(*w, width=320, height=240, t_start_ns=0, t_end_ns=50_000_000);"
        "print(hashlib.sha256(img.tobytes()).hexdigest())"
    )
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    digests = set()
    for threads in ("1", "2", "3"):
        env = dict(os.environ, RAYON_NUM_THREADS=threads)
        out = subprocess.run([sys.executable, "-c", code], env=env, cwd=here, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        digests.add(out.stdout.strip())
    x, y, t, p = random_window(400_000, 320, 240, 50 * MS, 9)
    local = e3ct(x, y, t, p, width=320, height=240, t_start_ns=0, t_end_ns=50 * MS)
    assert digests == {hashlib.sha256(local.tobytes()).hexdigest()}


def test_baselines_match_numpy():
    x, y, t, p = random_window(10_000, 32, 24, 20 * MS, seed=5)
    kw = dict(width=32, height=24, t_start_ns=0, t_end_ns=20 * MS)
    counts = np.zeros((24, 32, 2))
    np.add.at(counts, (y, x, (p == 0).astype(int)), 1.0)
    np.testing.assert_array_equal(count_image(x, y, t, p, polarity="split", **kw), counts)
    np.testing.assert_array_equal(count_image(x, y, t, p, **kw)[..., 0], counts.sum(axis=2))
    latest = np.full((24, 32, 2), -1, np.int64)
    latest[y, x, (p == 0).astype(int)] = t  # numpy keeps the last assignment: the latest event
    want = np.where(latest >= 0, np.exp(-(20 * MS - latest) / (7.0 * MS)), 0.0)
    np.testing.assert_allclose(time_surface(x, y, t, p, tau_ms=7.0, **kw), want, atol=1e-6)
    s = t / (20 * MS) * 4
    grid = np.zeros((24, 32, 5))
    sign = np.where(p == 1, 1.0, -1.0)
    for j in range(5):
        np.add.at(grid, (y, x, j), sign * np.maximum(0.0, 1.0 - np.abs(s - j)))
    np.testing.assert_allclose(voxel_grid(x, y, t, p, bins=5, **kw), grid, atol=1e-4)


def test_postprocess_median_stretch_threshold():
    img = np.zeros((9, 9, 3), np.float32)
    img[4, 4] = 1.0  # an isolated hot pixel: the median removes it
    img[0:3, 0:3, 1] = 0.5
    assert postprocess(img, median=3)[4, 4].max() == 0.0
    stretched = postprocess(img, stretch=True)
    assert stretched[..., 1].max() == 1.0 and stretched[1, 1, 1] == 0.5
    binary = postprocess(img, threshold=0.4)
    assert set(np.unique(binary)) == {0.0, 1.0} and binary[1, 1, 1] == 1.0 and binary[1, 1, 0] == 0.0
    noisy = np.clip(img + np.random.default_rng(0).normal(0, 0.05, img.shape), 0, 1).astype(np.float32)
    assert np.abs(postprocess(noisy, denoise=10.0) - img).mean() < np.abs(noisy - img).mean()
    with pytest.raises(InputError):
        postprocess(img, median=7)


def test_fusion_windows_follow_mid_exposure_times(tmp_path):
    from dhptam.datasets import CAMERA_KEYS, RigCalibration, TumVieWriter, load_tumvie

    cam = Camera("kb4", [100.0, 100.0, 31.5, 23.5, 0.0, 0.0, 0.0, 0.0], 64, 48)
    rig = RigCalibration(dict.fromkeys(CAMERA_KEYS, cam), dict.fromkeys(CAMERA_KEYS, SE3()))
    black = np.zeros((48, 64), np.uint8)
    # Frames start exposing at 10, 60, 110 ms with 4, 8, 2 ms exposures: t_f = 12, 64, 111 ms.
    stamps = [(10 * MS, 4 * MS), (60 * MS, 8 * MS), (110 * MS, 2 * MS)]
    times = np.arange(0, 120 * MS, MS // 2, dtype=np.int64)  # an event every 0.5 ms
    with TumVieWriter(tmp_path, "seq", rig, SE3()) as w:
        for t, e in stamps:
            w.add_frame_pair(t, e, black, black)
        for side in ("left", "right"):
            w.add_events(side, np.zeros_like(times), np.zeros_like(times), times, np.ones_like(times))
    with load_tumvie(tmp_path / "seq") as seq:
        got = [
            (pair.index, t0, t1, lw.t_ns.min(), lw.t_ns.max(), len(rw))
            for pair, lw, rw, t0, t1 in fusion_windows(seq.frames, seq.events["left"], seq.events["right"])
        ]
    assert got == [
        (0, -40 * MS, 12 * MS, 0, 12 * MS - MS // 2, 24),
        (1, 12 * MS, 64 * MS, 12 * MS, 64 * MS - MS // 2, 104),
        (2, 64 * MS, 111 * MS, 64 * MS, 111 * MS - MS // 2, 94),
    ]


def test_events_and_fusion_config_sections():
    from dhptam.errors import ConfigError

    cfg = Config.from_toml(
        '[events]\npolarity = "split"\nchannels = 4\n[fusion]\nmode = "events"\nbeta_max = 0.3\n'
    )
    assert cfg.to_dict()["events"]["polarity"] == "split" and cfg.to_dict()["fusion"]["beta_max"] == 0.3
    for bad, key in [
        ("[events]\nchannels = 1\n", "events.channels"),
        ("[events]\nnormalise_percentile = 0.0\n", "events.normalise_percentile"),
        ("[fusion]\nbeta_max = 2.0\n", "fusion.beta_max"),
        ("[fusion]\ndark_level = 240.0\n", "fusion.dark_level/bright_level"),
        ('[fusion]\nmode = "both"\n', "both"),
    ]:
        with pytest.raises(ConfigError, match=key):
            Config.from_toml(bad)
    x, y, t, p = random_window(2_000, 32, 24, 20 * MS, seed=8)
    from dhptam.datasets import EventWindow

    w = EventWindow(x=x, y=y, t_ns=t, p=p)
    left, _, scales = stereo_e3ct(w, w, width=32, height=24, t_start_ns=0, t_end_ns=20 * MS, config=cfg)
    assert left.shape == (24, 32, 8) and scales.shape == (8,)


def test_the_hot_pixel_detector_takes_any_integer_arrays_and_names_bad_events() -> None:
    from dhptam.events import HotPixels

    detector = HotPixels(16, 12, ratio=3.0, min_rate_hz=50.0, time_constant_s=0.5)
    # Plain int64 lists are converted once; an edge sweeping the image is never hot, a pixel
    # firing 600 times a second alone is, once it has fired in three sampled windows in a row
    # (one window in two is counted at τ = 0.5 s: windows 0, 2 and 4).
    changed = []
    for k in range(10):
        edge_x, edge_y = [k] * 12 * 5, list(range(12)) * 5
        changed.append(detector.update(np.array(edge_x + [14] * 30), np.array(edge_y + [2] * 30), 0.05))
    assert changed.index(True) == 4 and detector.pixels().tolist() == [2 * 16 + 14] and len(detector) == 1
    with pytest.raises(InputError, match="event 1") as err:
        detector.update([1, 16], [1, 1], 0.05)
    assert "16×12" in str(err.value)
    with pytest.raises(InputError, match="x must fit uint16"):
        detector.update([-1], [1], 0.05)
    assert detector.pixels().tolist() == [2 * 16 + 14]
    with pytest.raises(InputError, match="ratio > 1"):
        HotPixels(16, 12, ratio=0.5)
