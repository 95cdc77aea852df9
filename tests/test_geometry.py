"""The geometry binding: Lie groups, camera models, and their agreement with OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import dhptam
from dhptam import SE3, SO3, Camera

N_EXAMPLES = 20


def random_rotation_vectors(rng: np.random.Generator) -> list[np.ndarray]:
    """Axis-angle vectors over the whole range, tiny and near-π angles included."""
    vectors = []
    for angle in [1e-9, 1e-4, 0.3, 1.0, 2.5, np.pi - 1e-6, *rng.uniform(0, np.pi, N_EXAMPLES)]:
        axis = rng.normal(size=3)
        vectors.append(axis / np.linalg.norm(axis) * angle)
    return vectors


def test_so3_exp_log_round_trip(rng):
    for phi in random_rotation_vectors(rng):
        np.testing.assert_allclose(SO3.exp(phi).log(), phi, atol=1e-9)


def test_so3_matches_rodrigues(rng):
    for phi in random_rotation_vectors(rng):
        expected, _ = cv2.Rodrigues(phi)
        np.testing.assert_allclose(SO3.exp(phi).matrix(), expected, atol=1e-12)


def test_quaternion_order_is_xyzw():
    half = np.pi / 4  # 90° about z
    q = SO3.exp([0.0, 0.0, np.pi / 2]).quat_xyzw()
    np.testing.assert_allclose(q, [0.0, 0.0, np.sin(half), np.cos(half)], atol=1e-15)
    np.testing.assert_allclose(SO3.from_quat_xyzw(q) @ np.array([1.0, 0.0, 0.0]), [0, 1, 0], atol=1e-15)


def test_se3_exp_log_and_composition(rng):
    for phi in random_rotation_vectors(rng):
        xi = np.concatenate([rng.normal(size=3), phi])
        t = SE3.exp(xi)
        np.testing.assert_allclose(t.log(), xi, atol=1e-9)
        other = SE3.exp(rng.normal(size=6))
        np.testing.assert_allclose((t @ other).matrix(), t.matrix() @ other.matrix(), atol=1e-12)
        np.testing.assert_allclose((t @ t.inverse()).matrix(), np.eye(4), atol=1e-12)


def test_se3_transforms_point_arrays_like_its_matrix(rng):
    world_from_cam = SE3.exp(rng.normal(size=6))
    points = rng.normal(size=(1000, 3))
    expected = points @ world_from_cam.matrix()[:3, :3].T + world_from_cam.matrix()[:3, 3]
    np.testing.assert_allclose(world_from_cam @ points, expected, atol=1e-12)
    np.testing.assert_allclose(world_from_cam @ points[0], expected[0], atol=1e-12)


def numeric_left_jacobian(xi: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """d/dδ log(exp(ξ + δ) exp(ξ)⁻¹) by central differences."""
    base_inv = SE3.exp(xi).inverse()
    cols = []
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        plus = (SE3.exp(xi + d) @ base_inv).log()
        minus = (SE3.exp(xi - d) @ base_inv).log()
        cols.append((plus - minus) / (2 * eps))
    return np.stack(cols, axis=1)


def test_se3_jacobians_against_finite_differences(rng):
    for phi in random_rotation_vectors(rng)[:12]:
        phi = phi * min(1.0, 3.0 / max(np.linalg.norm(phi), 1e-12))  # keep clear of π
        xi = np.concatenate([rng.normal(size=3), phi])
        np.testing.assert_allclose(SE3.left_jacobian(xi), numeric_left_jacobian(xi), atol=1e-6)
        np.testing.assert_allclose(SE3.right_jacobian(xi), numeric_left_jacobian(-xi), atol=1e-6)
        np.testing.assert_allclose(
            SE3.left_jacobian_inverse(xi) @ SE3.left_jacobian(xi), np.eye(6), atol=1e-9
        )


def test_se3_adjoint(rng):
    for _ in range(N_EXAMPLES):
        t = SE3.exp(rng.normal(size=6))
        xi = rng.normal(size=6) * 0.5
        lhs = t @ SE3.exp(xi) @ t.inverse()
        np.testing.assert_allclose(lhs.matrix(), SE3.exp(t.adjoint() @ xi).matrix(), atol=1e-10)


def test_se3_interpolation_endpoints_and_midpoint(rng):
    for _ in range(N_EXAMPLES):
        a, b = SE3.exp(rng.normal(size=6)), SE3.exp(rng.normal(size=6))
        np.testing.assert_allclose(a.interpolate(b, 0.0).matrix(), a.matrix(), atol=1e-12)
        np.testing.assert_allclose(a.interpolate(b, 1.0).matrix(), b.matrix(), atol=1e-9)
        mid = a.interpolate(b, 0.5)
        # The midpoint is equally far from both ends along the geodesic.
        np.testing.assert_allclose(
            np.linalg.norm((a.inverse() @ mid).log()), np.linalg.norm((mid.inverse() @ b).log()), atol=1e-9
        )


def test_invalid_rotation_inputs_raise_input_error():
    with pytest.raises(dhptam.InputError, match="quaternion"):
        SO3.from_quat_xyzw([0, 0, 0, 0])
    with pytest.raises(dhptam.InputError, match="finite"):
        SO3.from_quat_xyzw([0, 0, np.nan, 1])
    with pytest.raises(dhptam.InputError, match="orthonormal"):
        SO3.from_matrix(np.diag([1.0, 2.0, 1.0]))
    with pytest.raises(dhptam.InputError, match="phi"):
        SO3.exp([1.0, 2.0])


# ---------------------------------------------------------------------------------------------
# Cameras

CAMERAS = {
    "pinhole": Camera("pinhole", [458.0, 457.0, 367.2, 248.4], 752, 480),
    "radtan": Camera("radtan", [458.7, 457.3, 367.2, 248.4, -0.2834, 0.0740, 1.9e-4, 1.8e-5, 0.0], 752, 480),
    # TUM-VIE-like fisheye frame camera.
    "kb4": Camera("kb4", [747.3, 747.2, 490.8, 506.3, 0.0037, 0.0181, -0.0302, 0.0173], 1024, 1024),
}


def points_in_view(camera: Camera, n: int, rng: np.random.Generator) -> np.ndarray:
    pixels = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(n, 2))
    depth = rng.uniform(0.5, 10.0, size=(n, 1))
    return camera.unproject(pixels) * depth


@pytest.mark.parametrize("name", list(CAMERAS))
def test_project_unproject_round_trip(name, rng):
    camera = CAMERAS[name]
    pixels = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(2000, 2))
    bearings = camera.unproject(pixels)
    np.testing.assert_allclose(np.linalg.norm(bearings, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(camera.project(bearings * 3.0), pixels, atol=1e-9)


@pytest.mark.parametrize("name", ["pinhole", "radtan"])
def test_projection_agrees_with_opencv(name, rng):
    camera = CAMERAS[name]
    points = points_in_view(camera, 2000, rng)
    dist = np.array(camera.params[4:] if name == "radtan" else [])
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.K, dist)
    np.testing.assert_allclose(camera.project(points), expected.reshape(-1, 2), atol=1e-8)


def test_kb4_agrees_with_opencv_fisheye(rng):
    camera = CAMERAS["kb4"]
    points = points_in_view(camera, 2000, rng)
    expected, _ = cv2.fisheye.projectPoints(
        points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, np.array(camera.params[4:])
    )
    np.testing.assert_allclose(camera.project(points), expected.reshape(-1, 2), atol=1e-8)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_projection_jacobian_against_finite_differences(name, rng):
    camera = CAMERAS[name]
    points = points_in_view(camera, 50, rng)
    _, jacobians = camera.project_with_jacobian(points)
    eps = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        numeric = (camera.project(points + d) - camera.project(points - d)) / (2 * eps)
        np.testing.assert_allclose(jacobians[:, :, k], numeric, rtol=1e-5, atol=1e-4)


def test_points_behind_a_perspective_camera_are_nan():
    uv = CAMERAS["pinhole"].project(np.array([[0.0, 0.0, -1.0], [0.1, 0.2, 1.0]]))
    assert np.isnan(uv[0]).all() and np.isfinite(uv[1]).all()


def test_camera_construction_errors_name_the_problem():
    with pytest.raises(dhptam.InputError, match="fx > 0"):
        Camera("pinhole", [0.0, 1.0, 1.0, 1.0], 10, 10)
    with pytest.raises(dhptam.InputError, match="8 parameters"):
        Camera("kb4", [1.0, 1.0, 1.0, 1.0], 10, 10)
    with pytest.raises(dhptam.InputError, match="image size"):
        Camera("pinhole", [1.0, 1.0, 1.0, 1.0], 0, 10)
    with pytest.raises(dhptam.InputError, match=r"points: expected an \(N, 3\) array"):
        CAMERAS["pinhole"].project(np.zeros((4, 2)))


# ---------------------------------------------------------------------------------------------
# The array boundary: inputs read in place, GIL released.


def test_float64_c_contiguous_input_is_read_in_place(rng):
    points = rng.normal(size=(100, 3))
    assert dhptam._core._data_address(points) == points.ctypes.data
    # A float32 array cannot be read in place: it is converted, so the address differs...
    points32 = points.astype(np.float32)
    assert dhptam._core._data_address(points32) != points32.ctypes.data
    # ...and the results agree with the float64 path.
    camera = CAMERAS["radtan"]
    pts = points_in_view(camera, 100, rng)
    np.testing.assert_allclose(
        camera.project(pts.astype(np.float32)), camera.project(pts.astype(np.float32).astype(np.float64))
    )
    # Strided and Fortran-ordered inputs are accepted too.
    np.testing.assert_allclose(camera.project(np.asfortranarray(pts)), camera.project(pts))
    np.testing.assert_allclose(camera.project(pts[::2]), camera.project(pts)[::2])
    np.testing.assert_allclose(camera.project(pts.tolist()), camera.project(pts))


def test_projection_releases_the_gil():
    """While a large projection runs in a thread, the main thread keeps running Python."""
    import threading
    import time

    camera = CAMERAS["kb4"]
    points = np.tile([[0.1, -0.2, 2.0]], (4_000_000, 1))
    started, done = threading.Event(), threading.Event()
    span = {}

    def work():
        started.set()
        t0 = time.perf_counter()
        camera.project(points)
        span["call"] = time.perf_counter() - t0
        done.set()

    thread = threading.Thread(target=work)
    thread.start()
    started.wait()
    ticks = []
    while not done.is_set():
        ticks.append(time.perf_counter())
    thread.join()
    gaps = np.diff(ticks) if len(ticks) > 1 else np.array([span["call"]])
    # With the GIL held the main thread would stall for the whole call: one gap ≈ call time.
    assert len(ticks) > 100, f"main thread ran {len(ticks)} iterations during a {span['call']:.3f}s call"
    assert gaps.max() < 0.5 * span["call"], f"longest stall {gaps.max():.3f}s of a {span['call']:.3f}s call"
