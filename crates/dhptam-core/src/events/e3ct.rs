//! The Event 3-Channel Tensor (E3CT) of DH-PTAM (paper eqs. 3–4, SPEC-NOTES §3).
//!
//! For a window `[t_s, t_e)` of `Δ = t_e − t_s` nanoseconds and `B` channels (3 in the paper),
//! an event `(x, y, t, p)` adds to pixel `(x, y)`:
//!
//! ```text
//! a    = (t_e − t) / 1 ms                       age of the event at the end of the window
//! V1   = exp(−α ((a − η/2) / (η/6))²)           decay kernel, α = 0.5, η = 30 ms
//! τ    = (t − t_s) / Δ ∈ [0, 1)                 normalised time inside the window
//! s    = τ (B − 1),  i = ⌊s⌋,  f = s − i
//! E[y, x, i]     += V1 (1 − f)                  trilinear (tent) temporal voting:
//! E[y, x, i + 1] += V1 f                        max(0, 1 − |s − j|) for channel j
//! ```
//!
//! The age counts from the end of the window (the fusion time t_f): the kernel then weighs
//! an event by how long before the fused frame it fired, the same way for every window
//! length; `docs/E3CT.md` gives the full reasoning. Both polarities add to the same channels
//! ([`PolarityMode::Both`]); [`PolarityMode::Split`] keeps ON events in channels `0..B` and
//! OFF events in `B..2B`, for ablations.
//!
//! [`channel_scales`] and [`apply_scales`] normalise each channel to `[0, 1]` by a high
//! percentile of its non-zero values; computing the scales once over the left and right
//! tensors together and applying them to both keeps the synthetic colours of the two cameras
//! identical for the same scene.
//!
//! Determinism: accumulation in `f32` depends on the order of the additions, so every pixel
//! receives its events in input (time) order, whatever the number of threads (see [`e3ct()`]
//! for how: on several threads a stable bucket sort into bands of rows, then one task per
//! band).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::window::{check_frame, EventSlice};
use crate::config::EventsConfig;
use crate::error::{Error, Result};

/// How polarities map to channels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PolarityMode {
    /// ON and OFF events add to the same `B` channels (the paper's E3CT).
    Both,
    /// ON events (p = 1) fill channels `0..B`, OFF events (p = 0) channels `B..2B`.
    Split,
}

/// Parameters of the E3CT.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct E3ctParams {
    /// Sharpness α of the decay kernel (0.5 in the paper).
    pub alpha: f64,
    /// Span η of the decay kernel, milliseconds (30 in the paper): the kernel peaks at an age
    /// of η/2 with standard deviation η/6 (for α = 0.5).
    pub eta_ms: f64,
    /// Temporal channels B per polarity group (3 in the paper), at least 2.
    pub channels: usize,
    /// Whether polarities share channels or get their own.
    pub polarity: PolarityMode,
}

impl Default for E3ctParams {
    fn default() -> Self {
        Self::from(&EventsConfig::default())
    }
}

impl From<&EventsConfig> for E3ctParams {
    fn from(config: &EventsConfig) -> Self {
        Self {
            alpha: config.alpha,
            eta_ms: config.eta_ms,
            channels: config.channels as usize,
            polarity: config.polarity,
        }
    }
}

impl E3ctParams {
    /// Channels of the output image: `B`, or `2B` with [`PolarityMode::Split`].
    pub fn output_channels(&self) -> usize {
        match self.polarity {
            PolarityMode::Both => self.channels,
            PolarityMode::Split => 2 * self.channels,
        }
    }

    pub(crate) fn check(&self) -> Result<()> {
        if !(self.alpha.is_finite() && self.alpha > 0.0) {
            return Err(Error::invalid("alpha", "a positive number", self.alpha));
        }
        if !(self.eta_ms.is_finite() && self.eta_ms > 0.0) {
            return Err(Error::invalid(
                "eta_ms",
                "a positive span in milliseconds",
                self.eta_ms,
            ));
        }
        if !(2..=64).contains(&self.channels) {
            return Err(Error::invalid(
                "channels",
                "between 2 and 64 temporal channels",
                self.channels,
            ));
        }
        Ok(())
    }
}

