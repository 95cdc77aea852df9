//! [`LogReader`]: indexed, memory-bounded reads of a dhptam MCAP log.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::path::{Path, PathBuf};

use ::mcap::records::ChunkIndex;
use ::mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use ::mcap::Summary;
use memmap2::Mmap;
use rayon::prelude::*;

use super::schemas::{
    decode_event_batch, CameraCalibration, CompressedImage, EventColumns, PointCloud, PoseInFrame,
    RawImage, SchemaKind,
};
use super::{mcap_error, BATCH_EVENTS_KEY, MESSAGE_ENCODING};
use crate::error::{Error, Result};

const MAGIC: &[u8; 8] = b"\x89MCAP0\r\n";

/// Longest record a chunk may hold, bytes (256 MiB): far above any dhptam message (a 4K RGB
/// frame is 25 MB, an event batch 426 KiB), and the most a damaged length field can make the
/// reader allocate.
const MAX_RECORD_BYTES: usize = 256 << 20;

/// Where one message lies: its chunk (index into the reader's chunk list) and log time.
#[derive(Debug, Clone, Copy)]
struct Location {
    chunk: usize,
    /// Position among the channel's messages inside the same chunk.
    rank: usize,
    offset: u64,
    log_time: u64,
}

/// One channel of a log.
#[derive(Debug, Clone)]
pub struct TopicInfo {
    /// The channel's topic, e.g. `/events/left`.
    pub topic: String,
    /// Schema name (`foxglove.RawImage`, `dhptam.EventBatch`, ...).
    pub schema_name: String,
    /// Schema encoding (`protobuf` for dhptam logs).
    pub schema_encoding: String,
    /// Message encoding (`protobuf` for dhptam logs).
    pub message_encoding: String,
    /// The channel's metadata.
    pub metadata: BTreeMap<String, String>,
    /// Number of messages, from the chunk message indexes.
    pub message_count: usize,
    channel_id: u16,
    locations: Vec<Location>,
}

/// The layout of an event channel, computed when the log is opened.
#[derive(Debug, Clone)]
struct EventIndex {
    batch_events: usize,
    count: usize,
    t_first_ns: i64,
    t_last_ns: i64,
}

/// A dhptam MCAP log opened for reading.
///
/// Opening maps the file and reads its summary and message indexes only (no chunk is
/// decompressed except the last event batch of each event channel, for the event count); every
/// read then decompresses just the chunks holding the requested messages, so memory stays
/// proportional to what is read. Errors name the file and the channel concerned.
pub struct LogReader {
    path: PathBuf,
    map: Mmap,
    summary: Summary,
    chunks: Vec<ChunkIndex>,
    topics: BTreeMap<String, TopicInfo>,
    events: HashMap<String, EventIndex>,
}

fn format_error(path: &Path, field: &str, message: impl Into<String>) -> Error {
    Error::Format {
        path: path.to_path_buf(),
        field: field.to_owned(),
        message: message.into(),
    }
}

/// For a chunk record stored without compression (`bytes`: opcode, length, chunk), the first
/// record inside it whose length runs past the chunk's data, described; `None` when every
/// record fits, or when the chunk is compressed or its header is malformed (the `mcap` crate
/// reports those). The crate subtracts such a length from the bytes left without a check (an
/// overflow panic in debug builds, a wrap-around in release ones), so it is caught here first.
fn uncompressed_chunk_overrun(bytes: &[u8]) -> Option<String> {
    let u32_at = |at: usize| -> Option<u32> {
        Some(u32::from_le_bytes(bytes.get(at..at + 4)?.try_into().ok()?))
    };
    let u64_at = |at: usize| -> Option<u64> {
        Some(u64::from_le_bytes(bytes.get(at..at + 8)?.try_into().ok()?))
    };
    // opcode (1) + record length (8), then start time, end time, uncompressed size (8 each),
    // uncompressed CRC (4), the compression string (u32 length + bytes), compressed size (8).
    let compression_len = u32_at(9 + 24 + 4)? as usize;
    if compression_len != 0 {
        return None;
    }
    let compressed_size = u64_at(9 + 24 + 4 + 4)?;
    let data_start: usize = 9 + 24 + 4 + 4 + 8;
    let data_end = data_start.checked_add(usize::try_from(compressed_size).ok()?)?;
    let data = bytes.get(data_start..data_end)?;
    let mut at = 0usize;
    while at < data.len() {
        let len = data
            .get(at + 1..at + 9)
            .and_then(|b| b.try_into().ok())
            .map(u64::from_le_bytes);
        let fits = len
            .and_then(|len| usize::try_from(len).ok())
            .and_then(|len| len.checked_add(9))
            .filter(|&total| total <= data.len() - at);
        match fits {
            Some(total) => at += total,
            None => {
                return Some(format!(
                    "the record at byte {at} of its {} data bytes is {} bytes long, past the \
                     chunk's end",
                    data.len(),
                    len.map_or_else(|| "an unreadable number of".to_string(), |l| l.to_string())
                ))
            }
        }
    }
    None
}

