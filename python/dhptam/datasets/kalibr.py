"""Kalibr ``camchain.yaml`` (and ``camchain-imucam.yaml``) import.

A camchain file has one entry ``camN`` per camera, N = 0, 1, 2, ...::

    cam1:
      camera_model: pinhole                 # the only projection dhptam reads
      intrinsics: [fu, fv, pu, pv]          # pixels
      distortion_model: radtan | equidistant
      distortion_coeffs: [k1, k2, r1, r2]   # radtan; equidistant: [k1, k2, k3, k4]
      resolution: [width, height]
      T_cn_cnm1: 4x4                        # cam1_from_cam0: maps cam(N-1) points into camN
      T_cam_imu: 4x4                        # camchain-imucam only: cam1_from_imu
      rostopic: /cam1/image_raw

Conventions (Kalibr's, stated in dhptam's naming):

* ``T_cn_cnm1`` = ``cam_from_previous_cam``, absent on ``cam0``;
* ``T_cam_imu`` = ``cam_from_imu``, so ``imu_from_cam = inverse(T_cam_imu)``;
* ``radtan`` maps to dhptam's ``Camera("radtan", [fx, fy, cx, cy, k1, k2, p1, p2, k3])`` with
  ``p1, p2 = r1, r2`` and ``k3 = 0`` (Kalibr's radtan has four coefficients); ``equidistant`` is
  Kannala–Brandt and maps to ``Camera("kb4", [fx, fy, cx, cy, k1, k2, k3, k4])``.

:func:`rig_from_kalibr` builds a :class:`~dhptam.datasets.RigCalibration` from it: with
``T_cam_imu`` on every camera the rig frame is the IMU's, otherwise it is ``cam0`` and the
chain ``cam0_from_camN = inverse(T_cn_cnm1(N) · ... · T_cn_cnm1(1))`` gives the extrinsics.

Example::

    >>> import tempfile, pathlib
    >>> from dhptam.datasets import read_kalibr_camchain
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "camchain.yaml"
    >>> _ = path.write_text('''
    ... cam0:
    ...   camera_model: pinhole
    ...   intrinsics: [300.0, 300.0, 160.0, 120.0]
    ...   distortion_model: equidistant
    ...   distortion_coeffs: [0.1, 0.0, 0.0, 0.0]
    ...   resolution: [320, 240]
    ... ''')
    >>> chain = read_kalibr_camchain(path)
    >>> chain["cam0"].camera.model, chain["cam0"].camera.params[4]
    ('kb4', 0.1)
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError, ParseError
from ..geometry import SE3, Camera
from ._common import get_key, load_yaml, numbers, se3
from .sequence import CAMERA_KEYS, RigCalibration


@dataclass(frozen=True)
class KalibrCamera:
    """One ``camN`` entry of a camchain file."""

    name: str
    camera: Camera
    cam_from_previous_cam: SE3 | None
    """``T_cn_cnm1``; ``None`` on ``cam0`` (or when the file leaves it out)."""
    cam_from_imu: SE3 | None
    """``T_cam_imu`` of camchain-imucam files; ``None`` otherwise."""
    rostopic: str | None


_CAM_KEY = re.compile(r"^cam(\d+)$")


def _camera(entry: object, path: Path, name: str) -> Camera:
    model = get_key(entry, "camera_model", path, name)
    if model != "pinhole":
        raise InputError(
            f"{path}: {name}.camera_model {model!r} is not supported (pinhole)",
            path=str(path),
            field=f"{name}.camera_model",
        )
    fx, fy, cx, cy = numbers(get_key(entry, "intrinsics", path, name), 4, path, f"{name}.intrinsics")
    dist = get_key(entry, "distortion_model", path, name)
    coeffs = get_key(entry, "distortion_coeffs", path, name)
    if dist == "radtan":
        k1, k2, r1, r2 = numbers(coeffs, 4, path, f"{name}.distortion_coeffs")
        kind, params = "radtan", [fx, fy, cx, cy, k1, k2, r1, r2, 0.0]
    elif dist in ("equidistant", "equi"):
        kind, params = "kb4", [fx, fy, cx, cy, *numbers(coeffs, 4, path, f"{name}.distortion_coeffs")]
    elif dist == "none":
        kind, params = "pinhole", [fx, fy, cx, cy]
    else:
        raise InputError(
            f"{path}: {name}.distortion_model {dist!r} is not supported (radtan, equidistant, none)",
            path=str(path),
            field=f"{name}.distortion_model",
        )
    res = get_key(entry, "resolution", path, name)
    if not (isinstance(res, list) and len(res) == 2 and all(isinstance(v, int) and v > 0 for v in res)):
        raise ParseError(
            f"{path}: {name}.resolution must be [width, height] positive integers, got {res!r}",
            path=str(path),
            field=f"{name}.resolution",
        )
    try:
        return Camera(kind, params, res[0], res[1])
    except ValueError as err:
        raise InputError(f"{path}: {name}: {err}", path=str(path), field=name) from None


def read_kalibr_camchain(path: str | Path) -> dict[str, KalibrCamera]:
    """Read every ``camN`` of a Kalibr camchain file, in N order; N must run 0, 1, 2, ..."""
    path = Path(path)
    doc = load_yaml(path, "Kalibr camchain")
    indices = sorted(int(m.group(1)) for k in doc if (m := _CAM_KEY.match(str(k))))
    if not indices:
        raise ParseError(f"{path}: no cam0, cam1, ... entries", path=str(path), field="cam0")
    if indices != list(range(len(indices))):
        missing = sorted(set(range(max(indices) + 1)) - set(indices))
        raise ParseError(
            f"{path}: camera entries must be cam0..cam{max(indices)}; missing "
            + ", ".join(f"cam{i}" for i in missing),
            path=str(path),
            field=f"cam{missing[0]}",
        )
    out: dict[str, KalibrCamera] = {}
    for i in indices:
        name = f"cam{i}"
        entry = doc[name]
        if not isinstance(entry, dict):
            raise ParseError(f"{path}: {name} must be a mapping", path=str(path), field=name)
        chain = entry.get("T_cn_cnm1")
        imu = entry.get("T_cam_imu")
        topic = entry.get("rostopic")
        out[name] = KalibrCamera(
            name=name,
            camera=_camera(entry, path, name),
            cam_from_previous_cam=None if chain is None else se3(chain, path, f"{name}.T_cn_cnm1"),
            cam_from_imu=None if imu is None else se3(imu, path, f"{name}.T_cam_imu"),
            rostopic=None if topic is None else str(topic),
        )
    return out


def cam0_from_cams(chain: dict[str, KalibrCamera], path: Path | None = None) -> dict[str, SE3]:
    """``cam0_from_camN`` for every camera, composed along ``T_cn_cnm1``."""
    out: dict[str, SE3] = {}
    camn_from_cam0 = SE3()
    for i, (name, cam) in enumerate(chain.items()):
        if i > 0:
            if cam.cam_from_previous_cam is None:
                raise ParseError(
                    f"{path}: {name}.T_cn_cnm1 is missing (needed to place {name} in the rig)",
                    path=None if path is None else str(path),
                    field=f"{name}.T_cn_cnm1",
                )
            camn_from_cam0 = cam.cam_from_previous_cam @ camn_from_cam0
        out[name] = camn_from_cam0.inverse()
    return out


def rig_from_kalibr(
    path: str | Path, mapping: dict[str, str] | None = None
) -> tuple[RigCalibration, dict[str, KalibrCamera]]:
    """A :class:`RigCalibration` from a camchain file.

    Parameters
    ----------
    path
        The camchain(-imucam) YAML.
    mapping
        Which ``camN`` each of :data:`~dhptam.datasets.CAMERA_KEYS` is. Default:
        ``cam0, cam1, cam2, cam3`` in that order when the file has four cameras; with two,
        ``cam0``/``cam1`` serve as both the frame and the event cameras (a DAVIS rig, whose
        frames and events come from one sensor).

    Returns
    -------
    The rig (``imu_from_cam`` in the IMU frame when every used camera has ``T_cam_imu``,
    else in ``cam0``'s frame) and the parsed entries.
    """
    path = Path(path)
    chain = read_kalibr_camchain(path)
    if mapping is None:
        if len(chain) >= 4:
            mapping = dict(zip(CAMERA_KEYS, ("cam0", "cam1", "cam2", "cam3"), strict=True))
        elif len(chain) >= 2:
            mapping = dict(zip(CAMERA_KEYS, ("cam0", "cam1", "cam0", "cam1"), strict=True))
        else:
            raise InputError(
                f"{path}: a stereo rig needs at least cam0 and cam1; the file has {len(chain)} camera(s)",
                path=str(path),
                field="cam1",
            )
    for key in CAMERA_KEYS:
        name = mapping.get(key)
        if name not in chain:
            raise InputError(
                f"{path}: the rig's {key} is mapped to {name!r}, which the file does not have "
                f"(it has {', '.join(chain)})",
                path=str(path),
                field=str(name),
            )
    used = [chain[mapping[k]] for k in CAMERA_KEYS]
    if all(c.cam_from_imu is not None for c in used):
        imu_from_cam = {k: chain[mapping[k]].cam_from_imu.inverse() for k in CAMERA_KEYS}  # type: ignore[union-attr]
    else:
        cam0_from = cam0_from_cams(chain, path)
        imu_from_cam = {k: cam0_from[mapping[k]] for k in CAMERA_KEYS}
    cameras = {k: chain[mapping[k]].camera for k in CAMERA_KEYS}
    return RigCalibration(cameras=cameras, imu_from_cam=imu_from_cam), chain


__all__ = ["KalibrCamera", "cam0_from_cams", "read_kalibr_camchain", "rig_from_kalibr"]