/// The per-event weights: decay kernel and temporal voting, for one window.
struct Kernel {
    t_start_ns: i64,
    t_end_ns: i64,
    span_ns: f64,
    alpha: f64,
    half_eta_ms: f64,
    inv_sigma_ms: f64,
    last_bin: f64,
    max_lower: usize,
}

impl Kernel {
    fn new(params: &E3ctParams, t_start_ns: i64, t_end_ns: i64) -> Self {
        Self {
            t_start_ns,
            t_end_ns,
            span_ns: (t_end_ns - t_start_ns) as f64,
            alpha: params.alpha,
            half_eta_ms: 0.5 * params.eta_ms,
            inv_sigma_ms: 6.0 / params.eta_ms,
            last_bin: (params.channels - 1) as f64,
            max_lower: params.channels - 2,
        }
    }

    /// `(i, V1 (1 − f), V1 f)` for an event at `t_ns` inside the window.
    #[inline]
    fn weights(&self, t_ns: i64) -> (usize, f32, f32) {
        let age_ms = (self.t_end_ns - t_ns) as f64 * 1e-6;
        let z = (age_ms - self.half_eta_ms) * self.inv_sigma_ms;
        let v1 = (-self.alpha * z * z).exp();
        let s = (t_ns - self.t_start_ns) as f64 / self.span_ns * self.last_bin;
        // τ < 1, so ⌊s⌋ ≤ B − 2; the min guards rounding for windows of months.
        let i = (s as usize).min(self.max_lower);
        let f = s - i as f64;
        (i, (v1 * (1.0 - f)) as f32, (v1 * f) as f32)
    }
}

/// Output values one band of rows may span: 2¹⁶ `f32` (256 KiB). A band then stays in the
/// core's L2 cache while its events are added (the whole image, 11 MB at 1280×720×3, does
/// not), and an event's place inside its band fits the low 16 bits of its [`Packed`] word.
const BAND_VALUES: usize = 1 << 16;

/// Distinct time stamps one [`Segment`] holds: a stamp's index fits the high 16 bits of a
/// [`Packed`] word. A chunk with more stamps (windows longer than 65 ms at µs stamps, or
/// ns stamps) simply fills several segments.
const SEGMENT_STAMPS: usize = 1 << 16;

/// Fewest events per chunk of the first pass: smaller windows do not pay for a second thread.
const MIN_CHUNK_EVENTS: usize = 1 << 14;

/// One event after the first pass: the index of its time stamp in its segment's vote table
/// (high 16 bits) and its first output value inside its band, lower channel and polarity
/// group included (low 16 bits). Four bytes per event, half the memory traffic of a pointer.
type Packed = u32;

/// A run of one chunk's events whose distinct time stamps share one vote table.
#[derive(Debug, Default)]
struct Segment {
    /// `[V1 (1 − f), V1 f]` of each distinct stamp, in order ([`SEGMENT_STAMPS`] slots).
    votes: Vec<[f32; 2]>,
    /// Per band: the segment's events falling into the band, packed, in input order.
    lists: Vec<Vec<Packed>>,
}

/// Events one band gathers in its staging line before they move to the band's list: one
/// 64-byte cache line. Appending to a few dozen lists at once would otherwise miss the cache
/// on most stores; the staging lines stay in L1 and each list receives whole lines.
const STAGE: usize = 16;

/// The first-pass output of one chunk of the input.
#[derive(Debug, Default)]
struct ChunkScratch {
    /// Segments in input order; the first `used` hold this window's events.
    segments: Vec<Segment>,
    /// Segments filled for the current window.
    used: usize,
    /// Per band, the staging line of the current segment and how full it is.
    stage: Vec<[Packed; STAGE]>,
    /// Per band, the number of events in its staging line.
    fill: Vec<usize>,
    /// The first invalid event of the chunk (global index), if any.
    bad: Option<usize>,
}

impl ChunkScratch {
    /// Starts the next segment, emptied, with one list per band; returns its index.
    fn next_segment(&mut self, bands: usize) -> usize {
        if self.used == self.segments.len() {
            self.segments.push(Segment::default());
        }
        let segment = &mut self.segments[self.used];
        self.used += 1;
        segment.votes.resize(SEGMENT_STAMPS, [0.0; 2]);
        segment.lists.resize_with(bands, Vec::new);
        for list in &mut segment.lists {
            list.clear();
        }
        self.used - 1
    }

