//! Fusion of events and frames: the online β, the blend, and the event→frame warp.

use dhptam_core::config::FusionConfig;
use std::sync::{Arc, Mutex};

use dhptam_core::fusion::{self, Depth, EventFrameWarp, EventRectifier, EventStereo, WarpMap};
use dhptam_core::geometry::Pinhole;
use nalgebra::Vector2;
use numpy::ndarray::{Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use crate::arrays;
use crate::config::PyConfig;
use crate::errors::DetachGuarded;
use crate::errors::{input_error, IntoPyResult};
use crate::geometry::PySe3;
use crate::stereo::{parse_side, PyRectifiedStereo};

fn settings(config: Option<&PyConfig>) -> FusionConfig {
    config.map(|c| c.inner.fusion.clone()).unwrap_or_default()
}

/// β of an 8-bit frame: `(bias, beta, ratio, clipped_fraction)`.
#[pyfunction]
#[pyo3(signature = (frame, feature_count=None, config=None))]
pub fn _choose_beta(
    py: Python<'_>,
    frame: PyReadonlyArray2<'_, u8>,
    feature_count: Option<usize>,
    config: Option<&PyConfig>,
) -> PyResult<(String, f64, f64, f64)> {
    let pixels = frame
        .as_slice()
        .map_err(|_| input_error("frame", "a C-contiguous uint8 image", "a strided view"))?;
    let settings = settings(config);
    let d = py
        .detach_guarded("fusion::_choose_beta", || {
            fusion::choose_beta(pixels, feature_count, &settings)
        })?
        .py()?;
    Ok((
        d.bias.as_str().to_owned(),
        d.beta,
        d.ratio,
        d.clipped_fraction,
    ))
}

/// What the exposure check found, and the stretched frame when it was stretched:
/// `(image or None, failed, low, high, noise, clipped_fraction)`.
type ExposureResult<'py> = (Option<Bound<'py, PyArray2<u8>>>, bool, u8, u8, f64, f64);

/// Checks an 8-bit frame's exposure and stretches a failed frame with a good signal
/// (`fusion::recover_exposure`); the input is not modified.
#[pyfunction]
#[pyo3(signature = (frame, config=None))]
pub fn _recover_exposure<'py>(
    py: Python<'py>,
    frame: PyReadonlyArray2<'py, u8>,
    config: Option<&PyConfig>,
) -> PyResult<ExposureResult<'py>> {
    let (h, w) = (frame.shape()[0], frame.shape()[1]);
    let pixels = frame
        .as_slice()
        .map_err(|_| input_error("frame", "a C-contiguous uint8 image", "a strided view"))?;
    let settings = settings(config);
    // The frame is copied only when it is to be stretched (most frames pass the test).
    let (image, check) = py
        .detach_guarded("fusion::_recover_exposure", || {
            fusion::check_exposure(pixels, w, &settings).map(|check| {
                let image = check.stretched.then(|| {
                    let mut image = pixels.to_vec();
                    fusion::stretch_levels(&mut image, w, check.low, check.high);
                    image
                });
                (image, check)
            })
        })?
        .py()?;
    let stretched = if let Some(image) = image {
        let array = Array2::from_shape_vec((h, w), image)
            .map_err(|e| input_error("frame", "a consistent size", e))?;
        Some(array.into_pyarray(py))
    } else {
        None
    };
    Ok((
        stretched,
        check.failed,
        check.low,
        check.high,
        check.noise,
        check.clipped_fraction,
    ))
}

