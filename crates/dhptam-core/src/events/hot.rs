//! Hot pixels: event-camera pixels that fire on their own, whatever the scene does.
//!
//! Real event sensors have a few such pixels (leaky or defective comparators), firing at tens
//! to thousands of hertz. In an event image each one is a bright dot at a fixed place: a
//! perfect corner for a feature detector, and a feature that does not move with the camera,
//! so it pulls every pose towards the previous one. The simulator can add them
//! (`dhptam simulate --hot-pixels`), and `docs/BENCHMARKS.md` measures what they cost.
//!
//! Detection, per camera and causal. Hot pixels fire steadily, so windows are sampled: the
//! first one, then one whenever τ/8 has passed since the last sampled one started (every
//! third window of a 20 Hz camera at τ = 1 s; the others cost nothing). With `n_i` the
//! sampled window's events at raw pixel `i`, `Δt` its length and `s` the time since the last
//! sampled window started:
//!
//! ```text
//! a_i  ← d · a_i + n_i          d = exp(−s / τ)
//! W    ← d · W + Δt             the sampled time the activities have seen
//! m_i  = max_{j ∈ 8-neighbours(i)} a_j
//! hot_i ⇔ a_i ≥ r_min · W  and  a_i − k · m_i > 3 √a_i
//!         and (i fired in each of the last 3 sampled windows, or was hot already)
//! ```
//!
//! `a_i / W` is the pixel's event rate over the last few τ. Edges, textures, flicker and
//! illumination floods fire in patches, so a pixel of theirs has neighbours about as active
//! as itself; a hot pixel is `k` times more active than every neighbour, by a margin of three
//! standard deviations of its own count (a Poisson count's, √a), so that a pixel of a faint
//! texture whose few events happen to outnumber its neighbours' is not taken for one. A hot
//! pixel also fires all the time, where a pixel on a sharp detail of the scene fires in a
//! burst of a few windows as the detail passes: the streak of three sampled windows (about
//! τ/4 of steady firing) keeps such bursts, and the first windows of a run, out. A pixel stops
//! being hot when the rate tests fail (its rate fell, or its neighbourhood caught up). Two hot
//! pixels side by side are not found (each has an active neighbour); isolated ones are by far
//! the most common.

use rayon::prelude::*;

use crate::error::{Error, Result};

/// At most this many threads count a window's events (each into an array of its own).
const MAX_COUNT_PARTS: usize = 4;

/// A window is counted when this fraction of τ has passed since the last one counted started.
const SAMPLE_EVERY: f64 = 0.125;

/// Sampled windows in a row a pixel must fire in before it can become hot.
const MIN_STREAK: u8 = 3;

/// How far ahead the counting pass prefetches table entries, in events.
const PREFETCH: usize = 24;

/// Rows of the activity image per task of the decay pass.
const ROWS_PER_TASK: usize = 16;

/// Parameters of [`HotPixels`] (the `[events] hot_pixel_*` settings).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HotPixelParams {
    /// `k`: how many times more active than its most active neighbour a hot pixel is.
    pub ratio: f64,
    /// `r_min`: the least event rate of a hot pixel, Hz.
    pub min_rate_hz: f64,
    /// `τ`: time constant of the activities, seconds.
    pub time_constant_s: f64,
}

impl Default for HotPixelParams {
    /// The `[events] hot_pixel_*` defaults.
    fn default() -> Self {
        let events = crate::config::EventsConfig::default();
        Self {
            ratio: events.hot_pixel_ratio,
            min_rate_hz: events.hot_pixel_min_rate_hz,
            time_constant_s: events.hot_pixel_time_s,
        }
    }
}

impl HotPixelParams {
    /// Checks the ranges: ratio > 1, min rate > 0, time constant > 0.
    pub fn validate(&self) -> Result<()> {
        let ok = self.ratio.is_finite()
            && self.ratio > 1.0
            && self.min_rate_hz.is_finite()
            && self.min_rate_hz > 0.0
            && self.time_constant_s.is_finite()
            && self.time_constant_s > 0.0;
        if ok {
            Ok(())
        } else {
            Err(Error::invalid(
                "hot pixel parameters",
                "ratio > 1, min_rate_hz > 0, time_constant_s > 0",
                format!("{self:?}"),
            ))
        }
    }
}

