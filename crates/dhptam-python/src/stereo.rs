//! Python classes for stereo geometry: `StereoRig`, `RectifiedStereo`, and triangulation.

use std::sync::OnceLock;

use dhptam_core::config::TriangulationConfig;
use dhptam_core::geometry::rectify::{
    remap_bilinear, RectifiedStereo, RemapPixel, Side, StereoRig,
};
use dhptam_core::geometry::triangulate::{
    triangulate, triangulate_rectified, Rejected, Triangulated,
};
use dhptam_core::geometry::{Pinhole, Se3};
use nalgebra::{Vector2, Vector3};
use numpy::ndarray::{Array1, Array2};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::arrays;
use crate::config::PyConfig;
use crate::errors::DetachGuarded;
use crate::errors::{input_error, IntoPyResult};
use crate::geometry::{mat_to_py, PyCamera, PySe3, PySo3};

pub(crate) fn parse_side(side: &str) -> PyResult<Side> {
    match side {
        "left" => Ok(Side::Left),
        "right" => Ok(Side::Right),
        other => Err(input_error(
            "side",
            "\"left\" or \"right\"",
            format!("{other:?}"),
        )),
    }
}

/// A calibrated stereo pair: two cameras and the transform from the left camera frame to the
/// right one.
#[pyclass(name = "StereoRig", module = "dhptam._core", frozen)]
#[derive(Clone, Copy)]
pub struct PyStereoRig {
    pub inner: StereoRig,
}

#[pymethods]
impl PyStereoRig {
    #[new]
    fn new(left: &PyCamera, right: &PyCamera, right_from_left: &PySe3) -> Self {
        Self {
            inner: StereoRig {
                left: left.inner,
                right: right.inner,
                right_from_left: right_from_left.inner,
            },
        }
    }

    /// The left camera.
    #[getter]
    fn left(&self) -> PyCamera {
        self.inner.left.into()
    }

    /// The right camera.
    #[getter]
    fn right(&self) -> PyCamera {
        self.inner.right.into()
    }

    /// Transform from the left camera frame to the right camera frame.
    #[getter]
    fn right_from_left(&self) -> PySe3 {
        self.inner.right_from_left.into()
    }

    fn __repr__(&self) -> String {
        format!(
            "StereoRig(left={}, right={}, baseline_m={:.4})",
            self.inner.left.model.name(),
            self.inner.right.model.name(),
            self.inner.right_from_left.translation.norm()
        )
    }
}

/// The rectified geometry of a stereo pair: one pinhole K for both images, rows aligned,
/// the right camera at `(baseline_m, 0, 0)` of the rectified left frame.
///
/// Remap tables are computed on first use and kept.
#[pyclass(name = "RectifiedStereo", module = "dhptam._core", frozen)]
pub struct PyRectifiedStereo {
    pub inner: RectifiedStereo,
    tables: [OnceLock<(Vec<f32>, Vec<f32>)>; 2],
}

