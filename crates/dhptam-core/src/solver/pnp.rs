//! Perspective-n-point with RANSAC: a P3P minimal solver inside an adaptive RANSAC loop, then
//! [`refine_pose`] on the inliers, as loop closing and relocalisation verify a candidate.
//!
//! ## P3P
//! With bearing vectors yᵢ (unit, camera frame) of three world points xᵢ, the unknown depths
//! λᵢ satisfy the law of cosines (Grunert 1841; the formulation and its review in Haralick et
//! al., "Review and analysis of solutions of the three point perspective pose estimation
//! problem", IJCV 1994):
//!
//! ```text
//! λᵢ² + λⱼ² − 2 cᵢⱼ λᵢ λⱼ = aᵢⱼ,   cᵢⱼ = yᵢ·yⱼ,   aᵢⱼ = ‖xᵢ − xⱼ‖²
//! ```
//!
//! With λ₂ = u λ₁ and λ₃ = v λ₁, eliminating λ₁ leaves two conics in (u, v):
//!
//! ```text
//! E1: a₁₃ u² − 2 a₁₃ c₁₂ u + (a₁₃ − a₁₂) − a₁₂ v² + 2 a₁₂ c₁₃ v = 0
//! E2: (a₂₃ − a₁₂) u² − 2 a₂₃ c₁₂ u + 2 a₁₂ c₂₃ u v + a₂₃ − a₁₂ v² = 0
//! ```
//!
//! Seen as quadratics A u² + B(v) u + C(v) in u, their Sylvester resultant
//! (A₁C₂ − A₂C₁)² − (A₁B₂ − A₂B₁)(B₁C₂ − B₂C₁) is a quartic in v whose real roots give u
//! from the u-linear combination A₂·E1 − A₁·E2; λ₁ follows, and up to four poses. Each depth
//! triple is polished by Gauss–Newton on the three equations (as Persson & Nordberg's Lambda
//! Twist does, ECCV 2018), then the pose is the rigid motion between the two triangles.
//!
//! ## RANSAC
//! Samples of three distinct correspondences come from a seeded ChaCha8 generator, so a run
//! is reproducible. Hypotheses are ranked by the MSAC score Σ min(e², τ²) over all points (e:
//! reprojection error in pixels, τ: `threshold_px`); the iteration count adapts as
//! N = log(1 − confidence) / log(1 − w³) with w the best inlier ratio so far.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::lm::LmOptions;
use super::pose::{refine_pose, PoseObservation, PoseOptions, StereoIntrinsics};
use super::robust::Loss;
use crate::error::{ensure_finite, Error, Result};
use crate::geometry::{Se3, So3};

/// Options of [`solve_pnp_ransac`].
#[derive(Clone, Debug, PartialEq)]
pub struct PnpRansacOptions {
    /// Largest reprojection error (pixels) of an inlier. Default 2.0.
    pub threshold_px: f64,
    /// Probability of drawing at least one all-inlier sample, which sets the adaptive
    /// iteration count. Default 0.999.
    pub confidence: f64,
    /// Most RANSAC iterations. Default 1000.
    pub max_iterations: usize,
    /// Fewest inliers of an accepted model (`None` below). Default 10.
    pub min_inliers: usize,
    /// Seed of the sample generator. Default 0.
    pub seed: u64,
}

impl Default for PnpRansacOptions {
    fn default() -> Self {
        Self {
            threshold_px: 2.0,
            confidence: 0.999,
            max_iterations: 1000,
            min_inliers: 10,
            seed: 0,
        }
    }
}

/// The pose found by [`solve_pnp_ransac`].
#[derive(Clone, Debug, PartialEq)]
pub struct PnpResult {
    /// Pose of the camera: maps world points into the camera frame.
    pub cam_from_world: Se3,
    /// Per correspondence: in front of the camera with a reprojection error ≤ `threshold_px`.
    pub inliers: Vec<bool>,
    /// Number of `true` in `inliers`.
    pub inlier_count: usize,
    /// RANSAC iterations run.
    pub iterations: usize,
}

