//! # dhptam-core
//!
//! The pure-Rust core of dhptam, a stereo events+frames SLAM system after DH-PTAM. It has no
//! Python dependency: the binding lives in `crates/dhptam-python`.
//!
//! Modules:
//! - [`geometry`]: SO(3)/SE(3), camera models, stereo rectification, triangulation.
//! - [`config`]: typed, documented, TOML-backed configuration of every stage.
//! - [`error`]: the error type shared by the whole core.

pub mod config;
pub mod error;
pub mod geometry;
pub mod io;
pub mod solver;

pub use error::{Error, Result};
