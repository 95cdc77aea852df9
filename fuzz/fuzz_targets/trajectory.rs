//! Simulator trajectory files (TUM and CSV): any bytes give a trajectory or a line-numbered
//! `Error::Parse`, never a panic. The reader takes a path, so each input is written to a
//! per-process scratch file first.
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use dhptam_core::sim::trajectory::Trajectory;
use libfuzzer_sys::fuzz_target;

fn scratch() -> &'static PathBuf {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        std::env::temp_dir().join(format!("dhptam-fuzz-trajectory-{}", std::process::id()))
    })
}

fuzz_target!(|data: &[u8]| {
    let path = scratch();
    if std::fs::write(path, data).is_err() {
        return;
    }
    for read in [Trajectory::read_tum, Trajectory::read_csv] {
        if let Ok(trajectory) = read(path) {
            let (t0, t1) = trajectory.span_ns();
            assert!(t0 <= t1);
            let _ = trajectory.pose_at(t0 / 2 + t1 / 2);
        }
    }
});
