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

// -- panics (issue 10) ----------------------------------------------------------------------

/// Text of a panic payload (`panic!("...")` carries a `&str` or a `String`).
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_owned()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic without a message".to_owned()
    }
}

/// Turns a panic caught in `what` into `dhptam.errors.InternalError` (a `DhptamError` and a
/// `RuntimeError`), so that no raw `pyo3_runtime.PanicException` (a `BaseException`, which
/// `except Exception` does not catch) reaches Python code.
pub fn panic_to_py_err(what: &str, payload: Box<dyn std::any::Any + Send>) -> PyErr {
    let message = format!(
        "internal error in {what}: {} (this is a dhptam bug; please report it with the input)",
        panic_message(payload.as_ref())
    );
    log::error!("{message}");
    Python::attach(|py| {
        class(py, "InternalError")
            .and_then(|cls| cls.call1((message.clone(),)))
            .map(PyErr::from_value)
            .unwrap_or_else(|_| PyRuntimeError::new_err(message))
    })
}

/// Runs `f` with the GIL released (like `Python::detach`) and converts a panic inside it into
/// `InternalError` instead of letting it unwind into PyO3.
pub trait DetachGuarded {
    /// `detach` + `catch_unwind`; `what` names the call in the error message.
    fn detach_guarded<T, F>(self, what: &str, f: F) -> PyResult<T>
    where
        F: Send + FnOnce() -> T,
        T: Send;
}

impl DetachGuarded for Python<'_> {
    fn detach_guarded<T, F>(self, what: &str, f: F) -> PyResult<T>
    where
        F: Send + FnOnce() -> T,
        T: Send,
    {
        self.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)))
            .map_err(|payload| panic_to_py_err(what, payload))
    }
}

/// Test-only entry point: panics with `message` inside [`DetachGuarded::detach_guarded`], so the
/// test suite can show that a core panic reaches Python as `dhptam.errors.InternalError`
/// carrying the message (and the interpreter lives on). It does nothing else; no dhptam code
/// calls it.
#[pyfunction]
pub fn _testing_panic(py: Python<'_>, message: &str) -> PyResult<()> {
    py.detach_guarded("_testing_panic", || -> () { panic!("{message}") })
}
