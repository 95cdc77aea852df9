"""Ground truth the simulator knows but does not write: depth maps of any camera.

``simulator_like`` rebuilds the ``_core.Simulator`` that ``dhptam.sim.simulate`` drives for a
preset and seed (same rig, photographs, trajectory, lighting), so tests can render the exact
depth seen by a camera of a simulated sequence at any time.
"""

from __future__ import annotations

from dhptam import _core
from dhptam.datasets import CAMERA_KEYS
from dhptam.sim.presets import PRESETS, RIGS
from dhptam.sim.textures import load_photos

_NS = 1_000_000_000


def simulator_like(preset: str, seed: int = 0, duration_s: float | None = None) -> _core.Simulator:
    """The simulator of ``simulate(..., preset=preset, seed=seed, duration_s=duration_s)``
    with default settings (a built-in motion is laid out over the duration)."""
    spec = PRESETS[preset]
    rig = RIGS[spec.rig]
    cameras, imu_from_cam = rig.cameras(), rig.imu_from_cam()
    duration_ns = round((spec.duration_s if duration_s is None else duration_s) * _NS)
    traj_t, traj_poses = _core.sim_builtin_trajectory(spec.motion, duration_ns)
    return _core.Simulator(
        [cameras[k] for k in CAMERA_KEYS],
        [imu_from_cam[k] for k in CAMERA_KEYS],
        load_photos(),
        traj_t,
        traj_poses,
        spec.profile,
        min(duration_ns, int(traj_t[-1])),
        seed,
        _core.Config(),
    )
