//! Undistortion and rectification of events through a lookup table.
//!
//! An event camera has a few hundred thousand pixels and a window carries up to millions of
//! events, so each raw pixel's rectified pixel is computed once (unproject through the
//! camera model, rotate into the rectified frame, project with the rectified K) and looked up
//! per event. Events are moved to the nearest rectified pixel (an error of at most half a
//! pixel, below the blur of any event image); events whose ray leaves the rectified view are
//! dropped — they have no pixel to land on, unlike out-of-range raw coordinates, which are
//! still errors.

use std::mem::MaybeUninit;

use nalgebra::Vector2;
use rayon::prelude::*;

use crate::error::Result;
use crate::events::window::check_frame;
use crate::events::EventSlice;
use crate::geometry::rectify::{RectifiedStereo, Side};

/// Marks a raw pixel without a rectified pixel in the table.
const OUTSIDE: u32 = u32::MAX;

/// Raw event pixel → rectified pixel table of one camera of a rectified event-camera pair.
#[derive(Clone, Debug)]
pub struct EventRectifier {
    /// Raw image width (the event camera's).
    pub width: u32,
    /// Raw image height.
    pub height: u32,
    /// Rectified image width.
    pub rect_width: u32,
    /// Rectified image height.
    pub rect_height: u32,
    /// `v · width + u` → `v' · 2¹⁶ + u'`, or [`OUTSIDE`] (rectified coordinates are `u16`, and
    /// `v' = 2¹⁶ − 1` cannot occur, so the marker is no pixel).
    table: Vec<u32>,
    /// Raw pixels masked by [`Self::set_masked`] with their table entries before masking.
    masked: Vec<(u32, u32)>,
}

/// Events moved to rectified pixels (owned: the pixels changed, the times did not).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RectifiedEvents {
    /// Rectified column.
    pub x: Vec<u16>,
    /// Rectified row.
    pub y: Vec<u16>,
    /// Time, nanoseconds (unchanged).
    pub t_ns: Vec<i64>,
    /// Polarity (unchanged).
    pub p: Vec<i8>,
}

impl RectifiedEvents {
    /// Borrows the events as a window.
    pub fn as_slice(&self) -> EventSlice<'_> {
        EventSlice {
            x: &self.x,
            y: &self.y,
            t_ns: &self.t_ns,
            p: &self.p,
        }
    }
}