/// The same check as [`uncompressed_chunk_overrun`] for the chunk records the `mcap` crate's
/// summary reader would meet: it reads every record from the footer's `summary_start` to the
/// footer, so a damaged `summary_start` pointing into the data section hands it chunks.
fn summary_chunk_overrun(map: &[u8]) -> Option<String> {
    // The footer record (opcode, length 20, summary_start, summary_offset_start, CRC) ends
    // just before the closing magic.
    let footer = map.len().checked_sub(8 + 9 + 20)?;
    let summary_start = u64::from_le_bytes(map.get(footer + 9..footer + 17)?.try_into().ok()?);
    let mut at = usize::try_from(summary_start).ok()?;
    if at == 0 {
        return None;
    }
    while at < footer {
        let opcode = *map.get(at)?;
        let len = usize::try_from(u64::from_le_bytes(
            map.get(at + 1..at + 9)?.try_into().ok()?,
        ))
        .ok()?;
        let end = at.checked_add(9)?.checked_add(len)?;
        let record = map.get(at..end)?;
        if opcode == ::mcap::records::op::CHUNK {
            if let Some(message) = uncompressed_chunk_overrun(record) {
                return Some(format!(
                    "chunk record at byte {at} of the summary section: {message}"
                ));
            }
        }
        at = end;
    }
    None
}

