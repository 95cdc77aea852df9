"""Memory of a long ``dhptam run``: resident set size sampled over time, peak and slope.

Simulates (once, cached in ``--cache``) a long sequence with the ``tiny`` rig (128×128 event
cameras, 128×72 frames), normal lighting and the closed-loop motion (one loop around the room,
so the run revisits places and closes loops), then runs ``python -m dhptam run`` on it in a
child process and samples the child's RSS from ``/proc/PID/status`` every ``--interval``
seconds. Prints a Markdown row for docs/BENCHMARKS.md (peak RSS, RSS at 25 % and at the end,
slope of a least-squares line over the second half of the run, in MiB per minute of
sequence) and writes the samples as JSON and a plot next to the run's outputs.

    python benches/bench_memory.py --minutes 10 [--minutes 30] [--fps 20] [--out bench-memory] [--mode frames]

The slope over the second half is the figure that says whether memory is bounded: keyframe
and map-point culling and the bounded queues must keep it near zero while the sequence goes
on. The simulated sequence is small (tiny rig; ``--fps`` lowers the frame rate from the
default 20 Hz; event cameras rendered at least every 100 ms instead of 10 ms; no blur
sub-renders) so that 30 minutes can be generated on a 2-core box; the map it builds grows
with the keyframes and frames, not the resolution.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _rss_mib(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _looped_trajectory(path: Path, minutes: float, loops: int) -> Path:
    """The built-in ``closed_loop`` motion of ``minutes / loops`` minutes written ``loops`` times
    in a row as one TUM file (10 Hz samples; the loop ends where it starts, so the path is
    continuous and every lap revisits the places mapped in the first)."""
    from dhptam import _core

    lap_ns = round(60e9 * minutes / loops)
    t, poses = _core.sim_builtin_trajectory("closed_loop", lap_ns)
    keep = np.arange(0, len(t), max(1, len(t) // max(1, lap_ns // 100_000_000)))
    rows = []
    for lap in range(loops):
        for k in keep:
            if lap > 0 and k == 0:
                continue  # the lap's start is the previous lap's end
            ts = int(t[k]) + lap * lap_ns
            rows.append(f"{ts // 10**9}.{ts % 10**9:09d} " + " ".join(f"{v:.9f}" for v in poses[k]))
    path.write_text("\n".join(rows) + "\n")
    return path


def _sequence(cache: Path, minutes: float, seed: int, fps: float, loops: int, event_step_ms: float) -> Path:
    from dhptam import Config
    from dhptam.sim import simulate

    name = f"long-{minutes:g}min-{fps:g}hz-s{seed}"
    if loops > 1:
        name += f"-{loops}laps"
    path = cache / name
    if (path / "groundtruth_frame_left.txt").is_file():
        return path
    trajectory = "closed_loop"
    if loops > 1:
        trajectory = str(_looped_trajectory(cache / f"{name}-trajectory.tum", minutes, loops))
    step_us = 1000.0 * event_step_ms
    t0 = time.perf_counter()
    summary = simulate(
        cache,
        preset="tiny",
        name=name,
        seed=seed,
        duration_s=60.0 * minutes,
        profile="normal",
        trajectory=trajectory,
        overwrite=True,
        progress=True,
        # Slow motion: event-camera renders every `event_step_ms` at most (100 ms by default;
        # the per-pixel log step still bounds them unless the step is longer than 100 ms, where
        # it is lifted too: such sequences are for `frames` mode, whose memory is measured) and
        # no motion-blur sub-renders, to make 30 minutes affordable.
        config=Config.from_toml(
            f"[sim]\nfps = {fps}\nmax_render_step_us = {step_us}\nblur_samples = 1\n"
            + (f"min_render_step_us = {step_us}\nmax_log_step = 1000.0\n" if event_step_ms > 100.0 else "")
        ),
    )
    print(
        f"simulated {name}: {summary.frames} frame pairs, "
        f"{summary.events_left + summary.events_right} events in {time.perf_counter() - t0:.0f} s",
        file=sys.stderr,
    )
    return summary.path


def _repeated(sequence: Path, times: int) -> Path:
    """The sequence played ``times`` times in a row (timestamps shifted by its length), written
    next to it in the TUM-VIE layout. The closed-loop motion ends where it starts, so the
    camera path is continuous and every repetition revisits mapped places."""
    from dhptam.datasets import TumVieWriter, load_tumvie
    from dhptam.sim import IMU_FROM_MARKER

    name = f"{sequence.name}-x{times}"
    if (sequence.parent / name / "done").is_file():
        return sequence.parent / name
    with load_tumvie(sequence) as seq:
        frames = seq.frames
        step = int(frames.t_ns[1] - frames.t_ns[0])
        period = int(frames.t_ns[-1] - frames.t_ns[0]) + step
        with TumVieWriter(sequence.parent, name, seq.calibration, IMU_FROM_MARKER, overwrite=True) as writer:
            for r in range(times):
                for k in range(len(frames)):
                    pair = frames[k]
                    writer.add_frame_pair(pair.t_ns + r * period, pair.exposure_ns, pair.left, pair.right)
                    t0 = int(frames.t_ns[0]) + k * step
                    for side, source in seq.events.items():
                        w = source.window(t0, t0 + step)
                        writer.add_events(side, w.x, w.y, w.t_ns + r * period, w.p)
    (sequence.parent / name / "done").write_text("")
    return sequence.parent / name


_MAP_SIZE = re.compile(r"mapping: map at t=(-?\d+) ns: (\d+) keyframes, (\d+) points")


def _map_sizes(log: Path) -> list[tuple[float, int, int]]:
    """(sequence time [s], keyframes, map points) from the mapping thread's periodic log line."""
    sizes = []
    for line in log.read_text().splitlines():
        m = _MAP_SIZE.search(line)
        if m:
            sizes.append((int(m.group(1)) / 1e9, int(m.group(2)), int(m.group(3))))
    return sorted(sizes)


