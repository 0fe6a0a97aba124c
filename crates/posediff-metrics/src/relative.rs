//! Relative-pose errors of all pairs `i < j`, exactly as the official `util/metric.py`
//! (`camera_to_rel_deg`, `so3_relative_angle`, `compare_translation_by_angle`).
//!
//! For cam-from-world poses `(R_i, t_i)` (OpenCV), the relative pose of pair `(i, j)` is camera
//! `j` from camera `i`: `R_ij = R_j R_iᵀ`, `t_ij = t_j − R_ij t_i`. The official code does the
//! same in PyTorch3D's row-vector convention; the two differ by the axis flip `diag(−1, −1, 1)`,
//! which leaves both angles below unchanged.
//!
//! - Rotation error: the angle of `R_ij,gt R_ij,predᵀ`, `cos = (tr − 1)/2`, through PyTorch3D's
//!   `acos_linear_extrapolation` with bounds `±(1 − 1e−4)`: beyond the bounds acos is replaced by
//!   its tangent at the bound, so **identical rotations give 0.4050717°, not 0**.
//! - Translation error: the angle between the directions, sign-ambiguous (`[0°, 90°]`):
//!   `acos(sqrt(1 − clamp_min(1 − (t̂_gt·t̂_pred)², 1e−15)))`, `t̂ = t / (‖t‖ + 1e−15)`.
//!
//! # Pitfalls
//! - Pairs are `i < j` in lexicographic order (`torch.combinations`).
//! - A zero relative translation has no direction: its error is 90°, as in the official code.

use nalgebra::{Matrix3, Vector3};
use posediff_geometry::{Pose, relative_pose};

use crate::error::{MetricsError, Result};

/// `cos_bound` of PyTorch3D's `so3_relative_angle`: acos is extrapolated linearly beyond
/// `±(1 − COS_BOUND)`.
pub const COS_BOUND: f64 = 1e-4;

/// `eps` of `so3_rotation_angle`: traces outside `[−1 − eps, 3 + eps]` are rejected.
pub const TRACE_EPS: f64 = 1e-4;

/// `eps` of the official `compare_translation_by_angle` (norm offset and clamp floor).
pub const TRANSLATION_EPS: f64 = 1e-15;

/// Rotation error charged to every pair of a camera the method did not estimate.
pub const FAILED_ROTATION_DEG: f64 = 180.0;

/// Translation error charged to every pair of a camera the method did not estimate.
pub const FAILED_TRANSLATION_DEG: f64 = 90.0;

/// PyTorch3D `acos_linear_extrapolation(x, (−bound, bound))`:
/// `(x − x0)·dacos(x0) + acos(x0)` beyond the bounds. The official code evaluates `x − x0` on a
/// float32 tensor, so `x0` enters the difference rounded to float32 (`0.9999` becomes
/// `0.99989998`), while `dacos(x0)` and `acos(x0)` are Python doubles. We do the same; it is what
/// makes identical rotations come out at exactly 0.4050717° (in exact arithmetic: 0.405139°).
fn acos_linear_extrapolation(x: f64, bound: f64) -> f64 {
    let tangent_at = |x0: f64| {
        let x0_in_tensor = f64::from(x0 as f32);
        (x - x0_in_tensor) * (-1.0 / (1.0 - x0 * x0).sqrt()) + x0.acos()
    };
    if x >= bound {
        tangent_at(bound)
    } else if x <= -bound {
        tangent_at(-bound)
    } else {
        x.acos()
    }
}

/// The official rotation error between two rotations, in degrees (PyTorch3D
/// `so3_relative_angle(r_gt, r_pred)` with the default bounds).
///
/// # Errors
/// [`MetricsError::NotARotation`] when `tr(r_gt r_predᵀ)` is outside `[−1 − 1e−4, 3 + 1e−4]`,
/// [`MetricsError::NonFinite`] for NaN or infinities.
pub fn rotation_angle_deg(r_gt: &Matrix3<f64>, r_pred: &Matrix3<f64>) -> Result<f64> {
    let trace = (r_gt * r_pred.transpose()).trace();
    if !trace.is_finite() {
        return Err(MetricsError::NonFinite { what: "rotation" });
    }
    if !(-1.0 - TRACE_EPS..=3.0 + TRACE_EPS).contains(&trace) {
        return Err(MetricsError::NotARotation { trace });
    }
    let cos = (trace - 1.0) * 0.5;
    Ok(acos_linear_extrapolation(cos, 1.0 - COS_BOUND).to_degrees())
}

/// The official sign-ambiguous angle between two translation directions, in degrees, `[0, 90]`.
///
/// # Errors
/// [`MetricsError::NonFinite`] for NaN or infinities.
pub fn translation_angle_deg(t_gt: &Vector3<f64>, t_pred: &Vector3<f64>) -> Result<f64> {
    if !t_gt.iter().chain(t_pred.iter()).all(|v| v.is_finite()) {
        return Err(MetricsError::NonFinite {
            what: "translation",
        });
    }
    let a = t_gt / (t_gt.norm() + TRANSLATION_EPS);
    let b = t_pred / (t_pred.norm() + TRANSLATION_EPS);
    let loss = (1.0 - a.dot(&b).powi(2)).max(TRANSLATION_EPS);
    Ok((1.0 - loss).sqrt().acos().to_degrees())
}

