//! Property tests of SO(3) and SE(3) on seeded random samples: exp/log round trips, the
//! Jacobians against central finite differences, adjoints, interpolation, inverses and the
//! quaternion and matrix boundaries.

use std::f64::consts::PI;

use dhptam_core::geometry::{Se3, So3};
use nalgebra::{Matrix3, Matrix4, Matrix6, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SAMPLES: usize = 20;

fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

fn unit_vector(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n = v.norm();
        if n > 0.1 && n <= 1.0 {
            return v / n;
        }
    }
}

/// Rotation vectors covering every regime of the closed forms: tiny angles (Taylor branch of
/// exp/log), the series branch of the Jacobians (θ < 0.5), moderate angles and angles near π.
fn rotation_vectors(rng: &mut ChaCha8Rng) -> Vec<Vector3<f64>> {
    let mut out = Vec::new();
    for i in 0..SAMPLES {
        let angle = match i % 5 {
            0 => rng.random_range(1e-10..1e-8),
            1 => rng.random_range(1e-4..0.1),
            2 => rng.random_range(0.1..0.5),
            3 => rng.random_range(0.5..3.0),
            _ => PI - rng.random_range(1e-7..1e-5),
        };
        out.push(unit_vector(rng) * angle);
    }
    out
}

/// Rotation vectors whose angle stays away from π, where finite differences of `log` are
/// well conditioned.
fn jacobian_vectors(rng: &mut ChaCha8Rng) -> Vec<Vector3<f64>> {
    (0..SAMPLES)
        .map(|i| {
            let angle = match i % 4 {
                0 => rng.random_range(1e-9..1e-6),
                1 => rng.random_range(1e-3..0.5),
                2 => rng.random_range(0.5..1.5),
                _ => rng.random_range(1.5..2.8),
            };
            unit_vector(rng) * angle
        })
        .collect()
}

fn twist(rho: Vector3<f64>, phi: Vector3<f64>) -> Vector6<f64> {
    Vector6::new(rho.x, rho.y, rho.z, phi.x, phi.y, phi.z)
}

fn random_translation(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    unit_vector(rng) * rng.random_range(0.0..3.0)
}

fn random_rotation(rng: &mut ChaCha8Rng) -> So3 {
    So3::exp(&(unit_vector(rng) * rng.random_range(0.0..PI)))
}

fn random_pose(rng: &mut ChaCha8Rng) -> Se3 {
    Se3::new(random_rotation(rng), random_translation(rng))
}

fn assert_matrix_close<const R: usize, const C: usize>(
    a: &nalgebra::SMatrix<f64, R, C>,
    b: &nalgebra::SMatrix<f64, R, C>,
    tol: f64,
    what: &str,
) {
    let err = (a - b).amax();
    assert!(
        err <= tol,
        "{what}: max |difference| = {err:e} > {tol:e}\n{a}\n{b}"
    );
}

#[test]
fn so3_log_of_exp_returns_the_rotation_vector() {
    let mut rng = rng(1);
    for phi in rotation_vectors(&mut rng) {
        let back = So3::exp(&phi).log();
        let err = (back - phi).norm();
        assert!(
            err <= 1e-12 + 1e-9 * phi.norm(),
            "phi = {phi:?}: log(exp(phi)) = {back:?}, error {err:e}"
        );
    }
}

#[test]
fn so3_exp_of_log_returns_the_rotation() {
    let mut rng = rng(2);
    for phi in rotation_vectors(&mut rng) {
        let r = So3::exp(&phi);
        let back = So3::exp(&r.log());
        assert_matrix_close(&back.matrix(), &r.matrix(), 1e-12, "exp(log(R))");
    }
    // Exactly π: log must return a vector of length π about the right axis (either sign).
    let axis = Vector3::new(1.0, 2.0, -2.0) / 3.0;
    let r = So3::exp(&(axis * PI));
    let phi = r.log();
    assert!((phi.norm() - PI).abs() < 1e-12, "{phi:?}");
    assert_matrix_close(
        &So3::exp(&phi).matrix(),
        &r.matrix(),
        1e-12,
        "exp(log(R)) at π",
    );
}

