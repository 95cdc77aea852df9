//! SE(3), rigid-body transforms `p ↦ R p + t`.
//!
//! Tangent vectors are ξ = [ρ; φ] ∈ ℝ⁶, translation part first (the Sophus order), and
//! `exp(ξ) = (exp(φ), J_l(φ) ρ)`. The 6×6 Jacobians are Barfoot's (2017, §7.1.5):
//!
//! ```text
//! J_l(ξ) = [ J_l(φ)  Q(ρ, φ) ]      J_l⁻¹(ξ) = [ J_l⁻¹(φ)  −J_l⁻¹(φ) Q J_l⁻¹(φ) ]
//!          [   0     J_l(φ)  ]                 [    0            J_l⁻¹(φ)        ]
//! exp(ξ + δ) ≈ exp(J_l(ξ) δ) · exp(ξ),      J_r(ξ) = J_l(−ξ)
//! ```
//!
//! Names carry the frames a transform maps between: `world_from_cam * p_cam = p_world`.

use std::ops::Mul;

use nalgebra::{Matrix3, Matrix4, Matrix6, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use super::so3::{alternating_series, hat, So3, SERIES_ANGLE};
use crate::error::Result;

/// A rigid-body transform. `a_from_b * b_from_c = a_from_c`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Se3 {
    /// Rotation part.
    pub rotation: So3,
    /// Translation part (the origin of the source frame expressed in the target frame).
    pub translation: Vector3<f64>,
}

impl Se3 {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            rotation: So3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// From a rotation and a translation.
    pub fn new(rotation: So3, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    /// From translation (x, y, z) and a quaternion in (x, y, z, w) order — the TUM line layout.
    pub fn from_translation_quaternion_xyzw(t: [f64; 3], q_xyzw: [f64; 4]) -> Result<Self> {
        crate::error::ensure_finite("translation", &t)?;
        Ok(Self {
            rotation: So3::from_quaternion_xyzw(q_xyzw)?,
            translation: Vector3::from(t),
        })
    }

    /// From a 4×4 homogeneous matrix whose last row is (0, 0, 0, 1).
    pub fn from_matrix(m: &Matrix4<f64>) -> Result<Self> {
        crate::error::ensure_finite("transform matrix", m.as_slice())?;
        let last = m.fixed_view::<1, 4>(3, 0);
        if (last - nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0)).norm() > 1e-9 {
            return Err(crate::error::Error::invalid(
                "transform matrix",
                "last row (0, 0, 0, 1)",
                format!("{last}"),
            ));
        }
        let rotation = So3::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned())?;
        Ok(Self {
            rotation,
            translation: m.fixed_view::<3, 1>(0, 3).into_owned(),
        })
    }

    /// The 4×4 homogeneous matrix.
    pub fn matrix(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&self.rotation.matrix());
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.translation);
        m
    }

    /// The exponential map of ξ = [ρ; φ].
    pub fn exp(xi: &Vector6<f64>) -> Self {
        let rho = xi.fixed_rows::<3>(0).into_owned();
        let phi = xi.fixed_rows::<3>(3).into_owned();
        Self {
            rotation: So3::exp(&phi),
            translation: So3::left_jacobian(&phi) * rho,
        }
    }

    /// The logarithm ξ = [ρ; φ], rotation angle in [0, π].
    pub fn log(&self) -> Vector6<f64> {
        let phi = self.rotation.log();
        let rho = So3::left_jacobian_inverse(&phi) * self.translation;
        let mut xi = Vector6::zeros();
        xi.fixed_rows_mut::<3>(0).copy_from(&rho);
        xi.fixed_rows_mut::<3>(3).copy_from(&phi);
        xi
    }

    /// The inverse transform: `a_from_b.inverse() = b_from_a`.
    pub fn inverse(&self) -> Self {
        let r_inv = self.rotation.inverse();
        Self {
            rotation: r_inv,
            translation: -(r_inv * self.translation),
        }
    }

    /// Applies the transform to a point.
    pub fn transform_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        &self.rotation * p + self.translation
    }

    /// The adjoint `Ad(T) = [[R, t^ R], [0, R]]`, so that `T exp(ξ) T⁻¹ = exp(Ad(T) ξ)`.
    pub fn adjoint(&self) -> Matrix6<f64> {
        let r = self.rotation.matrix();
        let mut ad = Matrix6::zeros();
        ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        ad.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(hat(&self.translation) * r));
        ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
        ad
    }

    /// Geodesic interpolation: `s = 0` gives `self`, `s = 1` gives `other`.
    pub fn interpolate(&self, other: &Se3, s: f64) -> Se3 {
        *self * Se3::exp(&((self.inverse() * *other).log() * s))
    }

    /// Left Jacobian `J_l(ξ)` (6×6).
    pub fn left_jacobian(xi: &Vector6<f64>) -> Matrix6<f64> {
        let rho = xi.fixed_rows::<3>(0).into_owned();
        let phi = xi.fixed_rows::<3>(3).into_owned();
        let jl = So3::left_jacobian(&phi);
        let mut j = Matrix6::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&jl);
        j.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&q_matrix(&rho, &phi));
        j.fixed_view_mut::<3, 3>(3, 3).copy_from(&jl);
        j
    }

    /// Inverse of the left Jacobian (closed form).
    pub fn left_jacobian_inverse(xi: &Vector6<f64>) -> Matrix6<f64> {
        let rho = xi.fixed_rows::<3>(0).into_owned();
        let phi = xi.fixed_rows::<3>(3).into_owned();
        let jl_inv = So3::left_jacobian_inverse(&phi);
        let q = q_matrix(&rho, &phi);
        let mut j = Matrix6::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&jl_inv);
        j.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(-jl_inv * q * jl_inv));
        j.fixed_view_mut::<3, 3>(3, 3).copy_from(&jl_inv);
        j
    }

    /// Right Jacobian `J_r(ξ) = J_l(−ξ)`.
    pub fn right_jacobian(xi: &Vector6<f64>) -> Matrix6<f64> {
        Self::left_jacobian(&-xi)
    }

    /// Inverse of the right Jacobian.
    pub fn right_jacobian_inverse(xi: &Vector6<f64>) -> Matrix6<f64> {
        Self::left_jacobian_inverse(&-xi)
    }
}