/// `(1 − β) frame + β · 255 · max_c(e3ct)`, rounded to uint8.
#[pyfunction]
pub fn _fuse<'py>(
    py: Python<'py>,
    frame: PyReadonlyArray2<'py, u8>,
    e3ct: PyReadonlyArray3<'py, f32>,
    beta: f64,
) -> PyResult<Bound<'py, PyArray2<u8>>> {
    let (h, w) = (frame.shape()[0], frame.shape()[1]);
    if e3ct.shape()[..2] != [h, w] {
        return Err(input_error(
            "e3ct",
            &format!("an ({h}, {w}, C) array, the frame's size"),
            format!("shape {:?}", e3ct.shape()),
        ));
    }
    let c = e3ct.shape()[2];
    let pixels = frame
        .as_slice()
        .map_err(|_| input_error("frame", "a C-contiguous uint8 image", "a strided view"))?;
    let events = e3ct
        .as_slice()
        .map_err(|_| input_error("e3ct", "a C-contiguous float32 array", "a strided view"))?;
    let fused = py
        .detach_guarded("fusion::_fuse", || {
            fusion::fuse_e3ct(pixels, events, c, beta)
        })?
        .py()?;
    Array2::from_shape_vec((h, w), fused)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| input_error("frame", "a consistent size", e))
}

fn pinhole(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Pinhole> {
    let [fx, fy, cx, cy] = arrays::vector::<4>(obj, name)?;
    Ok(Pinhole { fx, fy, cx, cy })
}

/// Warp maps kept for reuse, most recently used first (the front-end warps every frame of a
/// sequence with the same two warps).
static WARP_MAPS: Mutex<Vec<(WarpKey, Arc<WarpMap>)>> = Mutex::new(Vec::new());
/// How many warp maps [`WARP_MAPS`] keeps (12 bytes per frame pixel each).
const WARP_MAPS_KEPT: usize = 4;

/// What a warp map depends on: the bits of the homography and of δP_align, and the sizes.
#[derive(Clone, Copy, PartialEq, Eq)]
struct WarpKey {
    homography: [u64; 9],
    align: [u64; 2],
    sizes: [usize; 4],
}

/// The warp map of `warp` for these sizes, from the cache or built (with the GIL released by
/// the caller) and cached.
fn cached_map(
    warp: &EventFrameWarp,
    align: [f64; 2],
    sizes: [usize; 4],
) -> dhptam_core::Result<Arc<WarpMap>> {
    let key = WarpKey {
        homography: std::array::from_fn(|i| warp.homography().as_slice()[i].to_bits()),
        align: align.map(f64::to_bits),
        sizes,
    };
    // A poisoned lock only means another thread panicked while holding it; the list is valid.
    let lock = || WARP_MAPS.lock().unwrap_or_else(|e| e.into_inner());
    {
        let mut maps = lock();
        if let Some(i) = maps.iter().position(|(k, _)| *k == key) {
            let entry = maps.remove(i);
            let map = Arc::clone(&entry.1);
            maps.insert(0, entry);
            return Ok(map);
        }
    }
    let [sw, sh, w, h] = sizes;
    let map = Arc::new(warp.map(sw, sh, w, h)?);
    let mut maps = lock();
    maps.insert(0, (key, Arc::clone(&map)));
    maps.truncate(WARP_MAPS_KEPT);
    Ok(map)
}

/// The warp of eq. 5 from the binding's arguments (`depth_m` 0: infinity) and δP_align.
fn event_frame_warp(
    k_event: &Bound<'_, PyAny>,
    k_frame: &Bound<'_, PyAny>,
    frame_from_event: &PySe3,
    depth_m: f64,
    align_px: &Bound<'_, PyAny>,
) -> PyResult<(EventFrameWarp, [f64; 2])> {
    let depth = if depth_m == 0.0 {
        Depth::Infinity
    } else {
        Depth::Plane { depth_m }
    };
    let [ax, ay] = arrays::vector::<2>(align_px, "align_px")?;
    let warp = EventFrameWarp::new(
        pinhole(k_event, "k_event")?,
        pinhole(k_frame, "k_frame")?,
        frame_from_event.inner,
        depth,
        Vector2::new(ax, ay),
    )
    .py()?;
    Ok((warp, [ax, ay]))
}

/// The event image's values in place and its `[height, width, channels]`, with `scales`
/// (if any) checked to be one per channel.
fn event_image<'a>(
    image: &'a PyReadonlyArray3<'_, f32>,
    scales: Option<&[f32]>,
) -> PyResult<(&'a [f32], [usize; 3])> {
    let shape = [image.shape()[0], image.shape()[1], image.shape()[2]];
    let c = shape[2];
    let src = image
        .as_slice()
        .map_err(|_| input_error("image", "a C-contiguous float32 array", "a strided view"))?;
    if let Some(scales) = scales {
        if scales.len() != c {
            return Err(input_error(
                "scales",
                &format!("{c} scales, one per channel of image"),
                format!("{} scales", scales.len()),
            ));
        }
    }
    Ok((src, shape))
}

