//! Stereo rectification of a calibrated camera pair, any camera models.
//!
//! Rectification rotates both cameras about their centres so that they share one orientation
//! whose x axis runs along the baseline, and re-images both through one pinhole K. Afterwards
//! a point has the same row in both images and its depth is `fx · b / (u_left − u_right)`.
//!
//! The rotations follow Bouguet's construction. With `right_from_left = (R, t)` and
//! `φ = log R`, turning the left camera by `exp(φ/2)` and the right one by `exp(−φ/2)` gives
//! both the same orientation, in which the right camera centre sits at
//! `c = −exp(−φ/2) t` from the left one. A final rotation `R_rect` with rows
//!
//! ```text
//! e₁ = c / |c|,   e₂ = (ẑ × e₁) / |ẑ × e₁|,   e₃ = e₁ × e₂
//! ```
//!
//! sends the baseline to +x (so the rectified right camera is at `(b, 0, 0)` in the rectified
//! left frame, `b = |t|`) while tilting the optical axis as little as possible. Then
//! `rect_left_from_left = R_rect exp(φ/2)` and `rect_right_from_right = R_rect exp(−φ/2)`, and
//! `p_rect_right = p_rect_left − (b, 0, 0)`.
//!
//! The shared intrinsics come from where the two images land in the rectified view. The
//! border pixels of each image are unprojected, rotated and projected at unit focal length.
//! For each side this gives an inner rectangle (inside the image's footprint: every
//! rectified pixel there has a source pixel) and an outer one (containing the whole
//! footprint). The output window is fitted inside the intersection of the inner rectangles
//! when `balance = 0`, around the union of the outer ones when `balance = 1`, and its edges
//! move linearly in between. The window fixes the focal length (square pixels) and the
//! principal point, which are the same for both sides so that rows match.

use nalgebra::{Matrix3, Matrix3x4, Vector2, Vector3};
use rayon::prelude::*;

use super::camera::{Camera, Pinhole, Projective};
use super::se3::Se3;
use super::so3::So3;
use crate::config::RectificationConfig;
use crate::error::{ensure_finite, Error, Result};

/// A calibrated stereo pair.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StereoRig {
    /// The left camera (the reference of the rectified frame).
    pub left: Camera,
    /// The right camera.
    pub right: Camera,
    /// Maps points from the left camera frame to the right camera frame.
    pub right_from_left: Se3,
}

/// Which camera of a stereo pair.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Side {
    /// The left camera.
    Left,
    /// The right camera.
    Right,
}

/// Value written into both remap tables where the camera model cannot image the ray of a
/// rectified pixel. It lies outside every image, so `cv2.remap(..., borderMode=
/// cv2.BORDER_CONSTANT)` and [`remap_bilinear_u8`] fill such pixels with the border value.
pub const REMAP_INVALID: f32 = -1.0;

/// Rays closer than this cosine to the rectified image plane (about 84°) are too oblique to
/// bound the rectified view: they are left out of the rectangles and do not constrain them.
const MIN_RAY_COSINE: f64 = 0.1;

/// The baseline must make at least this sine with the optical axis (30°): horizontal
/// rectification of a pair looking along its own baseline stretches the images without bound.
const MIN_BASELINE_SINE: f64 = 0.5;

/// The rectified geometry of a stereo pair: shared pinhole intrinsics, the rotation of each
/// camera into its rectified frame and the baseline.
#[derive(Clone, Debug, PartialEq)]
pub struct RectifiedStereo {
    /// Intrinsics of both rectified images (fx = fy).
    pub pinhole: Pinhole,
    /// Width of the rectified images, pixels.
    pub width: u32,
    /// Height of the rectified images, pixels.
    pub height: u32,
    /// Rotation from the original left camera frame to the rectified left frame.
    pub rect_left_from_left: So3,
    /// Rotation from the original right camera frame to the rectified right frame.
    pub rect_right_from_right: So3,
    /// Distance between the camera centres, metres; the rectified right camera sits at
    /// `(baseline_m, 0, 0)` in the rectified left frame.
    pub baseline_m: f64,
    left: Camera,
    right: Camera,
}

/// Axis-aligned rectangle in normalised rectified coordinates (x/z, y/z).
#[derive(Clone, Copy, Debug)]
struct Rect {
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
}

impl Rect {
    fn lerp(&self, other: &Rect, s: f64) -> Rect {
        let mix = |a: f64, b: f64| a + (b - a) * s;
        Rect {
            x0: mix(self.x0, other.x0),
            x1: mix(self.x1, other.x1),
            y0: mix(self.y0, other.y0),
            y1: mix(self.y1, other.y1),
        }
    }
}