def measure(
    sequence: Path, out: Path, mode: str, interval_s: float, fps: float, config: str | None = None
) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "dhptam", "run", "--sequence", str(sequence), "--out", str(out / "run")]
    cmd += ["--mode", mode, "-q"]
    if config:
        cmd += ["--config", config]
    t0 = time.perf_counter()
    child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    samples: list[tuple[float, float]] = []
    while child.poll() is None:
        rss = _rss_mib(child.pid)
        if rss is not None:
            samples.append((time.perf_counter() - t0, rss))
        time.sleep(interval_s)
    stdout, stderr = child.communicate()
    if child.returncode != 0:
        raise SystemExit(f"dhptam run failed ({child.returncode}):\n{stderr[-4000:]}")
    wall = time.perf_counter() - t0
    timing = json.loads((out / "run" / "timing.json").read_text())
    t = np.array([s[0] for s in samples])
    rss = np.array([s[1] for s in samples])
    half = t >= t[-1] / 2
    # Wall time maps linearly to sequence time (frames are processed in order): express the
    # slope per minute of sequence.
    seq_minutes = timing["frames"] / fps / 60.0
    slope_per_wall_s = float(np.polyfit(t[half], rss[half], 1)[0]) if half.sum() > 2 else float("nan")
    slope = slope_per_wall_s * wall / seq_minutes if seq_minutes > 0 else float("nan")
    result = {
        "sequence": sequence.name,
        "mode": mode,
        "frames": timing["frames"],
        "states": timing["states"],
        "wall_s": wall,
        "peak_rss_mib": float(rss.max()),
        "rss_at_25pct_mib": float(rss[np.searchsorted(t, 0.25 * t[-1])]),
        "final_rss_mib": float(rss[-1]),
        "slope_mib_per_seq_min_second_half": slope,
        "keyframes": sum(
            1 for line in (out / "run" / "keyframes.tum").read_text().splitlines() if line[:1].isdigit()
        ),
        "map_points": _ply_vertices(out / "run" / "map.ply"),
        "map_sizes": _map_sizes(out / "run" / "run.log"),
        "summary": stdout.strip(),
        "samples": samples,
    }
    (out / "memory.json").write_text(json.dumps(result, indent=1) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 3.2))
        ax.plot(t / wall * seq_minutes, rss, lw=1)
        ax.set_xlabel("sequence time [min]")
        ax.set_ylabel("RSS [MiB]")
        ax.set_title(f"dhptam run, {sequence.name}, {mode}")
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out / "memory.png", dpi=110)
        plt.close(fig)
    except ImportError:
        pass
    return result


def _ply_vertices(path: Path) -> int:
    with open(path, "rb") as f:
        for raw in f:
            line = raw.decode("ascii", "replace").strip()
            if line.startswith("element vertex"):
                return int(line.split()[2])
            if line == "end_header":
                break
    return -1


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--minutes", type=float, action="append", help="sequence length(s) in minutes")
    parser.add_argument("--mode", default="frames", choices=["fusion", "frames", "events"])
    parser.add_argument("--cache", default=os.path.expanduser("~/.cache/dhptam/bench-memory"))
    parser.add_argument("--out", default="bench-memory")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--repeat", type=int, default=1, help="play each simulated sequence this many times in a row"
    )
    parser.add_argument("--fps", type=float, default=20.0, help="frame rate of the simulated sequence [Hz]")
    parser.add_argument("--interval", type=float, default=1.0, help="RSS sampling period [s]")
    parser.add_argument(
        "--loops", type=int, default=1, help="laps of the closed-loop motion in one simulated sequence"
    )
    parser.add_argument(
        "--event-step-ms",
        type=float,
        default=100.0,
        help="longest interval between event-camera renders [ms]; above 100 every render is this far apart",
    )
    parser.add_argument("--config", default=None, help="TOML config for `dhptam run` (e.g. culling off)")
    args = parser.parse_args()
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores", file=sys.stderr)
    print(
        "| sequence | mode | frames | wall [s] | peak RSS [MiB] | RSS at 25 % | final RSS "
        "| slope, 2nd half [MiB/min] | keyframes | map points | keyframes at 1/3, 2/3, end |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for minutes in args.minutes or [10.0]:
        seq = _sequence(cache, minutes, args.seed, args.fps, args.loops, args.event_step_ms)
        if args.repeat > 1:
            seq = _repeated(seq, args.repeat)
        tag = Path(args.config).stem if args.config else "default"
        run_out = Path(args.out) / f"{seq.name}-{tag}"
        r = measure(seq, run_out, args.mode, args.interval, args.fps, args.config)
        sizes = r["map_sizes"]
        at = [sizes[min(len(sizes) - 1, len(sizes) * k // 3)][1] for k in (1, 2, 3)] if sizes else []
        thirds = ", ".join(map(str, at)) or "-"
        print(
            f"| {r['sequence']} ({tag}) | {r['mode']} | {r['frames']} | {r['wall_s']:.0f} "
            f"| {r['peak_rss_mib']:.0f} | {r['rss_at_25pct_mib']:.0f} | {r['final_rss_mib']:.0f} "
            f"| {r['slope_mib_per_seq_min_second_half']:+.2f} | {r['keyframes']} | {r['map_points']} "
            f"| {thirds} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