/// Warps a rectified event image (H, W, C) into the rectified frame camera; with `scales`
/// (one per channel) each bilinear tap is normalised first (`_e3ct_apply_scales`), the same
/// values as warping the normalised image. The inverse map of the warp is computed once per
/// (warp, sizes) and reused by later calls.
#[pyfunction]
#[pyo3(signature = (image, k_event, k_frame, frame_from_event, depth_m, align_px, width, height, pixels=None, scales=None))]
#[allow(clippy::too_many_arguments)]
pub fn _warp_to_frame<'py>(
    py: Python<'py>,
    image: PyReadonlyArray3<'py, f32>,
    k_event: &Bound<'py, PyAny>,
    k_frame: &Bound<'py, PyAny>,
    frame_from_event: &PySe3,
    depth_m: f64,
    align_px: &Bound<'py, PyAny>,
    width: usize,
    height: usize,
    pixels: Option<&Bound<'py, PyAny>>,
    scales: Option<Vec<f32>>,
) -> PyResult<(Bound<'py, PyArray3<f32>>, Option<Bound<'py, PyArray2<f64>>>)> {
    let (warp, [ax, ay]) = event_frame_warp(k_event, k_frame, frame_from_event, depth_m, align_px)?;
    let (src, [sh, sw, c]) = event_image(&image, scales.as_deref())?;
    let out = py
        .detach_guarded("fusion::_warp_to_frame", || {
            cached_map(&warp, [ax, ay], [sw, sh, width, height])?.apply(src, c, scales.as_deref())
        })?
        .py()?;
    let out = Array3::from_shape_vec((height, width, c), out)
        .map_err(|e| input_error("image", "a consistent size", e))?
        .into_pyarray(py);
    let warped = match pixels {
        None => None,
        Some(p) => {
            let p = arrays::rows(p, 2, "pixels")?;
            let view = p.as_array();
            let mut uv = Array2::from_elem((view.nrows(), 2), f64::NAN);
            for (i, row) in view.rows().into_iter().enumerate() {
                if let Some(q) = warp.warp_pixel(&Vector2::new(row[0], row[1])) {
                    uv[[i, 0]] = q.x;
                    uv[[i, 1]] = q.y;
                }
            }
            Some(uv.into_pyarray(py))
        }
    };
    Ok((out, warped))
}

/// `_warp_to_frame` of `image` into the frame camera of `frame` (its size) and, in the same
/// pass, `_fuse(frame, warped, beta)`: returns `(warped, fused)`, the same values as the two
/// calls, without reading the warped image back (β is chosen from the frame before the warp).
#[pyfunction]
#[pyo3(signature = (image, k_event, k_frame, frame_from_event, depth_m, align_px, frame, beta, scales=None))]
#[allow(clippy::too_many_arguments)]
pub fn _warp_and_fuse<'py>(
    py: Python<'py>,
    image: PyReadonlyArray3<'py, f32>,
    k_event: &Bound<'py, PyAny>,
    k_frame: &Bound<'py, PyAny>,
    frame_from_event: &PySe3,
    depth_m: f64,
    align_px: &Bound<'py, PyAny>,
    frame: PyReadonlyArray2<'py, u8>,
    beta: f64,
    scales: Option<Vec<f32>>,
) -> PyResult<(Bound<'py, PyArray3<f32>>, Bound<'py, PyArray2<u8>>)> {
    let (warp, [ax, ay]) = event_frame_warp(k_event, k_frame, frame_from_event, depth_m, align_px)?;
    let (src, [sh, sw, c]) = event_image(&image, scales.as_deref())?;
    let (height, width) = (frame.shape()[0], frame.shape()[1]);
    let pixels = frame
        .as_slice()
        .map_err(|_| input_error("frame", "a C-contiguous uint8 image", "a strided view"))?;
    let (warped, fused) = py
        .detach_guarded("fusion::_warp_and_fuse", || {
            cached_map(&warp, [ax, ay], [sw, sh, width, height])?.apply_fused(
                src,
                c,
                scales.as_deref(),
                pixels,
                beta,
            )
        })?
        .py()?;
    let warped = Array3::from_shape_vec((height, width, c), warped)
        .map_err(|e| input_error("image", "a consistent size", e))?
        .into_pyarray(py);
    let fused = Array2::from_shape_vec((height, width), fused)
        .map_err(|e| input_error("frame", "a consistent size", e))?
        .into_pyarray(py);
    Ok((warped, fused))
}