fn check_camera(name: &str, camera: &Camera) -> Result<()> {
    ensure_finite(&format!("{name} camera parameters"), &camera.model.params())?;
    if camera.width < 2 || camera.height < 2 {
        return Err(Error::invalid(
            format!("{name} camera image size"),
            "at least 2×2 pixels",
            format!("{}×{}", camera.width, camera.height),
        ));
    }
    Ok(())
}

/// The inner and outer rectangles of one image's footprint in the rectified view.
///
/// The border is sampled at every pixel centre (u ∈ {0, w − 1}, v ∈ {0, h − 1}), so the inner
/// rectangle keeps half a pixel of margin from the image edge. The inner rectangle is bounded
/// by the innermost sample of each edge; this is exact for footprints whose edges are
/// monotone curves, which holds for lens distortion and rotations of a few tens of degrees.
fn footprint(name: &str, camera: &Camera, rect_from_cam: &So3) -> Result<(Rect, Rect)> {
    let w = f64::from(camera.width - 1);
    let h = f64::from(camera.height - 1);
    let project = |u: f64, v: f64| -> Option<Vector2<f64>> {
        let p = rect_from_cam * &camera.unproject(&Vector2::new(u, v))?;
        (p.z > MIN_RAY_COSINE * p.norm()).then(|| Vector2::new(p.x / p.z, p.y / p.z))
    };
    let mut outer = Rect {
        x0: f64::INFINITY,
        x1: f64::NEG_INFINITY,
        y0: f64::INFINITY,
        y1: f64::NEG_INFINITY,
    };
    let mut inner = Rect {
        x0: f64::NEG_INFINITY,
        x1: f64::INFINITY,
        y0: f64::NEG_INFINITY,
        y1: f64::INFINITY,
    };
    // Edge samples per edge that could be used; an edge with none leaves its bound unknown.
    let mut used = [0usize; 4];
    let mut include = |m: Vector2<f64>, edge: usize, inner: &mut Rect| {
        outer.x0 = outer.x0.min(m.x);
        outer.x1 = outer.x1.max(m.x);
        outer.y0 = outer.y0.min(m.y);
        outer.y1 = outer.y1.max(m.y);
        match edge {
            0 => inner.x0 = inner.x0.max(m.x),
            1 => inner.x1 = inner.x1.min(m.x),
            2 => inner.y0 = inner.y0.max(m.y),
            _ => inner.y1 = inner.y1.min(m.y),
        }
        used[edge] += 1;
    };
    for v in 0..camera.height {
        let v = f64::from(v);
        if let Some(m) = project(0.0, v) {
            include(m, 0, &mut inner);
        }
        if let Some(m) = project(w, v) {
            include(m, 1, &mut inner);
        }
    }
    for u in 0..camera.width {
        let u = f64::from(u);
        if let Some(m) = project(u, 0.0) {
            include(m, 2, &mut inner);
        }
        if let Some(m) = project(u, h) {
            include(m, 3, &mut inner);
        }
    }
    if let Some(edge) = used.iter().position(|&n| n == 0) {
        let edge_name = ["left", "right", "top", "bottom"][edge];
        return Err(Error::numerical(
            "stereo rectification",
            format!("no pixel on the {edge_name} edge of the {name} image can be brought into the rectified view"),
        ));
    }
    Ok((inner, outer))
}

