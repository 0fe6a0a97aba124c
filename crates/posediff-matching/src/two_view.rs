//! Two-view geometry of a matched pair through OpenCV: a least-squares fundamental matrix, a
//! homography test for pairs without parallax, and the relative pose from the essential matrix
//! when the intrinsics are known.
//!
//! Conventions: `kp1` in image `a`, `kp2` in image `b` (OpenCV pixels); the relative pose maps
//! camera `a`'s frame into camera `b`'s: `x_b = R x_a + t`, `|t| = 1`.

use nalgebra::{Matrix3, Vector3};
use opencv::core::{Mat, Point2d, Point2f, Vector};
use opencv::prelude::*;

use crate::error::Result;

/// Settings of the two-view estimates.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct TwoViewConfig {
    /// Inlier threshold in pixels (essential matrix and homography).
    pub threshold_px: f64,
    /// RANSAC confidence.
    pub confidence: f64,
    /// A pair is a homography pair when at least this fraction of its matches fit one
    /// homography within the threshold.
    pub homography_fraction: f64,
    /// The homography RANSAC runs only the iterations that find, at `confidence`, a
    /// homography explaining at least this fraction `w` of the matches: `ln(1 − c) /
    /// ln(1 − w⁴)` (108 at 0.5 and 0.999), where OpenCV's cap was 10,000. Only fractions of at
    /// least `homography_fraction` (0.9) decide anything, and OpenCV's adaptive count stops a
    /// pair whose best fraction is ≥ `w` at the same iteration either way, so such pairs get
    /// the same homography; pairs below `w` (general pairs, some 10–40 %) stop early. Measured
    /// on the 300-frame orbit of `cargo xtask bench-scale` (docs/BENCHMARKS.md, "Video-scale
    /// speed"): `findHomography` was 15 % of the mapper's time with OpenCV's cap; with 0.5 the
    /// mapper took 54.1 / 49.4 s instead of 60.7 / 62.3 s, same pairs and scores.
    pub homography_min_fraction: f64,
    /// The cheirality test of the relative pose counts a triangulated match only nearer than
    /// this, in units of the baseline, to both cameras (farther points are at infinity, their
    /// depth sign is noise): OpenCV's `recoverPose` `distanceThresh`, whose default (50) this
    /// keeps, so the poses are OpenCV's.
    pub cheirality_distance: f64,
    /// A homography pair whose `K_b⁻¹HK_a` has singular values within this ratio of each other
    /// is a rotation (no measurable baseline).
    pub rotation_tolerance: f64,
    /// Fewest essential-matrix inliers in front of both cameras for a usable pose.
    pub min_inliers: usize,
}

impl Default for TwoViewConfig {
    fn default() -> Self {
        Self {
            threshold_px: 1.0,
            confidence: 0.999,
            homography_fraction: 0.9,
            homography_min_fraction: 0.5,
            cheirality_distance: 50.0,
            rotation_tolerance: 1.05,
            min_inliers: 15,
        }
    }
}

/// The relative pose of a pair (`posediff_geometry::TwoViewPose`).
pub use posediff_geometry::TwoViewPose as RelativePose;

fn points(p: &[[f64; 2]]) -> Vector<Point2f> {
    p.iter()
        .map(|q| Point2f::new(q[0] as f32, q[1] as f32))
        .collect()
}

fn points_f64(p: &[[f64; 2]]) -> Vector<Point2d> {
    p.iter().map(|q| Point2d::new(q[0], q[1])).collect()
}

fn to_matrix3(m: &Mat) -> Result<Option<Matrix3<f64>>> {
    if m.rows() < 3 || m.cols() != 3 {
        return Ok(None);
    }
    let mut out = Matrix3::zeros();
    for i in 0..3 {
        for j in 0..3 {
            out[(i, j)] = *m.at_2d::<f64>(i as i32, j as i32)?;
        }
    }
    Ok(out.iter().all(|v| v.is_finite()).then_some(out))
}

fn mask_count(mask: &Mat) -> Result<usize> {
    if mask.empty() {
        return Ok(0);
    }
    Ok(mask.data_typed::<u8>()?.iter().filter(|m| **m != 0).count())
}

