//! Relative pose, essential and fundamental matrices, Sampson and epipolar errors.
//!
//! Convention: `F` maps image 1 to lines in image 2, `x2ᵀ F x1 = 0` for homogeneous pixels,
//! `x = (u, v, 1)`, OpenCV pixels. For cameras `(K_i, R_i, t_i)` (cam from world):
//! `R₁₂ = R₂ R₁ᵀ`, `t₁₂ = t₂ − R₁₂ t₁` (camera 2 from camera 1), `E = [t₁₂]ₓ R₁₂`,
//! `F = K₂⁻ᵀ E K₁⁻¹`.
//!
//! PoseDiffusion's `get_fundamental_matrices` computes `E = R₁₂ [−R₁₂ᵀ t₁₂]ₓ = −[t₁₂]ₓ R₁₂`: the
//! same matrix with the opposite sign ([`fundamental_official`]). Neither is normalised.
//!
//! Sampson error (px²): `(x2ᵀ F x1)² / ((F x1)₀² + (F x1)₁² + (Fᵀ x2)₀² + (Fᵀ x2)₁²)`.
//!
//! # Pitfalls
//! - `Fᵀ` is the fundamental matrix from image 2 to image 1. Swapping the two is silent for a
//!   perfect match but wrong for everything else; the tests check the asymmetry.
//! - The official GGS transposes `F` and evaluates `x1ᵀ Fᵀ x2`: the same Sampson value.

use nalgebra::{Matrix3, Point2, Rotation3, Vector3};

use crate::camera::{Camera, Pose};
use crate::error::{GeometryError, Result};

/// `[v]ₓ`, the cross-product matrix: `[v]ₓ w = v × w` (PyTorch3D `hat`).
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The rotation angle of `r` in radians, stable near 0 and π (no `acos` of a rounded trace).
pub fn rotation_angle(r: &Rotation3<f64>) -> f64 {
    let m = r.matrix();
    let sin2 = Vector3::new(
        m[(2, 1)] - m[(1, 2)],
        m[(0, 2)] - m[(2, 0)],
        m[(1, 0)] - m[(0, 1)],
    )
    .norm();
    sin2.atan2(m.trace() - 1.0)
}

/// The angle between two rotation matrices in degrees: the rotation angle of `aᵀ b` (stable
/// near 0 and 180°, see [`rotation_angle`]).
pub fn rotation_angle_between_deg(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    rotation_angle(&Rotation3::from_matrix_unchecked(a.transpose() * b)).to_degrees()
}

/// The rotation closest to `K_b⁻¹ H K_a` (a homography of a pure rotation is `K_b R K_a⁻¹`)
/// and the ratio of its largest to smallest singular value after scaling to unit determinant
/// (1 for an exact rotation homography at the right intrinsics). `None` when singular.
pub fn homography_rotation(
    h: &Matrix3<f64>,
    k_a: &Matrix3<f64>,
    k_b_inverse: &Matrix3<f64>,
) -> Option<(Matrix3<f64>, f64)> {
    let m = k_b_inverse * h * k_a;
    let det = m.determinant();
    if !det.is_finite() || det.abs() < 1e-300 {
        return None;
    }
    let m = m / det.cbrt();
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let s = svd.singular_values;
    let ratio = s.max() / s.min().max(1e-300);
    let mut r = u * v_t;
    if r.determinant() < 0.0 {
        r = -r;
    }
    Some((r, ratio))
}

/// Camera 2 from camera 1: `R₁₂ = R₂ R₁ᵀ`, `t₁₂ = t₂ − R₁₂ t₁`, for cam-from-world poses.
pub fn relative_pose(cam1_from_world: &Pose, cam2_from_world: &Pose) -> Pose {
    cam2_from_world.compose(&cam1_from_world.inverse())
}

/// `E = [t]ₓ R` for `pose` = camera 2 from camera 1: `x̂2ᵀ E x̂1 = 0` for normalised coordinates.
pub fn essential_matrix(cam2_from_cam1: &Pose) -> Matrix3<f64> {
    skew(&cam2_from_cam1.translation) * cam2_from_cam1.rotation
}

/// `F = K₂⁻ᵀ [t₁₂]ₓ R₁₂ K₁⁻¹`, so that `x2ᵀ F x1 = 0` (OpenCV's and Hartley–Zisserman's `F`).
pub fn fundamental_from_cameras(cam1: &Camera, cam2: &Camera) -> Matrix3<f64> {
    let rel = relative_pose(&cam1.cam_from_world, &cam2.cam_from_world);
    cam2.intrinsics.inverse_matrix().transpose()
        * essential_matrix(&rel)
        * cam1.intrinsics.inverse_matrix()
}

