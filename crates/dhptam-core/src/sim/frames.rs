//! Frame formation: lighting profiles, a lagging auto-exposure and the sensor model.
//!
//! A global-shutter frame integrates `illumination(t) · radiance(t)` over its exposure
//! (motion blur comes from averaging renders spread over the exposure). The sensor turns the
//! mean irradiance into photo-electrons, `e = I · exposure_s · sensitivity`, adds shot noise
//! (Gaussian with variance `e`, the Poisson limit) and read noise, clips at the full-well
//! capacity and quantises linearly to 8 bits. Auto-exposure sees only the frame it just
//! produced and moves the exposure a fraction of the way (in log space) towards the value
//! that would have put the mean at the target, within the camera's limits: it lags behind
//! sudden lighting changes, which is what makes frames fail where events do not.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use crate::error::{Error, Result};

/// The lighting of a sequence, as a function of normalised time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Profile {
    /// Constant illumination.
    Normal,
    /// A segment 60× darker (30–55 % of the sequence) and a segment 30× brighter (70–85 %)
    /// that saturates the frames even at the shortest exposure.
    Hdr,
    /// Constant illumination, but the exposure alternates ×8 / ÷8 over the first
    /// [`FLICKER_FRAMES`] frames, like the over/under-exposed start of TUM-VIE recordings.
    Flicker,
    /// Constant illumination 40× below normal.
    Dark,
}

/// Frames whose exposure alternates in the `flicker` profile.
pub const FLICKER_FRAMES: u64 = 45;

/// Illumination factor of the dark segment of `hdr`.
pub const HDR_DARK_FACTOR: f64 = 1.0 / 60.0;
/// Illumination factor of the bright segment of `hdr`.
pub const HDR_BRIGHT_FACTOR: f64 = 30.0;
/// Illumination factor of the `dark` profile.
pub const DARK_FACTOR: f64 = 1.0 / 40.0;

/// Fraction of the sequence the lighting takes to change between levels.
const RAMP: f64 = 0.03;

impl Profile {
    /// Parses `normal`, `hdr`, `flicker` or `dark`.
    pub fn parse(name: &str) -> Result<Self> {
        match name {
            "normal" => Ok(Profile::Normal),
            "hdr" => Ok(Profile::Hdr),
            "flicker" => Ok(Profile::Flicker),
            "dark" => Ok(Profile::Dark),
            other => Err(Error::invalid(
                "lighting profile",
                "one of normal, hdr, flicker, dark",
                format!("{other:?}"),
            )),
        }
    }

    /// The profile's name.
    pub fn name(self) -> &'static str {
        match self {
            Profile::Normal => "normal",
            Profile::Hdr => "hdr",
            Profile::Flicker => "flicker",
            Profile::Dark => "dark",
        }
    }

    /// Illumination at normalised time `s = t / duration` (1 = normal light). Level changes
    /// are linear in log illumination over [`RAMP`] of the sequence.
    pub fn illumination(self, s: f64) -> f64 {
        match self {
            Profile::Normal | Profile::Flicker => 1.0,
            Profile::Dark => DARK_FACTOR,
            Profile::Hdr => {
                let dark = window(s, 0.30, 0.55);
                let bright = window(s, 0.70, 0.85);
                (dark * HDR_DARK_FACTOR.ln() + bright * HDR_BRIGHT_FACTOR.ln()).exp()
            }
        }
    }

    /// The factor applied to the auto-exposure's choice for frame `index`.
    pub fn exposure_factor(self, index: u64) -> f64 {
        match self {
            Profile::Flicker if index < FLICKER_FRAMES => {
                if index % 2 == 0 {
                    8.0
                } else {
                    0.125
                }
            }
            _ => 1.0,
        }
    }

    /// Segments of normalised time `[start, end)` at full strength, labelled `dark`,
    /// `bright` or `normal` (ramps excluded), for evaluating what each lighting does.
    pub fn segments(self) -> Vec<(&'static str, f64, f64)> {
        match self {
            Profile::Hdr => vec![
                ("normal", 0.0, 0.30),
                ("dark", 0.30 + RAMP, 0.55 - RAMP),
                ("normal", 0.55 + RAMP, 0.70),
                ("bright", 0.70 + RAMP, 0.85 - RAMP),
                ("normal", 0.85 + RAMP, 1.0),
            ],
            Profile::Dark => vec![("dark", 0.0, 1.0)],
            Profile::Normal | Profile::Flicker => vec![("normal", 0.0, 1.0)],
        }
    }
}

/// 1 inside `[start + RAMP, end − RAMP]`, 0 outside `[start, end]`, linear in between.
fn window(s: f64, start: f64, end: f64) -> f64 {
    let rise = ((s - start) / RAMP).clamp(0.0, 1.0);
    let fall = ((end - s) / RAMP).clamp(0.0, 1.0);
    rise.min(fall)
}

/// Sensor and auto-exposure parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SensorParams {
    /// Shortest exposure, nanoseconds.
    pub min_exposure_ns: i64,
    /// Longest exposure, nanoseconds.
    pub max_exposure_ns: i64,
    /// Exposure of the first frame, nanoseconds.
    pub initial_exposure_ns: i64,
    /// Mean 8-bit level auto-exposure aims at.
    pub target_mean: f64,
    /// Fraction of the log-exposure correction applied per frame, in (0, 1]; smaller lags more.
    pub ae_rate: f64,
    /// Photo-electrons per second per unit irradiance.
    pub sensitivity: f64,
    /// Full-well capacity, electrons (maps to 255).
    pub full_well: f64,
    /// Read noise, electrons RMS.
    pub read_noise: f64,
}

