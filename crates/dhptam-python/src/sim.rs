//! Python class for the simulator (`Simulator`) and its trajectory helpers.
//!
//! Poses cross the boundary as `(N, 7)` float64 rows `x y z qx qy qz qw`, times as int64 ns.

use std::path::PathBuf;

use dhptam_core::config::Config;
use dhptam_core::geometry::Se3;
use dhptam_core::sim::{
    BuiltinMotion, Event, Profile, RigCamera, Scene, Simulator, Texture, Trajectory,
};
use numpy::ndarray::{Array1, Array2};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use crate::config::PyConfig;
use crate::errors::DetachGuarded;
use crate::errors::{input_error, IntoPyResult};
use crate::geometry::{PyCamera, PySe3};

/// Event arrays `(x uint16, y uint16, t_ns int64, p int8 in {0, 1})`.
type EventArrays<'py> = (
    Bound<'py, PyArray1<u16>>,
    Bound<'py, PyArray1<u16>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<i8>>,
);

/// Times `(N,)` int64 ns and poses `(N, 7)`.
type PoseArrays<'py> = (Bound<'py, PyArray1<i64>>, Bound<'py, PyArray2<f64>>);

fn poses_to_py<'py>(py: Python<'py>, poses: &[Se3]) -> Bound<'py, PyArray2<f64>> {
    Array2::from_shape_fn((poses.len(), 7), |(i, c)| {
        let p = &poses[i];
        if c < 3 {
            p.translation[c]
        } else {
            p.rotation.to_quaternion_xyzw()[c - 3]
        }
    })
    .into_pyarray(py)
}

fn trajectory_to_py<'py>(py: Python<'py>, trajectory: &Trajectory) -> PoseArrays<'py> {
    (
        Array1::from_vec(trajectory.times_ns().to_vec()).into_pyarray(py),
        poses_to_py(py, trajectory.poses()),
    )
}

fn trajectory_from_py(t_ns: &Bound<'_, PyAny>, poses: &Bound<'_, PyAny>) -> PyResult<Trajectory> {
    let t: PyReadonlyArray1<'_, i64> = t_ns
        .extract()
        .map_err(|_| input_error("trajectory_t_ns", "a 1-D int64 array", "another type"))?;
    let rows = crate::arrays::rows(poses, 7, "trajectory_poses")?;
    let view = rows.as_array();
    let mut out = Vec::with_capacity(view.nrows());
    for r in view.outer_iter() {
        out.push(
            Se3::from_translation_quaternion_xyzw([r[0], r[1], r[2]], [r[3], r[4], r[5], r[6]])
                .py()?,
        );
    }
    Trajectory::new(t.as_slice()?.to_vec(), out).py()
}

fn events_to_py<'py>(py: Python<'py>, events: &[Event]) -> EventArrays<'py> {
    let x: Vec<u16> = events.iter().map(|e| e.x).collect();
    let y: Vec<u16> = events.iter().map(|e| e.y).collect();
    let t: Vec<i64> = events.iter().map(|e| e.t_ns).collect();
    let p: Vec<i8> = events.iter().map(|e| i8::from(e.on)).collect();
    (
        x.into_pyarray(py),
        y.into_pyarray(py),
        t.into_pyarray(py),
        p.into_pyarray(py),
    )
}

/// The events+frames simulator: the desk room with `photos` on its walls and objects, a
/// four-camera rig (frame left/right, event left/right) moving along a body trajectory,
/// lit by a lighting `profile` (`normal`, `hdr`, `flicker`, `dark`) over `duration_ns`.
#[pyclass(name = "Simulator", module = "dhptam._core")]
pub struct PySimulator {
    inner: Simulator,
    shapes: [(usize, usize); 4],
}

