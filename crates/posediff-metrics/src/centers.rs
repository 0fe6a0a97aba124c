//! Metrics after aligning the predicted cameras to the ground truth.
//!
//! - [`camera_center_accuracy`]: RelPose++'s camera-centre accuracy. The predicted centres are
//!   aligned to the ground-truth centres by the least-squares similarity (Umeyama); a camera is
//!   correct when its aligned centre is within `threshold × scene scale` of the truth, the scene
//!   scale being the distance from the centroid of the ground-truth centres to the furthest one.
//!   Cameras the method did not estimate count as wrong.
//! - [`absolute_rotation_errors_deg`]: the official demo's `compute_ARE` after PyTorch3D's
//!   `corresponding_cameras_alignment(mode="extrinsics")`.

use nalgebra::{Point3, Vector3};
use posediff_geometry::{Camera, GeometryError, align_cameras_by_extrinsics, umeyama_with_scale};

use crate::error::{MetricsError, Result};

/// RelPose++'s threshold: 10 % of the scene scale.
pub const RELPOSE_CENTER_THRESHOLD: f64 = 0.1;

fn centroid(points: &[Point3<f64>]) -> Vector3<f64> {
    points.iter().map(|p| p.coords).sum::<Vector3<f64>>() / points.len() as f64
}

/// The least-squares similarity image of `src` on `dst`, also where the similarity is not
/// unique: one point maps onto its target, two points onto theirs, and collinear points along
/// the best direction (the residual does not depend on the free rotation about the line).
fn aligned_points(src: &[Point3<f64>], dst: &[Point3<f64>]) -> Result<Vec<Point3<f64>>> {
    if src.len() <= 2 {
        return Ok(dst.to_vec());
    }
    match umeyama_with_scale(src, dst) {
        Ok(sim) => Ok(src.iter().map(|p| sim.transform_point(p)).collect()),
        Err(GeometryError::Degenerate { .. }) => {
            // Collinear (or coincident) source points: X_i = mu + a_i u. The optimum is
            // dst_mu + a_i m / Σa², m = Σ a_i (y_i − dst_mu), whatever the rotation about u.
            let mu = centroid(src);
            let mu_dst = centroid(dst);
            let spread = src
                .iter()
                .map(|p| p.coords - mu)
                .max_by(|a, b| a.norm_squared().total_cmp(&b.norm_squared()))
                .unwrap_or_else(Vector3::zeros);
            if spread.norm() == 0.0 {
                return Ok(vec![Point3::from(mu_dst); src.len()]);
            }
            let u = spread.normalize();
            let a: Vec<f64> = src.iter().map(|p| (p.coords - mu).dot(&u)).collect();
            let a2: f64 = a.iter().map(|v| v * v).sum();
            let m: Vector3<f64> = a
                .iter()
                .zip(dst)
                .map(|(ai, y)| *ai * (y.coords - mu_dst))
                .sum();
            Ok(a.iter()
                .map(|ai| Point3::from(mu_dst + m * (*ai / a2)))
                .collect())
        }
        Err(e) => Err(e.into()),
    }
}

/// RelPose++ camera-centre accuracy: the fraction of cameras whose centre, after the
/// similarity alignment of all estimated centres, lies within `threshold × scene scale` of the
/// ground truth (strictly). `None` marks a camera the method did not estimate (a failure).
///
/// # Errors
/// Different lengths, fewer than two ground-truth cameras, coincident ground-truth centres
/// (no scene scale), non-finite centres.
pub fn camera_center_accuracy(
    gt: &[Camera],
    pred: &[Option<Camera>],
    threshold: f64,
) -> Result<f64> {
    if gt.len() != pred.len() {
        return Err(MetricsError::LengthMismatch {
            what: "camera centre accuracy",
            predicted: pred.len(),
            ground_truth: gt.len(),
        });
    }
    if gt.len() < 2 {
        return Err(MetricsError::TooFew {
            what: "cameras for camera centre accuracy",
            needed: 2,
            got: gt.len(),
        });
    }
    let gt_centers: Vec<Point3<f64>> = gt.iter().map(Camera::center).collect();
    if !gt_centers
        .iter()
        .flat_map(|p| p.iter())
        .all(|v| v.is_finite())
    {
        return Err(MetricsError::NonFinite {
            what: "ground-truth camera centre",
        });
    }
    let mid = centroid(&gt_centers);
    let scene_scale = gt_centers
        .iter()
        .map(|c| (c.coords - mid).norm())
        .fold(0.0, f64::max);
    if scene_scale == 0.0 {
        return Err(MetricsError::Geometry(GeometryError::Degenerate {
            what: "camera centre accuracy",
            reason: "all ground-truth centres coincide",
        }));
    }
    let (src, dst): (Vec<Point3<f64>>, Vec<Point3<f64>>) = pred
        .iter()
        .zip(&gt_centers)
        .filter_map(|(p, g)| p.map(|p| (p.center(), *g)))
        .unzip();
    let aligned = aligned_points(&src, &dst)?;
    let correct = aligned
        .iter()
        .zip(&dst)
        .filter(|(a, g)| (*a - *g).norm() < threshold * scene_scale)
        .count();
    Ok(correct as f64 / gt.len() as f64)
}

