//! The core's error type.
//!
//! Every fallible function of the core returns [`Result`]. Variants carry the facts a user
//! needs to fix the input — which file, which field, what was expected — so that the Python
//! binding can turn them into exceptions with one `match` and no string parsing.

use std::path::PathBuf;

/// Result alias used throughout the core.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Everything that can go wrong inside `dhptam-core`.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A value handed to the core does not meet the documented expectation
    /// (wrong shape, NaN, out of range, ...).
    #[error("invalid {what}: expected {expected}, got {got}")]
    InvalidInput {
        /// The argument or field, e.g. `"points"` or `"intrinsics.fx"`.
        what: String,
        /// What the core expected, phrased for a user.
        expected: String,
        /// What it received.
        got: String,
    },

    /// A configuration file or string could not be used.
    #[error("configuration error in {source_name}: {message}")]
    Config {
        /// Where the configuration came from: a file path or `"<string>"`.
        source_name: String,
        /// What is wrong, naming the key where there is one.
        message: String,
    },

    /// A text file could not be parsed; the line is 1-based.
    #[error("{path}:{line}: {message}")]
    Parse {
        /// The file being read.
        path: PathBuf,
        /// 1-based line number of the offending line.
        line: usize,
        /// What was expected on that line.
        message: String,
    },

    /// Reading or writing a file failed.
    #[error("cannot {action} {path}: {source}")]
    Io {
        /// `"read"`, `"write"`, `"create"`, ...
        action: &'static str,
        /// The file concerned.
        path: PathBuf,
        /// The operating-system error.
        #[source]
        source: std::io::Error,
    },

    /// A binary file (an MCAP log) is malformed or lacks what the reader needs.
    #[error("{path}: {field}: {message}")]
    Format {
        /// The file being read or written.
        path: PathBuf,
        /// The part of the file concerned: a channel topic (`/events/left`), a record kind
        /// (`summary`, `magic`), a metadata name.
        field: String,
        /// What is wrong and what was expected.
        message: String,
    },

    /// A numerical procedure failed on valid input (degenerate geometry, no convergence).
    #[error("numerical failure in {operation}: {reason}")]
    Numerical {
        /// The procedure, e.g. `"stereo rectification"`.
        operation: &'static str,
        /// Why it failed.
        reason: String,
    },
}

impl Error {
    /// Shorthand for [`Error::InvalidInput`].
    pub fn invalid(
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl ToString,
    ) -> Self {
        Error::InvalidInput {
            what: what.into(),
            expected: expected.into(),
            got: got.to_string(),
        }
    }

    /// Shorthand for [`Error::Numerical`].
    pub fn numerical(operation: &'static str, reason: impl Into<String>) -> Self {
        Error::Numerical {
            operation,
            reason: reason.into(),
        }
    }
}

/// Checks that every value is finite, naming the field in the error otherwise.
pub fn ensure_finite(what: &str, values: &[f64]) -> Result<()> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => Err(Error::invalid(
            format!("{what}[{i}]"),
            "a finite number",
            values[i],
        )),
    }
}

/// Checks a per-observation measurement noise: `count` values (the list is named `what`),
/// each a finite positive number of pixels.
pub fn ensure_sigmas<T>(what: &str, sigmas: &[T], count: usize) -> Result<()>
where
    T: Copy + Into<f64> + std::fmt::Display,
{
    if sigmas.len() != count {
        return Err(Error::invalid(
            what,
            format!("{count} values, one per observation"),
            sigmas.len(),
        ));
    }
    match sigmas.iter().position(|&s| {
        let s: f64 = s.into();
        !(s.is_finite() && s > 0.0)
    }) {
        None => Ok(()),
        Some(i) => Err(Error::invalid(
            format!("{what}[{i}]"),
            "a finite positive number of pixels",
            sigmas[i],
        )),
    }
}
