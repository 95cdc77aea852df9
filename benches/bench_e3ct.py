"""E3CT of 1 M events at 1280×720: dhptam (Rust, through the Python API) against numpy.

The numpy baselines compute the same formula (docs/E3CT.md) in float64, vectorised over the
events:

* ``numpy add.at``: decay weights and tent votes as arrays, scattered with ``np.add.at``
  (the straightforward way to write it);
* ``numpy bincount``: the same weights, accumulated with ``np.bincount`` on flat pixel
  indices (the fastest scatter numpy offers).

Both are checked equal to dhptam's tensor to 1e-5 (relative, with 1e-6 absolute) before
anything is timed. The window is the criterion bench's kind: µs-quantised sorted stamps over
50 ms, 70 % of the events on a few hundred line segments, 30 % uniform. dhptam uses the rayon
pool of the process: set ``RAYON_NUM_THREADS`` to pin it (the script prints it).

``--previous PATH`` adds a row for another build of ``dhptam._core`` (e.g. a copy of the
extension built from an earlier commit), loaded side by side in the same process and checked
equal too: the ratio against the previous kernel comes from the same run.

The ``stream`` rows run ``--stream`` distinct windows in turn (``--repeats`` passes, three
tensors kept alive, median per window), as the front-end does: the first rows repeat one
window, whose arrays stay in cache and whose freed tensor the allocator hands back at once.

    python benches/bench_e3ct.py [--events 1000000] [--repeats 7] [--stream 12] [--previous OLD/_core.abi3.so]
"""

from __future__ import annotations

import argparse
import importlib.machinery
import importlib.util
import os
import platform
import time
from types import ModuleType

import numpy as np

from dhptam import _core
from dhptam.events import e3ct

W, H = 1280, 720
SPAN_NS = 50_000_000


