"""Generate a stereo events+frames sequence with exact ground truth, in the TUM-VIE layout."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .. import _core
from .._core import Config
from ..datasets import CAMERA_KEYS, RigCalibration, TumVieWriter, compose_poses
from ..errors import InputError
from ..eval.segments import LIGHTING_FILE, segments_text
from .presets import (
    DEFAULT_PRESET,
    IMU_FROM_MARKER,
    MOTIONS,
    PRESETS,
    PROFILES,
    RIGS,
    Preset,
    RigSpec,
    lighting_segments,
)
from .textures import load_photos

log = logging.getLogger(__name__)

MOCAP_RATE_HZ = 120.0
GROUND_TRUTH_RATE_HZ = 200.0
GROUND_TRUTH_FILE = "groundtruth_frame_left.txt"
_NS = 1_000_000_000


@dataclass(frozen=True)
class SimulationSummary:
    """What :func:`simulate` wrote."""

    path: Path
    frames: int
    events_left: int
    events_right: int
    duration_ns: int
    renders: int
    seconds: float


def _trajectory(spec: str, duration_ns: int | None) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """A built-in motion by name, or a TUM (``.txt``/``.tum``) or CSV (``.csv``) file."""
    if spec in MOTIONS:
        if duration_ns is None:
            raise InputError("a built-in motion needs a duration", field="duration")
        return _core.sim_builtin_trajectory(spec, duration_ns)
    path = Path(spec)
    if not path.exists():
        raise InputError(
            f"trajectory {spec!r} is neither a built-in motion ({', '.join(MOTIONS)}) nor an existing file",
            field="trajectory",
        )
    fmt = "csv" if path.suffix.lower() == ".csv" else "tum"
    return _core.sim_file_trajectory(str(path), fmt)


def _tum_lines(t_ns: npt.NDArray[np.int64], poses: npt.NDArray[np.float64]) -> str:
    rows = [
        f"{t // _NS}.{t % _NS:09d} " + " ".join(f"{v:.9f}" for v in pose)
        for t, pose in zip(t_ns.tolist(), poses, strict=True)
    ]
    return "# timestamp[s] tx ty tz qx qy qz qw (world_from_cam of frame_left)\n" + "\n".join(rows) + "\n"


def _build(
    spec: Preset,
    seed: int,
    duration_s: float | None,
    profile: str,
    motion: str,
    config: Config,
    shake: tuple[float, float] | None,
    pause: tuple[float, float] | None = None,
) -> tuple[_core.Simulator, RigSpec, int]:
    """The simulator of a preset's rig along ``motion``, its rig and the simulated span (ns)."""
    rig = RIGS[spec.rig]
    cameras, imu_from_cam = rig.cameras(), rig.imu_from_cam()
    requested_ns = round((duration_s if duration_s is not None else spec.duration_s) * _NS)
    traj_t, traj_poses = _trajectory(motion, requested_ns)
    if pause is not None:
        traj_t, traj_poses = _paused(traj_t, traj_poses, _span_ns(pause, "pause"))
    if shake is not None:
        traj_poses = _shaken(traj_t, traj_poses, _span_ns(shake, "shake"))
    duration_ns = min(requested_ns, int(traj_t[-1]))
    sim = _core.Simulator(
        [cameras[k] for k in CAMERA_KEYS],
        [imu_from_cam[k] for k in CAMERA_KEYS],
        load_photos(),
        traj_t,
        traj_poses,
        profile,
        duration_ns,
        seed,
        config,
    )
    return sim, rig, duration_ns


def simulator_for(
    preset: str = DEFAULT_PRESET,
    *,
    seed: int = 0,
    duration_s: float | None = None,
    trajectory: str | None = None,
    config: Config | None = None,
) -> _core.Simulator:
    """The simulator that :func:`simulate` drives for the same arguments (same rig,
    photographs, trajectory, lighting and seed), for ground truth a sequence's files do not
    hold, such as ``render_depth`` of any camera at any time."""
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}", field="preset")
    spec = PRESETS[preset]
    motion = trajectory or spec.motion
    return _build(spec, seed, duration_s, spec.profile, motion, config or Config(), None)[0]


