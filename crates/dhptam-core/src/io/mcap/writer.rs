//! [`LogWriter`]: writes a dhptam MCAP log atomically (temporary file, then rename).

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use ::mcap::records::{MessageHeader, Metadata};
use ::mcap::{Compression, WriteOptions, Writer};

use super::schemas::{
    encode_event_batch, CameraCalibration, CompressedImage, EventColumns, PointCloud, PoseInFrame,
    RawImage, SchemaKind,
};
use super::{mcap_error, BATCH_EVENTS_KEY, MESSAGE_ENCODING, PROFILE};
use crate::error::{Error, Result};

/// Chunk compression of a log.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LogCompression {
    /// zstd (the default): about twice lz4's ratio on event batches.
    #[default]
    Zstd,
    /// lz4: faster to write and read, larger files.
    Lz4,
    /// No compression.
    None,
}

impl LogCompression {
    /// Parses `"zstd"`, `"lz4"` or `"none"`.
    pub fn parse(name: &str) -> Result<Self> {
        match name {
            "zstd" => Ok(LogCompression::Zstd),
            "lz4" => Ok(LogCompression::Lz4),
            "none" => Ok(LogCompression::None),
            other => Err(Error::invalid(
                "compression",
                "\"zstd\", \"lz4\" or \"none\"",
                format!("{other:?}"),
            )),
        }
    }
}

/// How a log is written.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogOptions {
    /// Chunk compression. Default: zstd.
    pub compression: LogCompression,
    /// Uncompressed size at which a chunk is closed, bytes. Default: 4 MiB (a chunk is the
    /// unit a reader decompresses to reach one message).
    pub chunk_size_bytes: u64,
    /// Events per `dhptam.EventBatch` message (the last batch of a stream may hold fewer).
    /// Default: 32768 (426 KiB a batch before compression).
    pub batch_events: usize,
}

impl Default for LogOptions {
    fn default() -> Self {
        LogOptions {
            compression: LogCompression::Zstd,
            chunk_size_bytes: 4 << 20,
            batch_events: 32_768,
        }
    }
}

/// Events buffered for one event channel until a full batch is ready.
struct EventStream {
    channel: u16,
    frame_id: String,
    pending: EventColumns,
    written: u64,
    batches: u32,
    last_t_ns: Option<i64>,
}

/// Writes a dhptam log: event batches and Foxglove messages on named channels (topics), in
/// zstd/lz4 chunks with message indexes and a summary, so readers seek by time.
///
/// The log is written to `<path>.tmp-<pid>` and renamed to `path` by [`LogWriter::finish`];
/// a writer dropped without `finish` (an error, an interrupted run) deletes its temporary file,
/// so `path` is either absent or a complete log.
///
/// Messages of one channel must come in time order; different channels may interleave freely.
pub struct LogWriter {
    path: PathBuf,
    tmp: PathBuf,
    writer: Option<Writer<BufWriter<File>>>,
    options: LogOptions,
    schemas: HashMap<SchemaKind, u16>,
    channels: HashMap<String, (u16, SchemaKind, u32)>,
    events: BTreeMap<String, EventStream>,
}

impl LogWriter {
    /// Starts a log that will appear at `path` when finished.
    pub fn create(path: impl AsRef<Path>, options: LogOptions) -> Result<Self> {
        let path = path.as_ref().to_path_buf();
        if options.batch_events == 0 {
            return Err(Error::invalid("batch_events", "at least 1", 0));
        }
        let mut tmp_name = path.file_name().unwrap_or_default().to_os_string();
        tmp_name.push(format!(".tmp-{}", std::process::id()));
        let tmp = path.with_file_name(tmp_name);
        let file = File::create(&tmp).map_err(|source| Error::Io {
            action: "create",
            path: tmp.clone(),
            source,
        })?;
        let compression = match options.compression {
            LogCompression::Zstd => Some(Compression::Zstd),
            LogCompression::Lz4 => Some(Compression::Lz4),
            LogCompression::None => None,
        };
        let writer = WriteOptions::new()
            .profile(PROFILE)
            .library(concat!("dhptam ", env!("CARGO_PKG_VERSION")))
            .compression(compression)
            .chunk_size(Some(options.chunk_size_bytes))
            .create(BufWriter::with_capacity(1 << 20, file));
        let writer = match writer {
            Ok(w) => w,
            Err(e) => {
                let _ = std::fs::remove_file(&tmp);
                return Err(mcap_error(&path, "header", e));
            }
        };
        Ok(LogWriter {
            path,
            tmp,
            writer: Some(writer),
            options,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            events: BTreeMap::new(),
        })
    }

