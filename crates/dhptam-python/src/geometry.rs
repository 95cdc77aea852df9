//! Python classes for the geometry core: `SO3`, `SE3`, `Camera`.

use dhptam_core::geometry::{Camera, Projective, Se3, So3};
use nalgebra::{SMatrix, SVector, Vector3, Vector6};
use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayMethods, PyReadonlyArray2,
    PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use crate::arrays;
use crate::errors::DetachGuarded;
use crate::errors::{input_error, IntoPyResult};

/// Pixels (N, 2) with their projection Jacobians (N, 2, 3).
type PixelsAndJacobians<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray3<f64>>);

pub(crate) fn vec3_to_py<'py>(py: Python<'py>, v: &Vector3<f64>) -> Bound<'py, PyArray1<f64>> {
    Array1::from_vec(v.as_slice().to_vec()).into_pyarray(py)
}

pub(crate) fn mat_to_py<'py, const R: usize, const C: usize>(
    py: Python<'py>,
    m: &nalgebra::SMatrix<f64, R, C>,
) -> Bound<'py, PyArray2<f64>> {
    Array2::from_shape_fn((R, C), |(r, c)| m[(r, c)]).into_pyarray(py)
}

/// Evaluates one of a Lie group's N×N Jacobians at the tangent vector `obj` (called `name` in
/// errors).
fn tangent_jacobian<'py, const N: usize>(
    py: Python<'py>,
    obj: &Bound<'py, PyAny>,
    name: &str,
    jacobian: fn(&SVector<f64, N>) -> SMatrix<f64, N, N>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let v = SVector::<f64, N>::from(arrays::vector::<N>(obj, name)?);
    Ok(mat_to_py(py, &jacobian(&v)))
}

/// Applies `f` to every row of an (N, 3) array with the GIL released, returning an (N, 3) array.
fn map_points<'py>(
    py: Python<'py>,
    points: &PyReadonlyArray2<'py, f64>,
    f: impl Fn(Vector3<f64>) -> Vector3<f64> + Send + Sync,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let n = points.shape()[0];
    let src = points.as_slice()?;
    let out = py.detach_guarded("geometry::map_points", || {
        use rayon::prelude::*;
        let mut out = vec![0.0; src.len()];
        out.par_chunks_mut(3 * 4096)
            .zip(src.par_chunks(3 * 4096))
            .for_each(|(dst, src)| {
                for (d, s) in dst.chunks_exact_mut(3).zip(src.chunks_exact(3)) {
                    d.copy_from_slice(f(Vector3::new(s[0], s[1], s[2])).as_slice());
                }
            });
        out
    })?;
    Ok(Array2::from_shape_vec((n, 3), out)
        .map_err(|e| input_error("points", "(N, 3)", e))?
        .into_pyarray(py))
}

/// `f` applied to a Python argument holding points: an (N, 3) array gives an (N, 3) array,
/// one 3-vector (1-D array or sequence of 3 numbers) gives a 3-vector.
fn map_point_arg(
    py: Python<'_>,
    arg: &Bound<'_, PyAny>,
    f: impl Fn(Vector3<f64>) -> Vector3<f64> + Send + Sync,
) -> PyResult<Py<PyAny>> {
    let single = arg
        .getattr("ndim")
        .and_then(|d| d.extract::<usize>())
        .map(|d| d == 1)
        .unwrap_or(false)
        || arg.extract::<Vec<f64>>().is_ok();
    let points = arrays::rows(arg, 3, "points")?;
    let out = map_points(py, &points, f)?;
    Ok(if single {
        out.reshape([3])?.into_any().unbind()
    } else {
        out.into_any().unbind()
    })
}

/// A 3-D rotation (unit quaternion inside).
///
/// Quaternions enter and leave in (x, y, z, w) order, Hamilton convention.
#[pyclass(name = "SO3", module = "dhptam._core", frozen)]
#[derive(Clone, Copy)]
pub struct PySo3 {
    pub inner: So3,
}

impl From<So3> for PySo3 {
    fn from(inner: So3) -> Self {
        Self { inner }
    }
}

#[pymethods]
impl PySo3 {
    /// The identity rotation.
    #[new]
    fn new() -> Self {
        So3::identity().into()
    }

    /// Rotation from a rotation vector (axis × angle in radians).
    #[staticmethod]
    fn exp(phi: &Bound<'_, PyAny>) -> PyResult<Self> {
        Ok(So3::exp(&Vector3::from(arrays::vector::<3>(phi, "phi")?)).into())
    }

    /// Rotation from a quaternion in (x, y, z, w) order; it is normalised.
    #[staticmethod]
    fn from_quat_xyzw(q: &Bound<'_, PyAny>) -> PyResult<Self> {
        Ok(
            So3::from_quaternion_xyzw(arrays::vector::<4>(q, "quat_xyzw")?)
                .py()?
                .into(),
        )
    }

