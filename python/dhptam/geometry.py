"""Geometry: SO(3)/SE(3), camera models, stereo rectification and triangulation.

All of it is implemented in the Rust core; this module is the public place to import it
from. Conventions:

* transforms are named by the frames they map: ``world_from_cam @ p_cam == p_world``;
* SE(3) tangent vectors are ``[rho, phi]`` (translation part first);
* quaternions cross the API in ``(x, y, z, w)`` order (Hamilton), as in TUM trajectories;
* pixel ``(0, 0)`` is the centre of the top-left pixel (OpenCV convention);
* camera parameters follow OpenCV's order: radtan ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]``,
  kb4 ``[fx, fy, cx, cy, k1, k2, k3, k4]``.

Array arguments are read in place when they are float64 and C-contiguous (otherwise they are
converted once), and the heavy calls release the GIL.

Example: rectify a stereo pair and triangulate a correspondence::

    >>> import numpy as np
    >>> from dhptam.geometry import Camera, SE3, StereoRig, RectifiedStereo
    >>> cam = Camera("pinhole", [400.0, 400.0, 320.0, 240.0], 640, 480)
    >>> rig = StereoRig(cam, cam, SE3(translation=[-0.1, 0.0, 0.0]))  # right 10 cm to the right
    >>> rect = RectifiedStereo(rig)
    >>> uv_l, uv_r = rect.project(np.array([[0.2, 0.1, 2.0]]))
    >>> points, ok, why = rect.triangulate(uv_l, uv_r[:, 0])
    >>> np.allclose(points, [[0.2, 0.1, 2.0]]), bool(ok[0])
    (True, True)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ._core import SE3, SO3, Camera, Config, RectifiedStereo, StereoRig, _triangulate


@dataclass(frozen=True)
class Triangulation:
    """Outcome of :func:`triangulate` for one point.

    ``point_world`` is ``None`` when the point was rejected; ``rejection`` then says why
    (behind a camera, too close or far, too little parallax, reprojection error).
    """

    point_world: npt.NDArray[np.float64] | None
    parallax_deg: float
    max_reprojection_px: float
    rejection: str | None

    @property
    def accepted(self) -> bool:
        """Whether the point passed every check."""
        return self.rejection is None


def triangulate(
    cams_from_world: Sequence[SE3],
    pixels: npt.ArrayLike,
    intrinsics: npt.ArrayLike,
    config: Config | None = None,
) -> Triangulation:
    """Triangulate one point observed by several rectified (pinhole) cameras.

    Parameters
    ----------
    cams_from_world
        One transform per view, mapping world points into that camera.
    pixels
        ``(V, 2)`` observations, one per view.
    intrinsics
        ``(fx, fy, cx, cy)`` of the pinhole cameras.
    config
        Supplies the ``[triangulation]`` thresholds; defaults when omitted.
    """
    point, parallax, error, rejection = _triangulate(list(cams_from_world), pixels, intrinsics, config)
    return Triangulation(
        point_world=None if point is None else np.asarray(point, dtype=np.float64),
        parallax_deg=parallax,
        max_reprojection_px=error,
        rejection=rejection,
    )


__all__ = ["SE3", "SO3", "Camera", "RectifiedStereo", "StereoRig", "Triangulation", "triangulate"]
