//! The public camera type, in the OpenCV convention.
//!
//! A world point `X` maps to camera coordinates `x_cam = R X + t` ([`Pose`], "cam from world"),
//! camera axes +x right, +y down, +z forward, and to pixels `u = K x_cam / z` with
//! `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]` ([`Intrinsics`]). Pixel coordinates are OpenCV's:
//! the centre of the top-left pixel is `(0, 0)`.
//!
//! # Pitfalls
//! - `R` maps world to camera; the camera centre is `−Rᵀ t`, not `t`.
//! - PyTorch3D cameras use row vectors and NDC units; convert only through
//!   [`crate::pytorch3d`].
//! - PyTorch3D's conversion puts a zero NDC principal point at `(W/2, H/2)`, half a pixel right
//!   of and below the geometric centre `((W−1)/2, (H−1)/2)` of OpenCV pixel centres. The official
//!   code does this and so do we; keypoint mappings must use the same convention.

use nalgebra::{Matrix3, Matrix3x4, Point2, Point3, Vector3};

use crate::error::{GeometryError, Result, ensure_finite};

/// Width and height of an image in pixels; both positive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ImageSize {
    width: u32,
    height: u32,
}

impl ImageSize {
    /// # Errors
    /// [`GeometryError::InvalidImageSize`] if a side is zero.
    pub const fn new(width: u32, height: u32) -> Result<Self> {
        if width == 0 || height == 0 {
            Err(GeometryError::InvalidImageSize { width, height })
        } else {
            Ok(Self { width, height })
        }
    }

    /// Width in pixels.
    pub const fn width(self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub const fn height(self) -> u32 {
        self.height
    }

    /// `min(width, height)`.
    pub const fn min_side(self) -> u32 {
        if self.width < self.height {
            self.width
        } else {
            self.height
        }
    }
}

/// Pinhole intrinsics in pixels, zero skew; focal lengths positive and everything finite.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

impl Intrinsics {
    /// # Errors
    /// [`GeometryError::InvalidIntrinsics`] unless `fx, fy > 0` and all four are finite.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Result<Self> {
        if ![fx, fy, cx, cy].iter().all(|v| v.is_finite()) {
            return Err(GeometryError::InvalidIntrinsics {
                reason: "values must be finite",
            });
        }
        if fx <= 0.0 || fy <= 0.0 {
            return Err(GeometryError::InvalidIntrinsics {
                reason: "focal lengths must be positive",
            });
        }
        Ok(Self { fx, fy, cx, cy })
    }

    /// Reads `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`.
    ///
    /// # Errors
    /// [`GeometryError::InvalidIntrinsics`] for skew, a last row other than `[0, 0, 1]`, or
    /// invalid values.
    pub fn from_matrix(k: &Matrix3<f64>) -> Result<Self> {
        if k[(0, 1)] != 0.0 || k[(1, 0)] != 0.0 {
            return Err(GeometryError::InvalidIntrinsics {
                reason: "skew is not supported",
            });
        }
        if k[(2, 0)] != 0.0 || k[(2, 1)] != 0.0 || k[(2, 2)] != 1.0 {
            return Err(GeometryError::InvalidIntrinsics {
                reason: "last row must be [0, 0, 1]",
            });
        }
        Self::new(k[(0, 0)], k[(1, 1)], k[(0, 2)], k[(1, 2)])
    }

    /// Focal length along x in pixels.
    pub const fn fx(&self) -> f64 {
        self.fx
    }
    /// Focal length along y in pixels.
    pub const fn fy(&self) -> f64 {
        self.fy
    }
    /// Principal point x in pixels.
    pub const fn cx(&self) -> f64 {
        self.cx
    }
    /// Principal point y in pixels.
    pub const fn cy(&self) -> f64 {
        self.cy
    }

    /// The matrix `K`.
    pub fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// `K⁻¹`, in closed form.
    pub fn inverse_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(
            1.0 / self.fx,
            0.0,
            -self.cx / self.fx,
            0.0,
            1.0 / self.fy,
            -self.cy / self.fy,
            0.0,
            0.0,
            1.0,
        )
    }
}

/// A rigid transform `y = R x + t` from a source frame to a target frame. As a camera's
/// extrinsics it is "cam from world".
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation `R` (target from source).
    pub rotation: Matrix3<f64>,
    /// Translation `t`, in target coordinates.
    pub translation: Vector3<f64>,
}

impl Pose {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// The pose of a camera with world-to-camera rotation `R` whose centre is `C` in the
    /// world: `t = −R C`.
    pub fn from_rotation_centre(rotation: Matrix3<f64>, centre: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation: -(rotation * centre),
        }
    }

    /// Builds a pose from `R` and `t`.
    pub const fn new(rotation: Matrix3<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    /// The inverse transform `x = Rᵀ y − Rᵀ t` (valid for a rotation `R`).
    pub fn inverse(&self) -> Self {
        let rt = self.rotation.transpose();
        Self::new(rt, -(rt * self.translation))
    }

    /// `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &Self) -> Self {
        Self::new(
            self.rotation * other.rotation,
            self.rotation * other.translation + self.translation,
        )
    }

    /// Applies the transform to a point.
    pub fn transform_point(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.rotation * p.coords + self.translation)
    }

    /// Checks that all entries are finite.
    ///
    /// # Errors
    /// [`GeometryError::NonFinite`].
    pub fn ensure_finite(&self) -> Result<()> {
        ensure_finite("pose", self.rotation.iter().chain(self.translation.iter()))
    }
}