    /// Rotation from an orthonormal 3×3 matrix with determinant +1.
    #[staticmethod]
    fn from_matrix(m: &Bound<'_, PyAny>) -> PyResult<Self> {
        Ok(So3::from_matrix(&arrays::matrix::<3, 3>(m, "matrix")?)
            .py()?
            .into())
    }

    /// The rotation vector, angle in [0, π].
    fn log<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        vec3_to_py(py, &self.inner.log())
    }

    /// The quaternion in (x, y, z, w) order with w ≥ 0.
    fn quat_xyzw<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        Array1::from_vec(self.inner.to_quaternion_xyzw().to_vec()).into_pyarray(py)
    }

    /// The 3×3 rotation matrix.
    fn matrix<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        mat_to_py(py, &self.inner.matrix())
    }

    /// The inverse rotation.
    fn inverse(&self) -> Self {
        self.inner.inverse().into()
    }

    /// The adjoint matrix (equal to the rotation matrix for SO(3)).
    fn adjoint<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        mat_to_py(py, &self.inner.adjoint())
    }

    /// Rotation angle in radians.
    fn angle(&self) -> f64 {
        self.inner.angle()
    }

    /// Geodesic interpolation; `s = 0` gives self, `s = 1` gives `other`.
    fn interpolate(&self, other: &PySo3, s: f64) -> Self {
        self.inner.interpolate(&other.inner, s).into()
    }

    /// Left Jacobian J_l(φ).
    #[staticmethod]
    fn left_jacobian<'py>(
        py: Python<'py>,
        phi: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        tangent_jacobian(py, phi, "phi", So3::left_jacobian)
    }

    /// Right Jacobian J_r(φ) = J_l(−φ).
    #[staticmethod]
    fn right_jacobian<'py>(
        py: Python<'py>,
        phi: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        tangent_jacobian(py, phi, "phi", So3::right_jacobian)
    }

    /// Inverse of the left Jacobian.
    #[staticmethod]
    fn left_jacobian_inverse<'py>(
        py: Python<'py>,
        phi: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        tangent_jacobian(py, phi, "phi", So3::left_jacobian_inverse)
    }

    /// Inverse of the right Jacobian.
    #[staticmethod]
    fn right_jacobian_inverse<'py>(
        py: Python<'py>,
        phi: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        tangent_jacobian(py, phi, "phi", So3::right_jacobian_inverse)
    }

    /// `R1 @ R2` composes; `R @ points` rotates an (N, 3) array (or one 3-vector).
    fn __matmul__<'py>(&self, py: Python<'py>, rhs: &Bound<'py, PyAny>) -> PyResult<Py<PyAny>> {
        if let Ok(other) = rhs.extract::<PyRef<'_, PySo3>>() {
            return Ok(Py::new(py, PySo3::from(self.inner * other.inner))?.into_any());
        }
        let r = self.inner;
        map_point_arg(py, rhs, move |p| r * p)
    }

    fn __repr__(&self) -> String {
        let [x, y, z, w] = self.inner.to_quaternion_xyzw();
        format!("SO3(quat_xyzw=[{x:.6}, {y:.6}, {z:.6}, {w:.6}])")
    }
}

/// A rigid-body transform `p ↦ R p + t`; name instances by the frames they map,
/// e.g. `world_from_cam @ p_cam = p_world`.
///
/// Tangent vectors are ξ = [ρ, φ] (translation part first).
#[pyclass(name = "SE3", module = "dhptam._core", frozen)]
#[derive(Clone, Copy)]
pub struct PySe3 {
    pub inner: Se3,
}

impl From<Se3> for PySe3 {
    fn from(inner: Se3) -> Self {
        Self { inner }
    }
}

#[pymethods]
impl PySe3 {
    /// A transform from a rotation (default identity) and a translation (default zero).
    #[new]
    #[pyo3(signature = (rotation=None, translation=None))]
    fn new(rotation: Option<&PySo3>, translation: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        let t = match translation {
            Some(t) => Vector3::from(arrays::vector::<3>(t, "translation")?),
            None => Vector3::zeros(),
        };
        dhptam_core::error::ensure_finite("translation", t.as_slice()).py()?;
        Ok(Se3::new(rotation.map(|r| r.inner).unwrap_or_default(), t).into())
    }

    /// Exponential map of ξ = [ρ, φ].
    #[staticmethod]
    fn exp(xi: &Bound<'_, PyAny>) -> PyResult<Self> {
        Ok(Se3::exp(&Vector6::from(arrays::vector::<6>(xi, "xi")?)).into())
    }

