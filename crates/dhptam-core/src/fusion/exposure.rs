//! Under- and over-exposed frames given back their contrast before the fusion.
//!
//! A frame taken while the auto-exposure lags behind the light (the dark and bright segments of
//! an HDR sequence) often still holds the whole scene, squeezed into a few grey levels: a dark
//! frame of the demo spans 0–10 of 255 with a noise of 0.25 levels. Feature detectors compare
//! intensity differences with fixed thresholds (ORB's FAST: 20 levels), so such a frame yields
//! no features although its signal is good. A digital gain fixes that, as long as the frame's
//! range is well above its noise; a frame of noise stretched to full range would only make
//! features of the noise.
//!
//! [`recover_exposure`] does this for the frames the fusion's exposure test calls failed (more
//! than `[fusion] max_clipped_fraction` of their pixels at or below `dark_level` or at or
//! above `bright_level`; the same test as [`super::choose_beta`]): their grey levels between
//! the 1st and the 99th percentile are stretched linearly over 0–255 when that range holds at
//! least `[fusion] recover_min_snr` standard deviations of the frame's noise. The noise is
//! estimated from the frame alone (Immerkær's Laplacian-difference estimator, over the pixels
//! that are not clipped at 0 or 255). Well-exposed frames are never touched. The front-end then
//! chooses β on the recovered frame, so a dark frame with a good signal becomes APS-biased and
//! a saturated one stays DVS-biased (stretching does not unclip its pixels).

use rayon::prelude::*;

use crate::config::FusionConfig;
use crate::error::{Error, Result};

/// Rows per parallel piece of the histogram and of the noise estimate.
const ROWS_PER_PIECE: usize = 64;
/// Percentiles of the grey levels mapped to 0 and 255.
const LOW_PERCENTILE: f64 = 1.0;
const HIGH_PERCENTILE: f64 = 99.0;

/// What [`recover_exposure`] found on one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExposureCheck {
    /// Fraction of pixels at or below `dark_level` or at or above `bright_level`.
    pub clipped_fraction: f64,
    /// The exposure test failed (`clipped_fraction > max_clipped_fraction`).
    pub failed: bool,
    /// Grey level at the 1st percentile (mapped to 0 when stretched).
    pub low: u8,
    /// Grey level at the 99th percentile (mapped to 255 when stretched).
    pub high: u8,
    /// Noise standard deviation in grey levels (0 when not estimated: the frame passed).
    pub noise: f64,
    /// The frame was stretched ([`recover_exposure`]), or is to be ([`check_exposure`]).
    pub stretched: bool,
}

impl ExposureCheck {
    /// `(high − low) / noise`: how many noise deviations the stretched range holds (infinite
    /// for a noiseless frame, 0 when not estimated).
    pub fn snr(&self) -> f64 {
        let range = f64::from(self.high) - f64::from(self.low);
        if self.noise > 0.0 {
            range / self.noise
        } else if self.failed && range > 0.0 {
            f64::INFINITY
        } else {
            0.0
        }
    }
}

/// Checks an 8-bit `width`-wide frame and, when it failed the exposure test and its signal is
/// good enough, stretches it in place (see the module documentation). With `[fusion]
/// recover_exposure = false` the frame is only checked.
pub fn recover_exposure(
    frame: &mut [u8],
    width: usize,
    config: &FusionConfig,
) -> Result<ExposureCheck> {
    let check = check_exposure(frame, width, config)?;
    if check.stretched {
        stretch_levels(frame, width, check.low, check.high);
    }
    Ok(check)
}