/// Real roots of Σ cᵢ xⁱ (coefficients lowest degree first, degree ≤ 4), ascending. Roots are
/// bracketed between the real roots of the derivative and refined by bisection, so the
/// method cannot diverge; a root of even multiplicity is found where |p| vanishes at a
/// critical point.
fn real_roots(coefficients: &[f64]) -> Vec<f64> {
    let scale = coefficients.iter().fold(0.0f64, |m, c| m.max(c.abs()));
    if scale == 0.0 || !scale.is_finite() {
        return Vec::new();
    }
    let mut c: Vec<f64> = coefficients.iter().map(|x| x / scale).collect();
    while c.len() > 1 && c[c.len() - 1].abs() < 1e-13 {
        c.pop();
    }
    let degree = c.len() - 1;
    match degree {
        0 => return Vec::new(),
        1 => return vec![-c[0] / c[1]],
        _ => {}
    }
    let eval = |x: f64| c.iter().rev().fold(0.0, |acc, &k| acc * x + k);
    let lead = c[degree];
    let bound = 1.0
        + c[..degree]
            .iter()
            .fold(0.0f64, |m, k| m.max((k / lead).abs()));
    let derivative: Vec<f64> = (1..=degree).map(|i| c[i] * i as f64).collect();
    let mut knots = vec![-bound];
    knots.extend(
        real_roots(&derivative)
            .into_iter()
            .filter(|x| x.abs() < bound),
    );
    knots.push(bound);
    let mut roots: Vec<f64> = Vec::with_capacity(degree);
    for pair in knots.windows(2) {
        let (mut lo, mut hi) = (pair[0], pair[1]);
        let (mut flo, fhi) = (eval(lo), eval(hi));
        if flo == 0.0 {
            roots.push(lo);
            continue;
        }
        if flo.signum() == fhi.signum() {
            continue;
        }
        for _ in 0..100 {
            let mid = 0.5 * (lo + hi);
            if mid <= lo || mid >= hi {
                break;
            }
            let fm = eval(mid);
            if fm.signum() == flo.signum() {
                lo = mid;
                flo = fm;
            } else {
                hi = mid;
            }
        }
        roots.push(0.5 * (lo + hi));
    }
    // Touching roots at interior critical points (no sign change around them).
    let tol = 1e-10 * c.iter().fold(0.0f64, |m, k| m.max(k.abs()));
    for &x in &knots[1..knots.len() - 1] {
        if eval(x).abs() <= tol && roots.iter().all(|r| (r - x).abs() > 1e-9 * (1.0 + x.abs())) {
            roots.push(x);
        }
    }
    roots.sort_by(f64::total_cmp);
    roots
}

/// Product of two polynomials (lowest degree first).
fn poly_mul(a: &[f64], b: &[f64]) -> Vec<f64> {
    let mut out = vec![0.0; a.len() + b.len() - 1];
    for (i, x) in a.iter().enumerate() {
        for (j, y) in b.iter().enumerate() {
            out[i + j] += x * y;
        }
    }
    out
}

/// a − b for polynomials (lowest degree first).
fn poly_sub(a: &[f64], b: &[f64]) -> Vec<f64> {
    (0..a.len().max(b.len()))
        .map(|i| a.get(i).copied().unwrap_or(0.0) - b.get(i).copied().unwrap_or(0.0))
        .collect()
}

fn poly_scale(a: &[f64], s: f64) -> Vec<f64> {
    a.iter().map(|x| x * s).collect()
}

/// The orthonormal frame [e₁ e₂ n] of a triangle: e₁ along p₁→p₂, n its normal.
fn triangle_frame(p1: &Vector3<f64>, p2: &Vector3<f64>, p3: &Vector3<f64>) -> Option<Matrix3<f64>> {
    let e1 = (p2 - p1).try_normalize(1e-12)?;
    let n = e1.cross(&(p3 - p1)).try_normalize(1e-12)?;
    Some(Matrix3::from_columns(&[e1, n.cross(&e1), n]))
}