    /// From a 4×4 homogeneous matrix.
    #[staticmethod]
    fn from_matrix(m: &Bound<'_, PyAny>) -> PyResult<Self> {
        Ok(Se3::from_matrix(&arrays::matrix::<4, 4>(m, "matrix")?)
            .py()?
            .into())
    }

    /// From a translation (x, y, z) and a quaternion in (x, y, z, w) order: the TUM line layout.
    #[staticmethod]
    fn from_translation_quat_xyzw(
        translation: &Bound<'_, PyAny>,
        quat_xyzw: &Bound<'_, PyAny>,
    ) -> PyResult<Self> {
        let t = arrays::vector::<3>(translation, "translation")?;
        let q = arrays::vector::<4>(quat_xyzw, "quat_xyzw")?;
        Ok(Se3::from_translation_quaternion_xyzw(t, q).py()?.into())
    }

    /// The logarithm ξ = [ρ, φ].
    fn log<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        Array1::from_vec(self.inner.log().as_slice().to_vec()).into_pyarray(py)
    }

    /// The 4×4 homogeneous matrix.
    fn matrix<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        mat_to_py(py, &self.inner.matrix())
    }

    /// The rotation part.
    #[getter]
    fn rotation(&self) -> PySo3 {
        self.inner.rotation.into()
    }

    /// The translation part.
    #[getter]
    fn translation<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        vec3_to_py(py, &self.inner.translation)
    }

    /// The inverse transform (`a_from_b.inverse()` is `b_from_a`).
    fn inverse(&self) -> Self {
        self.inner.inverse().into()
    }

    /// The 6×6 adjoint.
    fn adjoint<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        mat_to_py(py, &self.inner.adjoint())
    }

    /// Geodesic interpolation; `s = 0` gives self, `s = 1` gives `other`.
    fn interpolate(&self, other: &PySe3, s: f64) -> Self {
        self.inner.interpolate(&other.inner, s).into()
    }

    /// Left Jacobian J_l(ξ) (6×6).
    #[staticmethod]
    fn left_jacobian<'py>(
        py: Python<'py>,
        xi: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        tangent_jacobian(py, xi, "xi", Se3::left_jacobian)
    }

    /// Right Jacobian J_r(ξ) = J_l(−ξ).
    #[staticmethod]
    fn right_jacobian<'py>(
        py: Python<'py>,
        xi: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        tangent_jacobian(py, xi, "xi", Se3::right_jacobian)
    }

    /// Inverse of the left Jacobian.
    #[staticmethod]
    fn left_jacobian_inverse<'py>(
        py: Python<'py>,
        xi: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        tangent_jacobian(py, xi, "xi", Se3::left_jacobian_inverse)
    }

    /// Inverse of the right Jacobian.
    #[staticmethod]
    fn right_jacobian_inverse<'py>(
        py: Python<'py>,
        xi: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        tangent_jacobian(py, xi, "xi", Se3::right_jacobian_inverse)
    }

    /// `a_from_b @ b_from_c` composes; `a_from_b @ points_b` transforms an (N, 3) array (or one
    /// 3-vector), reading a float64 C-contiguous input in place and releasing the GIL.
    fn __matmul__<'py>(&self, py: Python<'py>, rhs: &Bound<'py, PyAny>) -> PyResult<Py<PyAny>> {
        if let Ok(other) = rhs.extract::<PyRef<'_, PySe3>>() {
            return Ok(Py::new(py, PySe3::from(self.inner * other.inner))?.into_any());
        }
        let t = self.inner;
        map_point_arg(py, rhs, move |p| t.transform_point(&p))
    }

    fn __repr__(&self) -> String {
        let t = self.inner.translation;
        let [x, y, z, w] = self.inner.rotation.to_quaternion_xyzw();
        format!(
            "SE3(translation=[{:.6}, {:.6}, {:.6}], quat_xyzw=[{x:.6}, {y:.6}, {z:.6}, {w:.6}])",
            t.x, t.y, t.z
        )
    }
}

/// A camera: model (`"pinhole"`, `"radtan"`, `"kb4"`), parameters in OpenCV order and image size.
///
/// radtan: `[fx, fy, cx, cy, k1, k2, p1, p2(, k3)]`; kb4: `[fx, fy, cx, cy, k1, k2, k3, k4]`.
#[pyclass(name = "Camera", module = "dhptam._core", frozen)]
#[derive(Clone, Copy)]
pub struct PyCamera {
    pub inner: Camera,
}

impl From<Camera> for PyCamera {
    fn from(inner: Camera) -> Self {
        Self { inner }
    }
}

