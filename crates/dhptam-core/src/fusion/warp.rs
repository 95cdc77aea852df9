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

use std::mem::MaybeUninit;

use nalgebra::{Matrix3, Vector2, Vector3};
use rayon::prelude::*;

use super::blend::{blend_piece, blend_weights};
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
    /// image of `dst_w × dst_h × channels`, bilinear, 0 outside the event image: the same
    /// values as [`Self::unwarp_pixel`] followed by a bilinear sample.
    ///
    /// Builds the [`WarpMap`] for these sizes and applies it; to warp many images of the same
    /// sizes, build the map once with [`Self::map`] and call [`WarpMap::apply`].
    pub fn warp_image(
        &self,
        src: &[f32],
        src_w: usize,
        src_h: usize,
        channels: usize,
        dst_w: usize,
        dst_h: usize,
    ) -> Result<Vec<f32>> {
        self.map(src_w, src_h, dst_w, dst_h)?
            .apply(src, channels, None)
    }

    /// The inverse warp of every pixel of a `dst_w × dst_h` frame image into a `src_w × src_h`
    /// event image, computed once (see [`WarpMap`]).
    ///
    /// Parallel over frame rows. Along a row the homogeneous source point is affine in the
    /// column, so each pixel costs two additions and one divide.
    pub fn map(&self, src_w: usize, src_h: usize, dst_w: usize, dst_h: usize) -> Result<WarpMap> {
        if src_w.saturating_mul(src_h) >= NO_SOURCE as usize {
            return Err(Error::invalid(
                "src",
                format!("fewer than {NO_SOURCE} event pixels"),
                format!("{src_w}×{src_h}"),
            ));
        }
        let h = self.event_from_frame_h;
        let step = h.column(0).into_owned();
        let rows: Vec<(Vec<MapEntry>, Vec<EdgePixel>)> = (0..dst_h)
            .into_par_iter()
            .map(|v| {
                let mut entries = Vec::with_capacity(dst_w);
                let mut edges = Vec::new();
                // p(u) = H (u − a_x, v − a_y, 1) = H (−a_x, v − a_y, 1) + u H e₁.
                let start = h * Vector3::new(-self.align_px.x, v as f64 - self.align_px.y, 1.0);
                for u in 0..dst_w {
                    let p = start + step * u as f64;
                    let mut entry = MapEntry {
                        base: NO_SOURCE,
                        ax: 0.0,
                        ay: 0.0,
                    };
                    let (x, y) = (p.x / p.z, p.y / p.z);
                    if p.z > 0.0 && x > -1.0 && y > -1.0 && x < src_w as f64 && y < src_h as f64 {
                        let (xf, yf) = (x.floor(), y.floor());
                        let (ax, ay) = ((x - xf) as f32, (y - yf) as f32);
                        let (x0, y0) = (xf as isize, yf as isize);
                        if x0 >= 0
                            && y0 >= 0
                            && (x0 as usize) + 1 < src_w
                            && (y0 as usize) + 1 < src_h
                        {
                            entry = MapEntry {
                                base: (y0 as usize * src_w + x0 as usize) as u32,
                                ax,
                                ay,
                            };
                        } else {
                            edges.push(EdgePixel {
                                pixel: v * dst_w + u,
                                x0,
                                y0,
                                ax,
                                ay,
                            });
                        }
                    }
                    entries.push(entry);
                }
                (entries, edges)
            })
            .collect();
        let mut entries = Vec::with_capacity(dst_w * dst_h);
        let mut edges = Vec::new();
        for (row, edge) in rows {
            entries.extend(row);
            edges.extend(edge);
        }
        Ok(WarpMap {
            src_w,
            src_h,
            dst_w,
            dst_h,
            entries,
            edges,
        })
    }
}

/// The frame, the output and the weights `(1 − β, 255 β)` of a blend done inside the warp.
struct Blend<'a> {
    frame: &'a [u8],
    out: &'a mut [u8],
    weights: (f32, f32),
}