#[test]
fn se3_log_exp_round_trips() {
    let mut rng = rng(3);
    for phi in rotation_vectors(&mut rng) {
        let xi = twist(random_translation(&mut rng), phi);
        let back = Se3::exp(&xi).log();
        let err = (back - xi).norm();
        // Near π the translation part goes through J_l⁻¹, whose cot(θ/2) loses a few digits.
        assert!(
            err <= 1e-9 * (1.0 + xi.norm()),
            "xi = {xi:?}: log(exp(xi)) = {back:?}, error {err:e}"
        );
        let t = Se3::exp(&xi);
        assert_matrix_close(
            &Se3::exp(&t.log()).matrix(),
            &t.matrix(),
            1e-9,
            "exp(log(T))",
        );
    }
}

/// Column k of the numerical derivative of `f` at 0, by central differences.
fn central_difference<const N: usize>(
    f: impl Fn(&nalgebra::SVector<f64, N>) -> nalgebra::SVector<f64, N>,
) -> nalgebra::SMatrix<f64, N, N> {
    let h = 1e-6;
    let mut j = nalgebra::SMatrix::<f64, N, N>::zeros();
    for k in 0..N {
        let mut d = nalgebra::SVector::<f64, N>::zeros();
        d[k] = h;
        j.set_column(k, &((f(&d) - f(&-d)) / (2.0 * h)));
    }
    j
}

#[test]
fn so3_jacobians_match_finite_differences() {
    let mut rng = rng(4);
    for phi in jacobian_vectors(&mut rng) {
        let r_inv = So3::exp(&phi).inverse();
        // exp(φ + δ) exp(φ)⁻¹ = exp(J_l δ) and exp(φ)⁻¹ exp(φ + δ) = exp(J_r δ).
        let left = central_difference(|d: &Vector3<f64>| (So3::exp(&(phi + d)) * r_inv).log());
        let right = central_difference(|d: &Vector3<f64>| (r_inv * So3::exp(&(phi + d))).log());
        assert_matrix_close(
            &So3::left_jacobian(&phi),
            &left,
            1e-8,
            &format!("SO3 J_l at |phi| = {}", phi.norm()),
        );
        assert_matrix_close(
            &So3::right_jacobian(&phi),
            &right,
            1e-8,
            &format!("SO3 J_r at |phi| = {}", phi.norm()),
        );
    }
}

#[test]
fn se3_jacobians_match_finite_differences() {
    let mut rng = rng(5);
    for phi in jacobian_vectors(&mut rng) {
        let xi = twist(random_translation(&mut rng), phi);
        let t_inv = Se3::exp(&xi).inverse();
        let left = central_difference(|d: &Vector6<f64>| (Se3::exp(&(xi + d)) * t_inv).log());
        let right = central_difference(|d: &Vector6<f64>| (t_inv * Se3::exp(&(xi + d))).log());
        assert_matrix_close(
            &Se3::left_jacobian(&xi),
            &left,
            1e-7,
            &format!("SE3 J_l at |phi| = {}", phi.norm()),
        );
        assert_matrix_close(
            &Se3::right_jacobian(&xi),
            &right,
            1e-7,
            &format!("SE3 J_r at |phi| = {}", phi.norm()),
        );
    }
}

#[test]
fn jacobian_inverses_invert_the_jacobians() {
    let mut rng = rng(6);
    let mut vectors = jacobian_vectors(&mut rng);
    // Around the series/closed-form switches of J_l (0.5) and of J_l⁻¹ (0.1), and near π.
    for angle in [0.0999999, 0.1000001, 0.4999999, 0.5000001, 3.1] {
        vectors.push(unit_vector(&mut rng) * angle);
    }
    for phi in vectors {
        let i3 = Matrix3::identity();
        assert_matrix_close(
            &(So3::left_jacobian_inverse(&phi) * So3::left_jacobian(&phi)),
            &i3,
            1e-12,
            "SO3 J_l⁻¹ J_l",
        );
        assert_matrix_close(
            &(So3::right_jacobian_inverse(&phi) * So3::right_jacobian(&phi)),
            &i3,
            1e-12,
            "SO3 J_r⁻¹ J_r",
        );
        let xi = twist(random_translation(&mut rng), phi);
        let i6 = Matrix6::identity();
        assert_matrix_close(
            &(Se3::left_jacobian_inverse(&xi) * Se3::left_jacobian(&xi)),
            &i6,
            1e-11,
            "SE3 J_l⁻¹ J_l",
        );
        assert_matrix_close(
            &(Se3::right_jacobian_inverse(&xi) * Se3::right_jacobian(&xi)),
            &i6,
            1e-11,
            "SE3 J_r⁻¹ J_r",
        );
    }
}

