//! Robust losses ρ(s) of the squared residual norm s = ‖r‖², and the corrector that folds them
//! into a Gauss–Newton step.
//!
//! The cost of a residual block is ½ρ(s). With ρ' and ρ'' its derivatives, the second-order
//! model of ½ρ(‖r + Jδ‖²) is matched by a rescaled residual r̃ = √ρ' / (1 − α) · r and Jacobian
//! J̃ = √ρ' (I − α r rᵀ / s) J, where α solves ½α² − α = ρ'' s / ρ' (Triggs et al., "Bundle
//! adjustment — a modern synthesis", §4.3). Where ρ'' ≤ 0 (Huber, Cauchy, Tukey in their
//! down-weighting region) the root is taken as α = 0: plain iteratively reweighted least
//! squares, which keeps the model Hessian positive semi-definite.

use nalgebra::{SMatrix, SVector};
use serde::{Deserialize, Serialize};

/// A robust loss with scale δ (the residual norm where it departs from the quadratic).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub enum Loss {
    /// ρ(s) = s: ordinary least squares.
    #[default]
    Trivial,
    /// ρ(s) = s for s ≤ δ², 2δ√s − δ² beyond: linear growth of the cost.
    Huber(f64),
    /// ρ(s) = δ² ln(1 + s/δ²): logarithmic growth.
    Cauchy(f64),
    /// ρ(s) = δ²/3 (1 − (1 − s/δ²)³) for s ≤ δ², δ²/3 beyond: outliers carry no gradient.
    Tukey(f64),
}

impl Loss {
    /// [ρ(s), ρ'(s), ρ''(s)].
    pub fn evaluate(&self, s: f64) -> [f64; 3] {
        match *self {
            Loss::Trivial => [s, 1.0, 0.0],
            Loss::Huber(delta) => {
                let d2 = delta * delta;
                if s <= d2 {
                    [s, 1.0, 0.0]
                } else {
                    let r = s.sqrt();
                    [2.0 * delta * r - d2, delta / r, -0.5 * delta / (s * r)]
                }
            }
            Loss::Cauchy(delta) => {
                let d2 = delta * delta;
                let inv = 1.0 / (1.0 + s / d2);
                [d2 * (s / d2).ln_1p(), inv, -inv * inv / d2]
            }
            Loss::Tukey(delta) => {
                let d2 = delta * delta;
                if s <= d2 {
                    let u = 1.0 - s / d2;
                    [d2 / 3.0 * (1.0 - u * u * u), u * u, -2.0 * u / d2]
                } else {
                    [d2 / 3.0, 0.0, 0.0]
                }
            }
        }
    }

    /// The scale δ, `None` for the trivial loss.
    /// The corrector for a residual block of squared norm `s`, or `None` for the trivial
    /// loss (whose residuals and Jacobians are used as they are).
    pub fn corrector(&self, s: f64) -> Option<Corrector> {
        (*self != Loss::Trivial).then(|| Corrector::new(self, s))
    }

    pub fn scale(&self) -> Option<f64> {
        match *self {
            Loss::Trivial => None,
            Loss::Huber(d) | Loss::Cauchy(d) | Loss::Tukey(d) => Some(d),
        }
    }
}

/// The rescaling of one residual block under a loss (see the module docs).
#[derive(Clone, Copy, Debug)]
pub struct Corrector {
    /// Factor on the residual, √ρ' / (1 − α).
    pub residual_scale: f64,
    /// √ρ'.
    pub sqrt_rho1: f64,
    /// α / s: the Jacobian becomes √ρ' (J − (α/s) r (rᵀJ)).
    pub alpha_over_s: f64,
}

impl Corrector {
    /// The corrector for a block with squared norm `s` under `loss`.
    pub fn new(loss: &Loss, s: f64) -> Self {
        let [_, rho1, rho2] = loss.evaluate(s);
        let sqrt_rho1 = rho1.max(0.0).sqrt();
        if s == 0.0 || rho2 <= 0.0 || rho1 <= 0.0 {
            return Self {
                residual_scale: sqrt_rho1,
                sqrt_rho1,
                alpha_over_s: 0.0,
            };
        }
        // ½α² − α − ρ''s/ρ' = 0, smaller root; the argument of the root is ≥ 1 here.
        let alpha = 1.0 - (1.0 + 2.0 * s * rho2 / rho1).sqrt();
        Self {
            residual_scale: sqrt_rho1 / (1.0 - alpha),
            sqrt_rho1,
            alpha_over_s: alpha / s,
        }
    }

    /// Whether the Jacobian needs more than a scalar factor.
    pub fn is_scalar(&self) -> bool {
        self.alpha_over_s == 0.0
    }

    /// Corrects the Jacobian of one parameter block, J ← √ρ' (J − (α/s) r (rᵀJ)), for the
    /// block's residual `r` as it was before [`Corrector::correct_residual`].
    #[inline]
    pub fn correct_jacobian<const R: usize, const N: usize>(
        &self,
        r: &SVector<f64, R>,
        j: &mut SMatrix<f64, R, N>,
    ) {
        if !self.is_scalar() {
            let rtj = r.transpose() * *j;
            *j -= r * rtj * self.alpha_over_s;
        }
        *j *= self.sqrt_rho1;
    }

    /// Corrects the residual, r ← r √ρ' / (1 − α). Call after the Jacobians are corrected.
    #[inline]
    pub fn correct_residual<const R: usize>(&self, r: &mut SVector<f64, R>) {
        *r *= self.residual_scale;
    }
}