/// All poses `cam_from_world` (up to four) that map the three world points onto the three
/// unit bearing vectors (camera frame) with positive depths. Empty for degenerate input
/// (coincident or collinear points, parallel bearings).
pub fn p3p(world: &[Vector3<f64>; 3], bearings: &[Vector3<f64>; 3]) -> Vec<Se3> {
    let [x1, x2, x3] = world;
    let [y1, y2, y3] = bearings;
    let (a12, a13, a23) = (
        (x1 - x2).norm_squared(),
        (x1 - x3).norm_squared(),
        (x2 - x3).norm_squared(),
    );
    let (c12, c13, c23) = (y1.dot(y2), y1.dot(y3), y2.dot(y3));
    if a12.min(a13).min(a23) <= 0.0
        || (x2 - x1).cross(&(x3 - x1)).norm_squared() <= 1e-18 * a12 * a13
    {
        return Vec::new();
    }
    // Quadratics in u with coefficients polynomial in v (lowest degree first).
    let a1 = a13;
    let b1 = [-2.0 * a13 * c12];
    let cc1 = [a13 - a12, 2.0 * a12 * c13, -a12];
    let a2 = a23 - a12;
    let b2 = [-2.0 * a23 * c12, 2.0 * a12 * c23];
    let cc2 = [a23, 0.0, -a12];
    let ac = poly_sub(&poly_scale(&cc2, a1), &poly_scale(&cc1, a2)); // A₁C₂ − A₂C₁
    let ab = poly_sub(&poly_scale(&b2, a1), &poly_scale(&b1, a2)); // A₁B₂ − A₂B₁
    let bc = poly_sub(&poly_mul(&b1, &cc2), &poly_mul(&b2, &cc1)); // B₁C₂ − B₂C₁
    let resultant = poly_sub(&poly_mul(&ac, &ac), &poly_mul(&ab, &bc));
    let eval = |p: &[f64], x: f64| p.iter().rev().fold(0.0, |acc, &k| acc * x + k);
    let Some(frame_world) = triangle_frame(x1, x2, x3) else {
        return Vec::new();
    };
    let mut poses = Vec::with_capacity(4);
    for v in real_roots(&resultant) {
        if v <= 0.0 {
            continue;
        }
        // u from A₂·E1 − A₁·E2 = −(A₁B₂ − A₂B₁) u − (A₁C₂ − A₂C₁) = 0; where that is
        // degenerate, from E1's own roots checked against E2.
        let (abv, acv) = (eval(&ab, v), eval(&ac, v));
        let (c1v, c2v, b2v) = (eval(&cc1, v), eval(&cc2, v), eval(&b2, v));
        let e2 = |u: f64| a2 * u * u + b2v * u + c2v;
        let mut candidates = Vec::with_capacity(2);
        if abv.abs() > 1e-9 * (acv.abs() + 1e-300) {
            candidates.push(-acv / abv);
        } else {
            for u in real_roots(&[c1v, b1[0], a1]) {
                if e2(u).abs() <= 1e-6 * (a2.abs() * u * u + c2v.abs() + 1e-300) {
                    candidates.push(u);
                }
            }
        }
        for u in candidates {
            let denom = 1.0 + v * v - 2.0 * c13 * v;
            if u <= 0.0 || denom <= 0.0 {
                continue;
            }
            let l1 = (a13 / denom).sqrt();
            let mut lambda = Vector3::new(l1, u * l1, v * l1);
            polish_depths(&mut lambda, [a12, a13, a23], [c12, c13, c23]);
            if lambda.iter().any(|l| !(l.is_finite() && *l > 0.0)) {
                continue;
            }
            let (p1, p2, p3) = (y1 * lambda.x, y2 * lambda.y, y3 * lambda.z);
            let Some(frame_cam) = triangle_frame(&p1, &p2, &p3) else {
                continue;
            };
            // A product of two orthonormal frames: a rotation up to rounding, read directly.
            let rotation = So3::from_unit_quaternion(UnitQuaternion::from_rotation_matrix(
                &Rotation3::from_matrix_unchecked(frame_cam * frame_world.transpose()),
            ));
            let translation = p1 - rotation.matrix() * x1;
            let pose = Se3::new(rotation, translation);
            // Two roots may describe one pose (a double root split by rounding).
            if poses.iter().all(|q: &Se3| {
                (q.translation - pose.translation).norm() > 1e-9 * (1.0 + translation.norm())
                    || (q.rotation.matrix() - rotation.matrix()).norm() > 1e-9
            }) {
                poses.push(pose);
            }
        }
    }
    poses
}

