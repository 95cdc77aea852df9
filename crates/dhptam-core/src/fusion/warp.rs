//! The rectified event image → the rectified frame camera (paper eq. 5).
//!
//! With `K_d`, `K_c` the rectified intrinsics of the event and frame cameras and
//! `frame_from_event = [R | t]` between their rectified frames, an event pixel `P_d` at depth
//! `λ` goes to
//!
//! ```text
//! X_d  = λ K_d⁻¹ P_d                      back-projection at depth λ (z = λ)
//! X_c  = R X_d + t
//! P_c  = (1/λ') K_c X_c + δP_align,       λ' = (K_c X_c)_z = z of X_c   (the real divide)
//! ```
//!
//! For a fronto-parallel plane `z_d = λ` this is the plane-induced homography
//! `H = K_c (R + t e₃ᵀ / λ) K_d⁻¹`; at infinity `H = K_c R K_d⁻¹` (rotation only). The public
//! code of the authors dropped the divide and added a per-frame offset (SPEC-NOTES §6); here
//! `δP_align` is a constant of the rig. Images are resampled backwards: each frame pixel
//! `P_c` looks up `P_d = π(H⁻¹ (P_c − δP_align))`, which is exact for the same plane.
//! `Depth::Plane` can be updated per frame, e.g. to the median depth of tracked map points.

use nalgebra::{Matrix3, Vector2, Vector3};
use rayon::prelude::*;

use crate::error::{ensure_finite, Error, Result};
use crate::geometry::{Pinhole, Se3};

/// The depth the event pixels are assumed to lie at.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Depth {
    /// Points at infinity: only the rotation between the cameras matters.
    Infinity,
    /// A plane `z = depth_m` (metres) in front of the rectified event camera.
    Plane {
        /// Depth of the plane, metres, positive.
        depth_m: f64,
    },
}

/// The warp from one rectified event camera into its rectified frame camera.
#[derive(Clone, Debug)]
pub struct EventFrameWarp {
    k_event: Pinhole,
    k_frame: Pinhole,
    frame_from_event: Se3,
    depth: Depth,
    align_px: Vector2<f64>,
    frame_from_event_h: Matrix3<f64>,
    event_from_frame_h: Matrix3<f64>,
}

impl EventFrameWarp {
    /// Builds the warp; `frame_from_event` maps points of the rectified event camera frame
    /// into the rectified frame camera frame, `align_px` is δP_align in frame pixels.
    pub fn new(
        k_event: Pinhole,
        k_frame: Pinhole,
        frame_from_event: Se3,
        depth: Depth,
        align_px: Vector2<f64>,
    ) -> Result<Self> {
        ensure_finite("align_px", align_px.as_slice())?;
        ensure_finite(
            "frame_from_event.translation",
            frame_from_event.translation.as_slice(),
        )?;
        let r = frame_from_event.rotation.matrix();
        let m = match depth {
            Depth::Infinity => r,
            Depth::Plane { depth_m } => {
                if !(depth_m.is_finite() && depth_m > 0.0) {
                    return Err(Error::invalid("depth_m", "a positive plane depth", depth_m));
                }
                let mut m = r;
                let column = m.column(2) + frame_from_event.translation / depth_m;
                m.set_column(2, &column);
                m
            }
        };
        let h = k_frame.k_matrix() * m * inverse_k(&k_event);
        let h_inv = h.try_inverse().ok_or_else(|| {
            Error::numerical(
                "event-to-frame warp",
                "the plane passes through the frame camera centre (singular homography)",
            )
        })?;
        Ok(Self {
            k_event,
            k_frame,
            frame_from_event,
            depth,
            align_px,
            frame_from_event_h: h,
            event_from_frame_h: h_inv,
        })
    }

    /// The homography from event pixels to frame pixels (before δP_align).
    pub fn homography(&self) -> Matrix3<f64> {
        self.frame_from_event_h
    }

    /// Frame pixel of event pixel `p_event`, by eq. 5 step by step; `None` when the point
    /// lands behind the frame camera.
    pub fn warp_pixel(&self, p_event: &Vector2<f64>) -> Option<Vector2<f64>> {
        let lambda = match self.depth {
            Depth::Plane { depth_m } => depth_m,
            // Far enough that t/λ vanishes next to R: the same limit as the homography.
            Depth::Infinity => {
                let p = self.frame_from_event_h * Vector3::new(p_event.x, p_event.y, 1.0);
                return (p.z > 0.0).then(|| p.xy() / p.z + self.align_px);
            }
        };
        let ray = inverse_k(&self.k_event) * Vector3::new(p_event.x, p_event.y, 1.0);
        let x_c = self.frame_from_event * (ray * lambda);
        let q = self.k_frame.k_matrix() * x_c;
        (q.z > 0.0).then(|| q.xy() / q.z + self.align_px)
    }

