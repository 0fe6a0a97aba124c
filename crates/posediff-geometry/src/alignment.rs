//! Similarity transforms, Umeyama alignment of point sets and alignment of camera sets.
//!
//! A [`Sim3`] acts on world points as `X' = s R X + t`. Applying it to a camera
//! ([`Sim3::transform_camera`]) gives the camera that sees `X'` exactly where the original saw
//! `X`; its camera frame is scaled by `s`, so projections (and relative rotations, and
//! translation directions) are unchanged.
//!
//! # Pitfalls
//! - Umeyama needs three non-collinear points for a unique rotation; two points or a line leave a
//!   rotation about the line free, and this module says so instead of guessing.
//! - PyTorch3D's `corresponding_cameras_alignment` (mode `"extrinsics"`, what the official demo
//!   calls) is *not* Umeyama on centres: it averages rotations and matches `Rᵀt` terms.
//!   Both are here, under their own names.

use nalgebra::{Matrix3, Point3, Vector3};

use crate::camera::{Camera, Pose};
use crate::error::{GeometryError, Result, ensure_finite};

/// Relative size of the second singular value of the cross-covariance below which the point
/// sets are taken as collinear (rotation undetermined).
const COLLINEAR_TOLERANCE: f64 = 1e-12;

/// `eps` of PyTorch3D's `corresponding_cameras_alignment` as the official demo calls it: the
/// floor of the variance in the scale estimate.
pub const EXTRINSICS_ALIGNMENT_EPS: f64 = 1e-9;

/// A similarity transform `X' = s R X + t`, `s > 0`, `R` a rotation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3 {
    /// Rotation `R`.
    pub rotation: Matrix3<f64>,
    /// Translation `t`.
    pub translation: Vector3<f64>,
    /// Scale `s`.
    pub scale: f64,
}

impl Sim3 {
    /// The identity.
    pub fn identity() -> Self {
        Self {
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        }
    }

    /// A rigid transform (scale 1).
    pub fn from_pose(pose: &Pose) -> Self {
        Self {
            rotation: pose.rotation,
            translation: pose.translation,
            scale: 1.0,
        }
    }

    /// The inverse `X = Rᵀ (X' − t) / s`.
    pub fn inverse(&self) -> Self {
        let rt = self.rotation.transpose();
        Self {
            rotation: rt,
            translation: -(rt * self.translation) / self.scale,
            scale: 1.0 / self.scale,
        }
    }

    /// `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &Self) -> Self {
        Self {
            rotation: self.rotation * other.rotation,
            translation: self.scale * (self.rotation * other.translation) + self.translation,
            scale: self.scale * other.scale,
        }
    }

    /// `s R X + t`.
    pub fn transform_point(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.scale * (self.rotation * p.coords) + self.translation)
    }

    /// The extrinsics that see the transformed world as `pose` saw the original one:
    /// `R' = R Rₛᵀ`, `t' = s t − R' tₛ`.
    pub fn transform_pose(&self, pose: &Pose) -> Pose {
        let r = pose.rotation * self.rotation.transpose();
        Pose::new(r, self.scale * pose.translation - r * self.translation)
    }

    /// [`Self::transform_pose`] applied to a camera's extrinsics; intrinsics unchanged.
    pub fn transform_camera(&self, camera: &Camera) -> Camera {
        Camera {
            cam_from_world: self.transform_pose(&camera.cam_from_world),
            ..*camera
        }
    }
}

fn check_pair(src: &[Point3<f64>], dst: &[Point3<f64>]) -> Result<()> {
    if src.len() != dst.len() {
        return Err(GeometryError::LengthMismatch {
            what: "Umeyama point sets",
            left: src.len(),
            right: dst.len(),
        });
    }
    if src.len() < 3 {
        return Err(GeometryError::TooFew {
            what: "Umeyama points",
            needed: 3,
            got: src.len(),
        });
    }
    ensure_finite(
        "Umeyama points",
        src.iter().chain(dst).flat_map(|p| p.iter()),
    )
}

fn mean(points: &[Point3<f64>]) -> Vector3<f64> {
    points.iter().map(|p| p.coords).sum::<Vector3<f64>>() / points.len() as f64
}

/// The parts of an Umeyama fit.
struct UmeyamaFit {
    rotation: Matrix3<f64>,
    scale: f64,
    mu_src: Vector3<f64>,
    mu_dst: Vector3<f64>,
}

