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
        10_000,
        config.confidence,
    )?;
    let Some(h) = to_matrix3(&h)? else {
        return Ok(None);
    };
    Ok(Some((h, mask_count(&mask)? as f64 / kp1.len() as f64)))
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
    let normalise = |p: &[[f64; 2]], k_inv: &Matrix3<f64>| -> Vector<Point2d> {
        p.iter()
            .map(|q| {
                let x = k_inv * Vector3::new(q[0], q[1], 1.0);
                Point2d::new(x.x / x.z, x.y / x.z)
            })
            .collect()
    };
    let (n1, n2) = (normalise(kp1, &ka_inv), normalise(kp2, &kb_inv));
    // The pixel threshold in normalised coordinates, by the mean focal.
    let focal = 0.25 * (k_a[(0, 0)] + k_a[(1, 1)] + k_b[(0, 0)] + k_b[(1, 1)]);
    let identity = Mat::from_slice_2d(&[[1.0f64, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])?;
    let mut mask = Mat::default();
    let e = opencv::calib3d::find_essential_mat(
        &n1,
        &n2,
        &identity,
        opencv::calib3d::RANSAC,
        config.confidence,
        config.threshold_px / focal,
        10_000,
        &mut mask,
    )?;
    if e.rows() < 3 || mask.empty() {
        return Ok(None);
    }
    let e3 = Mat::roi(&e, opencv::core::Rect::new(0, 0, 3, 3))?.try_clone()?;
    let (mut r, mut t) = (Mat::default(), Mat::default());
    let inliers = opencv::calib3d::recover_pose_estimated(
        &e3, &n1, &n2, &identity, &mut r, &mut t, &mut mask,
    )?;
    let inliers = usize::try_from(inliers).unwrap_or(0);
    if inliers < config.min_inliers {
        return Ok(None);
    }
    let Some(rotation) = to_matrix3(&r)? else {
        return Ok(None);
    };
    if t.rows() != 3 {
        return Ok(None);
    }
    let translation = Vector3::new(
        *t.at_2d::<f64>(0, 0)?,
        *t.at_2d::<f64>(1, 0)?,
        *t.at_2d::<f64>(2, 0)?,
    );
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
