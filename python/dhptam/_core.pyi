"""Type stub of the compiled core module ``dhptam._core`` (checked by ``mypy.stubtest``)."""

import os
from typing import Any, final, overload

import numpy as np
import numpy.typing as npt

__all__ = [
    "SE3",
    "SO3",
    "Camera",
    "Config",
    "PySystem",
    "RectifiedStereo",
    "Simulator",
    "StereoRig",
    "__version__",
    "_bundle_adjust",
    "_choose_beta",
    "_count_image",
    "_data_address",
    "_e3ct",
    "_e3ct_apply_scales",
    "_e3ct_scales",
    "_fuse",
    "_log_from_rust",
    "_r2d2_heads",
    "_recover_exposure",
    "_reset_log_cache",
    "_solve_bal_file",
    "_solve_pose_graph_file",
    "_testing_panic",
    "_time_surface",
    "_triangulate",
    "_voxel_grid",
    "_warp_and_fuse",
    "_warp_to_frame",
    "sim_builtin_trajectory",
    "sim_file_trajectory",
    "sim_profile_segments",
    "solve_pnp_ransac",
    "thread_count",
]
__version__: str

_FloatArray = npt.NDArray[np.float64]
_ArrayLike = npt.ArrayLike

@final
class SO3:
    """A 3-D rotation; quaternions in (x, y, z, w) order."""

    def __new__(cls) -> SO3: ...
    @staticmethod
    def exp(phi: _ArrayLike) -> SO3: ...
    @staticmethod
    def from_quat_xyzw(q: _ArrayLike) -> SO3: ...
    @staticmethod
    def from_matrix(m: _ArrayLike) -> SO3: ...
    def log(self) -> _FloatArray: ...
    def quat_xyzw(self) -> _FloatArray: ...
    def matrix(self) -> _FloatArray: ...
    def inverse(self) -> SO3: ...
    def adjoint(self) -> _FloatArray: ...
    def angle(self) -> float: ...
    def interpolate(self, other: SO3, s: float) -> SO3: ...
    @staticmethod
    def left_jacobian(phi: _ArrayLike) -> _FloatArray: ...
    @staticmethod
    def right_jacobian(phi: _ArrayLike) -> _FloatArray: ...
    @staticmethod
    def left_jacobian_inverse(phi: _ArrayLike) -> _FloatArray: ...
    @staticmethod
    def right_jacobian_inverse(phi: _ArrayLike) -> _FloatArray: ...
    @overload
    def __matmul__(self, rhs: SO3, /) -> SO3: ...
    @overload
    def __matmul__(self, rhs: _ArrayLike, /) -> _FloatArray: ...
    def __rmatmul__(self, other: object, /) -> Any: ...

@final
class SE3:
    """A rigid-body transform; tangent vectors are [rho, phi]."""

    def __new__(cls, rotation: SO3 | None = None, translation: _ArrayLike | None = None) -> SE3: ...
    @staticmethod
    def exp(xi: _ArrayLike) -> SE3: ...
    @staticmethod
    def from_matrix(m: _ArrayLike) -> SE3: ...
    @staticmethod
    def from_translation_quat_xyzw(translation: _ArrayLike, quat_xyzw: _ArrayLike) -> SE3: ...
    def log(self) -> _FloatArray: ...
    def matrix(self) -> _FloatArray: ...
    @property
    def rotation(self) -> SO3: ...
    @property
    def translation(self) -> _FloatArray: ...
    def inverse(self) -> SE3: ...
    def adjoint(self) -> _FloatArray: ...
    def interpolate(self, other: SE3, s: float) -> SE3: ...
    @staticmethod
    def left_jacobian(xi: _ArrayLike) -> _FloatArray: ...
    @staticmethod
    def right_jacobian(xi: _ArrayLike) -> _FloatArray: ...
    @staticmethod
    def left_jacobian_inverse(xi: _ArrayLike) -> _FloatArray: ...
    @staticmethod
    def right_jacobian_inverse(xi: _ArrayLike) -> _FloatArray: ...
    @overload
    def __matmul__(self, rhs: SE3, /) -> SE3: ...
    @overload
    def __matmul__(self, rhs: _ArrayLike, /) -> _FloatArray: ...
    def __rmatmul__(self, other: object, /) -> Any: ...