/// PoseDiffusion's `get_fundamental_matrix(K1, R1, t1, K2, R2, t2)` term for term:
/// `F = K₂⁻ᵀ R₁₂ [−R₁₂ᵀ t₁₂]ₓ K₁⁻¹` (`= −`[`fundamental_from_cameras`] for rotations). Self
/// pairs give the zero matrix.
pub fn fundamental_official(cam1: &Camera, cam2: &Camera) -> Matrix3<f64> {
    let rel = relative_pose(&cam1.cam_from_world, &cam2.cam_from_world);
    let e = rel.rotation * skew(&(-(rel.rotation.transpose() * rel.translation)));
    cam2.intrinsics.inverse_matrix().transpose() * e * cam1.intrinsics.inverse_matrix()
}

/// The epipolar terms of a match: `x2ᵀ F x1`, `F x1` and `Fᵀ x2`.
fn epipolar_terms(
    f_2from1: &Matrix3<f64>,
    x1: &Point2<f64>,
    x2: &Point2<f64>,
) -> (f64, Vector3<f64>, Vector3<f64>) {
    let h1 = x1.to_homogeneous();
    let h2 = x2.to_homogeneous();
    let l2 = f_2from1 * h1;
    let l1 = f_2from1.transpose() * h2;
    (h2.dot(&l2), l2, l1)
}

fn degenerate_lines() -> GeometryError {
    GeometryError::Degenerate {
        what: "epipolar error",
        reason: "an epipolar line is undefined (F x1 or Fᵀ x2 has no direction)",
    }
}

/// Sampson error of the match `x1 ↔ x2` under `F` (`x2ᵀ F x1 = 0`), in px².
///
/// # Errors
/// [`GeometryError::Degenerate`] when the denominator vanishes (e.g. `F = 0`, a self pair) or the
/// result is not finite.
pub fn sampson_error(f_2from1: &Matrix3<f64>, x1: &Point2<f64>, x2: &Point2<f64>) -> Result<f64> {
    let (e, l2, l1) = epipolar_terms(f_2from1, x1, x2);
    let den = l2.x * l2.x + l2.y * l2.y + l1.x * l1.x + l1.y * l1.y;
    let value = e * e / den;
    if den > 0.0 && value.is_finite() {
        Ok(value)
    } else {
        Err(degenerate_lines())
    }
}

/// Sum of the squared distances of `x2` to the epipolar line `F x1` and of `x1` to `Fᵀ x2`,
/// in px².
///
/// # Errors
/// As [`sampson_error`], when either line is undefined.
pub fn symmetric_epipolar_distance_sq(
    f_2from1: &Matrix3<f64>,
    x1: &Point2<f64>,
    x2: &Point2<f64>,
) -> Result<f64> {
    let (e, l2, l1) = epipolar_terms(f_2from1, x1, x2);
    let n2 = l2.x * l2.x + l2.y * l2.y;
    let n1 = l1.x * l1.x + l1.y * l1.y;
    let value = e * e * (1.0 / n2 + 1.0 / n1);
    if n1 > 0.0 && n2 > 0.0 && value.is_finite() {
        Ok(value)
    } else {
        Err(degenerate_lines())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn skew_is_the_cross_product() {
        let a = Vector3::new(0.3, -1.2, 2.0);
        let b = Vector3::new(-0.7, 0.4, 1.1);
        assert!((skew(&a) * b - a.cross(&b)).norm() < 1e-15);
    }

    #[test]
    fn angle_between_rotations_is_the_relative_rotation_angle() {
        let axis = nalgebra::Unit::new_normalize(Vector3::new(0.2, -0.5, 0.8));
        let a = Rotation3::from_axis_angle(&axis, 0.7);
        for deg in [0.0, 1e-6, 37.0, 179.999_99, 180.0] {
            let d = Rotation3::from_axis_angle(
                &nalgebra::Unit::new_normalize(Vector3::new(-0.9, 0.1, 0.3)),
                f64::to_radians(deg),
            );
            let b = a * d;
            let got = rotation_angle_between_deg(a.matrix(), b.matrix());
            assert!((got - deg).abs() < 1e-9, "{deg}: {got}");
            // Symmetric, and the same in either world frame.
            let back = rotation_angle_between_deg(b.matrix(), a.matrix());
            assert!((back - got).abs() < 1e-9);
        }
    }

    #[test]
    fn zero_f_is_an_error_not_nan() {
        let p = Point2::new(1.0, 2.0);
        assert!(sampson_error(&Matrix3::zeros(), &p, &p).is_err());
        assert!(symmetric_epipolar_distance_sq(&Matrix3::zeros(), &p, &p).is_err());
    }
}
