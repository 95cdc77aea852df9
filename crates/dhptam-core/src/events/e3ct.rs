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

/// Bytes of output one band of rows may span, so that a band stays in the L2 cache while its
/// events are added (the whole image, 11 MB at 1280×720×3, does not).
const BAND_BYTES: usize = 192 * 1024;

/// One event after the bucket pass: its first output value inside its band (low 32 bits) and
/// the index of its weights in its chunk's weight table (high 32 bits).
type Packed = u64;

/// What the bucket pass produces for one chunk of the input: the weights `(i, V1 (1 − f),
/// V1 f)` of each distinct time stamp, and the chunk's events per band.
#[derive(Debug, Default)]
struct Chunk {
    weights: Vec<(u32, f32, f32)>,
    per_band: Vec<Vec<Packed>>,
}

/// The E3CT of one window: a `height × width × C` image (channel fastest, `C` from
/// [`E3ctParams::output_channels`]), not normalised (see [`channel_scales`]).
///
/// The window is validated first (see [`EventSlice::validate`]): pixels outside the image,
/// polarities other than 0/1, times outside `[t_start_ns, t_end_ns)` or decreasing times are
/// [`Error::InvalidInput`] naming the first offending event. An empty window gives zeros.
///
/// On one rayon thread the events are added straight into the image, in input order. On
/// more, two passes, both parallel. (1) The input is cut into one chunk per thread; each chunk
/// computes the weights once per distinct time stamp (event cameras stamp in µs, so a busy
/// window has tens of events per stamp) into its own table and distributes its events, in
/// order, into per-band lists. (2) Each band of rows (small enough to stay in cache) reads the
/// lists of chunk 0, 1, … in turn and adds the weights. Every pixel thus receives its events
/// in input order whatever the thread count, which makes the `f32` sums bit-identical.
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

/// Scratch memory of [`e3ct_into`], kept between windows so that a stream of windows does not
/// fault in fresh pages for every one (page faults cost more than the accumulation itself).
#[derive(Debug, Default)]
pub struct E3ctWorkspace {
    chunks: Vec<Chunk>,
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
    if u32::try_from(n).is_err() {
        return Err(Error::invalid(
            "events",
            "fewer than 2³² events in one window",
            n,
        ));
    }
    let kernel = Kernel::new(params, t_start_ns, t_end_ns);
    let off_offset = match params.polarity {
        PolarityMode::Both => 0,
        PolarityMode::Split => params.channels,
    };
    let threads = rayon::current_num_threads();
    if threads == 1 {
        // One pass straight into the image: on one core the bucket sort costs more than the
        // cache misses it saves. Same order of additions per pixel, so the same bits.
        out.fill(0.0);
        let mut last_t = i64::MIN;
        let mut weights = (0usize, 0f32, 0f32);
        for k in 0..n {
            let t = events.t_ns[k];
            if t != last_t {
                weights = kernel.weights(t);
                last_t = t;
            }
            let polarity = if events.p[k] == 0 { off_offset } else { 0 };
            let at = (usize::from(events.y[k]) * w + usize::from(events.x[k])) * c
                + polarity
                + weights.0;
            out[at] += weights.1;
            out[at + 1] += weights.2;
        }
        return Ok(());
    }
    let row_values = w * c;
    let rows_per_band = (BAND_BYTES / (4 * row_values)).clamp(1, h);
    let bands = h.div_ceil(rows_per_band);
    // Band of each row and the offset of the row's first value inside its band.
    let row_place: Vec<(u32, u32)> = (0..h)
        .map(|r| {
            (
                (r / rows_per_band) as u32,
                ((r % rows_per_band) * row_values) as u32,
            )
        })
        .collect();
    let chunk_len = n.div_ceil(threads).max(1 << 12);
    let n_chunks = n.div_ceil(chunk_len);
    let chunks = &mut workspace.chunks;
    chunks.resize_with(n_chunks.max(chunks.len()), Chunk::default);
    chunks[..n_chunks]
        .par_iter_mut()
        .enumerate()
        .for_each(|(index, chunk)| {
            let range = index * chunk_len..((index + 1) * chunk_len).min(n);
            chunk.weights.clear();
            chunk.per_band.resize_with(bands, Vec::new);
            chunk.per_band.truncate(bands);
            // Exact list sizes first: over-allocating would fault in pages never used.
            let mut counts = vec![0usize; bands];
            for &y in &events.y[range.clone()] {
                counts[row_place[usize::from(y)].0 as usize] += 1;
            }
            for (list, &k) in chunk.per_band.iter_mut().zip(&counts) {
                list.clear();
                list.reserve_exact(k);
            }
            let mut last_t = i64::MIN;
            for k in range {
                let t = events.t_ns[k];
                if t != last_t {
                    let (i, w0, w1) = kernel.weights(t);
                    chunk.weights.push((i as u32, w0, w1));
                    last_t = t;
                }
                let (band, row_offset) = row_place[usize::from(events.y[k])];
                let polarity = if events.p[k] == 0 { off_offset } else { 0 };
                let local = row_offset as usize + usize::from(events.x[k]) * c + polarity;
                let id = (chunk.weights.len() - 1) as u64;
                chunk.per_band[band as usize].push((id << 32) | local as u64);
            }
        });
    let chunks = &workspace.chunks[..n_chunks];
    out.par_chunks_mut(rows_per_band * row_values)
        .enumerate()
        .for_each(|(band, rows)| {
            rows.fill(0.0);
            for chunk in chunks {
                for &packed in &chunk.per_band[band] {
                    let (i, w0, w1) = chunk.weights[(packed >> 32) as usize];
                    let at = (packed & 0xFFFF_FFFF) as usize + i as usize;
                    rows[at] += w0;
                    rows[at + 1] += w1;
                }
            }
        });
    Ok(())
}

