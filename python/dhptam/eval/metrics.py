"""Trajectory accuracy through evo: APE (ATE RMSE), RPE, coverage.

Procedure (what :func:`evaluate` does, in order):

1. The reference is interpolated at every estimate time inside its span (SE(3) geodesic
   interpolation between the two bracketing reference poses, which must be at most
   ``max_interp_gap_s`` apart). Interpolating instead of nearest-stamp association keeps a
   200 Hz reference from adding up to 2.5 ms of motion to every error.
2. evo aligns the estimate to the reference with Umeyama: ``se3`` (rotation + translation,
   for stereo) or ``sim3`` (plus scale). Estimates are never smoothed or shifted otherwise
   (SPEC-NOTES §6). When the matched positions cannot fix the rotation (all on one line, e.g.
   a back-and-forth translation, or one point), the rotation comes from the orientations
   instead: the rotation closest to the mean of ref_R·est_Rᵀ over the matched poses (chordal
   mean, by SVD), then the translation (and the ``sim3`` scale) from the positions by least
   squares. ``EvalResult.aligned_by`` says which (``"positions"`` or ``"orientations"``).
3. evo computes APE on the translation part (ATE; its RMSE is the headline number) and RPE
   on the translation part between poses ``rpe_delta`` frames apart.
4. Coverage is the fraction of the reference's time span covered by the estimate: the sum of
   the intervals between consecutive estimate stamps that are at most ``max_gap_s`` apart
   (default: three times the median estimate interval), clipped to the reference span,
   divided by that span. A tracker that loses the camera and stops reporting poses leaves a
   gap and loses coverage.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .._core import SE3
from ..errors import InputError, NumericalError
from ..trajectory import poses_to_rows, read_tum

_NS = 1_000_000_000
_I64 = npt.NDArray[np.int64]
_F64 = npt.NDArray[np.float64]
ALIGNMENTS = ("se3", "sim3")
REFERENCE_FORMATS = ("tum", "tum-vie-mocap")


@dataclass(frozen=True)
class Trajectory:
    """Times (int64 ns) and ``world_from_cam`` rows ``x y z qx qy qz qw`` (N, 7)."""

    t_ns: _I64
    rows: _F64
    source: str = ""

    def __post_init__(self) -> None:
        if self.t_ns.ndim != 1 or self.rows.shape != (self.t_ns.shape[0], 7):
            raise InputError(
                f"{self.source or 'trajectory'}: {self.t_ns.shape} times do not match rows of shape "
                f"{self.rows.shape} (expected (N, 7))",
                field="rows",
            )

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @staticmethod
    def from_poses(t_ns: npt.ArrayLike, poses: npt.ArrayLike, source: str = "") -> Trajectory:
        """From ``(N, 4, 4)`` matrices or ``(N, 7)`` rows."""
        return Trajectory(np.asarray(t_ns, np.int64), poses_to_rows(poses), source)

    def path_length_m(self) -> float:
        """Sum of the distances between consecutive positions."""
        return (
            float(np.linalg.norm(np.diff(self.rows[:, :3], axis=0), axis=1).sum()) if len(self) > 1 else 0.0
        )


def load_trajectory(
    path: str | Path,
    fmt: str = "tum",
    *,
    mocap_calibration: str | Path | None = None,
    calibration: str | Path | None = None,
) -> Trajectory:
    """Reads a trajectory of the left frame camera.

    ``fmt`` is ``tum`` (seconds, ``world_from_cam``) or ``tum-vie-mocap``: a TUM-VIE
    ``mocap_data.txt`` (or the sequence folder holding it) turned into the left frame camera's
    poses by the datasets code, world_from_cam = world_from_marker · inv(imu_from_marker) ·
    imu_from_cam. ``mocap_calibration`` (``mocap-imu-calibration*.json``) and ``calibration``
    (``camera-calibration*.json``) default to the files found next to the sequence or in its
    parent.
    """
    p = Path(path)
    if fmt == "tum":
        t_ns, rows = read_tum(p)
        return Trajectory(t_ns, rows, str(p))
    if fmt == "tum-vie-mocap":
        from ..datasets.tumvie import (
            _find_calibration,
            _load_ground_truth,
            read_basalt_calibration,
        )
        from ..errors import FileError

        seq_dir = p if p.is_dir() else p.parent
        if not p.is_dir() and p.name != "mocap_data.txt":
            raise InputError(
                f"{p}: a tum-vie-mocap reference is a sequence's mocap_data.txt (or its folder)",
                path=str(p),
                field="reference",
            )
        calib_path = Path(calibration) if calibration else _find_calibration(seq_dir, "camera-calibration")
        if calib_path is None:
            raise FileError(
                f"{seq_dir}: no camera-calibration{{A,B}}.json next to the sequence or in its parent; "
                "pass --calibration",
                path=str(seq_dir),
                field="calibration",
            )
        rig = read_basalt_calibration(calib_path)
        truth, _ = _load_ground_truth(seq_dir, rig, mocap_calibration)
        if truth is None:
            raise FileError(
                f"{seq_dir / 'mocap_data.txt'}: file not found", path=str(seq_dir / "mocap_data.txt")
            )
        return Trajectory(truth.t_ns, truth.world_from_cam, str(seq_dir / "mocap_data.txt"))
    raise InputError(
        f"unknown trajectory format {fmt!r}; choose one of {', '.join(REFERENCE_FORMATS)}", field="format"
    )


def interpolate(reference: Trajectory, t_ns: _I64, max_gap_s: float) -> tuple[_F64, npt.NDArray[np.bool_]]:
    """Reference rows at ``t_ns`` (SE(3) geodesic interpolation) and which times had a
    bracketing pair of reference poses at most ``max_gap_s`` apart."""
    ref_t = reference.t_ns
    out = np.full((t_ns.shape[0], 7), np.nan)
    ok = np.zeros(t_ns.shape[0], bool)
    j = np.searchsorted(ref_t, t_ns, side="left")
    max_gap_ns = max_gap_s * _NS
    for i, (t, k) in enumerate(zip(t_ns.tolist(), j.tolist(), strict=True)):
        if k < len(ref_t) and ref_t[k] == t:
            out[i], ok[i] = reference.rows[k], True
            continue
        if k == 0 or k >= len(ref_t):
            continue
        t0, t1 = int(ref_t[k - 1]), int(ref_t[k])
        if t1 - t0 > max_gap_ns:
            continue
        a = SE3.from_translation_quat_xyzw(reference.rows[k - 1, :3], reference.rows[k - 1, 3:])
        b = SE3.from_translation_quat_xyzw(reference.rows[k, :3], reference.rows[k, 3:])
        pose = a.interpolate(b, (t - t0) / (t1 - t0))
        out[i, :3] = pose.translation
        out[i, 3:] = pose.rotation.quat_xyzw()
        ok[i] = True
    return out, ok


def coverage(reference_t_ns: _I64, estimate_t_ns: _I64, max_gap_s: float | None = None) -> float:
    """Fraction of ``[reference first, reference last]`` covered by the estimate (see module)."""
    if len(reference_t_ns) < 2 or len(estimate_t_ns) < 2:
        return 0.0
    lo, hi = int(reference_t_ns[0]), int(reference_t_ns[-1])
    gaps = np.diff(estimate_t_ns)
    limit = 3.0 * float(np.median(gaps)) if max_gap_s is None else max_gap_s * _NS
    start = np.clip(estimate_t_ns[:-1], lo, hi)
    end = np.clip(estimate_t_ns[1:], lo, hi)
    covered = float(np.sum(np.where(gaps <= limit, end - start, 0)))
    return covered / (hi - lo) if hi > lo else 0.0


@dataclass
class EvalResult:
    """What :func:`evaluate` measured; ``to_dict`` is the JSON written by ``dhptam eval``."""

    estimate: str
    reference: str
    align: str
    poses_estimate: int
    poses_reference: int
    poses_matched: int
    coverage: float
    path_length_m: float
    ate_rmse_m: float
    ate_percent_of_path: float
    ape: dict[str, float]
    rpe: dict[str, float]
    rpe_delta_frames: int
    scale: float
    rotation_deg: float
    translation_m: list[float]
    # Per matched pose, for the plots (not in the JSON).
    t_ns: _I64 = field(repr=False, default_factory=lambda: np.empty(0, np.int64))
    errors_m: _F64 = field(repr=False, default_factory=lambda: np.empty(0))
    estimate_aligned_xyz: _F64 = field(repr=False, default_factory=lambda: np.empty((0, 3)))
    reference_xyz: _F64 = field(repr=False, default_factory=lambda: np.empty((0, 3)))
    #: What fixed the alignment's rotation: ``"positions"`` (Umeyama) or ``"orientations"``
    #: (positions on one line or point).
    aligned_by: str = "positions"

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        for key in ("t_ns", "errors_m", "estimate_aligned_xyz", "reference_xyz"):
            d.pop(key)
        return d


@dataclass(frozen=True)
class SegmentError:
    """Position error of the matched poses inside one labelled part of a run (see
    :func:`errors_by_segment`): ``poses`` of them, ``rmse_m`` their ATE RMSE (NaN without
    any)."""

    label: str
    poses: int
    rmse_m: float


def errors_by_segment(
    result: EvalResult, segments: Sequence[tuple[str, int, int]]
) -> dict[str, SegmentError]:
    """The ATE RMSE of ``result``'s matched poses inside each labelled span ``(label,
    start_ns, end_ns)`` (start included, end excluded; spans sharing a label are pooled), keyed
    by label in order of first appearance. The errors are those of ``result``'s alignment over
    the whole run: what each part contributes to the headline figure, not the part aligned on
    its own. Used for the lighting segments of simulated sequences
    (:func:`dhptam.sim.lighting_segments`).

    >>> import numpy as np
    >>> r = EvalResult("e", "r", "se3", 4, 4, 4, 1.0, 1.0, 0.0, 0.0, {}, {}, 1, 1.0, 0.0, [0.0] * 3,
    ...                t_ns=np.array([0, 1, 2, 3]), errors_m=np.array([0.1, 0.1, 0.3, 0.4]))
    >>> {k: round(v.rmse_m, 3) for k, v in errors_by_segment(r, [("a", 0, 2), ("b", 2, 3)]).items()}
    {'a': 0.1, 'b': 0.3}
    """
    for name, start, end in segments:
        if end < start:
            raise InputError(f"segment {name!r} ends before it starts ({start} > {end} ns)", field="segments")
    out: dict[str, SegmentError] = {}
    t = np.asarray(result.t_ns, np.int64)
    errors = np.asarray(result.errors_m, np.float64)
    for label in dict.fromkeys(label for label, _, _ in segments):
        inside = np.zeros(t.shape, bool)
        for name, start, end in segments:
            if name == label:
                inside |= (t >= start) & (t < end)
        n = int(np.count_nonzero(inside))
        rmse = float(np.sqrt(np.mean(errors[inside] ** 2))) if n else float("nan")
        out[label] = SegmentError(label, n, rmse)
    return out


def _evo_trajectory(t_ns: _I64, rows: _F64) -> Any:
    from evo.core.trajectory import PoseTrajectory3D

    # evo stores quaternions w-x-y-z; ours are x-y-z-w.
    return PoseTrajectory3D(
        positions_xyz=rows[:, :3].copy(),
        orientations_quat_wxyz=rows[:, [6, 3, 4, 5]].copy(),
        timestamps=t_ns.astype(np.float64) / _NS,
    )


def _orientation_alignment(est: Any, ref: Any, with_scale: bool, what: str) -> tuple[_F64, _F64, float]:
    """(R, t, s) with ref ≈ s·R·est + t where the positions alone cannot fix R: R is the
    rotation nearest to Σ ref_Rᵢ·est_Rᵢᵀ (chordal mean), s and t least squares given R."""
    ref_r = np.asarray([p[:3, :3] for p in ref.poses_se3])
    est_r = np.asarray([p[:3, :3] for p in est.poses_se3])
    u, _, vt = np.linalg.svd(np.einsum("nij,nkj->ik", ref_r, est_r))
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    e, r = np.asarray(est.positions_xyz), np.asarray(ref.positions_xyz)
    ce, cr = e.mean(axis=0), r.mean(axis=0)
    scale = 1.0
    if with_scale:
        spread = float(((e - ce) ** 2).sum())
        if spread == 0.0:
            raise NumericalError(
                f"{what}: sim3 alignment needs estimate positions that are not all one point",
                field="estimate",
            )
        scale = float((((e - ce) @ rotation.T) * (r - cr)).sum() / spread)
    return rotation, cr - scale * rotation @ ce, scale


def evaluate(
    estimate: Trajectory,
    reference: Trajectory,
    *,
    align: str = "se3",
    rpe_delta: int = 1,
    max_interp_gap_s: float = 0.1,
    max_gap_s: float | None = None,
) -> EvalResult:
    """APE/RPE/coverage of ``estimate`` against ``reference`` (see the module docstring)."""
    from evo.core import metrics

    if align not in ALIGNMENTS:
        raise InputError(f"align must be one of {', '.join(ALIGNMENTS)}, got {align!r}", field="align")
    if rpe_delta < 1:
        raise InputError(f"rpe_delta must be at least 1 frame, got {rpe_delta}", field="rpe_delta")
    ref_rows, ok = interpolate(reference, estimate.t_ns, max_interp_gap_s)
    matched = int(ok.sum())
    if matched < 3:
        raise InputError(
            f"{estimate.source or 'estimate'}: only {matched} of {len(estimate)} poses fall inside the "
            f"reference {reference.source or ''} (span {reference.t_ns[0] / _NS:.3f}–"
            f"{reference.t_ns[-1] / _NS:.3f} s); need at least 3 to align. "
            "Are both in seconds of the same clock?",
            field="estimate",
        )
    t = estimate.t_ns[ok]
    ref = _evo_trajectory(t, ref_rows[ok])
    est = _evo_trajectory(t, estimate.rows[ok])
    from evo.core import lie_algebra as lie
    from evo.core.geometry import GeometryException

    aligned_by = "positions"
    try:
        rotation, translation, scale = est.align(ref, correct_scale=align == "sim3")
    except GeometryException:
        aligned_by = "orientations"
        est = _evo_trajectory(t, estimate.rows[ok])
        rotation, translation, scale = _orientation_alignment(
            est, ref, align == "sim3", estimate.source or "estimate"
        )
        if align == "sim3":
            est.scale(scale)
        est.transform(lie.se3(rotation, translation))
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    ape_stats = {k: float(v) for k, v in ape.get_all_statistics().items()}
    rpe_stats: dict[str, float] = {}
    if matched > rpe_delta:
        rpe = metrics.RPE(
            metrics.PoseRelation.translation_part, delta=rpe_delta, delta_unit=metrics.Unit.frames
        )
        rpe.process_data((ref, est))
        rpe_stats = {k: float(v) for k, v in rpe.get_all_statistics().items()}
    path_length = Trajectory(t, ref_rows[ok]).path_length_m()
    angle = float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))
    return EvalResult(
        estimate=estimate.source,
        reference=reference.source,
        align=align,
        poses_estimate=len(estimate),
        poses_reference=len(reference),
        poses_matched=matched,
        coverage=coverage(reference.t_ns, estimate.t_ns, max_gap_s),
        path_length_m=path_length,
        ate_rmse_m=ape_stats["rmse"],
        ate_percent_of_path=100.0 * ape_stats["rmse"] / path_length if path_length > 0 else float("nan"),
        ape=ape_stats,
        rpe=rpe_stats,
        rpe_delta_frames=rpe_delta,
        scale=float(scale),
        rotation_deg=angle,
        translation_m=[float(v) for v in translation],
        t_ns=t,
        errors_m=np.asarray(ape.error, np.float64),
        estimate_aligned_xyz=np.asarray(est.positions_xyz),
        reference_xyz=np.asarray(ref.positions_xyz),
        aligned_by=aligned_by,
    )


__all__ = [
    "ALIGNMENTS",
    "REFERENCE_FORMATS",
    "EvalResult",
    "Trajectory",
    "coverage",
    "evaluate",
    "interpolate",
    "load_trajectory",
]
