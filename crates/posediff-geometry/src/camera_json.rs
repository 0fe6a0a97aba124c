//! The `cameras.json` record: one camera per image, OpenCV convention, pixels.
//!
//! ```json
//! {"image": "images/x.png", "width": 640, "height": 480,
//!  "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "R": [[...], [...], [...]], "t": [tx, ty, tz]}
//! ```
//!
//! `x_cam = R x_world + t`; `R` rows are stored as the inner arrays. Unknown fields are ignored
//! when reading, so files with extra metadata load.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, ImageSize, Intrinsics, Pose};
use crate::error::{GeometryError, Result, ensure_finite};
use crate::pytorch3d::{NdcIntrinsics, Pytorch3dCamera};

/// Rows of a 3×3 matrix.
pub type Rows3 = [[f64; 3]; 3];

/// One entry of a `cameras.json` list.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraRecord {
    /// Image path, relative to the folder the file describes.
    pub image: String,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Intrinsics matrix in pixels, rows.
    #[serde(rename = "K")]
    pub k: Rows3,
    /// Rotation world → camera, rows.
    #[serde(rename = "R")]
    pub r: Rows3,
    /// Translation world → camera.
    pub t: [f64; 3],
}

fn matrix(rows: &Rows3) -> Matrix3<f64> {
    Matrix3::from_fn(|i, j| rows[i][j])
}

fn rows(m: &Matrix3<f64>) -> Rows3 {
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| m[(i, j)]))
}

/// Rotations stored in text files carry ~1e-9 of rounding; anything further from orthonormal is
/// not a rotation.
const ROTATION_TOLERANCE: f64 = 1e-5;

impl CameraRecord {
    /// The camera this record describes.
    ///
    /// # Errors
    /// A zero image side, invalid `K`, non-finite values, or an `R` that is not a rotation.
    pub fn to_camera(&self) -> Result<Camera> {
        let size = ImageSize::new(self.width, self.height)?;
        let k = Intrinsics::from_matrix(&matrix(&self.k))?;
        let r = matrix(&self.r);
        ensure_finite("camera record R/t", r.iter().chain(&self.t))?;
        if (r.transpose() * r - Matrix3::identity()).norm() > ROTATION_TOLERANCE
            || (r.determinant() - 1.0).abs() > ROTATION_TOLERANCE
        {
            return Err(GeometryError::Degenerate {
                what: "camera record",
                reason: "R is not a rotation matrix",
            });
        }
        Ok(Camera::new(k, Pose::new(r, Vector3::from(self.t)), size))
    }

    /// The record of `camera` for `image`.
    pub fn from_camera(image: impl Into<String>, camera: &Camera) -> Self {
        let t = camera.cam_from_world.translation;
        Self {
            image: image.into(),
            width: camera.image_size.width(),
            height: camera.image_size.height(),
            k: rows(&camera.intrinsics.matrix()),
            r: rows(&camera.cam_from_world.rotation),
            t: [t.x, t.y, t.z],
        }
    }
}

/// A PyTorch3D `PerspectiveCameras` entry as JSON records hold it (CO3D annotations,
/// `pytorch3d.json`): row-vector `R` (`X_cam = X_world · R + T`), `T`, and the NDC
/// `focal_length` and `principal_point`. Records embed it with `#[serde(flatten)]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pytorch3dParams {
    /// Row-vector rotation, rows.
    #[serde(rename = "R")]
    pub r: Rows3,
    /// Translation.
    #[serde(rename = "T")]
    pub t: [f64; 3],
    /// Focal length, NDC.
    pub focal_length: [f64; 2],
    /// Principal point, NDC.
    pub principal_point: [f64; 2],
}

impl From<&Pytorch3dCamera> for Pytorch3dParams {
    fn from(p: &Pytorch3dCamera) -> Self {
        Self {
            r: rows(&p.r),
            t: [p.t.x, p.t.y, p.t.z],
            focal_length: [p.intrinsics.focal.x, p.intrinsics.focal.y],
            principal_point: [
                p.intrinsics.principal_point.x,
                p.intrinsics.principal_point.y,
            ],
        }
    }
}

impl Pytorch3dParams {
    /// The camera.
    pub fn camera(&self) -> Pytorch3dCamera {
        Pytorch3dCamera {
            r: matrix(&self.r),
            t: Vector3::from(self.t),
            intrinsics: NdcIntrinsics {
                focal: nalgebra::Vector2::from(self.focal_length),
                principal_point: nalgebra::Vector2::from(self.principal_point),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pytorch3d_params_keep_the_camera_and_the_official_keys() {
        let p = Pytorch3dCamera {
            r: crate::Quaternion::new(0.4, -0.3, 0.8, 0.1)
                .to_rotation_matrix()
                .unwrap_or_else(|_| Matrix3::identity()),
            t: Vector3::new(0.3, -0.4, 5.0),
            intrinsics: NdcIntrinsics {
                focal: nalgebra::Vector2::new(2.0, 2.2),
                principal_point: nalgebra::Vector2::new(0.1, -0.05),
            },
        };
        let params = Pytorch3dParams::from(&p);
        assert_eq!(params.camera(), p);
        // Rows are rows: R[0][1] is the matrix's (0, 1).
        assert_eq!(params.r[0][1], p.r[(0, 1)]);
        let json = serde_json::to_string(&params).unwrap_or_default();
        assert!(
            json.starts_with(r#"{"R":[["#) && json.contains(r#""T":[0.3,-0.4,5.0]"#),
            "{json}"
        );
        assert!(json.contains(r#""focal_length":[2.0,2.2]"#), "{json}");
    }
}