impl SensorParams {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<()> {
        let ok = self.min_exposure_ns > 0
            && self.max_exposure_ns >= self.min_exposure_ns
            && (self.min_exposure_ns..=self.max_exposure_ns).contains(&self.initial_exposure_ns)
            && self.target_mean > 0.0
            && self.target_mean < 255.0
            && self.ae_rate > 0.0
            && self.ae_rate <= 1.0
            && self.sensitivity > 0.0
            && self.full_well > 0.0
            && self.read_noise >= 0.0;
        if ok {
            Ok(())
        } else {
            Err(Error::invalid(
                "sensor parameters",
                "0 < min ≤ initial ≤ max exposure, 0 < target < 255, 0 < ae_rate ≤ 1, \
                 positive sensitivity and full well, read noise ≥ 0",
                format!("{self:?}"),
            ))
        }
    }
}

/// A frame sensor with its auto-exposure state and noise source.
#[derive(Clone, Debug)]
pub struct Sensor {
    params: SensorParams,
    exposure_ns: f64,
    rng: ChaCha8Rng,
}

impl Sensor {
    /// A sensor at its initial exposure; noise from `seed`.
    pub fn new(params: SensorParams, seed: u64) -> Result<Self> {
        params.validate()?;
        Ok(Self {
            exposure_ns: params.initial_exposure_ns as f64,
            params,
            rng: ChaCha8Rng::seed_from_u64(seed),
        })
    }

    /// The exposure auto-exposure currently asks for, nanoseconds.
    pub fn exposure_ns(&self) -> i64 {
        self.exposure_ns.round() as i64
    }

    /// The parameters.
    pub fn params(&self) -> &SensorParams {
        &self.params
    }

    /// Converts a mean irradiance image (illumination × radiance, averaged over the exposure)
    /// into an 8-bit image for an exposure of `exposure_ns`.
    pub fn capture(&mut self, irradiance: &[f32], exposure_ns: i64) -> Vec<u8> {
        let p = self.params;
        let scale = exposure_ns as f64 * 1e-9 * p.sensitivity;
        let to_dn = 255.0 / p.full_well;
        irradiance
            .iter()
            .map(|&i| {
                let electrons = f64::from(i).max(0.0) * scale;
                let noise: f64 = StandardNormal.sample(&mut self.rng);
                let sigma = (electrons + p.read_noise * p.read_noise).sqrt();
                let e = (electrons + sigma * noise).clamp(0.0, p.full_well);
                (e * to_dn).round().clamp(0.0, 255.0) as u8
            })
            .collect()
    }

    /// Updates the exposure from the mean level of the frame just captured with
    /// `exposure_ns`. Saturated or black frames still move the exposure (by the full rate).
    pub fn auto_expose(&mut self, mean_level: f64, exposure_ns: i64) {
        let p = self.params;
        let mean = mean_level.clamp(0.5, 254.5);
        let wanted = exposure_ns as f64 * p.target_mean / mean;
        let log_next = self.exposure_ns.ln() + p.ae_rate * (wanted.ln() - self.exposure_ns.ln());
        self.exposure_ns = log_next
            .exp()
            .clamp(p.min_exposure_ns as f64, p.max_exposure_ns as f64);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params() -> SensorParams {
        SensorParams {
            min_exposure_ns: 1_000_000,
            max_exposure_ns: 20_000_000,
            initial_exposure_ns: 5_000_000,
            target_mean: 100.0,
            ae_rate: 0.5,
            sensitivity: 1.2e6,
            full_well: 10_000.0,
            read_noise: 4.0,
        }
    }

    #[test]
    fn hdr_profile_levels() {
        let p = Profile::Hdr;
        assert_eq!(p.illumination(0.1), 1.0);
        assert!((p.illumination(0.42) - HDR_DARK_FACTOR).abs() < 1e-12);
        assert!((p.illumination(0.78) - HDR_BRIGHT_FACTOR).abs() < 1e-9);
        // Ramps are monotonic in between.
        assert!(p.illumination(0.315) < 1.0 && p.illumination(0.315) > HDR_DARK_FACTOR);
        assert!(Profile::parse("disco").is_err());
    }

    #[test]
    fn sensor_saturates_and_quantises() {
        let mut s = Sensor::new(params(), 1).unwrap();
        let img = s.capture(&[0.0, 0.5, 100.0], 5_000_000);
        assert!(img[0] < 3);
        // 0.5 · 5 ms · 1.2e6 = 3000 e⁻ → 76.5 DN (± noise of ~55 e⁻ ≈ 1.4 DN).
        assert!((f64::from(img[1]) - 76.5).abs() < 8.0, "{img:?}");
        assert_eq!(img[2], 255);
    }

    #[test]
    fn auto_exposure_lags_then_converges_within_limits() {
        let mut s = Sensor::new(params(), 1).unwrap();
        s.auto_expose(25.0, 5_000_000); // 4× too dark: halfway in log space is ×2
        assert!((s.exposure_ns() - 10_000_000).abs() <= 1);
        for _ in 0..50 {
            s.auto_expose(1.0, s.exposure_ns());
        }
        assert_eq!(s.exposure_ns(), 20_000_000);
    }
}
