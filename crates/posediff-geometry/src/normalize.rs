//! The official canonicalisation of ground-truth cameras (PoseDiffusion
//! `util/normalize_cameras.py`, as `Co3dDataset` calls it for training and testing).
//!
//! 1. `p*` = least-squares intersection of the optical axes: `Σ(I − d dᵀ) p = Σ(I − d dᵀ) C`.
//! 2. Move the world origin to `p*` and divide by `dist_0 = |C_0 − p*|`, the distance of
//!    **camera 0** (not a median).
//! 3. Re-express everything in camera 0's **PyTorch3D** view frame: camera 0 becomes `R = I,
//!    T = 0` as a PyTorch3D camera, i.e. `R = diag(−1, −1, 1)`, `t = 0` as an OpenCV [`Camera`].
//!    This is the frame the official training targets (pose encodings) live in.
//!
//! The three steps form one similarity transform of the world ([`Canonicalized`]), so the
//! canonicalisation can be undone ([`Canonicalized::restore`]).
//!
//! # Pitfalls
//! - The optical axis is camera +z whatever the principal point (the official code unprojects
//!   the principal point at depth 1).
//! - Parallel optical axes have no intersection; the official code would return a least-squares
//!   solution of a singular system. Here that is an error.

use nalgebra::{Matrix3, Point3, Vector3};

use crate::alignment::Sim3;
use crate::camera::{Camera, Pose};
use crate::error::{GeometryError, Result};
use crate::pytorch3d::axis_flip;

/// Smallest eigenvalue of `Σ(I − d dᵀ)`, relative to the largest, below which the optical axes
/// are taken as parallel.
const PARALLEL_AXES_TOLERANCE: f64 = 1e-12;

/// Distance of camera 0 to the intersection, relative to the largest camera distance, below
/// which camera 0 is taken to sit on the intersection (the official code only rejects exact 0
/// and would divide by rounding noise).
const MIN_RELATIVE_SCALE: f64 = 1e-9;

/// The least-squares intersection of the optical axes and each camera's distance to it.
#[derive(Debug, Clone, PartialEq)]
pub struct OpticalAxisIntersection {
    /// The point closest to all optical axes, in world coordinates.
    pub point: Point3<f64>,
    /// `|C_i − point|` for every camera.
    pub distances: Vec<f64>,
}

/// Official `compute_optical_axis_intersection`.
///
/// # Errors
/// Fewer than two cameras, non-finite poses, parallel optical axes.
pub fn optical_axis_intersection(cameras: &[Camera]) -> Result<OpticalAxisIntersection> {
    if cameras.len() < 2 {
        return Err(GeometryError::TooFew {
            what: "cameras for an optical-axis intersection",
            needed: 2,
            got: cameras.len(),
        });
    }
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for cam in cameras {
        cam.cam_from_world.ensure_finite()?;
        let d = cam.optical_axis().normalize();
        let proj = Matrix3::identity() - d * d.transpose();
        a += proj;
        b += proj * cam.center().coords;
    }
    let eig = a.symmetric_eigenvalues();
    let (lo, hi) = (eig.min(), eig.max());
    if lo <= PARALLEL_AXES_TOLERANCE * hi {
        return Err(GeometryError::Degenerate {
            what: "optical-axis intersection",
            reason: "the optical axes are parallel",
        });
    }
    let Some(p) = a.lu().solve(&b) else {
        return Err(GeometryError::Degenerate {
            what: "optical-axis intersection",
            reason: "singular system",
        });
    };
    let point = Point3::from(p);
    let distances = cameras
        .iter()
        .map(|c| (c.center() - point).norm())
        .collect();
    Ok(OpticalAxisIntersection { point, distances })
}

/// Cameras in the canonical frame and the similarity that took them there.
#[derive(Debug, Clone, PartialEq)]
pub struct Canonicalized {
    /// The cameras; camera 0 is the PyTorch3D identity (`R = diag(−1, −1, 1)`, `t = 0` here).
    pub cameras: Vec<Camera>,
    /// Maps original world points to canonical ones.
    pub canonical_from_world: Sim3,
}

impl Canonicalized {
    /// Cameras expressed in the canonical frame mapped back to the original world.
    pub fn restore(&self, cameras: &[Camera]) -> Vec<Camera> {
        let back = self.canonical_from_world.inverse();
        cameras.iter().map(|c| back.transform_camera(c)).collect()
    }
}

/// Step 3 on top of a first similarity: the PyTorch3D view frame of camera 0 after `first`.
fn with_first_camera_frame(cameras: &[Camera], first: Sim3) -> Canonicalized {
    let cam0 = first.transform_camera(&cameras[0]);
    let flip = Pose::new(axis_flip(), Vector3::zeros());
    let pytorch3d_view_from_world = flip.compose(&cam0.cam_from_world);
    let canonical_from_world = Sim3::from_pose(&pytorch3d_view_from_world).compose(&first);
    Canonicalized {
        cameras: cameras
            .iter()
            .map(|c| canonical_from_world.transform_camera(c))
            .collect(),
        canonical_from_world,
    }
}

