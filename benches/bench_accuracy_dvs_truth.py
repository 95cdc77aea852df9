"""Ground-truth diagnosis of the error on event-dominated frames of the HDR demo (issue #8).

For every ``--seeds`` the ``demo`` sequence (cached, as for ``dhptam demo``) is run in ``fusion``
mode (synchronous back-end, ORB) and measured against the simulator, which renders the true
depth of any camera at any time (``dhptam.sim.simulator_for``):

* **per point**: every keyframe's new map points (read from the map after each tracked frame;
  the map keeps points in id order, so the new ones are its tail) in that keyframe's camera
  against the true depth at their pixel: relative depth error and disparity error, split by
  the keyframe's fusion mode (APS- or DVS-biased);
* **per frame**: the step error (estimated minus true frame-to-frame translation, in the
  previous camera), split by mode and, on clean DVS frames, keyframes against the others; the
  time offset ``dt`` for which the SE(3)-aligned DVS positions fit the truth at ``t − dt``
  best (a lag of the event image behind ``t_f`` would show here);
* **per segment**: over each run of clean DVS frames, the estimated translation projected on
  the true one (1 = right length; < 1 = motion under-estimated);
* **per match**: ORB matches between two images ``gap`` frames apart against the true flow
  (true depth and poses): median distance to it, share within 1 px, slope of the measured on
  the true displacement, matches per pair; DVS-biased pairs against APS-biased ones.

    python benches/bench_accuracy_dvs_truth.py [--seeds 0,2] [--gap 3] [--out bench-dvs-truth]
"""

from __future__ import annotations

import argparse
import csv
import itertools
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np


@contextmanager
def _map_after_each_frame(log: list[tuple[int, bool, Any, Any, Any, Any]]) -> Iterator[None]:
    """Records (t_ns, keyframe, points before, points after, keyframe times, poses) per tracked frame."""
    import dhptam.system as system

    original = system.System.track

    def track(self: Any, t_ns: int, left: Any, right: Any, **how: Any) -> Any:
        before = self.map_points()
        result = original(self, t_ns, left, right, **how)
        kt, kp = self.keyframe_trajectory()
        log.append((int(t_ns), bool(result.keyframe), before, self.map_points(), kt, kp))
        return result

    system.System.track = track  # type: ignore[method-assign]
    try:
        yield
    finally:
        system.System.track = original  # type: ignore[method-assign]


class _Truth:
    """True depth of the rectified left frame camera and true poses of a demo sequence."""

    def __init__(self, sequence: Path, seed: int, frontend: Any) -> None:
        import cv2

        from dhptam.sim import simulator_for

        self.cv2 = cv2
        self.sim = simulator_for("demo", seed=seed)
        self.fe = frontend
        fx, fy, cx, cy, self.baseline, w, h = frontend.calibration
        self.k = (fx, fy, cx, cy, w, h)
        self.maps = frontend.frame_rect.remap_tables("left")
        rect_from_raw = frontend.frame_rect.rect_left_from_left.matrix()
        v, u = np.mgrid[0:h, 0:w]
        b_rect = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones((h, w))], axis=-1)
        b_rect /= np.linalg.norm(b_rect, axis=-1, keepdims=True)
        self.z_ratio = b_rect[..., 2] / (b_rect @ rect_from_raw)[..., 2]
        self.rect_from_raw = np.eye(4)
        self.rect_from_raw[:3, :3] = rect_from_raw
        gt = np.loadtxt(sequence / "groundtruth_frame_left.txt")
        self.gt = gt

    def depth(self, t_ns: int) -> Any:
        """True z [m] of every rectified left pixel at ``t_ns`` (NaN: nothing hit)."""
        raw = self.sim.render_depth(0, t_ns)
        z = self.cv2.remap(raw, *self.maps, self.cv2.INTER_NEAREST, borderValue=np.nan)
        return z * self.z_ratio

    def position(self, t_s: float) -> Any:
        return np.array([np.interp(t_s, self.gt[:, 0], self.gt[:, i]) for i in (1, 2, 3)])

    def world_from_raw(self, t_s: float) -> Any:
        """True world_from_cam of the left frame camera (as in the ground truth file) at ``t_s``."""
        from scipy.spatial.transform import Rotation, Slerp

        slerp = Slerp(self.gt[:, 0], Rotation.from_quat(self.gt[:, 4:8]))
        m = np.eye(4)
        m[:3, :3] = slerp([t_s]).as_matrix()[0]
        m[:3, 3] = self.position(t_s)
        return m

    def world_from_rect(self, t_s: float) -> Any:
        """True world_from_cam of the rectified left frame camera at ``t_s``."""
        return self.world_from_raw(t_s) @ np.linalg.inv(self.rect_from_raw)