impl PyRectifiedStereo {
    /// Rectifies an image of camera `side` whose shape the caller has checked.
    fn resample<'py, T: RemapPixel + numpy::Element + Default>(
        &self,
        py: Python<'py>,
        side: Side,
        image: &numpy::PyReadonlyArray2<'py, T>,
        expected: &str,
    ) -> PyResult<Py<PyAny>> {
        let camera = *self.inner.camera(side);
        let src = image
            .as_slice()
            .map_err(|_| input_error("image", "a C-contiguous array", "a strided view"))?;
        let (map_x, map_y) = self.tables(side);
        let shape = self.shape();
        let mut dst = vec![T::default(); shape.0 * shape.1];
        let (w, h) = (camera.width as usize, camera.height as usize);
        py.detach_guarded("stereo::resample", || {
            remap_bilinear(src, w, h, map_x, map_y, &mut dst)
        })?
        .py()?;
        let out =
            Array2::from_shape_vec(shape, dst).map_err(|e| input_error("image", expected, e))?;
        Ok(out.into_pyarray(py).into_any().unbind())
    }

    fn tables(&self, side: Side) -> &(Vec<f32>, Vec<f32>) {
        let index = usize::from(side == Side::Right);
        self.tables[index].get_or_init(|| self.inner.remap_tables(side))
    }

    fn shape(&self) -> (usize, usize) {
        (self.inner.height as usize, self.inner.width as usize)
    }

    fn map_pixels<'py>(
        &self,
        py: Python<'py>,
        pixels: &Bound<'py, PyAny>,
        f: impl Fn(&Vector2<f64>) -> Option<Vector2<f64>> + Send + Sync,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let pixels: PyReadonlyArray2<'py, f64> = arrays::rows(pixels, 2, "pixels")?;
        let n = pixels.shape()[0];
        let src = pixels.as_slice()?;
        let out = py.detach_guarded("stereo::map_pixels", || {
            let mut out = vec![f64::NAN; 2 * n];
            for (q, o) in src.chunks_exact(2).zip(out.chunks_exact_mut(2)) {
                if let Some(r) = f(&Vector2::new(q[0], q[1])) {
                    o[0] = r.x;
                    o[1] = r.y;
                }
            }
            out
        })?;
        Ok(Array2::from_shape_vec((n, 2), out)
            .map_err(|e| input_error("pixels", "(N, 2)", e))?
            .into_pyarray(py))
    }
}

#[pymethods]
impl PyRectifiedStereo {
    /// Rectifies `rig`; `config` supplies `[rectification]` (balance, output size).
    #[new]
    #[pyo3(signature = (rig, config=None))]
    fn new(py: Python<'_>, rig: &PyStereoRig, config: Option<&PyConfig>) -> PyResult<Self> {
        let settings = config
            .map(|c| c.inner.rectification.clone())
            .unwrap_or_default();
        let rig = rig.inner;
        let inner = py
            .detach_guarded("stereo::new", || RectifiedStereo::new(&rig, &settings))?
            .py()?;
        Ok(Self {
            inner,
            tables: [OnceLock::new(), OnceLock::new()],
        })
    }