    /// Moves the staged events of every band to the lists of segment `index`.
    fn flush(&mut self, index: usize) {
        let lists = &mut self.segments[index].lists;
        for ((list, line), fill) in lists.iter_mut().zip(&self.stage).zip(&mut self.fill) {
            list.extend_from_slice(&line[..*fill]);
            *fill = 0;
        }
    }
}

/// Where a segment's filling stands: its stamps so far and the packed stamp of the last one.
struct Stamps {
    count: usize,
    last_t: i64,
    lower: Packed,
}

impl Stamps {
    fn new() -> Self {
        Self {
            count: 0,
            last_t: i64::MIN,
            lower: 0,
        }
    }
}

/// Events validated and bucketed at a time by one chunk: small enough that the block's
/// arrays are still in the L2 cache when the bucketing reads them after the validation.
const BLOCK_EVENTS: usize = 1 << 14;

/// Scratch memory of [`e3ct_into`], kept between windows so that a stream of windows does not
/// fault in fresh pages for every one (page faults cost more than the accumulation itself).
/// About 4 bytes per event of the largest window served, plus 512 KiB per segment.
#[derive(Debug, Default)]
pub struct E3ctWorkspace {
    /// One per chunk of the first pass.
    chunks: Vec<ChunkScratch>,
}

/// The E3CT of one window: a `height × width × C` image (channel fastest, `C` from
/// [`E3ctParams::output_channels`]), not normalised (see [`channel_scales`]).
///
/// The window is validated first (see [`EventSlice::validate`]): pixels outside the image,
/// polarities other than 0/1, times outside `[t_start_ns, t_end_ns)` or decreasing times are
/// [`Error::InvalidInput`] naming the first offending event. An empty window gives zeros.
///
/// Two passes over the events, on any number of rayon threads. (1) The input is cut into
/// chunks (one per thread); each chunk computes the votes once per distinct time stamp (event
/// cameras stamp in µs, so a busy window has tens of events per stamp) and appends each event,
/// as one 32-bit word, to the list of its band of rows, each band small enough to stay in the
/// L2 cache. (2) Each band adds the votes of its events, those of chunk 0 first, then chunk 1,
/// …, into its rows: the writes hit cache instead of the whole image in memory. Every pixel
/// thus receives its events in input order whatever the thread count, which makes the `f32`
/// sums bit-identical to adding every event straight into the image in input order.
pub fn e3ct(
    events: &EventSlice<'_>,
    width: u32,
    height: u32,
    t_start_ns: i64,
    t_end_ns: i64,
    params: &E3ctParams,
) -> Result<Vec<f32>> {
    let mut out = vec![0f32; width as usize * height as usize * params.output_channels()];
    let mut workspace = E3ctWorkspace::default();
    e3ct_into(
        events,
        width,
        height,
        t_start_ns,
        t_end_ns,
        params,
        &mut workspace,
        &mut out,
    )?;
    Ok(out)
}

