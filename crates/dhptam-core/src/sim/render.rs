//! Per-pixel ray casting of a [`Scene`] through any [`Camera`] model.
//!
//! Each camera's pixels are unprojected once into a [`RayTable`] of unit bearings (and the
//! angle each pixel subtends, which picks the texture's mip level); a render rotates the
//! bearings into the world and traces them, in parallel over rows. The result is the
//! radiance under unit illumination, in row-major order. Renders are deterministic: every
//! pixel is computed independently of the thread that computes it.

use nalgebra::{Vector2, Vector3};
use rayon::prelude::*;

use super::scene::Scene;
use crate::geometry::{Camera, Projective, Se3};

/// The rays of a camera's pixel centres, in the camera frame.
#[derive(Clone, Debug)]
pub struct RayTable {
    width: usize,
    height: usize,
    /// Unit bearing per pixel; NaN where the model cannot unproject the pixel.
    bearings: Vec<[f32; 3]>,
    /// Angle between the pixel's ray and its right neighbour's, radians.
    pixel_angle: Vec<f32>,
}

impl RayTable {
    /// Unprojects every pixel centre of `camera`.
    pub fn new(camera: &Camera) -> Self {
        let (width, height) = (camera.width as usize, camera.height as usize);
        let rows: Vec<(Vec<[f32; 3]>, Vec<f32>)> = (0..height)
            .into_par_iter()
            .map(|y| {
                let mut bearings = Vec::with_capacity(width);
                let mut angles = Vec::with_capacity(width);
                for x in 0..width {
                    let at = |u: f64, v: f64| camera.unproject(&Vector2::new(u, v));
                    let (u, v) = (x as f64, y as f64);
                    match at(u, v) {
                        Some(b) => {
                            // Neighbour one pixel over (left of the last column).
                            let du = if x + 1 < width { 1.0 } else { -1.0 };
                            let angle = at(u + du, v)
                                .map(|n| b.angle(&n))
                                .filter(|a| *a > 0.0)
                                .unwrap_or(1e-3);
                            bearings.push([b.x as f32, b.y as f32, b.z as f32]);
                            angles.push(angle as f32);
                        }
                        None => {
                            bearings.push([f32::NAN; 3]);
                            angles.push(0.0);
                        }
                    }
                }
                (bearings, angles)
            })
            .collect();
        let mut bearings = Vec::with_capacity(width * height);
        let mut pixel_angle = Vec::with_capacity(width * height);
        for (b, a) in rows {
            bearings.extend(b);
            pixel_angle.extend(a);
        }
        Self {
            width,
            height,
            bearings,
            pixel_angle,
        }
    }

    /// Image width, pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height, pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.bearings.len()
    }

    /// Whether the table has no pixels (never true for a valid camera).
    pub fn is_empty(&self) -> bool {
        self.bearings.is_empty()
    }
}

/// Renders the radiance seen by a camera at `world_from_cam` into `out` (row-major,
/// `rays.len()` values). Pixels without a ray, or whose ray leaves the scene, get 0.
pub fn render(scene: &Scene, rays: &RayTable, world_from_cam: &Se3, out: &mut [f32]) {
    assert_eq!(
        out.len(),
        rays.len(),
        "output buffer must hold one value per pixel"
    );
    let r = world_from_cam.rotation.matrix().cast::<f32>();
    let t = world_from_cam.translation.cast::<f32>();
    let origin = [t.x, t.y, t.z];
    out.par_chunks_mut(rays.width)
        .enumerate()
        .for_each(|(y, row)| {
            let start = y * rays.width;
            for (x, value) in row.iter_mut().enumerate() {
                let b = rays.bearings[start + x];
                if b[0].is_nan() {
                    *value = 0.0;
                    continue;
                }
                let d: Vector3<f32> = r * Vector3::new(b[0], b[1], b[2]);
                *value = scene
                    .trace(origin, [d.x, d.y, d.z], rays.pixel_angle[start + x])
                    .map_or(0.0, |h| h.radiance);
            }
        });
}

/// Renders the depth seen by a camera at `world_from_cam` into `out` (row-major, one value
/// per pixel): the z coordinate, in metres, of the first surface hit by the pixel's ray, in
/// the camera frame (not the distance along the ray). Pixels without a ray, or whose ray
/// leaves the scene, get NaN. This is the ground truth for dense-depth and warp tests.
pub fn render_depth(scene: &Scene, rays: &RayTable, world_from_cam: &Se3, out: &mut [f32]) {
    assert_eq!(
        out.len(),
        rays.len(),
        "output buffer must hold one value per pixel"
    );
    let r = world_from_cam.rotation.matrix().cast::<f32>();
    let t = world_from_cam.translation.cast::<f32>();
    let origin = [t.x, t.y, t.z];
    out.par_chunks_mut(rays.width)
        .enumerate()
        .for_each(|(y, row)| {
            let start = y * rays.width;
            for (x, value) in row.iter_mut().enumerate() {
                let b = rays.bearings[start + x];
                if b[0].is_nan() {
                    *value = f32::NAN;
                    continue;
                }
                let d: Vector3<f32> = r * Vector3::new(b[0], b[1], b[2]);
                // A unit bearing b travelled `distance` reaches the camera-frame point
                // distance · b, whose depth is distance · b_z.
                *value = scene
                    .trace(origin, [d.x, d.y, d.z], rays.pixel_angle[start + x])
                    .map_or(f32::NAN, |h| h.distance * b[2]);
            }
        });
}

/// Renders into a new buffer; see [`render`].
pub fn render_image(scene: &Scene, rays: &RayTable, world_from_cam: &Se3) -> Vec<f32> {
    let mut out = vec![0.0; rays.len()];
    render(scene, rays, world_from_cam, &mut out);
    out
}