impl RectifiedStereo {
    /// Rectifies a stereo pair (see the module documentation for the construction).
    ///
    /// Errors: [`Error::InvalidInput`] for non-finite parameters, a zero baseline, images
    /// smaller than 2×2 or a configuration out of range; [`Error::Numerical`] when the
    /// baseline runs (nearly) along the optical axis or the two views have no common region.
    pub fn new(rig: &StereoRig, config: &RectificationConfig) -> Result<Self> {
        check_camera("left", &rig.left)?;
        check_camera("right", &rig.right)?;
        let t = rig.right_from_left.translation;
        ensure_finite("right_from_left.translation", t.as_slice())?;
        ensure_finite(
            "right_from_left.rotation",
            &rig.right_from_left.rotation.to_quaternion_xyzw(),
        )?;
        if !(0.0..=1.0).contains(&config.balance) {
            return Err(Error::invalid(
                "rectification.balance",
                "a value in [0, 1]",
                config.balance,
            ));
        }
        let (width, height) = match (config.width, config.height) {
            (0, 0) => (rig.left.width, rig.left.height),
            (w, h) if w >= 2 && h >= 2 => (w, h),
            (w, h) => {
                return Err(Error::invalid(
                    "rectification.width/height",
                    "both 0 (the left camera's size) or both at least 2",
                    format!("{w}×{h}"),
                ))
            }
        };
        let baseline_m = t.norm();
        if baseline_m <= 1e-9 {
            return Err(Error::invalid(
                "right_from_left.translation",
                "a non-zero baseline between the cameras",
                format!("|t| = {baseline_m:e} m"),
            ));
        }

        let phi = rig.right_from_left.rotation.log();
        let half_left = So3::exp(&(phi * 0.5));
        let half_right = So3::exp(&(phi * -0.5));
        // Right camera centre in the common (half-rotated) frame.
        let centre = -(half_right * t);
        let e1 = centre / baseline_m;
        let e2_raw = Vector3::z().cross(&e1);
        let e2_norm = e2_raw.norm();
        if e2_norm < MIN_BASELINE_SINE {
            return Err(Error::numerical(
                "stereo rectification",
                format!(
                    "the baseline makes {:.1}° with the optical axis; horizontal rectification needs at least {:.0}°",
                    e2_norm.clamp(-1.0, 1.0).asin().to_degrees(),
                    MIN_BASELINE_SINE.asin().to_degrees()
                ),
            ));
        }
        let e2 = e2_raw / e2_norm;
        let e3 = e1.cross(&e2);
        let rect_from_common = So3::from_matrix(&Matrix3::from_rows(&[
            e1.transpose(),
            e2.transpose(),
            e3.transpose(),
        ]))?;
        let rect_left_from_left = rect_from_common * half_left;
        let rect_right_from_right = rect_from_common * half_right;

        let (inner_l, outer_l) = footprint("left", &rig.left, &rect_left_from_left)?;
        let (inner_r, outer_r) = footprint("right", &rig.right, &rect_right_from_right)?;
        let inner = Rect {
            x0: inner_l.x0.max(inner_r.x0),
            x1: inner_l.x1.min(inner_r.x1),
            y0: inner_l.y0.max(inner_r.y0),
            y1: inner_l.y1.min(inner_r.y1),
        };
        let outer = Rect {
            x0: outer_l.x0.min(outer_r.x0),
            x1: outer_l.x1.max(outer_r.x1),
            y0: outer_l.y0.min(outer_r.y0),
            y1: outer_l.y1.max(outer_r.y1),
        };
        if inner.x1 <= inner.x0 || inner.y1 <= inner.y0 {
            return Err(Error::numerical(
                "stereo rectification",
                format!(
                    "the rectified views of the two cameras have no common valid region (x ∈ [{:.3}, {:.3}], y ∈ [{:.3}, {:.3}])",
                    inner.x0, inner.x1, inner.y0, inner.y1
                ),
            ));
        }

        // Pixel centres 0 and width − 1 map to the window's edges.
        let span_x = f64::from(width - 1);
        let span_y = f64::from(height - 1);
        // A window with the output's aspect ratio centred on `r`, scaled by focal length f.
        let window = |r: &Rect, f: f64| {
            let (xc, yc) = (0.5 * (r.x0 + r.x1), 0.5 * (r.y0 + r.y1));
            let (hw, hh) = (0.5 * span_x / f, 0.5 * span_y / f);
            Rect {
                x0: xc - hw,
                x1: xc + hw,
                y0: yc - hh,
                y1: yc + hh,
            }
        };
        // Largest window inside the common valid region, smallest window around everything.
        let f_inner = (span_x / (inner.x1 - inner.x0)).max(span_y / (inner.y1 - inner.y0));
        let f_outer = (span_x / (outer.x1 - outer.x0)).min(span_y / (outer.y1 - outer.y0));
        let chosen = window(&inner, f_inner).lerp(&window(&outer, f_outer), config.balance);
        let f = span_x / (chosen.x1 - chosen.x0);
        let pinhole = Pinhole {
            fx: f,
            fy: f,
            cx: -f * chosen.x0,
            cy: -f * chosen.y0,
        };
        ensure_finite(
            "rectified intrinsics",
            &[pinhole.fx, pinhole.cx, pinhole.cy],
        )?;

        let reference_fy = rig
            .left
            .model
            .pinhole()
            .fy
            .min(rig.right.model.pinhole().fy);
        log::info!(
            "stereo rectification: K = [fx = fy = {:.3}, cx = {:.3}, cy = {:.3}] ({:.3}× the smaller source fy), {}×{} px, baseline {:.4} m, balance {}",
            pinhole.fx,
            pinhole.cx,
            pinhole.cy,
            f / reference_fy,
            width,
            height,
            baseline_m,
            config.balance
        );
        Ok(Self {
            pinhole,
            width,
            height,
            rect_left_from_left,
            rect_right_from_right,
            baseline_m,
            left: rig.left,
            right: rig.right,
        })
    }

