"""dhptam's least-squares solvers against Ceres (through pycolmap) and GTSAM, same machine,
same run, same thread count.

    python benches/bench_solver.py [--threads N] [--repeat R] [--json OUT.json]

BAL problems (``$DHPTAM_SHARED/data/bal/problem-*.txt``): dhptam's bundle adjustment against
Ceres with DENSE_SCHUR and SPARSE_SCHUR. COLMAP's reprojection cost drops observations whose
point lies behind the camera, so dhptam runs with ``zero_behind_camera`` to solve the same
objective; the initial costs are printed side by side to show that it is the same.
Pose graphs (``$DHPTAM_SHARED/data/posegraph/*.g2o``): dhptam against GTSAM's
Levenberg–Marquardt with default parameters (GTSAM's threading is its own: TBB if built in).

For each problem the script prints initial and final costs, wall-clock seconds (best of R
runs), and dhptam's time to reach within 0.1 % of the better baseline's final cost (from the
per-step history of the same run). Baselines need the ``bench`` extra:
``pip install -e '.[bench]'``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _baselines import ceres_bal, gtsam_pose_graph

from dhptam import solver

SHARED = Path(os.environ.get("DHPTAM_SHARED", Path(__file__).resolve().parents[2] / "shared"))


def _best(runs: list[dict]) -> dict:
    return min(runs, key=lambda r: r["seconds"])


def bench_bal(path: Path, threads: int, repeat: int) -> dict:
    ours = _best(
        [solver.solve_bal(path, threads=threads, zero_behind_camera=True).__dict__ for _ in range(repeat)]
    )
    plain = solver.solve_bal(path, threads=threads)
    baselines = {
        ls: _best([ceres_bal(path, ls, threads) for _ in range(repeat)])
        for ls in ("DENSE_SCHUR", "SPARSE_SCHUR")
    }
    return _summarise(path.name, ours, baselines, plain_bal=plain)


def bench_pose_graph(path: Path, threads: int, repeat: int) -> dict:
    ours = _best([solver.solve_pose_graph(path, threads=threads).__dict__ for _ in range(repeat)])
    baselines = {"GTSAM_LM": _best([gtsam_pose_graph(path) for _ in range(repeat)])}
    return _summarise(path.name, ours, baselines)


def _summarise(name: str, ours: dict, baselines: dict[str, dict], plain_bal=None) -> dict:
    best_name = min(baselines, key=lambda k: baselines[k]["final_cost"])
    fastest = min(b["seconds"] for b in baselines.values())
    target = baselines[best_name]["final_cost"] * 1.001
    to_target = next((s for c, s in ours["history"] if c <= target), None)
    row = {
        "problem": name,
        "dhptam": {k: ours[k] for k in ("initial_cost", "final_cost", "iterations", "seconds", "threads")},
        "dhptam_seconds_to_target": to_target,
        "target_cost": target,
        "baselines": baselines,
        "cost_ratio_vs_best_baseline": ours["final_cost"] / baselines[best_name]["final_cost"],
        "speedup_to_target_vs_fastest_baseline": None if to_target is None else fastest / to_target,
    }
    if plain_bal is not None:
        row["dhptam_plain_bal_cost"] = {
            "initial_cost": plain_bal.initial_cost,
            "final_cost": plain_bal.final_cost,
            "seconds": plain_bal.seconds,
        }
    return row


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    rows = []
    for path in sorted((SHARED / "data" / "bal").glob("problem-*.txt")):
        rows.append(bench_bal(path, args.threads, args.repeat))
    for path in sorted((SHARED / "data" / "posegraph").glob("*.g2o")):
        rows.append(bench_pose_graph(path, args.threads, args.repeat))
    for r in rows:
        print(f"\n{r['problem']} (threads={args.threads})")
        d = r["dhptam"]
        print(
            f"  {'dhptam':14s} initial {d['initial_cost']:.7e}  final {d['final_cost']:.7e}  "
            f"{d['iterations']:3d} it  {d['seconds']:.3f} s  (to target {r['dhptam_seconds_to_target']})"
        )
        for name, b in r["baselines"].items():
            print(
                f"  {name:14s} initial {b['initial_cost']:.7e}  final {b['final_cost']:.7e}  "
                f"{b['iterations']:3d} it  {b['seconds']:.3f} s"
            )
        if "dhptam_plain_bal_cost" in r:
            p = r["dhptam_plain_bal_cost"]
            print(
                f"  {'dhptam plain':14s} initial {p['initial_cost']:.7e}  final {p['final_cost']:.7e}  "
                f"       {p['seconds']:.3f} s  (every observation counted)"
            )
        speed = r["speedup_to_target_vs_fastest_baseline"]
        print(
            f"  final cost / best baseline = {r['cost_ratio_vs_best_baseline']:.6f};  "
            f"fastest baseline time / dhptam time to target = "
            f"{'not reached' if speed is None else f'{speed:.2f}x'}"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
