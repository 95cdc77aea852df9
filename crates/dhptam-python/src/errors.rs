//! The one place where core errors become Python exceptions.
//!
//! The exception classes live in `python/dhptam/errors.py` (so that they can inherit from both
//! `DhptamError` and the matching built-in, e.g. `ValueError`); this module looks them up once
//! and attaches the facts the core error carries (`path`, `line`, `field`) as attributes.

use dhptam_core::Error;
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::PyType;

/// Converts a core error into the matching `dhptam.errors` exception.
pub fn to_py_err(error: Error) -> PyErr {
    Python::attach(|py| match build(py, &error) {
        Ok(err) => err,
        // The Python package is always importable next to `_core`; if not, still say what failed.
        Err(import_failure) => PyRuntimeError::new_err(format!(
            "{error} (and dhptam.errors failed: {import_failure})"
        )),
    })
}

fn class<'py>(py: Python<'py>, name: &str) -> PyResult<Bound<'py, PyType>> {
    static MODULE: PyOnceLock<Py<PyModule>> = PyOnceLock::new();
    let module = MODULE.get_or_try_init(py, || py.import("dhptam.errors").map(Bound::unbind))?;
    Ok(module.bind(py).getattr(name)?.cast_into::<PyType>()?)
}

fn build(py: Python<'_>, error: &Error) -> PyResult<PyErr> {
    let (name, field, path, line) = match error {
        Error::InvalidInput { what, .. } => ("InputError", Some(what.clone()), None, None),
        Error::Config { source_name, .. } => ("ConfigError", None, Some(source_name.clone()), None),
        Error::Parse { path, line, .. } => (
            "ParseError",
            None,
            Some(path.display().to_string()),
            Some(*line),
        ),
        Error::Io { path, .. } => ("FileError", None, Some(path.display().to_string()), None),
        Error::Format { path, field, .. } => (
            "ParseError",
            Some(field.clone()),
            Some(path.display().to_string()),
            None,
        ),
        Error::Numerical { .. } => ("NumericalError", None, None, None),
    };
    let instance = class(py, name)?.call1((error.to_string(),))?;
    instance.setattr("field", field)?;
    instance.setattr("path", path)?;
    instance.setattr("line", line)?;
    Ok(PyErr::from_value(instance))
}

/// Raises `dhptam.errors.InputError` with the usual "invalid X: expected Y, got Z" message.
pub fn input_error(what: &str, expected: &str, got: impl ToString) -> PyErr {
    to_py_err(Error::invalid(what, expected, got))
}

/// `?`-friendly conversion for core results.
pub trait IntoPyResult<T> {
    /// Maps the core error into a Python exception.
    fn py(self) -> PyResult<T>;
}

impl<T> IntoPyResult<T> for dhptam_core::Result<T> {
    fn py(self) -> PyResult<T> {
        self.map_err(to_py_err)
    }
}