    /// The original (unrectified) camera of one side.
    pub fn camera(&self, side: Side) -> &Camera {
        match side {
            Side::Left => &self.left,
            Side::Right => &self.right,
        }
    }

    /// Rotation from the original camera frame of `side` to its rectified frame.
    pub fn rect_from_camera(&self, side: Side) -> So3 {
        match side {
            Side::Left => self.rect_left_from_left,
            Side::Right => self.rect_right_from_right,
        }
    }

    /// The left projection matrix `K [I | 0]`, acting on points in the rectified left frame.
    pub fn projection_left(&self) -> Matrix3x4<f64> {
        let mut p = Matrix3x4::zeros();
        p.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&self.pinhole.k_matrix());
        p
    }

    /// The right projection matrix `K [I | (−b, 0, 0)ᵀ] = [K | (−fx b, 0, 0)ᵀ]`, acting on
    /// points in the rectified left frame.
    pub fn projection_right(&self) -> Matrix3x4<f64> {
        let mut p = self.projection_left();
        p[(0, 3)] = -self.pinhole.fx * self.baseline_m;
        p
    }

    /// The rectified left pixel of a point in the rectified left frame (`None` behind it).
    pub fn project_left(&self, p_rect_left: &Vector3<f64>) -> Option<Vector2<f64>> {
        self.pinhole.project(p_rect_left)
    }

    /// The rectified right pixel of a point in the rectified left frame (`None` behind it).
    pub fn project_right(&self, p_rect_left: &Vector3<f64>) -> Option<Vector2<f64>> {
        self.pinhole
            .project(&(p_rect_left - Vector3::new(self.baseline_m, 0.0, 0.0)))
    }

    /// The rectified pixel of an original (distorted) pixel of `side`, or `None` when the
    /// model cannot unproject it or its ray points away from the rectified image plane.
    pub fn rectify_pixel(&self, side: Side, uv_distorted: &Vector2<f64>) -> Option<Vector2<f64>> {
        let ray = self.camera(side).unproject(uv_distorted)?;
        self.pinhole.project(&(self.rect_from_camera(side) * ray))
    }

    /// The original (distorted) pixel seen by a rectified pixel of `side`, or `None` when the
    /// camera model cannot image that ray. The pixel may lie outside the source image.
    pub fn unrectify_pixel(&self, side: Side, uv_rect: &Vector2<f64>) -> Option<Vector2<f64>> {
        let ray = Vector3::new(
            (uv_rect.x - self.pinhole.cx) / self.pinhole.fx,
            (uv_rect.y - self.pinhole.cy) / self.pinhole.fy,
            1.0,
        );
        let p = self.rect_from_camera(side).inverse() * ray;
        self.camera(side).project(&p)
    }

    /// Remap tables `(map_x, map_y)` for `side`, each `height × width` row-major: entry
    /// `v · width + u` is the source (distorted) pixel of rectified pixel (u, v), pixel
    /// centres at integers. Where the model cannot image the ray both entries are
    /// [`REMAP_INVALID`] (−1); source pixels that exist but fall outside the image are kept as
    /// they are. The tables work directly with `cv2.remap(img, map_x, map_y,
    /// cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)` and with [`remap_bilinear_u8`].
    pub fn remap_tables(&self, side: Side) -> (Vec<f32>, Vec<f32>) {
        let w = self.width as usize;
        let n = w * self.height as usize;
        let mut map_x = vec![REMAP_INVALID; n];
        let mut map_y = vec![REMAP_INVALID; n];
        let cam_from_rect = self.rect_from_camera(side).inverse().matrix();
        let camera = self.camera(side);
        let Pinhole { fx, fy, cx, cy } = self.pinhole;
        map_x
            .par_chunks_mut(w)
            .zip(map_y.par_chunks_mut(w))
            .enumerate()
            .for_each(|(row, (xs, ys))| {
                let y = (row as f64 - cy) / fy;
                for (col, (mx, my)) in xs.iter_mut().zip(ys.iter_mut()).enumerate() {
                    let ray = cam_from_rect * Vector3::new((col as f64 - cx) / fx, y, 1.0);
                    if let Some(uv) = camera.project(&ray) {
                        if uv.x.is_finite() && uv.y.is_finite() {
                            *mx = uv.x as f32;
                            *my = uv.y as f32;
                        }
                    }
                }
            });
        (map_x, map_y)
    }
}

