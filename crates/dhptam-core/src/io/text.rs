//! Line-oriented tokenising shared by the text readers: every token knows its 1-based line.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// Reads a whole text file, mapping the OS error to [`Error::Io`].
pub(crate) fn read_to_string(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|source| Error::Io {
        action: "read",
        path: path.to_path_buf(),
        source,
    })
}

/// Writes a whole text file through a temporary sibling, so a failure leaves nothing
/// half-written under the final name.
pub(crate) fn write_atomically(path: &Path, text: &str) -> Result<()> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    std::fs::write(&tmp, text).map_err(|source| Error::Io {
        action: "write",
        path: tmp.clone(),
        source,
    })?;
    std::fs::rename(&tmp, path).map_err(|source| Error::Io {
        action: "rename into",
        path: path.to_path_buf(),
        source,
    })
}

/// The tokens of one line with its number, for parsing a line with a known layout.
pub(crate) struct Line<'a> {
    pub path: &'a Path,
    pub number: usize,
    tokens: std::str::SplitWhitespace<'a>,
}

impl<'a> Line<'a> {
    pub fn new(path: &'a Path, number: usize, text: &'a str) -> Self {
        Self {
            path,
            number,
            tokens: text.split_whitespace(),
        }
    }

    pub fn error(&self, message: impl Into<String>) -> Error {
        Error::Parse {
            path: self.path.to_path_buf(),
            line: self.number,
            message: message.into(),
        }
    }

    /// The next token, or an error naming `what` was missing.
    pub fn token(&mut self, what: &str) -> Result<&'a str> {
        self.tokens
            .next()
            .ok_or_else(|| self.error(format!("missing {what}")))
    }

    /// The next token as a finite f64.
    pub fn float(&mut self, what: &str) -> Result<f64> {
        let tok = self.token(what)?;
        match tok.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err(self.error(format!("{what}: expected a finite number, got {tok:?}"))),
        }
    }

    /// The next token as an index no larger than `limit - 1` (no limit when `None`).
    pub fn index(&mut self, what: &str, limit: Option<usize>) -> Result<usize> {
        let tok = self.token(what)?;
        let v = tok.parse::<usize>().map_err(|_| {
            self.error(format!(
                "{what}: expected a non-negative integer, got {tok:?}"
            ))
        })?;
        match limit {
            Some(n) if v >= n => Err(self.error(format!(
                "{what}: index {v} out of range (expected below {n})"
            ))),
            _ => Ok(v),
        }
    }

    /// Errors when tokens are left over.
    pub fn finish(mut self) -> Result<()> {
        match self.tokens.next() {
            None => Ok(()),
            Some(tok) => Err(self.error(format!("unexpected extra token {tok:?}"))),
        }
    }
}
