//! The one place where PyTorch3D cameras meet OpenCV cameras.
//!
//! PyTorch3D (`PerspectiveCameras`, as the official PoseDiffusion code uses them):
//! - row vectors: `X_cam = X_world · R + T`, so the 4×4 world-to-view matrix is `[[R, 0], [T, 1]]`;
//! - camera axes +X left, +Y up, +Z forward;
//! - focal length and principal point in NDC units of half the **shorter** image side `s`:
//!   `f_px = f_ndc · s`, `p_px = (W/2, H/2) − p_ndc · s`.
//!
//! `opencv_from_cameras_projection` (PyTorch3D) is then exactly
//! `R_cv = (R with columns 0 and 1 negated)ᵀ`, `t_cv = T with components 0 and 1 negated`,
//! `K = [[fx·s, 0, W/2 − px·s], [0, fy·s, H/2 − py·s], [0, 0, 1]]`.
//!
//! # Pitfalls
//! - Forgetting the transpose gives the inverse rotation; forgetting the sign flips mirrors the
//!   image. The tests compare against the official conversion at two image sizes.
//! - NDC is relative to half the shorter side for both axes, even for non-square images.
//! - The NDC principal point is measured leftwards/upwards from `(W/2, H/2)`.

use nalgebra::{Matrix3, Matrix4, Vector2, Vector3};

use crate::camera::{Camera, ImageSize, Intrinsics, Pose};
use crate::error::{Result, ensure_finite};

/// `diag(−1, −1, 1)`: the flip between PyTorch3D's (+X left, +Y up) and OpenCV's (+x right,
/// +y down) camera axes; its own inverse. A PyTorch3D view-space point is `axis_flip() · x_cv`.
pub fn axis_flip() -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(-1.0, -1.0, 1.0))
}

/// Half the shorter side and the image centre `(W/2, H/2)`, the NDC scale and origin of
/// PyTorch3D's screen conversion, for a (possibly fractional) size in pixels.
fn ndc_frame(width: f64, height: f64) -> (f64, Vector2<f64>) {
    (
        width.min(height) / 2.0,
        Vector2::new(width / 2.0, height / 2.0),
    )
}

/// Focal length and principal point in PyTorch3D NDC units (half the shorter image side).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NdcIntrinsics {
    /// `(fx, fy)` in NDC.
    pub focal: Vector2<f64>,
    /// `(px, py)` in NDC; `(0, 0)` is the image centre, positive towards the left/top.
    pub principal_point: Vector2<f64>,
}

/// Focal length and principal point in pixels (the pair PyTorch3D's `_convert_*` helpers pass
/// around, before a [`crate::Intrinsics`] is formed).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelIntrinsics {
    /// `(fx, fy)` in pixels.
    pub focal: Vector2<f64>,
    /// `(cx, cy)` in pixels.
    pub principal_point: Vector2<f64>,
}

/// An axis-aligned crop box `[x0, y0, x0 + width, y0 + height]` in pixels of the source image;
/// it may extend past the image (training jitter pads with zeros).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CropBox {
    /// Left edge.
    pub x0: f64,
    /// Top edge.
    pub y0: f64,
    /// Width in pixels.
    pub width: f64,
    /// Height in pixels.
    pub height: f64,
}

impl NdcIntrinsics {
    /// PyTorch3D `_convert_ndc_to_pixels` for an image of `width × height` pixels.
    pub fn to_pixels(&self, width: f64, height: f64) -> PixelIntrinsics {
        let (s, c0) = ndc_frame(width, height);
        PixelIntrinsics {
            focal: self.focal * s,
            principal_point: c0 - self.principal_point * s,
        }
    }

    /// PyTorch3D `_convert_pixels_to_ndc` for an image of `width × height` pixels.
    pub fn from_pixels(px: &PixelIntrinsics, width: f64, height: f64) -> Self {
        let (s, c0) = ndc_frame(width, height);
        Self {
            focal: px.focal / s,
            principal_point: (c0 - px.principal_point) / s,
        }
    }

    /// Official `adjust_camera_to_bbox_crop_`: intrinsics of the crop `crop` of an image of
    /// `image_width × image_height`, in NDC of the crop.
    pub fn adjusted_to_crop(&self, image_width: f64, image_height: f64, crop: &CropBox) -> Self {
        let mut px = self.to_pixels(image_width, image_height);
        px.principal_point -= Vector2::new(crop.x0, crop.y0);
        Self::from_pixels(&px, crop.width, crop.height)
    }

    /// Official `adjust_camera_to_image_scale_`: intrinsics after resizing an image of
    /// `original` size `(W, H)` to `new` size, scaling by `min(new / original)`.
    pub fn adjusted_to_scale(&self, original: (f64, f64), new: (f64, f64)) -> Self {
        let mut px = self.to_pixels(original.0, original.1);
        let scale = (new.0 / original.0).min(new.1 / original.1);
        px.focal *= scale;
        px.principal_point *= scale;
        Self::from_pixels(&px, new.0, new.1)
    }
}

/// One PyTorch3D `PerspectiveCameras` entry: row-vector extrinsics and NDC intrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pytorch3dCamera {
    /// Row-vector rotation: `X_cam = X_world · R + T`.
    pub r: Matrix3<f64>,
    /// Row translation `T`.
    pub t: Vector3<f64>,
    /// Focal length and principal point in NDC.
    pub intrinsics: NdcIntrinsics,
}