/// Bilinear sample of a row-major image at (x, y), pixel centres at integers; neighbours
/// outside the image count as 0 (a constant black border, as `cv2.BORDER_CONSTANT`).
#[inline]
fn bilinear<T: Copy + Into<f32>>(src: &[T], w: usize, h: usize, x: f32, y: f32) -> f32 {
    if x.is_nan() || y.is_nan() || x <= -1.0 || y <= -1.0 || x >= w as f32 || y >= h as f32 {
        return 0.0;
    }
    let (xf, yf) = (x.floor(), y.floor());
    let (ax, ay) = (x - xf, y - yf);
    let (x0, y0) = (xf as isize, yf as isize);
    let at = |xi: isize, yi: isize| -> f32 {
        if xi < 0 || yi < 0 || xi as usize >= w || yi as usize >= h {
            0.0
        } else {
            src[yi as usize * w + xi as usize].into()
        }
    };
    let top = at(x0, y0) * (1.0 - ax) + at(x0 + 1, y0) * ax;
    let bottom = at(x0, y0 + 1) * (1.0 - ax) + at(x0 + 1, y0 + 1) * ax;
    top * (1.0 - ay) + bottom * ay
}

/// Output pixels per rayon task in the remap functions (a few image rows).
const REMAP_CHUNK: usize = 4096;

fn check_remap(
    src_len: usize,
    src_w: usize,
    src_h: usize,
    map_x: usize,
    map_y: usize,
    dst: usize,
) -> Result<()> {
    if src_len != src_w * src_h {
        return Err(Error::invalid(
            "src",
            format!("{src_w}×{src_h} = {} pixels", src_w * src_h),
            format!("{src_len} pixels"),
        ));
    }
    if map_x != dst || map_y != dst {
        return Err(Error::invalid(
            "map_x/map_y",
            format!("{dst} entries each (one per dst pixel)"),
            format!("{map_x} and {map_y}"),
        ));
    }
    Ok(())
}

/// A pixel type the remap functions can resample.
pub trait RemapPixel: Copy + Into<f32> + Send + Sync {
    /// Converts an interpolated value back to the pixel type.
    fn from_interpolated(value: f32) -> Self;
}

impl RemapPixel for u8 {
    fn from_interpolated(value: f32) -> Self {
        // The value is within [0, 255] (a convex combination of u8 values and 0): round it.
        (value + 0.5).min(255.0) as u8
    }
}

impl RemapPixel for f32 {
    fn from_interpolated(value: f32) -> Self {
        value
    }
}

/// Resamples a single-channel image through remap tables with bilinear interpolation:
/// `dst[i]` is `src` at `(map_x[i], map_y[i])` (rounded for `u8`), with a black border (see
/// [`RectifiedStereo::remap_tables`]). Runs in parallel over blocks of rows.
pub fn remap_bilinear<T: RemapPixel>(
    src: &[T],
    src_w: usize,
    src_h: usize,
    map_x: &[f32],
    map_y: &[f32],
    dst: &mut [T],
) -> Result<()> {
    check_remap(src.len(), src_w, src_h, map_x.len(), map_y.len(), dst.len())?;
    dst.par_chunks_mut(REMAP_CHUNK)
        .zip(map_x.par_chunks(REMAP_CHUNK))
        .zip(map_y.par_chunks(REMAP_CHUNK))
        .for_each(|((out, xs), ys)| {
            for ((d, &x), &y) in out.iter_mut().zip(xs).zip(ys) {
                *d = T::from_interpolated(bilinear(src, src_w, src_h, x, y));
            }
        });
    Ok(())
}

/// [`remap_bilinear`] for 8-bit images.
pub fn remap_bilinear_u8(
    src: &[u8],
    src_w: usize,
    src_h: usize,
    map_x: &[f32],
    map_y: &[f32],
    dst: &mut [u8],
) -> Result<()> {
    remap_bilinear(src, src_w, src_h, map_x, map_y, dst)
}

/// [`remap_bilinear`] for `f32` images (no rounding; the border is 0.0).
pub fn remap_bilinear_f32(
    src: &[f32],
    src_w: usize,
    src_h: usize,
    map_x: &[f32],
    map_y: &[f32],
    dst: &mut [f32],
) -> Result<()> {
    remap_bilinear(src, src_w, src_h, map_x, map_y, dst)
}
