//! `PySystem`: the SLAM back-end. Keypoints ((N, 2) float32), descriptors ((N, D) float32 or
//! (N, B) uint8) and the optional left keypoints' σ ((N,) float32) are read in place; tracking, saving and loading run with the GIL released.
//! The system sits behind a mutex so that `shutdown` may come from another Python thread while
//! a `track` call is running (it waits for that frame).

use std::path::PathBuf;
use std::sync::Mutex;

use dhptam_core::geometry::Se3;
use dhptam_core::slam::{
    DisparityCorrection, FrameFeatures, StereoCalibration, System, TrackResult,
};
use numpy::ndarray::{Array1, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2,
    PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::config::PyConfig;
use crate::errors::DetachGuarded;
use crate::errors::{input_error, IntoPyResult};
use crate::fusion::PyEventStereo;
use crate::matching::DescriptorArray;

fn keypoints<'py>(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<PyReadonlyArray2<'py, f32>> {
    let expected = "a C-contiguous (N, 2) float32 array";
    let a = obj
        .extract::<PyReadonlyArray2<'py, f32>>()
        .map_err(|_| input_error(name, expected, crate::arrays::describe(obj)))?;
    if !a.is_c_contiguous() || a.shape()[1] != 2 {
        return Err(input_error(name, expected, crate::arrays::describe(obj)));
    }
    Ok(a)
}

/// Optional per-keypoint σ: an (N,) float32 array read in place (others converted once).
fn sigmas<'py>(
    obj: Option<&Bound<'py, PyAny>>,
    name: &str,
) -> PyResult<Option<PyReadonlyArray1<'py, f32>>> {
    match obj {
        Some(o) if !o.is_none() => crate::arrays::values_f32(o, name).map(Some),
        _ => Ok(None),
    }
}

/// One image's features read in place from checked arrays, with how the tracker reads them
/// (the `FrameFeatures` fields past the arrays, one argument each as `track` takes them).
#[allow(clippy::too_many_arguments)]
fn features<'a>(
    keypoints: &'a PyReadonlyArray2<'_, f32>,
    descriptors: &'a DescriptorArray<'_>,
    sigmas: Option<&'a PyReadonlyArray1<'_, f32>>,
    sigma_scale: f32,
    disparity: (f32, f32),
    event_stereo: Option<&'a PyEventStereo>,
    viewpoint: [f32; 3],
    dvs_biased: bool,
    quiet: bool,
) -> PyResult<FrameFeatures<'a>> {
    Ok(FrameFeatures {
        keypoints: keypoints
            .as_slice()
            .map_err(|_| input_error("keypoints", "a C-contiguous array", "a strided view"))?,
        descriptors: descriptors.view()?,
        sigmas: sigmas
            .map(|s| {
                s.as_slice()
                    .map_err(|_| input_error("sigmas", "a C-contiguous array", "a strided view"))
            })
            .transpose()?,
        sigma_scale,
        disparity: DisparityCorrection {
            scale: disparity.0,
            offset_px: disparity.1,
        },
        event_stereo: event_stereo.map(|e| &e.inner),
        viewpoint,
        dvs_biased,
        quiet,
    })
}

fn pose_array<'py>(py: Python<'py>, pose: &Se3) -> Bound<'py, PyArray2<f64>> {
    let m = pose.matrix();
    let rows: Vec<Vec<f64>> = (0..4)
        .map(|r| (0..4).map(|c| m[(r, c)]).collect())
        .collect();
    // A 4×4 from fixed-size rows cannot fail.
    PyArray2::from_vec2(py, &rows).unwrap_or_else(|_| unreachable!())
}

/// A tracking result as Python receives it: (pose (4, 4) world_from_cam, state, inliers,
/// keyframe inserted).
type TrackTuple<'py> = (Bound<'py, PyArray2<f64>>, &'static str, usize, bool);

fn track_tuple<'py>(py: Python<'py>, r: &TrackResult) -> TrackTuple<'py> {
    (
        pose_array(py, &r.world_from_cam),
        r.state.as_str(),
        r.inliers,
        r.keyframe,
    )
}

fn poses_arrays<'py>(
    py: Python<'py>,
    poses: &[(i64, Se3)],
) -> (Bound<'py, PyArray1<i64>>, Bound<'py, PyArray3<f64>>) {
    let t: Array1<i64> = poses.iter().map(|p| p.0).collect();
    let mut out = Array3::<f64>::zeros((poses.len(), 4, 4));
    for (i, (_, p)) in poses.iter().enumerate() {
        let m = p.matrix();
        for r in 0..4 {
            for c in 0..4 {
                out[(i, r, c)] = m[(r, c)];
            }
        }
    }
    (t.into_pyarray(py), out.into_pyarray(py))
}