/// Normalisation scale of each of `channels` channels: the `percentile`-th percentile
/// (nearest rank) of the channel's non-zero values, pooled over all `tensors`.
///
/// Pass the left and right E3CT of one stereo window together and apply the result to both
/// with [`apply_scales`]: the same scale for the same channel keeps their colours equal.
/// Only non-zero values count because most pixels see no event in a short window; a
/// percentile over all pixels would be 0. A channel without any non-zero value gets scale 1
/// (it stays 0).
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
        if let Some(i) = t.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                format!("tensors[{k}][{i}]"),
                "a finite value",
                t[i],
            ));
        }
    }
    Ok((0..channels)
        .into_par_iter()
        .map(|ch| {
            let mut values: Vec<f32> = tensors
                .iter()
                .flat_map(|t| t.iter().skip(ch).step_by(channels))
                .copied()
                .filter(|&v| v != 0.0)
                .map(f32::abs)
                .collect();
            if values.is_empty() {
                return 1.0;
            }
            let rank = ((percentile / 100.0 * values.len() as f64).ceil() as usize)
                .clamp(1, values.len())
                - 1;
            let (_, &mut scale, _) = values.select_nth_unstable_by(rank, f32::total_cmp);
            scale
        })
        .collect())
}

/// Divides each channel by its scale and clips to `[0, 1]`, in place.
pub fn apply_scales(tensor: &mut [f32], scales: &[f32]) -> Result<()> {
    let c = scales.len();
    if let Some(i) = scales.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(Error::invalid(
            format!("scales[{i}]"),
            "a positive finite scale",
            scales[i],
        ));
    }
    if c == 0 || tensor.len() % c != 0 {
        return Err(Error::invalid(
            "tensor",
            format!("a multiple of {c} values (one scale per channel)"),
            format!("{} values", tensor.len()),
        ));
    }
    let inv: Vec<f32> = scales.iter().map(|s| 1.0 / s).collect();
    tensor.par_chunks_mut(c * 4096).for_each(|block| {
        for pixel in block.chunks_exact_mut(c) {
            for (v, k) in pixel.iter_mut().zip(&inv) {
                *v = (*v * k).clamp(0.0, 1.0);
            }
        }
    });
    Ok(())
}