impl Pytorch3dCamera {
    /// `get_world_to_view_transform().get_matrix()`: `[[R, 0], [T, 1]]`.
    pub fn world_to_view_matrix(&self) -> Matrix4<f64> {
        let mut m = Matrix4::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&self.r);
        m.fixed_view_mut::<1, 3>(3, 0)
            .copy_from(&self.t.transpose());
        m[(3, 3)] = 1.0;
        m
    }

    /// `get_camera_center()`: `C = −T Rᵀ` (as a column, `−R T`).
    pub fn camera_center(&self) -> Vector3<f64> {
        -(self.r * self.t)
    }

    /// The extrinsics in the OpenCV convention (independent of the image size).
    pub fn opencv_pose(&self) -> Pose {
        let flip = axis_flip();
        Pose::new(flip * self.r.transpose(), flip * self.t)
    }

    /// PyTorch3D `opencv_from_cameras_projection` for an image of `size`.
    ///
    /// # Errors
    /// Non-finite values or non-positive focal lengths.
    pub fn to_opencv(&self, size: ImageSize) -> Result<Camera> {
        ensure_finite("PyTorch3D camera", self.r.iter().chain(self.t.iter()))?;
        let px = self
            .intrinsics
            .to_pixels(f64::from(size.width()), f64::from(size.height()));
        let k = Intrinsics::new(
            px.focal.x,
            px.focal.y,
            px.principal_point.x,
            px.principal_point.y,
        )?;
        Ok(Camera::new(k, self.opencv_pose(), size))
    }

    /// PyTorch3D `cameras_from_opencv_projection`: the inverse of [`Self::to_opencv`], using the
    /// camera's own image size.
    pub fn from_opencv(camera: &Camera) -> Self {
        let flip = axis_flip();
        let pose = &camera.cam_from_world;
        let k = &camera.intrinsics;
        let size = camera.image_size;
        let px = PixelIntrinsics {
            focal: Vector2::new(k.fx(), k.fy()),
            principal_point: Vector2::new(k.cx(), k.cy()),
        };
        Self {
            r: (flip * pose.rotation).transpose(),
            t: flip * pose.translation,
            intrinsics: NdcIntrinsics::from_pixels(
                &px,
                f64::from(size.width()),
                f64::from(size.height()),
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Point3, Vector4};

    use super::*;

    fn p3d_camera() -> Pytorch3dCamera {
        Pytorch3dCamera {
            r: crate::Quaternion::new(0.4, -0.3, 0.8, 0.1)
                .to_rotation_matrix()
                .unwrap(),
            t: Vector3::new(0.3, -0.4, 5.0),
            intrinsics: NdcIntrinsics {
                focal: Vector2::new(2.0, 2.2),
                principal_point: Vector2::new(0.1, -0.05),
            },
        }
    }

    #[test]
    fn opencv_projection_agrees_with_pytorch3d_ndc_projection() {
        // PyTorch3D projects X to NDC: x_ndc = f · X_cam.xy / Z + p, with +X left and +Y up;
        // screen pixels are then (W/2 − x_ndc s, H/2 − y_ndc s).
        let cam = p3d_camera();
        let size = ImageSize::new(320, 180).unwrap();
        let (w, h) = (320.0, 180.0);
        let s = 90.0;
        let x = Point3::new(0.2, -0.1, 0.4);
        let x_view = cam.world_to_view_matrix().transpose() * Vector4::new(x.x, x.y, x.z, 1.0);
        let ndc = Vector2::new(
            cam.intrinsics.focal.x * x_view.x / x_view.z + cam.intrinsics.principal_point.x,
            cam.intrinsics.focal.y * x_view.y / x_view.z + cam.intrinsics.principal_point.y,
        );
        let expected = Vector2::new(w / 2.0 - ndc.x * s, h / 2.0 - ndc.y * s);
        let got = cam.to_opencv(size).unwrap().project(&x).unwrap();
        assert!(
            (got.coords - expected).norm() < 1e-10,
            "{got} vs {expected}"
        );
    }

    #[test]
    fn centres_agree() {
        let cam = p3d_camera();
        let cv = cam.to_opencv(ImageSize::new(100, 200).unwrap()).unwrap();
        assert!((cv.center().coords - cam.camera_center()).norm() < 1e-12);
    }

    #[test]
    fn crop_then_scale_matches_pixel_arithmetic() {
        let ndc = p3d_camera().intrinsics;
        let crop = CropBox {
            x0: 80.0,
            y0: 0.0,
            width: 480.0,
            height: 480.0,
        };
        let cropped = ndc.adjusted_to_crop(640.0, 480.0, &crop);
        let scaled = cropped.adjusted_to_scale((480.0, 480.0), (224.0, 224.0));
        let before = ndc.to_pixels(640.0, 480.0);
        let after = scaled.to_pixels(224.0, 224.0);
        let k = 224.0 / 480.0;
        assert!((after.focal - before.focal * k).norm() < 1e-10);
        let expected_pp = (before.principal_point - Vector2::new(80.0, 0.0)) * k;
        assert!((after.principal_point - expected_pp).norm() < 1e-10);
    }
}