/// Rectified event arrays `(x uint16, y uint16, t_ns int64, p int8)`.
type RectifiedArrays<'py> = (
    Bound<'py, PyArray1<u16>>,
    Bound<'py, PyArray1<u16>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<i8>>,
);

/// Raw event pixel → rectified pixel lookup table of one camera of a rectified event-camera
/// pair, built once (see `dhptam_core::fusion::EventRectifier`).
#[pyclass(name = "EventRectifier", module = "dhptam._core")]
pub struct PyEventRectifier {
    inner: EventRectifier,
}

#[pymethods]
impl PyEventRectifier {
    /// Builds the table of camera `side` ("left"/"right") of the rectified pair `rect`.
    #[new]
    fn new(py: Python<'_>, rect: &PyRectifiedStereo, side: &str) -> PyResult<Self> {
        let side = parse_side(side)?;
        let inner = py.detach_guarded("fusion::new", || EventRectifier::new(&rect.inner, side))?;
        Ok(Self { inner })
    }

    /// Drops the events of raw pixels `pixels` (uint32 indices `v · width + u`, e.g.
    /// `HotPixels.pixels()`) from now on, replacing the previous mask; `[]` restores the table.
    fn set_masked(&mut self, pixels: PyReadonlyArray1<'_, u32>) -> PyResult<()> {
        let pixels = crate::events::exact(&pixels, "pixels")?;
        self.inner.set_masked(pixels).py()
    }

    /// How many raw pixels inside the rectified view the mask drops.
    #[getter]
    fn masked_count(&self) -> usize {
        self.inner.masked_count()
    }

    /// Raw (event camera) image size `(width, height)`.
    #[getter]
    fn raw_size(&self) -> (u32, u32) {
        (self.inner.width, self.inner.height)
    }

    /// Rectified image size `(width, height)`.
    #[getter]
    fn rect_size(&self) -> (u32, u32) {
        (self.inner.rect_width, self.inner.rect_height)
    }

    /// Moves the events of `[t_start_ns, t_end_ns)` to their rectified pixels (nearest pixel).
    ///
    /// The arrays must have the exact dtypes (uint16, uint16, int64, int8) and be
    /// C-contiguous; they are read in place with the GIL released. Raw pixels outside the raw
    /// image, bad polarities and times outside the window or decreasing are errors naming the
    /// event; events whose ray leaves the rectified view are dropped.
    #[allow(clippy::too_many_arguments)]
    fn apply<'py>(
        &self,
        py: Python<'py>,
        x: PyReadonlyArray1<'py, u16>,
        y: PyReadonlyArray1<'py, u16>,
        t_ns: PyReadonlyArray1<'py, i64>,
        p: PyReadonlyArray1<'py, i8>,
        t_start_ns: i64,
        t_end_ns: i64,
    ) -> PyResult<RectifiedArrays<'py>> {
        let window = (x, y, t_ns, p);
        let slice = crate::events::event_slice(&window)?;
        let out = py
            .detach_guarded("fusion::apply", || {
                self.inner.apply(&slice, t_start_ns, t_end_ns)
            })?
            .py()?;
        Ok((
            out.x.into_pyarray(py),
            out.y.into_pyarray(py),
            out.t_ns.into_pyarray(py),
            out.p.into_pyarray(py),
        ))
    }

    /// Rectified pixels `(N, 2)` (float64, NaN outside the rectified view) of raw integer
    /// pixels `(N, 2)`, through the same table as [`apply`].
    fn lookup<'py>(
        &self,
        py: Python<'py>,
        pixels: PyReadonlyArray2<'py, i64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let view = pixels.as_array();
        if view.ncols() != 2 {
            return Err(input_error(
                "pixels",
                "an (N, 2) array",
                format!("shape {:?}", view.shape()),
            ));
        }
        let mut out = Array2::from_elem((view.nrows(), 2), f64::NAN);
        for (i, row) in view.rows().into_iter().enumerate() {
            let (u, v) = (row[0], row[1]);
            if let (Ok(u), Ok(v)) = (u16::try_from(u), u16::try_from(v)) {
                if let Some((ru, rv)) = self.inner.lookup(u, v) {
                    out[[i, 0]] = f64::from(ru);
                    out[[i, 1]] = f64::from(rv);
                }
            }
        }
        Ok(out.into_pyarray(py))
    }
}

