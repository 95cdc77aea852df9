"""Time to generate a simulator preset (default: the demo sequence), on N threads and on one.

Each run is a fresh process (rayon reads ``RAYON_NUM_THREADS`` once), writing the sequence to
a temporary folder through the TUM-VIE writer exactly as ``dhptam simulate`` does. The
one-thread run is the baseline measured in the same invocation. Prints a Markdown table for
docs/BENCHMARKS.md, including the renders performed and the resulting rays per second.

    python benches/bench_simulate.py [--preset demo] [--threads 2] [--no-baseline]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys

CHILD = """
import json, sys, tempfile, time
from dhptam import _core
from dhptam.sim import PRESETS, RIGS, simulate
preset = sys.argv[1]
rig = RIGS[PRESETS[preset].rig]
with tempfile.TemporaryDirectory() as out:
    t0 = time.perf_counter()
    s = simulate(out, preset=preset, seed=0)
    wall = time.perf_counter() - t0
print(json.dumps({
    "threads": _core.thread_count(), "wall_s": wall, "renders": s.renders, "frames": s.frames,
    "events": s.events_left + s.events_right, "duration_s": s.duration_ns / 1e9,
    "frame_px": rig.frame_size[0] * rig.frame_size[1], "event_px": rig.event_size[0] * rig.event_size[1],
}))
"""


def run(preset: str, threads: int) -> dict:
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run(
        [sys.executable, "-c", CHILD, preset], env=env, check=True, capture_output=True, text=True
    )
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    # CPU time of the whole child process (imports and setup included): on an otherwise idle
    # machine the wall time cannot drop below cpu_s / threads.
    result["cpu_s"] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", default="demo")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-baseline", action="store_true", help="skip the one-thread run")
    args = parser.parse_args()
    counts = [args.threads] if args.no_baseline else [args.threads, 1]
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs visible, preset {args.preset}"
    )
    print(f"# load average before: {os.getloadavg()[0]:.1f}")
    print(
        "| threads | wall [s] | CPU [s] | simulated [s] | frame pairs | events | renders "
        "| rays per wall second |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for threads in counts:
        r = run(args.preset, threads)
        # Frame renders: 2 cameras × blur samples per pair; the rest are event-camera renders.
        frame_renders = r["frames"] * 2 * 3
        rays = frame_renders * r["frame_px"] + (r["renders"] - frame_renders) * r["event_px"]
        print(
            f"| {r['threads']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['duration_s']:.1f} | "
            f"{r['frames']} | {r['events']:,} | {r['renders']:,} | {rays / r['wall_s'] / 1e6:.1f} M |"
        )


if __name__ == "__main__":
    main()
