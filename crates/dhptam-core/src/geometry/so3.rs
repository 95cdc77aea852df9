//! SO(3), the group of 3-D rotations, stored as a unit quaternion.
//!
//! Tangent vectors are rotation vectors φ ∈ ℝ³ (axis · angle, radians). `exp`/`log` map between
//! the two; the Jacobians follow Barfoot, *State Estimation for Robotics* (2017), §7.1.5:
//!
//! ```text
//! exp(φ + δ) ≈ exp(J_l(φ) δ) · exp(φ) ≈ exp(φ) · exp(J_r(φ) δ),     J_r(φ) = J_l(−φ)
//! J_l(φ) = I + (1 − cos θ)/θ² φ^ + (θ − sin θ)/θ³ φ^²,                θ = |φ|
//! J_l⁻¹(φ) = I − ½ φ^ + (1/θ² − (1 + cos θ)/(2 θ sin θ)) φ^²
//! ```
//!
//! Quaternions cross the API boundary only through [`So3::from_quaternion_xyzw`] and
//! [`So3::to_quaternion_xyzw`]: Hamilton convention, scalar last (the TUM / ROS order).

use std::ops::Mul;

use nalgebra::{Matrix3, Quaternion, Rotation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Below this angle (radians) `exp`/`log` switch to their Taylor expansions (no cancellation
/// above it: they only divide by sin or atan2).
const SMALL_ANGLE: f64 = 1e-6;

/// Below this angle the Jacobian coefficients, whose closed forms subtract nearly equal
/// numbers, are evaluated by their (rapidly converging) power series instead.
pub(crate) const SERIES_ANGLE: f64 = 0.5;

/// `Σ_{j≥0} (−1)^j θ^{2j} / (2j + m)!`, summed to double precision for θ ≤ [`SERIES_ANGLE`].
///
/// m = 2 gives (1 − cos θ)/θ², m = 3 gives (θ − sin θ)/θ³, and so on.
pub(crate) fn alternating_series(theta_sq: f64, m: u32) -> f64 {
    let mut factorial: f64 = (1..=m).map(f64::from).product();
    let mut power = 1.0;
    let mut sum = 0.0;
    for j in 0..10u32 {
        let term = power / factorial;
        sum += if j % 2 == 0 { term } else { -term };
        power *= theta_sq;
        let n = f64::from(2 * j + m);
        factorial *= (n + 1.0) * (n + 2.0);
    }
    sum
}

/// The skew-symmetric matrix `v^` with `v^ w = v × w`.
pub fn hat(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Inverse of [`hat`]: the vector of a skew-symmetric matrix (its antisymmetric part).
pub fn vee(m: &Matrix3<f64>) -> Vector3<f64> {
    Vector3::new(
        m[(2, 1)] - m[(1, 2)],
        m[(0, 2)] - m[(2, 0)],
        m[(1, 0)] - m[(0, 1)],
    ) * 0.5
}

/// A rotation. `a * b` composes (apply `b` first), `r * v` rotates a vector.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct So3 {
    quaternion: UnitQuaternion<f64>,
}

impl Default for So3 {
    fn default() -> Self {
        Self::identity()
    }
}

impl So3 {
    /// The identity rotation.
    pub fn identity() -> Self {
        Self {
            quaternion: UnitQuaternion::identity(),
        }
    }

    /// Wraps a nalgebra unit quaternion.
    pub fn from_unit_quaternion(quaternion: UnitQuaternion<f64>) -> Self {
        Self { quaternion }
    }

    /// From a quaternion in (x, y, z, w) order, Hamilton convention. The input is normalised;
    /// it must be finite and not (nearly) zero.
    pub fn from_quaternion_xyzw(q: [f64; 4]) -> Result<Self> {
        crate::error::ensure_finite("quaternion_xyzw", &q)?;
        let quaternion = Quaternion::new(q[3], q[0], q[1], q[2]);
        let norm = quaternion.norm();
        if norm < 1e-12 {
            return Err(Error::invalid(
                "quaternion_xyzw",
                "a non-zero quaternion",
                format!("{q:?}"),
            ));
        }
        Ok(Self {
            quaternion: UnitQuaternion::new_unchecked(quaternion / norm),
        })
    }

    /// The quaternion in (x, y, z, w) order with w ≥ 0.
    pub fn to_quaternion_xyzw(&self) -> [f64; 4] {
        let q = self.quaternion.quaternion();
        let s = if q.w < 0.0 { -1.0 } else { 1.0 };
        [s * q.i, s * q.j, s * q.k, s * q.w]
    }

    /// From a rotation matrix. The matrix must be orthonormal with determinant +1 to within
    /// `1e-6`; it is then re-orthonormalised.
    pub fn from_matrix(m: &Matrix3<f64>) -> Result<Self> {
        crate::error::ensure_finite("rotation matrix", m.as_slice())?;
        let orthogonality = (m.transpose() * m - Matrix3::identity()).norm();
        let det = m.determinant();
        if orthogonality > 1e-6 || (det - 1.0).abs() > 1e-6 {
            return Err(Error::invalid(
                "rotation matrix",
                "an orthonormal matrix with determinant +1 (tolerance 1e-6)",
                format!("|RᵀR − I| = {orthogonality:.3e}, det = {det:.6}"),
            ));
        }
        // The quaternion read off the matrix is exact for an exact rotation; Müller's iteration
        // started from it only has to remove the (≤ 1e-6) non-orthogonality, and can run to
        // machine precision. (Started from the identity with a 1e-12 tolerance, it returned
        // rotations off by ~1e-12 even for exact input.)
        // nalgebra does not normalise a quaternion read off a non-orthonormal matrix.
        let read = |r: &Rotation3<f64>| {
            UnitQuaternion::new_normalize(*UnitQuaternion::from_rotation_matrix(r).quaternion())
        };
        let guess = read(&Rotation3::from_matrix_unchecked(*m)).to_rotation_matrix();
        let rotation = Rotation3::from_matrix_eps(m, f64::EPSILON, 100, guess);
        Ok(Self {
            quaternion: read(&rotation),
        })
    }

    /// The underlying unit quaternion.
    pub fn unit_quaternion(&self) -> &UnitQuaternion<f64> {
        &self.quaternion
    }

    /// The 3×3 rotation matrix.
    pub fn matrix(&self) -> Matrix3<f64> {
        self.quaternion.to_rotation_matrix().into_inner()
    }

    /// The exponential map: the rotation by |φ| radians about φ/|φ|.
    pub fn exp(phi: &Vector3<f64>) -> Self {
        let theta_sq = phi.norm_squared();
        let theta = theta_sq.sqrt();
        let (w, k) = if theta < SMALL_ANGLE {
            // cos(θ/2) and sin(θ/2)/θ to fourth order.
            (1.0 - theta_sq / 8.0, 0.5 - theta_sq / 48.0)
        } else {
            let half = 0.5 * theta;
            (half.cos(), half.sin() / theta)
        };
        let q = Quaternion::new(w, k * phi.x, k * phi.y, k * phi.z);
        Self {
            quaternion: UnitQuaternion::new_normalize(q),
        }
    }

    /// The logarithm: the rotation vector with angle in [0, π].
    pub fn log(&self) -> Vector3<f64> {
        let q = self.quaternion.quaternion();
        let (mut w, mut v) = (q.w, q.imag());
        if w < 0.0 {
            w = -w;
            v = -v;
        }
        let n = v.norm();
        if n < SMALL_ANGLE {
            // θ = 2 atan(n / w) ≈ 2 n / w (1 − n²/(3w²)).
            v * (2.0 / w * (1.0 - n * n / (3.0 * w * w)))
        } else {
            v * (2.0 * n.atan2(w) / n)
        }
    }

    /// The inverse rotation.
    pub fn inverse(&self) -> Self {
        Self {
            quaternion: self.quaternion.inverse(),
        }
    }

    /// The adjoint `Ad(R) = R`: `R exp(φ) Rᵀ = exp(R φ)`.
    pub fn adjoint(&self) -> Matrix3<f64> {
        self.matrix()
    }

    /// Rotation angle in radians, in [0, π].
    pub fn angle(&self) -> f64 {
        self.log().norm()
    }

    /// Geodesic interpolation: `s = 0` gives `self`, `s = 1` gives `other`.
    pub fn interpolate(&self, other: &So3, s: f64) -> So3 {
        *self * So3::exp(&((self.inverse() * *other).log() * s))
    }

    /// Left Jacobian `J_l(φ)`.
    pub fn left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
        let theta_sq = phi.norm_squared();
        let theta = theta_sq.sqrt();
        let phi_hat = hat(phi);
        let (a, b) = if theta < SERIES_ANGLE {
            (
                alternating_series(theta_sq, 2),
                alternating_series(theta_sq, 3),
            )
        } else {
            (
                (1.0 - theta.cos()) / theta_sq,
                (theta - theta.sin()) / (theta_sq * theta),
            )
        };
        Matrix3::identity() + phi_hat * a + phi_hat * phi_hat * b
    }

    /// Inverse of the left Jacobian, `J_l⁻¹(φ)` (valid for |φ| < 2π).
    pub fn left_jacobian_inverse(phi: &Vector3<f64>) -> Matrix3<f64> {
        let theta_sq = phi.norm_squared();
        let theta = theta_sq.sqrt();
        let phi_hat = hat(phi);
        // 1/θ² − cot(θ/2)/(2θ) = 1/12 + θ²/720 + θ⁴/30240 + θ⁶/1209600 + O(θ⁸); the closed
        // form loses ~eps/θ² to cancellation, so the series is used below θ = 0.1.
        let c = if theta < 0.1 {
            1.0 / 12.0
                + theta_sq * (1.0 / 720.0 + theta_sq * (1.0 / 30240.0 + theta_sq / 1_209_600.0))
        } else {
            1.0 / theta_sq - (1.0 + theta.cos()) / (2.0 * theta * theta.sin())
        };
        Matrix3::identity() - phi_hat * 0.5 + phi_hat * phi_hat * c
    }

    /// Right Jacobian `J_r(φ) = J_l(−φ)`.
    pub fn right_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
        Self::left_jacobian(&-phi)
    }

    /// Inverse of the right Jacobian.
    pub fn right_jacobian_inverse(phi: &Vector3<f64>) -> Matrix3<f64> {
        Self::left_jacobian_inverse(&-phi)
    }
}

impl Mul for So3 {
    type Output = So3;
    fn mul(self, rhs: So3) -> So3 {
        // Renormalise so that long products do not drift off the unit sphere.
        So3 {
            quaternion: UnitQuaternion::new_normalize(
                *(self.quaternion * rhs.quaternion).quaternion(),
            ),
        }
    }
}

impl Mul<Vector3<f64>> for So3 {
    type Output = Vector3<f64>;
    fn mul(self, v: Vector3<f64>) -> Vector3<f64> {
        self.quaternion * v
    }
}

impl Mul<&Vector3<f64>> for &So3 {
    type Output = Vector3<f64>;
    fn mul(self, v: &Vector3<f64>) -> Vector3<f64> {
        self.quaternion * v
    }
}