/// [`recover_exposure`] without touching the frame: `stretched` says whether it would be.
pub fn check_exposure(frame: &[u8], width: usize, config: &FusionConfig) -> Result<ExposureCheck> {
    if width == 0 || frame.is_empty() || frame.len() % width != 0 {
        return Err(Error::invalid(
            "frame",
            format!("a non-empty image whose size is a multiple of its width {width}"),
            format!("{} pixels", frame.len()),
        ));
    }
    let histogram = histogram(frame, width);
    let n = frame.len() as f64;
    let clipped: u64 = histogram
        .iter()
        .enumerate()
        .filter(|&(v, _)| {
            let v = v as f64;
            v <= config.dark_level || v >= config.bright_level
        })
        .map(|(_, &c)| c)
        .sum();
    let clipped_fraction = clipped as f64 / n;
    let failed = clipped_fraction > config.max_clipped_fraction;
    let (low, high) = (
        percentile(&histogram, LOW_PERCENTILE),
        percentile(&histogram, HIGH_PERCENTILE),
    );
    let mut check = ExposureCheck {
        clipped_fraction,
        failed,
        low,
        high,
        noise: 0.0,
        stretched: false,
    };
    if !failed || !config.recover_exposure || high <= low {
        return Ok(check);
    }
    check.noise = noise_sigma(frame, width);
    check.stretched = check.snr() >= config.recover_min_snr;
    log::debug!(
        "exposure: {:.0} % clipped, levels {low}..{high}, {:.1} noise deviations: {}",
        100.0 * clipped_fraction,
        check.snr(),
        if check.stretched {
            "stretched"
        } else {
            "left as it is"
        }
    );
    Ok(check)
}

/// Maps grey level `low` to 0 and `high` (> `low`) to 255, linearly, clipping outside; in place.
pub fn stretch_levels(frame: &mut [u8], width: usize, low: u8, high: u8) {
    let scale = 255.0 / (f64::from(high) - f64::from(low)).max(1.0);
    let lut: [u8; 256] = std::array::from_fn(|v| {
        ((v as f64 - f64::from(low)) * scale)
            .round()
            .clamp(0.0, 255.0) as u8
    });
    frame
        .par_chunks_mut(ROWS_PER_PIECE * width.max(1))
        .for_each(|piece| piece.iter_mut().for_each(|v| *v = lut[usize::from(*v)]));
}

/// Counts of each grey level.
fn histogram(frame: &[u8], width: usize) -> [u64; 256] {
    frame
        .par_chunks(ROWS_PER_PIECE * width)
        .map(|piece| {
            let mut h = [0u64; 256];
            for &v in piece {
                h[usize::from(v)] += 1;
            }
            h
        })
        .reduce(
            || [0u64; 256],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
                a
            },
        )
}

/// The smallest grey level with at least `p` % of the pixels at or below it.
fn percentile(histogram: &[u64; 256], p: f64) -> u8 {
    let total: u64 = histogram.iter().sum();
    let target = (p / 100.0 * total as f64).ceil().max(1.0) as u64;
    let mut seen = 0;
    for (v, &c) in histogram.iter().enumerate() {
        seen += c;
        if seen >= target {
            return v as u8;
        }
    }
    255
}