/// Official `normalize_cameras(compute_optical=True, first_camera=True)`.
///
/// # Errors
/// As [`optical_axis_intersection`]; also camera 0 lying on the intersection (zero scale).
pub fn canonicalize(cameras: &[Camera]) -> Result<Canonicalized> {
    let hit = optical_axis_intersection(cameras)?;
    let scale = hit.distances[0];
    let largest = hit.distances.iter().copied().fold(0.0, f64::max);
    if scale <= MIN_RELATIVE_SCALE * largest {
        return Err(GeometryError::Degenerate {
            what: "canonicalisation",
            reason: "camera 0 lies on the optical-axis intersection",
        });
    }
    let to_origin = Sim3 {
        rotation: Matrix3::identity(),
        translation: -hit.point.coords,
        scale: 1.0,
    };
    let shrink = Sim3 {
        scale: 1.0 / scale,
        ..Sim3::identity()
    };
    Ok(with_first_camera_frame(cameras, shrink.compose(&to_origin)))
}

/// Official `normalize_cameras(compute_optical=False, first_camera=True)`: every translation
/// divided by `sqrt(‖T‖_F)` (the square root of the Frobenius norm of all translations, sic),
/// then the first-camera frame.
///
/// # Errors
/// No cameras, non-finite poses, all translations zero.
pub fn canonicalize_without_optical_axis(cameras: &[Camera]) -> Result<Canonicalized> {
    if cameras.is_empty() {
        return Err(GeometryError::TooFew {
            what: "cameras to canonicalise",
            needed: 1,
            got: 0,
        });
    }
    for c in cameras {
        c.cam_from_world.ensure_finite()?;
    }
    let frobenius = cameras
        .iter()
        .map(|c| c.cam_from_world.translation.norm_squared())
        .sum::<f64>()
        .sqrt();
    if frobenius == 0.0 {
        return Err(GeometryError::Degenerate {
            what: "canonicalisation",
            reason: "all translations are zero",
        });
    }
    let shrink = Sim3 {
        scale: 1.0 / frobenius.sqrt(),
        ..Sim3::identity()
    };
    Ok(with_first_camera_frame(cameras, shrink))
}

#[cfg(test)]
mod tests {
    use nalgebra::Point3;

    use super::*;
    use crate::camera::{ImageSize, Intrinsics};

    /// A camera at `center` looking at `target` (OpenCV axes, y down roughly along −world z).
    fn look_at(center: Point3<f64>, target: Point3<f64>) -> Camera {
        let z = (target - center).normalize();
        let x = z.cross(&Vector3::z()).normalize();
        let y = z.cross(&x);
        let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
        Camera::new(
            Intrinsics::new(200.0, 200.0, 100.0, 100.0).unwrap(),
            Pose::from_rotation_centre(r, center.coords),
            ImageSize::new(200, 200).unwrap(),
        )
    }

    #[test]
    fn cameras_looking_at_a_point_intersect_there() {
        let target = Point3::new(0.5, -0.2, 0.1);
        let cams: Vec<Camera> = [[4.0, 0.0, 1.0], [0.0, 3.0, 0.5], [-2.0, -2.0, 2.0]]
            .iter()
            .map(|c| look_at(Point3::new(c[0], c[1], c[2]), target))
            .collect();
        let hit = optical_axis_intersection(&cams).unwrap();
        assert!((hit.point - target).norm() < 1e-12);
        let canon = canonicalize(&cams).unwrap();
        // Camera 0 at unit distance from the intersection, which is on its +z axis.
        let c0 = &canon.cameras[0];
        assert!(c0.center().coords.norm() < 1e-12);
        let t = canon.canonical_from_world.transform_point(&target);
        assert!((t.coords.norm() - 1.0).abs() < 1e-12);
        assert!((c0.cam_from_world.transform_point(&t).coords - Vector3::z()).norm() < 1e-12);
    }

    #[test]
    fn degenerate_configurations_are_errors() {
        let target = Point3::new(0.0, 0.0, 0.0);
        let one = [look_at(Point3::new(3.0, 0.0, 0.0), target)];
        assert!(matches!(
            optical_axis_intersection(&one),
            Err(GeometryError::TooFew { .. })
        ));
        // Parallel optical axes: translated copies of one camera.
        let a = look_at(Point3::new(3.0, 0.0, 0.0), target);
        let mut b = a;
        b.cam_from_world.translation += Vector3::new(0.5, 0.0, 0.0);
        assert!(matches!(
            optical_axis_intersection(&[a, b]),
            Err(GeometryError::Degenerate { .. })
        ));
        // Camera 0 sits on the intersection of the others' axes and its own.
        let cams = [
            look_at(Point3::new(0.0, 0.0, 0.0), Point3::new(1.0, 0.0, 0.0)),
            look_at(Point3::new(0.0, 3.0, 0.0), Point3::new(0.0, 0.0, 0.0)),
            look_at(Point3::new(0.0, -3.0, 1.0), Point3::new(0.0, 0.0, 0.0)),
        ];
        assert!(matches!(
            canonicalize(&cams),
            Err(GeometryError::Degenerate { .. })
        ));
        let zero = [Camera {
            cam_from_world: Pose::identity(),
            ..a
        }];
        assert!(matches!(
            canonicalize_without_optical_axis(&zero),
            Err(GeometryError::Degenerate { .. })
        ));
    }
}