/// The errors of one pair `i < j`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairError {
    /// First frame.
    pub i: usize,
    /// Second frame, `j > i`.
    pub j: usize,
    /// Relative rotation error in degrees.
    pub rotation_deg: f64,
    /// Relative translation direction error in degrees (sign-ambiguous).
    pub translation_deg: f64,
}

impl PairError {
    /// `max(rotation, translation)`, the per-pair error mAA integrates.
    pub fn max_deg(&self) -> f64 {
        self.rotation_deg.max(self.translation_deg)
    }
}

/// All pairs `(i, j)`, `i < j`, in `torch.combinations` order.
pub fn all_pairs(n: usize) -> impl Iterator<Item = (usize, usize)> {
    (0..n).flat_map(move |i| (i + 1..n).map(move |j| (i, j)))
}

/// Official `camera_to_rel_deg` for one sequence: the errors of every pair `i < j`.
///
/// # Errors
/// Different lengths, fewer than two cameras, non-finite poses or non-rotations.
pub fn relative_pose_errors(gt: &[Pose], pred: &[Pose]) -> Result<Vec<PairError>> {
    let pred: Vec<Option<Pose>> = pred.iter().copied().map(Some).collect();
    relative_pose_errors_with_failures(gt, &pred)
}

/// [`relative_pose_errors`] where `None` marks a camera the method failed to estimate: each of
/// its pairs counts as [`FAILED_ROTATION_DEG`] / [`FAILED_TRANSLATION_DEG`], a failure at every
/// threshold.
///
/// # Errors
/// As [`relative_pose_errors`].
pub fn relative_pose_errors_with_failures(
    gt: &[Pose],
    pred: &[Option<Pose>],
) -> Result<Vec<PairError>> {
    if gt.len() != pred.len() {
        return Err(MetricsError::LengthMismatch {
            what: "relative pose errors",
            predicted: pred.len(),
            ground_truth: gt.len(),
        });
    }
    if gt.len() < 2 {
        return Err(MetricsError::TooFew {
            what: "cameras for relative pose errors",
            needed: 2,
            got: gt.len(),
        });
    }
    all_pairs(gt.len())
        .map(|(i, j)| {
            let rel_gt = relative_pose(&gt[i], &gt[j]);
            let (rotation_deg, translation_deg) = match (pred[i], pred[j]) {
                (Some(pi), Some(pj)) => {
                    let rel = relative_pose(&pi, &pj);
                    (
                        rotation_angle_deg(&rel_gt.rotation, &rel.rotation)?,
                        translation_angle_deg(&rel_gt.translation, &rel.translation)?,
                    )
                }
                _ => (FAILED_ROTATION_DEG, FAILED_TRANSLATION_DEG),
            };
            Ok(PairError {
                i,
                j,
                rotation_deg,
                translation_deg,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_rotations_give_the_extrapolated_floor() {
        let e = rotation_angle_deg(&Matrix3::identity(), &Matrix3::identity()).unwrap();
        assert!((e - 0.405_071_7).abs() < 1e-7, "{e}");
    }

    #[test]
    fn opposite_rotations_and_bad_matrices() {
        let flip = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
        let e = rotation_angle_deg(&Matrix3::identity(), &flip).unwrap();
        assert!((e - 180.0).abs() < 1.0, "{e}");
        assert!(matches!(
            rotation_angle_deg(&Matrix3::identity(), &(Matrix3::identity() * 2.0)),
            Err(MetricsError::NotARotation { .. })
        ));
    }

    #[test]
    fn translation_angle_is_sign_ambiguous() {
        let a = Vector3::new(1.0, 0.0, 0.0);
        // The 1e-15 norm offset and clamp floor leave a few 1e-6° in float64 (the official
        // float32 rounds them to 0; the reference tolerance is 1e-3°).
        assert!(translation_angle_deg(&a, &(-2.0 * a)).unwrap() < 1e-5);
        let e = translation_angle_deg(&Vector3::y(), &Vector3::new(0.0, 1.0, 1.0)).unwrap();
        assert!((e - 45.0).abs() < 1e-9);
        let zero = translation_angle_deg(&Vector3::zeros(), &a).unwrap();
        assert!((zero - 90.0).abs() < 1e-9);
    }

    #[test]
    fn pairs_are_lexicographic() {
        let p: Vec<_> = all_pairs(4).collect();
        assert_eq!(p, vec![(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]);
    }

    #[test]
    fn a_failed_camera_fails_all_its_pairs() {
        let gt = vec![Pose::identity(); 3];
        let mut p1 = Pose::identity();
        p1.translation.x = 1.0;
        let mut gt = gt;
        gt[1] = p1;
        gt[2].translation.y = 1.0;
        let pred = vec![Some(gt[0]), None, Some(gt[2])];
        let e = relative_pose_errors_with_failures(&gt, &pred).unwrap();
        assert_eq!(e.len(), 3);
        assert_eq!(e[0].rotation_deg, FAILED_ROTATION_DEG);
        assert_eq!(e[2].rotation_deg, FAILED_ROTATION_DEG);
        assert!(e[1].rotation_deg < 1.0 && e[1].translation_deg < 1e-5);
    }
}