/// Umeyama (1991) least-squares alignment `dst ≈ s R src + t`.
fn umeyama_impl(src: &[Point3<f64>], dst: &[Point3<f64>]) -> Result<UmeyamaFit> {
    check_pair(src, dst)?;
    let n = src.len() as f64;
    let mu_src = mean(src);
    let mu_dst = mean(dst);
    let mut cov = Matrix3::zeros();
    let mut var_src = 0.0;
    for (p, q) in src.iter().zip(dst) {
        let a = p.coords - mu_src;
        let b = q.coords - mu_dst;
        cov += b * a.transpose();
        var_src += a.norm_squared();
    }
    cov /= n;
    var_src /= n;
    if var_src == 0.0 {
        return Err(GeometryError::Degenerate {
            what: "Umeyama alignment",
            reason: "all source points coincide",
        });
    }
    let svd = cov.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(GeometryError::Degenerate {
            what: "Umeyama alignment",
            reason: "SVD failed",
        });
    };
    let d = svd.singular_values;
    if d[0] == 0.0 || d[1] <= COLLINEAR_TOLERANCE * d[0] {
        return Err(GeometryError::Degenerate {
            what: "Umeyama alignment",
            reason: "points are collinear or coincide: rotation undetermined",
        });
    }
    let mut s = Vector3::new(1.0, 1.0, 1.0);
    if (u.determinant() * v_t.determinant()) < 0.0 {
        s[2] = -1.0;
    }
    let rotation = u * Matrix3::from_diagonal(&s) * v_t;
    let scale = d.dot(&s) / var_src;
    Ok(UmeyamaFit {
        rotation,
        scale,
        mu_src,
        mu_dst,
    })
}

/// Rigid alignment (rotation + translation, no scale) with `dst ≈ R src + t`, by Umeyama's
/// method without the scale.
///
/// # Errors
/// Fewer than three points, different lengths, non-finite values, coincident or collinear points.
pub fn umeyama(src: &[Point3<f64>], dst: &[Point3<f64>]) -> Result<Sim3> {
    let fit = umeyama_impl(src, dst)?;
    Ok(Sim3 {
        rotation: fit.rotation,
        translation: fit.mu_dst - fit.rotation * fit.mu_src,
        scale: 1.0,
    })
}

/// Similarity alignment `dst ≈ s R src + t` (Umeyama 1991; PyTorch3D
/// `corresponding_points_alignment(estimate_scale=True, allow_reflection=False)`).
///
/// # Errors
/// As [`umeyama`]; also a zero scale (all target points coincide).
pub fn umeyama_with_scale(src: &[Point3<f64>], dst: &[Point3<f64>]) -> Result<Sim3> {
    let UmeyamaFit {
        rotation,
        scale,
        mu_src,
        mu_dst,
    } = umeyama_impl(src, dst)?;
    if scale <= 0.0 || !scale.is_finite() {
        return Err(GeometryError::Degenerate {
            what: "Umeyama alignment",
            reason: "the estimated scale is not positive",
        });
    }
    Ok(Sim3 {
        rotation,
        translation: mu_dst - scale * (rotation * mu_src),
        scale,
    })
}

/// The similarity that moves the centres of `src` onto those of `dst` (Umeyama with scale;
/// PyTorch3D `corresponding_cameras_alignment(mode="centers")`).
///
/// # Errors
/// As [`umeyama_with_scale`].
pub fn align_cameras_by_centers(src: &[Camera], dst: &[Camera]) -> Result<Sim3> {
    let a: Vec<_> = src.iter().map(Camera::center).collect();
    let b: Vec<_> = dst.iter().map(Camera::center).collect();
    umeyama_with_scale(&a, &b)
}

