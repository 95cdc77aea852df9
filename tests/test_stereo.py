"""Stereo rectification and triangulation through the binding, checked against OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import dhptam
from dhptam import SE3, SO3, Camera, RectifiedStereo, StereoRig, triangulate

KB4 = Camera("kb4", [747.3, 747.2, 490.8, 506.3, 0.0037, 0.0181, -0.0302, 0.0173], 1024, 1024)
KB4_RIGHT = Camera("kb4", [744.1, 744.0, 500.2, 503.9, 0.0051, 0.0140, -0.0260, 0.0150], 1024, 1024)
RADTAN = Camera("radtan", [458.7, 457.3, 367.2, 248.4, -0.2834, 0.0740, 1.9e-4, 1.8e-5, 0.0], 752, 480)
RADTAN_RIGHT = Camera(
    "radtan", [457.6, 456.1, 379.9, 255.2, -0.2836, 0.0745, -1.0e-4, -3.6e-5, 0.0], 752, 480
)


def random_rig(left: Camera, right: Camera, rng: np.random.Generator) -> StereoRig:
    """The right camera 5–20 cm to the right, rotated by up to ~3°."""
    baseline = rng.uniform(0.05, 0.2)
    right_from_left = SE3(SO3.exp(rng.normal(scale=0.03, size=3)), [-baseline, 0.0, 0.0]) @ SE3(
        translation=rng.normal(scale=0.003, size=3)
    )
    return StereoRig(left, right, right_from_left)


def points_seen_by_both(rig: StereoRig, n: int, rng: np.random.Generator) -> np.ndarray:
    points = rng.uniform([-1.0, -0.8, 1.0], [1.0, 0.8, 6.0], size=(n, 3))
    uv_l = rig.left.project(points)
    uv_r = rig.right.project(rig.right_from_left @ points)
    seen = rig.left.contains(uv_l) & rig.right.contains(uv_r)
    return points[seen]


@pytest.mark.parametrize(("left", "right"), [(KB4, KB4_RIGHT), (RADTAN, RADTAN_RIGHT)])
def test_rectified_correspondences_share_rows(left, right, rng):
    for _ in range(5):
        rig = random_rig(left, right, rng)
        rect = RectifiedStereo(rig)
        points = points_seen_by_both(rig, 500, rng)
        rl = rect.rectify_pixels("left", rig.left.project(points))
        rr = rect.rectify_pixels("right", rig.right.project(rig.right_from_left @ points))
        ok = np.isfinite(rl).all(axis=1) & np.isfinite(rr).all(axis=1)
        assert ok.mean() > 0.95
        np.testing.assert_allclose(rl[ok, 1], rr[ok, 1], atol=1e-6)
        assert (rl[ok, 0] - rr[ok, 0] > 0).all()
        # The projection matrices give the same pixels for the points in the rectified frame.
        p_rect = rect.rect_left_from_left @ points
        pl, pr = rect.project(p_rect)
        np.testing.assert_allclose(pl[ok], rl[ok], atol=1e-6)
        np.testing.assert_allclose(pr[ok], rr[ok], atol=1e-6)
        hom = np.c_[p_rect, np.ones(len(p_rect))] @ rect.P_right.T
        np.testing.assert_allclose(hom[ok, :2] / hom[ok, 2:], rr[ok], atol=1e-6)


def test_rectifying_rotations_agree_with_opencv(rng):
    """For a pinhole pair the rectified x axis is the baseline, as in OpenCV's Bouguet method.

    The roll about the baseline is a free choice (OpenCV takes the smallest rotation carrying
    the half-rotated baseline onto x); both choices differ only by a small rotation about x.
    """
    cam = Camera("pinhole", [458.0, 457.0, 367.2, 248.4], 752, 480)
    for _ in range(5):
        rig = random_rig(cam, cam, rng)
        m = rig.right_from_left.matrix()
        no_dist = np.zeros(5)
        r1, r2, *_ = cv2.stereoRectify(
            cam.K, no_dist, cam.K, no_dist, (752, 480), m[:3, :3], m[:3, 3:].copy(), alpha=0
        )
        rect = RectifiedStereo(rig)
        for ours, theirs in (
            (rect.rect_left_from_left.matrix(), r1),
            (rect.rect_right_from_right.matrix(), r2),
        ):
            np.testing.assert_allclose(ours[0], theirs[0], atol=1e-9)
            difference = SO3.from_matrix(ours @ theirs.T).log()
            np.testing.assert_allclose(difference[1:], 0.0, atol=1e-9)  # a rotation about x only
            assert abs(difference[0]) < 0.01


def test_remap_tables_drive_cv2_remap_and_match_rectify_image(rng):
    rig = random_rig(RADTAN, RADTAN_RIGHT, rng)
    rect = RectifiedStereo(rig)
    image = cv2.GaussianBlur(rng.integers(0, 256, size=(480, 752), dtype=np.uint8), (7, 7), 2.0)
    for side in ("left", "right"):
        map_x, map_y = rect.remap_tables(side)
        assert map_x.dtype == np.float32
        assert map_x.shape == (rect.height, rect.width)
        ours = rect.rectify_image(side, image)
        theirs = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        inner = (map_x > 1) & (map_y > 1) & (map_x < 750) & (map_y < 478)
        assert inner.mean() > 0.9
        # OpenCV interpolates with 5-bit fixed-point weights; allow one grey level of rounding.
        assert np.abs(ours.astype(int) - theirs.astype(int))[inner].max() <= 1
        as_float = rect.rectify_image(side, image.astype(np.float32))
        assert np.abs(as_float - ours)[inner].max() <= 0.5 + 1e-3


def test_triangulation_of_rectified_correspondences(rng):
    rig = random_rig(KB4, KB4_RIGHT, rng)
    rect = RectifiedStereo(rig)
    truth = rng.uniform([-0.5, -0.5, 1.0], [0.5, 0.5, 5.0], size=(200, 3))
    uv_l, uv_r = rect.project(truth)
    points, accepted, reasons = rect.triangulate(uv_l, uv_r[:, 0])
    assert accepted.all()
    assert all(r is None for r in reasons)
    np.testing.assert_allclose(points, truth, rtol=1e-9)
    # Zero and negative disparity are rejected with the reason.
    points, accepted, reasons = rect.triangulate(uv_l[:2], [uv_l[0, 0], uv_l[1, 0] + 3.0])
    assert not accepted.any()
    assert np.isnan(points).all()
    assert "minimum" in reasons[0] or "farther" in reasons[0] or "inf" in reasons[0]
    assert "behind" in reasons[1]


def test_multiview_triangulation(rng):
    fx, fy, cx, cy = 450.0, 450.0, 320.0, 240.0
    cam = Camera("pinhole", [fx, fy, cx, cy], 640, 480)
    truth = np.array([0.3, -0.2, 4.0])
    cams_from_world = [
        SE3.exp(np.r_[rng.normal(scale=0.3, size=3), rng.normal(scale=0.05, size=3)]) for _ in range(3)
    ]
    pixels = np.array([cam.project((c @ truth)[None])[0] for c in cams_from_world])
    result = triangulate(cams_from_world, pixels, [fx, fy, cx, cy])
    assert result.accepted
    np.testing.assert_allclose(result.point_world, truth, rtol=1e-9)
    assert result.parallax_deg > 1.0
    too_close = triangulate(
        cams_from_world,
        pixels,
        [fx, fy, cx, cy],
        dhptam.Config.from_toml("[triangulation]\nmin_depth_m = 10.0\nmax_depth_m = 20.0\n"),
    )
    assert not too_close.accepted
    assert too_close.point_world is None
    assert "closer" in too_close.rejection


def test_bad_arguments_name_the_problem(rng):
    rect = RectifiedStereo(random_rig(RADTAN, RADTAN_RIGHT, rng))
    with pytest.raises(dhptam.InputError, match="side"):
        rect.remap_tables("middle")
    with pytest.raises(dhptam.InputError, match=r"\(480, 752\)"):
        rect.rectify_image("left", np.zeros((10, 10), dtype=np.uint8))
    with pytest.raises(dhptam.InputError, match="u_right"):
        rect.triangulate(np.zeros((3, 2)), np.zeros(2))
    with pytest.raises(dhptam.InputError, match="baseline"):
        RectifiedStereo(StereoRig(RADTAN, RADTAN_RIGHT, SE3()))
    # Cameras looking along their own baseline cannot be rectified to horizontal rows.
    with pytest.raises(dhptam.NumericalError):
        RectifiedStereo(StereoRig(RADTAN, RADTAN_RIGHT, SE3(translation=[0.0, 0.0, -0.1])))