def window(n: int, seed: int = 42) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    segments = np.column_stack(
        [rng.uniform(0, W, 300), rng.uniform(0, H, 300), rng.uniform(-60, 60, 300), rng.uniform(-60, 60, 300)]
    )
    on_edge = rng.random(n) < 0.7
    s = segments[rng.integers(0, 300, n)]
    a = rng.random(n)
    u = np.where(on_edge, s[:, 0] + a * s[:, 2], rng.uniform(0, W, n))
    v = np.where(on_edge, s[:, 1] + a * s[:, 3], rng.uniform(0, H, n))
    t = np.sort(rng.integers(0, SPAN_NS // 1000, n)).astype(np.int64) * 1000
    return (
        np.clip(u, 0, W - 1).astype(np.uint16),
        np.clip(v, 0, H - 1).astype(np.uint16),
        t,
        rng.integers(0, 2, n).astype(np.int8),
    )


def weights(t: np.ndarray, alpha: float = 0.5, eta_ms: float = 30.0, b: int = 3) -> tuple[np.ndarray, ...]:
    age_ms = (SPAN_NS - t) * 1e-6
    v1 = np.exp(-alpha * ((age_ms - eta_ms / 2) / (eta_ms / 6)) ** 2)
    s = t / SPAN_NS * (b - 1)
    i = np.minimum(s.astype(np.int64), b - 2)
    f = s - i
    return v1, i, f


def numpy_add_at(x, y, t, p) -> np.ndarray:
    v1, i, f = weights(t)
    out = np.zeros((H, W, 3))
    np.add.at(out, (y, x, i), v1 * (1 - f))
    np.add.at(out, (y, x, i + 1), v1 * f)
    return out


def numpy_bincount(x, y, t, p) -> np.ndarray:
    v1, i, f = weights(t)
    base = (y.astype(np.int64) * W + x) * 3 + i
    n = H * W * 3
    out = np.bincount(base, v1 * (1 - f), minlength=n) + np.bincount(base + 1, v1 * f, minlength=n)
    return out.reshape(H, W, 3)


def load_previous(path: str) -> ModuleType:
    """Loads another build of the ``_core`` extension under its own module object."""
    loader = importlib.machinery.ExtensionFileLoader("_core", path)
    spec = importlib.util.spec_from_file_location("_core", path, loader=loader)
    if spec is None:
        raise SystemExit(f"--previous {path}: not a loadable extension module")
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def best_of(fn, repeats: int) -> tuple[float, float]:
    """Smallest wall time and smallest process CPU time (all threads) over ``repeats`` runs.

    On a shared machine the wall time includes waiting for a core; the CPU time does not.
    """
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return min(wall), min(cpu)


def stream_median(
    module: ModuleType, windows: list[tuple[np.ndarray, ...]], rounds: int
) -> tuple[float, float]:
    """Median wall and CPU time per window over ``rounds`` passes through ``windows``, the last
    three tensors kept alive (the front-end holds a few frames in flight)."""
    wall, cpu, alive = [], [], []
    for _ in range(rounds):
        for events in windows:
            t0, c0 = time.perf_counter(), time.process_time()
            alive.append(module._e3ct(*events, W, H, 0, SPAN_NS, 0.5, 30.0, 3, "both"))
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            alive = alive[-3:]
    return float(np.median(wall)), float(np.median(cpu))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--previous", help="another build of dhptam._core to time as the previous kernel")
    ap.add_argument(
        "--stream",
        type=int,
        default=12,
        help="distinct windows of the stream rows (median per window); 0: none",
    )
    args = ap.parse_args()
    x, y, t, p = window(args.events)

    def ours() -> np.ndarray:
        return e3ct(x, y, t, p, width=W, height=H, t_start_ns=0, t_end_ns=SPAN_NS)

    mine = ours()
    for name, fn in (("numpy add.at", numpy_add_at), ("numpy bincount", numpy_bincount)):
        np.testing.assert_allclose(mine, fn(x, y, t, p), rtol=1e-5, atol=1e-6, err_msg=name)

    t_ours = best_of(ours, args.repeats)
    rows = [("dhptam e3ct", t_ours)]
    previous = load_previous(args.previous) if args.previous else None
    if previous is not None:

        def theirs() -> np.ndarray:
            return previous._e3ct(x, y, t, p, W, H, 0, SPAN_NS, 0.5, 30.0, 3, "both")

        np.testing.assert_allclose(mine, theirs(), rtol=1e-5, atol=1e-6, err_msg="previous kernel")
        rows.append(("previous kernel", best_of(theirs, args.repeats)))
    if args.stream:
        # A stream of distinct windows with a few tensors alive, as in the front-end: the cache
        # is cold and the allocator reuses freed memory, unlike the same window repeated.
        windows = [window(args.events, seed) for seed in range(100, 100 + args.stream)]
        modules = [("dhptam e3ct, stream", _core)] + (
            [("previous kernel, stream", previous)] if previous else []
        )
        for name, module in modules:
            rows.append((name, stream_median(module, windows, args.repeats)))
    for name, fn in (("numpy add.at", numpy_add_at), ("numpy bincount", numpy_bincount)):
        rows.append((name, best_of(lambda fn=fn: fn(x, y, t, p), max(3, args.repeats // 2))))
    print(
        f"{args.events} events, {W}×{H}, rayon threads {_core.thread_count()} "
        f"(RAYON_NUM_THREADS={os.environ.get('RAYON_NUM_THREADS', 'unset')}), "
        f"{platform.processor() or platform.machine()}, numpy {np.__version__}, "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; results equal to 1e-5"
    )
    print("| method | wall [ms] | CPU [ms] | M events/s (wall) | dhptam speed-up (wall / CPU) |")
    print("|---|---|---|---|---|")
    for name, (wall, cpu) in rows:
        print(
            f"| {name} | {wall * 1e3:.2f} | {cpu * 1e3:.2f} | {args.events / wall / 1e6:.1f} | "
            f"{wall / t_ours[0]:.1f}× / {cpu / t_ours[1]:.1f}× |"
        )


if __name__ == "__main__":
    main()
