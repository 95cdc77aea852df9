"""Structure of event windows at rest and in motion: the measurements behind ``[fusion]
quiet_structure`` (issue #8, docs/FUSION.md "Quiet windows").

For every window of each simulated sequence given (TUM-VIE layout with ground truth), the
share of each event camera's pixels supported beyond chance (``dhptam.events.activity``) and
the share of active pixels; a window is at rest when the ground truth does not move over it.
Prints, per sequence, the largest share at rest, the smallest while moving (among windows
under 10 % active, the test's own limit; frame 0's window, which ends a few milliseconds into
the recording, is left out of both), and which windows the default test flags.

    python benches/bench_quiet_structure.py SEQUENCE_DIR [SEQUENCE_DIR ...]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from dhptam.datasets import load
from dhptam.frontend import Frontend, is_noise


def _still(seq: object, windows: list[tuple[int, int]]) -> list[bool]:
    """Whether the ground-truth pose is the same at both ends of each window (within a
    micrometre and a millionth of each quaternion component: a window that starts in the
    last microseconds of a motion is at rest)."""
    gt = seq.ground_truth  # type: ignore[attr-defined]
    ends = np.array([t for w in windows for t in w], np.float64)
    pose = np.stack([np.interp(ends, gt.t_ns, gt.world_from_cam[:, i]) for i in range(7)], 1)
    step = np.abs(pose[1::2] - pose[0::2]).max(axis=1)
    return list(step < 1e-6)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("sequences", nargs="+", help="simulated sequence folders (TUM-VIE layout)")
    args = parser.parse_args(argv)
    print(
        "| sequence | windows | at rest | flagged at rest | flagged moving "
        "| max share at rest | min share moving |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for path in args.sequences:
        with load("tum-vie", path) as seq:
            fe = Frontend(seq, "events", prefetch=0)
            windows = [fe.window_ns(k) for k in range(len(fe))]
            still = _still(seq, windows)
            rest_shares, moving_shares, flagged_rest, flagged_moving = [], [], 0, 0
            for k, (t0, t1) in enumerate(windows):
                stats = fe._event_tensors(t0, t1)[1]
                if stats.activity is None:
                    raise SystemExit("[fusion] quiet_structure is 0 in this configuration")
                share = max(a.structured_share for a in stats.activity)
                busy = max(a.active_share for a in stats.activity) >= 0.1
                noise = is_noise(stats.activity, share=fe.quiet_structure)
                if k == 0:
                    continue
                if still[k]:
                    rest_shares.append(share)
                    flagged_rest += noise
                else:
                    moving_shares += [] if busy else [share]
                    flagged_moving += noise
            rest_max = f"{100 * max(rest_shares):.2f} %" if rest_shares else "–"
            moving_min = f"{100 * min(moving_shares):.2f} %" if moving_shares else "–"
            print(
                f"| {path} | {len(windows) - 1} | {len(rest_shares)} | {flagged_rest} | {flagged_moving} "
                f"| {rest_max} | {moving_min} |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