/// Noise standard deviation in grey levels (J. Immerkær, "Fast noise variance estimation",
/// 1996): the mean absolute response of the 3×3 difference of two Laplacians, which cancels
/// smooth image content, times √(π/2) / 6. Pixels clipped at 0 or 255 hold no noise, so
/// responses centred on them are left out; 0 for frames under 3×3 or without such pixels.
pub fn noise_sigma(frame: &[u8], width: usize) -> f64 {
    let height = frame.len() / width.max(1);
    if width < 3 || height < 3 {
        return 0.0;
    }
    let (sum, count) = (1..height - 1)
        .into_par_iter()
        .map(|y| {
            let (above, row, below) = (
                &frame[(y - 1) * width..y * width],
                &frame[y * width..(y + 1) * width],
                &frame[(y + 1) * width..(y + 2) * width],
            );
            let (mut sum, mut count) = (0u64, 0u64);
            for x in 1..width - 1 {
                let c = row[x];
                if c == 0 || c == 255 {
                    continue;
                }
                let v = |r: &[u8], dx: usize| i32::from(r[x + dx - 1]);
                let response = v(above, 0) + v(above, 2) + v(below, 0) + v(below, 2)
                    - 2 * (v(above, 1) + v(below, 1) + v(row, 0) + v(row, 2))
                    + 4 * i32::from(c);
                sum += u64::from(response.unsigned_abs());
                count += 1;
            }
            (sum, count)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if count == 0 {
        return 0.0;
    }
    (std::f64::consts::PI / 2.0).sqrt() * sum as f64 / (6.0 * count as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{rngs::StdRng, Rng, SeedableRng};
    use rand_distr::StandardNormal;

    /// A `w × h` ramp image with values `offset + span · x / w` plus Gaussian noise `sigma`.
    fn ramp(w: usize, h: usize, offset: f64, span: f64, sigma: f64, seed: u64) -> Vec<u8> {
        let mut rng = StdRng::seed_from_u64(seed);
        (0..w * h)
            .map(|i| {
                let x = (i % w) as f64;
                let n: f64 = rng.sample(StandardNormal);
                (offset + span * x / w as f64 + sigma * n)
                    .round()
                    .clamp(0.0, 255.0) as u8
            })
            .collect()
    }

    #[test]
    fn a_dark_frame_with_a_clean_signal_is_stretched_over_the_full_range() {
        let config = FusionConfig::default();
        let mut frame = ramp(200, 100, 1.0, 14.0, 0.3, 1);
        let check = recover_exposure(&mut frame, 200, &config).unwrap();
        assert!(check.failed && check.stretched, "{check:?}");
        assert!(check.snr() > config.recover_min_snr, "{check:?}");
        let (lo, hi) = (*frame.iter().min().unwrap(), *frame.iter().max().unwrap());
        assert_eq!((lo, hi), (0, 255));
        // The ramp keeps its order: column means increase.
        let mean = |x: usize| (0..100).map(|y| f64::from(frame[y * 200 + x])).sum::<f64>() / 100.0;
        assert!(mean(20) + 50.0 < mean(100) && mean(100) + 50.0 < mean(180));
    }

    #[test]
    fn a_well_exposed_frame_is_left_untouched() {
        let config = FusionConfig::default();
        let original = ramp(120, 80, 30.0, 190.0, 2.0, 2);
        let mut frame = original.clone();
        let check = recover_exposure(&mut frame, 120, &config).unwrap();
        assert!(!check.failed && !check.stretched);
        assert_eq!(frame, original);
    }

    #[test]
    fn a_dark_frame_of_noise_is_left_untouched() {
        // Range ~ 12 levels with a noise of 2 levels: under the default 20 deviations.
        let config = FusionConfig::default();
        let original = ramp(200, 100, 6.0, 2.0, 2.0, 3);
        let mut frame = original.clone();
        let check = recover_exposure(&mut frame, 200, &config).unwrap();
        assert!(check.failed && !check.stretched, "{check:?}");
        assert!((check.noise - 2.0).abs() < 0.3, "noise {}", check.noise);
        assert_eq!(frame, original);
    }

    #[test]
    fn switched_off_the_frame_is_only_checked() {
        let config = FusionConfig {
            recover_exposure: false,
            ..FusionConfig::default()
        };
        let original = ramp(200, 100, 1.0, 10.0, 0.3, 4);
        let mut frame = original.clone();
        let check = recover_exposure(&mut frame, 200, &config).unwrap();
        assert!(check.failed && !check.stretched);
        assert_eq!(frame, original);
    }

    #[test]
    fn the_noise_estimate_follows_the_true_deviation() {
        for sigma in [0.7, 1.5, 4.0] {
            let frame = ramp(300, 200, 60.0, 120.0, sigma, 5);
            let estimate = noise_sigma(&frame, 300);
            assert!(
                (estimate - sigma).abs() < 0.15 * sigma + 0.1,
                "σ {sigma}: estimated {estimate}"
            );
        }
    }

    #[test]
    fn bad_shapes_are_named() {
        let config = FusionConfig::default();
        let err = recover_exposure(&mut [0u8; 10], 3, &config).unwrap_err();
        assert!(err.to_string().contains("frame"), "{err}");
        assert!(recover_exposure(&mut [], 3, &config).is_err());
    }
}