#[test]
fn adjoint_moves_tangent_vectors_through_the_group() {
    let mut rng = rng(7);
    for phi in jacobian_vectors(&mut rng) {
        let r = random_rotation(&mut rng);
        let lhs = r * So3::exp(&phi) * r.inverse();
        assert_matrix_close(
            &lhs.matrix(),
            &So3::exp(&(r.adjoint() * phi)).matrix(),
            1e-12,
            "SO3 adjoint",
        );

        let t = random_pose(&mut rng);
        let xi = twist(random_translation(&mut rng), phi);
        let lhs = t * Se3::exp(&xi) * t.inverse();
        assert_matrix_close(
            &lhs.matrix(),
            &Se3::exp(&(t.adjoint() * xi)).matrix(),
            1e-11,
            "SE3 adjoint",
        );
    }
}

#[test]
fn interpolation_hits_the_endpoints_and_halves_the_way() {
    let mut rng = rng(8);
    for _ in 0..SAMPLES {
        let (a, b) = (random_rotation(&mut rng), random_rotation(&mut rng));
        assert_matrix_close(
            &a.interpolate(&b, 0.0).matrix(),
            &a.matrix(),
            1e-12,
            "SO3 interpolate at 0",
        );
        assert_matrix_close(
            &a.interpolate(&b, 1.0).matrix(),
            &b.matrix(),
            1e-12,
            "SO3 interpolate at 1",
        );
        // a⁻¹ m = exp(ξ/2), so (a⁻¹ m)² = a⁻¹ b.
        let half = a.inverse() * a.interpolate(&b, 0.5);
        assert_matrix_close(
            &(half * half).matrix(),
            &(a.inverse() * b).matrix(),
            1e-12,
            "SO3 midpoint squared",
        );

        let (a, b) = (random_pose(&mut rng), random_pose(&mut rng));
        assert_matrix_close(
            &a.interpolate(&b, 0.0).matrix(),
            &a.matrix(),
            1e-12,
            "SE3 interpolate at 0",
        );
        assert_matrix_close(
            &a.interpolate(&b, 1.0).matrix(),
            &b.matrix(),
            1e-11,
            "SE3 interpolate at 1",
        );
        let m = a.interpolate(&b, 0.5);
        let half = a.inverse() * m;
        assert_matrix_close(
            &(half * half).matrix(),
            &(a.inverse() * b).matrix(),
            1e-11,
            "SE3 midpoint squared",
        );
        let (d1, d2) = (
            (a.inverse() * m).log().norm(),
            (m.inverse() * b).log().norm(),
        );
        assert!(
            (d1 - d2).abs() < 1e-10,
            "SE3 midpoint distances {d1} and {d2}"
        );
    }
}

#[test]
fn inverses_undo_the_transform() {
    let mut rng = rng(9);
    for _ in 0..SAMPLES {
        let t = random_pose(&mut rng);
        let p = random_translation(&mut rng);
        let back = t.inverse().transform_point(&t.transform_point(&p));
        assert!((back - p).norm() < 1e-12, "{back:?} vs {p:?}");
        assert_matrix_close(
            &(t * t.inverse()).matrix(),
            &Matrix4::identity(),
            1e-12,
            "T T⁻¹",
        );
        assert_matrix_close(
            &t.inverse().matrix(),
            &t.matrix().try_inverse().unwrap(),
            1e-12,
            "T⁻¹ vs matrix inverse",
        );
        let r = t.rotation;
        assert_matrix_close(
            &(r * r.inverse()).matrix(),
            &Matrix3::identity(),
            1e-12,
            "R R⁻¹",
        );
    }
}

