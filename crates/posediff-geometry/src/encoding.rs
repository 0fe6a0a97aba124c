//! The official 9-D pose encoding `absT_quaR_logFL` (PoseDiffusion `util/camera_transform.py`).
//!
//! Per frame: `[T_x, T_y, T_z, q_w, q_x, q_y, q_z, log f_x − 1.8, log f_y − 1.8]`, where `T` and
//! the quaternion describe a PyTorch3D camera (`X_cam = X_world · R(q) + T`) and `f` is the NDC
//! focal length. Decoding clamps the focal to `[0.1, 20]`, does not clamp `T`, does not normalise
//! `q` (the matrix formula divides by `|q|²`), and sets the principal point to the image centre.
//!
//! # Pitfalls
//! - The quaternion is w-first and describes the *row-vector* PyTorch3D rotation.
//! - The focal is in NDC of half the shorter side of the image the model saw (the 224 crop).
//! - Encoding is not the exact inverse of decoding: it returns a unit quaternion of a fixed sign
//!   and clamps the focal.

use nalgebra::{Vector2, Vector3};

use crate::camera::{Camera, ImageSize};
use crate::error::{Result, ensure_finite};
use crate::pytorch3d::{NdcIntrinsics, Pytorch3dCamera};
use crate::quaternion::{Quaternion, QuaternionSign};

/// Number of values per frame.
pub const POSE_ENCODING_DIM: usize = 9;
/// `log_focal_length_bias` of `pose_encoding_to_camera` / `camera_to_pose_encoding`.
pub const LOG_FOCAL_BIAS: f64 = 1.8;
/// `min_focal_length` of the official decode (NDC).
pub const FOCAL_MIN_NDC: f64 = 0.1;
/// `max_focal_length` of the official decode (NDC).
pub const FOCAL_MAX_NDC: f64 = 20.0;

/// One frame's `absT_quaR_logFL` encoding.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseEncoding(pub [f64; POSE_ENCODING_DIM]);

impl PoseEncoding {
    /// `T`, entries 0..3.
    pub fn translation(&self) -> Vector3<f64> {
        Vector3::new(self.0[0], self.0[1], self.0[2])
    }

    /// The (not necessarily unit) quaternion, entries 3..7, w first.
    pub fn quaternion(&self) -> Quaternion {
        Quaternion::new(self.0[3], self.0[4], self.0[5], self.0[6])
    }

    /// The NDC focal lengths `clamp(exp(x + 1.8), 0.1, 20)`, entries 7..9.
    pub fn focal_ndc(&self) -> Vector2<f64> {
        let f = |x: f64| {
            (x + LOG_FOCAL_BIAS)
                .exp()
                .clamp(FOCAL_MIN_NDC, FOCAL_MAX_NDC)
        };
        Vector2::new(f(self.0[7]), f(self.0[8]))
    }

    /// Official `pose_encoding_to_camera`.
    ///
    /// # Errors
    /// Non-finite entries or a zero quaternion.
    pub fn decode(&self) -> Result<Pytorch3dCamera> {
        ensure_finite("pose encoding", &self.0)?;
        Ok(Pytorch3dCamera {
            r: self.quaternion().to_rotation_matrix()?,
            t: self.translation(),
            intrinsics: NdcIntrinsics {
                focal: self.focal_ndc(),
                principal_point: Vector2::zeros(),
            },
        })
    }

    /// Decodes to an OpenCV camera for an image of `size` (the official pipeline uses the
    /// 224×224 crop).
    ///
    /// # Errors
    /// As [`Self::decode`].
    pub fn to_camera(&self, size: ImageSize) -> Result<Camera> {
        self.decode()?.to_opencv(size)
    }

    /// Official `camera_to_pose_encoding`: `[T, matrix_to_quaternion(R), log(clamp(f)) − 1.8]`.
    /// The principal point is not encoded.
    ///
    /// # Errors
    /// Non-finite values.
    pub fn encode(camera: &Pytorch3dCamera, sign: QuaternionSign) -> Result<Self> {
        ensure_finite("camera translation", camera.t.iter())?;
        ensure_finite("camera focal length", camera.intrinsics.focal.iter())?;
        let q = Quaternion::from_rotation_matrix(&camera.r, sign)?;
        let log_f = |f: f64| f.clamp(FOCAL_MIN_NDC, FOCAL_MAX_NDC).ln() - LOG_FOCAL_BIAS;
        let [w, x, y, z] = q.to_wxyz();
        Ok(Self([
            camera.t.x,
            camera.t.y,
            camera.t.z,
            w,
            x,
            y,
            z,
            log_f(camera.intrinsics.focal.x),
            log_f(camera.intrinsics.focal.y),
        ]))
    }

    /// [`Self::encode`] of an OpenCV camera (through [`Pytorch3dCamera::from_opencv`]).
    ///
    /// # Errors
    /// As [`Self::encode`].
    pub fn from_camera(camera: &Camera, sign: QuaternionSign) -> Result<Self> {
        Self::encode(&Pytorch3dCamera::from_opencv(camera), sign)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn focal_is_clamped_both_ways() {
        let mut e = PoseEncoding([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 5.0, -9.0]);
        assert_eq!(e.focal_ndc(), Vector2::new(FOCAL_MAX_NDC, FOCAL_MIN_NDC));
        e.0[7] = 0.0;
        assert!((e.focal_ndc().x - LOG_FOCAL_BIAS.exp()).abs() < 1e-12);
    }

    #[test]
    fn zero_quaternion_and_nan_are_errors() {
        let e = PoseEncoding([0.0; 9]);
        assert!(e.decode().is_err());
        let mut e = PoseEncoding([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert!(e.decode().is_ok());
        e.0[1] = f64::NAN;
        assert!(e.decode().is_err());
    }
}