/// A pinhole camera in the OpenCV convention: intrinsics in pixels, extrinsics cam-from-world,
/// and the size of the image the intrinsics refer to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Intrinsics in pixels of an image of size `image_size`.
    pub intrinsics: Intrinsics,
    /// Extrinsics: `x_cam = R x_world + t`.
    pub cam_from_world: Pose,
    /// The image the intrinsics refer to.
    pub image_size: ImageSize,
}

impl Camera {
    /// Builds a camera.
    pub const fn new(intrinsics: Intrinsics, cam_from_world: Pose, image_size: ImageSize) -> Self {
        Self {
            intrinsics,
            cam_from_world,
            image_size,
        }
    }

    /// The camera centre in world coordinates, `C = −Rᵀ t`.
    pub fn center(&self) -> Point3<f64> {
        Point3::from(self.cam_from_world.inverse().translation)
    }

    /// The optical axis (camera +z) in world coordinates: the third row of `R`.
    pub fn optical_axis(&self) -> Vector3<f64> {
        self.cam_from_world.rotation.row(2).transpose()
    }

    /// The 3×4 projection matrix `K [R | t]`.
    pub fn projection_matrix(&self) -> Matrix3x4<f64> {
        let mut rt = Matrix3x4::zeros();
        rt.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&self.cam_from_world.rotation);
        rt.set_column(3, &self.cam_from_world.translation);
        self.intrinsics.matrix() * rt
    }

    /// Projects a world point to pixels; `None` when the point is not in front of the camera
    /// (`z ≤ 0`).
    pub fn project(&self, x_world: &Point3<f64>) -> Option<Point2<f64>> {
        let x = self.cam_from_world.transform_point(x_world);
        if x.z <= 0.0 {
            return None;
        }
        let k = &self.intrinsics;
        Some(Point2::new(
            k.fx * x.x / x.z + k.cx,
            k.fy * x.y / x.z + k.cy,
        ))
    }

    /// The world point at depth `depth` (along the optical axis, camera z) seen at `pixel`.
    pub fn unproject(&self, pixel: &Point2<f64>, depth: f64) -> Point3<f64> {
        let k = &self.intrinsics;
        let x_cam = Point3::new(
            (pixel.x - k.cx) / k.fx * depth,
            (pixel.y - k.cy) / k.fy * depth,
            depth,
        );
        self.cam_from_world.inverse().transform_point(&x_cam)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pose_from_rotation_and_centre_has_that_centre() {
        let r = crate::Quaternion::new(0.9, 0.1, -0.3, 0.2)
            .to_rotation_matrix()
            .unwrap_or_else(|_| Matrix3::identity());
        let c = Vector3::new(1.5, -2.0, 0.25);
        let pose = Pose::from_rotation_centre(r, c);
        let cam = Camera::new(
            Intrinsics::new(500.0, 500.0, 320.0, 240.0).unwrap_or_else(|_| unreachable!()),
            pose,
            ImageSize::new(640, 480).unwrap_or_else(|_| unreachable!()),
        );
        assert!((cam.center().coords - c).norm() < 1e-12);
        assert_eq!(pose.rotation, r);
    }

    fn camera() -> Camera {
        let r = crate::Quaternion::new(0.9, 0.1, -0.3, 0.2)
            .to_rotation_matrix()
            .unwrap();
        Camera::new(
            Intrinsics::new(500.0, 520.0, 320.0, 240.0).unwrap(),
            Pose::new(r, Vector3::new(0.1, -0.2, 3.0)),
            ImageSize::new(640, 480).unwrap(),
        )
    }

    #[test]
    fn invalid_sizes_and_intrinsics_are_errors() {
        assert!(ImageSize::new(0, 10).is_err());
        assert!(Intrinsics::new(0.0, 1.0, 0.0, 0.0).is_err());
        assert!(Intrinsics::new(1.0, f64::INFINITY, 0.0, 0.0).is_err());
        let mut k = Matrix3::new(1.0, 0.5, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert!(Intrinsics::from_matrix(&k).is_err());
        k[(0, 1)] = 0.0;
        assert!(Intrinsics::from_matrix(&k).is_ok());
    }

    #[test]
    fn centre_projects_nowhere_and_unproject_inverts_project() {
        let cam = camera();
        let c = cam.center();
        assert!(cam.cam_from_world.transform_point(&c).coords.norm() < 1e-12);
        assert_eq!(cam.project(&c), None);
        let px = Point2::new(100.0, 400.0);
        let x = cam.unproject(&px, 2.5);
        let back = cam.project(&x).unwrap();
        assert!((back - px).norm() < 1e-10);
        // The optical axis leads from the centre to the principal point.
        let on_axis = c + cam.optical_axis() * 4.0;
        let pp = cam.project(&on_axis).unwrap();
        assert!((pp - Point2::new(320.0, 240.0)).norm() < 1e-10);
    }

    #[test]
    fn projection_matrix_agrees_with_project() {
        let cam = camera();
        let x = Point3::new(0.3, 0.1, 0.5);
        let h = cam.projection_matrix() * x.to_homogeneous();
        let px = cam.project(&x).unwrap();
        assert!((Point2::new(h.x / h.z, h.y / h.z) - px).norm() < 1e-10);
        assert!(
            (cam.intrinsics.matrix() * cam.intrinsics.inverse_matrix() - Matrix3::identity())
                .norm()
                < 1e-15
        );
    }

    #[test]
    fn pose_inverse_and_compose() {
        let p = camera().cam_from_world;
        let id = p.compose(&p.inverse());
        assert!((id.rotation - Matrix3::identity()).norm() < 1e-14);
        assert!(id.translation.norm() < 1e-14);
    }
}