@final
class Camera:
    """A camera model ("pinhole", "radtan", "kb4") with OpenCV-ordered parameters."""

    def __new__(cls, model: str, params: list[float], width: int, height: int) -> Camera: ...
    @property
    def model(self) -> str: ...
    @property
    def params(self) -> list[float]: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def K(self) -> _FloatArray: ...
    def project(self, points: _ArrayLike) -> _FloatArray: ...
    def unproject(self, pixels: _ArrayLike) -> _FloatArray: ...
    def project_with_jacobian(self, points: _ArrayLike) -> tuple[_FloatArray, _FloatArray]: ...
    def contains(self, pixels: _ArrayLike) -> npt.NDArray[np.bool_]: ...

@final
class Config:
    """The typed dhptam configuration."""

    def __new__(cls) -> Config: ...
    @staticmethod
    def from_toml(text: str, source_name: str = "<string>") -> Config: ...
    @staticmethod
    def from_file(path: str | Any) -> Config: ...
    @staticmethod
    def defaults_toml() -> str: ...
    def to_toml(self) -> str: ...
    def to_commented_toml(self) -> str: ...
    def to_dict(self) -> dict[str, Any]: ...
    def __eq__(self, other: object, /) -> bool: ...

@final
class StereoRig:
    """A calibrated stereo pair."""

    def __new__(cls, left: Camera, right: Camera, right_from_left: SE3) -> StereoRig: ...
    @property
    def left(self) -> Camera: ...
    @property
    def right(self) -> Camera: ...
    @property
    def right_from_left(self) -> SE3: ...

@final
class RectifiedStereo:
    """Rectified geometry of a stereo pair (shared K, aligned rows)."""

    def __new__(cls, rig: StereoRig, config: Config | None = None) -> RectifiedStereo: ...
    @property
    def K(self) -> _FloatArray: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def baseline_m(self) -> float: ...
    @property
    def P_left(self) -> _FloatArray: ...
    @property
    def P_right(self) -> _FloatArray: ...
    @property
    def rect_left_from_left(self) -> SO3: ...
    @property
    def rect_right_from_right(self) -> SO3: ...
    def rectify_pixels(self, side: str, pixels: _ArrayLike) -> _FloatArray: ...
    def unrectify_pixels(self, side: str, pixels: _ArrayLike) -> _FloatArray: ...
    def project(self, points: _ArrayLike) -> tuple[_FloatArray, _FloatArray]: ...
    def remap_tables(self, side: str) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]: ...
    def rectify_image(self, side: str, image: npt.NDArray[Any]) -> npt.NDArray[Any]: ...
    def triangulate(
        self, uv_left: _ArrayLike, u_right: _ArrayLike, config: Config | None = None
    ) -> tuple[_FloatArray, npt.NDArray[np.bool_], list[str | None]]: ...

def _triangulate(
    cams_from_world: list[SE3], pixels: _ArrayLike, intrinsics: _ArrayLike, config: Config | None = None
) -> tuple[tuple[float, float, float] | None, float, float, str | None]: ...
def thread_count() -> int: ...
def _data_address(array: _ArrayLike) -> int: ...
def _reset_log_cache() -> None: ...
def _log_from_rust(level: str, message: str) -> None: ...

_EventArrays = tuple[
    npt.NDArray[np.uint16], npt.NDArray[np.uint16], npt.NDArray[np.int64], npt.NDArray[np.int8]
]

@final
class Simulator:
    """The events+frames simulator (desk room, four-camera rig, lighting profile)."""

    def __new__(
        cls,
        cameras: list[Camera],
        imu_from_cam: list[SE3],
        photos: list[npt.NDArray[np.uint8]],
        trajectory_t_ns: npt.NDArray[np.int64],
        trajectory_poses: _ArrayLike,
        profile: str,
        duration_ns: int,
        seed: int,
        config: Config | None = None,
    ) -> Simulator: ...
    def frame_pair(self, t_ns: int) -> tuple[int, npt.NDArray[np.uint8], npt.NDArray[np.uint8]]: ...
    def events_until(self, t_ns: int) -> tuple[_EventArrays, _EventArrays]: ...
    def render(self, camera: int, t_ns: int) -> npt.NDArray[np.float32]: ...
    def render_depth(self, camera: int, t_ns: int) -> npt.NDArray[np.float32]: ...
    def world_from_cam(self, camera: int, t_ns: npt.NDArray[np.int64]) -> _FloatArray: ...
    def world_from_body(self, t_ns: npt.NDArray[np.int64]) -> _FloatArray: ...
    def illumination(self, t_ns: int) -> float: ...
    @property
    def render_count(self) -> int: ...

