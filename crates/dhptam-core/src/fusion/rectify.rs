//! Undistortion and rectification of events through a lookup table.
//!
//! An event camera has a few hundred thousand pixels and a window carries up to millions of
//! events, so each raw pixel's rectified pixel is computed once (unproject through the
//! camera model, rotate into the rectified frame, project with the rectified K) and looked up
//! per event. Events are moved to the nearest rectified pixel (an error of at most half a
//! pixel, below the blur of any event image); events whose ray leaves the rectified view are
//! dropped — they have no pixel to land on, unlike out-of-range raw coordinates, which are
//! still errors.

use nalgebra::Vector2;
use rayon::prelude::*;

use crate::error::Result;
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
    /// `v · width + u` → `v' · rect_width + u'`, or [`OUTSIDE`].
    table: Vec<u32>,
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
        let (rw, rh) = (f64::from(rect.width), f64::from(rect.height));
        let mut table = vec![OUTSIDE; w * h];
        table.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
            for (u, entry) in row.iter_mut().enumerate() {
                if let Some(r) = rect.rectify_pixel(side, &Vector2::new(u as f64, v as f64)) {
                    let (ru, rv) = (r.x.round(), r.y.round());
                    if (0.0..rw).contains(&ru) && (0.0..rh).contains(&rv) {
                        *entry = rv as u32 * rect.width + ru as u32;
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
        }
    }

    /// The rectified pixel of raw pixel `(u, v)`, `None` outside the rectified view.
    pub fn lookup(&self, u: u16, v: u16) -> Option<(u16, u16)> {
        let entry = *self
            .table
            .get(usize::from(v) * self.width as usize + usize::from(u))?;
        (entry != OUTSIDE && u32::from(u) < self.width).then(|| {
            (
                (entry % self.rect_width) as u16,
                (entry / self.rect_width) as u16,
            )
        })
    }

    /// Rectifies a window; raw coordinates outside the raw image are an error (see
    /// [`EventSlice::validate`]), events leaving the rectified view are dropped.
    pub fn apply(
        &self,
        events: &EventSlice<'_>,
        t_start_ns: i64,
        t_end_ns: i64,
    ) -> Result<RectifiedEvents> {
        events.validate(self.width, self.height, t_start_ns, t_end_ns)?;
        let mut out = RectifiedEvents::default();
        for k in 0..events.len() {
            if let Some((x, y)) = self.lookup(events.x[k], events.y[k]) {
                out.x.push(x);
                out.y.push(y);
                out.t_ns.push(events.t_ns[k]);
                out.p.push(events.p[k]);
            }
        }
        Ok(out)
    }
}
