//! A borrowed window of events and its validation.
//!
//! Events arrive as four parallel arrays (TUM-VIE's `/events/{x,y,t,p}` after the time
//! conversion to nanoseconds). [`EventSlice`] borrows them, so a window cut from a large
//! recording is never copied.
//!
//! Handling of bad input (the same for every representation): the whole window is checked
//! before any output is written, and the first offending event is reported as
//! [`Error::InvalidInput`] naming its index. Out-of-range pixel coordinates, polarities other
//! than 0/1, times outside `[t_start_ns, t_end_ns)` and decreasing times are errors, not
//! skipped: each of them means the caller cut the window wrongly, mixed two cameras or
//! passed the wrong calibration, and silently dropping events would hide that.

use rayon::prelude::*;

use crate::error::{Error, Result};

/// Events checked per rayon task during validation.
const CHECK_CHUNK: usize = 1 << 16;

/// The events of one camera in a time window, as borrowed parallel arrays.
#[derive(Clone, Copy, Debug)]
pub struct EventSlice<'a> {
    /// Column of each event, pixels.
    pub x: &'a [u16],
    /// Row of each event, pixels.
    pub y: &'a [u16],
    /// Time of each event, nanoseconds, non-decreasing.
    pub t_ns: &'a [i64],
    /// Polarity of each event: 1 brighter (ON), 0 darker (OFF).
    pub p: &'a [i8],
}

impl<'a> EventSlice<'a> {
    /// Borrows four arrays of equal length.
    pub fn new(x: &'a [u16], y: &'a [u16], t_ns: &'a [i64], p: &'a [i8]) -> Result<Self> {
        let n = t_ns.len();
        for (name, len) in [("x", x.len()), ("y", y.len()), ("p", p.len())] {
            if len != n {
                return Err(Error::invalid(
                    name,
                    format!("{n} entries, as many as t_ns"),
                    format!("{len} entries"),
                ));
            }
        }
        Ok(Self { x, y, t_ns, p })
    }

    /// Number of events.
    pub fn len(&self) -> usize {
        self.t_ns.len()
    }

    /// Whether the window holds no event.
    pub fn is_empty(&self) -> bool {
        self.t_ns.is_empty()
    }

    /// Events `range` of this window (still borrowed).
    pub fn sub(&self, range: std::ops::Range<usize>) -> EventSlice<'a> {
        EventSlice {
            x: &self.x[range.clone()],
            y: &self.y[range.clone()],
            t_ns: &self.t_ns[range.clone()],
            p: &self.p[range],
        }
    }

    /// Checks every event against the image size and the window `[t_start_ns, t_end_ns)`,
    /// and that times never decrease; the error names the first offending event.
    pub fn validate(&self, width: u32, height: u32, t_start_ns: i64, t_end_ns: i64) -> Result<()> {
        check_frame(width, height, t_start_ns, t_end_ns)?;
        // The first chunk holding a bad event is found in parallel, the event inside it
        // sequentially.
        let n = self.len();
        let bad = (0..n.div_ceil(CHECK_CHUNK))
            .into_par_iter()
            .find_map_first(|chunk| {
                let start = chunk * CHECK_CHUNK;
                self.first_invalid(
                    start..(start + CHECK_CHUNK).min(n),
                    width,
                    height,
                    t_start_ns,
                    t_end_ns,
                )
            });
        match bad {
            None => Ok(()),
            Some(i) => Err(self.invalid_event(i, width, height, t_start_ns, t_end_ns)),
        }
    }

    /// The index of the first event of `range` that [`Self::validate`] refuses (its time is
    /// also compared with the event before `range`), `None` when all are fine. The image size
    /// and the window must have passed [`check_frame`].
    pub(crate) fn first_invalid(
        &self,
        range: std::ops::Range<usize>,
        width: u32,
        height: u32,
        t_start_ns: i64,
        t_end_ns: i64,
    ) -> Option<usize> {
        let (start, end) = (range.start, range.end);
        if start >= end {
            return None;
        }
        let previous = if start == 0 {
            i64::MIN
        } else {
            self.t_ns[start - 1]
        };
        let block = Block {
            xs: &self.x[start..end],
            ys: &self.y[start..end],
            ts: &self.t_ns[start..end],
            ps: &self.p[start..end],
        };
        if block.is_valid(previous, width, height, t_start_ns, t_end_ns) {
            return None;
        }
        (start..end).find(|&k| {
            let t = self.t_ns[k];
            u32::from(self.x[k]) >= width
                || u32::from(self.y[k]) >= height
                || !(0..=1).contains(&self.p[k])
                || !(t_start_ns..t_end_ns).contains(&t)
                || (k > 0 && t < self.t_ns[k - 1])
        })
    }

    /// The error naming event `i`, which [`Self::first_invalid`] found.
    pub(crate) fn invalid_event(
        &self,
        i: usize,
        width: u32,
        height: u32,
        t_start_ns: i64,
        t_end_ns: i64,
    ) -> Error {
        let (x, y, t, p) = (self.x[i], self.y[i], self.t_ns[i], self.p[i]);
        if u32::from(x) >= width || u32::from(y) >= height {
            Error::invalid(
                format!("event {i} (x, y)"),
                format!("a pixel inside the {width}×{height} image"),
                format!("({x}, {y})"),
            )
        } else if !(0..=1).contains(&p) {
            Error::invalid(format!("event {i} p"), "polarity 0 or 1", p)
        } else if !(t_start_ns..t_end_ns).contains(&t) {
            Error::invalid(
                format!("event {i} t_ns"),
                format!("a time in the window [{t_start_ns}, {t_end_ns}) ns"),
                t,
            )
        } else {
            let before = i.saturating_sub(1);
            Error::invalid(
                format!("event {i} t_ns"),
                format!(
                    "times sorted in non-decreasing order (event {before} is at {} ns)",
                    self.t_ns[before]
                ),
                t,
            )
        }
    }
}

