//! Descriptor matching, and the one place where descriptor arrays are read from numpy.
//!
//! Descriptors arrive as C-contiguous (N, D) float32 or (N, B) uint8 arrays and are borrowed
//! in place: `dhptam.features` produces them that way, so nothing is copied on the way in.

use dhptam_core::matching::{self, Descriptors, MatchOptions};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::errors::DetachGuarded;
use crate::errors::{input_error, IntoPyResult};

/// A descriptor array borrowed from Python: float32 or uint8 rows.
pub enum DescriptorArray<'py> {
    /// (N, D) float32.
    Float(PyReadonlyArray2<'py, f32>),
    /// (N, B) uint8, packed bits.
    Binary(PyReadonlyArray2<'py, u8>),
}

impl<'py> DescriptorArray<'py> {
    /// Reads `obj` in place; anything but a C-contiguous 2-D float32/uint8 array is refused with
    /// the argument named (a silent conversion would hide a copy the caller did not expect).
    pub fn extract(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<Self> {
        let expected = "a C-contiguous (N, D) float32 or (N, B) uint8 array";
        let array = if let Ok(a) = obj.extract::<PyReadonlyArray2<'py, f32>>() {
            (a.is_c_contiguous(), DescriptorArray::Float(a))
        } else if let Ok(a) = obj.extract::<PyReadonlyArray2<'py, u8>>() {
            (a.is_c_contiguous(), DescriptorArray::Binary(a))
        } else {
            let got = match (obj.getattr("dtype"), obj.getattr("shape")) {
                (Ok(d), Ok(s)) => format!("dtype {d}, shape {s}"),
                _ => obj
                    .get_type()
                    .name()
                    .map(|n| n.to_string())
                    .unwrap_or_default(),
            };
            return Err(input_error(name, expected, got));
        };
        match array {
            (true, a) => Ok(a),
            (false, _) => Err(input_error(name, expected, "a non-contiguous view")),
        }
    }

    /// The rows as the core sees them (no copy).
    pub fn view(&self) -> PyResult<Descriptors<'_>> {
        let strided = |_| input_error("descriptors", "a C-contiguous array", "a strided view");
        match self {
            DescriptorArray::Float(a) => {
                Descriptors::float(a.as_slice().map_err(strided)?, a.shape()[1].max(1)).py()
            }
            DescriptorArray::Binary(a) => {
                Descriptors::binary(a.as_slice().map_err(strided)?, a.shape()[1].max(1)).py()
            }
        }
    }

    /// Address of the first element (for zero-copy checks).
    pub fn address(&self) -> usize {
        match self {
            DescriptorArray::Float(a) => a.as_array().as_ptr() as usize,
            DescriptorArray::Binary(a) => a.as_array().as_ptr() as usize,
        }
    }
}

/// Mutual-nearest-neighbour matching with a ratio test; returns (pairs (M, 2) int64 of
/// (query row, train row), distances (M,) float32).
#[pyfunction]
#[pyo3(signature = (query, train, max_distance, ratio=0.9, mutual=true))]
pub fn match_descriptors<'py>(
    py: Python<'py>,
    query: &Bound<'py, PyAny>,
    train: &Bound<'py, PyAny>,
    max_distance: f32,
    ratio: f32,
    mutual: bool,
) -> PyResult<(Bound<'py, PyArray2<i64>>, Bound<'py, PyArray1<f32>>)> {
    let q = DescriptorArray::extract(query, "query")?;
    let t = DescriptorArray::extract(train, "train")?;
    let (qv, tv) = (q.view()?, t.view()?);
    let options = MatchOptions {
        max_distance,
        ratio,
        mutual,
    };
    let matches = py
        .detach_guarded("matching::match_descriptors", || {
            matching::match_descriptors(qv, tv, &options)
        })?
        .py()?;
    let mut pairs = Array2::<i64>::zeros((matches.len(), 2));
    for (row, m) in pairs.outer_iter_mut().zip(&matches) {
        let mut row = row;
        row[0] = i64::from(m.query);
        row[1] = i64::from(m.train);
    }
    let distances: Vec<f32> = matches.iter().map(|m| m.distance).collect();
    Ok((pairs.into_pyarray(py), distances.into_pyarray(py)))
}

/// Address of the first element of a feature array as the binding reads it: uint8 (N, B)
/// descriptors through [`DescriptorArray`], float32 (N, k) keypoints/descriptors and (N,)
/// scores through `arrays::rows_f32` / `arrays::values_f32` (which convert anything else once,
/// so a different address means a copy was made). Used by the zero-copy tests of
/// `dhptam.features`.
#[pyfunction]
pub fn _buffer_address(array: &Bound<'_, PyAny>) -> PyResult<usize> {
    let ndim: usize = array.getattr("ndim")?.extract()?;
    if ndim == 1 {
        let values = crate::arrays::values_f32(array, "array")?;
        return Ok(values.as_array().as_ptr() as usize);
    }
    if let Ok(binary) = array.extract::<PyReadonlyArray2<'_, u8>>() {
        if binary.is_c_contiguous() {
            return Ok(DescriptorArray::Binary(binary).address());
        }
    }
    let cols = array
        .getattr("shape")?
        .extract::<Vec<usize>>()?
        .get(1)
        .copied()
        .unwrap_or(1);
    let rows = crate::arrays::rows_f32(array, cols, "array")?;
    Ok(rows.as_array().as_ptr() as usize)
}
