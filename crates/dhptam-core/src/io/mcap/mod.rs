//! MCAP logs, the project's own recording format: events, frames, calibration, poses and point
//! clouds in one indexed file that Foxglove opens without a plugin.
//!
//! # Layout
//! Every channel carries protobuf messages (`message_encoding = "protobuf"`) whose schema is
//! a `FileDescriptorSet` (`schema encoding = "protobuf"`), the encoding Foxglove decodes
//! natively. Protobuf rather than JSON because images, event batches and point clouds are
//! bulk bytes: JSON would carry them base64-encoded (a third larger, and a text parse per
//! message). Topics written by `dhptam.datasets.mcap` and `dhptam run --record`:
//!
//! | topic | schema | content |
//! |---|---|---|
//! | `/events/{left,right}` | `dhptam.EventBatch` | fixed-size batches of events ([`schemas`]) |
//! | `/frames/{left,right}` | `foxglove.RawImage` or `foxglove.CompressedImage` | `mono8` frames (or lossless PNG), logged at exposure start |
//! | `/calibration/<camera>` | `foxglove.CameraCalibration` | intrinsics of each camera |
//! | `/ground_truth`, `/slam/...` | `foxglove.PoseInFrame` | `world_from_cam` poses |
//! | `/slam/map` | `foxglove.PointCloud` | map points (`x, y, z` float32) |
//!
//! Messages are written in zstd (or lz4) chunks with message indexes and a summary, so a
//! reader finds any message without scanning the file. Event batches hold exactly
//! [`LogOptions::batch_events`] events each (the last one fewer), stated in the channel's
//! metadata under `batch_events`, and are logged at their first event's time: event `i` is in
//! batch `i / batch_events`, and the batch holding time `t` is found by a binary search over
//! the index's log times; a window read decompresses only the chunks of its batches.

mod proto;
pub mod reader;
pub mod schemas;
pub mod writer;

use std::path::Path;

pub use reader::{LogReader, TopicInfo};
pub use schemas::{
    CameraCalibration, CompressedImage, EventColumns, PointCloud, PoseInFrame, RawImage, SchemaKind,
};
pub use writer::{LogCompression, LogOptions, LogWriter};

use crate::error::Error;

/// The MCAP header's profile field for dhptam logs.
pub const PROFILE: &str = "dhptam";
/// Message encoding of every channel.
pub const MESSAGE_ENCODING: &str = "protobuf";
/// Event-channel metadata key holding the number of events per batch.
pub const BATCH_EVENTS_KEY: &str = "batch_events";

/// Maps an `mcap` crate error to the core's error, naming the file and the part concerned.
fn mcap_error(path: &Path, field: &str, error: ::mcap::McapError) -> Error {
    match error {
        ::mcap::McapError::Io(source) => Error::Io {
            action: "read or write",
            path: path.to_path_buf(),
            source,
        },
        other => Error::Format {
            path: path.to_path_buf(),
            field: field.to_owned(),
            message: other.to_string(),
        },
    }
}