def simulate(
    out_dir: str | Path,
    *,
    preset: str = DEFAULT_PRESET,
    name: str | None = None,
    seed: int = 0,
    duration_s: float | None = None,
    profile: str | None = None,
    trajectory: str | None = None,
    config: Config | None = None,
    overwrite: bool = False,
    progress: bool = False,
    blackout: tuple[float, float] | None = None,
    shake: tuple[float, float] | None = None,
    hot_pixels: float = 0.0,
    pause: tuple[float, float] | None = None,
) -> SimulationSummary:
    """Simulate a sequence and write it to ``out_dir / name`` in the TUM-VIE layout.

    Parameters
    ----------
    out_dir
        Parent folder of the sequence.
    preset
        One of :data:`dhptam.sim.PRESETS` (rig size, motion, lighting, duration).
    name
        Sequence name (folder and file prefix); the preset's name by default.
    seed
        Seeds the procedural textures, threshold mismatch, event and frame noise: the same
        seed gives byte-identical event files and images.
    duration_s
        Overrides the preset's duration (for a file trajectory: at most the file's span).
    profile
        Overrides the lighting: ``normal``, ``hdr``, ``flicker`` or ``dark``.
    trajectory
        Overrides the motion: a built-in name or a TUM / CSV trajectory file, which is fitted
        into the room.
    config
        Supplies the ``[sim]`` section (thresholds, noise, sensor, frame rate).
    overwrite
        Replace an existing sequence folder.
    progress
        Show a progress bar (tqdm) on stderr.
    blackout
        ``(start_s, duration_s)``: the lenses are covered over that span (tracking-loss tests).
        Frames whose exposure starts inside it are black (all zero) and the events inside it
        are dropped; the event cameras' per-pixel references keep following the scene, so the
        uncovering gives no burst of events (a real sensor would give one).
    shake
        ``(start_s, duration_s)``: a violent hand shake added to the motion over that span
        (see :func:`shake_offsets`): rotation up to about 0.33 rad about all axes at
        6-9 Hz (rates up to about 20 rad/s) and a few centimetres of translation, faded in and
        out over 0.1 s.
    pause
        ``(start_s, duration_s)``: the camera stops for that long (see :func:`_paused`), then
        goes on along the rest of the motion, shifted by the pause; the sequence keeps its
        duration, so its motion ends ``duration_s`` earlier.
    hot_pixels
        Fraction of each event camera's pixels that are hot (:class:`HotPixelSource`), like a
        real sensor's defective pixels; 0 (default) adds none.

    Returns
    -------
    SimulationSummary
        The sequence folder and counts. The folder holds the TUM-VIE files
        (``load_tumvie`` reads them) plus ``groundtruth_frame_left.txt``, the left frame
        camera's poses as a TUM trajectory, and ``lighting.csv``, the spans lit at one level
        (:func:`lighting_segments`; a segments file, :mod:`dhptam.eval.segments`).
    """
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}", field="preset")
    spec = PRESETS[preset]
    profile = profile or spec.profile
    if profile not in PROFILES:
        raise InputError(f"unknown profile {profile!r}; choose one of {', '.join(PROFILES)}", field="profile")
    if duration_s is not None and not duration_s > 0:
        raise InputError(f"duration must be positive, got {duration_s}", field="duration")
    config = config or Config()
    fps = float(config.to_dict()["sim"]["fps"])
    covered = _span_ns(blackout, "blackout") if blackout is not None else None
    motion = trajectory or spec.motion

    started = time.perf_counter()
    sim, rig, duration_ns = _build(spec, seed, duration_s, profile, motion, config, shake, pause)
    cameras, imu_from_cam = rig.cameras(), rig.imu_from_cam()
    frame_step_ns = round(_NS / fps)
    n_frames = max(1, duration_ns // frame_step_ns)
    log.info(
        "simulating %s: preset %s, %s, %s lighting, %.2f s, %d frame pairs, seed %d",
        name or preset,
        preset,
        motion,
        profile,
        duration_ns / _NS,
        n_frames,
        seed,
    )
    calibration = RigCalibration(cameras=cameras, imu_from_cam=imu_from_cam)
    hot = {
        side: HotPixelSource(
            cameras[f"event_{side}"].width, cameras[f"event_{side}"].height, hot_pixels, seed, side
        )
        for side in ("left", "right")
    }
    counts = {"left": 0, "right": 0}
    bar = _progress(n_frames, progress)
    with TumVieWriter(out_dir, name or preset, calibration, IMU_FROM_MARKER, overwrite=overwrite) as writer:
        for k in range(n_frames):
            t_ns = k * frame_step_ns
            exposure_ns, left, right = sim.frame_pair(t_ns)
            if covered is not None and covered[0] <= t_ns < covered[1]:
                left, right = np.zeros_like(left), np.zeros_like(right)
            writer.add_frame_pair(t_ns, exposure_ns, left, right)
            t_end = duration_ns if k == n_frames - 1 else (k + 1) * frame_step_ns
            t_start = k * frame_step_ns
            for side, (x, y, t, p) in zip(("left", "right"), sim.events_until(t_end), strict=True):
                x, y, t, p = hot[side].merged(x, y, t, p, t_start, t_end)
                if covered is not None:
                    seen = (t < covered[0]) | (t >= covered[1])
                    x, y, t, p = x[seen], y[seen], t[seen], p[seen]
                writer.add_events(side, x, y, t, p)
                counts[side] += len(t)
            if bar is not None:
                bar.update(1)
        mocap_t = np.arange(0, duration_ns + 1, round(_NS / MOCAP_RATE_HZ), dtype=np.int64)
        writer.set_mocap(mocap_t, compose_poses(sim.world_from_body(mocap_t), IMU_FROM_MARKER))
        gt_t = np.arange(0, duration_ns + 1, round(_NS / GROUND_TRUTH_RATE_HZ), dtype=np.int64)
        writer.add_text_file(GROUND_TRUTH_FILE, _tum_lines(gt_t, sim.world_from_cam(0, gt_t)))
        writer.add_text_file(LIGHTING_FILE, segments_text(lighting_segments(profile, duration_ns / _NS)))
    if bar is not None:
        bar.close()
    path = Path(out_dir) / (name or preset)
    summary = SimulationSummary(
        path=path,
        frames=n_frames,
        events_left=counts["left"],
        events_right=counts["right"],
        duration_ns=duration_ns,
        renders=sim.render_count,
        seconds=time.perf_counter() - started,
    )
    log.info("wrote %s in %.1f s (%d renders)", path, summary.seconds, summary.renders)
    return summary


class HotPixelSource:
    """The hot pixels of one simulated event camera: pixels that fire on their own.

    ``round(fraction · width · height)`` pixels, drawn from ``seed`` (and the side), each firing
    one polarity periodically at its own rate, log-uniform between :attr:`RATES_HZ`, with a
    random phase, whatever the scene does. :meth:`merged` adds their events of a span to the
    simulator's events of the same span.
    """

    #: Range of the hot pixels' rates, Hz.
    RATES_HZ = (20.0, 2000.0)

    def __init__(self, width: int, height: int, fraction: float, seed: int, side: str) -> None:
        if not 0.0 <= float(fraction) <= 0.1:
            raise InputError(
                f"hot_pixels must be a fraction of the pixels in [0, 0.1], got {fraction!r}",
                field="hot_pixels",
            )
        rng = np.random.default_rng([int(seed), 0x407, 0 if side == "left" else 1])
        n = round(float(fraction) * width * height)
        index = rng.choice(width * height, size=n, replace=False)
        self.x = (index % width).astype(np.uint16)
        self.y = (index // width).astype(np.uint16)
        low, high = np.log(self.RATES_HZ[0]), np.log(self.RATES_HZ[1])
        self.period_ns = np.round(_NS / np.exp(rng.uniform(low, high, size=n))).astype(np.int64)
        self.phase_ns = (rng.uniform(0.0, 1.0, size=n) * self.period_ns).astype(np.int64)
        self.p = rng.integers(0, 2, size=n).astype(np.int8)

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def events(self, t0_ns: int, t1_ns: int) -> tuple[npt.NDArray[Any], ...]:
        """The hot pixels' events in ``(t0_ns, t1_ns]``, sorted by time."""
        first = -((self.phase_ns - t0_ns) // self.period_ns)  # least m with phase + m·period > t0
        first = np.where(self.phase_ns + first * self.period_ns > t0_ns, first, first + 1)
        last = (t1_ns - self.phase_ns) // self.period_ns  # greatest m with phase + m·period <= t1
        count = np.maximum(last - first + 1, 0)
        pixel = np.repeat(np.arange(len(self)), count)
        step = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
        t = self.phase_ns[pixel] + (first[pixel] + step) * self.period_ns[pixel]
        order = np.argsort(t, kind="stable")
        return self.x[pixel][order], self.y[pixel][order], t[order], self.p[pixel][order]

    def merged(
        self,
        x: npt.NDArray[Any],
        y: npt.NDArray[Any],
        t: npt.NDArray[Any],
        p: npt.NDArray[Any],
        t0_ns: int,
        t1_ns: int,
    ) -> tuple[npt.NDArray[Any], ...]:
        """The events ``(x, y, t, p)`` of ``(t0_ns, t1_ns]`` with the hot pixels' added, sorted
        by time (the given events first among equal times); unchanged without hot pixels."""
        if len(self) == 0:
            return x, y, t, p
        hx, hy, ht, hp = self.events(t0_ns, t1_ns)
        t_all = np.concatenate([np.asarray(t, np.int64), ht])
        order = np.argsort(t_all, kind="stable")
        return (
            np.concatenate([np.asarray(x, np.uint16), hx])[order],
            np.concatenate([np.asarray(y, np.uint16), hy])[order],
            t_all[order],
            np.concatenate([np.asarray(p, np.int8), hp])[order],
        )


def _span_ns(span: tuple[float, float], field: str) -> tuple[int, int]:
    start_s, duration_s = (float(v) for v in span)
    if not (np.isfinite(start_s) and np.isfinite(duration_s) and start_s >= 0 and duration_s > 0):
        raise InputError(
            f"{field} must be (start_s >= 0, duration_s > 0), got ({start_s}, {duration_s})", field=field
        )
    return round(start_s * _NS), round((start_s + duration_s) * _NS)


def shake_offsets(t_s: npt.NDArray[np.float64], duration_s: float) -> npt.NDArray[np.float64]:
    """The violent shake: body-frame rotation vectors (rad) and translations (m), (N, 6),
    at times ``t_s`` counted from the start of the shake.

    Sums of sines at 6-9 Hz with amplitudes up to 0.2-0.25 rad per axis (rotation angles up to
    about 0.33 rad, angular rates up to about 20 rad/s) and 2-3 cm, under a raised-cosine
    envelope of 0.1 s at both ends (zero outside ``[0, duration_s]``).
    """
    ramp = 0.1
    env = np.clip(np.minimum(t_s, duration_s - t_s) / ramp, 0.0, 1.0)
    env = 0.5 - 0.5 * np.cos(np.pi * env)
    out = np.empty((len(t_s), 6))
    for axis, (amp_rad, amp_m, hz, phase) in enumerate(
        ((0.25, 0.03, 7.3, 0.0), (0.22, 0.02, 8.9, 1.1), (0.20, 0.025, 6.1, 2.3))
    ):
        wave = np.sin(2 * np.pi * hz * t_s + phase) + 0.4 * np.sin(2 * np.pi * 1.7 * hz * t_s + 2 * phase)
        out[:, axis] = amp_rad * env * wave / 1.4
        out[:, 3 + axis] = amp_m * env * np.cos(2 * np.pi * hz * t_s + phase)
    return out


def _paused(
    t_ns: npt.NDArray[np.int64], poses: npt.NDArray[np.float64], span_ns: tuple[int, int]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """The trajectory samples ``(t_ns, poses)`` with the camera held still over the pause
    ``span_ns``: from the last sample at or before its start (the first sample when the pause
    starts before it), the pose stays for the pause's duration, and the later samples follow
    shifted by it. A pause after the last sample leaves the trajectory unchanged."""
    start, end = span_ns
    held = max(int(np.searchsorted(t_ns, start, side="right")) - 1, 0)
    if t_ns[held] > start or start > t_ns[-1]:
        return t_ns, poses
    after = np.arange(held, len(t_ns))
    return (
        np.concatenate([t_ns[: held + 1], t_ns[after] + (end - start)]),
        np.concatenate([poses[: held + 1], poses[after]]),
    )


def _shaken(
    t_ns: npt.NDArray[np.int64], poses: npt.NDArray[np.float64], span_ns: tuple[int, int]
) -> npt.NDArray[np.float64]:
    """``world_from_body · [exp(ω(t)) | τ(t)]`` over the shake span, poses as (N, 7) x-y-z-w."""
    inside = (t_ns >= span_ns[0]) & (t_ns <= span_ns[1])
    offsets = shake_offsets((t_ns[inside] - span_ns[0]) / _NS, (span_ns[1] - span_ns[0]) / _NS)
    out = poses.copy()
    q_body = poses[inside, 3:]
    angle = np.linalg.norm(offsets[:, :3], axis=1, keepdims=True)
    axis = offsets[:, :3] / np.maximum(angle, 1e-12)
    q_shake = np.hstack([axis * np.sin(angle / 2), np.cos(angle / 2)])
    out[inside, :3] = poses[inside, :3] + _rotate(q_body, offsets[:, 3:])
    out[inside, 3:] = _quat_mul(q_body, q_shake)
    return out


def _quat_mul(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Hamilton products of (N, 4) x-y-z-w quaternions."""
    av, aw, bv, bw = a[:, :3], a[:, 3:], b[:, :3], b[:, 3:]
    return np.hstack([aw * bv + bw * av + np.cross(av, bv), aw * bw - np.sum(av * bv, axis=1, keepdims=True)])


def _rotate(q: npt.NDArray[np.float64], v: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Rotates (N, 3) vectors by (N, 4) x-y-z-w unit quaternions."""
    u, w = q[:, :3], q[:, 3:]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _progress(total: int, enabled: bool):  # type: ignore[no-untyped-def]
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=total, unit="frame", desc="simulate", leave=False)