/// Marks a frame pixel of a [`WarpMap`] whose four taps are not all inside the event image.
const NO_SOURCE: u32 = u32::MAX;

/// Frame pixels per parallel piece of [`WarpMap::apply`].
const APPLY_PIECE: usize = 1 << 14;

/// One frame pixel of a [`WarpMap`]: the event pixel index of its top-left bilinear tap and
/// the fractions toward the right and lower taps.
#[derive(Clone, Copy, Debug)]
struct MapEntry {
    /// `y0 · src_w + x0`, or [`NO_SOURCE`] (nothing to sample, or an [`EdgePixel`]).
    base: u32,
    ax: f32,
    ay: f32,
}

/// A frame pixel whose bilinear taps straddle the event image's border (some taps outside).
#[derive(Clone, Copy, Debug)]
struct EdgePixel {
    /// Frame pixel index `v · dst_w + u`.
    pixel: usize,
    x0: isize,
    y0: isize,
    ax: f32,
    ay: f32,
}

/// The inverse warp of an [`EventFrameWarp`] for one event-image size and one frame-image
/// size, precomputed: per frame pixel the event pixel of its top-left bilinear tap and the
/// two fractions (12 bytes), so that warping an image is one gather pass without any
/// homography, divide or bounds test. The few frame pixels whose taps straddle the event
/// image's border are kept apart and sampled tap by tap.
///
/// The values are those of [`EventFrameWarp::unwarp_pixel`] followed by a bilinear sample
/// (pixel centres at integers, 0 outside the event image), bit for bit: the fractions are
/// stored as the `f32` the sample computes, and the taps are added in the same order.
#[derive(Clone, Debug)]
pub struct WarpMap {
    src_w: usize,
    src_h: usize,
    dst_w: usize,
    dst_h: usize,
    entries: Vec<MapEntry>,
    edges: Vec<EdgePixel>,
}

impl WarpMap {
    /// Event image size `(width, height)` the map samples.
    pub fn src_size(&self) -> (usize, usize) {
        (self.src_w, self.src_h)
    }

    /// Frame image size `(width, height)` the map fills.
    pub fn dst_size(&self) -> (usize, usize) {
        (self.dst_w, self.dst_h)
    }

    /// Warps `src` (`src_w × src_h × channels`, channel fastest) into a new frame image
    /// (`dst_w × dst_h × channels`).
    ///
    /// With `scales` (one positive finite value per channel), each tap is first normalised as
    /// [`crate::events::scaled`] does (`(s · (1 / scale)).clamp(0, 1)`): the result equals
    /// warping the normalised image, bit for bit, without making it (for finite values: a NaN
    /// tap of zero weight, which the per-pixel sample skips, makes the value NaN here).
    /// Clipping is not linear, so it cannot move after the interpolation without changing
    /// the values.
    ///
    /// Parallel over pieces of frame pixels; every output value is written once (the output
    /// is not zeroed first).
    pub fn apply(&self, src: &[f32], channels: usize, scales: Option<&[f32]>) -> Result<Vec<f32>> {
        Ok(self.apply_inner(src, channels, scales, None)?.0)
    }

    /// [`Self::apply`] and, in the same pass, the fusion of its result with the frame
    /// (`dst_w × dst_h` 8-bit pixels) at weight `beta`: returns the warped image and
    /// [`crate::fusion::fuse_e3ct`]`(frame, warped, channels, beta)`, bit for bit, without
    /// reading the warped image back from memory (each piece is blended while it is in
    /// cache). β must be chosen before the warp (it depends on the frame only, see
    /// [`crate::fusion::choose_beta`]).
    pub fn apply_fused(
        &self,
        src: &[f32],
        channels: usize,
        scales: Option<&[f32]>,
        frame: &[u8],
        beta: f64,
    ) -> Result<(Vec<f32>, Vec<u8>)> {
        if frame.len() != self.dst_w * self.dst_h {
            return Err(Error::invalid(
                "frame",
                format!(
                    "{}×{} pixels, the warp's frame size",
                    self.dst_w, self.dst_h
                ),
                format!("{} pixels", frame.len()),
            ));
        }
        let weights = blend_weights(beta)?;
        let (warped, fused) = self.apply_inner(src, channels, scales, Some((frame, weights)))?;
        Ok((warped, fused.unwrap_or_default()))
    }

