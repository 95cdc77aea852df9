"""Keypoints of each mode's images measured against the simulator's ground truth (issue #8).

What limits a mode's accuracy before any pose is estimated: how precisely the features of its
images (`fusion`, `frames` or `events`, as the front-end renders them) land where the scene
puts them. For every ``--step``-th frame k of each sequence:

* **frame to frame**: the keypoints of frame k are matched to those of frame k+1 (mutual
  nearest descriptors, ratio 0.9). Each matched keypoint of k is carried to k+1 with the
  simulator's truth: its depth from ``render_depth`` of the left frame camera at k's fusion
  time, the true poses at both fusion times (interpolated ground truth). The distance to its
  match in k+1 is the localisation error of the pair (both keypoints' errors together, plus
  any wrong match). Per pair, the median displacement of the matches within 3 px is the part
  common to the whole image (it moves the pose) and the median distance to it the scatter.
* **stereo**: left-right matches on the same rectified row (±2 px, positive disparity;
  ``dhptam.viz.stereo_matches``); the disparity after the image's correction
  (``Frontend.event_disparity`` for event-dominated images, as the tracker applies it)
  against the true one, ``f · b / z``.

Keypoints on depth edges (the true depth varying by more than 5 % in the 3×3 pixels around)
are left out, since one depth cannot be assigned to them. The sequences are those of the
accuracy benches (cached; generated on first use): the ``normal`` sequences driven by the
real trajectories (``--normal-duration``, seed 1) and the HDR demo (``--demo-seeds``).
Everything is measured in the rectified frame cameras, so mode ``events`` runs here with its
images warped into them (``[fusion] events_geometry = "frame"``), not in the event cameras
where ``dhptam run`` tracks it by default.

    python benches/bench_keypoint_truth.py [--modes fusion,frames,events] [--features orb]
        [--normal-duration 8] [--demo-seeds 0] [--step 4] [--out bench-keypoint-truth]
"""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path
from typing import Any

import numpy as np
from _accuracy import choices, finish_table

REPO = Path(__file__).resolve().parents[1]
EDGE_DEPTH_RATIO = 0.05
COMMON_WITHIN_PX = 3.0