#[pymethods]
impl PyCamera {
    #[new]
    fn new(model: &str, params: Vec<f64>, width: u32, height: u32) -> PyResult<Self> {
        Ok(Camera::new(model, &params, width, height).py()?.into())
    }

    /// The model name: `pinhole`, `radtan` or `kb4`.
    #[getter]
    fn model(&self) -> &'static str {
        self.inner.model.name()
    }

    /// The parameters in OpenCV order.
    #[getter]
    fn params(&self) -> Vec<f64> {
        self.inner.model.params()
    }

    /// Image width in pixels.
    #[getter]
    fn width(&self) -> u32 {
        self.inner.width
    }

    /// Image height in pixels.
    #[getter]
    fn height(&self) -> u32 {
        self.inner.height
    }

    /// The 3×3 calibration matrix of the model's linear part.
    #[getter(K)]
    fn k<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        mat_to_py(py, &self.inner.model.pinhole().k_matrix())
    }

    /// Projects an (N, 3) array of points in the camera frame to (N, 2) pixels; rows the model
    /// cannot image are NaN. A float64 C-contiguous input is read in place; the GIL is released.
    fn project<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let points = arrays::rows(points, 3, "points")?;
        let n = points.shape()[0];
        let src = points.as_slice()?;
        let camera = self.inner;
        let out = py.detach_guarded("geometry::project", || {
            let mut uv = vec![0.0; 2 * n];
            camera.project_points(src, &mut uv).map(|()| uv)
        })?;
        Ok(Array2::from_shape_vec((n, 2), out.py()?)
            .map_err(|e| input_error("points", "(N, 3)", e))?
            .into_pyarray(py))
    }

    /// Unprojects an (N, 2) array of pixels to (N, 3) unit bearing vectors; NaN rows where the
    /// model cannot invert the pixel. The GIL is released.
    fn unproject<'py>(
        &self,
        py: Python<'py>,
        pixels: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let pixels = arrays::rows(pixels, 2, "pixels")?;
        let n = pixels.shape()[0];
        let src = pixels.as_slice()?;
        let camera = self.inner;
        let out = py.detach_guarded("geometry::unproject", || {
            let mut xyz = vec![0.0; 3 * n];
            camera.unproject_points(src, &mut xyz).map(|()| xyz)
        })?;
        Ok(Array2::from_shape_vec((n, 3), out.py()?)
            .map_err(|e| input_error("pixels", "(N, 2)", e))?
            .into_pyarray(py))
    }

    /// Pixels (N, 2) and Jacobians ∂(u, v)/∂(x, y, z) (N, 2, 3); NaN where not imageable.
    fn project_with_jacobian<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<PixelsAndJacobians<'py>> {
        let points = arrays::rows(points, 3, "points")?;
        let view = points.as_array();
        let n = view.nrows();
        let mut uv = Array2::from_elem((n, 2), f64::NAN);
        let mut jac = Array3::from_elem((n, 2, 3), f64::NAN);
        for (i, row) in view.outer_iter().enumerate() {
            if let Some((pixel, j)) = self
                .inner
                .project_with_jacobian(&Vector3::new(row[0], row[1], row[2]))
            {
                uv[[i, 0]] = pixel.x;
                uv[[i, 1]] = pixel.y;
                for r in 0..2 {
                    for c in 0..3 {
                        jac[[i, r, c]] = j[(r, c)];
                    }
                }
            }
        }
        Ok((uv.into_pyarray(py), jac.into_pyarray(py)))
    }

    /// Whether each pixel of an (N, 2) array lies inside the image.
    fn contains<'py>(
        &self,
        py: Python<'py>,
        pixels: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<bool>>> {
        let pixels = arrays::rows(pixels, 2, "pixels")?;
        let inside: Vec<bool> = pixels
            .as_array()
            .outer_iter()
            .map(|r| self.inner.contains(&nalgebra::Vector2::new(r[0], r[1])))
            .collect();
        Ok(Array1::from_vec(inside).into_pyarray(py))
    }

    fn __repr__(&self) -> String {
        format!(
            "Camera(model={:?}, params={:?}, width={}, height={})",
            self.inner.model.name(),
            self.inner.model.params(),
            self.inner.width,
            self.inner.height
        )
    }
}

/// The address of the first element of a float64 C-contiguous array as the binding reads it;
/// used by tests to prove that inputs are read in place, without a copy.
#[pyfunction]
pub fn _data_address(array: &Bound<'_, PyAny>) -> PyResult<usize> {
    let cols = array
        .getattr("shape")?
        .extract::<Vec<usize>>()?
        .get(1)
        .copied()
        .unwrap_or(1);
    let rows = arrays::rows(array, cols, "array")?;
    Ok(rows.as_slice()?.as_ptr() as usize)
}
