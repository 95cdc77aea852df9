//! R2D2's detection heads, fused with the network's final bilinear 2× upsampling.
//!
//! In torch the fast R2D2 variant ends with a bilinear upsampling of its 128-channel map,
//! then squares it and applies two 1×1 convolutions: three passes that each read and write
//! a full-resolution 128-channel tensor, more time on the CPU than all the network's
//! convolutions after the first three. Here every output pixel interpolates its descriptor
//! from the four low-resolution neighbours, squares it and takes the three dot products in
//! registers; only the two score maps are written.

use rayon::prelude::*;

use crate::{Error, Result};

/// The heads' two 1×1 convolutions, both applied to the element-wise square of the
/// descriptor map: `clf` (2 outputs, softmax → reliability) and `sal` (1 output, softplus →
/// repeatability).
#[derive(Debug, Clone, Copy)]
pub struct HeadWeights<'a> {
    /// `3 × C` row-major: the two `clf` rows, then the `sal` row.
    pub weights: &'a [f32],
    /// Biases in the same order.
    pub bias: [f32; 3],
}

/// The network's map before the heads, `(batch, h, w, c)` channels-last.
#[derive(Debug, Clone, Copy)]
pub enum FeatureMap<'a> {
    /// float32 values.
    F32(&'a [f32]),
    /// bfloat16 values as their bit patterns (the upper half of the float32 bits), what a
    /// network run in bfloat16 produces; converted on the fly.
    Bf16(&'a [u16]),
}

impl FeatureMap<'_> {
    /// Number of values.
    pub fn len(&self) -> usize {
        match self {
            FeatureMap::F32(v) => v.len(),
            FeatureMap::Bf16(v) => v.len(),
        }
    }

    /// Whether the map holds no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// `out = wa · map[a..a + n] + wb · map[b..b + n]` in float32, `n = out.len()`.
    fn blend_rows(&self, a: usize, b: usize, wa: f32, wb: f32, out: &mut [f32]) {
        let n = out.len();
        match self {
            FeatureMap::F32(v) => {
                for ((d, x), y) in out.iter_mut().zip(&v[a..a + n]).zip(&v[b..b + n]) {
                    *d = wa * x + wb * y;
                }
            }
            FeatureMap::Bf16(v) => {
                let f = |bits: u16| f32::from_bits(u32::from(bits) << 16);
                for ((d, x), y) in out.iter_mut().zip(&v[a..a + n]).zip(&v[b..b + n]) {
                    *d = wa * f(*x) + wb * f(*y);
                }
            }
        }
    }
}

/// The heads' per-pixel outputs at the output resolution, each `(B, height, width)` row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct HeadMaps {
    /// Reliability in [0, 1]: the second channel of the `clf` softmax.
    pub reliability: Vec<f32>,
    /// Repeatability in [0, 1): `s / (1 + s)` with `s = softplus(sal)`.
    pub repeatability: Vec<f32>,
    /// Output rows (`h · upsample`).
    pub height: usize,
    /// Output columns (`w · upsample`).
    pub width: usize,
}

/// Source rows (or columns) and weights of output index `i` for a 2× bilinear upsampling of
/// `n` samples with half-pixel centres and clamped borders (torch's `align_corners=False`):
/// output `2m` reads `0.25·x[m−1] + 0.75·x[m]`, output `2m+1` reads `0.75·x[m] + 0.25·x[m+1]`,
/// and a neighbour outside `[0, n)` is replaced by the border sample.
fn taps(i: usize, n: usize) -> (usize, usize, f32, f32) {
    let m = i / 2;
    if i % 2 == 0 {
        if m == 0 {
            (0, 0, 1.0, 0.0)
        } else {
            (m - 1, m, 0.25, 0.75)
        }
    } else if m + 1 < n {
        (m, m + 1, 0.75, 0.25)
    } else {
        (m, m, 1.0, 0.0)
    }
}

const LANES: usize = 8;

/// `Σ_k w_j[k] · (wa·a[k] + wb·b[k])²` for the three rows `w_j` of `weights`.
#[inline]
fn squared_dots(a: &[f32], b: &[f32], wa: f32, wb: f32, weights: &[f32], c: usize) -> [f32; 3] {
    let (w0, rest) = weights.split_at(c);
    let (w1, w2) = rest.split_at(c);
    let mut acc = [[0.0f32; LANES]; 3];
    let body = c - c % LANES;
    for ((((a8, b8), x0), x1), x2) in a[..body]
        .chunks_exact(LANES)
        .zip(b[..body].chunks_exact(LANES))
        .zip(w0[..body].chunks_exact(LANES))
        .zip(w1[..body].chunks_exact(LANES))
        .zip(w2[..body].chunks_exact(LANES))
    {
        for l in 0..LANES {
            let u = wa * a8[l] + wb * b8[l];
            let q = u * u;
            acc[0][l] += x0[l] * q;
            acc[1][l] += x1[l] * q;
            acc[2][l] += x2[l] * q;
        }
    }
    let mut out = acc.map(|lanes| lanes.iter().sum::<f32>());
    for k in body..c {
        let u = wa * a[k] + wb * b[k];
        let q = u * u;
        out[0] += w0[k] * q;
        out[1] += w1[k] * q;
        out[2] += w2[k] * q;
    }
    out
}

