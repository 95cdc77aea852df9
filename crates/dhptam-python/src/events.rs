//! Event representations: the E3CT, its normalisation and the ablation baselines.
//!
//! The event arrays must arrive with their exact dtypes (x, y uint16; t_ns int64; p int8)
//! and C-contiguous; they are then read in place. `dhptam.events` converts anything else once,
//! with range checks, before calling these functions.

use std::sync::Mutex;

use dhptam_core::events::{self, E3ctParams, E3ctWorkspace, EventSlice, PolarityMode};
use numpy::ndarray::{Array3, ArrayD, IxDyn};
use numpy::{
    Element, IntoPyArray, PyArray3, PyArrayDyn, PyArrayMethods, PyReadonlyArray1,
    PyReadonlyArrayDyn, PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use crate::errors::DetachGuarded;
use crate::errors::{input_error, IntoPyResult};

/// A contiguous 1-D array of exactly `T`, borrowed in place.
pub(crate) fn exact<'a, 'py, T: Element>(
    array: &'a PyReadonlyArray1<'py, T>,
    name: &str,
) -> PyResult<&'a [T]> {
    array
        .as_slice()
        .map_err(|_| input_error(name, "a C-contiguous array", "a strided view"))
}

fn parse_polarity(polarity: &str) -> PyResult<PolarityMode> {
    match polarity {
        "both" => Ok(PolarityMode::Both),
        "split" => Ok(PolarityMode::Split),
        other => Err(input_error(
            "polarity",
            "\"both\" or \"split\"",
            format!("{other:?}"),
        )),
    }
}

pub(crate) type Window<'py> = (
    PyReadonlyArray1<'py, u16>,
    PyReadonlyArray1<'py, u16>,
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, i8>,
);

/// The four event arrays of `window` borrowed in place as one [`EventSlice`] (equal lengths,
/// contiguous; errors name the array).
pub(crate) fn event_slice<'a>(window: &'a Window<'_>) -> PyResult<EventSlice<'a>> {
    EventSlice::new(
        exact(&window.0, "x")?,
        exact(&window.1, "y")?,
        exact(&window.2, "t_ns")?,
        exact(&window.3, "p")?,
    )
    .py()
}

/// Runs `f` on the borrowed window with the GIL released and shapes its output (H, W, C).
fn image<'py>(
    py: Python<'py>,
    window: &Window<'py>,
    width: u32,
    height: u32,
    f: impl FnOnce(&EventSlice<'_>) -> dhptam_core::Result<Vec<f32>> + Send,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let slice = event_slice(window)?;
    let data = py.detach_guarded("events::image", || f(&slice))?.py()?;
    let pixels = width as usize * height as usize;
    let channels = data.len().checked_div(pixels).unwrap_or(0);
    Array3::from_shape_vec((height as usize, width as usize, channels), data)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| input_error("width/height", "a consistent image size", e))
}

/// E3CT of one window, (H, W, C) float32, not normalised.
#[pyfunction]
#[pyo3(signature = (x, y, t_ns, p, width, height, t_start_ns, t_end_ns, alpha, eta_ms, channels, polarity))]
#[allow(clippy::too_many_arguments)]
pub fn _e3ct<'py>(
    py: Python<'py>,
    x: PyReadonlyArray1<'py, u16>,
    y: PyReadonlyArray1<'py, u16>,
    t_ns: PyReadonlyArray1<'py, i64>,
    p: PyReadonlyArray1<'py, i8>,
    width: u32,
    height: u32,
    t_start_ns: i64,
    t_end_ns: i64,
    alpha: f64,
    eta_ms: f64,
    channels: usize,
    polarity: &str,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let params = E3ctParams {
        alpha,
        eta_ms,
        channels,
        polarity: parse_polarity(polarity)?,
    };
    let window = (x, y, t_ns, p);
    let slice = event_slice(&window)?;
    let image = numpy_image(py, width, height, params.output_channels());
    let mut view = image.readwrite();
    let out = view.as_slice_mut()?;
    py.detach_guarded("events::e3ct", || {
        with_workspace(|workspace| {
            events::e3ct_into(
                &slice, width, height, t_start_ns, t_end_ns, &params, workspace, out,
            )
        })
    })?
    .py()?;
    drop(view);
    Ok(image)
}

/// An uninitialised `(height, width, channels)` float32 array from numpy's allocator, for
/// `e3ct_into`, which writes every value (each band zeroes its rows, in parallel, before
/// adding). A zeroed `Vec` cost a serial memset of the whole 11 MB tensor (1280×720×3) before
/// the kernel: ~2 ms per window on the 2-core box (BENCHMARKS, "E3CT output without the
/// zeroing").
fn numpy_image(
    py: Python<'_>,
    width: u32,
    height: u32,
    channels: usize,
) -> Bound<'_, PyArray3<f32>> {
    let dims = [height as usize, width as usize, channels];
    // SAFETY: the caller hands the whole array to `e3ct_into`, which overwrites every value
    // (or fails before writing any), before the array reaches Python; on an error it is
    // dropped unread.
    unsafe { PyArray3::<f32>::new(py, dims, false) }
}

