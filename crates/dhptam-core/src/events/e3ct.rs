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

use super::window::EventSlice;
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

    fn check(&self) -> Result<()> {
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

/// Bytes of output one band of rows may span: a band stays in the core's L2 cache (2 MiB on
/// the machines measured, with room for the streamed event lists) while its events are added;
/// the whole image, 11 MB at 1280×720×3, does not.
const BAND_BYTES: usize = 512 * 1024;

/// Fewest events per chunk of the first pass: smaller windows do not pay for a second thread.
const MIN_CHUNK_EVENTS: usize = 1 << 14;

/// One event after the bucket pass: its first output value inside its band, lower channel
/// and polarity group included (low 32 bits), and the index of its time stamp in its chunk's
/// table of votes (high 32 bits).
type Packed = u64;

/// Scratch memory of [`e3ct_into`], kept between windows so that a stream of windows does not
/// fault in fresh pages for every one (page faults cost more than the accumulation itself).
#[derive(Debug, Default)]
pub struct E3ctWorkspace {
    /// Every event of the window as a [`Packed`], grouped by band, then by chunk, each group
    /// in input order (a stable counting sort).
    packed: Vec<Packed>,
    /// Per chunk: the votes `[V1 (1 − f), V1 f]` of each distinct time stamp, in order.
    votes: Vec<Vec<[f32; 2]>>,
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
/// cameras stamp in µs, so a busy window has tens of events per stamp) and distributes its
/// events by a stable counting sort into bands of rows, each band small enough to stay in the
/// L2 cache. (2) Each band adds the votes of its events, those of chunk 0 first, then chunk 1,
/// …, into its rows: the writes hit cache instead of the whole image in memory. Every pixel
/// thus receives its events in input order whatever the thread count, which makes the `f32`
/// sums bit-identical.
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

/// [`e3ct()`] writing into `out` (`height × width × C` values, overwritten) with reusable
/// scratch memory; results are identical.
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
    events.validate(width, height, t_start_ns, t_end_ns)?;
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
    let rows_per_band = (BAND_BYTES / (4 * row_values).max(1)).clamp(1, h.max(1));
    if n == 0 || row_values == 0 {
        out.fill(0.0);
        return Ok(());
    }
    let band_values = rows_per_band * row_values;
    if u32::try_from(band_values).is_err() || u32::try_from(n).is_err() {
        return Err(Error::invalid(
            "events",
            "fewer than 2³² events in one window and image rows of fewer than 2³² values",
            n,
        ));
    }
    let kernel = Kernel::new(params, t_start_ns, t_end_ns);
    let off_offset = match params.polarity {
        PolarityMode::Both => 0,
        PolarityMode::Split => params.channels as u64,
    };
    let bands = h.div_ceil(rows_per_band);
    // Band of each row (high 32 bits) and the offset of the row's first value inside its
    // band (low 32 bits).
    let row_place: Vec<u64> = (0..h)
        .map(|r| (((r / rows_per_band) as u64) << 32) | ((r % rows_per_band) * row_values) as u64)
        .collect();
    let threads = rayon::current_num_threads();
    let chunk_len = n.div_ceil(threads).max(MIN_CHUNK_EVENTS);
    let n_chunks = n.div_ceil(chunk_len);
    let chunk_range = |k: usize| k * chunk_len..((k + 1) * chunk_len).min(n);

    // Pass 0: events per (chunk, band).
    let counts: Vec<Vec<usize>> = (0..n_chunks)
        .into_par_iter()
        .map(|k| {
            let mut count = vec![0usize; bands];
            for &y in &events.y[chunk_range(k)] {
                count[(row_place[usize::from(y)] >> 32) as usize] += 1;
            }
            count
        })
        .collect();
    // Slots of the packed list: band-major, chunk-minor, so that each band's events are
    // contiguous and in input order.
    let E3ctWorkspace { packed, votes } = workspace;
    if packed.capacity() < n {
        // Fresh zeroed pages (no fill pass); pass 1 writes every slot.
        *packed = vec![0; n];
    } else {
        packed.resize(n, 0);
    }
    votes.resize_with(n_chunks.max(votes.len()), Vec::new);
    let mut lengths = Vec::with_capacity(bands * n_chunks);
    for b in 0..bands {
        lengths.extend(counts.iter().map(|count| count[b]));
    }
    let mut pieces = split_at_lengths(packed.as_mut_slice(), &lengths);
    // Regroup the pieces chunk-major for pass 1 (each chunk writes its own pieces), keeping
    // the band-major order of the slices for pass 2.
    let mut per_chunk: Vec<Vec<&mut [Packed]>> = (0..n_chunks).map(|_| Vec::new()).collect();
    for (index, piece) in pieces.drain(..).enumerate() {
        per_chunk[index % n_chunks].push(piece);
    }
    // Pass 1: votes per distinct stamp, and the counting sort of the events into bands.
    per_chunk
        .par_iter_mut()
        .zip(votes[..n_chunks].par_iter_mut())
        .enumerate()
        .for_each(|(k, (band_pieces, table))| {
            let range = chunk_range(k);
            table.clear();
            // Write cursor of each band piece of this chunk.
            let mut cursors: Vec<*mut Packed> =
                band_pieces.iter_mut().map(|p| p.as_mut_ptr()).collect();
            let mut last_t = i64::MIN;
            let mut lower = 0u64;
            let (xs, ys) = (&events.x[range.clone()], &events.y[range.clone()]);
            let (ts, ps) = (&events.t_ns[range.clone()], &events.p[range]);
            for (((&x, &y), &t), &p) in xs.iter().zip(ys).zip(ts).zip(ps) {
                if t != last_t {
                    let (i, w0, w1) = kernel.weights(t);
                    table.push([w0, w1]);
                    // The stamp's index goes to the high half of every packed event.
                    lower = (((table.len() - 1) as u64) << 32) | i as u64;
                    last_t = t;
                }
                let place = row_place[usize::from(y)];
                let band = (place >> 32) as usize;
                let polarity = if p == 0 { off_offset } else { 0 };
                let local = (place & 0xFFFF_FFFF) + u64::from(x) * c as u64 + polarity;
                // SAFETY: pass 0 counted this chunk's events of every band and the band's
                // piece has exactly that length; each event advances its band's cursor once,
                // so every write lands inside the piece (y < height was validated, so `band`
                // indexes `cursors`).
                unsafe {
                    let cursor = cursors.get_unchecked_mut(band);
                    cursor.write(lower + local);
                    *cursor = cursor.add(1);
                }
            }
        });
    // Pass 2: each band adds its events' votes into its rows, chunk after chunk.
    let mut band_lists: Vec<&[Packed]> = Vec::with_capacity(bands * n_chunks);
    let mut start = 0;
    for &len in &lengths {
        band_lists.push(&packed[start..start + len]);
        start += len;
    }
    let votes = &votes[..n_chunks];
    out.par_chunks_mut(band_values)
        .zip(band_lists.par_chunks(n_chunks))
        .for_each(|(rows, lists)| {
            rows.fill(0.0);
            for (list, table) in lists.iter().zip(votes) {
                accumulate(rows, list, table);
            }
        });
    Ok(())
}

/// Adds the votes of `list` (events of one band from one chunk) into the band's `rows`.
#[inline]
fn accumulate(rows: &mut [f32], list: &[Packed], table: &[[f32; 2]]) {
    for &packed in list {
        let id = (packed >> 32) as usize;
        let at = (packed & 0xFFFF_FFFF) as usize;
        assert!(id < table.len() && at + 1 < rows.len());
        let [w0, w1] = table[id];
        rows[at] += w0;
        rows[at + 1] += w1;
    }
}

/// Splits `data` into consecutive mutable pieces of the given lengths (their sum must not
/// exceed `data.len()`).
fn split_at_lengths<'a, T>(mut data: &'a mut [T], lengths: &[usize]) -> Vec<&'a mut [T]> {
    let mut pieces = Vec::with_capacity(lengths.len());
    for &len in lengths {
        let (head, tail) = std::mem::take(&mut data).split_at_mut(len);
        pieces.push(head);
        data = tail;
    }
    pieces
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
    // Pass 1, per piece and channel: the bit patterns of the non-zero magnitudes, compacted
    // without a branch per value (most values are 0, in no predictable pattern), their
    // histogram, and whether any value is not finite.
    struct Found {
        hist: Vec<u64>,
        lists: Vec<Vec<u32>>,
        non_finite: bool,
        scratch: Vec<u32>,
    }
    let empty = || Found {
        hist: vec![0; channels * SCALE_BINS],
        lists: Vec::new(),
        non_finite: false,
        scratch: Vec::new(),
    };
    let found = pieces
        .par_iter()
        .fold(empty, |mut found, piece| {
            let pixels = piece.len() / channels;
            found.scratch.resize(pixels, 0);
            for ch in 0..channels {
                let mut kept = 0;
                let mut bad = false;
                for (k, &v) in piece[ch..].iter().step_by(channels).enumerate() {
                    let bits = v.to_bits() & 0x7FFF_FFFF;
                    bad |= bits >= 0x7F80_0000;
                    // Written unconditionally, kept by advancing past it (kept ≤ k < pixels).
                    found.scratch[kept.min(k)] = bits;
                    kept += usize::from(bits != 0);
                }
                found.non_finite |= bad;
                let list = found.scratch[..kept].to_vec();
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
    // Pass 2: the magnitudes (as bits) of the wanted bin of every channel.
    let gathered: Vec<Vec<u32>> = (0..channels)
        .into_par_iter()
        .map(|ch| match wanted[ch] {
            Some((bin, _)) => found
                .lists
                .iter()
                .skip(ch)
                .step_by(channels)
                .flat_map(|list| list.iter().copied())
                .filter(|bits| bits >> SCALE_BIN_SHIFT == bin)
                .collect(),
            None => Vec::new(),
        })
        .collect();
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