/// The running hot-pixel detector of one event camera (raw sensor pixels).
#[derive(Clone, Debug)]
pub struct HotPixels {
    width: usize,
    height: usize,
    params: HotPixelParams,
    /// Exponentially weighted event count of every raw pixel (row-major).
    activity: Vec<f32>,
    /// Events of the current window per pixel, one array per part of the window counted on
    /// its own thread (all zero between updates; saturating, a pixel cannot fire 65 535 times
    /// in a window).
    counts: Vec<Vec<u16>>,
    /// Total weight of the sampled time so far, seconds (`W`).
    seen_s: f64,
    /// Time since the last sampled window started, seconds (`None` before the first).
    since_sample_s: Option<f64>,
    /// Sampled windows in a row, up to the last, in which each pixel fired (saturating).
    streak: Vec<u8>,
    /// The hot pixels, `v · width + u`, ascending.
    hot: Vec<u32>,
}

impl HotPixels {
    /// A detector for a `width × height` sensor that has seen nothing yet.
    pub fn new(width: u32, height: u32, params: HotPixelParams) -> Result<Self> {
        params.validate()?;
        if width == 0 || height == 0 {
            return Err(Error::invalid(
                "event camera size",
                "a non-empty image",
                format!("{width}×{height}"),
            ));
        }
        let n = width as usize * height as usize;
        Ok(Self {
            width: width as usize,
            height: height as usize,
            params,
            activity: vec![0.0; n],
            counts: Vec::new(),
            seen_s: 0.0,
            since_sample_s: None,
            streak: vec![0; n],
            hot: Vec::new(),
        })
    }

    /// The hot pixels after the last update, as raw pixel indices `v · width + u`, ascending.
    pub fn pixels(&self) -> &[u32] {
        &self.hot
    }

