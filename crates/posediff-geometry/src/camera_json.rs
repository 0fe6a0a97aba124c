//! The `cameras.json` record: one camera per image, OpenCV convention, pixels.
//!
//! ```json
//! {"image": "images/x.png", "width": 640, "height": 480,
//!  "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "R": [[...], [...], [...]], "t": [tx, ty, tz]}
//! ```
//!
//! `x_cam = R x_world + t`; `R` rows are stored as the inner arrays. Unknown fields are ignored
//! when reading, so files with extra metadata load.
//!
//! A lens with distortion adds COLMAP's model name and parameters in COLMAP's order
//! (`"model": "SIMPLE_RADIAL", "params": [f, cx, cy, k]`, see [`crate::lens`]); `K` then holds the
//! same focal and principal point, so a reader that knows only `K` still gets the pinhole part.
//! A record with only `K` is a PINHOLE camera.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, ImageSize, Intrinsics, Pose};
use crate::error::{GeometryError, Result, ensure_finite};
use crate::lens::{CameraModel, LensCamera};
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
    /// COLMAP camera model name (`PINHOLE`, `SIMPLE_RADIAL`, `OPENCV`, …); absent means PINHOLE
    /// with `K`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    /// The model's parameters in COLMAP's order; present exactly when `model` is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub params: Option<Vec<f64>>,
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
            model: None,
            params: None,
        }
    }

    /// The record of `camera` for `image` seen through `lens` (whose focal and principal point
    /// are written as `K` too; a lens without distortion writes only `K`).
    ///
    /// # Errors
    /// A lens whose pinhole part differs from `camera`'s intrinsics.
    pub fn from_lens_camera(
        image: impl Into<String>,
        camera: &Camera,
        lens: &LensCamera,
    ) -> Result<Self> {
        let mut record = Self::from_camera(image, camera);
        check_same_pinhole(&lens.intrinsics()?, &camera.intrinsics)?;
        if lens.is_distorted() {
            record.model = Some(lens.model().name().to_owned());
            record.params = Some(lens.params().to_vec());
        }
        Ok(record)
    }

    /// The lens this record describes: its `model` and `params`, or PINHOLE from `K`.
    ///
    /// # Errors
    /// A `model` without `params` or the other way round, an unknown model, the wrong number of
    /// parameters, or a focal/principal point that disagrees with `K`.
    pub fn lens(&self) -> Result<LensCamera> {
        let k = Intrinsics::from_matrix(&matrix(&self.k))?;
        match (&self.model, &self.params) {
            (None, None) => Ok(LensCamera::pinhole(&k)),
            (Some(name), Some(params)) => {
                let lens = LensCamera::new(CameraModel::from_name(name)?, params.clone())?;
                check_same_pinhole(&lens.intrinsics()?, &k)?;
                Ok(lens)
            }
            _ => Err(GeometryError::Degenerate {
                what: "camera record",
                reason: "`model` and `params` come together: give both or neither",
            }),
        }
    }
}

/// `K` and a lens's focal and principal point agree to a millionth of the focal (text rounding).
fn check_same_pinhole(lens: &Intrinsics, k: &Intrinsics) -> Result<()> {
    let scale = k.matrix()[(0, 0)].max(k.matrix()[(1, 1)]).max(1.0);
    let differs = (lens.matrix() - k.matrix()).abs().max() > 1e-6 * scale;
    if differs {
        return Err(GeometryError::Degenerate {
            what: "camera record",
            reason: "the model's focal or principal point disagrees with `K`",
        });
    }
    Ok(())
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

    fn record() -> CameraRecord {
        let k = Intrinsics::from_matrix(&Matrix3::new(
            500.0, 0.0, 319.5, 0.0, 500.0, 239.5, 0.0, 0.0, 1.0,
        ))
        .unwrap_or_else(|_| unreachable!());
        let size = ImageSize::new(640, 480).unwrap_or_else(|_| unreachable!());
        CameraRecord::from_camera("a.png", &Camera::new(k, Pose::identity(), size))
    }

    #[test]
    fn a_record_with_only_k_is_pinhole_and_a_distorted_lens_round_trips() {
        let plain = record();
        let lens = plain.lens().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(lens.model(), CameraModel::Pinhole);
        assert!(
            !serde_json::to_string(&plain)
                .unwrap_or_default()
                .contains("model")
        );

        let radial = LensCamera::new(CameraModel::SimpleRadial, vec![500.0, 319.5, 239.5, -0.1])
            .unwrap_or_else(|e| panic!("{e}"));
        let camera = plain.to_camera().unwrap_or_else(|e| panic!("{e}"));
        let with = CameraRecord::from_lens_camera("a.png", &camera, &radial)
            .unwrap_or_else(|e| panic!("{e}"));
        let text = serde_json::to_string(&with).unwrap_or_default();
        assert!(text.contains("\"model\":\"SIMPLE_RADIAL\""), "{text}");
        let back: CameraRecord = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(back.lens().unwrap_or_else(|e| panic!("{e}")), radial);
    }

    #[test]
    fn a_model_that_disagrees_with_k_or_lacks_params_is_an_error() {
        let mut r = record();
        r.model = Some("SIMPLE_RADIAL".into());
        assert!(r.lens().is_err(), "model without params");
        r.params = Some(vec![510.0, 319.5, 239.5, -0.1]);
        assert!(r.lens().is_err(), "focal 510 against K's 500");
        r.params = Some(vec![500.0, 319.5, 239.5]);
        assert!(r.lens().is_err(), "too few parameters");
        r.model = Some("FOV".into());
        r.params = Some(vec![500.0, 319.5, 239.5, 0.1]);
        assert!(r.lens().is_err(), "a model this crate does not know");
        r.model = Some("SIMPLE_RADIAL".into());
        r.params = Some(vec![500.0, 319.5, 239.5, -0.1]);
        assert!(r.lens().is_ok());
    }

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
