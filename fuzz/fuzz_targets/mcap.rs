//! MCAP logs: any bytes opened as a dhptam log give a reader or an error (`Error::Format` or
//! `Error::Io`), never a panic; every read of an opened log (each channel by its schema, event
//! windows, metadata) is a result or an error too, and an event channel that reads whole
//! holds exactly the count its index promises. The reader maps a path, so each input is
//! written to a per-process scratch file first.
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use dhptam_core::io::mcap::{LogReader, SchemaKind};
use libfuzzer_sys::fuzz_target;

fn scratch() -> &'static PathBuf {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        std::env::temp_dir().join(format!("dhptam-fuzz-mcap-{}.mcap", std::process::id()))
    })
}

/// At most this many messages of a channel are decoded per input (keeps each run short).
const MAX_MESSAGES: usize = 16;

fn exercise(reader: &LogReader) {
    let _ = reader.metadata("dhptam.sequence");
    for (topic, info) in reader.topics() {
        let Some(kind) = SchemaKind::from_name(&info.schema_name) else {
            continue;
        };
        let n = info.message_count;
        if let Ok(times) = reader.log_times(topic, kind) {
            assert_eq!(times.len(), n);
        }
        let few = 0..n.min(MAX_MESSAGES);
        match kind {
            SchemaKind::RawImage => {
                if let Ok(images) = reader.images(topic, few.clone()) {
                    assert_eq!(images.len(), few.len());
                }
            }
            SchemaKind::CompressedImage => {
                if let Ok(images) = reader.compressed_images(topic, few.clone()) {
                    assert_eq!(images.len(), few.len());
                }
            }
            SchemaKind::CameraCalibration if n <= MAX_MESSAGES => {
                let _ = reader.calibrations(topic);
            }
            SchemaKind::PoseInFrame if n <= MAX_MESSAGES => {
                let _ = reader.poses(topic);
            }
            SchemaKind::PointCloud if n <= MAX_MESSAGES => {
                let _ = reader.point_clouds(topic);
            }
            SchemaKind::EventBatch => {
                let Ok(count) = reader.event_count(topic) else {
                    continue;
                };
                if let Ok((t0, t1)) = reader.event_time_range(topic) {
                    assert!(count == 0 || t0 < t1, "span [{t0}, {t1}) of {count} events");
                    let mid = t0 / 2 + t1 / 2;
                    for (a, b) in [
                        (t0, t1),
                        (t0, mid),
                        (mid, t1),
                        (t1, t0),
                        (i64::MIN, i64::MAX),
                    ] {
                        if let Ok((i0, i1)) = reader.event_index_range(topic, a, b) {
                            assert!(i0 <= i1 && i1 <= count, "[{i0}, {i1}) of {count}");
                        }
                        let _ = reader.event_window(topic, a, b);
                    }
                }
                if n <= MAX_MESSAGES {
                    if let Ok(all) = reader.event_slice(topic, 0, usize::MAX) {
                        assert_eq!(all.len(), count);
                        assert_eq!(all.x.len(), count);
                        assert_eq!(all.p.len(), count);
                    }
                }
            }
            _ => {}
        }
    }
}

fuzz_target!(|data: &[u8]| {
    let path = scratch();
    if std::fs::write(path, data).is_err() {
        return;
    }
    if let Ok(reader) = LogReader::open(path) {
        exercise(&reader);
    }
});