/// The least-squares (normalised eight-point) fundamental matrix of matches that are already
/// inliers; `x_bᵀ F x_a = 0`. `None` for fewer than 8 matches or a degenerate configuration.
///
/// # Errors
/// OpenCV errors.
pub fn fundamental_least_squares(
    kp1: &[[f64; 2]],
    kp2: &[[f64; 2]],
) -> Result<Option<Matrix3<f64>>> {
    if kp1.len() < 8 || kp1.len() != kp2.len() {
        return Ok(None);
    }
    let mut mask = Mat::default();
    let f = opencv::calib3d::find_fundamental_mat(
        &points_f64(kp1),
        &points_f64(kp2),
        opencv::calib3d::FM_8POINT,
        1.0,
        0.99,
        1,
        &mut mask,
    )?;
    to_matrix3(&f)
}

/// Fraction of the matches that one homography explains within the threshold (RANSAC), and
/// the homography (`x_b ~ H x_a`).
///
/// # Errors
/// OpenCV errors.
pub fn homography_fit(
    kp1: &[[f64; 2]],
    kp2: &[[f64; 2]],
    config: &TwoViewConfig,
) -> Result<Option<(Matrix3<f64>, f64)>> {
    if kp1.len() < 4 || kp1.len() != kp2.len() {
        return Ok(None);
    }
    let mut mask = Mat::default();
    let h = opencv::calib3d::find_homography_ext(
        &points(kp1),
        &points(kp2),
        opencv::calib3d::RANSAC,
        config.threshold_px,
        &mut mask,
        homography_iterations(config),
        config.confidence,
    )?;
    let Some(h) = to_matrix3(&h)? else {
        return Ok(None);
    };
    Ok(Some((h, mask_count(&mask)? as f64 / kp1.len() as f64)))
}

/// `K⁻¹ x` of each pixel, dehomogenised.
fn normalised(p: &[[f64; 2]], k_inv: &Matrix3<f64>) -> Vec<[f64; 2]> {
    p.iter()
        .map(|q| {
            let x = k_inv * Vector3::new(q[0], q[1], 1.0);
            [x.x / x.z, x.y / x.z]
        })
        .collect()
}