def sim_builtin_trajectory(name: str, duration_ns: int) -> tuple[npt.NDArray[np.int64], _FloatArray]: ...
def sim_file_trajectory(path: str | Any, fmt: str) -> tuple[npt.NDArray[np.int64], _FloatArray]: ...
def sim_profile_segments(profile: str) -> list[tuple[str, float, float]]: ...

_U16 = npt.NDArray[np.uint16]
_I64 = npt.NDArray[np.int64]
_I8 = npt.NDArray[np.int8]
_F32 = npt.NDArray[np.float32]

# Descriptor matching (float32 rows by L2, uint8 rows by Hamming).
def match_descriptors(
    query: npt.NDArray[np.float32] | npt.NDArray[np.uint8],
    train: npt.NDArray[np.float32] | npt.NDArray[np.uint8],
    max_distance: float,
    ratio: float = 0.9,
    mutual: bool = True,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]: ...
def _buffer_address(array: npt.NDArray[np.float32] | npt.NDArray[np.uint8]) -> int: ...
def _e3ct(
    x: _U16,
    y: _U16,
    t_ns: _I64,
    p: _I8,
    width: int,
    height: int,
    t_start_ns: int,
    t_end_ns: int,
    alpha: float,
    eta_ms: float,
    channels: int,
    polarity: str,
) -> _F32: ...
def _count_image(
    x: _U16,
    y: _U16,
    t_ns: _I64,
    p: _I8,
    width: int,
    height: int,
    t_start_ns: int,
    t_end_ns: int,
    polarity: str,
) -> _F32: ...
def _time_surface(
    x: _U16,
    y: _U16,
    t_ns: _I64,
    p: _I8,
    width: int,
    height: int,
    t_start_ns: int,
    t_end_ns: int,
    tau_ms: float,
) -> _F32: ...
def _voxel_grid(
    x: _U16, y: _U16, t_ns: _I64, p: _I8, width: int, height: int, t_start_ns: int, t_end_ns: int, bins: int
) -> _F32: ...
def _e3ct_scales(tensors: list[_F32], percentile: float) -> list[float]: ...
def _e3ct_apply_scales(tensor: _F32, scales: list[float]) -> _F32: ...
def _choose_beta(
    frame: npt.NDArray[np.uint8], feature_count: int | None = None, config: Config | None = None
) -> tuple[str, float, float, float]: ...
def _fuse(frame: npt.NDArray[np.uint8], e3ct: _F32, beta: float) -> npt.NDArray[np.uint8]: ...
def _recover_exposure(
    frame: npt.NDArray[np.uint8], config: Config | None = None
) -> tuple[npt.NDArray[np.uint8] | None, bool, int, int, float, float]: ...
def _r2d2_heads(features: _F32, weights: _F32, bias: _F32, upsample: int) -> tuple[_F32, _F32]: ...
def _warp_to_frame(
    image: _F32,
    k_event: _ArrayLike,
    k_frame: _ArrayLike,
    frame_from_event: SE3,
    depth_m: float,
    align_px: _ArrayLike,
    width: int,
    height: int,
    pixels: _ArrayLike | None = None,
    scales: _ArrayLike | None = None,
) -> tuple[_F32, _FloatArray | None]: ...
def _warp_and_fuse(
    image: _F32,
    k_event: _ArrayLike,
    k_frame: _ArrayLike,
    frame_from_event: SE3,
    depth_m: float,
    align_px: _ArrayLike,
    frame: npt.NDArray[np.uint8],
    beta: float,
    scales: _ArrayLike | None = None,
) -> tuple[_F32, npt.NDArray[np.uint8]]: ...
def _solve_bal_file(
    path: str | os.PathLike[str],
    *,
    threads: int = 1,
    linear_solver: str = "auto",
    loss: str = "trivial",
    loss_scale: float = 1.0,
    zero_behind_camera: bool = False,
    max_iterations: int = 50,
    out: str | os.PathLike[str] | None = None,
) -> dict[str, Any]: ...
def _solve_pose_graph_file(
    path: str | os.PathLike[str],
    *,
    threads: int = 1,
    max_iterations: int = 50,
    out: str | os.PathLike[str] | None = None,
) -> dict[str, Any]: ...
def _bundle_adjust(
    cameras: _ArrayLike,
    points: _ArrayLike,
    camera_index: npt.NDArray[np.int64],
    point_index: npt.NDArray[np.int64],
    pixels: _ArrayLike,
    *,
    threads: int = 1,
    linear_solver: str = "auto",
    loss: str = "trivial",
    loss_scale: float = 1.0,
    fixed_cameras: list[int] = ...,
    max_iterations: int = 50,
) -> tuple[_FloatArray, _FloatArray, dict[str, Any]]: ...