    /// Offers a window of `duration_s` seconds holding the events at raw pixels `(x, y)`.
    /// Hot pixels fire steadily, so the detector samples windows: it counts the first one and
    /// then one whenever τ/8 has passed since the start of the last one counted (every third
    /// window at 20 Hz, τ = 1 s), decays the activities by the time in between, re-evaluates
    /// every pixel and returns whether the set of hot pixels changed; other windows cost
    /// nothing and return `false`. A pixel outside the sensor in a sampled window is an error
    /// naming the event, and leaves the detector unchanged.
    pub fn update(&mut self, x: &[u16], y: &[u16], duration_s: f64) -> Result<bool> {
        if x.len() != y.len() {
            return Err(Error::invalid(
                "event window",
                "x and y of equal length",
                format!("{} and {}", x.len(), y.len()),
            ));
        }
        if !(duration_s.is_finite() && duration_s >= 0.0) {
            return Err(Error::invalid(
                "window duration",
                "a non-negative number of seconds",
                duration_s,
            ));
        }
        let tau = self.params.time_constant_s;
        let since = match self.since_sample_s {
            Some(since) if since < SAMPLE_EVERY * tau => {
                self.since_sample_s = Some(since + duration_s);
                return Ok(false);
            }
            since => since.unwrap_or(0.0),
        };
        let (w, h) = (self.width, self.height);
        if let Some(k) = (0..x.len()).find(|&k| usize::from(x[k]) >= w || usize::from(y[k]) >= h) {
            return Err(Error::invalid(
                format!("event {k}"),
                format!("a pixel inside the {w}×{h} sensor"),
                format!("({}, {})", x[k], y[k]),
            ));
        }
        let n = w * h;
        // Counts: each part of the window on its own thread into its own array (random
        // increments inside an L2-sized table, no branch); the sums are exact integers, so the
        // result does not depend on the thread count.
        let parts = rayon::current_num_threads().clamp(1, MAX_COUNT_PARTS);
        if self.counts.len() != parts {
            self.counts = vec![vec![0u16; n]; parts];
        }
        let chunk = x.len().div_ceil(parts).max(1);
        self.counts
            .par_iter_mut()
            .enumerate()
            .for_each(|(part, counts)| {
                let (lo, hi) = (
                    (part * chunk).min(x.len()),
                    ((part + 1) * chunk).min(x.len()),
                );
                let (xs, ys) = (&x[lo..hi], &y[lo..hi]);
                let place = |k: usize| usize::from(ys[k]) * w + usize::from(xs[k]);
                for k in 0..xs.len() {
                    // The table is read and written at random: ask for the entry of the event
                    // PREFETCH places ahead early (as the rectifier does).
                    #[cfg(target_arch = "x86_64")]
                    if k + PREFETCH < xs.len() {
                        // SAFETY: a prefetch hint only; the address is that of a table entry.
                        unsafe {
                            std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                                counts.as_ptr().add(place(k + PREFETCH)).cast::<i8>(),
                            )
                        };
                    }
                    let c = &mut counts[place(k)];
                    *c = c.saturating_add(1);
                }
            });
        // Decayed by the time since the last sampled window started.
        let decay = (-since / tau).exp() as f32;
        // The parts summed into the first (saturating u16 adds), then one pass over the image.
        let block = ROWS_PER_TASK * w;
        let (total, rest) = self
            .counts
            .split_first_mut()
            .expect("at least one count part");
        for part in rest.iter() {
            total
                .par_chunks_mut(block)
                .zip(part.par_chunks(block))
                .for_each(|(t, p)| {
                    for (t, &p) in t.iter_mut().zip(p) {
                        *t = t.saturating_add(p);
                    }
                });
        }
        self.activity
            .par_chunks_mut(block)
            .zip(self.streak.par_chunks_mut(block))
            .zip(total.par_chunks(block))
            .for_each(|((activity, streak), total)| {
                for ((a, s), &c) in activity.iter_mut().zip(streak.iter_mut()).zip(total) {
                    *a = *a * decay + f32::from(c);
                    *s = if c > 0 { s.saturating_add(1) } else { 0 };
                }
            });
        self.counts.par_iter_mut().for_each(|c| c.fill(0));
        self.seen_s = self.seen_s * f64::from(decay) + duration_s;
        self.since_sample_s = Some(duration_s);
        let floor = (self.params.min_rate_hz * self.seen_s) as f32;
        let ratio = self.params.ratio as f32;
        let (activity, streak, previous) = (&self.activity, &self.streak, &self.hot);
        let row = |v: usize| &activity[v * w..(v + 1) * w];
        let hot: Vec<u32> = (0..h)
            .into_par_iter()
            .flat_map_iter(|v| {
                let (mid, up, down) = (
                    row(v),
                    (v > 0).then(|| row(v - 1)),
                    (v + 1 < h).then(|| row(v + 1)),
                );
                let mut found = Vec::new();
                for (u, &a) in mid.iter().enumerate() {
                    if !(a >= floor && a > 0.0) {
                        continue;
                    }
                    // The busiest of the 8 neighbours inside the image (activities are ≥ 0).
                    let left = if u > 0 { mid[u - 1] } else { 0.0 };
                    let right = if u + 1 < w { mid[u + 1] } else { 0.0 };
                    let mut most = left.max(right);
                    let (l, r) = (u.saturating_sub(1), (u + 1).min(w - 1));
                    for side in [up, down].into_iter().flatten() {
                        most = most.max(side[l]).max(side[u]).max(side[r]);
                    }
                    let excess = a - ratio * most;
                    let index = (v * w + u) as u32;
                    let steady = streak[index as usize] >= MIN_STREAK
                        || previous.binary_search(&index).is_ok();
                    if excess > 0.0 && excess > 3.0 * a.sqrt() && steady {
                        found.push(index);
                    }
                }
                found
            })
            .collect();
        let changed = hot != self.hot;
        self.hot = hot;
        Ok(changed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn detector(w: u32, h: u32) -> HotPixels {
        HotPixels::new(w, h, HotPixelParams::default()).unwrap()
    }

    /// Events of one 50 ms window: `per_pixel` events at each of `pixels`.
    fn window(pixels: &[(u16, u16)], per_pixel: usize) -> (Vec<u16>, Vec<u16>) {
        let mut x = Vec::new();
        let mut y = Vec::new();
        for _ in 0..per_pixel {
            for &(u, v) in pixels {
                x.push(u);
                y.push(v);
            }
        }
        (x, y)
    }

    #[test]
    fn an_isolated_busy_pixel_is_hot_and_a_moving_edge_is_not() {
        let mut hot = detector(40, 30);
        for k in 0..20u16 {
            // A vertical edge sweeping one column per window (40 events per pixel, far above
            // the rate floor), and a pixel firing at 200 Hz.
            let edge: Vec<(u16, u16)> = (5..25).map(|v| (5 + k, v)).collect();
            let (mut x, mut y) = window(&edge, 40);
            let (hx, hy) = window(&[(30, 3)], 10);
            x.extend(hx);
            y.extend(hy);
            hot.update(&x, &y, 0.05).unwrap();
        }
        assert_eq!(hot.pixels(), &[3 * 40 + 30]);
    }

    #[test]
    fn a_pixel_below_the_least_rate_or_beside_an_equal_neighbour_is_not_hot() {
        let mut hot = detector(20, 20);
        for _ in 0..40 {
            // Two neighbours firing at 400 Hz together, and a pixel alone at 40 Hz (two events
            // a window: clear of its silent neighbours, but under the 50 Hz floor).
            let (mut x, mut y) = window(&[(10, 10), (11, 10)], 20);
            x.extend([2, 2]);
            y.extend([2, 2]);
            hot.update(&x, &y, 0.05).unwrap();
        }
        assert!(hot.pixels().is_empty(), "{:?}", hot.pixels());
    }

    #[test]
    fn a_pixel_that_stops_firing_stops_being_hot() {
        let mut hot = detector(16, 16);
        let (x, y) = window(&[(4, 4)], 10);
        for _ in 0..10 {
            hot.update(&x, &y, 0.05).unwrap();
        }
        assert_eq!(hot.pixels(), &[4 * 16 + 4]);
        let mut changed = false;
        for _ in 0..100 {
            changed |= hot.update(&[], &[], 0.05).unwrap();
        }
        assert!(changed);
        assert!(hot.pixels().is_empty());
    }

    #[test]
    fn the_result_does_not_depend_on_the_thread_count() {
        let pixels: Vec<(u16, u16)> = (0..300u16)
            .map(|k| ((k * 37) % 64, (k * 11) % 48))
            .collect();
        let (x, y) = window(&pixels, 3);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut hot = detector(64, 48);
                for _ in 0..5 {
                    hot.update(&x, &y, 0.05).unwrap();
                }
                (hot.activity.clone(), hot.pixels().to_vec())
            })
        };
        assert_eq!(run(1), run(3));
    }

    #[test]
    fn bad_input_is_an_error_and_changes_nothing() {
        let mut hot = detector(8, 8);
        let err = hot.update(&[1, 9], &[1, 1], 0.05).unwrap_err().to_string();
        assert!(err.contains("event 1") && err.contains("8×8"), "{err}");
        assert!(hot.update(&[1], &[1, 2], 0.05).is_err());
        assert!(hot.update(&[1], &[1], f64::NAN).is_err());
        assert!(hot.activity.iter().all(|&a| a == 0.0) && hot.seen_s == 0.0);
        assert!(HotPixels::new(
            8,
            8,
            HotPixelParams {
                ratio: 1.0,
                ..Default::default()
            }
        )
        .is_err());
        assert!(HotPixels::new(0, 8, HotPixelParams::default()).is_err());
    }
}