/// [`e3ct()`] writing into `out` (`height × width × C` values, every one overwritten, so its
/// previous content does not matter) with reusable scratch memory; results are identical.
#[allow(clippy::too_many_arguments)]
pub fn e3ct_into(
    events: &EventSlice<'_>,
    width: u32,
    height: u32,
    t_start_ns: i64,
    t_end_ns: i64,
    params: &E3ctParams,
    workspace: &mut E3ctWorkspace,
    out: &mut [f32],
) -> Result<()> {
    params.check()?;
    // Two passes. The events are validated against the `width × height` image and the window
    // (see [`EventSlice::validate`]) block by block inside the first pass, while each block is
    // in cache; an invalid event is reported, naming the first one, before `out` is touched.
    let (raw_w, raw_h) = (width, height);
    check_frame(raw_w, raw_h, t_start_ns, t_end_ns)?;
    let (w, h) = (width as usize, height as usize);
    let c = params.output_channels();
    if out.len() != w * h * c {
        return Err(Error::invalid(
            "out",
            format!("{h}×{w}×{c} values"),
            format!("{} values", out.len()),
        ));
    }
    let n = events.len();
    let row_values = w * c;
    if n == 0 || row_values == 0 {
        out.fill(0.0);
        return Ok(());
    }
    let kernel = Kernel::new(params, t_start_ns, t_end_ns);
    let off_offset = match params.polarity {
        PolarityMode::Both => 0,
        PolarityMode::Split => params.channels as u32,
    };
    if row_values > BAND_VALUES {
        // A row wider than a band (over 21,845 pixels at 3 channels): no packed place fits
        // 16 bits; add every event straight into the image in input order (the same sums).
        events.validate(raw_w, raw_h, t_start_ns, t_end_ns)?;
        out.fill(0.0);
        for k in 0..n {
            let (x, y) = (events.x[k], events.y[k]);
            let (i, w0, w1) = kernel.weights(events.t_ns[k]);
            let group = if events.p[k] == 0 { off_offset } else { 0 } as usize;
            let at = (usize::from(y) * w + usize::from(x)) * c + group + i;
            out[at] += w0;
            out[at + 1] += w1;
        }
        return Ok(());
    }
    let rows_per_band = (BAND_VALUES / row_values).clamp(1, h);
    let band_values = rows_per_band * row_values;
    let bands = h.div_ceil(rows_per_band);
    // Band of each row (high 16 bits) and the offset of the row's first value inside its
    // band (low 16 bits; below BAND_VALUES).
    let row_place: Vec<u32> = (0..h)
        .map(|r| (((r / rows_per_band) as u32) << 16) | ((r % rows_per_band) * row_values) as u32)
        .collect();
    let threads = rayon::current_num_threads();
    let chunk_len = n.div_ceil(threads).max(MIN_CHUNK_EVENTS);
    let n_chunks = n.div_ceil(chunk_len);
    let chunks = &mut workspace.chunks;
    chunks.resize_with(n_chunks.max(chunks.len()), ChunkScratch::default);
    let c32 = c as u32;
    // Pass 1, block by block: validation, votes per distinct stamp, and each event appended
    // to its band's list (through the band's staging line).
    chunks[..n_chunks]
        .par_iter_mut()
        .enumerate()
        .for_each(|(k, chunk)| {
            chunk.used = 0;
            chunk.bad = None;
            chunk.stage.resize(bands, [0; STAGE]);
            chunk.fill.clear();
            chunk.fill.resize(bands, 0);
            let range = k * chunk_len..((k + 1) * chunk_len).min(n);
            let mut segment = chunk.next_segment(bands);
            let mut stamps = Stamps::new();
            let mut block = range.start;
            while block < range.end {
                let block_end = (block + BLOCK_EVENTS).min(range.end);
                chunk.bad =
                    events.first_invalid(block..block_end, raw_w, raw_h, t_start_ns, t_end_ns);
                if chunk.bad.is_some() {
                    return;
                }
                let mut from = block;
                loop {
                    let ChunkScratch {
                        segments,
                        stage,
                        fill,
                        ..
                    } = &mut *chunk;
                    from = fill_segment(
                        &mut segments[segment],
                        stage,
                        fill,
                        &mut stamps,
                        events,
                        from..block_end,
                        &kernel,
                        &row_place,
                        move |x, y, p| {
                            let polarity = if p == 0 { off_offset } else { 0 };
                            Some((usize::from(y), u32::from(x) * c32 + polarity))
                        },
                    );
                    if from == block_end {
                        break;
                    }
                    // The segment's vote table is full: its staged events go to its lists.
                    chunk.flush(segment);
                    segment = chunk.next_segment(bands);
                    stamps = Stamps::new();
                }
                block = block_end;
            }
            chunk.flush(segment);
        });
    if let Some(i) = chunks[..n_chunks].iter().find_map(|chunk| chunk.bad) {
        return Err(events.invalid_event(i, raw_w, raw_h, t_start_ns, t_end_ns));
    }
    // Pass 2: each band adds its events' votes into its rows, chunk after chunk.
    let chunks = &chunks[..n_chunks];
    out.par_chunks_mut(band_values)
        .enumerate()
        .for_each(|(band, rows)| {
            rows.fill(0.0);
            for chunk in chunks {
                for segment in &chunk.segments[..chunk.used] {
                    add_votes(rows, &segment.lists[band], &segment.votes);
                }
            }
        });
    Ok(())
}

