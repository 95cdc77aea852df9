//! The event generator: the ESIM model of a DVS pixel (Rebecq et al., CoRL 2018).
//!
//! Each pixel keeps a reference log intensity `L_ref`. Between two renders at `t0` and `t1`
//! the log intensity is taken to change linearly from `L0` to `L1`; every time it crosses
//! `L_ref + C⁺` (or `L_ref − C⁻`) the pixel fires an ON (OFF) event and the reference moves
//! by that threshold. The crossing of level `ℓ` is timestamped by linear interpolation,
//!
//! ```text
//! t = t0 + (t1 − t0) · (ℓ − L0) / (L1 − L0),
//! ```
//!
//! so the timestamps are exact whenever the log intensity really is linear in time between
//! renders (the driver keeps the renders close enough for that, see `simulator`).
//! Thresholds differ per pixel (Gaussian mismatch around C±, drawn once). A pixel that fired
//! less than the refractory period ago drops the crossing, but its reference still moves:
//! the comparator resets, only the output is blanked. Background activity (leak and shot
//! noise) adds events at uniformly random times, at a per-pixel Poisson rate that grows as the
//! pixel gets darker; noise events do not move the reference.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, Poisson};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// One event: pixel, time and polarity (`true` = ON, brighter).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Event {
    /// Time, nanoseconds.
    pub t_ns: i64,
    /// Column.
    pub x: u16,
    /// Row.
    pub y: u16,
    /// `true` for an increase of log intensity.
    pub on: bool,
}

/// The parameters of the pixel model.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EventParams {
    /// Nominal ON threshold C⁺ (log intensity).
    pub contrast_on: f64,
    /// Nominal OFF threshold C⁻ (log intensity, positive).
    pub contrast_off: f64,
    /// Standard deviation of the per-pixel thresholds around C± (clamped to ≥ 0.01).
    pub contrast_sigma: f64,
    /// Refractory period, nanoseconds.
    pub refractory_ns: i64,
    /// Background-activity rate of a pixel at `noise_reference_intensity`, Hz.
    pub noise_rate_hz: f64,
    /// Intensity at which the noise rate equals `noise_rate_hz`; the rate scales with
    /// `sqrt(noise_reference_intensity / I)` (shot-noise dominated), capped at ×30.
    pub noise_reference_intensity: f64,
}

impl EventParams {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<()> {
        let ok = self.contrast_on > 0.0
            && self.contrast_off > 0.0
            && self.contrast_sigma >= 0.0
            && self.refractory_ns >= 0
            && self.noise_rate_hz >= 0.0
            && self.noise_reference_intensity > 0.0;
        if ok {
            Ok(())
        } else {
            Err(Error::invalid(
                "event parameters",
                "C± > 0, sigma ≥ 0, refractory ≥ 0, noise rate ≥ 0, reference intensity > 0",
                format!("{self:?}"),
            ))
        }
    }
}

/// Largest factor by which darkness multiplies the background-activity rate.
const MAX_NOISE_GAIN: f64 = 30.0;

/// The state of every pixel of one event camera.
#[derive(Clone, Debug)]
pub struct EventGenerator {
    width: usize,
    params: EventParams,
    reference: Vec<f64>,
    previous_log: Vec<f64>,
    previous_t_ns: i64,
    contrast_on: Vec<f64>,
    contrast_off: Vec<f64>,
    last_event_ns: Vec<i64>,
    rng: ChaCha8Rng,
}