/// Runs `f` with a workspace from [`WORKSPACES`] (a fresh one when the pool is empty) and
/// returns it to the pool: fresh scratch pages for every window cost as much as the pass
/// that fills them.
fn with_workspace<R>(f: impl FnOnce(&mut E3ctWorkspace) -> R) -> R {
    let mut workspace = WORKSPACES
        .lock()
        .ok()
        .and_then(|mut pool| pool.pop())
        .unwrap_or_default();
    let result = f(&mut workspace);
    if let Ok(mut pool) = WORKSPACES.lock() {
        if pool.len() < MAX_POOLED_WORKSPACES {
            pool.push(workspace);
        }
    }
    result
}

/// E3CT scratch memory kept between calls, one per concurrent caller (up to
/// [`MAX_POOLED_WORKSPACES`]); each holds 8 bytes per event of the largest window it served.
static WORKSPACES: Mutex<Vec<E3ctWorkspace>> = Mutex::new(Vec::new());

/// Most workspaces [`WORKSPACES`] keeps (two cameras, a prefetching thread and a spare).
const MAX_POOLED_WORKSPACES: usize = 4;

/// Event count image, (H, W, 1) or (H, W, 2) float32.
#[pyfunction]
#[pyo3(signature = (x, y, t_ns, p, width, height, t_start_ns, t_end_ns, polarity))]
#[allow(clippy::too_many_arguments)]
pub fn _count_image<'py>(
    py: Python<'py>,
    x: PyReadonlyArray1<'py, u16>,
    y: PyReadonlyArray1<'py, u16>,
    t_ns: PyReadonlyArray1<'py, i64>,
    p: PyReadonlyArray1<'py, i8>,
    width: u32,
    height: u32,
    t_start_ns: i64,
    t_end_ns: i64,
    polarity: &str,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let polarity = parse_polarity(polarity)?;
    image(py, &(x, y, t_ns, p), width, height, |s| {
        events::count_image(s, width, height, t_start_ns, t_end_ns, polarity)
    })
}

/// Pixel activity of one window: `(pixels, active, supported)` (see the core's
/// `events::activity`); x and y uint16, C-contiguous, read in place with the GIL released.
#[pyfunction]
#[pyo3(signature = (x, y, width, height))]
pub fn _event_activity(
    py: Python<'_>,
    x: PyReadonlyArray1<'_, u16>,
    y: PyReadonlyArray1<'_, u16>,
    width: u32,
    height: u32,
) -> PyResult<(u64, u64, u64)> {
    let (xs, ys) = (exact(&x, "x")?, exact(&y, "y")?);
    let a = py
        .detach_guarded("events::activity", || {
            events::activity(xs, ys, width, height)
        })?
        .py()?;
    Ok((a.pixels, a.active, a.supported))
}

/// Time surface, (H, W, 2) float32 (ON, OFF).
#[pyfunction]
#[pyo3(signature = (x, y, t_ns, p, width, height, t_start_ns, t_end_ns, tau_ms))]
#[allow(clippy::too_many_arguments)]
pub fn _time_surface<'py>(
    py: Python<'py>,
    x: PyReadonlyArray1<'py, u16>,
    y: PyReadonlyArray1<'py, u16>,
    t_ns: PyReadonlyArray1<'py, i64>,
    p: PyReadonlyArray1<'py, i8>,
    width: u32,
    height: u32,
    t_start_ns: i64,
    t_end_ns: i64,
    tau_ms: f64,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    image(py, &(x, y, t_ns, p), width, height, |s| {
        events::time_surface(s, width, height, t_start_ns, t_end_ns, tau_ms)
    })
}

/// Voxel grid, (H, W, bins) float32.
#[pyfunction]
#[pyo3(signature = (x, y, t_ns, p, width, height, t_start_ns, t_end_ns, bins))]
#[allow(clippy::too_many_arguments)]
pub fn _voxel_grid<'py>(
    py: Python<'py>,
    x: PyReadonlyArray1<'py, u16>,
    y: PyReadonlyArray1<'py, u16>,
    t_ns: PyReadonlyArray1<'py, i64>,
    p: PyReadonlyArray1<'py, i8>,
    width: u32,
    height: u32,
    t_start_ns: i64,
    t_end_ns: i64,
    bins: usize,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    image(py, &(x, y, t_ns, p), width, height, |s| {
        events::voxel_grid(s, width, height, t_start_ns, t_end_ns, bins)
    })
}