/// Reads stereo matches of event images warped into the rectified frame cameras as the frame
/// cameras would have measured them (see `dhptam_core::fusion::EventStereo`).
#[pyclass(name = "EventStereo", module = "dhptam._core", frozen)]
pub struct PyEventStereo {
    pub(crate) inner: EventStereo,
}

#[pymethods]
impl PyEventStereo {
    /// `k_event`, `k_frame`: rectified intrinsics `[fx, fy, cx, cy]` of the event and frame
    /// pairs, with their baselines (metres); `frame_from_event_left`/`_right`: rectified
    /// event camera → rectified frame camera per side; `depth_m` the warp plane (0:
    /// infinity) and `align_px` δP_align, as the warps that rendered the images.
    #[new]
    #[pyo3(signature = (
        k_event, event_baseline_m, k_frame, frame_baseline_m, frame_from_event_left,
        frame_from_event_right, depth_m, align_px=(0.0, 0.0)
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        k_event: &Bound<'_, PyAny>,
        event_baseline_m: f64,
        k_frame: &Bound<'_, PyAny>,
        frame_baseline_m: f64,
        frame_from_event_left: &PySe3,
        frame_from_event_right: &PySe3,
        depth_m: f64,
        align_px: (f64, f64),
    ) -> PyResult<Self> {
        if !(depth_m.is_finite() && depth_m >= 0.0) {
            return Err(input_error(
                "depth_m",
                "a plane depth in metres (>= 0, 0: infinity)",
                depth_m,
            ));
        }
        let depth = if depth_m == 0.0 {
            Depth::Infinity
        } else {
            Depth::Plane { depth_m }
        };
        let inner = EventStereo::new(
            pinhole(k_event, "k_event")?,
            event_baseline_m,
            pinhole(k_frame, "k_frame")?,
            frame_baseline_m,
            [frame_from_event_left.inner, frame_from_event_right.inner],
            depth,
            Vector2::new(align_px.0, align_px.1),
        )
        .py()?;
        Ok(Self { inner })
    }

    /// The frame cameras' `(u_left, v, u_right)` `(N, 3)` of warped matches `(N, 3)`
    /// `(u_left, v, u_right)`; NaN rows where a match cannot be read (see `frame_reading`).
    fn frame_readings<'py>(
        &self,
        py: Python<'py>,
        matches: PyReadonlyArray2<'py, f32>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let view = matches.as_array();
        if view.ncols() != 3 {
            return Err(input_error(
                "matches",
                "an (N, 3) array of (u_left, v, u_right)",
                format!("shape {:?}", view.shape()),
            ));
        }
        let mut out = Array2::<f32>::from_elem((view.nrows(), 3), f32::NAN);
        for (mut row, m) in out.rows_mut().into_iter().zip(view.rows()) {
            if let Some(([u, v], ur)) = self.inner.frame_reading([m[0], m[1]], m[2]) {
                row[0] = u;
                row[1] = v;
                row[2] = ur;
            }
        }
        Ok(out.into_pyarray(py))
    }
}