#[pymethods]
impl PySimulator {
    #[new]
    #[pyo3(signature = (cameras, imu_from_cam, photos, trajectory_t_ns, trajectory_poses, profile, duration_ns, seed, config=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        cameras: Vec<PyCamera>,
        imu_from_cam: Vec<PySe3>,
        photos: Vec<PyReadonlyArray2<'_, u8>>,
        trajectory_t_ns: &Bound<'_, PyAny>,
        trajectory_poses: &Bound<'_, PyAny>,
        profile: &str,
        duration_ns: i64,
        seed: u64,
        config: Option<&PyConfig>,
    ) -> PyResult<Self> {
        if cameras.len() != 4 || imu_from_cam.len() != 4 {
            return Err(input_error(
                "cameras, imu_from_cam",
                "four cameras and four poses (frame left, frame right, event left, event right)",
                format!("{} and {}", cameras.len(), imu_from_cam.len()),
            ));
        }
        let rig: [RigCamera; 4] = std::array::from_fn(|i| RigCamera {
            camera: cameras[i].inner,
            imu_from_cam: imu_from_cam[i].inner,
        });
        let mut textures = Vec::with_capacity(photos.len());
        for (i, photo) in photos.iter().enumerate() {
            let shape = photo.shape();
            let data = photo.as_array();
            let values: Vec<u8> = data.iter().copied().collect();
            textures.push(
                Texture::from_u8(shape[1], shape[0], &values)
                    .map_err(|e| input_error(&format!("photos[{i}]"), "a 2-D uint8 image", e))?,
            );
        }
        let trajectory = trajectory_from_py(trajectory_t_ns, trajectory_poses)?;
        let profile = Profile::parse(profile).py()?;
        let params = config
            .map(|c| c.inner.sim.clone())
            .unwrap_or_else(|| Config::default().sim)
            .params();
        let shapes =
            std::array::from_fn(|i| (rig[i].camera.height as usize, rig[i].camera.width as usize));
        let inner = py
            .detach_guarded("sim::new", || {
                Simulator::new(
                    Scene::desk_room(textures, seed),
                    rig,
                    trajectory,
                    profile,
                    duration_ns,
                    params,
                    seed,
                )
            })?
            .py()?;
        Ok(Self { inner, shapes })
    }

    /// The next stereo pair exposed from `t_ns`: `(exposure_ns, left, right)`, uint8 images.
    fn frame_pair<'py>(
        &mut self,
        py: Python<'py>,
        t_ns: i64,
    ) -> PyResult<(i64, Bound<'py, PyArray2<u8>>, Bound<'py, PyArray2<u8>>)> {
        let pair = py.detach_guarded("sim::frame_pair", || self.inner.frame_pair(t_ns))?;
        let image = |data: Vec<u8>, (h, w): (usize, usize)| {
            Array2::from_shape_vec((h, w), data).map_err(|e| input_error("frame", "(H, W)", e))
        };
        Ok((
            pair.exposure_ns,
            image(pair.left, self.shapes[0])?.into_pyarray(py),
            image(pair.right, self.shapes[1])?.into_pyarray(py),
        ))
    }

    /// Events of both event cameras up to `t_ns`: `((x, y, t_ns, p) left, (…) right)`.
    fn events_until<'py>(
        &mut self,
        py: Python<'py>,
        t_ns: i64,
    ) -> PyResult<(EventArrays<'py>, EventArrays<'py>)> {
        let [left, right] = py
            .detach_guarded("sim::events_until", || self.inner.events_until(t_ns))?
            .py()?;
        Ok((events_to_py(py, &left), events_to_py(py, &right)))
    }

    /// Radiance under unit illumination seen by camera `camera` (0–3) at `t_ns`, float32.
    fn render<'py>(
        &mut self,
        py: Python<'py>,
        camera: usize,
        t_ns: i64,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (h, w) = *self
            .shapes
            .get(camera)
            .ok_or_else(|| input_error("camera", "an index 0–3", camera))?;
        let image =
            py.detach_guarded("sim::render", || self.inner.render_radiance(camera, t_ns))?;
        Ok(Array2::from_shape_vec((h, w), image)
            .map_err(|e| input_error("render", "(H, W)", e))?
            .into_pyarray(py))
    }

    /// Ground-truth depth `(H, W)` float32 of camera `camera` (0–3) at `t_ns`: camera-frame z
    /// in metres, NaN where the ray hits nothing.
    fn render_depth<'py>(
        &self,
        py: Python<'py>,
        camera: usize,
        t_ns: i64,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (h, w) = *self
            .shapes
            .get(camera)
            .ok_or_else(|| input_error("camera", "an index 0–3", camera))?;
        let depth = py.detach_guarded("sim::render_depth", || {
            self.inner.render_depth(camera, t_ns)
        })?;
        Ok(Array2::from_shape_vec((h, w), depth)
            .map_err(|e| input_error("render_depth", "(H, W)", e))?
            .into_pyarray(py))
    }

    /// Poses `(N, 7)` of camera `camera` (0–3) at the times `t_ns`.
    fn world_from_cam<'py>(
        &self,
        py: Python<'py>,
        camera: usize,
        t_ns: PyReadonlyArray1<'py, i64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        if camera >= 4 {
            return Err(input_error("camera", "an index 0–3", camera));
        }
        let poses: Vec<Se3> = t_ns
            .as_array()
            .iter()
            .map(|&t| self.inner.world_from_cam(camera, t))
            .collect();
        Ok(poses_to_py(py, &poses))
    }

    /// Poses `(N, 7)` of the body (IMU) at the times `t_ns`.
    fn world_from_body<'py>(
        &self,
        py: Python<'py>,
        t_ns: PyReadonlyArray1<'py, i64>,
    ) -> Bound<'py, PyArray2<f64>> {
        let poses: Vec<Se3> = t_ns
            .as_array()
            .iter()
            .map(|&t| self.inner.trajectory().pose_at(t))
            .collect();
        poses_to_py(py, &poses)
    }

    /// The lighting factor at `t_ns` (1 = normal light).
    fn illumination(&self, t_ns: i64) -> f64 {
        self.inner.illumination(t_ns)
    }

    /// Renders performed so far (all cameras).
    #[getter]
    fn render_count(&self) -> u64 {
        self.inner.render_count()
    }
}

