//! Grey-level textures with a mip pyramid and trilinear lookup, plus procedural textures.
//!
//! A texture holds reflectance in [0, 1] (linear, not gamma-encoded). A lookup takes the texture
//! coordinates `(s, t)` (one unit = one copy of the texture) and the footprint of the pixel
//! on the texture in level-0 texels; it blends the two mip levels around `log2(footprint)`
//! with bilinear interpolation in each (trilinear filtering). Filtering matters here more than
//! for looks: texture detail finer than a pixel would flicker from render to render and the
//! event generator would turn that flicker into spurious events.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::error::{Error, Result};

/// What happens outside `[0, 1)` texture coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wrap {
    /// Tile the texture.
    Repeat,
    /// Clamp to the border texels (a single poster or photograph).
    Clamp,
}

#[derive(Clone, Debug)]
struct Level {
    width: usize,
    height: usize,
    texels: Vec<f32>,
}

impl Level {
    /// Bilinear lookup; texel centres sit at integer + ½ in units of texels.
    #[inline]
    fn bilinear(&self, s: f32, t: f32, wrap: Wrap) -> f32 {
        let (x0, x1, fx) = neighbours(s, self.width, wrap);
        let (y0, y1, fy) = neighbours(t, self.height, wrap);
        let (r0, r1) = (y0 * self.width, y1 * self.width);
        let tx = &self.texels;
        let top = tx[r0 + x0] * (1.0 - fx) + tx[r0 + x1] * fx;
        let bottom = tx[r1 + x0] * (1.0 - fx) + tx[r1 + x1] * fx;
        top * (1.0 - fy) + bottom * fy
    }

    /// The next coarser level: 2×2 box average (odd sizes keep their last row/column).
    fn halve(&self) -> Level {
        let width = self.width.div_ceil(2);
        let height = self.height.div_ceil(2);
        let mut texels = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                let mut sum = 0.0;
                let mut n = 0.0;
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (sx, sy) = (2 * x + dx, 2 * y + dy);
                    if sx < self.width && sy < self.height {
                        sum += self.texels[sy * self.width + sx];
                        n += 1.0;
                    }
                }
                texels.push(sum / n);
            }
        }
        Level {
            width,
            height,
            texels,
        }
    }
}

/// A mip-mapped grey texture.
#[derive(Clone, Debug)]
pub struct Texture {
    levels: Vec<Level>,
}

impl Texture {
    /// A texture from row-major reflectances in [0, 1].
    pub fn new(width: usize, height: usize, texels: Vec<f32>) -> Result<Self> {
        if width == 0 || height == 0 || texels.len() != width * height {
            return Err(Error::invalid(
                "texture",
                "a non-empty width × height array",
                format!("{width}×{height} with {} values", texels.len()),
            ));
        }
        if let Some(i) = texels
            .iter()
            .position(|v| !v.is_finite() || !(0.0..=1.0).contains(v))
        {
            return Err(Error::invalid(
                format!("texture[{}, {}]", i / width, i % width),
                "a reflectance in [0, 1]",
                texels[i],
            ));
        }
        let mut levels = vec![Level {
            width,
            height,
            texels,
        }];
        while let Some(last) = levels.last() {
            if last.width == 1 && last.height == 1 {
                break;
            }
            let next = last.halve();
            levels.push(next);
        }
        Ok(Self { levels })
    }

    /// A texture from 8-bit grey values (0 → 0, 255 → 1).
    pub fn from_u8(width: usize, height: usize, values: &[u8]) -> Result<Self> {
        Self::new(
            width,
            height,
            values.iter().map(|&v| f32::from(v) / 255.0).collect(),
        )
    }

    /// Width of the full-resolution level, texels.
    pub fn width(&self) -> usize {
        self.levels[0].width
    }

    /// Height of the full-resolution level, texels.
    pub fn height(&self) -> usize {
        self.levels[0].height
    }

