"""``dhptam run`` end to end, per feature extractor: seconds per frame and per stage.

Runs :func:`dhptam.run.run` (the code behind ``dhptam run``: front-end thread, extraction
thread, tracking, mapping and loop-closing threads) in ``--mode`` on the demo sequence (the
cached one of ``dhptam demo``, simulated on first use; ``--sequence DIR`` for another) with
each extractor, and prints one table row per extractor:

- end to end: wall time of the run divided by its frames (sequence opening and the first,
  warm-up frames included; the extractor is built and warmed up on one frame beforehand, so
  weight loading is not counted);
- per stage: mean wall time of the reading, front-end, extraction and tracking of one frame
  (they run on their own threads and overlap, so they add up to more than the end-to-end time
  when the cores are free);
- CPU time of the process per frame (all threads, user + system): what the run costs the
  machine whatever else runs on it; on an idle box the wall time lies between CPU / cores and
  CPU;
- against the paper's CPU end-to-end time per frame (Table "Computational Complexity", CPU
  column: SuperPoint 3153–4208 ms, R2D2 8560–9125 ms), as paper / ours.

SuperPoint runs with random weights (no weights ship with dhptam; the cost does not depend on
their values, the tracking result does: its row is marked). R2D2 weights come from
``--r2d2-dir`` (default ``../shared/models/r2d2``).

With ``--viz rerun`` every run also writes its rerun recording (``dhptam run --viz rerun``),
to measure what the recording costs against a run without it.

    python benches/bench_end_to_end.py [--sequence DIR] [--frames 20] [--only r2d2] [--viz rerun]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dhptam import features
from dhptam.run import STAGES, run

PAPER_MS = {"superpoint": (3153.0, 4208.0), "r2d2": (8560.0, 9125.0)}
REPO = Path(__file__).resolve().parents[1]


def configurations(r2d2_dir: Path) -> list[tuple[str, str, str, Callable[[], Any]]]:
    """(row label, features name, paper family, constructor)."""

    def superpoint() -> Any:
        import torch

        from dhptam.features.superpoint import SuperPoint, SuperPointNet

        torch.manual_seed(0)
        return SuperPoint(None, net=SuperPointNet(), device="cpu", max_keypoints=1000)  # type: ignore[arg-type]

    full, fast = r2d2_dir / "r2d2_WASF_N16.pt", r2d2_dir / "faster2d2_WASF_N16.pt"
    return [
        ("orb", "orb", "", lambda: features.load("orb")),
        ("sift", "sift", "", lambda: features.load("sift")),
        ("superpoint (RANDOM weights)", "superpoint", "superpoint", superpoint),
        (
            "r2d2 r2d2_WASF_N16, scales 1/0.75/0.5 (default)",
            "r2d2",
            "r2d2",
            lambda: features.load("r2d2", full, device="cpu"),
        ),
        (
            "r2d2 faster2d2_WASF_N16, scale 1, bf16 trunk",
            "r2d2",
            "r2d2",
            lambda: features.load("r2d2", fast, device="cpu", scales=(1.0,), precision="bfloat16"),
        ),
    ]


def time_viz_frames() -> dict[str, list[float]]:
    """Wraps the rerun sink's per-frame methods so that each call's wall time is recorded:
    ``hand_over`` (:meth:`dhptam.viz.RerunSink.frame`, on the tracking thread) and ``logging``
    (encoding, matching for the drawing, handing to rerun's writer, on the sink's thread)."""
    import time

    from dhptam.viz import RerunSink

    seconds: dict[str, list[float]] = {"hand_over": [], "logging": []}

    def wrap(name: str, key: str) -> None:
        inner = getattr(RerunSink, name)

        def timed(self: RerunSink, *args: Any) -> None:
            start = time.perf_counter()
            inner(self, *args)
            seconds[key].append(time.perf_counter() - start)

        setattr(RerunSink, name, timed)

    wrap("frame", "hand_over")
    wrap("_log_frame", "logging")
    return seconds


def warm_up(extractor: Any, sequence: Path) -> None:
    """One extraction on the sequence's first frame pair (allocations, oneDNN kernel choice)."""
    from dhptam.datasets import load_tumvie

    with load_tumvie(sequence) as seq:
        pair = seq.frames[0]
        extractor.extract(pair.left, pair.right)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sequence", type=Path, help="TUM-VIE sequence (default: the demo sequence)")
    parser.add_argument("--mode", default="fusion", choices=["fusion", "frames", "events"])
    parser.add_argument("--frames", type=int, default=20, help="frames per run (default 20)")
    parser.add_argument("--only", default="", help="run only rows whose label contains this text")
    parser.add_argument("--viz", default="none", choices=["none", "rerun"], help="record with rerun too")
    parser.add_argument("--r2d2-dir", type=Path, default=REPO.parent / "shared" / "models" / "r2d2")
    args = parser.parse_args()

    if args.sequence is None:
        from dhptam.demo import demo_sequence

        args.sequence = demo_sequence()
    cores = os.cpu_count()
    print(f"# {args.sequence}, mode {args.mode}, {args.frames} frames, viz {args.viz}, {cores} cores")
    print(f"# load average before: {os.getloadavg()[0]:.2f}\n")
    print(
        "| extractor | frames (tracked) | end to end ms/frame (fps) | CPU ms/frame "
        "| reading / front-end / extraction / tracking ms (mean) | paper CPU end to end / ours (wall; CPU) |"
    )
    print("|---|---|---|---|---|---|")
    viz_seconds = time_viz_frames() if args.viz != "none" else {}
    for label, name, family, make in configurations(args.r2d2_dir):
        if args.only and args.only not in label:
            continue
        extractor = make()
        warm_up(extractor, args.sequence)
        cpu0 = time.process_time()
        with tempfile.TemporaryDirectory() as out:
            result = run(
                args.sequence,
                out,
                mode=args.mode,
                features=name,
                extractor=extractor,
                progress=False,
                max_frames=args.frames,
                viz=args.viz,
            )
            stages = json.loads((Path(out) / "timing.json").read_text())["stages"]
            cpu_ms = 1e3 * (time.process_time() - cpu0) / max(result.frames, 1)
            if "recording" in result.files:
                mb = result.files["recording"].stat().st_size / 1e6
                hand_over, logging = (1e3 * float(np.mean(viz_seconds[k])) for k in ("hand_over", "logging"))
                label += f", rerun recording {mb:.1f} MB, hand-over/logging {hand_over:.1f}/{logging:.1f} ms"
                for values in viz_seconds.values():
                    values.clear()
        ms = 1e3 * result.seconds / max(result.frames, 1)
        means = [stages[s].get("mean_ms", float("nan")) for s in STAGES]
        per_stage = " / ".join(f"{m:.0f}" for m in means)
        ratio = ""
        if family:
            low, high = PAPER_MS[family]
            ratio = f"{low / ms:.1f}–{high / ms:.1f}×; {low / cpu_ms:.1f}–{high / cpu_ms:.1f}×"
        print(
            f"| {label} | {result.frames} ({result.tracked}) | {ms:.0f} ({result.fps:.1f}) | {cpu_ms:.0f} "
            f"| {per_stage} | {ratio} |",
            flush=True,
        )
    print(f"\n# load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