/// Appends events `range` of `events` to the band lists of `segment` (through the staging
/// lines `stage`, `fill`) until the range ends or the segment's vote table is full; returns
/// the index of the first event not taken. `place(x, y, p)` gives the event's output row and
/// its value offset inside the row (polarity group included), or `None` to drop it.
#[inline]
#[allow(clippy::too_many_arguments)]
fn fill_segment(
    segment: &mut Segment,
    stage: &mut [[Packed; STAGE]],
    fill: &mut [usize],
    stamps: &mut Stamps,
    events: &EventSlice<'_>,
    range: std::ops::Range<usize>,
    kernel: &Kernel,
    row_place: &[u32],
    place: impl Fn(u16, u16, i8) -> Option<(usize, u32)>,
) -> usize {
    let Segment { votes, lists } = segment;
    let Stamps {
        mut count,
        mut last_t,
        mut lower,
    } = *stamps;
    let start = range.start;
    let part = events.sub(range);
    let mut taken = part.len();
    for (k, (((&x, &y), &t), &p)) in part
        .x
        .iter()
        .zip(part.y)
        .zip(part.t_ns)
        .zip(part.p)
        .enumerate()
    {
        if t != last_t {
            if count == SEGMENT_STAMPS {
                taken = k;
                break;
            }
            let (i, w0, w1) = kernel.weights(t);
            votes[count] = [w0, w1];
            // Stamp index in the high half, lower channel in the low half (added to the
            // place below; the sum stays under BAND_VALUES as every channel of the pixel
            // lies inside the band).
            lower = ((count as u32) << 16) | i as u32;
            count += 1;
            last_t = t;
        }
        let Some((row, offset)) = place(x, y, p) else {
            continue;
        };
        let at = row_place[row];
        let band = (at >> 16) as usize;
        let line = &mut stage[band];
        let used = fill[band];
        line[used % STAGE] = lower + (at & 0xFFFF) + offset;
        if used + 1 == STAGE {
            lists[band].extend_from_slice(line);
            fill[band] = 0;
        } else {
            fill[band] = used + 1;
        }
    }
    *stamps = Stamps {
        count,
        last_t,
        lower,
    };
    start + taken
}

/// Adds the votes of `list` (one segment's events of one band) into the band's `rows`.
#[inline]
fn add_votes(rows: &mut [f32], list: &[Packed], votes: &[[f32; 2]]) {
    for &packed in list {
        let [w0, w1] = votes[(packed >> 16) as usize];
        let at = (packed & 0xFFFF) as usize;
        if let Some([a, b]) = rows.get_mut(at..at + 2) {
            *a += w0;
            *b += w1;
        }
    }
}

/// Bits of an `f32` below the first-pass histogram bin of [`channel_scales`]: the bin of a
/// value is its magnitude's top 12 bits (8 of exponent, 4 of mantissa), so one bin spans a
/// sixteenth of an octave, and the integer order of the bit patterns of non-negative floats
/// is the order of their values.
const SCALE_BIN_SHIFT: u32 = 19;
/// Bins per channel of that histogram.
const SCALE_BINS: usize = 1 << (31 - SCALE_BIN_SHIFT);
/// Values per parallel piece of [`channel_scales`] and [`apply_scales`], in whole pixels.
const SCALE_PIECE_PIXELS: usize = 1 << 15;