/// A built-in motion (`desk_spiral`, `translation_1d`, `shake_6dof`, `closed_loop`) over
/// `duration_ns`, sampled at 1 kHz in the desk room: `(t_ns, world_from_body (N, 7))`.
#[pyfunction]
pub fn sim_builtin_trajectory<'py>(
    py: Python<'py>,
    name: &str,
    duration_ns: i64,
) -> PyResult<PoseArrays<'py>> {
    let motion = BuiltinMotion::parse(name).py()?;
    let trajectory = motion
        .trajectory(duration_ns, &Scene::desk_room_region())
        .py()?;
    Ok(trajectory_to_py(py, &trajectory))
}

/// Reads a trajectory file (`fmt` `"tum"`: `t[s] x y z qx qy qz qw`; `"csv"`:
/// `timestamp[ns], x, y, z, qx, qy, qz, qw`) and fits it into the desk room, times from 0.
#[pyfunction]
pub fn sim_file_trajectory<'py>(
    py: Python<'py>,
    path: PathBuf,
    fmt: &str,
) -> PyResult<PoseArrays<'py>> {
    let trajectory = match fmt {
        "tum" => Trajectory::read_tum(&path),
        "csv" => Trajectory::read_csv(&path),
        other => {
            return Err(input_error(
                "fmt",
                "\"tum\" or \"csv\"",
                format!("{other:?}"),
            ))
        }
    }
    .and_then(|t| t.fitted_into(&Scene::desk_room_region()))
    .py()?;
    Ok(trajectory_to_py(py, &trajectory))
}

/// Lighting segments of a profile as `(label, start, end)` in normalised time.
#[pyfunction]
pub fn sim_profile_segments(profile: &str) -> PyResult<Vec<(&'static str, f64, f64)>> {
    Ok(Profile::parse(profile).py()?.segments())
}