/// Gauss–Newton on fᵢⱼ(λ) = λᵢ² + λⱼ² − 2cᵢⱼλᵢλⱼ − aᵢⱼ for a few iterations.
fn polish_depths(lambda: &mut Vector3<f64>, a: [f64; 3], c: [f64; 3]) {
    let pairs = [(0usize, 1usize), (0, 2), (1, 2)];
    for _ in 0..3 {
        let mut f = Vector3::zeros();
        let mut j = Matrix3::zeros();
        for (row, &(i, k)) in pairs.iter().enumerate() {
            let (li, lk) = (lambda[i], lambda[k]);
            f[row] = li * li + lk * lk - 2.0 * c[row] * li * lk - a[row];
            j[(row, i)] = 2.0 * li - 2.0 * c[row] * lk;
            j[(row, k)] = 2.0 * lk - 2.0 * c[row] * li;
        }
        let Some(step) = j.lu().solve(&f) else {
            return;
        };
        let next = *lambda - step;
        if !next.iter().all(|x| x.is_finite()) {
            return;
        }
        *lambda = next;
    }
}

/// Squared reprojection error of `x` under `pose`, `None` behind the camera.
#[inline]
fn reprojection_sq(
    k: &StereoIntrinsics,
    rotation: &Matrix3<f64>,
    translation: &Vector3<f64>,
    x: &Vector3<f64>,
    pixel: &Vector2<f64>,
) -> Option<f64> {
    let p = rotation * x + translation;
    if p.z <= 1e-9 || !p.z.is_finite() {
        return None;
    }
    let du = k.fx * p.x / p.z + k.cx - pixel.x;
    let dv = k.fy * p.y / p.z + k.cy - pixel.y;
    Some(du * du + dv * dv)
}

/// Inlier flags, their count and the MSAC score Σ min(e², τ²) of a pose.
fn score(
    k: &StereoIntrinsics,
    pose: &Se3,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    threshold_sq: f64,
    inliers: &mut [bool],
) -> (usize, f64) {
    let rotation = pose.rotation.matrix();
    let mut count = 0;
    let mut total = 0.0;
    for ((x, px), flag) in points.iter().zip(pixels).zip(inliers.iter_mut()) {
        let e = reprojection_sq(k, &rotation, &pose.translation, x, px);
        *flag = e.is_some_and(|e| e <= threshold_sq);
        count += *flag as usize;
        total += e.map_or(threshold_sq, |e| e.min(threshold_sq));
    }
    (count, total)
}

fn check(
    k: &StereoIntrinsics,
    points_world: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    options: &PnpRansacOptions,
) -> Result<()> {
    ensure_finite("intrinsics", &[k.fx, k.fy, k.cx, k.cy])?;
    if k.fx <= 0.0 || k.fy <= 0.0 {
        return Err(Error::invalid(
            "intrinsics fx, fy",
            "positive focal lengths",
            format!("{}, {}", k.fx, k.fy),
        ));
    }
    if points_world.len() != pixels.len() {
        return Err(Error::invalid(
            "pixels",
            format!("one per world point ({})", points_world.len()),
            pixels.len(),
        ));
    }
    if points_world.len() < 4 {
        return Err(Error::invalid(
            "points_world",
            "at least 4 correspondences (3 for P3P and 1 to choose among its solutions)",
            points_world.len(),
        ));
    }
    if !(options.threshold_px.is_finite() && options.threshold_px > 0.0) {
        return Err(Error::invalid(
            "threshold_px",
            "a positive finite number of pixels",
            options.threshold_px,
        ));
    }
    if !(options.confidence > 0.0 && options.confidence < 1.0) {
        return Err(Error::invalid(
            "confidence",
            "a probability in (0, 1)",
            options.confidence,
        ));
    }
    if options.max_iterations == 0 {
        return Err(Error::invalid("max_iterations", "at least 1", 0));
    }
    for (i, (x, p)) in points_world.iter().zip(pixels).enumerate() {
        ensure_finite(&format!("points_world[{i}]"), x.as_slice())?;
        ensure_finite(&format!("pixels[{i}]"), p.as_slice())?;
    }
    Ok(())
}

