"""Reading 50 ms event windows from a 20 M events/s file: dhptam against plain h5py, same run.

Writes a TUM-VIE event file (Blosc zstd, ``/ms_to_idx``) with :class:`TumVieWriter` in a
temporary folder, then reads the same random windows of ``--window-ms`` with

* ``EventSource.window`` using ``/ms_to_idx`` (dhptam's default),
* ``EventSource.window`` with the index ignored (binary search over ``/events/t``),
* plain h5py as a user would write it without an index: load ``/events/t`` whole, build a
  boolean mask, fancy-index ``x, y, t, p`` with it (``mask``),
* the same with ``np.searchsorted`` on the loaded ``t`` and slices instead of the mask
  (``searchsorted``),
* ``t`` loaded once and kept in memory, then searchsorted + slices (``t in RAM``): the best a
  reader can do if it pays the memory of the whole time column.

Every method's result is checked against the first one's. Prints a Markdown table for
docs/BENCHMARKS.md.

    python benches/bench_event_slicing.py [--rate 20e6] [--duration 3] [--windows 50] [--naive-windows 5]

``--rss`` instead iterates the whole file in consecutive windows in a fresh process and reports
its peak resident memory before and after (Linux ``VmHWM``), e.g. for a long file::

    python benches/bench_event_slicing.py --rss --rate 5e6 --duration 120
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RSS_PROBE = """
import sys, time
from dhptam.datasets import EventSource

def vm(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) / 1024

with EventSource(sys.argv[1]) as source:
    step = int(sys.argv[2])
    source.window(0, step)
    before = vm("VmHWM")
    count = 0
    t0 = time.perf_counter()
    for window in source.iter_windows(step):
        count += len(window)
    elapsed = time.perf_counter() - t0
    print(count, before, vm("VmHWM"), elapsed)
