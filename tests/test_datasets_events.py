"""EventSource: time windows against a brute-force reference, with and without /ms_to_idx,
and bounded memory while iterating a large compressed file."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import tumvie_layout as tl

from dhptam import InputError, ParseError
from dhptam.datasets import EventSource

N_EVENTS = 300_000  # enough that the plain binary search does many single-element reads


@pytest.fixture(scope="module")
def event_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, tuple[np.ndarray, ...]]:
    """The same events in a file with /ms_to_idx and in one without."""
    rng = np.random.default_rng(3)
    folder = tmp_path_factory.mktemp("events")
    events = tl.random_events(rng, N_EVENTS, 2_000, 4_000_000, 640, 480)
    with_index, without_index = folder / "indexed.h5", folder / "plain.h5"
    tl.write_event_file(with_index, *events)
    tl.write_event_file(without_index, *events, index=None)
    return with_index, without_index, events


def reference(events: tuple[np.ndarray, ...], t0_ns: int, t1_ns: int, offset_us: int = 0) -> np.ndarray:
    t_ns = (events[2].astype(np.int64) + offset_us) * 1000
    return np.nonzero((t_ns >= t0_ns) & (t_ns < t1_ns))[0]


def query_times(rng: np.random.Generator, t_us: np.ndarray, offset_us: int = 0) -> list[tuple[int, int]]:
    """Random windows of every length, and the edge cases: exact event times and ms
    boundaries (both ends), sub-µs offsets, empty and reversed windows, windows outside."""
    lo, hi = (int(t_us[0]) + offset_us) * 1000, (int(t_us[-1]) + offset_us) * 1000
    windows = []
    for _ in range(150):
        a = int(rng.integers(lo - 10_000_000, hi + 10_000_000))
        windows.append(
            (a, a + int(rng.choice([1, 999, 1000, 50_000_000, 400_000_000]) * rng.uniform(0, 1.5)))
        )
    for _ in range(80):
        i, j = np.sort(rng.integers(0, len(t_us), 2))
        a, b = (int(t_us[i]) + offset_us) * 1000, (int(t_us[j]) + offset_us) * 1000
        windows += [(a, b), (a - 1, b + 1), (a + 1, b - 1), (a, a), (b, a)]
    for ms in rng.integers(lo // 1_000_000, hi // 1_000_000 + 2, 40):
        edge = int(ms) * 1_000_000
        windows += [(edge, edge + 1_000_000), (edge - 1, edge), (edge, edge + 1), (edge - 500, edge + 500)]
    windows += [(lo - 10**9, lo), (hi + 1, hi + 10**9), (lo, hi + 1), (-(10**15), 10**15)]
    return windows


def assert_window(
    source: EventSource, events: tuple[np.ndarray, ...], t0: int, t1: int, offset_us: int = 0
) -> None:
    idx = reference(events, t0, t1, offset_us)
    window = source.window(t0, t1)
    x, y, t_us, p = events
    np.testing.assert_array_equal(
        window.t_ns, (t_us[idx].astype(np.int64) + offset_us) * 1000, err_msg=f"{t0}, {t1}"
    )
    np.testing.assert_array_equal(window.x, x[idx])
    np.testing.assert_array_equal(window.y, y[idx])
    np.testing.assert_array_equal(window.p, p[idx])


@pytest.mark.parametrize("which", ["indexed", "plain", "indexed-ignored"])
def test_windows_match_brute_force(event_file, rng, which):
    with_index, without_index, events = event_file
    path = without_index if which == "plain" else with_index
    with EventSource(path, use_index=which != "indexed-ignored") as source:
        assert source.has_index == (which == "indexed")
        for t0, t1 in query_times(rng, events[2]):
            assert_window(source, events, t0, t1)


def test_both_search_paths_give_identical_index_ranges(event_file, rng):
    with_index, without_index, events = event_file
    with EventSource(with_index) as a, EventSource(without_index) as b:
        for t0, t1 in query_times(rng, events[2]):
            assert a.index_range(t0, t1) == b.index_range(t0, t1)


def test_an_index_that_stops_early_is_completed_by_binary_search(event_file, rng, tmp_path: Path):
    """Windows past the last /ms_to_idx entry fall back to the binary search."""
    _, _, events = event_file
    index = tl.ms_to_idx(events[2])
    path = tmp_path / "short-index.h5"
    short = index[: len(index) // 3]
    tl.write_event_file(path, *events, index=short)
    end_ns = 1_000_000 * (len(short) - 1)  # the last ms the index knows
    edges = [
        (end_ns + d, end_ns + d + e) for d in (-1000, -1, 0, 1, 999_999, 1_000_000) for e in (1, 1000, 10**6)
    ]
    with EventSource(path) as source:
        assert source.has_index
        for t0, t1 in query_times(rng, events[2]) + edges:
            assert_window(source, events, t0, t1)


def test_t_offset_shifts_the_file_clock(tmp_path: Path, rng: np.random.Generator):
    """DSEC files store t relative to /t_offset; the index counts ms of the stored t."""
    events = tl.random_events(rng, 50_000, 0, 900_000, 64, 48)
    offset = 1_650_000_123_456
    path = tmp_path / "dsec.h5"
    tl.write_event_file(path, *events, t_offset_us=offset)
    with EventSource(path) as source:
        assert source.has_index
        assert source.t_range_ns[0] == (int(events[2][0]) + offset) * 1000
        for t0, t1 in query_times(rng, events[2], offset):
            assert_window(source, events, t0, t1, offset)


def test_iterating_windows_returns_every_event_once(event_file):
    with_index, _, events = event_file
    with EventSource(with_index) as source:
        parts = list(source.iter_windows(33_333_333))
        assert all(len(w) == 0 or w.t_ns[-1] - w.t_ns[0] < 33_333_333 for w in parts)
        np.testing.assert_array_equal(
            np.concatenate([w.t_ns for w in parts]), events[2].astype(np.int64) * 1000
        )
        np.testing.assert_array_equal(np.concatenate([w.x for w in parts]), events[0])
        with pytest.raises(InputError):
            next(source.iter_windows(0))


def test_an_empty_file(tmp_path: Path):
    path = tmp_path / "empty.h5"
    empty = np.empty(0, np.int64)
    tl.write_event_file(path, empty, empty, empty, empty, index=np.zeros(1, np.uint64))
    with EventSource(path) as source:
        assert len(source) == 0 and source.t_range_ns == (0, 0)
        assert len(source.window(-(10**12), 10**12)) == 0
        assert list(source.iter_windows(10)) == []


@pytest.mark.parametrize("bad", ["float", "group", "array"])
def test_a_bad_t_offset_is_a_parse_error(tmp_path: Path, rng: np.random.Generator, bad: str):
    import h5py

    path = tmp_path / "dsec.h5"
    tl.write_event_file(path, *tl.random_events(rng, 100, 0, 5000, 64, 48))
    with h5py.File(path, "a") as f:
        if bad == "float":
            f["t_offset"] = 1.5
        elif bad == "group":
            f.create_group("t_offset")
        else:
            f["t_offset"] = np.arange(3)
    with pytest.raises(ParseError, match="t_offset") as info:
        EventSource(path)
    assert info.value.field == "t_offset" and info.value.path == str(path)


MEMORY_PROBE = textwrap.dedent(
    """
    import sys
    from dhptam.datasets import EventSource

    def rss_mib():
        # Peak RSS of this process image. Not ru_maxrss: Linux carries the parent's peak across
        # fork + exec into it, which would hide the growth measured here.
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024

    with EventSource(sys.argv[1]) as source:
        source.window(0, 50_000_000)
        before = rss_mib()
        count = 0
        for window in source.iter_windows(50_000_000):
            count += len(window)
        print(count, before, rss_mib())
    """
)


def test_iterating_a_large_file_keeps_memory_bounded(tmp_path: Path):
    """Peak RSS of a fresh process grows by less than a quarter of the events' in-memory size
    while it reads all of them in 50 ms windows (the file is written in 1 M-event pieces, so
    writing it needs little memory either)."""
    import h5py
    import hdf5plugin

    n_pieces, piece = 24, 1_000_000  # 24 M events: 312 MiB as x, y, t, p arrays
    rate = 5_000_000  # events/s, so 4.8 s of data and ~96 windows
    path = tmp_path / "large.h5"
    rng = np.random.default_rng(11)
    blosc = hdf5plugin.Blosc(cname="zstd", clevel=1, shuffle=hdf5plugin.Blosc.SHUFFLE)
    with h5py.File(path, "w") as f:
        dsets = {
            name: f.create_dataset(
                f"events/{name}", shape=(0,), maxshape=(None,), dtype=dtype, chunks=(1 << 15,), **blosc
            )
            for name, dtype in (("x", np.uint16), ("y", np.uint16), ("t", np.int64), ("p", np.int8))
        }
        for k in range(n_pieces):
            t = np.sort(rng.integers(k * piece, (k + 1) * piece, piece)) * 1_000_000 // rate
            columns = {
                "x": rng.integers(0, 1280, piece),
                "y": rng.integers(0, 720, piece),
                "t": t,
                "p": rng.integers(0, 2, piece),
            }
            for name, values in columns.items():
                dsets[name].resize(((k + 1) * piece,))
                dsets[name][k * piece :] = values
    total_mib = n_pieces * piece * (2 + 2 + 8 + 1) / 2**20
    out = subprocess.run(
        [sys.executable, "-c", MEMORY_PROBE, str(path)],
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
    )
    count, before, after = out.stdout.split()
    assert int(count) == n_pieces * piece
    growth = float(after) - float(before)
    print(f"read {total_mib:.0f} MiB of events; peak RSS {before} -> {after} MiB")
    assert growth < total_mib / 4, f"peak RSS grew by {growth:.0f} MiB reading {total_mib:.0f} MiB of events"
