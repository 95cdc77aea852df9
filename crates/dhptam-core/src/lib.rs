//! # dhptam-core
//!
//! The pure-Rust core of dhptam, a stereo events+frames SLAM system after DH-PTAM. It has no
//! Python dependency: the binding lives in `crates/dhptam-python`.
//!
//! Modules:
//! - [`geometry`]: SO(3)/SE(3), camera models, stereo rectification, triangulation.
//! - [`sim`]: the stereo events+frames simulator (ray casting, ESIM events, frame sensor).
//! - [`events`]: event windows, the E3CT and baseline event representations.
//! - [`fusion`]: event rectification, event→frame warp, online β fusion.
//! - [`matching`]: float/binary descriptors, distances, brute-force and guided matching.
//! - [`config`]: typed, documented, TOML-backed configuration of every stage.
//! - [`error`]: the error type shared by the whole core.

pub mod config;
pub mod error;
pub mod events;
pub mod features;
pub mod fusion;
pub mod geometry;
pub mod io;
pub mod matching;
pub mod place;
pub mod sim;
pub mod slam;
pub mod solver;

pub use error::{Error, Result};