/// OpenCV's five-point RANSAC on normalised matches: the essential matrix and its inlier mask
/// (`None` when it finds none).
fn essential_ransac(
    n1: &[[f64; 2]],
    n2: &[[f64; 2]],
    threshold: f64,
    confidence: f64,
) -> Result<Option<(Matrix3<f64>, Vec<bool>)>> {
    let identity = Mat::from_slice_2d(&[[1.0f64, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])?;
    let mut mask = Mat::default();
    let e = opencv::calib3d::find_essential_mat(
        &points_f64(n1),
        &points_f64(n2),
        &identity,
        opencv::calib3d::RANSAC,
        confidence,
        threshold,
        10_000,
        &mut mask,
    )?;
    if e.rows() < 3 || mask.empty() {
        return Ok(None);
    }
    let e3 = Mat::roi(&e, opencv::core::Rect::new(0, 0, 3, 3))?.try_clone()?;
    let Some(e3) = to_matrix3(&e3)? else {
        return Ok(None);
    };
    let ransac: Vec<bool> = mask.data_bytes()?.iter().map(|&m| m != 0).collect();
    Ok((ransac.len() == n1.len()).then_some((e3, ransac)))
}

/// OpenCV 4.6's `recoverPose(E, points1, points2, I, R, t, mask)` on normalised points, without
/// its per-point 4×4 SVDs (`triangulatePoints` was 15 % of a 300-frame orbit's mapper; perf,
/// docs/BENCHMARKS.md "Video-scale speed"): `E` is decomposed as `decomposeEssentialMat` does
/// (`R₁ = UWVᵀ`, `R₂ = UWᵀVᵀ`, `t = U₃`, `U` and `V` made proper), each of the four poses
/// triangulates every RANSAC inlier and counts those in front of both cameras and nearer than
/// `max_distance` ([`TwoViewConfig::cheirality_distance`]), and the first pose with the most wins, in OpenCV's order.
///
/// The triangulation fixes the point's fourth coordinate at 1 and solves the DLT's 4×3 least
/// squares (a 3×3 system) where OpenCV takes the 4×4 system's smallest singular vector; the two
/// agree on the side of each camera a point lies on except for points at the thresholds, and
/// the pose chosen is the same (tested against OpenCV). Returns `(R, t, count)`, `|t| = 1`.
fn recover_pose(
    e: &Matrix3<f64>,
    n1: &[[f64; 2]],
    n2: &[[f64; 2]],
    ransac: &[bool],
    max_distance: f64,
) -> Option<(Matrix3<f64>, Vector3<f64>, usize)> {
    let svd = e.svd(true, true);
    let (mut u, mut v_t) = (svd.u?, svd.v_t?);
    // The smallest singular value's column of U is t; order the rest as OpenCV (descending).
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| svd.singular_values[b].total_cmp(&svd.singular_values[a]));
    u = Matrix3::from_columns(&order.map(|k| u.column(k).into_owned()));
    v_t = Matrix3::from_rows(&order.map(|k| v_t.row(k).into_owned()));
    if u.determinant() < 0.0 {
        u = -u;
    }
    if v_t.determinant() < 0.0 {
        v_t = -v_t;
    }
    let w = Matrix3::new(0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let (r1, r2) = (u * w * v_t, u * w.transpose() * v_t);
    let t: Vector3<f64> = u.column(2).into_owned();
    let candidates = [(r1, t), (r2, t), (r1, -t), (r2, -t)];
    let in_front = |r: &Matrix3<f64>, t: &Vector3<f64>, x1: &[f64; 2], x2: &[f64; 2]| {
        // DLT rows: x₁P₀³ − P₀¹, y₁P₀³ − P₀², x₂P³ − P¹, y₂P³ − P², P₀ = [I | 0], P = [R | t].
        let rows = [
            [-1.0, 0.0, x1[0], 0.0],
            [0.0, -1.0, x1[1], 0.0],
            [
                x2[0] * r[(2, 0)] - r[(0, 0)],
                x2[0] * r[(2, 1)] - r[(0, 1)],
                x2[0] * r[(2, 2)] - r[(0, 2)],
                x2[0] * t[2] - t[0],
            ],
            [
                x2[1] * r[(2, 0)] - r[(1, 0)],
                x2[1] * r[(2, 1)] - r[(1, 1)],
                x2[1] * r[(2, 2)] - r[(1, 2)],
                x2[1] * t[2] - t[1],
            ],
        ];
        let mut m = Matrix3::zeros();
        let mut b = Vector3::zeros();
        for row in &rows {
            for i in 0..3 {
                b[i] -= row[i] * row[3];
                for j in 0..3 {
                    m[(i, j)] += row[i] * row[j];
                }
            }
        }
        let Some(x) = m.try_inverse().map(|mi| mi * b) else {
            return false;
        };
        let z2 = (r * x + t).z;
        x.z > 0.0 && x.z < max_distance && z2 > 0.0 && z2 < max_distance
    };
    let counts = candidates.map(|(r, t)| {
        n1.iter()
            .zip(n2)
            .zip(ransac)
            .filter(|((x1, x2), inlier)| **inlier && in_front(&r, &t, x1, x2))
            .count()
    });
    // OpenCV's order: the first of the most.
    let best = (0..4).find(|&k| counts.iter().all(|&c| counts[k] >= c))?;
    let (r, t) = candidates[best];
    Some((r, t, counts[best]))
}

/// The homography RANSAC's iteration cap ([`TwoViewConfig::homography_min_fraction`]):
/// `⌈ln(1 − c) / ln(1 − w⁴)⌉`, at least 1 and at most OpenCV's 10,000.
#[must_use]
pub fn homography_iterations(config: &TwoViewConfig) -> i32 {
    let w4 = config.homography_min_fraction.clamp(0.0, 1.0).powi(4);
    let c = config.confidence.clamp(0.0, 1.0 - 1e-12);
    if w4 <= 0.0 {
        return 10_000;
    }
    if w4 >= 1.0 {
        return 1;
    }
    let k = ((1.0 - c).ln() / (1.0 - w4).ln()).ceil();
    if k.is_finite() {
        k.clamp(1.0, 10_000.0) as i32
    } else {
        10_000
    }
}

pub use posediff_geometry::homography_rotation;

/// The relative pose of a matched pair with known intrinsics (`K_a`, `K_b`), from the
/// essential matrix of the normalised matches (OpenCV RANSAC five-point, then the cheirality
/// test of `recoverPose`). Rotation-only pairs are detected first by [`homography_fit`]. `None`
/// when no pose has enough inliers.
///
/// # Errors
/// OpenCV errors.
pub fn relative_pose(
    kp1: &[[f64; 2]],
    kp2: &[[f64; 2]],
    k_a: &Matrix3<f64>,
    k_b: &Matrix3<f64>,
    config: &TwoViewConfig,
) -> Result<Option<RelativePose>> {
    if kp1.len() < config.min_inliers.max(5) || kp1.len() != kp2.len() {
        return Ok(None);
    }
    let homography = homography_fit(kp1, kp2, config)?;
    relative_pose_with_homography(kp1, kp2, homography, k_a, k_b, config)
}

/// [`relative_pose`] with the pair's [`homography_fit`] already made (it does not depend on the
/// intrinsics, so a caller trying several focals fits it once).
///
/// # Errors
/// OpenCV errors.
pub fn relative_pose_with_homography(
    kp1: &[[f64; 2]],
    kp2: &[[f64; 2]],
    homography: Option<(Matrix3<f64>, f64)>,
    k_a: &Matrix3<f64>,
    k_b: &Matrix3<f64>,
    config: &TwoViewConfig,
) -> Result<Option<RelativePose>> {
    if kp1.len() < config.min_inliers.max(5) || kp1.len() != kp2.len() {
        return Ok(None);
    }
    let (Some(ka_inv), Some(kb_inv)) = (k_a.try_inverse(), k_b.try_inverse()) else {
        return Ok(None);
    };
    if let Some((h, fraction)) = homography
        && fraction >= config.homography_fraction
        && let Some((rotation, ratio)) = homography_rotation(&h, k_a, &kb_inv)
        && ratio <= config.rotation_tolerance
    {
        return Ok(Some(RelativePose::RotationOnly {
            rotation,
            inliers: (fraction * kp1.len() as f64).round() as usize,
        }));
    }
    let (n1, n2) = (normalised(kp1, &ka_inv), normalised(kp2, &kb_inv));
    // The pixel threshold in normalised coordinates, by the mean focal.
    let focal = 0.25 * (k_a[(0, 0)] + k_a[(1, 1)] + k_b[(0, 0)] + k_b[(1, 1)]);
    let Some((e3, ransac)) =
        essential_ransac(&n1, &n2, config.threshold_px / focal, config.confidence)?
    else {
        return Ok(None);
    };
    let Some((rotation, translation, inliers)) =
        recover_pose(&e3, &n1, &n2, &ransac, config.cheirality_distance)
    else {
        return Ok(None);
    };
    if inliers < config.min_inliers {
        return Ok(None);
    }
    let norm = translation.norm();
    if !(norm > 0.0 && norm.is_finite()) {
        return Ok(None);
    }
    Ok(Some(RelativePose::General {
        rotation,
        translation: translation / norm,
        inliers,
    }))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    use nalgebra::{Point3, Rotation3};

    #[test]
    fn the_homography_cap_finds_a_fraction_of_at_least_the_minimum() {
        let cap = |w: f64| {
            homography_iterations(&TwoViewConfig {
                homography_min_fraction: w,
                ..TwoViewConfig::default()
            })
        };
        assert_eq!(cap(0.5), 108);
        // At the cap, a sample of four inliers of fraction w is drawn with probability ≥ c.
        for w in [0.3, 0.5, 0.9] {
            let k = f64::from(cap(w));
            assert!(1.0 - (1.0 - w.powi(4)).powf(k) >= 0.999);
            assert!(1.0 - (1.0 - w.powi(4)).powf(k - 1.0) < 0.999);
        }
        assert_eq!(cap(1.0), 1);
        assert_eq!(cap(0.0), 10_000);
        assert_eq!(cap(0.01), 10_000, "OpenCV's cap bounds it");
    }

    /// Matches in both images, `K`, and the true `R`, `t` of the pair.
    type Scene = (
        Vec<[f64; 2]>,
        Vec<[f64; 2]>,
        Matrix3<f64>,
        Matrix3<f64>,
        Vector3<f64>,
    );

    fn scene(baseline: f64) -> Scene {
        let k = Matrix3::new(500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0);
        let r = *Rotation3::from_euler_angles(0.05, -0.2, 0.03).matrix();
        let t = Vector3::new(baseline, 0.1 * baseline, 0.02 * baseline);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        let mut s: u64 = 7;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..200 {
            let x = Point3::new(rnd() * 4.0 - 2.0, rnd() * 3.0 - 1.5, 4.0 + rnd() * 3.0);
            let xb = r * x.coords + t;
            let pa = k * x.coords;
            let pb = k * xb;
            a.push([pa.x / pa.z, pa.y / pa.z]);
            b.push([pb.x / pb.z, pb.y / pb.z]);
        }
        (a, b, k, r, t)
    }

    #[test]
    fn the_pose_recovered_is_opencvs() {
        for (baseline, noise_px) in [(1.0, 0.0), (1.0, 0.7), (0.3, 0.5)] {
            let (mut a, mut b, k, r, _) = scene(baseline);
            let mut s: u64 = 3;
            let mut rnd = || {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1);
                (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
            };
            for p in a.iter_mut().chain(b.iter_mut()) {
                p[0] += 2.0 * noise_px * rnd();
                p[1] += 2.0 * noise_px * rnd();
            }
            // Twenty outliers.
            b[..20].rotate_left(7);
            let k_inv = k.try_inverse().unwrap();
            let (n1, n2) = (normalised(&a, &k_inv), normalised(&b, &k_inv));
            let (e, ransac) = essential_ransac(&n1, &n2, 1.0 / 500.0, 0.999)
                .unwrap()
                .unwrap();
            let (ours_r, ours_t, ours_n) = recover_pose(
                &e,
                &n1,
                &n2,
                &ransac,
                TwoViewConfig::default().cheirality_distance,
            )
            .unwrap();
            let rows: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| e[(i, j)]));
            let e3 = Mat::from_slice_2d(&rows).unwrap();
            let identity = Mat::eye(3, 3, opencv::core::CV_64F)
                .unwrap()
                .to_mat()
                .unwrap();
            let mut mask =
                Mat::from_slice(&ransac.iter().map(|&m| u8::from(m)).collect::<Vec<_>>())
                    .unwrap()
                    .try_clone()
                    .unwrap();
            let (mut cv_r, mut cv_t) = (Mat::default(), Mat::default());
            let cv_n = opencv::calib3d::recover_pose_estimated(
                &e3,
                &points_f64(&n1),
                &points_f64(&n2),
                &identity,
                &mut cv_r,
                &mut cv_t,
                &mut mask,
            )
            .unwrap();
            let cv_r = to_matrix3(&cv_r).unwrap().unwrap();
            let cv_t = Vector3::new(
                *cv_t.at_2d::<f64>(0, 0).unwrap(),
                *cv_t.at_2d::<f64>(1, 0).unwrap(),
                *cv_t.at_2d::<f64>(2, 0).unwrap(),
            );
            assert!((ours_r - cv_r).norm() < 1e-9, "R at baseline {baseline}");
            assert!((ours_t - cv_t).norm() < 1e-9, "t at baseline {baseline}");
            assert_eq!(
                ours_n,
                usize::try_from(cv_n).unwrap(),
                "count at {baseline}"
            );
            assert!(ours_n >= 170, "{ours_n} of 200");
            assert!((ours_r - r).norm() < 0.05);
        }
    }

    #[test]
    fn pose_from_exact_matches() {
        let (a, b, k, r, t) = scene(1.0);
        let Some(RelativePose::General {
            rotation,
            translation,
            ..
        }) = relative_pose(&a, &b, &k, &k, &TwoViewConfig::default()).unwrap()
        else {
            panic!("expected a general pose");
        };
        assert!((rotation - r).norm() < 1e-3);
        assert!((translation - t.normalize()).norm() < 1e-3, "{translation}");
        let f = fundamental_least_squares(&a, &b).unwrap().unwrap();
        let x1 = Vector3::new(a[3][0], a[3][1], 1.0);
        let x2 = Vector3::new(b[3][0], b[3][1], 1.0);
        let line = f * x1;
        assert!((x2.dot(&line) / line.xy().norm()).abs() < 1e-3);
    }

    #[test]
    fn pure_rotation_is_detected() {
        let (a, b, k, r, _) = scene(0.0);
        match relative_pose(&a, &b, &k, &k, &TwoViewConfig::default()).unwrap() {
            Some(RelativePose::RotationOnly { rotation, .. }) => {
                assert!((rotation - r).norm() < 1e-4);
            }
            other => panic!("expected rotation only, got {other:?}"),
        }
    }
}