    /// The shared 3×3 intrinsic matrix of the rectified images.
    #[getter(K)]
    fn k<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        mat_to_py(py, &self.inner.pinhole.k_matrix())
    }

    /// Rectified image width in pixels.
    #[getter]
    fn width(&self) -> u32 {
        self.inner.width
    }

    /// Rectified image height in pixels.
    #[getter]
    fn height(&self) -> u32 {
        self.inner.height
    }

    /// Distance between the camera centres, metres.
    #[getter]
    fn baseline_m(&self) -> f64 {
        self.inner.baseline_m
    }

    /// 3×4 projection matrix of the rectified left camera, K [I | 0].
    #[getter(P_left)]
    fn p_left<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        mat_to_py(py, &self.inner.projection_left())
    }

    /// 3×4 projection matrix of the rectified right camera, K [I | (−fx·b, 0, 0)ᵀ].
    #[getter(P_right)]
    fn p_right<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        mat_to_py(py, &self.inner.projection_right())
    }

    /// Rotation from the original left camera frame to the rectified left frame.
    #[getter]
    fn rect_left_from_left(&self) -> PySo3 {
        self.inner.rect_left_from_left.into()
    }

    /// Rotation from the original right camera frame to the rectified right frame.
    #[getter]
    fn rect_right_from_right(&self) -> PySo3 {
        self.inner.rect_right_from_right.into()
    }

    /// Original (distorted) pixels (N, 2) of camera `side` → rectified pixels; NaN where the
    /// model cannot invert a pixel.
    fn rectify_pixels<'py>(
        &self,
        py: Python<'py>,
        side: &str,
        pixels: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let side = parse_side(side)?;
        self.map_pixels(py, pixels, |uv| self.inner.rectify_pixel(side, uv))
    }

    /// Rectified pixels (N, 2) → original (distorted) pixels of camera `side`.
    fn unrectify_pixels<'py>(
        &self,
        py: Python<'py>,
        side: &str,
        pixels: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let side = parse_side(side)?;
        self.map_pixels(py, pixels, |uv| self.inner.unrectify_pixel(side, uv))
    }

    /// Projects points (N, 3) of the rectified left frame into both rectified images:
    /// returns `(uv_left, uv_right)`, NaN for points behind the cameras.
    fn project<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<f64>>)> {
        let points = arrays::rows(points, 3, "points")?;
        let view = points.as_array();
        let n = view.nrows();
        let mut left = Array2::from_elem((n, 2), f64::NAN);
        let mut right = Array2::from_elem((n, 2), f64::NAN);
        for (i, p) in view.outer_iter().enumerate() {
            let p = Vector3::new(p[0], p[1], p[2]);
            if let (Some(l), Some(r)) = (self.inner.project_left(&p), self.inner.project_right(&p))
            {
                left[[i, 0]] = l.x;
                left[[i, 1]] = l.y;
                right[[i, 0]] = r.x;
                right[[i, 1]] = r.y;
            }
        }
        Ok((left.into_pyarray(py), right.into_pyarray(py)))
    }

    /// `(map_x, map_y)`, float32 (height, width): for each rectified pixel, the source pixel
    /// of camera `side`; −1 where the camera cannot see that ray. Usable with `cv2.remap`.
    fn remap_tables<'py>(
        &self,
        py: Python<'py>,
        side: &str,
    ) -> PyResult<(Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<f32>>)> {
        let side = parse_side(side)?;
        let (map_x, map_y) =
            py.detach_guarded("stereo::remap_tables", || self.tables(side).clone())?;
        let shape = self.shape();
        let to_py = |v: Vec<f32>| Array2::from_shape_vec(shape, v).map(|a| a.into_pyarray(py));
        Ok((
            to_py(map_x).map_err(|e| input_error("remap table", "height × width", e))?,
            to_py(map_y).map_err(|e| input_error("remap table", "height × width", e))?,
        ))
    }

    /// Rectifies a single-channel image of camera `side` (uint8 or float32, shape
    /// (height, width) of that camera) by bilinear interpolation; pixels without a source are 0.
    fn rectify_image<'py>(
        &self,
        py: Python<'py>,
        side: &str,
        image: &Bound<'py, PyAny>,
    ) -> PyResult<Py<PyAny>> {
        let side = parse_side(side)?;
        let camera = *self.inner.camera(side);
        let (w, h) = (camera.width as usize, camera.height as usize);
        let expected = format!("a ({h}, {w}) uint8 or float32 image of the {side:?} camera");
        let check = |shape: &[usize]| {
            if shape == [h, w] {
                Ok(())
            } else {
                Err(input_error("image", &expected, format!("shape {shape:?}")))
            }
        };
        if let Ok(img) = image.extract::<numpy::PyReadonlyArray2<'py, u8>>() {
            check(img.shape())?;
            return self.resample(py, side, &img, &expected);
        }
        if let Ok(img) = image.extract::<numpy::PyReadonlyArray2<'py, f32>>() {
            check(img.shape())?;
            return self.resample(py, side, &img, &expected);
        }
        let shape = image
            .getattr("shape")
            .map(|s| s.to_string())
            .unwrap_or_default();
        let dtype = image
            .getattr("dtype")
            .map(|s| s.to_string())
            .unwrap_or_default();
        Err(input_error(
            "image",
            &expected,
            format!("shape {shape}, dtype {dtype}"),
        ))
    }

    /// Triangulates rectified correspondences: left pixels (N, 2) and right columns (N,)
    /// (same rows). Returns `(points (N, 3) in the rectified left frame, accepted (N,) bool,
    /// reasons: list of None or the rejection message)`; rejected points are NaN.
    #[pyo3(signature = (uv_left, u_right, config=None))]
    fn triangulate<'py>(
        &self,
        py: Python<'py>,
        uv_left: &Bound<'py, PyAny>,
        u_right: &Bound<'py, PyAny>,
        config: Option<&PyConfig>,
    ) -> PyResult<(
        Bound<'py, PyArray2<f64>>,
        Bound<'py, PyArray1<bool>>,
        Vec<Option<String>>,
    )> {
        let settings = triangulation_settings(config);
        let uv_left = arrays::rows(uv_left, 2, "uv_left")?;
        let u_right = arrays::values(u_right, "u_right")?;
        let n = uv_left.shape()[0];
        if u_right.shape()[0] != n {
            return Err(input_error(
                "u_right",
                &format!("{n} values (one per left pixel)"),
                u_right.shape()[0],
            ));
        }
        let (left, right) = (uv_left.as_slice()?, u_right.as_slice()?);
        let (pinhole, baseline) = (self.inner.pinhole, self.inner.baseline_m);
        let results: Vec<Result<Triangulated, Rejected>> =
            py.detach_guarded("stereo::triangulate", || {
                left.chunks_exact(2)
                    .zip(right)
                    .map(|(l, &r)| {
                        triangulate_rectified(
                            &pinhole,
                            baseline,
                            &Vector2::new(l[0], l[1]),
                            r,
                            &settings,
                        )
                    })
                    .collect()
            })?;
        Ok(collect_points(py, &results))
    }

    fn __repr__(&self) -> String {
        let p = self.inner.pinhole;
        format!(
            "RectifiedStereo(width={}, height={}, fx={:.3}, cx={:.3}, cy={:.3}, baseline_m={:.5})",
            self.inner.width, self.inner.height, p.fx, p.cx, p.cy, self.inner.baseline_m
        )
    }
}