    /// The path the finished log will have.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn inner(&mut self) -> Result<&mut Writer<BufWriter<File>>> {
        self.writer.as_mut().ok_or_else(|| Error::Format {
            path: self.path.clone(),
            field: "writer".into(),
            message: "the log is already finished".into(),
        })
    }

    fn channel(
        &mut self,
        topic: &str,
        kind: SchemaKind,
        metadata: BTreeMap<String, String>,
    ) -> Result<u16> {
        if let Some(&(id, existing, _)) = self.channels.get(topic) {
            if existing != kind {
                return Err(Error::invalid(
                    format!("topic {topic}"),
                    format!("messages of its schema {}", existing.name()),
                    kind.name(),
                ));
            }
            return Ok(id);
        }
        let path = self.path.clone();
        let schema = match self.schemas.get(&kind) {
            Some(&id) => id,
            None => {
                let data = kind.descriptor_set();
                let id = self
                    .inner()?
                    .add_schema(kind.name(), "protobuf", &data)
                    .map_err(|e| mcap_error(&path, topic, e))?;
                self.schemas.insert(kind, id);
                id
            }
        };
        let id = self
            .inner()?
            .add_channel(schema, topic, MESSAGE_ENCODING, &metadata)
            .map_err(|e| mcap_error(&path, topic, e))?;
        self.channels.insert(topic.to_owned(), (id, kind, 0));
        Ok(id)
    }

    fn write(&mut self, topic: &str, kind: SchemaKind, t_ns: i64, data: &[u8]) -> Result<()> {
        let id = self.channel(topic, kind, BTreeMap::new())?;
        self.write_to(topic, id, t_ns, data)
    }

    fn write_to(&mut self, topic: &str, id: u16, t_ns: i64, data: &[u8]) -> Result<()> {
        let log_time = u64::try_from(t_ns)
            .map_err(|_| Error::invalid(format!("{topic} timestamp"), "a time >= 0 ns", t_ns))?;
        let sequence = match self.channels.get_mut(topic) {
            Some(entry) => {
                entry.2 += 1;
                entry.2 - 1
            }
            None => 0,
        };
        let path = self.path.clone();
        self.inner()?
            .write_to_known_channel(
                &MessageHeader {
                    channel_id: id,
                    sequence,
                    log_time,
                    publish_time: log_time,
                },
                data,
            )
            .map_err(|e| mcap_error(&path, topic, e))
    }

    /// Writes a `foxglove.RawImage` on `topic`, logged at the image's time.
    pub fn add_image(&mut self, topic: &str, image: &RawImage) -> Result<()> {
        let expected = image.step as u64 * image.height as u64;
        if image.data.len() as u64 != expected {
            return Err(Error::invalid(
                format!("{topic} image data"),
                format!("step × height = {expected} bytes"),
                image.data.len(),
            ));
        }
        self.write(topic, SchemaKind::RawImage, image.t_ns, &image.encode())
    }

    /// Writes a `foxglove.CompressedImage` (PNG or JPEG bytes, not checked) on `topic`, logged
    /// at the image's time.
    pub fn add_compressed_image(&mut self, topic: &str, image: &CompressedImage) -> Result<()> {
        if image.data.is_empty() || image.format.is_empty() {
            return Err(Error::invalid(
                format!("{topic} compressed image"),
                "non-empty data and format",
                format!("{} bytes of format {:?}", image.data.len(), image.format),
            ));
        }
        self.write(
            topic,
            SchemaKind::CompressedImage,
            image.t_ns,
            &image.encode(),
        )
    }

    /// Writes a `foxglove.CameraCalibration` on `topic`.
    pub fn add_calibration(&mut self, topic: &str, calibration: &CameraCalibration) -> Result<()> {
        for (name, v, n) in [
            ("K", &calibration.k, 9),
            ("R", &calibration.r, 9),
            ("P", &calibration.p, 12),
        ] {
            if v.len() != n {
                return Err(Error::invalid(
                    format!("{topic} calibration {name}"),
                    format!("{n} values"),
                    v.len(),
                ));
            }
        }
        self.write(
            topic,
            SchemaKind::CameraCalibration,
            calibration.t_ns,
            &calibration.encode(),
        )
    }

    /// Writes a `foxglove.PoseInFrame` on `topic`.
    pub fn add_pose(&mut self, topic: &str, pose: &PoseInFrame) -> Result<()> {
        crate::error::ensure_finite(topic, &pose.translation)?;
        crate::error::ensure_finite(topic, &pose.quat_xyzw)?;
        self.write(topic, SchemaKind::PoseInFrame, pose.t_ns, &pose.encode())
    }

    /// Writes a `foxglove.PointCloud` on `topic`.
    pub fn add_point_cloud(&mut self, topic: &str, cloud: &PointCloud) -> Result<()> {
        self.write(topic, SchemaKind::PointCloud, cloud.t_ns, &cloud.encode())
    }

    /// Writes a named metadata record (string key-value pairs).
    pub fn add_metadata(&mut self, name: &str, entries: BTreeMap<String, String>) -> Result<()> {
        let path = self.path.clone();
        self.inner()?
            .write_metadata(&Metadata {
                name: name.to_owned(),
                metadata: entries,
            })
            .map_err(|e| mcap_error(&path, name, e))
    }

    /// Appends events of one camera to the `dhptam.EventBatch` channel `topic`.
    ///
    /// Events are buffered and written in batches of [`LogOptions::batch_events`]; times must be
    /// non-decreasing across calls, and all four columns must have the same length.
    pub fn add_events(
        &mut self,
        topic: &str,
        frame_id: &str,
        x: &[u16],
        y: &[u16],
        t_ns: &[i64],
        p: &[i8],
    ) -> Result<()> {
        let n = t_ns.len();
        if x.len() != n || y.len() != n || p.len() != n {
            return Err(Error::invalid(
                format!("{topic} events"),
                "x, y, t_ns and p of equal length",
                format!("{}, {}, {}, {}", x.len(), y.len(), n, p.len()),
            ));
        }
        if !self.events.contains_key(topic) {
            let meta = BTreeMap::from([
                (
                    BATCH_EVENTS_KEY.to_owned(),
                    self.options.batch_events.to_string(),
                ),
                ("frame_id".to_owned(), frame_id.to_owned()),
            ]);
            let channel = self.channel(topic, SchemaKind::EventBatch, meta)?;
            self.events.insert(
                topic.to_owned(),
                EventStream {
                    channel,
                    frame_id: frame_id.to_owned(),
                    pending: EventColumns::default(),
                    written: 0,
                    batches: 0,
                    last_t_ns: None,
                },
            );
        }
        let Some(stream) = self.events.get_mut(topic) else {
            return Ok(());
        };
        let mut prev = stream.last_t_ns.unwrap_or(0);
        for (i, &t) in t_ns.iter().enumerate() {
            if t < prev {
                return Err(Error::invalid(
                    format!("{topic} t_ns[{i}]"),
                    format!("times >= 0 and non-decreasing (previous event at {prev} ns)"),
                    t,
                ));
            }
            prev = t;
        }
        if n == 0 {
            return Ok(());
        }
        stream.last_t_ns = Some(prev);
        stream.pending.x.extend_from_slice(x);
        stream.pending.y.extend_from_slice(y);
        stream.pending.t_ns.extend_from_slice(t_ns);
        stream.pending.p.extend_from_slice(p);
        let batch = self.options.batch_events;
        if self.events[topic].pending.len() >= batch {
            self.flush_events(topic, false)?;
        }
        Ok(())
    }

    /// Writes the full batches pending on `topic` (and the partial last one when `all`).
    fn flush_events(&mut self, topic: &str, all: bool) -> Result<()> {
        let batch = self.options.batch_events;
        let Some(stream) = self.events.get_mut(topic) else {
            return Ok(());
        };
        let pending = std::mem::take(&mut stream.pending);
        let (channel, frame_id) = (stream.channel, stream.frame_id.clone());
        let mut start = 0;
        let mut messages = Vec::new();
        while pending.len() - start >= batch || (all && start < pending.len()) {
            let end = (start + batch).min(pending.len());
            let data = encode_event_batch(
                &frame_id,
                stream.written,
                &pending.x[start..end],
                &pending.y[start..end],
                &pending.t_ns[start..end],
                &pending.p[start..end],
            );
            messages.push((pending.t_ns[start], data));
            stream.written += (end - start) as u64;
            stream.batches += 1;
            start = end;
        }
        stream.pending = EventColumns {
            x: pending.x[start..].to_vec(),
            y: pending.y[start..].to_vec(),
            t_ns: pending.t_ns[start..].to_vec(),
            p: pending.p[start..].to_vec(),
        };
        for (t0, data) in messages {
            self.write_to(topic, channel, t0, &data)?;
        }
        Ok(())
    }

    /// Writes the pending event batches, the summary and the indexes, then renames the
    /// temporary file to the log's path.
    pub fn finish(mut self) -> Result<()> {
        let result = self.finish_inner();
        if result.is_err() {
            let _ = std::fs::remove_file(&self.tmp);
        }
        result
    }

    fn finish_inner(&mut self) -> Result<()> {
        let topics: Vec<String> = self.events.keys().cloned().collect();
        for topic in topics {
            self.flush_events(&topic, true)?;
        }
        let path = self.path.clone();
        let mut writer = self.writer.take().ok_or_else(|| Error::Format {
            path: path.clone(),
            field: "writer".into(),
            message: "the log is already finished".into(),
        })?;
        writer
            .finish()
            .map_err(|e| mcap_error(&path, "summary", e))?;
        let file = writer.into_inner().into_inner().map_err(|e| Error::Io {
            action: "write",
            path: self.tmp.clone(),
            source: e.into_error(),
        })?;
        file.sync_all().map_err(|source| Error::Io {
            action: "write",
            path: self.tmp.clone(),
            source,
        })?;
        drop(file);
        std::fs::rename(&self.tmp, &self.path).map_err(|source| Error::Io {
            action: "rename into",
            path: self.path.clone(),
            source,
        })
    }
}

impl Drop for LogWriter {
    fn drop(&mut self) {
        if self.writer.take().is_some() {
            // Not finished: leave nothing half-written behind.
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}