/// Normalisation scale of each of `channels` channels: the `percentile`-th percentile
/// (nearest rank) of the channel's non-zero values, pooled over all `tensors`.
///
/// Pass the left and right E3CT of one stereo window together and apply the result to both
/// with [`apply_scales`]: the same scale for the same channel keeps their colours equal.
/// Only non-zero values count because most pixels see no event in a short window; a
/// percentile over all pixels would be 0. A channel without any non-zero value gets scale 1
/// (it stays 0). Magnitudes count (the E3CT has no negative value).
///
/// An exact selection without sorting: one parallel pass builds a histogram per channel of
/// the magnitudes' top bits (whose integer order is their order as numbers), which locates
/// the bin holding the wanted rank; a second pass gathers the few values of that bin, among
/// which the rank is selected. A non-finite value is an error naming it.
pub fn channel_scales(tensors: &[&[f32]], channels: usize, percentile: f64) -> Result<Vec<f32>> {
    if channels == 0 {
        return Err(Error::invalid("channels", "at least one channel", 0));
    }
    if !(percentile > 0.0 && percentile <= 100.0) {
        return Err(Error::invalid(
            "percentile",
            "a percentile in (0, 100]",
            percentile,
        ));
    }
    for (k, t) in tensors.iter().enumerate() {
        if t.len() % channels != 0 {
            return Err(Error::invalid(
                format!("tensors[{k}]"),
                format!("a multiple of {channels} values (H × W × {channels})"),
                format!("{} values", t.len()),
            ));
        }
    }
    let pieces: Vec<&[f32]> = tensors
        .iter()
        .flat_map(|t| t.chunks(SCALE_PIECE_PIXELS * channels))
        .collect();
    // Pass 1, per piece: the bit patterns of each channel's non-zero magnitudes, compacted in
    // one pass over the piece without a branch per value ([`compact_piece`]), their
    // histogram, and whether any value is not finite.
    struct Found {
        hist: Vec<u64>,
        lists: Vec<Vec<u32>>,
        non_finite: bool,
        scratch: Vec<u32>,
        kept: Vec<usize>,
    }
    let empty = || Found {
        hist: vec![0; channels * SCALE_BINS],
        lists: Vec::new(),
        non_finite: false,
        scratch: Vec::new(),
        kept: Vec::new(),
    };
    let found = pieces
        .par_iter()
        .fold(empty, |mut found, piece| {
            let pixels = piece.len() / channels;
            found.scratch.resize(pixels * channels, 0);
            found.kept.clear();
            found.kept.resize(channels, 0);
            found.non_finite |= match channels {
                1 => compact_piece::<1>(piece, 1, &mut found.scratch, &mut found.kept),
                2 => compact_piece::<2>(piece, 2, &mut found.scratch, &mut found.kept),
                3 => compact_piece::<3>(piece, 3, &mut found.scratch, &mut found.kept),
                4 => compact_piece::<4>(piece, 4, &mut found.scratch, &mut found.kept),
                6 => compact_piece::<6>(piece, 6, &mut found.scratch, &mut found.kept),
                c => compact_piece::<0>(piece, c, &mut found.scratch, &mut found.kept),
            };
            for (ch, plane) in found.scratch.chunks_exact(pixels.max(1)).enumerate() {
                let list = plane[..found.kept[ch]].to_vec();
                let hist = &mut found.hist[ch * SCALE_BINS..(ch + 1) * SCALE_BINS];
                for &bits in &list {
                    hist[(bits >> SCALE_BIN_SHIFT) as usize] += 1;
                }
                // One list per channel in channel order, so list i is of channel i % C.
                found.lists.push(list);
            }
            found
        })
        .reduce(empty, |mut a, b| {
            a.hist.iter_mut().zip(&b.hist).for_each(|(x, y)| *x += y);
            a.lists.extend(b.lists);
            a.non_finite |= b.non_finite;
            a
        });
    let (hist, non_finite) = (&found.hist, found.non_finite);
    if non_finite {
        for (k, t) in tensors.iter().enumerate() {
            if let Some(i) = t.iter().position(|v| !v.is_finite()) {
                return Err(Error::invalid(
                    format!("tensors[{k}][{i}]"),
                    "a finite value",
                    t[i],
                ));
            }
        }
    }
    // Per channel: the bin holding the nearest rank and the rank inside that bin.
    let wanted: Vec<Option<(u32, usize)>> = hist
        .chunks_exact(SCALE_BINS)
        .map(|bins| {
            let total: u64 = bins.iter().sum();
            if total == 0 {
                return None;
            }
            let rank = ((percentile / 100.0 * total as f64).ceil() as u64).clamp(1, total) - 1;
            let mut below = 0u64;
            for (bin, &count) in bins.iter().enumerate() {
                if below + count > rank {
                    return Some((bin as u32, (rank - below) as usize));
                }
                below += count;
            }
            None
        })
        .collect();
    // Pass 2: the magnitudes (as bits) of the wanted bin of every channel, list by list in
    // parallel (lists are in piece order, list i of channel i % C), then joined per channel.
    let per_list: Vec<Vec<u32>> = found
        .lists
        .par_iter()
        .enumerate()
        .map(|(i, list)| match wanted[i % channels] {
            Some((bin, _)) => list
                .iter()
                .copied()
                .filter(|bits| bits >> SCALE_BIN_SHIFT == bin)
                .collect(),
            None => Vec::new(),
        })
        .collect();
    let mut gathered: Vec<Vec<u32>> = vec![Vec::new(); channels];
    for (i, list) in per_list.into_iter().enumerate() {
        gathered[i % channels].extend(list);
    }
    Ok(wanted
        .iter()
        .zip(gathered)
        .map(|(want, mut bits)| match want {
            // The rank inside the bin is below the bin's count, which `bits` holds exactly.
            Some((_, rank)) if *rank < bits.len() => {
                let (_, &mut scale, _) = bits.select_nth_unstable(*rank);
                f32::from_bits(scale)
            }
            _ => 1.0,
        })
        .collect())
}

