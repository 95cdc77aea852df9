"""Dense front-end depth: semi-global matching on the rectified (fused) stereo pair (issue 5).

The paper compares dense depth maps of frames, events and fusion; we compute them with
OpenCV's ``StereoSGBM`` (Hirschmüller's semi-global matching, not a re-implementation) on the
rectified images the front-end produces, and turn them into inverse-depth maps and coloured
point clouds per keyframe.

For rectified stereo with focal length ``fx`` (pixels) and baseline ``b`` (metres), a
disparity ``d = u_left − u_right`` (pixels) gives depth ``z = fx · b / d`` and inverse depth
``1 / z = d / (fx · b)``; invalid pixels (no match, or failed the uniqueness / left-right
checks) are NaN.

Example (a synthetic pair: the right image is the left one shifted by 4 px)::

    >>> import numpy as np
    >>> from dhptam.depth import sgbm
    >>> rng = np.random.default_rng(0)
    >>> texture = (rng.random((60, 120)) * 255).astype(np.uint8)
    >>> left, right = texture[:, 10:110], texture[:, 14:114]
    >>> inv = sgbm(left, right, (100.0, 100.0, 50.0, 30.0, 0.1, 100, 60))
    >>> round(float(np.nanmedian(inv)), 6)  # d = 4 px → 1/z = 4 / (100 · 0.1)
    0.4
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from .errors import InputError
from .trajectory import atomic_write_bytes

_F32 = npt.NDArray[np.float32]


def _calibration(calibration: Sequence[float]) -> tuple[float, float, float, float, float, int, int]:
    """``(fx, fy, cx, cy, baseline_m, width, height)`` from a ``RectifiedCalibration`` or tuple."""
    values = tuple(calibration)
    if len(values) != 7:
        raise InputError(
            f"calibration must be (fx, fy, cx, cy, baseline_m, width, height), got {len(values)} values",
            field="calibration",
        )
    fx, fy, cx, cy, b = (float(v) for v in values[:5])
    if not (fx > 0 and fy > 0 and b > 0):
        raise InputError(f"fx, fy and baseline_m must be positive, got {fx}, {fy}, {b}", field="calibration")
    return fx, fy, cx, cy, b, int(values[5]), int(values[6])


def sgbm(
    left: npt.NDArray[np.uint8],
    right: npt.NDArray[np.uint8],
    calibration: Sequence[float],
    *,
    min_depth_m: float = 0.3,
    block_size: int = 5,
    uniqueness: int = 10,
) -> _F32:
    """Inverse depth (1/m, float32 ``(H, W)``, NaN where invalid) of the rectified left image.

    Parameters
    ----------
    left, right
        Rectified uint8 grayscale images of the calibration's size (e.g. ``FrontendFrame.left``
        and ``.right``).
    calibration
        ``(fx, fy, cx, cy, baseline_m, width, height)`` of the rectified left camera
        (``Frontend.calibration``).
    min_depth_m
        Nearest depth searched: the disparity range is ``fx · b / min_depth_m`` rounded up to
        a multiple of 16 (SGBM's requirement).
    block_size
        Odd matching block size; the smoothness penalties are OpenCV's usual
        ``P1 = 8 · block²``, ``P2 = 32 · block²``.
    uniqueness
        Percentage by which the best cost must beat the second best.
    """
    import cv2

    fx, _, _, _, baseline, width, height = _calibration(calibration)
    images = []
    for name, image in (("left", left), ("right", right)):
        array = np.asarray(image)
        if array.dtype != np.uint8 or array.shape != (height, width):
            raise InputError(
                f"{name} must be a uint8 ({height}, {width}) image (the calibration's size), "
                f"got {array.dtype} {array.shape}",
                field=name,
            )
        images.append(np.ascontiguousarray(array))
    if block_size < 1 or block_size % 2 == 0:
        raise InputError(f"block_size must be odd and positive, got {block_size}", field="block_size")
    if not min_depth_m > 0:
        raise InputError(f"min_depth_m must be positive, got {min_depth_m}", field="min_depth_m")
    num_disparities = 16 * max(1, math.ceil(fx * baseline / min_depth_m / 16.0))
    matcher = cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=num_disparities,
        blockSize=block_size,
        P1=8 * block_size * block_size,
        P2=32 * block_size * block_size,
        disp12MaxDiff=1,
        uniquenessRatio=uniqueness,
        speckleWindowSize=50,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM,
    )
    # SGBM returns fixed-point disparities with 4 fractional bits; invalid ones are negative.
    disparity = matcher.compute(images[0], images[1]).astype(np.float32) / 16.0
    inverse = np.full(disparity.shape, np.nan, np.float32)
    valid = disparity > 0
    inverse[valid] = disparity[valid] / np.float32(fx * baseline)
    return inverse


def point_cloud(
    inverse_depth: _F32,
    image: npt.NDArray[np.uint8],
    calibration: Sequence[float],
    *,
    world_from_cam: npt.ArrayLike | None = None,
    stride: int = 1,
    max_depth_m: float = 20.0,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.uint8]]:
    """Coloured 3-D points ``(N, 3)`` and grey colours ``(N, 3)`` uint8 of the valid pixels.

    Points are in the rectified left camera frame, or in the world when ``world_from_cam``
    (4×4, the keyframe's pose of the rectified left camera) is given; pixels farther than
    ``max_depth_m`` are dropped; ``stride`` subsamples the pixel grid.
    """
    fx, fy, cx, cy, _, width, height = _calibration(calibration)
    inv = np.asarray(inverse_depth, np.float32)
    img = np.asarray(image)
    if inv.shape != (height, width) or img.shape[:2] != (height, width):
        raise InputError(
            f"inverse_depth and image must be ({height}, {width}), got {inv.shape} and {img.shape}",
            field="inverse_depth",
        )
    v, u = np.mgrid[0:height:stride, 0:width:stride]
    rho = inv[v, u]
    keep = np.isfinite(rho) & (rho > 1.0 / max_depth_m)
    z = 1.0 / rho[keep].astype(np.float64)
    points = np.c_[(u[keep] - cx) / fx * z, (v[keep] - cy) / fy * z, z]
    if world_from_cam is not None:
        m = np.asarray(world_from_cam, np.float64)
        if m.shape != (4, 4):
            raise InputError(f"world_from_cam must be 4x4, got {m.shape}", field="world_from_cam")
        points = points @ m[:3, :3].T + m[:3, 3]
    grey = img[v, u][keep]
    colours = np.repeat(grey[:, None], 3, axis=1) if grey.ndim == 1 else grey[:, :3]
    return points, np.ascontiguousarray(colours, dtype=np.uint8)


def write_ply(path: str, points: npt.ArrayLike, colours: npt.ArrayLike | None = None) -> None:
    """Writes a binary little-endian PLY point cloud (x y z float32, optional red green blue
    uint8) atomically."""
    xyz = np.asarray(points, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be (N, 3), got {xyz.shape}", field="points")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colours is not None:
        rgb = np.asarray(colours, np.uint8)
        if rgb.shape != xyz.shape:
            raise InputError(f"colours must be (N, 3) like points, got {rgb.shape}", field="colours")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    records = np.empty(xyz.shape[0], dtype=fields)
    records["x"], records["y"], records["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if colours is not None:
        records["red"], records["green"], records["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {xyz.shape[0]}"]
    header += [f"property {types[t]} {name}" for name, t in fields]
    header.append("end_header")
    atomic_write_bytes(path, ("\n".join(header) + "\n").encode("ascii") + records.tobytes())


__all__ = ["point_cloud", "sgbm", "write_ply"]