/// The official demo's absolute rotation errors: `pred` aligned to `gt` by PyTorch3D's
/// extrinsics alignment, then per camera `acos(clip((tr(R_gtᵀ R) − 1)/2))` in degrees, folded as
/// `min(e, |180 − e|)`.
///
/// # Errors
/// As [`posediff_geometry::align_cameras_by_extrinsics`].
pub fn absolute_rotation_errors_deg(gt: &[Camera], pred: &[Camera]) -> Result<Vec<f64>> {
    let sim = align_cameras_by_extrinsics(pred, gt)?;
    Ok(gt
        .iter()
        .zip(pred)
        .map(|(g, p)| {
            let aligned = sim.transform_camera(p);
            let r = g.cam_from_world.rotation.transpose() * aligned.cam_from_world.rotation;
            let e = ((r.trace() - 1.0) / 2.0)
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees();
            e.min((180.0 - e).abs())
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use nalgebra::Matrix3;
    use posediff_geometry::{ImageSize, Intrinsics, Pose, Quaternion, Sim3};

    use super::*;

    fn camera_at(center: Vector3<f64>) -> Camera {
        // Identity rotation: t = −C.
        Camera::new(
            Intrinsics::new(100.0, 100.0, 50.0, 50.0).unwrap(),
            Pose::new(Matrix3::identity(), -center),
            ImageSize::new(100, 100).unwrap(),
        )
    }

    fn ring() -> Vec<Camera> {
        (0..6)
            .map(|i| {
                let a = f64::from(i) * 1.1;
                camera_at(Vector3::new(a.cos(), a.sin(), 0.3 * f64::from(i % 2)))
            })
            .collect()
    }

    fn similarity() -> Sim3 {
        Sim3 {
            rotation: Quaternion::new(0.6, 0.3, -0.2, 0.7)
                .to_rotation_matrix()
                .unwrap(),
            translation: Vector3::new(3.0, -1.0, 2.0),
            scale: 0.37,
        }
    }

    #[test]
    fn a_similar_prediction_is_fully_accurate_and_an_outlier_is_not() {
        let gt = ring();
        let sim = similarity();
        let mut pred: Vec<Option<Camera>> =
            gt.iter().map(|c| Some(sim.transform_camera(c))).collect();
        let acc = camera_center_accuracy(&gt, &pred, RELPOSE_CENTER_THRESHOLD).unwrap();
        assert!((acc - 1.0).abs() < 1e-12);
        // Move one predicted centre far away (in the prediction's frame) and drop another.
        let far = sim.transform_point(&Point3::new(0.0, 0.0, 5.0));
        pred[2] = Some(camera_at(far.coords));
        pred[4] = None;
        let acc = camera_center_accuracy(&gt, &pred, RELPOSE_CENTER_THRESHOLD).unwrap();
        assert!(acc <= 4.0 / 6.0 + 1e-12, "{acc}");
        assert!(acc < 1.0);
    }

    #[test]
    fn collinear_centres_still_align() {
        let gt: Vec<Camera> = (0..5)
            .map(|i| camera_at(Vector3::new(0.0, 0.0, f64::from(i))))
            .collect();
        let sim = similarity();
        let pred: Vec<Option<Camera>> = gt.iter().map(|c| Some(sim.transform_camera(c))).collect();
        let acc = camera_center_accuracy(&gt, &pred, 0.01).unwrap();
        assert!((acc - 1.0).abs() < 1e-12);
    }

    #[test]
    fn invalid_inputs_are_errors() {
        let gt = ring();
        assert!(camera_center_accuracy(&gt, &[None], 0.1).is_err());
        let same = vec![camera_at(Vector3::zeros()); 3];
        assert!(camera_center_accuracy(&same, &[None, None, None], 0.1).is_err());
        let none: Vec<Option<Camera>> = vec![None; gt.len()];
        assert_eq!(camera_center_accuracy(&gt, &none, 0.1).unwrap(), 0.0);
    }

    #[test]
    fn absolute_rotation_error_of_a_similar_prediction_is_zero() {
        let gt = ring();
        let sim = similarity();
        let pred: Vec<Camera> = gt.iter().map(|c| sim.transform_camera(c)).collect();
        for e in absolute_rotation_errors_deg(&gt, &pred).unwrap() {
            assert!(e < 1e-5, "{e}");
        }
    }
}