#[test]
fn quaternion_xyzw_round_trips_and_rejects_bad_input() {
    let mut rng = rng(10);
    for _ in 0..SAMPLES {
        let mut q = [0.0; 4];
        for v in q.iter_mut() {
            *v = rng.random_range(-1.0..1.0);
        }
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        let sign = if q[3] < 0.0 { -1.0 } else { 1.0 };
        let expected = q.map(|v| sign * v / norm);
        // Scaled and sign-flipped inputs describe the same rotation.
        let scaled = q.map(|v| -2.5 * v);
        let r = So3::from_quaternion_xyzw(scaled).unwrap();
        let back = r.to_quaternion_xyzw();
        for k in 0..4 {
            assert!(
                (back[k] - expected[k]).abs() < 1e-14,
                "{back:?} vs {expected:?}"
            );
        }
        let t = Se3::from_translation_quaternion_xyzw([1.0, 2.0, 3.0], q).unwrap();
        assert_matrix_close(&t.rotation.matrix(), &r.matrix(), 1e-14, "pose rotation");
    }
    // x = (1, 0, 0, 0) is a rotation by π about x: the scalar-last order is honoured.
    let r = So3::from_quaternion_xyzw([1.0, 0.0, 0.0, 0.0]).unwrap();
    assert_matrix_close(
        &r.matrix(),
        &Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0)),
        1e-15,
        "q = x",
    );
    assert!(So3::from_quaternion_xyzw([0.0; 4]).is_err());
    assert!(So3::from_quaternion_xyzw([0.0, f64::NAN, 0.0, 1.0]).is_err());
    assert!(So3::from_quaternion_xyzw([0.0, 0.0, f64::INFINITY, 1.0]).is_err());
    assert!(
        Se3::from_translation_quaternion_xyzw([f64::NAN, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]).is_err()
    );
}

#[test]
fn from_matrix_round_trips_and_rejects_non_rotations() {
    let mut rng = rng(11);
    for phi in rotation_vectors(&mut rng) {
        let r = So3::exp(&phi);
        let back = So3::from_matrix(&r.matrix()).unwrap();
        assert_matrix_close(
            &back.matrix(),
            &r.matrix(),
            1e-14,
            &format!("from_matrix at angle {}", phi.norm()),
        );
        let t = Se3::new(r, random_translation(&mut rng));
        let back = Se3::from_matrix(&t.matrix()).unwrap();
        assert_matrix_close(&back.matrix(), &t.matrix(), 1e-14, "SE3 from_matrix");
    }
    // Slightly off-orthonormal input (within the 1e-6 tolerance) gives the nearby rotation.
    for _ in 0..SAMPLES {
        let r = random_rotation(&mut rng);
        let noise = Matrix3::from_fn(|_, _| rng.random_range(-1e-8..1e-8));
        let back = So3::from_matrix(&(r.matrix() + noise)).unwrap();
        assert_matrix_close(
            &(back.matrix().transpose() * back.matrix()),
            &Matrix3::identity(),
            1e-14,
            "orthonormalised",
        );
        assert_matrix_close(
            &back.matrix(),
            &r.matrix(),
            1e-7,
            "orthonormalised close to input",
        );
    }
    let m = So3::exp(&Vector3::new(0.3, -0.2, 0.1)).matrix();
    let err = So3::from_matrix(&(m * 1.01)).unwrap_err();
    assert!(err.to_string().contains("rotation matrix"), "{err}");
    let mut sheared = m;
    sheared[(0, 1)] += 1e-3;
    assert!(So3::from_matrix(&sheared).is_err());
    let reflection = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0));
    assert!(
        So3::from_matrix(&reflection).is_err(),
        "a reflection has determinant −1"
    );
    let mut with_nan = m;
    with_nan[(2, 2)] = f64::NAN;
    assert!(So3::from_matrix(&with_nan).is_err());
    let mut bad_last_row = Se3::identity().matrix();
    bad_last_row[(3, 0)] = 0.5;
    assert!(Se3::from_matrix(&bad_last_row).is_err());
}