impl EventRectifier {
    /// Builds the table of camera `side` of the rectified event-camera pair `rect`.
    pub fn new(rect: &RectifiedStereo, side: Side) -> Self {
        let camera = rect.camera(side);
        let (w, h) = (camera.width as usize, camera.height as usize);
        // Rectified pixels are u16 (the last row value is the table's marker).
        let (rw, rh) = (
            f64::from(rect.width).min(65536.0),
            f64::from(rect.height).min(65535.0),
        );
        let mut table = vec![OUTSIDE; w * h];
        table.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
            for (u, entry) in row.iter_mut().enumerate() {
                if let Some(r) = rect.rectify_pixel(side, &Vector2::new(u as f64, v as f64)) {
                    let (ru, rv) = (r.x.round(), r.y.round());
                    if (0.0..rw).contains(&ru) && (0.0..rh).contains(&rv) {
                        *entry = ((rv as u32) << 16) | ru as u32;
                    }
                }
            }
        });
        Self {
            width: camera.width,
            height: camera.height,
            rect_width: rect.width,
            rect_height: rect.height,
            table,
            masked: Vec::new(),
        }
    }

    /// Drops every event of the raw pixels `pixels` (`v · width + u`, e.g. the hot pixels of
    /// [`crate::events::HotPixels`]) from now on, as if their rays left the view; the pixels
    /// of the previous call are restored first, so each call replaces the mask. Indices
    /// outside the raw image are an error and change nothing.
    pub fn set_masked(&mut self, pixels: &[u32]) -> Result<()> {
        let n = self.table.len();
        if let Some(&bad) = pixels.iter().find(|&&i| i as usize >= n) {
            return Err(crate::error::Error::invalid(
                "masked pixel",
                format!(
                    "an index below {n} ({}×{} raw pixels)",
                    self.width, self.height
                ),
                bad,
            ));
        }
        for (i, entry) in self.masked.drain(..) {
            self.table[i as usize] = entry;
        }
        for &i in pixels {
            let entry = std::mem::replace(&mut self.table[i as usize], OUTSIDE);
            if entry != OUTSIDE {
                self.masked.push((i, entry));
            }
        }
        Ok(())
    }

    /// The raw pixels masked by [`Self::set_masked`] (those inside the rectified view).
    pub fn masked_count(&self) -> usize {
        self.masked.len()
    }

    /// The rectified pixel of raw pixel `(u, v)`, `None` outside the rectified view.
    pub fn lookup(&self, u: u16, v: u16) -> Option<(u16, u16)> {
        let entry = *self
            .table
            .get(usize::from(v) * self.width as usize + usize::from(u))?;
        (entry != OUTSIDE && u32::from(u) < self.width)
            .then_some(((entry & 0xFFFF) as u16, (entry >> 16) as u16))
    }

    /// Rectifies a window; raw coordinates outside the raw image are an error (see
    /// [`EventSlice::validate`]), events leaving the rectified view are dropped.
    ///
    /// Parallel over chunks of [`APPLY_CHUNK`] events with rayon; the chunks' outputs are
    /// concatenated in input order, so the result is identical for any thread count.
    pub fn apply(
        &self,
        events: &EventSlice<'_>,
        t_start_ns: i64,
        t_end_ns: i64,
    ) -> Result<RectifiedEvents> {
        check_frame(self.width, self.height, t_start_ns, t_end_ns)?;
        let n = events.len();
        // Pass 1, chunk by chunk: the chunk's events validated (see `EventSlice::validate`)
        // while its arrays come into cache, then the rectified pixel index of every event (or
        // OUTSIDE) and the chunk's kept count, which places each chunk's output after the
        // previous chunks' outputs. Allocated without zeroing: every slot is written here,
        // every output value below. A chunk with an invalid event stops before its lookups
        // (the table is only read at valid raw pixels) and reports its first invalid event.
        let mut index: Vec<u32> = Vec::with_capacity(n);
        let counts: Vec<std::result::Result<usize, usize>> = index.spare_capacity_mut()[..n]
            .par_chunks_mut(APPLY_CHUNK)
            .enumerate()
            .map(|(c, out)| {
                let start = c * APPLY_CHUNK;
                let end = start + out.len();
                if let Some(bad) =
                    events.first_invalid(start..end, self.width, self.height, t_start_ns, t_end_ns)
                {
                    return Err(bad);
                }
                let xs = &events.x[start..end];
                let ys = &events.y[start..end];
                // Validated above: u < width and v < height.
                Ok(self.lookup_chunk(xs, ys, out))
            })
            .collect();
        // The first invalid event of the window lies in the first chunk reporting one.
        let counts: Vec<usize> = match counts.iter().find_map(|c| c.err()) {
            Some(bad) => {
                return Err(events.invalid_event(
                    bad,
                    self.width,
                    self.height,
                    t_start_ns,
                    t_end_ns,
                ))
            }
            None => counts.into_iter().flatten().collect(),
        };
        // SAFETY: the chunks above cover all `n` slots and each wrote every one of its slots.
        unsafe { index.set_len(n) };
        let total: usize = counts.iter().sum();
        let (mut x, mut y, mut t_ns, mut p) = (
            Vec::with_capacity(total),
            Vec::with_capacity(total),
            Vec::with_capacity(total),
            Vec::with_capacity(total),
        );
        // Pass 2: every chunk writes its kept events into its own disjoint output ranges.
        let mut xs = split_at_offsets(&mut x.spare_capacity_mut()[..total], &counts);
        let mut ys = split_at_offsets(&mut y.spare_capacity_mut()[..total], &counts);
        let mut ts = split_at_offsets(&mut t_ns.spare_capacity_mut()[..total], &counts);
        let mut ps = split_at_offsets(&mut p.spare_capacity_mut()[..total], &counts);
        xs.par_iter_mut()
            .zip(ys.par_iter_mut())
            .zip(ts.par_iter_mut().zip(ps.par_iter_mut()))
            .enumerate()
            .for_each(|(c, ((xo, yo), (to, po)))| {
                let start = c * APPLY_CHUNK;
                let end = (start + APPLY_CHUNK).min(n);
                compact_chunk(
                    &index[start..end],
                    &events.t_ns[start..end],
                    &events.p[start..end],
                    xo,
                    yo,
                    to,
                    po,
                );
            });
        // SAFETY: chunk c kept exactly counts[c] events (pass 1 counted the same test), so it
        // wrote every slot of its ranges, and the ranges cover `total` slots of each array.
        unsafe {
            x.set_len(total);
            y.set_len(total);
            t_ns.set_len(total);
            p.set_len(total);
        }
        Ok(RectifiedEvents { x, y, t_ns, p })
    }
}

