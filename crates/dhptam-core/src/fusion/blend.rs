//! Online β and the fusion `f(C, D) = (1 − β) C + β D` (paper eq. 6, SPEC-NOTES §4).
//!
//! With `r = mean(C) / max(C)` of the frame:
//!
//! ```text
//! APS-biased (the frame is usable):    β = min(r, 1 − r, aps_β_max)
//! DVS-biased (the frame fails):        β = max(r, 1 − r, dvs_β_min)   ≥ 1/2
//! then β = min(β, β_max)
//! ```
//!
//! `aps_β_max` (`[fusion] aps_beta_max`, 0.3) caps the events' weight in well-exposed
//! frames: uncapped, min(r, 1 − r) is about 0.45 for a typical frame, and the event edges
//! blended in at that weight cost tracking accuracy under normal light (docs/FUSION.md).
//! `dvs_β_min` (`[fusion] dvs_beta_min`, 0.5: the paper's formula) raises the events' weight
//! in failing frames; 1 renders them from their events alone.
//!
//! The frame "fails" when it is under- or over-exposed — more than `dvs_clipped_fraction` of
//! its pixels at or below `dark_level` or at or above `bright_level` — or when the caller
//! reports fewer than `min_features` features detected on it. Modes `frames` and `events` fix
//! β to 0 and 1.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::config::FusionConfig;
use crate::error::{Error, Result};

/// Pixels per parallel piece of [`choose_beta`] and [`fuse_e3ct`].
const BETA_PIECE: usize = 1 << 16;

/// Which images the front-end feeds to the features.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FusionMode {
    /// Frames and events blended with the online β (the paper's default).
    Fusion,
    /// Frames only (β = 0).
    Frames,
    /// Events only (β = 1).
    Events,
}

/// Why β has its value.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Bias {
    /// The frame is usable: β = min(r, 1 − r, aps_β_max).
    Aps,
    /// The frame is under/over-exposed or yields too few features: β = max(r, 1 − r,
    /// dvs_β_min).
    Dvs,
    /// Mode `frames`: β = 0.
    FramesOnly,
    /// Mode `events`: β = 1.
    EventsOnly,
}

impl Bias {
    /// Name used in logs and in Python: "aps", "dvs", "frames", "events".
    pub fn as_str(self) -> &'static str {
        match self {
            Bias::Aps => "aps",
            Bias::Dvs => "dvs",
            Bias::FramesOnly => "frames",
            Bias::EventsOnly => "events",
        }
    }
}

/// The β of one frame with what it was derived from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BetaDecision {
    /// Weight of the events in the fused image, in [0, 1].
    pub beta: f64,
    /// The mode that chose it.
    pub bias: Bias,
    /// `mean(C) / max(C)` (0 for a black frame).
    pub ratio: f64,
    /// Fraction of pixels at or below `dark_level` or at or above `bright_level`.
    pub clipped_fraction: f64,
}

/// Chooses β for an 8-bit frame; `feature_count` is the number of features detected on the
/// frame alone, when known.
pub fn choose_beta(
    frame: &[u8],
    feature_count: Option<usize>,
    config: &FusionConfig,
) -> Result<BetaDecision> {
    if frame.is_empty() {
        return Err(Error::invalid(
            "frame",
            "at least one pixel",
            "an empty image",
        ));
    }
    // The clipping tests as integer bounds (pixels are integers): v < dark_end is dark,
    // v ≥ bright_start is bright. Comparisons with the f64 levels are monotone in v.
    let dark_end = (0..=255u16)
        .take_while(|&v| f64::from(v) <= config.dark_level)
        .count() as u16;
    let bright_start = (0..=255u16)
        .find(|&v| f64::from(v) >= config.bright_level)
        .unwrap_or(256);
    // One pass, parallel over pieces; each piece's loop has no branch and vectorises.
    let (sum, max, clipped) = frame
        .par_chunks(BETA_PIECE)
        .map(|piece| {
            let (mut sum, mut max, mut clipped) = (0u64, 0u8, 0u64);
            for block in piece.chunks(1 << 12) {
                // Per block in u32: 4096 × 255 fits, and u32 lanes vectorise better.
                let (mut s, mut c) = (0u32, 0u32);
                for &v in block {
                    s += u32::from(v);
                    max = max.max(v);
                    let v = u16::from(v);
                    c += u32::from((v < dark_end) | (v >= bright_start));
                }
                sum += u64::from(s);
                clipped += u64::from(c);
            }
            (sum, max, clipped)
        })
        .reduce(|| (0, 0, 0), |a, b| (a.0 + b.0, a.1.max(b.1), a.2 + b.2));
    let n = frame.len() as f64;
    let ratio = if max == 0 {
        0.0
    } else {
        sum as f64 / n / f64::from(max)
    };
    let clipped_fraction = clipped as f64 / n;
    let (beta, bias) = match config.mode {
        FusionMode::Frames => (0.0, Bias::FramesOnly),
        FusionMode::Events => (1.0, Bias::EventsOnly),
        FusionMode::Fusion => {
            let too_few = feature_count.is_some_and(|k| k < config.min_features as usize);
            if too_few || clipped_fraction > config.dvs_clipped_fraction {
                let beta = ratio.max(1.0 - ratio).max(config.dvs_beta_min);
                (beta.min(config.beta_max), Bias::Dvs)
            } else {
                let beta = ratio.min(1.0 - ratio).min(config.aps_beta_max);
                (beta.min(config.beta_max), Bias::Aps)
            }
        }
    };
    log::debug!(
        "fusion: beta = {beta:.3} ({}), r = {ratio:.3}, clipped {clipped_fraction:.3}, features {feature_count:?}",
        bias.as_str()
    );
    Ok(BetaDecision {
        beta,
        bias,
        ratio,
        clipped_fraction,
    })
}