/// PyTorch3D `corresponding_cameras_alignment(mode="extrinsics", estimate_scale=True,
/// eps=1e-9)`, the alignment of the official demo: the rotation from the SVD of
/// `mean_i(R_src,iᵀ R_dst,i)`, then scale and translation by least squares on
/// `A_i = R_src,iᵀ t_src,i`, `B_i = R_src,iᵀ t_dst,i` (OpenCV matrices; the PyTorch3D axis flips
/// cancel). Unlike PyTorch3D, a reflection is never returned: the rotation is projected onto
/// SO(3) like Umeyama's.
///
/// # Errors
/// Empty or differently sized inputs, non-finite poses, a non-positive scale.
pub fn align_cameras_by_extrinsics(src: &[Camera], dst: &[Camera]) -> Result<Sim3> {
    if src.len() != dst.len() {
        return Err(GeometryError::LengthMismatch {
            what: "camera sets",
            left: src.len(),
            right: dst.len(),
        });
    }
    if src.is_empty() {
        return Err(GeometryError::TooFew {
            what: "cameras to align",
            needed: 1,
            got: 0,
        });
    }
    for c in src.iter().chain(dst) {
        c.cam_from_world.ensure_finite()?;
    }
    let n = src.len() as f64;
    let rr_cov = src
        .iter()
        .zip(dst)
        .map(|(s, d)| s.cam_from_world.rotation.transpose() * d.cam_from_world.rotation)
        .sum::<Matrix3<f64>>()
        / n;
    let svd = rr_cov.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(GeometryError::Degenerate {
            what: "extrinsics alignment",
            reason: "SVD failed",
        });
    };
    // torch.svd: RRcov = U S Vᵀ, R_A = V Uᵀ.
    let v = v_t.transpose();
    let mut fix = Vector3::new(1.0, 1.0, 1.0);
    if (v * u.transpose()).determinant() < 0.0 {
        fix[2] = -1.0;
    }
    let r_a = v * Matrix3::from_diagonal(&fix) * u.transpose();

    let a: Vec<Vector3<f64>> = src
        .iter()
        .map(|c| c.cam_from_world.rotation.transpose() * c.cam_from_world.translation)
        .collect();
    let b: Vec<Vector3<f64>> = src
        .iter()
        .zip(dst)
        .map(|(s, d)| s.cam_from_world.rotation.transpose() * d.cam_from_world.translation)
        .collect();
    let a_mu = a.iter().sum::<Vector3<f64>>() / n;
    let b_mu = b.iter().sum::<Vector3<f64>>() / n;
    let scale = if src.len() > 1 {
        let (mut num, mut den) = (0.0, 0.0);
        for (ai, bi) in a.iter().zip(&b) {
            let ac = ai - a_mu;
            num += ac.dot(&(bi - b_mu));
            den += ac.norm_squared();
        }
        let elements = 3.0 * n;
        (num / elements) / (den / elements).max(EXTRINSICS_ALIGNMENT_EPS)
    } else {
        1.0
    };
    if scale <= 0.0 || !scale.is_finite() {
        return Err(GeometryError::Degenerate {
            what: "extrinsics alignment",
            reason: "the estimated scale is not positive",
        });
    }
    let t_a = b_mu - scale * a_mu;
    Ok(Sim3 {
        rotation: r_a,
        translation: -(r_a * t_a),
        scale,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sim() -> Sim3 {
        Sim3 {
            rotation: crate::Quaternion::new(0.7, 0.2, -0.4, 0.5)
                .to_rotation_matrix()
                .unwrap(),
            translation: Vector3::new(1.0, -2.0, 0.5),
            scale: 2.5,
        }
    }

    #[test]
    fn inverse_and_compose() {
        let s = sim();
        let id = s.compose(&s.inverse());
        assert!((id.rotation - Matrix3::identity()).norm() < 1e-12);
        assert!(id.translation.norm() < 1e-12);
        assert!((id.scale - 1.0).abs() < 1e-12);
        let p = Point3::new(0.3, 0.2, -1.0);
        let q = s.compose(&s).transform_point(&p);
        assert!((q - s.transform_point(&s.transform_point(&p))).norm() < 1e-12);
    }

    #[test]
    fn degenerate_point_sets_are_errors() {
        let p = Point3::new(1.0, 2.0, 3.0);
        assert!(matches!(
            umeyama_with_scale(&[p, p, p], &[p, p, p]),
            Err(GeometryError::Degenerate { .. })
        ));
        let line: Vec<_> = (0..5)
            .map(|i| Point3::new(f64::from(i), 0.0, 0.0))
            .collect();
        assert!(matches!(
            umeyama(&line, &line),
            Err(GeometryError::Degenerate { .. })
        ));
        assert!(matches!(
            umeyama(&line[..2], &line[..2]),
            Err(GeometryError::TooFew { .. })
        ));
        assert!(matches!(
            umeyama(&line[..3], &line[..4]),
            Err(GeometryError::LengthMismatch { .. })
        ));
    }

    #[test]
    fn rigid_umeyama_ignores_scale() {
        let s = sim();
        let src: Vec<_> = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 2.0, 0.0],
            [0.0, 0.0, 3.0],
        ]
        .iter()
        .map(|p| Point3::new(p[0], p[1], p[2]))
        .collect();
        let rigid = Sim3 { scale: 1.0, ..s };
        let dst: Vec<_> = src.iter().map(|p| rigid.transform_point(p)).collect();
        let est = umeyama(&src, &dst).unwrap();
        assert!((est.rotation - s.rotation).norm() < 1e-12);
        assert!((est.translation - s.translation).norm() < 1e-12);
        assert_eq!(est.scale, 1.0);
    }
}
