//! The written trajectory's smoother: camera centres re-estimated from every tracked frame at
//! once, each frame weighted by the covariance its own pose refinement measured, under a
//! white-noise-acceleration motion prior.
//!
//! Tracking places each frame against the map alone, so its pose carries that frame's
//! measurement noise; event images give keypoints about twice as scattered as frames and
//! fewer of them, and the narrow field of view turns that into centre errors of several
//! millimetres along the direction a small rotation can mimic (docs/BENCHMARKS.md, "The
//! trajectory smoother"). Over a segment of `n` frames at times `t_k` the smoother minimises
//!
//! ```text
//! Σ_k (c_k − m_k)ᵀ Λ_k (c_k − m_k)  +  Σ_k τ_k ‖a_k‖² / q
//! a_k = 2 / (Δ₋ + Δ₊) · ((c_{k+1} − c_k)/Δ₊ − (c_k − c_{k−1})/Δ₋),   τ_k = (Δ₋ + Δ₊)/2
//! ```
//!
//! over the centres `c`, with `m_k` the tracked centre, `Λ_k` the inverse of its covariance
//! (the tracker's `s² (JᵀJ)⁻¹`, rotated into the world), `a_k` the acceleration at frame `k`
//! from its neighbours `Δ₋`, `Δ₊` seconds away and `q` (m²/s³) the spectral density of the
//! acceleration noise: the second sum is the discretised `∫ ‖a‖² dt / q`, the negative log
//! density of a white-noise-acceleration motion. A precise frame keeps its centre; a noisy one
//! is pulled towards the motion its neighbours imply, by as much as its own covariance allows
//! along each direction. Frames without a measurement (predictions) have no first term and
//! are placed by the prior alone. Orientations are left as tracked.
//!
//! The normal equations are block pentadiagonal (3 × 3 blocks) and solved by the sparse
//! Cholesky factorisation the bundle adjustment uses.

use nalgebra::{Matrix3, Vector3};

use crate::error::{Error, Result};
use crate::solver::linear::{BlockCholesky, BlockPattern};
use crate::solver::LinearSolver;

/// One frame of a segment to smooth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CentreSample {
    /// Time, seconds (any origin), increasing along the segment.
    pub t_s: f64,
    /// Tracked camera centre, world frame, metres.
    pub centre: Vector3<f64>,
    /// Inverse covariance of `centre`, 1/m², world axes; `None`: no measurement.
    pub information: Option<Matrix3<f64>>,
}

