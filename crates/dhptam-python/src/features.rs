//! CPU kernels of the learned feature extractors (`dhptam.features`).

use dhptam_core::features::{r2d2_heads, FeatureMap, HeadWeights};
use numpy::ndarray::Array3;
use numpy::{
    IntoPyArray, PyArray3, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray4,
    PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use crate::errors::DetachGuarded;
use crate::errors::{input_error, IntoPyResult};

/// R2D2's `(reliability, repeatability)`, each `(B, H·upsample, W·upsample)` float32, from the
/// network's channels-last map `(B, H, W, C)` before its final upsampling (float32, or int16
/// holding bfloat16 bit patterns), the heads' `(3, C)` weights (`clf` rows, then `sal`) and
/// `(3,)` biases. Reads the map in place, GIL released.
#[pyfunction]
pub fn _r2d2_heads<'py>(
    py: Python<'py>,
    features: &Bound<'py, PyAny>,
    weights: PyReadonlyArray2<'py, f32>,
    bias: PyReadonlyArray1<'py, f32>,
    upsample: usize,
) -> PyResult<(Bound<'py, PyArray3<f32>>, Bound<'py, PyArray3<f32>>)> {
    let expected = "a C-contiguous (B, H, W, C) float32 or int16 (bfloat16 bits) array";
    let f32_map = features.extract::<PyReadonlyArray4<'py, f32>>().ok();
    let bf16_map = features.extract::<PyReadonlyArray4<'py, i16>>().ok();
    let (s, x) = match (&f32_map, &bf16_map) {
        (Some(a), _) => (a.shape(), a.as_slice().map(FeatureMap::F32)),
        (None, Some(a)) => (
            a.shape(),
            // SAFETY: i16 and u16 have the same size and alignment; only the bits are read.
            a.as_slice().map(|v| {
                FeatureMap::Bf16(unsafe { std::slice::from_raw_parts(v.as_ptr().cast(), v.len()) })
            }),
        ),
        (None, None) => {
            return Err(input_error("features", expected, "another array type"));
        }
    };
    let shape = [s[0], s[1], s[2], s[3]];
    let x = x.map_err(|_| input_error("features", expected, "a strided view"))?;
    let w = weights.as_slice().map_err(|_| {
        input_error(
            "weights",
            "a C-contiguous (3, C) float32 array",
            "a strided view",
        )
    })?;
    let b: [f32; 3] = bias
        .as_slice()
        .ok()
        .and_then(|b| b.try_into().ok())
        .ok_or_else(|| {
            input_error(
                "bias",
                "3 float32 values",
                format!("shape {:?}", bias.shape()),
            )
        })?;
    let maps = py
        .detach_guarded("features::_r2d2_heads", || {
            r2d2_heads(
                x,
                shape,
                upsample,
                &HeadWeights {
                    weights: w,
                    bias: b,
                },
            )
        })?
        .py()?;
    let dims = (shape[0], maps.height, maps.width);
    let as_array = |v: Vec<f32>| {
        Array3::from_shape_vec(dims, v)
            .map(|a| a.into_pyarray(py))
            .map_err(|e| input_error("features", "a consistent size", e))
    };
    Ok((as_array(maps.reliability)?, as_array(maps.repeatability)?))
}