    /// Event pixel seen at frame pixel `p_frame` (the inverse warp), `None` behind.
    pub fn unwarp_pixel(&self, p_frame: &Vector2<f64>) -> Option<Vector2<f64>> {
        let c = p_frame - self.align_px;
        let p = self.event_from_frame_h * Vector3::new(c.x, c.y, 1.0);
        (p.z > 0.0).then(|| p.xy() / p.z)
    }

    /// Resamples an event image (`src_w × src_h × channels`, channel fastest) into a frame
    /// image of `dst_w × dst_h × channels`, bilinear, 0 outside the event image.
    ///
    /// Parallel over rows. Along a row the homogeneous source point is affine in the column,
    /// so each pixel costs two additions, one divide and the four taps; taps inside the
    /// image (all but a one-pixel border) skip the per-tap bounds tests. Same values as
    /// [`Self::unwarp_pixel`] followed by a bilinear sample.
    pub fn warp_image(
        &self,
        src: &[f32],
        src_w: usize,
        src_h: usize,
        channels: usize,
        dst_w: usize,
        dst_h: usize,
    ) -> Result<Vec<f32>> {
        if channels == 0 || src.len() != src_w * src_h * channels {
            return Err(Error::invalid(
                "src",
                format!("{src_w}×{src_h}×{channels} values"),
                format!("{} values", src.len()),
            ));
        }
        let mut dst = vec![0f32; dst_w * dst_h * channels];
        if dst.is_empty() {
            return Ok(dst);
        }
        let h = self.event_from_frame_h;
        let step = h.column(0).into_owned();
        dst.par_chunks_mut(dst_w * channels)
            .enumerate()
            .for_each(|(v, row)| {
                // p(u) = H (u − a_x, v − a_y, 1) = H (−a_x, v − a_y, 1) + u H e₁.
                let start = h * Vector3::new(-self.align_px.x, v as f64 - self.align_px.y, 1.0);
                for (u, out) in row.chunks_exact_mut(channels).enumerate() {
                    let p = start + step * u as f64;
                    if p.z > 0.0 {
                        sample(src, src_w, src_h, channels, p.x / p.z, p.y / p.z, out);
                    }
                }
            });
        Ok(dst)
    }
}

fn inverse_k(k: &Pinhole) -> Matrix3<f64> {
    Matrix3::new(
        1.0 / k.fx,
        0.0,
        -k.cx / k.fx,
        0.0,
        1.0 / k.fy,
        -k.cy / k.fy,
        0.0,
        0.0,
        1.0,
    )
}

/// Bilinear sample of every channel at (x, y), pixel centres at integers, 0 outside.
#[inline]
fn sample(src: &[f32], w: usize, h: usize, c: usize, x: f64, y: f64, out: &mut [f32]) {
    if !(x > -1.0 && y > -1.0 && x < w as f64 && y < h as f64) {
        return;
    }
    let (xf, yf) = (x.floor(), y.floor());
    let (ax, ay) = ((x - xf) as f32, (y - yf) as f32);
    let (x0, y0) = (xf as isize, yf as isize);
    let taps = [
        (0, 0, (1.0 - ax) * (1.0 - ay)),
        (1, 0, ax * (1.0 - ay)),
        (0, 1, (1.0 - ax) * ay),
        (1, 1, ax * ay),
    ];
    if x0 >= 0 && y0 >= 0 && (x0 as usize) + 1 < w && (y0 as usize) + 1 < h {
        // All four taps inside: one slice of two rows, no test per tap.
        let base = (y0 as usize * w + x0 as usize) * c;
        let block = &src[base..base + (w + 2) * c];
        for (dx, dy, weight) in taps {
            if weight == 0.0 {
                continue;
            }
            let at = (dy * w + dx) * c;
            for (o, s) in out.iter_mut().zip(&block[at..at + c]) {
                *o += weight * s;
            }
        }
        return;
    }
    for (dx, dy, weight) in taps {
        let (xi, yi) = (x0 + dx as isize, y0 + dy as isize);
        if xi < 0 || yi < 0 || xi as usize >= w || yi as usize >= h || weight == 0.0 {
            continue;
        }
        let base = (yi as usize * w + xi as usize) * c;
        for (o, s) in out.iter_mut().zip(&src[base..base + c]) {
            *o += weight * s;
        }
    }
}
