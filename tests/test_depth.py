"""Dense depth (dhptam.depth): StereoSGBM on rectified pairs against simulator ground truth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dhptam.datasets import load_tumvie
from dhptam.depth import point_cloud, sgbm, write_ply
from dhptam.errors import InputError
from dhptam.frontend import Frontend
from dhptam.sim import simulator_for


def _true_depth_in_rectified_left(fe: Frontend, depth_raw: np.ndarray) -> np.ndarray:
    """Ground-truth z of every rectified left pixel, from the raw camera's depth render: the
    same ray in both frames, so z_rect = z_raw / b_raw,z · b_rect,z."""
    fx, fy, cx, cy, _, w, h = fe.calibration
    map_x, map_y = fe.frame_rect.remap_tables("left")
    z_raw = cv2.remap(depth_raw, map_x, map_y, cv2.INTER_NEAREST, borderValue=np.nan)
    v, u = np.mgrid[0:h, 0:w]
    b_rect = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones((h, w))], axis=-1)
    b_rect /= np.linalg.norm(b_rect, axis=-1, keepdims=True)
    b_raw = b_rect @ fe.frame_rect.rect_left_from_left.matrix()  # rect → raw: Rᵀ b
    return z_raw / b_raw[..., 2] * b_rect[..., 2]


def test_sgbm_depth_matches_simulator_ground_truth(sim_tiny: Path) -> None:
    """Median relative depth error on normally lit frames of the tiny (128 px) sequence,
    measured 4.4–4.8 %; bounded at 8 %."""
    sim = simulator_for("tiny")
    with load_tumvie(sim_tiny) as seq:
        fe = Frontend(seq, "frames", prefetch=0)
        for k in (2, 5, 18):
            f = fe.process(k)
            inverse = sgbm(f.left, f.right, fe.calibration)
            truth = _true_depth_in_rectified_left(fe, sim.render_depth(0, f.t_ns))
            ok = np.isfinite(inverse) & np.isfinite(truth)
            assert ok.mean() > 0.5, ok.mean()
            relative = np.abs(1.0 / inverse[ok] - truth[ok]) / truth[ok]
            assert np.median(relative) < 0.08, (k, np.median(relative))


def test_point_cloud_and_ply(tmp_path: Path) -> None:
    calib = (100.0, 100.0, 4.0, 3.0, 0.1, 9, 7)
    inverse = np.full((7, 9), 0.5, np.float32)  # everything at 2 m
    inverse[0, 0] = np.nan
    image = np.arange(63, dtype=np.uint8).reshape(7, 9)
    points, colours = point_cloud(inverse, image, calib)
    assert points.shape == (62, 3) and colours.shape == (62, 3)
    assert np.allclose(points[:, 2], 2.0)
    centre = np.flatnonzero((np.abs(points[:, 0]) < 1e-12) & (np.abs(points[:, 1]) < 1e-12))
    assert colours[centre[0]].tolist() == [image[3, 4]] * 3
    world_from_cam = np.eye(4)
    world_from_cam[:3, 3] = [1.0, 2.0, 3.0]
    moved, _ = point_cloud(inverse, image, calib, world_from_cam=world_from_cam)
    assert np.allclose(moved - points, [1.0, 2.0, 3.0])
    path = tmp_path / "cloud.ply"
    write_ply(str(path), points, colours)
    data = path.read_bytes()
    header, _, body = data.partition(b"end_header\n")
    assert b"element vertex 62" in header and b"property uchar red" in header
    assert len(body) == 62 * 15
    first = np.frombuffer(body[:12], "<f4")
    assert np.allclose(first, points[0], atol=1e-6)


def test_bad_input_is_an_error() -> None:
    calib = (100.0, 100.0, 4.0, 3.0, 0.1, 9, 7)
    with pytest.raises(InputError, match=r"left must be a uint8 \(7, 9\)"):
        sgbm(np.zeros((7, 8), np.uint8), np.zeros((7, 9), np.uint8), calib)
    with pytest.raises(InputError, match="calibration"):
        sgbm(np.zeros((7, 9), np.uint8), np.zeros((7, 9), np.uint8), calib[:6])