def _new_points(before: Any, after: Any) -> Any:
    """The tail of ``after`` (id order) with no point of ``before`` within 5 mm."""
    from scipy.spatial import cKDTree

    if len(before) == 0:
        return after
    d, _ = cKDTree(before).query(after)
    i = len(after)
    while i > 0 and d[i - 1] > 0.005:
        i -= 1
    return after[i:]


def _per_point(log: list[Any], modes: dict[int, str], truth: _Truth) -> dict[str, list[float]]:
    fx, fy, cx, cy, w, h = truth.k
    out: dict[str, list[float]] = {}
    for t_ns, keyframe, before, after, kt, kp in log:
        which = np.flatnonzero(kt == t_ns)
        if not keyframe or len(before) == 0 or len(which) == 0 or t_ns not in modes:
            continue
        new = _new_points(before, after)
        cam_from_world = np.linalg.inv(kp[which[0]])
        x = new @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        x = x[x[:, 2] > 0.05]
        u = np.round(fx * x[:, 0] / x[:, 2] + cx).astype(int)
        v = np.round(fy * x[:, 1] / x[:, 2] + cy).astype(int)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        z_true = truth.depth(t_ns)[v[inside], u[inside]]
        z = x[inside, 2]
        ok = np.isfinite(z_true)
        rel = (z[ok] - z_true[ok]) / z_true[ok]
        disparity = fx * truth.baseline * (1.0 / z[ok] - 1.0 / z_true[ok])
        mode = modes[t_ns]
        out.setdefault(f"{mode}:rel", []).extend(rel.tolist())
        out.setdefault(f"{mode}:disp", []).extend(disparity.tolist())
        out.setdefault(f"{mode}:keyframes", []).append(1.0)
    return out


def _umeyama(a: Any, b: Any) -> tuple[Any, Any]:
    """Rotation and translation with b ≈ R a + t (least squares)."""
    ma, mb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((b - mb).T @ (a - ma))
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(u @ vt))
    r = u @ d @ vt
    return r, mb - r @ ma


def _per_frame(run_dir: Path, truth: _Truth) -> dict[str, Any]:
    from scipy.spatial.transform import Rotation

    with open(run_dir / "frames.csv", newline="") as f:
        rows = {round(float(r["t_s"]), 6): r for r in csv.DictReader(f)}
    est = np.loadtxt(run_dir / "trajectory_frame_left.tum")
    frames = []
    for r in est:
        row = rows[round(r[0], 6)]
        m = np.eye(4)
        m[:3, :3] = Rotation.from_quat(r[4:8]).as_matrix()
        m[:3, 3] = r[1:4]
        kind = "flood" if row["flood"] == "1" else row["bias"]
        frames.append((int(row["index"]), r[0], m, kind, row["keyframe"] == "1", row["state"]))
    steps: dict[str, list[float]] = {}
    signed: dict[str, list[float]] = {}
    for (i0, t0, m0, _, _, _), (i1, t1, m1, kind, kf, state) in itertools.pairwise(frames):
        if i1 != i0 + 1 or state == "predicted":
            continue
        g0, g1 = truth.world_from_raw(t0), truth.world_from_raw(t1)
        de = (np.linalg.inv(m0) @ m1)[:3, 3]
        dg = (np.linalg.inv(g0) @ g1)[:3, 3]
        keys = [kind] + ([f"{kind}:keyframe" if kf else f"{kind}:other"] if kind == "dvs" else [])
        for key in keys:
            steps.setdefault(key, []).append(float(np.linalg.norm(de - dg)))
            signed.setdefault(key, []).append(float((de - dg) @ dg / max(np.linalg.norm(dg), 1e-9)))
    # Time offset: aligned positions of clean DVS frames against the truth at t - dt.
    p = np.array([f[2][:3, 3] for f in frames])
    g = np.array([truth.position(f[1]) for f in frames])
    r, t = _umeyama(p, g)
    aligned = p @ r.T + t
    dvs = [k for k, f in enumerate(frames) if f[3] == "dvs" and f[5] != "predicted"]
    offsets = {}
    for dt_ms in range(-50, 51, 5):
        err = [np.linalg.norm(aligned[k] - truth.position(frames[k][1] - dt_ms * 1e-3)) for k in dvs]
        offsets[dt_ms] = float(np.median(err))
    # Segments of clean DVS frames: translation projected on the true one.
    ratios = []
    start = None
    index = [f[0] for f in frames]
    for k, f in enumerate([*frames, None]):
        clean = f is not None and f[3] == "dvs" and f[5] != "predicted"
        if clean and start is None:
            start = k
        elif not clean and start is not None:
            if k - 1 - start >= 3:
                e = (np.linalg.inv(frames[start][2]) @ frames[k - 1][2])[:3, 3]
                gt0, gt1 = truth.world_from_raw(frames[start][1]), truth.world_from_raw(frames[k - 1][1])
                tr = (np.linalg.inv(gt0) @ gt1)[:3, 3]
                ratio = float(e @ tr / (tr @ tr))
                ratios.append((index[start], index[k - 1], ratio, float(np.linalg.norm(tr))))
            start = None
    return {"steps": steps, "signed": signed, "offsets": offsets, "segments": ratios}