    /// Number of mip levels (1 for a 1×1 texture).
    pub fn level_count(&self) -> usize {
        self.levels.len()
    }

    /// Trilinear lookup at texture coordinates `(s, t)` for a pixel covering `footprint`
    /// level-0 texels (across); footprints of one texel or less read level 0 bilinearly.
    #[inline]
    pub fn sample(&self, s: f32, t: f32, footprint: f32, wrap: Wrap) -> f32 {
        let lod = if footprint > 1.0 {
            footprint.log2()
        } else {
            0.0
        };
        let top = (self.levels.len() - 1) as f32;
        let lod = lod.min(top);
        let l0 = lod.floor() as usize;
        let f = lod - l0 as f32;
        let a = self.levels[l0].bilinear(s, t, wrap);
        if f <= 0.0 || l0 + 1 >= self.levels.len() {
            return a;
        }
        a * (1.0 - f) + self.levels[l0 + 1].bilinear(s, t, wrap) * f
    }

    /// Fractal value noise: `octaves` layers of smoothly interpolated random lattices, each
    /// with twice the frequency and `persistence` times the amplitude of the previous one,
    /// stretched to span `[lo, hi]`. Tiles seamlessly (the lattices wrap).
    pub fn value_noise(
        size: usize,
        base_cells: usize,
        octaves: u32,
        persistence: f32,
        (lo, hi): (f32, f32),
        seed: u64,
    ) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut acc = vec![0.0f32; size * size];
        let mut amplitude = 1.0;
        for octave in 0..octaves {
            let cells = base_cells << octave;
            let lattice: Vec<f32> = (0..cells * cells).map(|_| rng.random::<f32>()).collect();
            let at = |i: usize, j: usize| lattice[(j % cells) * cells + (i % cells)];
            for y in 0..size {
                let gy = (y as f32 + 0.5) * cells as f32 / size as f32;
                let (j, fy) = (gy.floor() as usize, smooth(gy.fract()));
                for x in 0..size {
                    let gx = (x as f32 + 0.5) * cells as f32 / size as f32;
                    let (i, fx) = (gx.floor() as usize, smooth(gx.fract()));
                    let top = at(i, j) * (1.0 - fx) + at(i + 1, j) * fx;
                    let bottom = at(i, j + 1) * (1.0 - fx) + at(i + 1, j + 1) * fx;
                    acc[y * size + x] += amplitude * (top * (1.0 - fy) + bottom * fy);
                }
            }
            amplitude *= persistence;
        }
        stretch(&mut acc, lo, hi);
        Self::new(size, size, acc).expect("stretched noise lies in [lo, hi] ⊂ [0, 1]")
    }

    /// Tiles: a `count × count` grid of squares with random grey levels in `[lo, hi]`,
    /// separated by dark grout lines, overlaid with fine noise.
    pub fn tiles(size: usize, count: usize, (lo, hi): (f32, f32), seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let shades: Vec<f32> = (0..count * count)
            .map(|_| lo + (hi - lo) * rng.random::<f32>())
            .collect();
        let grain = Self::value_noise(size, 16, 3, 0.5, (0.0, 1.0), seed ^ 0x9e37);
        let cell = size as f32 / count as f32;
        let grout = (cell * 0.06).max(1.0);
        let texels = (0..size * size)
            .map(|k| {
                let (x, y) = ((k % size) as f32 + 0.5, (k / size) as f32 + 0.5);
                let (cx, cy) = ((x / cell) as usize, (y / cell) as usize);
                let (fx, fy) = (x % cell, y % cell);
                let base = if fx < grout || fy < grout {
                    lo * 0.5
                } else {
                    shades[cy.min(count - 1) * count + cx.min(count - 1)]
                };
                (base * (0.85 + 0.3 * grain.levels[0].texels[k])).clamp(0.0, 1.0)
            })
            .collect();
        Self::new(size, size, texels).expect("tile shades are clamped to [0, 1]")
    }
}

