//! Reading numpy arrays in place.
//!
//! A C-contiguous float64 array is read where it lies (no copy); anything else that numpy can
//! turn into one (lists, float32, Fortran order, strided views) is converted once by
//! `numpy.ascontiguousarray` and the converted copy is read. Shapes are checked here, with
//! errors that name the argument and the expected shape.

use numpy::{PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::input_error;

fn ascontiguous<'py>(obj: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
    let py = obj.py();
    let kwargs = PyDict::new(py);
    kwargs.set_item("dtype", "float64")?;
    py.import("numpy")?
        .getattr("ascontiguousarray")?
        .call((obj,), Some(&kwargs))
}

/// An (N, cols) float64 array, read in place when it already is one.
pub fn rows<'py>(
    obj: &Bound<'py, PyAny>,
    cols: usize,
    name: &str,
) -> PyResult<PyReadonlyArray2<'py, f64>> {
    let array = match obj.extract::<PyReadonlyArray2<'py, f64>>() {
        Ok(a) if a.is_c_contiguous() => a,
        _ => {
            let converted = ascontiguous(obj)
                .map_err(|e| input_error(name, &format!("an (N, {cols}) array of numbers"), e))?;
            if converted.getattr("ndim")?.extract::<usize>()? == 1 && cols > 0 {
                let len: usize = converted.getattr("size")?.extract()?;
                if len == cols {
                    // A single point given as a flat vector: treat it as one row.
                    return converted
                        .call_method1("reshape", (1, cols))?
                        .extract()
                        .map_err(Into::into);
                }
            }
            converted
                .extract::<PyReadonlyArray2<'py, f64>>()
                .map_err(|_| {
                    input_error(name, &format!("an (N, {cols}) array"), shape_of(&converted))
                })?
        }
    };
    if array.shape()[1] != cols {
        return Err(input_error(
            name,
            &format!("an (N, {cols}) array"),
            format!("shape {:?}", array.shape()),
        ));
    }
    Ok(array)
}

/// A float64 vector of any length, read in place when it already is a contiguous one.
pub fn values<'py>(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<PyReadonlyArray1<'py, f64>> {
    if let Ok(a) = obj.extract::<PyReadonlyArray1<'py, f64>>() {
        if a.is_c_contiguous() {
            return Ok(a);
        }
    }
    ascontiguous(obj)
        .and_then(|c| c.extract().map_err(Into::into))
        .map_err(|_| input_error(name, "a 1-D array of numbers", shape_of(obj)))
}

/// A float64 vector of exactly `N` numbers.
pub fn vector<const N: usize>(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<[f64; N]> {
    let converted = match obj.extract::<PyReadonlyArray1<'_, f64>>() {
        Ok(a) => a,
        Err(_) => ascontiguous(obj)
            .and_then(|c| c.call_method1("reshape", (-1,)))
            .and_then(|c| c.extract().map_err(Into::into))
            .map_err(|_| input_error(name, &format!("a vector of {N} numbers"), shape_of(obj)))?,
    };
    let view = converted.as_array();
    if view.len() != N {
        return Err(input_error(
            name,
            &format!("a vector of {N} numbers"),
            format!("{} numbers", view.len()),
        ));
    }
    let mut out = [0.0; N];
    for (o, v) in out.iter_mut().zip(view.iter()) {
        *o = *v;
    }
    Ok(out)
}

/// A float64 (R, C) matrix.
pub fn matrix<const R: usize, const C: usize>(
    obj: &Bound<'_, PyAny>,
    name: &str,
) -> PyResult<nalgebra::SMatrix<f64, R, C>> {
    let array = ascontiguous(obj)
        .map_err(|_| input_error(name, &format!("a {R}×{C} matrix"), shape_of(obj)))?;
    let array: PyReadonlyArray2<'_, f64> = array
        .extract()
        .map_err(|_| input_error(name, &format!("a {R}×{C} matrix"), shape_of(obj)))?;
    if array.shape() != [R, C] {
        return Err(input_error(
            name,
            &format!("a {R}×{C} matrix"),
            format!("shape {:?}", array.shape()),
        ));
    }
    let view = array.as_array();
    Ok(nalgebra::SMatrix::<f64, R, C>::from_fn(|r, c| view[[r, c]]))
}

fn shape_of(obj: &Bound<'_, PyAny>) -> String {
    match obj.getattr("shape") {
        Ok(shape) => format!("shape {shape}"),
        Err(_) => obj
            .get_type()
            .name()
            .map(|n| n.to_string())
            .unwrap_or_default(),
    }
}

// --- float32 arrays from dhptam.features (keypoints (N, 2), scores (N,)) ---------------------

fn ascontiguous_f32<'py>(obj: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
    let py = obj.py();
    let kwargs = PyDict::new(py);
    kwargs.set_item("dtype", "float32")?;
    py.import("numpy")?
        .getattr("ascontiguousarray")?
        .call((obj,), Some(&kwargs))
}

/// An (N, cols) float32 array, read in place when it already is a C-contiguous one (as
/// `dhptam.features` produces keypoints); anything else numpy can convert is converted once.
pub fn rows_f32<'py>(
    obj: &Bound<'py, PyAny>,
    cols: usize,
    name: &str,
) -> PyResult<PyReadonlyArray2<'py, f32>> {
    let expected = format!("an (N, {cols}) float32 array");
    let array = match obj.extract::<PyReadonlyArray2<'py, f32>>() {
        Ok(a) if a.is_c_contiguous() => a,
        _ => ascontiguous_f32(obj)
            .and_then(|c| c.extract().map_err(Into::into))
            .map_err(|_| input_error(name, &expected, shape_of(obj)))?,
    };
    if array.shape()[1] != cols {
        return Err(input_error(
            name,
            &expected,
            format!("shape {:?}", array.shape()),
        ));
    }
    Ok(array)
}

/// A float32 vector, read in place when it already is a contiguous one (as `dhptam.features`
/// produces scores); anything else numpy can convert is converted once.
pub fn values_f32<'py>(
    obj: &Bound<'py, PyAny>,
    name: &str,
) -> PyResult<PyReadonlyArray1<'py, f32>> {
    if let Ok(a) = obj.extract::<PyReadonlyArray1<'py, f32>>() {
        if a.is_c_contiguous() {
            return Ok(a);
        }
    }
    ascontiguous_f32(obj)
        .and_then(|c| c.extract().map_err(Into::into))
        .map_err(|_| input_error(name, "a 1-D float32 array", shape_of(obj)))
}

/// A short description of a Python object for error messages: dtype and shape of an array,
/// else its type name.
pub fn describe(obj: &Bound<'_, PyAny>) -> String {
    match (obj.getattr("dtype"), obj.getattr("shape")) {
        (Ok(d), Ok(s)) => format!("dtype {d}, shape {s}"),
        _ => obj
            .get_type()
            .name()
            .map(|n| n.to_string())
            .unwrap_or_default(),
    }
}
