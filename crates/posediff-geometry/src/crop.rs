//! The official demo/test image crop: the centre square of side `m = min(W, H)`,
//! `left = (W − m) / 2`, `top = (H − m) / 2` (integer division), resized to `target` (224) px
//! (SPEC.md §7.1).
//!
//! Keypoints. The official code maps COLMAP keypoints (pixel centres at `+0.5`) with
//! `(kp − 0.5 − [left, top]) · target / m`. An OpenCV keypoint `x` (pixel centres at integers)
//! is `kp − 0.5`, so the same mapping reads `(x − left) · r`, `r = target / m`: pixel indices of
//! the original crop scaled from the crop's corner. [`CenterCrop::to_model`] is exactly that
//! (what the official GGS saw); [`CenterCrop::from_model`] is its inverse.
//!
//! # Pitfalls
//! - Using the COLMAP formula on OpenCV keypoints shifts every match by half a source pixel.
//! - The "geometrically exact" resize mapping `(x + 0.5 − left)·r − 0.5` differs from the official
//!   one by `0.5 (r − 1)` px; we keep the official one so that official checkpoints see what they
//!   were tuned with.

use crate::camera::{Camera, ImageSize, Intrinsics};
use crate::error::Result;

/// The official model input side.
pub const MODEL_INPUT_SIDE: u32 = 224;

/// A centre-square crop resized to a square model input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CenterCrop {
    /// Left edge of the square in the original image.
    pub left: u32,
    /// Top edge of the square in the original image.
    pub top: u32,
    /// Side of the square in original pixels, `min(W, H)`.
    pub side: u32,
    /// Side of the resized square (224 officially).
    pub target: u32,
}

impl CenterCrop {
    /// The official crop of an image of `size` to a `target`-px square.
    pub fn official(size: ImageSize, target: u32) -> Self {
        let side = size.min_side();
        Self {
            left: (size.width() - side) / 2,
            top: (size.height() - side) / 2,
            side,
            target,
        }
    }

    /// `target / side`.
    pub fn scale(&self) -> f64 {
        f64::from(self.target) / f64::from(self.side)
    }

    /// The crop box `[left, top, left + side, top + side]`.
    pub fn bbox_xyxy(&self) -> [u32; 4] {
        [
            self.left,
            self.top,
            self.left + self.side,
            self.top + self.side,
        ]
    }

    /// An OpenCV keypoint of the original image in the model's input frame (official mapping).
    pub fn to_model(&self, kp: [f64; 2]) -> [f64; 2] {
        let r = self.scale();
        [
            (kp[0] - f64::from(self.left)) * r,
            (kp[1] - f64::from(self.top)) * r,
        ]
    }

    /// The inverse of [`Self::to_model`].
    pub fn from_model(&self, kp: [f64; 2]) -> [f64; 2] {
        let r = self.scale();
        [
            kp[0] / r + f64::from(self.left),
            kp[1] / r + f64::from(self.top),
        ]
    }
}

impl CenterCrop {
    /// A camera of the model's input frame as a camera of the original image, consistent with
    /// [`Self::from_model`]: `f ↦ f/r`, `c ↦ c/r + (left, top)` (a principal point at the
    /// model frame's centre lands on the crop centre).
    ///
    /// # Errors
    /// Invalid intrinsics.
    pub fn camera_from_model(&self, camera: &Camera, original: ImageSize) -> Result<Camera> {
        let k = &camera.intrinsics;
        let r = self.scale();
        let c = self.from_model([k.cx(), k.cy()]);
        Ok(Camera::new(
            Intrinsics::new(k.fx() / r, k.fy() / r, c[0], c[1])?,
            camera.cam_from_world,
            original,
        ))
    }

    /// An original-image camera as a camera of the model's input frame (the inverse of
    /// [`Self::camera_from_model`]).
    ///
    /// # Errors
    /// A zero target size, invalid intrinsics.
    pub fn camera_to_model(&self, camera: &Camera) -> Result<Camera> {
        let k = &camera.intrinsics;
        let r = self.scale();
        let c = self.to_model([k.cx(), k.cy()]);
        Ok(Camera::new(
            Intrinsics::new(k.fx() * r, k.fy() * r, c[0], c[1])?,
            camera.cam_from_world,
            ImageSize::new(self.target, self.target)?,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn portrait_and_landscape_crops() {
        let c = CenterCrop::official(ImageSize::new(251, 410).unwrap(), 224);
        assert_eq!(c.bbox_xyxy(), [0, 79, 251, 330]);
        let c = CenterCrop::official(ImageSize::new(400, 300).unwrap(), 224);
        assert_eq!(c.bbox_xyxy(), [50, 0, 350, 300]);
        let kp = [123.25, 47.5];
        let back = c.from_model(c.to_model(kp));
        assert!((back[0] - kp[0]).abs() < 1e-12 && (back[1] - kp[1]).abs() < 1e-12);
        // The crop's corner pixel maps to the model frame's origin.
        assert_eq!(c.to_model([50.0, 0.0]), [0.0, 0.0]);
    }

    #[test]
    fn cameras_map_like_keypoints() {
        use nalgebra::{Point3, Vector3};

        use crate::camera::Pose;
        let size = ImageSize::new(400, 300).unwrap();
        let c = CenterCrop::official(size, 224);
        let model = Camera::new(
            Intrinsics::new(250.0, 260.0, 112.0, 112.0).unwrap(),
            Pose::new(nalgebra::Matrix3::identity(), Vector3::new(0.1, -0.2, 3.0)),
            ImageSize::new(224, 224).unwrap(),
        );
        let original = c.camera_from_model(&model, size).unwrap();
        // The model frame's centre is the crop's centre.
        assert_eq!(
            (original.intrinsics.cx(), original.intrinsics.cy()),
            (200.0, 150.0)
        );
        // Projections agree through the keypoint mapping.
        let x = Point3::new(0.3, 0.2, 1.0);
        let (a, b) = (model.project(&x).unwrap(), original.project(&x).unwrap());
        let mapped = c.from_model([a.x, a.y]);
        assert!((mapped[0] - b.x).abs() < 1e-12 && (mapped[1] - b.y).abs() < 1e-12);
        let back = c.camera_to_model(&original).unwrap();
        assert!((back.intrinsics.matrix() - model.intrinsics.matrix()).norm() < 1e-12);
    }
}
