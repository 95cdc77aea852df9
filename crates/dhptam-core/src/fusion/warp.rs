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
                        sample(
                            src,
                            src_w,
                            src_h,
                            channels,
                            p.x / p.z,
                            p.y / p.z,
                            out,
                            |s, _| s,
                        );
                    }
                }
            });
        Ok(dst)
    }
    /// The fused frame of one camera in one pass over the frame's pixels: the same `u8`
    /// values as [`crate::fusion::fuse_e3ct`]`(frame, warp_image(scaled(src, scales)), C, β)`
    /// (normalise, warp, blend), bit for bit, without the normalised and the warped images.
    ///
    /// `frame` is the rectified 8-bit frame (`frame_w × frame_h`), `src` the raw
    /// (not normalised) rectified E3CT (`src_w × src_h × C`, `C = scales.len()`), `scales`
    /// the per-channel scales of [`crate::events::channel_scales`], `beta` the weight of the
    /// events in `[0, 1]`. Each bilinear tap is scaled and clipped before it is weighted,
    /// exactly as the three separate passes do. Parallel over frame rows.
    #[allow(clippy::too_many_arguments)]
    pub fn fuse_frame(
        &self,
        frame: &[u8],
        frame_w: usize,
        frame_h: usize,
        src: &[f32],
        src_w: usize,
        src_h: usize,
        scales: &[f32],
        beta: f64,
    ) -> Result<Vec<u8>> {
        let channels = scales.len();
        if channels == 0 || src.len() != src_w * src_h * channels {
            return Err(Error::invalid(
                "src",
                format!("{src_w}×{src_h}×{channels} values (one scale per channel)"),
                format!("{} values", src.len()),
            ));
        }
        if frame.len() != frame_w * frame_h {
            return Err(Error::invalid(
                "frame",
                format!("{frame_w}×{frame_h} pixels"),
                format!("{} pixels", frame.len()),
            ));
        }
        if let Some(i) = scales.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(Error::invalid(
                format!("scales[{i}]"),
                "a positive finite scale",
                scales[i],
            ));
        }
        if !(0.0..=1.0).contains(&beta) {
            return Err(Error::invalid("beta", "a weight in [0, 1]", beta));
        }
        let mut fused = vec![0u8; frame.len()];
        if fused.is_empty() {
            return Ok(fused);
        }
        // The same constants as `scaled` and `fuse_e3ct`, so the same roundings.
        let inv: Vec<f32> = scales.iter().map(|s| 1.0 / s).collect();
        let (a, b) = ((1.0 - beta) as f32, (beta * 255.0) as f32);
        let h = self.event_from_frame_h;
        let step = h.column(0).into_owned();
        fused
            .par_chunks_mut(frame_w)
            .zip(frame.par_chunks(frame_w))
            .enumerate()
            .for_each(|(v, (out, row))| {
                let start = h * Vector3::new(-self.align_px.x, v as f64 - self.align_px.y, 1.0);
                let mut px = vec![0f32; channels];
                for (u, (o, &c)) in out.iter_mut().zip(row).enumerate() {
                    px.fill(0.0);
                    let p = start + step * u as f64;
                    if p.z > 0.0 {
                        let scale = |s: f32, k: usize| (s * inv[k]).clamp(0.0, 1.0);
                        sample(
                            src,
                            src_w,
                            src_h,
                            channels,
                            p.x / p.z,
                            p.y / p.z,
                            &mut px,
                            scale,
                        );
                    }
                    let d = px.iter().copied().fold(0.0f32, f32::max).clamp(0.0, 1.0);
                    *o = (a * f32::from(c) + b * d.clamp(0.0, 1.0) + 0.5).min(255.0) as u8;
                }
            });
        Ok(fused)
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

/// Bilinear sample of every channel at (x, y), pixel centres at integers, 0 outside; each
/// tap's value `s` of channel `k` enters as `value(s, k)` (the identity, or a normalisation).
#[inline]
#[allow(clippy::too_many_arguments)]
fn sample(
    src: &[f32],
    w: usize,
    h: usize,
    c: usize,
    x: f64,
    y: f64,
    out: &mut [f32],
    value: impl Fn(f32, usize) -> f32,
) {
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
            for (k, (o, &s)) in out.iter_mut().zip(&block[at..at + c]).enumerate() {
                *o += weight * value(s, k);
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
        for (k, (o, &s)) in out.iter_mut().zip(&src[base..base + c]).enumerate() {
            *o += weight * value(s, k);
        }
    }
}
