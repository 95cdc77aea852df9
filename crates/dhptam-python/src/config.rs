//! `Config`: the typed configuration, loaded and printed from Python.

use std::path::PathBuf;

use dhptam_core::config::Config;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::errors::IntoPyResult;

/// The whole dhptam configuration (one table per stage). Unknown keys and out-of-range values
/// raise `ConfigError` naming the key.
#[pyclass(name = "Config", module = "dhptam._core", frozen)]
#[derive(Clone)]
pub struct PyConfig {
    pub inner: Config,
}

#[pymethods]
impl PyConfig {
    /// The defaults.
    #[new]
    fn new() -> Self {
        Self {
            inner: Config::default(),
        }
    }

    /// Parses TOML text; keys left out keep their defaults.
    #[staticmethod]
    #[pyo3(signature = (text, source_name="<string>"))]
    fn from_toml(text: &str, source_name: &str) -> PyResult<Self> {
        Ok(Self {
            inner: Config::from_toml_str(text, source_name).py()?,
        })
    }

    /// Reads a TOML file.
    #[staticmethod]
    fn from_file(path: PathBuf) -> PyResult<Self> {
        Ok(Self {
            inner: Config::from_file(&path).py()?,
        })
    }

    /// The default configuration as documented TOML.
    #[staticmethod]
    fn defaults_toml() -> String {
        Config::defaults_toml()
    }

    /// This configuration as plain TOML.
    fn to_toml(&self) -> String {
        self.inner.to_toml()
    }

    /// This configuration as documented TOML.
    fn to_commented_toml(&self) -> String {
        self.inner.to_commented_toml()
    }

    /// This configuration as nested dictionaries.
    fn to_dict<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let value = toml::Value::try_from(&self.inner).map_err(|e| {
            pyo3::exceptions::PyRuntimeError::new_err(format!("config serialisation: {e}"))
        })?;
        to_python(py, &value)
    }

    fn __eq__(&self, other: &PyConfig) -> bool {
        self.inner == other.inner
    }

    fn __repr__(&self) -> String {
        format!("Config({:?})", self.inner)
    }
}

fn to_python<'py>(py: Python<'py>, value: &toml::Value) -> PyResult<Bound<'py, PyAny>> {
    Ok(match value {
        toml::Value::String(s) => s.into_pyobject(py)?.into_any(),
        toml::Value::Integer(i) => i.into_pyobject(py)?.into_any(),
        toml::Value::Float(f) => f.into_pyobject(py)?.into_any(),
        toml::Value::Boolean(b) => b.into_pyobject(py)?.to_owned().into_any(),
        toml::Value::Datetime(d) => d.to_string().into_pyobject(py)?.into_any(),
        toml::Value::Array(items) => {
            let list = PyList::empty(py);
            for item in items {
                list.append(to_python(py, item)?)?;
            }
            list.into_any()
        }
        toml::Value::Table(table) => {
            let dict = PyDict::new(py);
            for (k, v) in table {
                dict.set_item(k, to_python(py, v)?)?;
            }
            dict.into_any()
        }
    })
}