def _true_points(fe: Any, sim: Any, camera: Any, index: int, pixels: np.ndarray) -> np.ndarray:
    """3-D points (rectified left frame camera of frame ``index``) seen at rectified
    ``pixels``; NaN rows on depth edges or where the renderer sees nothing."""
    k = fe.frame_rect.K
    rect_from_cam = np.asarray(fe.frame_rect.rect_left_from_left.matrix())
    rays = np.c_[(pixels[:, 0] - k[0, 2]) / k[0, 0], (pixels[:, 1] - k[1, 2]) / k[1, 1], np.ones(len(pixels))]
    rays_cam = rays @ rect_from_cam  # rect_from_cam⁻¹ · ray, row by row
    raw = np.asarray(camera.project(rays_cam), np.float64)
    depth = sim.render_depth(0, int(fe.t_f_ns[index]))
    h, w = depth.shape
    xy = np.where(np.isfinite(raw), np.round(raw), -1.0).astype(np.int64)
    x, y = xy[:, 0], xy[:, 1]
    inside = (x >= 1) & (x < w - 1) & (y >= 1) & (y < h - 1)
    x, y = np.where(inside, x, 1), np.where(inside, y, 1)
    # The 3×3 depths around each pixel: one surface (not an edge), seen (finite, positive).
    patch = np.stack([depth[y + dy, x + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=1)
    with np.errstate(invalid="ignore"):
        low, high = patch.min(axis=1), patch.max(axis=1)
        ok = inside & np.isfinite(patch).all(axis=1) & (low > 0) & (high - low <= EDGE_DEPTH_RATIO * low)
        points = (rays_cam * (depth[y, x] / rays_cam[:, 2])[:, None]) @ rect_from_cam.T
    return np.where(ok[:, None], points, np.nan)


def _world_from_rect(fe: Any, truth: Any, index: int) -> np.ndarray:
    """True pose of the rectified left frame camera at frame ``index``'s fusion time."""
    from dhptam._core import SE3
    from dhptam.eval.metrics import interpolate

    row, ok = interpolate(truth, np.asarray([fe.t_f_ns[index]], np.int64), max_gap_s=0.1)
    if not ok[0]:
        raise ValueError(f"no ground truth around frame {index}")
    world_from_cam = np.asarray(SE3.from_translation_quat_xyzw(row[0, :3], row[0, 3:]).matrix())
    return world_from_cam @ np.linalg.inv(np.asarray(fe.rect_from_cam.matrix()))


def _project(k: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixels of (N, 3) points through the rectified intrinsics ``k``."""
    return np.c_[
        k[0, 0] * points[:, 0] / points[:, 2] + k[0, 2], k[1, 1] * points[:, 1] / points[:, 2] + k[1, 2]
    ]


def measure(sequence: Path, sim: Any, mode: str, features: str, step: int) -> dict[str, float]:
    """The statistics of one sequence in one mode (see the module)."""
    from dhptam import _core
    from dhptam.datasets import load_tumvie
    from dhptam.demo import GROUND_TRUTH
    from dhptam.eval import load_trajectory
    from dhptam.features import from_config, match
    from dhptam.frontend import Frontend
    from dhptam.viz import stereo_matches

    truth = load_trajectory(sequence / GROUND_TRUTH)
    errors: list[float] = []
    common: list[float] = []
    scatter: list[float] = []
    disparity: list[float] = []
    pairs = matched = 0
    with load_tumvie(sequence) as seq:
        # The truth is rendered for the frame cameras: event images warped into them.
        config = _core.Config.from_toml('[fusion]\nevents_geometry = "frame"\n', "<bench>")
        fe = Frontend(seq, mode, config, prefetch=0)
        extractor = from_config(
            _core.Config.from_toml(f'[features]\nextractor = "{features}"', "<bench>"),
            image_size=(int(fe.frame_rect.width), int(fe.frame_rect.height)),
        )
        k = fe.frame_rect.K
        focal_baseline = float(k[0, 0] * fe.frame_rect.baseline_m)
        camera = seq.calibration.cameras["frame_left"]
        for index in range(1, len(fe) - 1, step):
            a, b = fe.process(index), fe.process(index + 1)
            if a.bias != b.bias or a.flood or b.flood:
                continue
            fa, fa_right = extractor.extract(a.left, a.right)
            fb_left, _ = extractor.extract(b.left, b.right)
            points = _true_points(fe, sim, camera, index, np.asarray(fa.keypoints, np.float64))
            # Stereo disparities of frame k against the truth.
            scale, offset = fe.event_disparity() if a.bias in ("dvs", "events") else (1.0, 0.0)
            lr = stereo_matches(fa, fa_right, ratio=0.9, limit=None)
            if len(lr):
                pl = np.asarray(fa.keypoints, np.float64)[lr[:, 0]]
                pr = np.asarray(fa_right.keypoints, np.float64)[lr[:, 1]]
                z = points[lr[:, 0], 2]
                measured = scale * (pl[:, 0] - pr[:, 0]) + offset
                disparity.extend((measured - focal_baseline / z)[np.isfinite(z)].tolist())
            # Frame k to frame k+1.
            ab, _ = match(fa, fb_left, ratio=0.9)
            if len(ab) == 0:
                continue
            b_from_a = np.linalg.inv(_world_from_rect(fe, truth, index + 1)) @ _world_from_rect(
                fe, truth, index
            )
            p = points[ab[:, 0]]
            q = _project(k, p @ b_from_a[:3, :3].T + b_from_a[:3, 3])
            d = np.asarray(fb_left.keypoints, np.float64)[ab[:, 1]] - q
            ok = np.isfinite(d).all(axis=1)
            dist = np.linalg.norm(d[ok], axis=1)
            pairs += 1
            matched += int(ok.sum())
            errors.extend(dist.tolist())
            near = d[ok][dist < COMMON_WITHIN_PX]
            if len(near) > 5:
                shift = np.median(near, axis=0)
                common.append(float(np.linalg.norm(shift)))
                scatter.append(float(np.median(np.linalg.norm(near - shift, axis=1))))
    e, s = np.asarray(errors), np.abs(np.asarray(disparity))
    return {
        "pairs": pairs,
        "matches": matched / max(pairs, 1),
        "median": float(np.median(e)) if len(e) else float("nan"),
        "under1": float((e < 1.0).mean()) if len(e) else float("nan"),
        "over5": float((e > 5.0).mean()) if len(e) else float("nan"),
        "common": float(np.median(common)) if common else float("nan"),
        "scatter": float(np.median(scatter)) if scatter else float("nan"),
        "stereo": len(s),
        "disparity": float(np.median(s)) if len(s) else float("nan"),
        "disparity_under05": float((s < 0.5).mean()) if len(s) else float("nan"),
    }


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--modes", default="fusion,frames,events")
    parser.add_argument("--features", default="orb", help="orb, sift, r2d2 or superpoint (default orb)")
    parser.add_argument(
        "--normal-duration", type=float, default=8.0, help="seconds of the normal sequences (0: none)"
    )
    parser.add_argument("--demo-seeds", default="0", help="demo seeds, comma-separated (empty: none)")
    parser.add_argument("--step", type=int, default=4, help="every step-th frame pair (default 4)")
    parser.add_argument("--out", type=Path, default=Path("bench-keypoint-truth"))
    args = parser.parse_args()
    modes = choices(parser, args.modes, ("fusion", "frames", "events"), "mode")

    from dhptam.demo import GROUND_TRUTH, cache_dir, demo_sequence
    from dhptam.sim import simulate, simulator_for

    jobs: list[tuple[str, Path, Any]] = []
    if args.normal_duration > 0:
        root = Path(os.environ.get("DHPTAM_SHARED", REPO.parent / "shared")) / "data" / "trajectories"
        folder = cache_dir() / "sequences" / f"normal-seed1-{args.normal_duration:g}s"
        for path in sorted(p for p in root.iterdir() if p.suffix in (".csv", ".tum", ".txt")):
            if not (folder / path.stem / GROUND_TRUTH).is_file():
                simulate(
                    folder,
                    preset="desk",
                    name=path.stem,
                    seed=1,
                    duration_s=args.normal_duration,
                    trajectory=str(path),
                    overwrite=True,
                )
            sim = simulator_for("desk", seed=1, duration_s=args.normal_duration, trajectory=str(path))
            jobs.append((f"normal {args.normal_duration:g} s {path.stem}", folder / path.stem, sim))
    for seed in (int(s) for s in args.demo_seeds.split(",") if s):
        jobs.append(
            (f"demo seed {seed}", demo_sequence(seed=seed, progress=False), simulator_for("demo", seed=seed))
        )

    lines = [
        f"Every {args.step}th frame pair, {args.features} features; "
        f"{platform.node()}, {os.cpu_count()} CPUs.",
        "",
        "| sequence | mode | pairs | matches per pair | frame to frame: median [px] | < 1 px | > 5 px "
        "| common shift / scatter [px] | stereo matches | disparity error: median [px] | < 0.5 px |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, sequence, sim in jobs:
        for mode in modes:
            r = measure(sequence, sim, mode, args.features, args.step)
            lines.append(
                f"| {name} | {mode} | {r['pairs']} | {r['matches']:.0f} | {r['median']:.2f} "
                f"| {r['under1']:.0%} | {r['over5']:.0%} | {r['common']:.2f} / {r['scatter']:.2f} "
                f"| {r['stereo']} | {r['disparity']:.2f} | {r['disparity_under05']:.0%} |"
            )
    return finish_table(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