/// Barfoot's Q(ρ, φ), the upper-right block of the SE(3) left Jacobian (eq. 7.86):
///
/// ```text
/// Q = ½ρ^ + c₁ (φ^ρ^ + ρ^φ^ + φ^ρ^φ^) − c₂ (φ^φ^ρ^ + ρ^φ^φ^ − 3 φ^ρ^φ^)
///         − c₃ (φ^ρ^φ^φ^ + φ^φ^ρ^φ^)
/// c₁ = (θ − sin θ)/θ³,  c₂ = (1 − θ²/2 − cos θ)/θ⁴,  c₃ = ½ [c₂ − 3 (θ − sin θ − θ³/6)/θ⁵]
/// ```
fn q_matrix(rho: &Vector3<f64>, phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta_sq = phi.norm_squared();
    let theta = theta_sq.sqrt();
    let (c1, c2, c3) = if theta < SERIES_ANGLE {
        // c₁ = Σ (−1)^j θ^{2j}/(2j+3)!,  c₂ = −Σ (−1)^j θ^{2j}/(2j+4)!,
        // (θ − sin θ − θ³/6)/θ⁵ = −Σ (−1)^j θ^{2j}/(2j+5)!.
        let c2 = -alternating_series(theta_sq, 4);
        let d = -alternating_series(theta_sq, 5);
        (alternating_series(theta_sq, 3), c2, 0.5 * (c2 - 3.0 * d))
    } else {
        let (s, c) = theta.sin_cos();
        let t3 = theta_sq * theta;
        let t4 = theta_sq * theta_sq;
        let t5 = t4 * theta;
        let c2 = (1.0 - theta_sq / 2.0 - c) / t4;
        (
            (theta - s) / t3,
            c2,
            0.5 * (c2 - 3.0 * (theta - s - t3 / 6.0) / t5),
        )
    };
    let p = hat(phi);
    let r = hat(rho);
    let pr = p * r;
    let rp = r * p;
    let prp = pr * p;
    r * 0.5 + (pr + rp + prp) * c1 - (p * pr + rp * p - prp * 3.0) * c2 - (prp * p + p * prp) * c3
}

impl Mul for Se3 {
    type Output = Se3;
    fn mul(self, rhs: Se3) -> Se3 {
        Se3 {
            rotation: self.rotation * rhs.rotation,
            translation: self.rotation * rhs.translation + self.translation,
        }
    }
}

impl Mul<Vector3<f64>> for Se3 {
    type Output = Vector3<f64>;
    fn mul(self, p: Vector3<f64>) -> Vector3<f64> {
        self.transform_point(&p)
    }
}