impl EventGenerator {
    /// Starts every pixel with its reference at `log_intensity` (row-major, `width` columns)
    /// at time `t_ns`; thresholds and noise come from `seed`.
    pub fn new(
        width: usize,
        params: EventParams,
        seed: u64,
        t_ns: i64,
        log_intensity: &[f64],
    ) -> Result<Self> {
        params.validate()?;
        if width == 0 || log_intensity.len() % width != 0 || log_intensity.is_empty() {
            return Err(Error::invalid(
                "log intensity image",
                format!("a non-empty multiple of the width {width}"),
                format!("{} values", log_intensity.len()),
            ));
        }
        if width > usize::from(u16::MAX) || log_intensity.len() / width > usize::from(u16::MAX) {
            return Err(Error::invalid(
                "event camera size",
                "at most 65535 pixels per side",
                width,
            ));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let n = log_intensity.len();
        let mut draw = |mean: f64| -> Result<Vec<f64>> {
            if params.contrast_sigma == 0.0 {
                return Ok(vec![mean; n]);
            }
            let normal = Normal::new(mean, params.contrast_sigma)
                .map_err(|e| Error::invalid("contrast_sigma", "a finite deviation", e))?;
            Ok((0..n).map(|_| normal.sample(&mut rng).max(0.01)).collect())
        };
        let contrast_on = draw(params.contrast_on)?;
        let contrast_off = draw(params.contrast_off)?;
        Ok(Self {
            width,
            params,
            reference: log_intensity.to_vec(),
            previous_log: log_intensity.to_vec(),
            previous_t_ns: t_ns,
            contrast_on,
            contrast_off,
            last_event_ns: vec![i64::MIN / 2; n],
            rng,
        })
    }

    /// Time of the last log-intensity image, nanoseconds.
    pub fn time_ns(&self) -> i64 {
        self.previous_t_ns
    }

    /// The log-intensity image last passed in.
    pub fn previous_log(&self) -> &[f64] {
        &self.previous_log
    }

    /// Advances to the log-intensity image `log_intensity` at `t_ns` (> the previous time),
    /// appending the events in `(previous time, t_ns]` to `out`, sorted by time (ties by
    /// row, then column). `noise_gain` scales the background activity (0 disables it).
    pub fn advance(
        &mut self,
        t_ns: i64,
        log_intensity: &[f64],
        noise_gain: f64,
        out: &mut Vec<Event>,
    ) -> Result<()> {
        if log_intensity.len() != self.reference.len() {
            return Err(Error::invalid(
                "log intensity image",
                format!("{} values", self.reference.len()),
                log_intensity.len(),
            ));
        }
        if t_ns <= self.previous_t_ns {
            return Err(Error::invalid(
                "render time",
                format!("after {} ns", self.previous_t_ns),
                t_ns,
            ));
        }
        let t0 = self.previous_t_ns;
        let dt = (t_ns - t0) as f64;
        let width = self.width;
        let refractory = self.params.refractory_ns;
        let first = out.len();
        // Crossings, row by row in parallel; each row's events come out in pixel order.
        let rows: Vec<Vec<Event>> = self
            .reference
            .par_chunks_mut(width)
            .zip(self.last_event_ns.par_chunks_mut(width))
            .zip(self.previous_log.par_chunks(width))
            .zip(log_intensity.par_chunks(width))
            .zip(self.contrast_on.par_chunks(width))
            .zip(self.contrast_off.par_chunks(width))
            .enumerate()
            .map(|(y, (((((reference, last), l0), l1), c_on), c_off))| {
                let mut events = Vec::new();
                for x in 0..width {
                    let (a, b) = (l0[x], l1[x]);
                    let slope = b - a;
                    if slope == 0.0 {
                        continue;
                    }
                    let (on, step) = if slope > 0.0 {
                        (true, c_on[x])
                    } else {
                        (false, -c_off[x])
                    };
                    loop {
                        let level = reference[x] + step;
                        // Crossed iff the level lies in (a, b] going up or [b, a) going down.
                        if (on && level > b) || (!on && level < b) {
                            break;
                        }
                        reference[x] = level;
                        let t = t0 + ((level - a) / slope * dt).round() as i64;
                        let t = t.clamp(t0 + 1, t_ns);
                        if t - last[x] >= refractory {
                            last[x] = t;
                            events.push(Event {
                                t_ns: t,
                                x: x as u16,
                                y: y as u16,
                                on,
                            });
                        }
                    }
                }
                events
            })
            .collect();
        for row in rows {
            out.extend(row);
        }
        if noise_gain > 0.0 && self.params.noise_rate_hz > 0.0 {
            self.background_activity(t0, t_ns, log_intensity, noise_gain, out)?;
        }
        out[first..].sort_by_key(|e| (e.t_ns, e.y, e.x));
        self.previous_log.copy_from_slice(log_intensity);
        self.previous_t_ns = t_ns;
        Ok(())
    }

    /// Poisson background activity over `(t0, t1]`: the total count is Poisson with the sum of
    /// the pixels' rates, each event's pixel is drawn in proportion to its rate.
    fn background_activity(
        &mut self,
        t0: i64,
        t1: i64,
        log_intensity: &[f64],
        gain: f64,
        out: &mut Vec<Event>,
    ) -> Result<()> {
        let dt_s = (t1 - t0) as f64 * 1e-9;
        let base = self.params.noise_rate_hz * gain * dt_s;
        let reference = self.params.noise_reference_intensity;
        let mut cumulative = Vec::with_capacity(log_intensity.len());
        let mut total = 0.0;
        for &l in log_intensity {
            let intensity = l.exp();
            let factor = (reference / intensity.max(1e-12))
                .sqrt()
                .min(MAX_NOISE_GAIN);
            total += base * factor;
            cumulative.push(total);
        }
        if total <= 0.0 {
            return Ok(());
        }
        let count = Poisson::new(total)
            .map_err(|e| Error::numerical("background activity", e.to_string()))?
            .sample(&mut self.rng) as u64;
        for _ in 0..count {
            let pick = self.rng.random::<f64>() * total;
            let pixel = cumulative
                .partition_point(|&c| c <= pick)
                .min(cumulative.len() - 1);
            let t = t0 + 1 + (self.rng.random::<f64>() * (t1 - t0 - 1) as f64).round() as i64;
            let on = self.rng.random::<bool>();
            out.push(Event {
                t_ns: t,
                x: (pixel % self.width) as u16,
                y: (pixel / self.width) as u16,
                on,
            });
        }
        Ok(())
    }
}