impl LogReader {
    /// Opens a log and reads its summary and indexes.
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref().to_path_buf();
        let file = File::open(&path).map_err(|source| Error::Io {
            action: "open",
            path: path.clone(),
            source,
        })?;
        // SAFETY: the map is read-only and private to this reader; a log modified by another
        // process while it is open is outside the contract (as for any memory-mapped reader).
        let map = unsafe { Mmap::map(&file) }.map_err(|source| Error::Io {
            action: "map",
            path: path.clone(),
            source,
        })?;
        if map.len() < 16 || &map[..8] != MAGIC {
            return Err(format_error(
                &path,
                "magic",
                "not an MCAP file: it does not start with the MCAP magic bytes",
            ));
        }
        if &map[map.len() - 8..] != MAGIC {
            return Err(format_error(
                &path,
                "magic",
                "the file does not end with the MCAP magic bytes (truncated or still being written)",
            ));
        }
        if let Some(message) = summary_chunk_overrun(&map) {
            return Err(format_error(&path, "summary", message));
        }
        let summary = Summary::read(&map)
            .map_err(|e| mcap_error(&path, "summary", e))?
            .ok_or_else(|| {
                format_error(
                    &path,
                    "summary",
                    "the log has no summary section, so it cannot be read by time (re-write it \
                     with an indexed MCAP writer)",
                )
            })?;
        let mut chunks = summary.chunk_indexes.clone();
        chunks.sort_by_key(|c| c.chunk_start_offset);
        let mut topics: BTreeMap<String, TopicInfo> = BTreeMap::new();
        let mut by_id: HashMap<u16, String> = HashMap::new();
        for channel in summary.channels.values() {
            let (schema_name, schema_encoding) = match &channel.schema {
                Some(s) => (s.name.clone(), s.encoding.clone()),
                None => (String::new(), String::new()),
            };
            by_id.insert(channel.id, channel.topic.clone());
            topics.insert(
                channel.topic.clone(),
                TopicInfo {
                    topic: channel.topic.clone(),
                    schema_name,
                    schema_encoding,
                    message_encoding: channel.message_encoding.clone(),
                    metadata: channel.metadata.clone(),
                    message_count: 0,
                    channel_id: channel.id,
                    locations: Vec::new(),
                },
            );
        }
        for (ci, chunk) in chunks.iter().enumerate() {
            if chunk.message_index_offsets.is_empty() {
                continue;
            }
            let indexes = summary
                .read_message_indexes(&map, chunk)
                .map_err(|e| mcap_error(&path, "message index", e))?;
            for (channel, entries) in indexes {
                let Some(topic) = by_id.get(&channel.id).and_then(|t| topics.get_mut(t)) else {
                    continue;
                };
                topic.locations.extend(entries.iter().map(|e| Location {
                    chunk: ci,
                    rank: 0,
                    offset: e.offset,
                    log_time: e.log_time,
                }));
            }
        }
        for topic in topics.values_mut() {
            // Write order: chunks in file order, then offsets inside a chunk.
            topic.locations.sort_by_key(|l| (l.chunk, l.offset));
            let mut previous = None;
            let mut rank = 0;
            for loc in &mut topic.locations {
                rank = if previous == Some(loc.chunk) {
                    rank + 1
                } else {
                    0
                };
                loc.rank = rank;
                previous = Some(loc.chunk);
            }
            topic.message_count = topic.locations.len();
        }
        let mut reader = LogReader {
            path,
            map,
            summary,
            chunks,
            topics,
            events: HashMap::new(),
        };
        let event_topics: Vec<String> = reader
            .topics
            .values()
            .filter(|t| t.schema_name == SchemaKind::EventBatch.name())
            .map(|t| t.topic.clone())
            .collect();
        for topic in event_topics {
            let index = reader.build_event_index(&topic)?;
            reader.events.insert(topic, index);
        }
        Ok(reader)
    }

    /// The log's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Every channel, by topic.
    pub fn topics(&self) -> &BTreeMap<String, TopicInfo> {
        &self.topics
    }

    /// The channel `topic`, checked to carry protobuf messages of schema `kind`.
    pub fn topic(&self, topic: &str, kind: SchemaKind) -> Result<&TopicInfo> {
        let info = self.topics.get(topic).ok_or_else(|| {
            format_error(
                &self.path,
                topic,
                format!(
                    "channel is missing (the log has {:?})",
                    self.topics.keys().collect::<Vec<_>>()
                ),
            )
        })?;
        if info.schema_name != kind.name() || info.message_encoding != MESSAGE_ENCODING {
            return Err(format_error(
                &self.path,
                topic,
                format!(
                    "expected {} messages encoded as {MESSAGE_ENCODING}, found schema {:?} with \
                     message encoding {:?}",
                    kind.name(),
                    info.schema_name,
                    info.message_encoding
                ),
            ));
        }
        Ok(info)
    }

    /// A metadata record's entries, `None` when the log has no record of that name.
    pub fn metadata(&self, name: &str) -> Result<Option<BTreeMap<String, String>>> {
        for index in &self.summary.metadata_indexes {
            if index.name == name {
                let record = ::mcap::read::metadata(&self.map, index)
                    .map_err(|e| mcap_error(&self.path, name, e))?;
                return Ok(Some(record.metadata));
            }
        }
        Ok(None)
    }

    /// Calls `f(k, data)` for messages `range` of the channel (k counts from `range.start`),
    /// decompressing each chunk involved once; chunks are read in parallel.
    fn read_messages<T: Send>(
        &self,
        info: &TopicInfo,
        range: std::ops::Range<usize>,
        f: impl Fn(usize, &[u8]) -> Result<T> + Sync,
    ) -> Result<Vec<T>> {
        let wanted = &info.locations
            [range.start.min(info.locations.len())..range.end.min(info.locations.len())];
        // Group the wanted messages by chunk: (chunk, first k, first rank, count).
        let mut groups: Vec<(usize, usize, usize, usize)> = Vec::new();
        for (k, loc) in wanted.iter().enumerate() {
            match groups.last_mut() {
                Some(g) if g.0 == loc.chunk => g.3 += 1,
                _ => groups.push((loc.chunk, k, loc.rank, 1)),
            }
        }
        let per_chunk: Vec<Vec<T>> = groups
            .par_iter()
            .map(|&(chunk, k0, first_rank, wanted)| {
                // A chunk streams its records in offset order, so the channel's messages come
                // by rank.
                let mut out = Vec::with_capacity(wanted);
                let mut rank = 0usize;
                self.for_each_message(&self.chunks[chunk], &info.topic, |channel, data| {
                    if channel != info.channel_id {
                        return Ok(true);
                    }
                    if rank >= first_rank {
                        out.push(f(k0 + rank - first_rank, data)?);
                        if out.len() == wanted {
                            return Ok(false);
                        }
                    }
                    rank += 1;
                    Ok(true)
                })?;
                if out.len() != wanted {
                    return Err(format_error(
                        &self.path,
                        &info.topic,
                        format!(
                            "chunk at byte {} holds fewer messages than its index lists",
                            self.chunks[chunk].chunk_start_offset
                        ),
                    ));
                }
                Ok(out)
            })
            .collect::<Result<_>>()?;
        Ok(per_chunk.into_iter().flatten().collect())
    }

    /// Calls `visit(channel id, message data)` for the messages of a chunk in file order until
    /// it returns `Ok(false)`.
    ///
    /// The chunk is streamed through the `mcap` crate's sans-io reader with a record length
    /// limit: no record inside a chunk can be longer than the chunk's uncompressed size, and a
    /// damaged length field must give an error, not an allocation of that size (the crate's
    /// `Summary::stream_chunk` sets no limit; the `mcap` fuzz target found the abort).
    fn for_each_message(
        &self,
        chunk: &ChunkIndex,
        topic: &str,
        mut visit: impl FnMut(u16, &[u8]) -> Result<bool>,
    ) -> Result<()> {
        let start = usize::try_from(chunk.chunk_start_offset).ok();
        let end = chunk
            .chunk_start_offset
            .checked_add(chunk.chunk_length)
            .and_then(|e| usize::try_from(e).ok());
        let bytes = match (start, end) {
            (Some(a), Some(b)) if a < b && b <= self.map.len() => &self.map[a..b],
            _ => {
                return Err(format_error(
                    &self.path,
                    topic,
                    format!(
                        "the index places a chunk at bytes {}..+{} of a {}-byte file",
                        chunk.chunk_start_offset,
                        chunk.chunk_length,
                        self.map.len()
                    ),
                ))
            }
        };
        if let Some(message) = uncompressed_chunk_overrun(bytes) {
            return Err(format_error(
                &self.path,
                topic,
                format!("chunk at byte {}: {message}", chunk.chunk_start_offset),
            ));
        }
        let inner_limit = usize::try_from(chunk.uncompressed_size)
            .unwrap_or(usize::MAX)
            .min(MAX_RECORD_BYTES);
        let options = LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_validate_chunk_crcs(true)
            .with_record_length_limit(inner_limit.max(bytes.len()));
        let mut reader = LinearReader::new_with_options(options);
        let mut rest = bytes;
        while let Some(event) = reader.next_event() {
            match event.map_err(|e| mcap_error(&self.path, topic, e))? {
                LinearReadEvent::ReadRequest(need) => {
                    let n = need.min(rest.len());
                    reader.insert(n).copy_from_slice(&rest[..n]);
                    reader.notify_read(n);
                    rest = &rest[n..];
                }
                LinearReadEvent::Record { data, opcode } => {
                    if opcode != ::mcap::records::op::MESSAGE {
                        continue;
                    }
                    if let ::mcap::records::Record::Message { header, data } =
                        ::mcap::parse_record(opcode, data)
                            .map_err(|e| mcap_error(&self.path, topic, e))?
                    {
                        if !visit(header.channel_id, &data)? {
                            return Ok(());
                        }
                    }
                }
            }
        }
        Ok(())
    }

    fn decode<T>(&self, topic: &str, k: usize, r: std::result::Result<T, String>) -> Result<T> {
        r.map_err(|m| format_error(&self.path, topic, format!("message {k}: {m}")))
    }

    /// Log times (ns) of every message of a channel, in write order.
    pub fn log_times(&self, topic: &str, kind: SchemaKind) -> Result<Vec<i64>> {
        let info = self.topic(topic, kind)?;
        Ok(info
            .locations
            .iter()
            .map(|l| i64::try_from(l.log_time).unwrap_or(i64::MAX))
            .collect())
    }

    /// Images `range` of a `foxglove.RawImage` channel.
    pub fn images(&self, topic: &str, range: std::ops::Range<usize>) -> Result<Vec<RawImage>> {
        let info = self.topic(topic, SchemaKind::RawImage)?;
        self.read_messages(info, range.clone(), |k, data| {
            self.decode(topic, range.start + k, RawImage::decode(data))
        })
    }

    /// Images `range` of a `foxglove.CompressedImage` channel (still compressed).
    pub fn compressed_images(
        &self,
        topic: &str,
        range: std::ops::Range<usize>,
    ) -> Result<Vec<CompressedImage>> {
        let info = self.topic(topic, SchemaKind::CompressedImage)?;
        self.read_messages(info, range.clone(), |k, data| {
            self.decode(topic, range.start + k, CompressedImage::decode(data))
        })
    }

    /// Every message of a `foxglove.PoseInFrame` channel.
    pub fn poses(&self, topic: &str) -> Result<Vec<PoseInFrame>> {
        let info = self.topic(topic, SchemaKind::PoseInFrame)?;
        self.read_messages(info, 0..info.message_count, |k, data| {
            self.decode(topic, k, PoseInFrame::decode(data))
        })
    }

    /// Every message of a `foxglove.CameraCalibration` channel.
    pub fn calibrations(&self, topic: &str) -> Result<Vec<CameraCalibration>> {
        let info = self.topic(topic, SchemaKind::CameraCalibration)?;
        self.read_messages(info, 0..info.message_count, |k, data| {
            self.decode(topic, k, CameraCalibration::decode(data))
        })
    }

    /// Every message of a `foxglove.PointCloud` channel.
    pub fn point_clouds(&self, topic: &str) -> Result<Vec<PointCloud>> {
        let info = self.topic(topic, SchemaKind::PointCloud)?;
        self.read_messages(info, 0..info.message_count, |k, data| {
            self.decode(topic, k, PointCloud::decode(data))
        })
    }

    // -- events --------------------------------------------------------------------------------

    fn build_event_index(&self, topic: &str) -> Result<EventIndex> {
        let info = self.topic(topic, SchemaKind::EventBatch)?;
        let batch_events: usize = info
            .metadata
            .get(BATCH_EVENTS_KEY)
            .and_then(|v| v.parse().ok())
            .filter(|&b| b > 0)
            .ok_or_else(|| {
                format_error(
                    &self.path,
                    topic,
                    format!("channel metadata lacks a positive integer {BATCH_EVENTS_KEY:?}"),
                )
            })?;
        let n = info.message_count;
        if n == 0 {
            return Ok(EventIndex {
                batch_events,
                count: 0,
                t_first_ns: 0,
                t_last_ns: 0,
            });
        }
        // Batches are found by a binary search over their log times: those must not decrease.
        if let Some(b) = info
            .locations
            .windows(2)
            .position(|w| w[1].log_time < w[0].log_time)
        {
            return Err(format_error(
                &self.path,
                topic,
                format!(
                    "event batch {} is logged at {} ns, before batch {b} ({} ns)",
                    b + 1,
                    info.locations[b + 1].log_time,
                    info.locations[b].log_time
                ),
            ));
        }
        let last = self.event_batches(topic, info, batch_events, n - 1..n)?;
        let last = last.into_iter().next().unwrap_or_default();
        let count = (n - 1) * batch_events + last.len();
        Ok(EventIndex {
            batch_events,
            count,
            t_first_ns: i64::try_from(info.locations[0].log_time).unwrap_or(i64::MAX),
            t_last_ns: last.t_ns.last().copied().unwrap_or(0),
        })
    }

    /// Decodes batches `range`, checking their place in the stream and their size.
    fn event_batches(
        &self,
        topic: &str,
        info: &TopicInfo,
        batch_events: usize,
        range: std::ops::Range<usize>,
    ) -> Result<Vec<EventColumns>> {
        let n = info.message_count;
        self.read_messages(info, range.clone(), |k, data| {
            let b = range.start + k;
            let batch = self.decode(topic, b, decode_event_batch(data))?;
            let full = b + 1 < n;
            let len = batch.events.len();
            if batch.first_index != (b * batch_events) as u64
                || (full && len != batch_events)
                || len == 0
                || len > batch_events
            {
                return Err(format_error(
                    &self.path,
                    topic,
                    format!(
                        "event batch {b} starts at event {} with {len} events; expected event {} \
                         and {} events",
                        batch.first_index,
                        b * batch_events,
                        if full {
                            batch_events.to_string()
                        } else {
                            format!("1..={batch_events}")
                        }
                    ),
                ));
            }
            // The index's log time is the batch's first event time (what the time searches
            // rely on), and times never decrease inside a batch.
            let log_time = info.locations[b].log_time;
            let t = &batch.events.t_ns;
            if u64::try_from(t[0]).ok() != Some(log_time) {
                return Err(format_error(
                    &self.path,
                    topic,
                    format!(
                        "event batch {b} is logged at {log_time} ns but its first event is at {} ns",
                        t[0]
                    ),
                ));
            }
            if let Some(k) = t.windows(2).position(|w| w[1] < w[0]) {
                return Err(format_error(
                    &self.path,
                    topic,
                    format!(
                        "event batch {b}: times decrease at event {} ({} ns after {} ns)",
                        b * batch_events + k + 1,
                        t[k + 1],
                        t[k]
                    ),
                ));
            }
            Ok(batch.events)
        })
    }

    fn event_index(&self, topic: &str) -> Result<&EventIndex> {
        match self.events.get(topic) {
            Some(index) => Ok(index),
            None => self.topic(topic, SchemaKind::EventBatch).and_then(|_| {
                Err(format_error(
                    &self.path,
                    topic,
                    "event channel was not indexed",
                ))
            }),
        }
    }

    /// Number of events of an event channel.
    pub fn event_count(&self, topic: &str) -> Result<usize> {
        Ok(self.event_index(topic)?.count)
    }

    /// Half-open span `[first, last + 1)` of the channel's event times, ns; `(0, 0)` if empty.
    pub fn event_time_range(&self, topic: &str) -> Result<(i64, i64)> {
        let e = self.event_index(topic)?;
        Ok(if e.count == 0 {
            (0, 0)
        } else {
            (e.t_first_ns, e.t_last_ns.saturating_add(1))
        })
    }

    /// First event index with `t >= t_ns` (the event count when none), decoding one batch.
    pub fn event_lower_bound(&self, topic: &str, t_ns: i64) -> Result<usize> {
        let index = self.event_index(topic)?;
        if index.count == 0 || t_ns <= index.t_first_ns {
            return Ok(0);
        }
        if t_ns > index.t_last_ns {
            return Ok(index.count);
        }
        let info = &self.topics[topic];
        // Batches are sorted by their first event's time (the log time): the answer lies in
        // the last batch starting before t_ns, or at the start of the next one.
        let v = t_ns as u64;
        let k = info.locations.partition_point(|l| l.log_time < v);
        let b = k.saturating_sub(1);
        let batch = self.event_batches(topic, info, index.batch_events, b..b + 1)?;
        let within = batch
            .first()
            .map(|e| e.t_ns.partition_point(|&t| t < t_ns))
            .unwrap_or(0);
        Ok((b * index.batch_events + within).min(index.count))
    }

    /// Indices `[i0, i1)` of the events with `t0_ns <= t < t1_ns`.
    pub fn event_index_range(&self, topic: &str, t0_ns: i64, t1_ns: i64) -> Result<(usize, usize)> {
        if t1_ns <= t0_ns {
            self.event_index(topic)?;
            return Ok((0, 0));
        }
        let i0 = self.event_lower_bound(topic, t0_ns)?;
        let i1 = self.event_lower_bound(topic, t1_ns)?;
        Ok((i0, i1.max(i0)))
    }

    /// Events `[i0, i1)` of an event channel (clamped to the stream), decoding only the batches
    /// that hold them.
    pub fn event_slice(&self, topic: &str, i0: usize, i1: usize) -> Result<EventColumns> {
        let index = self.event_index(topic)?.clone();
        let i1 = i1.min(index.count);
        if i1 <= i0 {
            return Ok(EventColumns::default());
        }
        let b = index.batch_events;
        let info = &self.topics[topic];
        let batches = self.event_batches(topic, info, b, i0 / b..(i1 - 1) / b + 1)?;
        let mut out = EventColumns {
            x: Vec::with_capacity(i1 - i0),
            y: Vec::with_capacity(i1 - i0),
            t_ns: Vec::with_capacity(i1 - i0),
            p: Vec::with_capacity(i1 - i0),
        };
        let first_batch = i0 / b;
        for (k, batch) in batches.iter().enumerate() {
            let base = (first_batch + k) * b;
            let lo = i0.saturating_sub(base).min(batch.len());
            let hi = (i1 - base).min(batch.len());
            out.x.extend_from_slice(&batch.x[lo..hi]);
            out.y.extend_from_slice(&batch.y[lo..hi]);
            out.t_ns.extend_from_slice(&batch.t_ns[lo..hi]);
            out.p.extend_from_slice(&batch.p[lo..hi]);
        }
        Ok(out)
    }

    /// The events with `t0_ns <= t < t1_ns`.
    pub fn event_window(&self, topic: &str, t0_ns: i64, t1_ns: i64) -> Result<EventColumns> {
        let (i0, i1) = self.event_index_range(topic, t0_ns, t1_ns)?;
        self.event_slice(topic, i0, i1)
    }
}
