//! Baseline event representations for ablations against the E3CT.
//!
//! All take a validated window (same error handling as [`super::e3ct()`]) and return
//! `height × width × C` `f32` images, channel fastest:
//!
//! - [`count_image`]: events per pixel (the "event image" of EVO), one channel or ON/OFF.
//! - [`time_surface`]: per polarity, `exp(−(t_e − t_last) / τ)` of the latest event at each
//!   pixel (0 where there is none).
//! - [`voxel_grid`]: `B` temporal bins, each event adding its signed polarity (+1 ON,
//!   −1 OFF) with the same tent voting over τ as the E3CT but no decay (Zhu et al. 2019).

use super::e3ct::PolarityMode;
use super::window::EventSlice;
use crate::error::{Error, Result};

/// Events per pixel: one channel (`Both`) or two, ON then OFF (`Split`).
pub fn count_image(
    events: &EventSlice<'_>,
    width: u32,
    height: u32,
    t_start_ns: i64,
    t_end_ns: i64,
    polarity: PolarityMode,
) -> Result<Vec<f32>> {
    events.validate(width, height, t_start_ns, t_end_ns)?;
    let c = match polarity {
        PolarityMode::Both => 1,
        PolarityMode::Split => 2,
    };
    let w = width as usize;
    let mut out = vec![0f32; w * height as usize * c];
    for k in 0..events.len() {
        let pixel = usize::from(events.y[k]) * w + usize::from(events.x[k]);
        let channel = usize::from(c == 2 && events.p[k] == 0);
        out[pixel * c + channel] += 1.0;
    }
    Ok(out)
}

/// Two channels (ON, OFF): `exp(−(t_end_ns − t_last) / tau)` with `t_last` the latest event
/// of that polarity at the pixel and `tau = tau_ms` milliseconds; 0 where none fired.
pub fn time_surface(
    events: &EventSlice<'_>,
    width: u32,
    height: u32,
    t_start_ns: i64,
    t_end_ns: i64,
    tau_ms: f64,
) -> Result<Vec<f32>> {
    if !(tau_ms.is_finite() && tau_ms > 0.0) {
        return Err(Error::invalid("tau_ms", "a positive time constant", tau_ms));
    }
    events.validate(width, height, t_start_ns, t_end_ns)?;
    let w = width as usize;
    let n_pixels = w * height as usize;
    // Times never decrease, so the last write to a pixel is its latest event.
    let mut latest = vec![i64::MIN; 2 * n_pixels];
    for k in 0..events.len() {
        let pixel = usize::from(events.y[k]) * w + usize::from(events.x[k]);
        latest[2 * pixel + usize::from(events.p[k] == 0)] = events.t_ns[k];
    }
    let inv_tau_ns = 1.0 / (tau_ms * 1e6);
    Ok(latest
        .iter()
        .map(|&t| {
            if t == i64::MIN {
                0.0
            } else {
                (-((t_end_ns - t) as f64) * inv_tau_ns).exp() as f32
            }
        })
        .collect())
}

/// `bins` channels; an event at normalised time τ adds `±max(0, 1 − |τ (B − 1) − j|)` to
/// bin `j` (+ for ON, − for OFF).
pub fn voxel_grid(
    events: &EventSlice<'_>,
    width: u32,
    height: u32,
    t_start_ns: i64,
    t_end_ns: i64,
    bins: usize,
) -> Result<Vec<f32>> {
    if !(2..=64).contains(&bins) {
        return Err(Error::invalid("bins", "between 2 and 64 bins", bins));
    }
    events.validate(width, height, t_start_ns, t_end_ns)?;
    let w = width as usize;
    let mut out = vec![0f32; w * height as usize * bins];
    let span = (t_end_ns - t_start_ns) as f64;
    let last = (bins - 1) as f64;
    for k in 0..events.len() {
        let s = (events.t_ns[k] - t_start_ns) as f64 / span * last;
        let i = (s as usize).min(bins - 2);
        let f = s - i as f64;
        let sign = if events.p[k] == 0 { -1.0 } else { 1.0 };
        let base = (usize::from(events.y[k]) * w + usize::from(events.x[k])) * bins + i;
        out[base] += (sign * (1.0 - f)) as f32;
        out[base + 1] += (sign * f) as f32;
    }
    Ok(out)
}