"""


def write_file(folder: Path, rate: float, duration_s: float, seed: int) -> tuple[Path, int, float]:
    """A sequence whose left event camera fires ``rate`` events/s for ``duration_s``."""
    import numpy as np

    from dhptam import SE3, Camera
    from dhptam.datasets import CAMERA_KEYS, RigCalibration, TumVieWriter

    # TUM-VIE's sensors: 1024x1024 frames (none written here), 1280x720 events.
    frame = Camera("kb4", [747.0, 747.0, 490.0, 505.0, 0.02, 0.002, 0.002, -0.001], 1024, 1024)
    event = Camera("kb4", [1049.0, 1049.0, 634.0, 263.0, -0.01, -0.006, 0.002, -0.002], 1280, 720)
    rig = RigCalibration(
        {"frame_left": frame, "frame_right": frame, "event_left": event, "event_right": event},
        {k: SE3() for k in CAMERA_KEYS},
    )
    rng = np.random.default_rng(seed)
    total = int(rate * duration_s)
    piece = 1_000_000
    t0 = time.perf_counter()
    with TumVieWriter(folder, "bench", rig, SE3()) as writer:
        for start in range(0, total, piece):
            n = min(piece, total - start)
            # Uniform arrival times over this piece's share of the duration (ns).
            lo = int(start / rate * 1e9)
            hi = int((start + n) / rate * 1e9)
            t_ns = np.sort(rng.integers(lo, hi, n))
            writer.add_events(
                "left", rng.integers(0, 1280, n), rng.integers(0, 720, n), t_ns, rng.integers(0, 2, n)
            )
    elapsed = time.perf_counter() - t0
    return folder / "bench" / "bench-events_left.h5", total, elapsed


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rate", type=float, default=20e6, help="events per second")
    parser.add_argument("--duration", type=float, default=3.0, help="seconds of events")
    parser.add_argument("--window-ms", type=float, default=50.0)
    parser.add_argument("--windows", type=int, default=50, help="random windows for the dhptam methods")
    parser.add_argument(
        "--naive-windows", type=int, default=5, help="of them, for the methods loading all of t"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rss", action="store_true", help="measure peak RSS while iterating instead")
    parser.add_argument(
        "--dir", type=Path, default=None, help="where to write the file (default: a temp dir)"
    )
    args = parser.parse_args()

    import h5py
    import numpy as np

    from dhptam.datasets import EventSource

    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        path, total, write_s = write_file(Path(tmp), args.rate, args.duration, args.seed)
        size_mib = path.stat().st_size / 2**20
        print(
            f"{total:,} events ({args.rate / 1e6:g} M/s x {args.duration:g} s) written in {write_s:.1f} s "
            f"({total / write_s / 1e6:.1f} M events/s); file {size_mib:.0f} MiB, "
            f"{total * 13 / 2**20:.0f} MiB as x, y, t, p arrays; {platform.processor() or platform.machine()}"
        )
        step_ns = int(args.window_ms * 1e6)
        if args.rss:
            out = subprocess.run(
                [sys.executable, "-c", RSS_PROBE, str(path), str(step_ns)],
                capture_output=True,
                text=True,
                check=True,
            )
            count, before, after, elapsed = out.stdout.split()
            assert int(count) == total
            print(
                f"iterated {int(count):,} events in {args.window_ms:g} ms windows in {float(elapsed):.1f} s; "
                f"peak RSS {float(before):.0f} MiB after the first window, {float(after):.0f} MiB at the end"
            )
            return

        rng = np.random.default_rng(args.seed + 1)
        span_ns = int(args.duration * 1e9)
        starts = rng.integers(0, span_ns - step_ns, args.windows)
        # Whole-µs bounds, so that the baselines' `t0 // 1000` is the exact file-time bound.
        windows = [(int(a) // 1000 * 1000, int(a) // 1000 * 1000 + step_ns) for a in starts]

        def dhptam_window(source: EventSource):
            def read(t0: int, t1: int):
                w = source.window(t0, t1)
                return w.x, w.y, w.t_ns, w.p

            return read

        f = h5py.File(path, "r")
        ev = f["events"]

        def naive_mask(t0: int, t1: int):
            t = ev["t"][:]
            mask = (t >= t0 // 1000) & (t < t1 // 1000)
            return ev["x"][mask], ev["y"][mask], ev["t"][mask] * 1000, ev["p"][mask]

        def naive_searchsorted(t0: int, t1: int):
            t = ev["t"][:]
            i0, i1 = np.searchsorted(t, [t0 // 1000, t1 // 1000])
            return ev["x"][i0:i1], ev["y"][i0:i1], t[i0:i1] * 1000, ev["p"][i0:i1]

        t_in_ram = ev["t"][:]

        def cached_searchsorted(t0: int, t1: int):
            i0, i1 = np.searchsorted(t_in_ram, [t0 // 1000, t1 // 1000])
            return ev["x"][i0:i1], ev["y"][i0:i1], t_in_ram[i0:i1] * 1000, ev["p"][i0:i1]

        with EventSource(path) as indexed, EventSource(path, use_index=False) as plain:
            methods = [
                ("dhptam `EventSource.window` (`/ms_to_idx`)", dhptam_window(indexed), args.windows),
                ("dhptam `EventSource.window` (binary search)", dhptam_window(plain), args.windows),
                ("h5py: load `t`, boolean mask, fancy indexing", naive_mask, args.naive_windows),
                ("h5py: load `t`, `np.searchsorted`, slices", naive_searchsorted, args.naive_windows),
                ("h5py: `t` kept in RAM, `np.searchsorted`, slices", cached_searchsorted, args.windows),
            ]
            reference = {}
            results = []
            for name, read, count in methods:
                times = []
                events = 0
                for t0, t1 in windows[:count]:
                    start = time.perf_counter()
                    out = read(t0, t1)
                    times.append(time.perf_counter() - start)
                    events += len(out[2])
                    expected = reference.setdefault((t0, t1), out)
                    for a, b in zip(out, expected, strict=True):
                        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
                results.append((name, count, float(np.median(times)), events / count))
        f.close()

    naive = results[2][2]
    print(f"\n{args.window_ms:g} ms windows, median over the windows read (same windows for every method):\n")
    print("| method | windows | median per window [ms] | events per window | naive mask / method |")
    print("|---|---:|---:|---:|---:|")
    for name, count, median, per_window in results:
        print(f"| {name} | {count} | {median * 1e3:.2f} | {per_window:,.0f} | {naive / median:.1f}× |")


if __name__ == "__main__":
    main()