    /// [`Self::apply`], and with `fuse = (frame, (1 − β, 255 β))` the blend as well.
    fn apply_inner(
        &self,
        src: &[f32],
        channels: usize,
        scales: Option<&[f32]>,
        fuse: Option<(&[u8], (f32, f32))>,
    ) -> Result<(Vec<f32>, Option<Vec<u8>>)> {
        if channels == 0 || src.len() != self.src_w * self.src_h * channels {
            return Err(Error::invalid(
                "src",
                format!("{}×{}×{channels} values", self.src_w, self.src_h),
                format!("{} values", src.len()),
            ));
        }
        let inv = match scales {
            None => None,
            Some(scales) => {
                if scales.len() != channels {
                    return Err(Error::invalid(
                        "scales",
                        format!("{channels} scales, one per channel"),
                        format!("{} scales", scales.len()),
                    ));
                }
                if let Some(i) = scales.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
                    return Err(Error::invalid(
                        format!("scales[{i}]"),
                        "a positive finite scale",
                        scales[i],
                    ));
                }
                // The same constants as `events::scaled`, so the same roundings.
                Some(scales.iter().map(|s| 1.0 / s).collect::<Vec<f32>>())
            }
        };
        let n = self.dst_w * self.dst_h * channels;
        let mut dst: Vec<f32> = Vec::with_capacity(n);
        let out = &mut dst.spare_capacity_mut()[..n];
        let mut fused = fuse.map(|_| vec![0u8; self.dst_w * self.dst_h]);
        let blend = fuse
            .zip(fused.as_deref_mut())
            .map(|((frame, ab), out)| Blend {
                frame,
                out,
                weights: ab,
            });
        // Constant channel counts get their own unrolled loops (the E3CT has 3 or 4 channels);
        // `C = 0` is the loop for any count.
        match inv.as_deref() {
            None => self.gather_any::<false>(src, channels, out, blend, |s, _| s),
            Some(k) => {
                // Normalised taps lie in [0, 1] (for finite input), so a zero weight adds +0 and
                // need not be skipped: the dense loop gives the same sums.
                self.gather_any::<true>(src, channels, out, blend, |s, i| {
                    (s * k[i]).clamp(0.0, 1.0)
                })
            }
        }
        // SAFETY: `gather` wrote all `n` values of the spare capacity: each piece writes every
        // value of every one of its pixels (a value, or 0 where nothing is sampled).
        unsafe { dst.set_len(n) };
        Ok((dst, fused))
    }

    /// [`Self::gather`] with the channel count a constant where it is 1 to 4.
    fn gather_any<const DENSE: bool>(
        &self,
        src: &[f32],
        c: usize,
        out: &mut [MaybeUninit<f32>],
        blend: Option<Blend<'_>>,
        value: impl Fn(f32, usize) -> f32 + Sync,
    ) {
        match c {
            1 => self.gather::<1, DENSE>(src, c, out, blend, value),
            2 => self.gather::<2, DENSE>(src, c, out, blend, value),
            3 => self.gather::<3, DENSE>(src, c, out, blend, value),
            4 => self.gather::<4, DENSE>(src, c, out, blend, value),
            _ => self.gather::<0, DENSE>(src, c, out, blend, value),
        }
    }

    /// The gather: every frame pixel's `c` values (`c = C` when `C > 0`), each tap's value
    /// entering as `value(s, k)`. Taps of zero weight are skipped, as the per-pixel sample
    /// skips them, unless `DENSE` (for values where adding `0 · value` changes nothing: the
    /// normalised taps, in [0, 1]; the loop then has no branch per tap).
    fn gather<const C: usize, const DENSE: bool>(
        &self,
        src: &[f32],
        c: usize,
        out: &mut [MaybeUninit<f32>],
        blend: Option<Blend<'_>>,
        value: impl Fn(f32, usize) -> f32 + Sync,
    ) {
        let c = if C > 0 { C } else { c };
        let (w, h) = (self.src_w, self.src_h);
        // Per piece, its slice of the blend's output (or none).
        let (frame, weights) = match &blend {
            Some(b) => (b.frame, b.weights),
            None => (&[][..], (0.0, 0.0)),
        };
        let mut fused: Vec<Option<&mut [u8]>> = match blend {
            Some(b) => b.out.chunks_mut(APPLY_PIECE).map(Some).collect(),
            None => (0..self.entries.len().div_ceil(APPLY_PIECE))
                .map(|_| None)
                .collect(),
        };
        out.par_chunks_mut(APPLY_PIECE * c)
            .zip(self.entries.par_chunks(APPLY_PIECE))
            .zip(fused.par_iter_mut())
            .enumerate()
            .for_each(|(piece, ((out, entries), fused))| {
                for (o, e) in out.chunks_exact_mut(c).zip(entries) {
                    if e.base == NO_SOURCE {
                        for o in o.iter_mut() {
                            o.write(0.0);
                        }
                        continue;
                    }
                    let (ax, ay) = (e.ax, e.ay);
                    let weights = [
                        (1.0 - ax) * (1.0 - ay),
                        ax * (1.0 - ay),
                        (1.0 - ax) * ay,
                        ax * ay,
                    ];
                    let at = e.base as usize * c;
                    let rows = [&src[at..at + 2 * c], &src[at + w * c..at + (w + 2) * c]];
                    let taps = [&rows[0][..c], &rows[0][c..], &rows[1][..c], &rows[1][c..]];
                    for k in 0..c {
                        // Per channel the taps in the order of the tap-by-tap sample, zero
                        // weights skipped as it skips them.
                        let mut acc = 0.0f32;
                        for (tap, &weight) in taps.iter().zip(&weights) {
                            if DENSE || weight != 0.0 {
                                acc += weight * value(tap[k], k);
                            }
                        }
                        o[k].write(acc);
                    }
                }
                // The pixels of this piece whose taps straddle the border.
                let first = piece * APPLY_PIECE;
                let end = first + entries.len();
                let lo = self.edges.partition_point(|e| e.pixel < first);
                let hi = self.edges.partition_point(|e| e.pixel < end);
                for e in &self.edges[lo..hi] {
                    let o = &mut out[(e.pixel - first) * c..(e.pixel - first + 1) * c];
                    let (ax, ay) = (e.ax, e.ay);
                    let taps = [
                        (0, 0, (1.0 - ax) * (1.0 - ay)),
                        (1, 0, ax * (1.0 - ay)),
                        (0, 1, (1.0 - ax) * ay),
                        (1, 1, ax * ay),
                    ];
                    for (k, o) in o.iter_mut().enumerate() {
                        let mut acc = 0.0f32;
                        for &(dx, dy, weight) in &taps {
                            let (xi, yi) = (e.x0 + dx, e.y0 + dy);
                            if xi < 0
                                || yi < 0
                                || xi as usize >= w
                                || yi as usize >= h
                                || weight == 0.0
                            {
                                continue;
                            }
                            acc += weight * value(src[(yi as usize * w + xi as usize) * c + k], k);
                        }
                        o.write(acc);
                    }
                }
                // The blend of the piece, read back while it is in cache.
                if let Some(fused) = fused {
                    // SAFETY: every value of `out` was written above (the interior loop writes
                    // every pixel of the piece, the edge loop rewrites some), and
                    // `MaybeUninit<f32>` has the layout of `f32`.
                    let warped: &[f32] = unsafe {
                        std::slice::from_raw_parts(out.as_ptr().cast::<f32>(), out.len())
                    };
                    let first = piece * APPLY_PIECE;
                    let (a, b) = weights;
                    blend_piece::<C>(fused, &frame[first..first + entries.len()], warped, c, a, b);
                }
            });
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
