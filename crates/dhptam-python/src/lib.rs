//! `dhptam._core`: the Python binding of `dhptam-core`.
//!
//! Thin wrappers only: each class holds the core type in `inner`, converts arrays at the
//! boundary (reading float64 C-contiguous numpy arrays in place) and releases the GIL around
//! work proportional to the input size. Core errors become `dhptam.errors` exceptions in
//! `errors.rs`, and nowhere else.

// Python functions return tuples of typed numpy arrays; naming each tuple would hide, not help.
#![allow(clippy::type_complexity)]

mod arrays;
mod config;
mod errors;
mod events;
mod features;
mod fusion;
mod geometry;
mod matching;
mod mcap;
mod sim;
mod slam;
mod solver;
mod stereo;

use std::sync::{Mutex, OnceLock};

use pyo3::prelude::*;

static LOG_RESET: OnceLock<Mutex<pyo3_log::ResetHandle>> = OnceLock::new();

/// Forgets the cached Python logger levels, so that a level set in Python after the first
/// message from Rust takes effect (`dhptam.logs.configure` calls this).
#[pyfunction]
fn _reset_log_cache() {
    if let Some(handle) = LOG_RESET.get() {
        if let Ok(handle) = handle.lock() {
            handle.reset();
        }
    }
}

/// Sends one message through the Rust `log` facade (for tests of the logging bridge).
#[pyfunction]
fn _log_from_rust(level: &str, message: &str) {
    let level = match level {
        "error" => log::Level::Error,
        "warn" | "warning" => log::Level::Warn,
        "debug" => log::Level::Debug,
        "trace" => log::Level::Trace,
        _ => log::Level::Info,
    };
    log::log!(target: "dhptam_core", level, "{message}");
}

/// Threads rayon uses for the core's parallel loops.
#[pyfunction]
fn thread_count() -> usize {
    rayon::current_num_threads()
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // Route the core's `log` records to Python's `logging` (logger names follow the Rust
    // module path, e.g. `dhptam_core.geometry.rectify`).
    let handle = pyo3_log::Logger::new(m.py(), pyo3_log::Caching::LoggersAndLevels)?.install();
    if let Ok(handle) = handle {
        let _ = LOG_RESET.set(Mutex::new(handle));
    }
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<geometry::PySo3>()?;
    m.add_class::<geometry::PySe3>()?;
    m.add_class::<geometry::PyCamera>()?;
    m.add_class::<config::PyConfig>()?;
    m.add_class::<stereo::PyStereoRig>()?;
    m.add_class::<stereo::PyRectifiedStereo>()?;
    m.add_function(wrap_pyfunction!(stereo::_triangulate, m)?)?;
    m.add_class::<sim::PySimulator>()?;
    m.add_function(wrap_pyfunction!(sim::sim_builtin_trajectory, m)?)?;
    m.add_function(wrap_pyfunction!(sim::sim_file_trajectory, m)?)?;
    m.add_function(wrap_pyfunction!(sim::sim_profile_segments, m)?)?;
    m.add_function(wrap_pyfunction!(matching::match_descriptors, m)?)?;
    m.add_function(wrap_pyfunction!(matching::_buffer_address, m)?)?;
    m.add_function(wrap_pyfunction!(events::_e3ct, m)?)?;
    m.add_class::<events::PyHotPixels>()?;
    m.add_function(wrap_pyfunction!(events::_count_image, m)?)?;
    m.add_function(wrap_pyfunction!(events::_event_activity, m)?)?;
    m.add_function(wrap_pyfunction!(events::_time_surface, m)?)?;
    m.add_function(wrap_pyfunction!(events::_voxel_grid, m)?)?;
    m.add_function(wrap_pyfunction!(events::_e3ct_scales, m)?)?;
    m.add_function(wrap_pyfunction!(events::_e3ct_apply_scales, m)?)?;
    m.add_function(wrap_pyfunction!(features::_r2d2_heads, m)?)?;
    m.add_function(wrap_pyfunction!(fusion::_choose_beta, m)?)?;
    m.add_function(wrap_pyfunction!(fusion::_fuse, m)?)?;
    m.add_function(wrap_pyfunction!(fusion::_recover_exposure, m)?)?;
    m.add_function(wrap_pyfunction!(fusion::_warp_to_frame, m)?)?;
    m.add_function(wrap_pyfunction!(fusion::_warp_and_fuse, m)?)?;
    m.add_class::<fusion::PyEventRectifier>()?;
    m.add_class::<fusion::PyEventStereo>()?;
    m.add_function(wrap_pyfunction!(geometry::_data_address, m)?)?;
    m.add_function(wrap_pyfunction!(solver::_solve_bal_file, m)?)?;
    m.add_function(wrap_pyfunction!(solver::_solve_pose_graph_file, m)?)?;
    m.add_function(wrap_pyfunction!(solver::_bundle_adjust, m)?)?;
    // MCAP logs (dhptam.datasets.mcap).
    m.add_class::<mcap::PyMcapWriter>()?;
    m.add_class::<mcap::PyMcapReader>()?;
    // Test-only: shows that a core panic becomes InternalError (tests/test_bad_input.py).
    m.add_function(wrap_pyfunction!(errors::_testing_panic, m)?)?;
    m.add_class::<slam::PySystem>()?;
    m.add_function(wrap_pyfunction!(solver::solve_pnp_ransac, m)?)?;
    m.add_function(wrap_pyfunction!(_reset_log_cache, m)?)?;
    m.add_function(wrap_pyfunction!(_log_from_rust, m)?)?;
    m.add_function(wrap_pyfunction!(thread_count, m)?)?;
    Ok(())
}