/// A run of events checked at once.
struct Block<'a> {
    xs: &'a [u16],
    ys: &'a [u16],
    ts: &'a [i64],
    ps: &'a [i8],
}

impl Block<'_> {
    /// Whether every event is fine, by one reduction per array (each vectorises; a block with
    /// a bad event fails at least one of them). On x86-64 the reductions run with AVX2 where
    /// the CPU has it (unsigned 16-bit maxima and 64-bit comparisons have no SSE2 form).
    fn is_valid(&self, previous: i64, width: u32, height: u32, t_s: i64, t_e: i64) -> bool {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            return unsafe { self.is_valid_avx2(previous, width, height, t_s, t_e) };
        }
        self.is_valid_plain(previous, width, height, t_s, t_e)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn is_valid_avx2(
        &self,
        previous: i64,
        width: u32,
        height: u32,
        t_s: i64,
        t_e: i64,
    ) -> bool {
        self.is_valid_plain(previous, width, height, t_s, t_e)
    }

    #[inline(always)]
    fn is_valid_plain(&self, previous: i64, width: u32, height: u32, t_s: i64, t_e: i64) -> bool {
        let Self { xs, ys, ts, ps } = self;
        let max_x = xs.iter().fold(0u16, |m, &v| m.max(v));
        let max_y = ys.iter().fold(0u16, |m, &v| m.max(v));
        // p ∈ {0, 1} ⇔ no bit other than the lowest is set.
        let p_bits = ps.iter().fold(0u8, |m, &v| m | (v as u8 & !1));
        let descents = ts
            .iter()
            .zip(&ts[1..])
            .fold(0u32, |m, (a, b)| m | u32::from(b < a));
        // Sorted (checked above and against the previous event), so the first and the last
        // time bound all of them.
        u32::from(max_x) < width
            && u32::from(max_y) < height
            && p_bits == 0
            && descents == 0
            && ts[0] >= previous
            && ts[0] >= t_s
            && ts[ts.len() - 1] < t_e
    }
}

/// Checks the image size and the window bounds shared by every representation.
pub(crate) fn check_frame(width: u32, height: u32, t_start_ns: i64, t_end_ns: i64) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(Error::invalid(
            "width/height",
            "a positive image size",
            format!("{width}×{height}"),
        ));
    }
    if t_end_ns <= t_start_ns {
        return Err(Error::invalid(
            "t_end_ns",
            format!("a window end after t_start_ns = {t_start_ns}"),
            t_end_ns,
        ));
    }
    // Window lengths and event ages are computed as `t_end_ns - t`: refuse windows whose
    // length does not fit an i64 (found by the `events` fuzz target: the subtraction
    // overflowed for a window from near i64::MIN to a positive end).
    if t_end_ns.checked_sub(t_start_ns).is_none() {
        return Err(Error::invalid(
            "t_end_ns",
            format!(
                "a window shorter than {} ns after t_start_ns = {t_start_ns}",
                i64::MAX
            ),
            t_end_ns,
        ));
    }
    Ok(())
}