/// Pass 1 of [`channel_scales`] on one piece of `c` interleaved channels (`c = C` when
/// `C > 0`, so that the loop over a pixel's channels unrolls): the bit patterns of the
/// non-zero magnitudes of channel `ch` are compacted, in pixel order, to the front of plane
/// `ch` of `scratch` (`c` planes of one value per pixel) and counted in `kept[ch]`; returns
/// whether any value is not finite. One pass over the piece, without a branch per value
/// (most values are 0, in no predictable pattern): every value is written to its plane's
/// next free slot, which only a non-zero value then moves past.
fn compact_piece<const C: usize>(
    piece: &[f32],
    c: usize,
    scratch: &mut [u32],
    kept: &mut [usize],
) -> bool {
    let c = if C > 0 { C } else { c };
    let pixels = piece.len() / c;
    assert!(scratch.len() >= pixels * c && kept.len() == c);
    let mut bad = false;
    for (k, px) in piece.chunks_exact(c).enumerate() {
        for (ch, &v) in px.iter().enumerate() {
            let bits = v.to_bits() & 0x7FFF_FFFF;
            bad |= bits >= 0x7F80_0000;
            let slot = ch * pixels + kept[ch];
            debug_assert!(kept[ch] <= k && k < pixels);
            // SAFETY: kept[ch] counts non-zero values among the k values of the plane before
            // this one, so kept[ch] ≤ k < pixels and the slot lies in plane ch, inside
            // `scratch` (asserted to hold c planes of `pixels` values).
            unsafe { *scratch.get_unchecked_mut(slot) = bits };
            kept[ch] += usize::from(bits != 0);
        }
    }
    bad
}

/// Divides each channel by its scale and clips to `[0, 1]`, in place.
pub fn apply_scales(tensor: &mut [f32], scales: &[f32]) -> Result<()> {
    let inv = inverse_scales(tensor.len(), scales)?;
    let c = scales.len();
    tensor
        .par_chunks_mut(c * SCALE_PIECE_PIXELS)
        .for_each(|block| {
            for pixel in block.chunks_exact_mut(c) {
                for (v, k) in pixel.iter_mut().zip(&inv) {
                    *v = (*v * k).clamp(0.0, 1.0);
                }
            }
        });
    Ok(())
}

/// [`apply_scales`] into a new buffer, leaving `tensor` as it is: one pass instead of a copy
/// and a pass.
pub fn scaled(tensor: &[f32], scales: &[f32]) -> Result<Vec<f32>> {
    let inv = inverse_scales(tensor.len(), scales)?;
    let c = scales.len();
    let mut out = vec![0f32; tensor.len()];
    out.par_chunks_mut(c * SCALE_PIECE_PIXELS)
        .zip(tensor.par_chunks(c * SCALE_PIECE_PIXELS))
        .for_each(|(dst, src)| {
            for (d, s) in dst.chunks_exact_mut(c).zip(src.chunks_exact(c)) {
                for ((d, s), k) in d.iter_mut().zip(s).zip(&inv) {
                    *d = (*s * k).clamp(0.0, 1.0);
                }
            }
        });
    Ok(out)
}

/// `1 / scale` per channel, after checking the scales and the tensor's length.
fn inverse_scales(len: usize, scales: &[f32]) -> Result<Vec<f32>> {
    let c = scales.len();
    if let Some(i) = scales.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(Error::invalid(
            format!("scales[{i}]"),
            "a positive finite scale",
            scales[i],
        ));
    }
    if c == 0 || len % c != 0 {
        return Err(Error::invalid(
            "tensor",
            format!("a multiple of {c} values (one scale per channel)"),
            format!("{len} values"),
        ));
    }
    Ok(scales.iter().map(|s| 1.0 / s).collect())
}