# -- frontend: event rectification table (fusion.rs) --------------------------------------------

@final
class EventRectifier:
    """Raw event pixel → rectified pixel lookup table of one camera of a rectified pair."""

    def __new__(cls, rect: RectifiedStereo, side: str) -> EventRectifier: ...
    @property
    def raw_size(self) -> tuple[int, int]: ...
    @property
    def rect_size(self) -> tuple[int, int]: ...
    def apply(
        self, x: _U16, y: _U16, t_ns: _I64, p: _I8, t_start_ns: int, t_end_ns: int
    ) -> tuple[_U16, _U16, _I64, _I8]: ...
    def lookup(self, pixels: npt.NDArray[np.int64]) -> _FloatArray: ...
    def set_masked(self, pixels: npt.NDArray[np.uint32]) -> None: ...
    @property
    def masked_count(self) -> int: ...

@final
class EventStereo:
    """Reads stereo matches of event images warped into the rectified frame cameras as the
    frame cameras would have measured them (triangulated with the event cameras)."""

    def __new__(
        cls,
        k_event: npt.ArrayLike,
        event_baseline_m: float,
        k_frame: npt.ArrayLike,
        frame_baseline_m: float,
        frame_from_event_left: SE3,
        frame_from_event_right: SE3,
        depth_m: float,
        align_px: tuple[float, float] = ...,  # (0.0, 0.0)
    ) -> EventStereo: ...
    def frame_readings(self, matches: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]: ...

@final
class HotPixels:
    """Running detector of the hot pixels of one event camera (raw pixels)."""

    def __new__(
        cls,
        width: int,
        height: int,
        *,
        ratio: float | None = None,
        min_rate_hz: float | None = None,
        time_constant_s: float | None = None,
    ) -> HotPixels: ...
    def update(self, x: _U16, y: _U16, duration_s: float) -> bool: ...
    def pixels(self) -> npt.NDArray[np.uint32]: ...
    def __len__(self) -> int: ...

def solve_pnp_ransac(
    points_world: _ArrayLike,
    pixels: _ArrayLike,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    *,
    threshold_px: float = 2.0,
    confidence: float = 0.999,
    max_iterations: int = 1000,
    min_inliers: int = 10,
    seed: int = 0,
) -> tuple[_FloatArray, npt.NDArray[np.bool_], int] | None: ...

# --- SLAM back-end (issue 7) ---
@final
class PySystem:
    """The SLAM back-end (wrapped by ``dhptam.System``)."""

    def __new__(
        cls,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        baseline_m: float,
        width: int,
        height: int,
        config: Config | None = None,
        threaded: bool = True,
    ) -> PySystem: ...
    def track(
        self,
        t_ns: int,
        left_keypoints: npt.NDArray[np.float32],
        left_descriptors: npt.NDArray[np.float32] | npt.NDArray[np.uint8],
        right_keypoints: npt.NDArray[np.float32],
        right_descriptors: npt.NDArray[np.float32] | npt.NDArray[np.uint8],
        left_sigmas: npt.NDArray[np.float32] | None = None,
        sigma_scale: float = 1.0,
        disparity: tuple[float, float] = ...,  # (1.0, 0.0)
        event_stereo: EventStereo | None = None,
        viewpoint: tuple[float, float, float] = ...,  # (0.0, 0.0, 0.0)
        dvs_biased: bool = False,
        quiet: bool = False,
    ) -> tuple[_FloatArray, str, int, bool]: ...
    # Predicted (untracked) frames across illumination floods (issue 8, accuracy).
    def predict(self, t_ns: int) -> tuple[_FloatArray, str, int, bool]: ...
    # Bridge keyframes across fusion-mode switches (issue 8, accuracy).
    def bridge(
        self,
        t_ns: int,
        left_keypoints: npt.NDArray[np.float32],
        left_descriptors: npt.NDArray[np.float32] | npt.NDArray[np.uint8],
        right_keypoints: npt.NDArray[np.float32],
        right_descriptors: npt.NDArray[np.float32] | npt.NDArray[np.uint8],
        other_left_keypoints: npt.NDArray[np.float32],
        other_left_descriptors: npt.NDArray[np.float32] | npt.NDArray[np.uint8],
        other_right_keypoints: npt.NDArray[np.float32],
        other_right_descriptors: npt.NDArray[np.float32] | npt.NDArray[np.uint8],
        left_sigmas: npt.NDArray[np.float32] | None = None,
        other_left_sigmas: npt.NDArray[np.float32] | None = None,
        sigma_scale: float = 1.0,
        other_sigma_scale: float = 1.0,
        disparity: tuple[float, float] = ...,  # (1.0, 0.0)
        other_disparity: tuple[float, float] = ...,  # (1.0, 0.0)
        event_stereo: EventStereo | None = None,
        other_event_stereo: EventStereo | None = None,
        viewpoint: tuple[float, float, float] = ...,  # (0.0, 0.0, 0.0)
        other_viewpoint: tuple[float, float, float] = ...,  # (0.0, 0.0, 0.0)
    ) -> tuple[int, int, int] | None: ...
    def refine_map(self, iterations: int) -> dict[str, int]: ...
    def tracking_totals(self) -> dict[str, int]: ...
    def tracked_depth(self) -> float | None: ...
    def trajectory(self, smoothed: bool = True) -> tuple[npt.NDArray[np.int64], _FloatArray]: ...
    def keyframe_trajectory(self) -> tuple[npt.NDArray[np.int64], _FloatArray]: ...
    def map_points(self) -> _FloatArray: ...
    def loop_closures(self) -> list[tuple[int, int]]: ...
    def timing(self) -> dict[str, dict[str, float]]: ...
    def save_map(self, path: str | os.PathLike[str]) -> None: ...
    def load_map(self, path: str | os.PathLike[str]) -> None: ...
    def shutdown(self) -> None: ...
    @property
    def threaded(self) -> bool: ...