/// The smoothed centres of `samples` (one segment, times strictly increasing) under
/// acceleration-noise density `q` (m²/s³, > 0). Fewer than three samples, or fewer than two
/// with information, are returned as given.
pub fn smooth_centres(samples: &[CentreSample], q: f64) -> Result<Vec<Vector3<f64>>> {
    if !(q.is_finite() && q > 0.0) {
        return Err(Error::invalid("q", "finite and > 0", q));
    }
    let n = samples.len();
    let measured = samples.iter().filter(|s| s.information.is_some()).count();
    if n < 3 || measured < 2 {
        return Ok(samples.iter().map(|s| s.centre).collect());
    }
    if let Some(w) = samples
        .windows(2)
        .find(|w| w[1].t_s.partial_cmp(&w[0].t_s) != Some(std::cmp::Ordering::Greater))
    {
        return Err(Error::invalid(
            "samples",
            "strictly increasing times",
            format!("{} then {}", w[0].t_s, w[1].t_s),
        ));
    }
    let pairs = (0..n - 1).flat_map(|k| [(k, k + 1), (k, (k + 2).min(n - 1))]);
    let pattern = BlockPattern::new(n, 3, pairs);
    let mut values = pattern.zeros();
    let mut rhs = vec![0.0; 3 * n];
    // Adds `m` to block (i, k), stored as the upper block (min, max).
    let add = |values: &mut [f64], i: usize, k: usize, m: &Matrix3<f64>| {
        let (i, k) = (i.min(k), i.max(k));
        let slot = pattern.slot(i, k).expect("block in the pattern");
        let block = &mut values[slot * 9..slot * 9 + 9];
        for c in 0..3 {
            for r in 0..3 {
                block[c * 3 + r] += m[(r, c)];
            }
        }
    };
    for (k, s) in samples.iter().enumerate() {
        if let Some(info) = &s.information {
            add(&mut values, k, k, info);
            let b = info * s.centre;
            rhs[3 * k..3 * k + 3].copy_from_slice(b.as_slice());
        }
    }
    for k in 1..n - 1 {
        let (dm, dp) = (
            samples[k].t_s - samples[k - 1].t_s,
            samples[k + 1].t_s - samples[k].t_s,
        );
        let span = dm + dp;
        let coeff = [2.0 / (span * dm), -2.0 / (dm * dp), 2.0 / (span * dp)];
        let weight = 0.5 * span / q;
        for (a, &ca) in coeff.iter().enumerate() {
            for (b, &cb) in coeff.iter().enumerate().skip(a) {
                let v = weight * ca * cb;
                // A diagonal block receives v once; an off-diagonal pair's upper block too
                // (the solver mirrors it).
                add(
                    &mut values,
                    k - 1 + a,
                    k - 1 + b,
                    &Matrix3::from_diagonal_element(v),
                );
            }
        }
    }
    let mut cholesky = BlockCholesky::new(&pattern, LinearSolver::Auto, 1)?;
    if !cholesky.solve(&pattern, &values, &mut rhs) {
        return Err(Error::numerical(
            "trajectory smoother",
            "normal equations not positive definite",
        ));
    }
    Ok((0..n)
        .map(|k| Vector3::new(rhs[3 * k], rhs[3 * k + 1], rhs[3 * k + 2]))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn samples(centres: &[Vector3<f64>], sigma: f64) -> Vec<CentreSample> {
        centres
            .iter()
            .enumerate()
            .map(|(k, &c)| CentreSample {
                t_s: 0.05 * k as f64,
                centre: c,
                information: Some(Matrix3::identity() / (sigma * sigma)),
            })
            .collect()
    }

    #[test]
    fn constant_velocity_is_a_fixed_point() {
        let c: Vec<_> = (0..20)
            .map(|k| Vector3::new(0.01 * k as f64, -0.02 * k as f64, 0.3))
            .collect();
        let out = smooth_centres(&samples(&c, 0.01), 1e-4).unwrap();
        for (a, b) in out.iter().zip(&c) {
            assert!((a - b).norm() < 1e-9, "{a} vs {b}");
        }
    }

    #[test]
    fn noise_shrinks_with_its_covariance() {
        // Alternating ±5 mm noise on a straight line: a noisy measurement (σ 10 mm) is pulled
        // onto the line, a precise one (σ 0.01 mm) stays where it was measured.
        let truth: Vec<_> = (0..40)
            .map(|k| Vector3::new(0.002 * k as f64, 0.0, 1.0))
            .collect();
        let noisy: Vec<_> = truth
            .iter()
            .enumerate()
            .map(|(k, c)| c + Vector3::new(0.0, if k % 2 == 0 { 0.005 } else { -0.005 }, 0.0))
            .collect();
        let q = 0.01;
        let loose = smooth_centres(&samples(&noisy, 0.01), q).unwrap();
        let tight = smooth_centres(&samples(&noisy, 1e-5), q).unwrap();
        let rms = |v: &[Vector3<f64>]| {
            (v.iter()
                .zip(&truth)
                .map(|(a, b)| (a - b).norm_squared())
                .sum::<f64>()
                / v.len() as f64)
                .sqrt()
        };
        assert!(rms(&loose) < 0.001, "loose {}", rms(&loose));
        assert!(rms(&tight) > 0.0049, "tight {}", rms(&tight));
    }

    #[test]
    fn anisotropic_information_moves_only_the_uncertain_axis() {
        let truth: Vec<_> = (0..30)
            .map(|k| Vector3::new(0.0, 0.0, 0.003 * k as f64))
            .collect();
        let mut s: Vec<_> = truth
            .iter()
            .enumerate()
            .map(|(k, c)| CentreSample {
                t_s: 0.05 * k as f64,
                centre: c + Vector3::new(if k % 2 == 0 { 0.004 } else { -0.004 }, 0.0, 0.0),
                // x uncertain (σ 10 mm), y and z precise (σ 0.1 mm).
                information: Some(Matrix3::from_diagonal(&Vector3::new(1e4, 1e8, 1e8))),
            })
            .collect();
        // A gap of predictions in the middle is bridged by the prior alone.
        for p in s.iter_mut().skip(12).take(3) {
            p.information = None;
            p.centre = Vector3::new(1.0, 1.0, 1.0);
        }
        let out = smooth_centres(&s, 0.01).unwrap();
        for (k, (o, t)) in out.iter().zip(&truth).enumerate() {
            assert!(
                (o.x - t.x).abs() < 0.0015,
                "frame {k}: x {} vs {}",
                o.x,
                t.x
            );
            assert!((o.z - t.z).abs() < 1e-4, "frame {k}: z {} vs {}", o.z, t.z);
        }
    }

    #[test]
    fn bad_input_is_refused() {
        let c = [Vector3::zeros(); 4];
        assert!(smooth_centres(&samples(&c, 0.01), 0.0).is_err());
        let mut s = samples(&c, 0.01);
        s[2].t_s = s[1].t_s;
        assert!(smooth_centres(&s, 1.0).is_err());
        // Too short to smooth: returned as given.
        assert_eq!(
            smooth_centres(&s[..2], 1.0).unwrap(),
            vec![Vector3::zeros(); 2]
        );
    }
}