/// `softplus(z) = ln(1 + eᶻ)`, evaluated without overflow.
fn softplus(z: f32) -> f32 {
    z.max(0.0) + (-z.abs()).exp().ln_1p()
}

/// R2D2's reliability and repeatability at every pixel of the (upsampled) descriptor map,
/// without materialising that map.
///
/// `features` is the network's output before its final upsampling, `(batch, h, w, c)`
/// channels-last, float32 or bfloat16; `upsample` is 1 (the map is already at full resolution: the heads only) or
/// 2 (bilinear, as described at [`taps`]). Per output pixel with descriptor `u`:
/// `z = W · (u ⊙ u) + b`, reliability `= 1 / (1 + exp(z₀ − z₁))` (the softmax's second
/// channel), repeatability `= s / (1 + s)` with `s = softplus(z₂)`. Output rows run in
/// parallel; the result does not depend on the thread count.
///
/// # Errors
/// [`Error::Invalid`] when the sizes disagree or `upsample` is neither 1 nor 2.
pub fn r2d2_heads(
    features: FeatureMap<'_>,
    shape: [usize; 4],
    upsample: usize,
    heads: &HeadWeights<'_>,
) -> Result<HeadMaps> {
    let [batch, h, w, c] = shape;
    if features.len() != batch * h * w * c {
        return Err(Error::invalid(
            "features",
            format!("{} values for the shape {shape:?}", batch * h * w * c),
            format!("{} values", features.len()),
        ));
    }
    if heads.weights.len() != 3 * c {
        return Err(Error::invalid(
            "weights",
            format!("3 × {c} values (three rows of the channel count)"),
            format!("{} values", heads.weights.len()),
        ));
    }
    if upsample != 1 && upsample != 2 {
        return Err(Error::invalid("upsample", "1 or 2", upsample.to_string()));
    }
    let (height, width) = (h * upsample, w * upsample);
    let mut reliability = vec![0.0f32; batch * height * width];
    let mut repeatability = vec![0.0f32; batch * height * width];
    if reliability.is_empty() || c == 0 {
        return Ok(HeadMaps {
            reliability,
            repeatability,
            height,
            width,
        });
    }
    let row_len = w * c;
    reliability
        .par_chunks_mut(width)
        .zip(repeatability.par_chunks_mut(width))
        .enumerate()
        .for_each_init(
            || vec![0.0f32; row_len],
            |row, (r, (rel, rep))| {
                let (b, i) = (r / height, r % height);
                // The output row's descriptors before the column interpolation.
                let (r0, r1, w0, w1) = if upsample == 1 {
                    (i, i, 1.0, 0.0)
                } else {
                    taps(i, h)
                };
                let at = |y: usize| (b * h + y) * row_len;
                features.blend_rows(at(r0), at(r1), w0, w1, row);
                let line: &[f32] = row;
                for (j, (rel, rep)) in rel.iter_mut().zip(rep.iter_mut()).enumerate() {
                    let (c0, c1, w0, w1) = if upsample == 1 {
                        (j, j, 1.0, 0.0)
                    } else {
                        taps(j, w)
                    };
                    let z = squared_dots(
                        &line[c0 * c..(c0 + 1) * c],
                        &line[c1 * c..(c1 + 1) * c],
                        w0,
                        w1,
                        heads.weights,
                        c,
                    );
                    let z = [
                        z[0] + heads.bias[0],
                        z[1] + heads.bias[1],
                        z[2] + heads.bias[2],
                    ];
                    *rel = 1.0 / (1.0 + (z[0] - z[1]).exp());
                    let s = softplus(z[2]);
                    *rep = s / (1.0 + s);
                }
            },
        );
    Ok(HeadMaps {
        reliability,
        repeatability,
        height,
        width,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The straightforward definition: upsample the whole map, square, three dot products.
    fn reference(
        x: &[f32],
        [b, h, w, c]: [usize; 4],
        up: usize,
        wt: &[f32],
        bias: [f32; 3],
    ) -> HeadMaps {
        let (hh, ww) = (h * up, w * up);
        let at =
            |bi: usize, y: usize, xx: usize, k: usize| x[((bi * h + y) * w + xx) * c + k] as f64;
        let mut rel = vec![];
        let mut rep = vec![];
        for bi in 0..b {
            for i in 0..hh {
                for j in 0..ww {
                    let (r0, r1, a0, a1) = if up == 1 {
                        (i, i, 1.0, 0.0)
                    } else {
                        taps(i, h)
                    };
                    let (c0, c1, b0, b1) = if up == 1 {
                        (j, j, 1.0, 0.0)
                    } else {
                        taps(j, w)
                    };
                    let mut z = [bias[0] as f64, bias[1] as f64, bias[2] as f64];
                    for k in 0..c {
                        let u = a0 as f64
                            * (b0 as f64 * at(bi, r0, c0, k) + b1 as f64 * at(bi, r0, c1, k))
                            + a1 as f64
                                * (b0 as f64 * at(bi, r1, c0, k) + b1 as f64 * at(bi, r1, c1, k));
                        for (o, zo) in z.iter_mut().enumerate() {
                            *zo += wt[o * c + k] as f64 * u * u;
                        }
                    }
                    rel.push((z[1].exp() / (z[0].exp() + z[1].exp())) as f32);
                    let s = (1.0 + z[2].exp()).ln();
                    rep.push((s / (1.0 + s)) as f32);
                }
            }
        }
        HeadMaps {
            reliability: rel,
            repeatability: rep,
            height: hh,
            width: ww,
        }
    }

    fn pseudo_random(n: usize, seed: u32) -> Vec<f32> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                (s >> 8) as f32 / (1u32 << 24) as f32 - 0.5
            })
            .collect()
    }

    #[test]
    fn fused_heads_match_the_straightforward_definition() {
        // 13 channels: one 8-lane block and a remainder; odd sizes exercise the borders.
        for (shape, up) in [([2, 5, 7, 13], 2), ([1, 4, 3, 16], 1), ([1, 1, 1, 9], 2)] {
            let x = pseudo_random(shape.iter().product(), 7);
            let wt: Vec<f32> = pseudo_random(3 * shape[3], 11)
                .iter()
                .map(|v| 4.0 * v)
                .collect();
            let bias = [0.1, -0.2, 0.3];
            let heads = HeadWeights { weights: &wt, bias };
            let got = r2d2_heads(FeatureMap::F32(&x), shape, up, &heads).unwrap();
            let want = reference(&x, shape, up, &wt, bias);
            assert_eq!((got.height, got.width), (want.height, want.width));
            for (g, w) in got
                .reliability
                .iter()
                .zip(&want.reliability)
                .chain(got.repeatability.iter().zip(&want.repeatability))
            {
                assert!((g - w).abs() < 1e-6, "{g} vs {w} for {shape:?} × {up}");
            }
        }
    }

    #[test]
    fn bfloat16_input_reads_as_its_float32_value() {
        // Values exactly representable in bfloat16 (8 significant bits) give identical maps.
        let shape = [1, 3, 4, 16];
        let x: Vec<f32> = pseudo_random(3 * 4 * 16, 3)
            .iter()
            .map(|v| f32::from_bits(v.to_bits() & 0xFFFF_0000))
            .collect();
        let bits: Vec<u16> = x.iter().map(|v| (v.to_bits() >> 16) as u16).collect();
        let wt = pseudo_random(48, 5);
        let heads = HeadWeights {
            weights: &wt,
            bias: [0.0; 3],
        };
        let a = r2d2_heads(FeatureMap::F32(&x), shape, 2, &heads).unwrap();
        let b = r2d2_heads(FeatureMap::Bf16(&bits), shape, 2, &heads).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn taps_reproduce_half_pixel_bilinear_upsampling() {
        // n = 3: outputs 0..6 read 0, (0,1)·(.75,.25) … and clamp at both borders.
        assert_eq!(taps(0, 3), (0, 0, 1.0, 0.0));
        assert_eq!(taps(1, 3), (0, 1, 0.75, 0.25));
        assert_eq!(taps(2, 3), (0, 1, 0.25, 0.75));
        assert_eq!(taps(5, 3), (2, 2, 1.0, 0.0));
    }

    #[test]
    fn bad_sizes_are_refused() {
        let w = [0.0f32; 6];
        let heads = HeadWeights {
            weights: &w,
            bias: [0.0; 3],
        };
        let map = |n: usize| FeatureMap::F32(&[0.0; 12][..n]);
        assert!(r2d2_heads(map(7), [1, 2, 2, 2], 2, &heads).is_err());
        assert!(r2d2_heads(map(8), [1, 2, 2, 2], 3, &heads).is_err());
        assert!(r2d2_heads(map(12), [1, 2, 2, 3], 2, &heads).is_err());
    }
}