fn triangulation_settings(config: Option<&PyConfig>) -> TriangulationConfig {
    config
        .map(|c| c.inner.triangulation.clone())
        .unwrap_or_default()
}

type PointsAccepted<'py> = (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<bool>>,
    Vec<Option<String>>,
);

fn collect_points<'py>(
    py: Python<'py>,
    results: &[Result<Triangulated, Rejected>],
) -> PointsAccepted<'py> {
    let mut points = Array2::from_elem((results.len(), 3), f64::NAN);
    let mut accepted = Array1::from_elem(results.len(), false);
    let mut reasons = Vec::with_capacity(results.len());
    for (i, r) in results.iter().enumerate() {
        match r {
            Ok(t) => {
                for k in 0..3 {
                    points[[i, k]] = t.point_world[k];
                }
                accepted[i] = true;
                reasons.push(None);
            }
            Err(why) => reasons.push(Some(why.to_string())),
        }
    }
    (points.into_pyarray(py), accepted.into_pyarray(py), reasons)
}

/// Triangulates one point seen by several rectified (pinhole) cameras.
///
/// `cams_from_world`: one SE3 per view; `pixels`: (V, 2); `intrinsics`: (fx, fy, cx, cy).
/// Returns `(point_world or None, parallax_deg, max_reprojection_px, rejection or None)`.
#[pyfunction]
#[pyo3(signature = (cams_from_world, pixels, intrinsics, config=None))]
pub fn _triangulate(
    cams_from_world: Vec<PyRef<'_, PySe3>>,
    pixels: &Bound<'_, PyAny>,
    intrinsics: &Bound<'_, PyAny>,
    config: Option<&PyConfig>,
) -> PyResult<(Option<[f64; 3]>, f64, f64, Option<String>)> {
    let [fx, fy, cx, cy] = arrays::vector::<4>(intrinsics, "intrinsics")?;
    let pinhole = Pinhole { fx, fy, cx, cy };
    let poses: Vec<Se3> = cams_from_world.iter().map(|p| p.inner).collect();
    let pixels = arrays::rows(pixels, 2, "pixels")?;
    let observations: Vec<Vector2<f64>> = pixels
        .as_array()
        .outer_iter()
        .map(|r| Vector2::new(r[0], r[1]))
        .collect();
    Ok(
        match triangulate(
            &poses,
            &observations,
            &pinhole,
            &triangulation_settings(config),
        ) {
            Ok(t) => (
                Some([t.point_world.x, t.point_world.y, t.point_world.z]),
                t.parallax_deg,
                t.max_reprojection_px,
                None,
            ),
            Err(why) => (None, f64::NAN, f64::NAN, Some(why.to_string())),
        },
    )
}
