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
"""

from __future__ import annotations

from ._core import SE3, SO3, Camera

__all__ = ["SE3", "SO3", "Camera"]