/// The SLAM system (see `dhptam.System`).
#[pyclass(name = "PySystem", module = "dhptam._core", frozen)]
pub struct PySystem {
    inner: Mutex<System>,
}

impl PySystem {
    fn with<T>(&self, f: impl FnOnce(&mut System) -> T) -> T {
        let mut guard = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        f(&mut guard)
    }
}

#[pymethods]
impl PySystem {
    /// A system for the rectified stereo calibration; `threaded` runs mapping on a thread.
    #[new]
    #[pyo3(signature = (fx, fy, cx, cy, baseline_m, width, height, config=None, threaded=true))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        baseline_m: f64,
        width: u32,
        height: u32,
        config: Option<PyRef<'_, PyConfig>>,
        threaded: bool,
    ) -> PyResult<Self> {
        let calib = StereoCalibration::new(fx, fy, cx, cy, baseline_m, width, height).py()?;
        let config = config.map(|c| c.inner.clone()).unwrap_or_default();
        Ok(Self {
            inner: Mutex::new(System::new(calib, config, threaded).py()?),
        })
    }

    /// Tracks one frame; returns (pose (4, 4) world_from_cam, state, inliers, keyframe).
    /// `left_sigmas`: the left keypoints' σ in pixels (None: 1 each); `sigma_scale`: a
    /// factor on all of them (e.g. an event-dominated image); `disparity`: (scale, offset px)
    /// mapping the pair's stereo disparities to the frame cameras' (event images);
    /// `event_stereo`: an `EventStereo` reading the pair's stereo matches through the event
    /// cameras' geometry instead (warped event images; `disparity` stays the identity);
    /// `viewpoint`: (x, y, z) m, the centre of the cameras whose view the image is, in the
    /// rectified left frame camera's axes (event images warped through the plane at
    /// infinity: the left event camera's; zero: the frame cameras'); `dvs_biased`: the
    /// images are the fusion's DVS-biased rendering (keyframe floor `[tracking]
    /// dvs_keyframe_min_tracked`); `quiet`: the event window is quiet (the camera likely at
    /// rest): a frame that cannot be tracked keeps the last pose (state "held").
    #[pyo3(signature = (
        t_ns, left_keypoints, left_descriptors, right_keypoints, right_descriptors,
        left_sigmas=None, sigma_scale=1.0, disparity=(1.0, 0.0), event_stereo=None,
        viewpoint=(0.0, 0.0, 0.0), dvs_biased=false, quiet=false
    ))]
    #[allow(clippy::too_many_arguments)]
    fn track<'py>(
        &self,
        py: Python<'py>,
        t_ns: i64,
        left_keypoints: &Bound<'py, PyAny>,
        left_descriptors: &Bound<'py, PyAny>,
        right_keypoints: &Bound<'py, PyAny>,
        right_descriptors: &Bound<'py, PyAny>,
        left_sigmas: Option<&Bound<'py, PyAny>>,
        sigma_scale: f32,
        disparity: (f32, f32),
        event_stereo: Option<PyRef<'py, PyEventStereo>>,
        viewpoint: (f32, f32, f32),
        dvs_biased: bool,
        quiet: bool,
    ) -> PyResult<TrackTuple<'py>> {
        let c = [viewpoint.0, viewpoint.1, viewpoint.2];
        let lk = keypoints(left_keypoints, "left.keypoints")?;
        let rk = keypoints(right_keypoints, "right.keypoints")?;
        let ld = DescriptorArray::extract(left_descriptors, "left.descriptors")?;
        let rd = DescriptorArray::extract(right_descriptors, "right.descriptors")?;
        let ls = sigmas(left_sigmas, "left.sigmas")?;
        let es = event_stereo.as_deref();
        let left = features(
            &lk,
            &ld,
            ls.as_ref(),
            sigma_scale,
            disparity,
            es,
            c,
            dvs_biased,
            quiet,
        )?;
        let right = features(
            &rk,
            &rd,
            None,
            sigma_scale,
            disparity,
            es,
            c,
            dvs_biased,
            quiet,
        )?;
        let r = py
            .detach_guarded("slam::track", || self.with(|s| s.track(t_ns, left, right)))?
            .py()?;
        Ok(track_tuple(py, &r))
    }

    /// Moves the pose on to `t_ns` with the motion model instead of tracking (a flooded
    /// event window); returns (pose (4, 4) world_from_cam, state, 0, False).
    fn predict<'py>(&self, py: Python<'py>, t_ns: i64) -> PyResult<TrackTuple<'py>> {
        let r = py
            .detach_guarded("slam::predict", || self.with(|s| s.predict(t_ns)))?
            .py()?;
        Ok(track_tuple(py, &r))
    }

    /// Bridge keyframe at the last tracked frame `t_ns` (see `dhptam.System.bridge`):
    /// `primary` features are the image that frame was tracked with, `other` the same data
    /// rendered the other way; `left_sigmas`/`other_left_sigmas` their left keypoints' σ
    /// (None: 1 each), `sigma_scale`/`other_sigma_scale` factors on them,
    /// `disparity`/`other_disparity` their disparity corrections and
    /// `event_stereo`/`other_event_stereo` their event-stereo readings and
    /// `viewpoint`/`other_viewpoint` their viewpoints (see `track`). Returns
    /// (keyframe id, re-matched map points, points from the other image), or None when
    /// refused.
    #[pyo3(signature = (
        t_ns, left_keypoints, left_descriptors, right_keypoints, right_descriptors,
        other_left_keypoints, other_left_descriptors, other_right_keypoints,
        other_right_descriptors, left_sigmas=None, other_left_sigmas=None, sigma_scale=1.0,
        other_sigma_scale=1.0, disparity=(1.0, 0.0), other_disparity=(1.0, 0.0),
        event_stereo=None, other_event_stereo=None, viewpoint=(0.0, 0.0, 0.0),
        other_viewpoint=(0.0, 0.0, 0.0)
    ))]
    #[allow(clippy::too_many_arguments)]
    fn bridge<'py>(
        &self,
        py: Python<'py>,
        t_ns: i64,
        left_keypoints: &Bound<'py, PyAny>,
        left_descriptors: &Bound<'py, PyAny>,
        right_keypoints: &Bound<'py, PyAny>,
        right_descriptors: &Bound<'py, PyAny>,
        other_left_keypoints: &Bound<'py, PyAny>,
        other_left_descriptors: &Bound<'py, PyAny>,
        other_right_keypoints: &Bound<'py, PyAny>,
        other_right_descriptors: &Bound<'py, PyAny>,
        left_sigmas: Option<&Bound<'py, PyAny>>,
        other_left_sigmas: Option<&Bound<'py, PyAny>>,
        sigma_scale: f32,
        other_sigma_scale: f32,
        disparity: (f32, f32),
        other_disparity: (f32, f32),
        event_stereo: Option<PyRef<'py, PyEventStereo>>,
        other_event_stereo: Option<PyRef<'py, PyEventStereo>>,
        viewpoint: (f32, f32, f32),
        other_viewpoint: (f32, f32, f32),
    ) -> PyResult<Option<(u64, usize, usize)>> {
        let c = [viewpoint.0, viewpoint.1, viewpoint.2];
        let oc = [other_viewpoint.0, other_viewpoint.1, other_viewpoint.2];
        let lk = keypoints(left_keypoints, "left.keypoints")?;
        let rk = keypoints(right_keypoints, "right.keypoints")?;
        let olk = keypoints(other_left_keypoints, "other_left.keypoints")?;
        let ork = keypoints(other_right_keypoints, "other_right.keypoints")?;
        let ld = DescriptorArray::extract(left_descriptors, "left.descriptors")?;
        let rd = DescriptorArray::extract(right_descriptors, "right.descriptors")?;
        let old = DescriptorArray::extract(other_left_descriptors, "other_left.descriptors")?;
        let ord = DescriptorArray::extract(other_right_descriptors, "other_right.descriptors")?;
        let ls = sigmas(left_sigmas, "left.sigmas")?;
        let ols = sigmas(other_left_sigmas, "other_left.sigmas")?;
        let (es, oes) = (event_stereo.as_deref(), other_event_stereo.as_deref());
        let primary = (
            // A bridge is a keyframe whatever its count: the floor does not apply; nor is
            // it ever held.
            features(
                &lk,
                &ld,
                ls.as_ref(),
                sigma_scale,
                disparity,
                es,
                c,
                false,
                false,
            )?,
            features(&rk, &rd, None, sigma_scale, disparity, es, c, false, false)?,
        );
        let other = (
            features(
                &olk,
                &old,
                ols.as_ref(),
                other_sigma_scale,
                other_disparity,
                oes,
                oc,
                false,
                false,
            )?,
            features(
                &ork,
                &ord,
                None,
                other_sigma_scale,
                other_disparity,
                oes,
                oc,
                false,
                false,
            )?,
        );
        let b = py
            .detach_guarded("slam::bridge", || {
                self.with(|s| s.bridge(t_ns, primary, other))
            })?
            .py()?;
        Ok(b.map(|b| (b.keyframe, b.linked, b.other_points)))
    }

    /// {bridges, bridges_refused, segments, relocalisations, predicted, held, implausible}
    /// since the start.
    fn tracking_totals<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let t = self.with(|s| s.tracking_totals());
        let d = PyDict::new(py);
        d.set_item("bridges", t.bridges)?;
        d.set_item("bridges_refused", t.bridges_refused)?;
        d.set_item("segments", t.segments)?;
        d.set_item("relocalisations", t.relocalisations)?;
        d.set_item("predicted", t.predicted)?;
        d.set_item("held", t.held)?;
        d.set_item("implausible", t.implausible)?;
        Ok(d)
    }

    /// Median depth (m) of the map points the last `track` measured its pose with; None
    /// before the first frame, after a lost one or without such points.
    fn tracked_depth(&self) -> Option<f64> {
        self.with(|s| s.tracked_depth())
    }

    /// (t_ns (N,) int64, poses (N, 4, 4) world_from_cam) of every tracked frame; `smoothed`:
    /// the centres of the trajectory smoother when `[tracking] smoothing_q` > 0.
    #[pyo3(signature = (smoothed = true))]
    fn trajectory<'py>(
        &self,
        py: Python<'py>,
        smoothed: bool,
    ) -> PyResult<(Bound<'py, PyArray1<i64>>, Bound<'py, PyArray3<f64>>)> {
        let poses = py.detach_guarded("slam::trajectory", || {
            self.with(|s| {
                if smoothed {
                    s.trajectory()
                } else {
                    s.tracked_trajectory()
                }
            })
        })?;
        Ok(poses_arrays(py, &poses))
    }

    /// The same for the keyframes.
    fn keyframe_trajectory<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(Bound<'py, PyArray1<i64>>, Bound<'py, PyArray3<f64>>)> {
        let poses = py.detach_guarded("slam::keyframe_trajectory", || {
            self.with(|s| s.keyframe_trajectory())
        })?;
        Ok(poses_arrays(py, &poses))
    }

    /// Map point positions (N, 3), world frame, metres.
    fn map_points<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let points = py.detach_guarded("slam::map_points", || self.with(|s| s.map_points()))?;
        let flat: Vec<f64> = points.iter().flatten().copied().collect();
        let n = points.len();
        numpy::ndarray::Array2::from_shape_vec((n, 3), flat)
            .map(|a| a.into_pyarray(py))
            .map_err(|e| input_error("map points", "an (N, 3) array", e))
    }

    /// Loop closures as (query keyframe t_ns, matched keyframe t_ns).
    fn loop_closures(&self, py: Python<'_>) -> PyResult<Vec<(i64, i64)>> {
        py.detach_guarded("slam::loop_closures", || self.with(|s| s.loop_closures()))
    }

    /// Stage → {count, total_s, mean_s, max_s}.
    fn timing<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let t = self.with(|s| s.timing());
        let d = PyDict::new(py);
        for (stage, s) in t {
            let e = PyDict::new(py);
            e.set_item("count", s.count)?;
            e.set_item("total_s", s.total_s)?;
            e.set_item("mean_s", s.mean_s())?;
            e.set_item("max_s", s.max_s)?;
            d.set_item(stage, e)?;
        }
        Ok(d)
    }

    /// Writes the map and tracker state to `path`.
    fn save_map(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        py.detach_guarded("slam::save_map", || self.with(|s| s.save_map(&path)))?
            .py()
    }

    /// Replaces the map and tracker state with those in `path`.
    fn load_map(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        py.detach_guarded("slam::load_map", || self.with(|s| s.load_map(&path)))?
            .py()
    }

    /// Bundle adjustment of the whole map (every keyframe and point; the first keyframe of
    /// each map segment held) with `iterations` iterations, for after the last frame;
    /// returns {optimised, fixed, points, outliers_removed, culled}.
    fn refine_map<'py>(&self, py: Python<'py>, iterations: u32) -> PyResult<Bound<'py, PyDict>> {
        let r = py
            .detach_guarded("slam::refine_map", || {
                self.with(|s| s.refine_map(iterations))
            })?
            .py()?;
        let d = PyDict::new(py);
        d.set_item("optimised", r.optimised)?;
        d.set_item("fixed", r.fixed)?;
        d.set_item("points", r.points)?;
        d.set_item("outliers_removed", r.outliers_removed)?;
        d.set_item("culled", r.culled)?;
        Ok(d)
    }

    /// Stops the worker threads; later `track` calls raise.
    fn shutdown(&self, py: Python<'_>) -> PyResult<()> {
        py.detach_guarded("slam::shutdown", || self.with(|s| s.shutdown()))
    }

    /// Whether mapping runs on its own thread.
    #[getter]
    fn threaded(&self) -> bool {
        self.with(|s| s.threaded())
    }
}