def _per_match(truth: _Truth, by_index: dict[int, str], gap: int) -> dict[str, list[float]]:
    import cv2

    orb = cv2.ORB_create(nfeatures=1000, nlevels=8, fastThreshold=20)
    fe = truth.fe
    fx, fy, cx, cy, _, _ = truth.k
    out: dict[str, list[float]] = {}
    for a in range(1, len(fe) - gap):
        b = a + gap
        kinds = {by_index.get(k) for k in range(a, b + 1)}
        if kinds not in ({"dvs"}, {"aps"}):
            continue  # both ends and everything between clean and of one mode
        kind = kinds.pop()
        fa, fb = fe.process(a), fe.process(b)
        k1, d1 = orb.detectAndCompute(fa.left, None)
        k2, d2 = orb.detectAndCompute(fb.left, None)
        if d1 is None or d2 is None:
            continue
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        matches = [m for m in matcher.match(d1, d2) if m.distance < 50]
        if not matches:
            continue
        p1 = np.array([k1[m.queryIdx].pt for m in matches])
        p2 = np.array([k2[m.trainIdx].pt for m in matches])
        z = truth.depth(fa.t_ns)[np.round(p1[:, 1]).astype(int), np.round(p1[:, 0]).astype(int)]
        x = np.stack([(p1[:, 0] - cx) / fx * z, (p1[:, 1] - cy) / fy * z, z], 1)
        rel = np.linalg.inv(truth.world_from_rect(fb.t_ns * 1e-9)) @ truth.world_from_rect(fa.t_ns * 1e-9)
        xb = x @ rel[:3, :3].T + rel[:3, 3]
        q = np.stack([fx * xb[:, 0] / xb[:, 2] + cx, fy * xb[:, 1] / xb[:, 2] + cy], 1)
        ok = np.isfinite(q).all(1)
        flow, moved = (q - p1)[ok], (p2 - p1)[ok]
        err = np.linalg.norm(moved - flow, axis=1)
        near = err < 3.0
        out.setdefault(f"{kind}:err", []).extend(err.tolist())
        out.setdefault(f"{kind}:pairs", []).append(float(ok.sum()))
        if near.any():
            out.setdefault(f"{kind}:slope", []).append(
                float((moved[near] * flow[near]).sum() / max((flow[near] ** 2).sum(), 1e-9))
            )
    return out


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", default="0,2")
    parser.add_argument("--gap", type=int, default=3, help="frames between the two images of a match")
    parser.add_argument("--config", default="", help="TOML text for the run's configuration")
    parser.add_argument("--out", type=Path, default=Path("bench-dvs-truth"))
    args = parser.parse_args()

    from _accuracy import evaluated_run, finish_table

    from dhptam import _core
    from dhptam.datasets import load_tumvie
    from dhptam.demo import GROUND_TRUTH, demo_sequence
    from dhptam.eval import load_trajectory
    from dhptam.frontend import Frontend

    def med(values: list[float] | None, scale: float = 1.0) -> str:
        return f"{scale * float(np.median(values)):.2f}" if values else "–"

    lines = []
    for seed in (int(s) for s in args.seeds.split(",") if s):
        sequence = demo_sequence(seed=seed, progress=False)
        out = args.out / f"seed{seed}"
        log: list[Any] = []
        with _map_after_each_frame(log):
            _, ev = evaluated_run(
                sequence, out, load_trajectory(sequence / GROUND_TRUTH), mode="fusion", features="orb",
                config=_core.Config.from_toml(args.config), threaded=False,
            )  # fmt: skip
        with open(out / "frames.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        modes = {round(float(r["t_s"]) * 1e9): ("flood" if r["flood"] == "1" else r["bias"]) for r in rows}
        with load_tumvie(sequence) as seq:
            truth = _Truth(sequence, seed, Frontend(seq, "fusion", prefetch=0))
            points = _per_point(log, modes, truth)
            frame = _per_frame(out, truth)
            by_index = {int(r["index"]): ("flood" if r["flood"] == "1" else r["bias"]) for r in rows}
            match = _per_match(truth, by_index, args.gap)
        lines += [f"### seed {seed}: fusion ATE {ev.ate_percent_of_path:.2f} % of path", ""]
        lines += [
            "| new points of keyframes | keyframes | points | median abs. depth error | median signed "
            "depth error | median abs. disparity error [px] | median signed disparity error [px] |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for mode in ("aps", "dvs"):
            rel, disp = points.get(f"{mode}:rel"), points.get(f"{mode}:disp")
            absolute = None if rel is None else np.abs(rel).tolist()
            abs_disp = None if disp is None else np.abs(disp).tolist()
            lines.append(
                f"| {mode.upper()}-biased | {len(points.get(f'{mode}:keyframes', []))} | {len(rel or [])} "
                f"| {med(absolute, 100)} % | {med(rel, 100)} % | {med(abs_disp)} | {med(disp)} |"
            )
        lines += [
            "",
            "| frames | steps | median step error [mm] | median signed error along the true step [mm] |",
            "|---|---:|---:|---:|",
        ]
        for key in ("aps", "dvs", "dvs:keyframe", "dvs:other"):
            s, g = frame["steps"].get(key), frame["signed"].get(key)
            lines.append(f"| {key} | {len(s or [])} | {med(s, 1000)} | {med(g, 1000)} |")
        best = min(frame["offsets"], key=frame["offsets"].get)
        lines += [
            "",
            f"Time offset (clean DVS frames, SE(3)-aligned): best dt = {best} ms, median position error "
            f"{1000 * frame['offsets'][best]:.1f} mm against {1000 * frame['offsets'][0]:.1f} mm at dt = 0 "
            f"(dt = ±20 ms: {1000 * frame['offsets'][-20]:.1f} / {1000 * frame['offsets'][20]:.1f} mm).",
            "",
            "DVS segments (estimated translation projected on the true one, true length): "
            + ", ".join(f"frames {a}–{b}: {r:.2f} ({1000 * n:.0f} mm)" for a, b, r, n in frame["segments"]),
            "",
            f"| ORB matches {args.gap} frames apart | pairs | matches per pair | median distance to "
            "the true flow [px] | within 1 px | slope measured / true |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for mode in ("aps", "dvs"):
            err, pairs = match.get(f"{mode}:err"), match.get(f"{mode}:pairs")
            share = f"{100 * np.mean(np.asarray(err) < 1.0):.0f} %" if err else "–"
            lines.append(
                f"| {mode.upper()}-biased | {len(pairs or [])} | {med(pairs)} | {med(err)} | {share} "
                f"| {med(match.get(f'{mode}:slope'))} |"
            )
        lines.append("")
        print("\n".join(lines[-26:]), file=sys.stderr)
    return finish_table(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