fn tensor_slice<'a>(t: &'a PyReadonlyArrayDyn<'_, f32>, name: &str) -> PyResult<&'a [f32]> {
    t.as_slice()
        .map_err(|_| input_error(name, "a C-contiguous float32 array", "a strided view"))
}

/// Per-channel scales pooled over `tensors` (each (H, W, C) float32, same C).
#[pyfunction]
pub fn _e3ct_scales(
    py: Python<'_>,
    tensors: Vec<PyReadonlyArrayDyn<'_, f32>>,
    percentile: f64,
) -> PyResult<Vec<f32>> {
    let Some(first) = tensors.first() else {
        return Err(input_error("tensors", "at least one tensor", "none"));
    };
    let channels = *first.shape().last().unwrap_or(&0);
    let mut slices = Vec::with_capacity(tensors.len());
    for (k, t) in tensors.iter().enumerate() {
        let name = format!("tensors[{k}]");
        if t.ndim() != 3 || t.shape()[2] != channels {
            return Err(input_error(
                &name,
                &format!("an (H, W, {channels}) array"),
                format!("shape {:?}", t.shape()),
            ));
        }
        slices.push(tensor_slice(t, &name)?);
    }
    py.detach_guarded("events::_e3ct_scales", || {
        events::channel_scales(&slices, channels, percentile)
    })?
    .py()
}

/// A copy of `tensor` (H, W, C) divided per channel by `scales` and clipped to [0, 1].
#[pyfunction]
pub fn _e3ct_apply_scales<'py>(
    py: Python<'py>,
    tensor: PyReadonlyArrayDyn<'py, f32>,
    scales: Vec<f32>,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    if tensor.ndim() != 3 || tensor.shape()[2] != scales.len() {
        return Err(input_error(
            "tensor",
            &format!("an (H, W, {}) array, one channel per scale", scales.len()),
            format!("shape {:?}", tensor.shape()),
        ));
    }
    let shape = tensor.shape().to_vec();
    let src = tensor_slice(&tensor, "tensor")?;
    let out = py
        .detach_guarded("events::_e3ct_apply_scales", || {
            events::scaled(src, &scales)
        })?
        .py()?;
    let out = ArrayD::from_shape_vec(IxDyn(&shape), out)
        .map_err(|e| input_error("tensor", "a consistent size", e))?
        .into_pyarray(py);
    Ok(out)
}

/// The running hot-pixel detector of one event camera (see `dhptam_core::events::hot`).
#[pyclass(name = "HotPixels", module = "dhptam._core")]
pub struct PyHotPixels {
    inner: events::HotPixels,
}

#[pymethods]
impl PyHotPixels {
    /// A detector for a `width × height` sensor (raw pixels); a parameter left out takes the
    /// `[events] hot_pixel_*` default.
    #[new]
    #[pyo3(signature = (width, height, *, ratio = None, min_rate_hz = None, time_constant_s = None))]
    fn new(
        width: u32,
        height: u32,
        ratio: Option<f64>,
        min_rate_hz: Option<f64>,
        time_constant_s: Option<f64>,
    ) -> PyResult<Self> {
        let defaults = events::HotPixelParams::default();
        let params = events::HotPixelParams {
            ratio: ratio.unwrap_or(defaults.ratio),
            min_rate_hz: min_rate_hz.unwrap_or(defaults.min_rate_hz),
            time_constant_s: time_constant_s.unwrap_or(defaults.time_constant_s),
        };
        Ok(Self {
            inner: events::HotPixels::new(width, height, params).py()?,
        })
    }

    /// Offers a window of `duration_s` seconds with events at raw pixels `(x, y)` (uint16,
    /// C-contiguous, read in place with the GIL released); returns whether the set of hot
    /// pixels changed (the detector counts one window every τ/8; see the core's docs).
    fn update(
        &mut self,
        py: Python<'_>,
        x: PyReadonlyArray1<'_, u16>,
        y: PyReadonlyArray1<'_, u16>,
        duration_s: f64,
    ) -> PyResult<bool> {
        let (xs, ys) = (exact(&x, "x")?, exact(&y, "y")?);
        let inner = &mut self.inner;
        py.detach_guarded("events::HotPixels.update", || {
            inner.update(xs, ys, duration_s)
        })?
        .py()
    }

    /// The hot pixels after the last update, raw indices `v · width + u` (uint32, ascending).
    fn pixels<'py>(&self, py: Python<'py>) -> Bound<'py, numpy::PyArray1<u32>> {
        self.inner.pixels().to_vec().into_pyarray(py)
    }

    fn __len__(&self) -> usize {
        self.inner.pixels().len()
    }
}