/// The E3CT in the frame's intensity domain: per pixel the largest normalised channel,
/// in [0, 1] (an edge is bright whatever part of the window it fired in).
pub fn intensity_from_e3ct(e3ct: &[f32], channels: usize) -> Result<Vec<f32>> {
    if channels == 0 || e3ct.len() % channels != 0 {
        return Err(Error::invalid(
            "e3ct",
            format!("a multiple of {channels} values"),
            format!("{} values", e3ct.len()),
        ));
    }
    Ok(e3ct
        .chunks_exact(channels)
        .map(|px| px.iter().copied().fold(0.0f32, f32::max).clamp(0.0, 1.0))
        .collect())
}

/// `round((1 − β) C + β · 255 · D)` per pixel: frame `C` (8 bit) blended with the event
/// intensity `D` in [0, 1] (from [`intensity_from_e3ct`] of the warped, normalised E3CT).
pub fn fuse(frame: &[u8], events: &[f32], beta: f64) -> Result<Vec<u8>> {
    if frame.len() != events.len() {
        return Err(Error::invalid(
            "events",
            format!("{} pixels, as many as the frame", frame.len()),
            format!("{} pixels", events.len()),
        ));
    }
    if !(0.0..=1.0).contains(&beta) {
        return Err(Error::invalid("beta", "a weight in [0, 1]", beta));
    }
    let (a, b) = ((1.0 - beta) as f32, (beta * 255.0) as f32);
    Ok(frame
        .iter()
        .zip(events)
        .map(|(&c, &d)| (a * f32::from(c) + b * d.clamp(0.0, 1.0) + 0.5).min(255.0) as u8)
        .collect())
}

/// [`fuse`] of the frame with [`intensity_from_e3ct`] of `e3ct` (`H × W × channels`, the
/// warped, normalised E3CT), in one parallel pass without the intermediate intensity image;
/// the same values.
pub fn fuse_e3ct(frame: &[u8], e3ct: &[f32], channels: usize, beta: f64) -> Result<Vec<u8>> {
    if channels == 0 || e3ct.len() != frame.len() * channels {
        return Err(Error::invalid(
            "e3ct",
            format!(
                "{} × {channels} values, {channels} per frame pixel",
                frame.len()
            ),
            format!("{} values", e3ct.len()),
        ));
    }
    if !(0.0..=1.0).contains(&beta) {
        return Err(Error::invalid("beta", "a weight in [0, 1]", beta));
    }
    let (a, b) = ((1.0 - beta) as f32, (beta * 255.0) as f32);
    let mut out = vec![0u8; frame.len()];
    // The common channel counts as constants, so the per-pixel maximum is unrolled.
    match channels {
        3 => blend_pieces::<3>(&mut out, frame, e3ct, 3, a, b),
        4 => blend_pieces::<4>(&mut out, frame, e3ct, 4, a, b),
        c => blend_pieces::<0>(&mut out, frame, e3ct, c, a, b),
    }
    Ok(out)
}

/// The loop of [`fuse_e3ct`] with `c = C` channels when `C > 0`.
fn blend_pieces<const C: usize>(
    out: &mut [u8],
    frame: &[u8],
    e3ct: &[f32],
    c: usize,
    a: f32,
    b: f32,
) {
    out.par_chunks_mut(BETA_PIECE)
        .zip(frame.par_chunks(BETA_PIECE))
        .zip(e3ct.par_chunks(BETA_PIECE * c))
        .for_each(|((out, frame), e3ct)| blend_piece::<C>(out, frame, e3ct, c, a, b));
}

/// The blend weights `(1 − β, 255 β)` of [`fuse`], after checking β.
pub(crate) fn blend_weights(beta: f64) -> Result<(f32, f32)> {
    if !(0.0..=1.0).contains(&beta) {
        return Err(Error::invalid("beta", "a weight in [0, 1]", beta));
    }
    Ok(((1.0 - beta) as f32, (beta * 255.0) as f32))
}

/// One piece of [`fuse_e3ct`] (`c = C` channels when `C > 0`), with the weights of
/// [`blend_weights`]: `out[i]` from `frame[i]` and pixel `i` of `e3ct`. Shared with the warp
/// that blends while its output is in cache (`WarpMap::apply_fused`), so both give the same
/// values.
#[inline]
pub(crate) fn blend_piece<const C: usize>(
    out: &mut [u8],
    frame: &[u8],
    e3ct: &[f32],
    c: usize,
    a: f32,
    b: f32,
) {
    let c = if C > 0 { C } else { c };
    for ((o, &f), px) in out.iter_mut().zip(frame).zip(e3ct.chunks_exact(c)) {
        let d = (0..c).fold(0.0f32, |m, k| m.max(px[k])).clamp(0.0, 1.0);
        *o = (a * f32::from(f) + b * d.clamp(0.0, 1.0) + 0.5).min(255.0) as u8;
    }
}
