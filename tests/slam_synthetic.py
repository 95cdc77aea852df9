"""Synthetic rectified stereo feature sequences with ground truth for the SLAM tests.

Landmarks lie on a rough cylinder around the world y axis (y down); the camera moves on a
circle of radius 1 m inside it, looking outwards. Each landmark has a random descriptor (unit
float rows, or 32-byte binary rows); every observation perturbs it and its pixel (σ in px),
and a fraction of observations are outliers at random pixels. ``drift_m``/``drift_deg``
inject drift: landmarks outside the start sector (|azimuth| > 60°) appear shifted along y /
rotated about y by an amount growing linearly to the given value at the last frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

import dhptam

CALIB = dhptam.StereoCalibration(400.0, 400.0, 320.0, 240.0, 0.12, 640, 480)


@dataclass(frozen=True)
class View:
    keypoints: NDArray[np.float32]
    descriptors: NDArray[np.float32] | NDArray[np.uint8]


@dataclass(frozen=True)
class Frame:
    t_ns: int
    world_from_cam: NDArray[np.float64]
    left: View
    right: View


def circle_pose(theta: float, radius: float = 1.0) -> NDArray[np.float64]:
    z = np.array([np.sin(theta), 0.0, np.cos(theta)])
    y = np.array([0.0, 1.0, 0.0])
    x = np.cross(y, z)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, y, z])
    pose[:3, 3] = radius * z
    return pose


def _noisy(
    rng: np.random.Generator, base: NDArray, binary: bool, sigma: float
) -> NDArray[np.float32] | NDArray[np.uint8]:
    if binary:
        flips = rng.random((base.shape[0], base.shape[1] * 8)) < 0.04
        return np.ascontiguousarray(base ^ np.packbits(flips, axis=1))
    d = base + sigma * rng.standard_normal(base.shape)
    return np.ascontiguousarray(d / np.linalg.norm(d, axis=1, keepdims=True), dtype=np.float32)


def generate(
    frames: int = 200,
    turns: float = 0.5,
    landmarks: int = 3000,
    pixel_noise: float = 0.5,
    outliers: float = 0.1,
    drift_m: float = 0.0,
    drift_deg: float = 0.0,
    binary: bool = False,
    seed: int = 0,
) -> list[Frame]:
    rng = np.random.default_rng(seed)
    c = CALIB
    azimuth = rng.uniform(-np.pi, np.pi, landmarks)
    r = rng.uniform(4.0, 7.0, landmarks)
    pts = np.column_stack([r * np.sin(azimuth), rng.uniform(-1.5, 1.5, landmarks), r * np.cos(azimuth)])
    if binary:
        desc = rng.integers(0, 256, (landmarks, 32), dtype=np.uint8)
    else:
        desc = rng.standard_normal((landmarks, 32))
        desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    deformed = np.abs(azimuth) > np.radians(60.0)
    out = []
    for i in range(frames):
        s = i / max(frames - 1, 1)
        pose = circle_pose(2 * np.pi * turns * s)
        a = np.radians(drift_deg * s)
        rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        world = pts.copy()
        world[deformed] = pts[deformed] @ rot.T + np.array([0.0, drift_m * s, 0.0])
        cam = (world - pose[:3, 3]) @ pose[:3, :3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = c.fx * cam[:, 0] / z + c.cx
            v = c.fy * cam[:, 1] / z + c.cy
            ur = u - c.fx * c.baseline_m / z
        seen = (z > 0.3) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
        right_seen = seen & (ur >= 0)
        views = []
        for mask, col in ((seen, u), (right_seen, ur)):
            n = int(mask.sum())
            kp = np.column_stack([col[mask], v[mask]]) + pixel_noise * rng.standard_normal((n, 2))
            bad = rng.random(n) < outliers
            kp[bad] = rng.uniform([0, 0], [c.width, c.height], (int(bad.sum()), 2))
            views.append(
                View(
                    np.ascontiguousarray(kp, dtype=np.float32),
                    _noisy(rng, desc[mask], binary, 0.03),
                )
            )
        out.append(Frame(i * 50_000_000, pose, views[0], views[1]))
    return out


def ate(estimated: NDArray[np.float64], truth: NDArray[np.float64]) -> float:
    """RMS position error after the best rigid alignment (Umeyama, no scale) of (N, 3) arrays."""
    me, mt = estimated.mean(axis=0), truth.mean(axis=0)
    h = (truth - mt).T @ (estimated - me)
    u, _, vt = np.linalg.svd(h)
    d = np.eye(3)
    if np.linalg.det(u @ vt) < 0:
        d[2, 2] = -1.0
    r = u @ d @ vt
    t = mt - r @ me
    return float(np.sqrt(np.mean(np.sum((estimated @ r.T + t - truth) ** 2, axis=1))))