impl EventRectifier {
    /// Pass 1 of [`Self::apply`] on one chunk of valid events: `out[k]` = the table entry of
    /// raw pixel `(xs[k], ys[k])`; returns how many are not [`OUTSIDE`]. The table (4 bytes per
    /// raw pixel, megabytes) is read at random, so the entry of the event `PREFETCH` places
    /// ahead is requested early, while the current ones are read.
    fn lookup_chunk(&self, xs: &[u16], ys: &[u16], out: &mut [MaybeUninit<u32>]) -> usize {
        let (n, width) = (out.len(), self.width as usize);
        assert!(xs.len() == n && ys.len() == n);
        let table = &self.table[..];
        let place = |k: usize| usize::from(ys[k]) * width + usize::from(xs[k]);
        let mut kept = 0;
        for k in 0..n {
            #[cfg(target_arch = "x86_64")]
            if k + PREFETCH < n {
                if let Some(entry) = table.get(place(k + PREFETCH)) {
                    // SAFETY: a prefetch hint only; the address is that of a table entry.
                    unsafe {
                        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                            (entry as *const u32).cast::<i8>(),
                        )
                    };
                }
            }
            let entry = table[place(k)];
            out[k].write(entry);
            kept += usize::from(entry != OUTSIDE);
        }
        kept
    }
}

/// How far ahead [`EventRectifier::lookup_chunk`] prefetches table entries, in events.
const PREFETCH: usize = 24;

/// Pass 2 of [`EventRectifier::apply`] on one chunk: the kept events (`index[k]` not
/// [`OUTSIDE`]) written, in order, to the chunk's output ranges, which hold exactly that many.
/// Compacted without a branch on the entry (events outside the rectified view fall anywhere
/// in the stream): every event is written to the next free slot, which only a kept event then
/// moves past; the bounds test only fails after the chunk's last kept event. A function of
/// its own, so that the output slices are known not to overlap each other.
fn compact_chunk(
    index: &[u32],
    t_ns: &[i64],
    p: &[i8],
    xo: &mut [MaybeUninit<u16>],
    yo: &mut [MaybeUninit<u16>],
    to: &mut [MaybeUninit<i64>],
    po: &mut [MaybeUninit<i8>],
) {
    let len = xo.len();
    assert!(yo.len() == len && to.len() == len && po.len() == len);
    assert!(t_ns.len() == index.len() && p.len() == index.len());
    let mut j = 0;
    for ((&e, &t), &q) in index.iter().zip(t_ns).zip(p) {
        if j < len {
            xo[j].write((e & 0xFFFF) as u16);
            yo[j].write((e >> 16) as u16);
            to[j].write(t);
            po[j].write(q);
        }
        j += usize::from(e != OUTSIDE);
    }
}

/// Events per parallel chunk of [`EventRectifier::apply`].
const APPLY_CHUNK: usize = 1 << 16;

/// Splits `data` into consecutive mutable pieces of the given lengths.
fn split_at_offsets<'a, T>(mut data: &'a mut [T], lengths: &[usize]) -> Vec<&'a mut [T]> {
    let mut pieces = Vec::with_capacity(lengths.len());
    for &len in lengths {
        let (head, tail) = std::mem::take(&mut data).split_at_mut(len);
        pieces.push(head);
        data = tail;
    }
    pieces
}