/// The two texels around texture coordinate `s` along an axis of `n` texels, and the weight
/// of the second. Wrapping happens in floating point first (`s − ⌊s⌋`), so the indices need
/// at most one correction instead of an integer remainder per texel.
#[inline]
fn neighbours(s: f32, n: usize, wrap: Wrap) -> (usize, usize, f32) {
    let last = n as i64 - 1;
    match wrap {
        Wrap::Repeat => {
            let x = (s - s.floor()) * n as f32 - 0.5; // in [−½, n − ½)
            let x0 = x.floor();
            let f = x - x0;
            let i0 = x0 as i64; // −1 ..= n − 1
            let a = if i0 < 0 { last } else { i0.min(last) };
            let b = if i0 + 1 > last { 0 } else { i0 + 1 };
            (a as usize, b as usize, f)
        }
        Wrap::Clamp => {
            let x = (s * n as f32 - 0.5).clamp(-1.0, n as f32);
            let x0 = x.floor();
            let f = x - x0;
            let i0 = x0 as i64;
            (
                (i0.clamp(0, last)) as usize,
                ((i0 + 1).clamp(0, last)) as usize,
                f,
            )
        }
    }
}

/// Smoothstep 3f² − 2f³: C¹ interpolation weights for value noise.
fn smooth(f: f32) -> f32 {
    f * f * (3.0 - 2.0 * f)
}

/// Affinely maps the values onto `[lo, hi]`.
fn stretch(values: &mut [f32], lo: f32, hi: f32) {
    let min = values.iter().copied().fold(f32::INFINITY, f32::min);
    let max = values.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let span = (max - min).max(1e-12);
    for v in values.iter_mut() {
        *v = (lo + (hi - lo) * (*v - min) / span).clamp(lo.min(hi), hi.max(lo));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_reproduces_a_linear_ramp_between_texel_centres() {
        let w = 8;
        let texels: Vec<f32> = (0..w * 2).map(|k| (k % w) as f32 / 10.0).collect();
        let tex = Texture::new(w, 2, texels).unwrap();
        // Texel x has its centre at s = (x + ½)/w and value x/10.
        for x in [1.25f32, 3.5, 6.0] {
            let s = (x + 0.5) / w as f32;
            assert!((tex.sample(s, 0.5, 1.0, Wrap::Clamp) - x / 10.0).abs() < 1e-6);
        }
    }

    #[test]
    fn coarse_footprint_reads_the_average() {
        // A 1-texel checkerboard averages to ½ once the footprint covers the whole texture.
        let n = 16;
        let texels = (0..n * n).map(|k| ((k % n + k / n) % 2) as f32).collect();
        let tex = Texture::new(n, n, texels).unwrap();
        assert_eq!(tex.level_count(), 5);
        assert!((tex.sample(0.3, 0.7, 64.0, Wrap::Repeat) - 0.5).abs() < 1e-6);
        assert!((tex.sample(0.3, 0.7, 2.0, Wrap::Repeat) - 0.5).abs() < 1e-6);
        assert!(tex.sample(0.5 / n as f32, 0.5 / n as f32, 1.0, Wrap::Repeat) < 1e-6);
    }

    #[test]
    fn rejects_out_of_range_texels() {
        assert!(Texture::new(2, 1, vec![0.5, 1.5]).is_err());
        assert!(Texture::new(2, 2, vec![0.5; 3]).is_err());
        assert!(Texture::new(1, 1, vec![f32::NAN]).is_err());
    }

    #[test]
    fn procedural_textures_are_deterministic_and_in_range() {
        let a = Texture::value_noise(64, 4, 4, 0.5, (0.2, 0.8), 7);
        let b = Texture::value_noise(64, 4, 4, 0.5, (0.2, 0.8), 7);
        assert_eq!(a.levels[0].texels, b.levels[0].texels);
        let t = Texture::tiles(64, 4, (0.3, 0.9), 3);
        assert!(t.levels[0].texels.iter().all(|v| (0.0..=1.0).contains(v)));
    }
}