# -- test-only: a deliberate panic inside the binding's panic guard (issue 10) -----------------
def _testing_panic(message: str) -> None:
    """Test-only: always raises ``dhptam.errors.InternalError`` naming ``message`` (a Rust panic
    caught at the boundary); no dhptam code calls it."""

# -- MCAP logs (dhptam.datasets.mcap) ----------------------------------------------------------
@final
class McapWriter:
    def __new__(
        cls,
        path: str | Any,
        compression: str = "zstd",
        chunk_size_bytes: int = 4194304,
        batch_events: int = 32768,
    ) -> McapWriter: ...
    def add_events(self, topic: str, frame_id: str, x: _U16, y: _U16, t_ns: _I64, p: _I8) -> None: ...
    def add_image(self, topic: str, frame_id: str, t_ns: int, image: npt.NDArray[np.uint8]) -> None: ...
    def add_compressed_image(
        self, topic: str, frame_id: str, t_ns: int, data: bytes, format: str
    ) -> None: ...
    def add_calibration(
        self,
        topic: str,
        frame_id: str,
        t_ns: int,
        width: int,
        height: int,
        distortion_model: str,
        d: list[float],
        k: list[float],
        r: list[float],
        p: list[float],
    ) -> None: ...
    def add_poses(self, topic: str, frame_id: str, t_ns: _I64, poses: _ArrayLike) -> None: ...
    def add_point_cloud(self, topic: str, frame_id: str, t_ns: int, points: _ArrayLike) -> None: ...
    def add_metadata(self, name: str, entries: dict[str, str]) -> None: ...
    def finish(self) -> None: ...
    def abort(self) -> None: ...
    @property
    def path(self) -> Any: ...

@final
class McapReader:
    def __new__(cls, path: str | Any) -> McapReader: ...
    @property
    def path(self) -> Any: ...
    def topics(self) -> dict[str, dict[str, Any]]: ...
    def metadata(self, name: str) -> dict[str, str] | None: ...
    def log_times(self, topic: str, schema: str) -> _I64: ...
    def images(self, topic: str, start: int, stop: int) -> list[tuple[int, str, npt.NDArray[np.uint8]]]: ...
    def compressed_images(self, topic: str, start: int, stop: int) -> list[tuple[int, str, str, bytes]]: ...
    def poses(self, topic: str) -> tuple[_I64, _FloatArray, list[str]]: ...
    def calibrations(self, topic: str) -> list[dict[str, Any]]: ...
    def point_clouds(self, topic: str) -> list[tuple[int, str, _F32]]: ...
    def event_count(self, topic: str) -> int: ...
    def event_time_range(self, topic: str) -> tuple[int, int]: ...
    def event_index_range(self, topic: str, t0_ns: int, t1_ns: int) -> tuple[int, int]: ...
    def event_slice(self, topic: str, i0: int, i1: int) -> tuple[_U16, _U16, _I64, _I8]: ...