/// RANSAC PnP of a pinhole camera (`k`'s fx, fy, cx, cy; the baseline is unused): the pose
/// `cam_from_world` that maps `points_world` (metres) onto `pixels` (x = column, y = row) with
/// the most inliers, refined by [`refine_pose`] on them and re-scored. `Ok(None)` when no
/// model reaches `min_inliers`; an error for mismatched lengths, fewer than 4
/// correspondences, non-finite values or options out of range.
pub fn solve_pnp_ransac(
    k: &StereoIntrinsics,
    points_world: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    options: &PnpRansacOptions,
) -> Result<Option<PnpResult>> {
    check(k, points_world, pixels, options)?;
    let n = points_world.len();
    if n < options.min_inliers.max(3) {
        return Ok(None);
    }
    let bearings: Vec<Vector3<f64>> = pixels
        .iter()
        .map(|p| Vector3::new((p.x - k.cx) / k.fx, (p.y - k.cy) / k.fy, 1.0).normalize())
        .collect();
    let threshold_sq = options.threshold_px * options.threshold_px;
    let mut rng = ChaCha8Rng::seed_from_u64(options.seed);
    let mut flags = vec![false; n];
    let mut best: Option<(Se3, usize, f64)> = None;
    let mut needed = options.max_iterations;
    let mut iterations = 0;
    while iterations < needed.min(options.max_iterations) {
        iterations += 1;
        let i = rng.random_range(0..n);
        let mut j = rng.random_range(0..n - 1);
        if j >= i {
            j += 1;
        }
        let mut l = rng.random_range(0..n - 2);
        for lo in [i.min(j), i.max(j)] {
            if l >= lo {
                l += 1;
            }
        }
        let sample = [i, j, l];
        let world = sample.map(|s| points_world[s]);
        let rays = sample.map(|s| bearings[s]);
        for pose in p3p(&world, &rays) {
            let (count, msac) = score(k, &pose, points_world, pixels, threshold_sq, &mut flags);
            if best.as_ref().is_none_or(|b| msac < b.2) {
                best = Some((pose, count, msac));
                let w = count as f64 / n as f64;
                let all_inlier = w.powi(3);
                needed = if all_inlier >= 1.0 - f64::EPSILON {
                    0
                } else if all_inlier <= 0.0 {
                    options.max_iterations
                } else {
                    let est = (1.0 - options.confidence).ln() / (1.0 - all_inlier).ln();
                    if est.is_finite() {
                        est.ceil().max(1.0) as usize
                    } else {
                        options.max_iterations
                    }
                };
            }
        }
    }
    let Some((mut pose, mut count, _)) = best else {
        return Ok(None);
    };
    if count < options.min_inliers.max(3) {
        return Ok(None);
    }
    score(k, &pose, points_world, pixels, threshold_sq, &mut flags);
    // Refine on the inliers, re-score on everything; a second round if the set changed.
    let refine_options = PoseOptions {
        loss: Loss::Huber(options.threshold_px),
        min_depth: 1e-9,
        outlier_threshold_sq: threshold_sq,
        lm: LmOptions {
            max_iterations: 10,
            ..Default::default()
        },
    };
    let mut refined_flags = vec![false; n];
    for _ in 0..2 {
        let observations: Vec<PoseObservation> = (0..n)
            .filter(|&s| flags[s])
            .map(|s| PoseObservation::Mono {
                point: points_world[s],
                pixel: pixels[s],
            })
            .collect();
        let Ok(refined) = refine_pose(pose, k, &observations, &refine_options) else {
            break;
        };
        let (new_count, _) = score(
            k,
            &refined.cam_from_world,
            points_world,
            pixels,
            threshold_sq,
            &mut refined_flags,
        );
        if new_count < count {
            break;
        }
        let changed = refined_flags != flags;
        pose = refined.cam_from_world;
        count = new_count;
        std::mem::swap(&mut flags, &mut refined_flags);
        if !changed {
            break;
        }
    }
    if count < options.min_inliers {
        return Ok(None);
    }
    Ok(Some(PnpResult {
        cam_from_world: pose,
        inliers: flags,
        inlier_count: count,
        iterations,
    }))
}
