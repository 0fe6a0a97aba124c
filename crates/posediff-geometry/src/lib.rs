//! Camera geometry for posediff, free of tensors, OpenCV and linear-algebra back ends beyond
//! nalgebra, so that downstream crates can depend on it alone.
//!
//! - [`Camera`]: the public camera type, OpenCV convention (`x_cam = R x_world + t`, pixels).
//! - [`pytorch3d`]: the only place PyTorch3D's row-vector / NDC cameras are converted.
//! - [`lens`]: the only place lens models live (COLMAP's models and parameter orders).
//! - [`Quaternion`] (w first) and the official 9-D [`PoseEncoding`].
//! - [`normalize`]: the official canonicalisation of ground-truth cameras.
//! - [`epipolar`]: relative pose, essential and fundamental matrices, Sampson error.
//! - [`alignment`]: [`Sim3`], Umeyama, alignment of camera sets.
//!
//! Everything works in `f64`; degenerate input gives a [`GeometryError`], never NaN.
//!
//! ```
//! use posediff_geometry::{Camera, ImageSize, Intrinsics, Pose, fundamental_from_cameras, sampson_error};
//! use nalgebra::{Matrix3, Point3, Vector3};
//!
//! let k = Intrinsics::new(500.0, 500.0, 320.0, 240.0)?;
//! let size = ImageSize::new(640, 480)?;
//! let cam1 = Camera::new(k, Pose::identity(), size);
//! let cam2 = Camera::new(k, Pose::new(Matrix3::identity(), Vector3::new(-1.0, 0.0, 0.0)), size);
//! let f = fundamental_from_cameras(&cam1, &cam2);
//! let x = Point3::new(0.2, -0.1, 5.0);
//! let (p1, p2) = (cam1.project(&x).unwrap(), cam2.project(&x).unwrap());
//! assert!(sampson_error(&f, &p1, &p2)? < 1e-20);
//! # Ok::<(), posediff_geometry::GeometryError>(())
//! ```
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod alignment;
pub mod camera;
#[cfg(feature = "serde")]
pub mod camera_json;
pub mod crop;
pub mod encoding;
pub mod epipolar;
pub mod error;
pub mod lens;
pub mod matches;
pub mod normalize;
pub mod pytorch3d;
pub mod quaternion;

pub use alignment::{
    Sim3, align_cameras_by_centers, align_cameras_by_extrinsics, umeyama, umeyama_with_scale,
};
pub use camera::{Camera, ImageSize, Intrinsics, Pose};
pub use crop::{CenterCrop, MODEL_INPUT_SIDE};
pub use encoding::{POSE_ENCODING_DIM, PoseEncoding};
pub use epipolar::{
    essential_matrix, fundamental_from_cameras, fundamental_official, homography_rotation,
    relative_pose, rotation_angle, rotation_angle_between_deg, sampson_error,
    symmetric_epipolar_distance_sq,
};
pub use error::{GeometryError, Result};
pub use lens::{CameraModel, LensCamera};
pub use matches::{PairMatches, TwoViewPose};
pub use normalize::{Canonicalized, canonicalize, canonicalize_without_optical_axis};
pub use pytorch3d::{NdcIntrinsics, Pytorch3dCamera};
pub use quaternion::{Quaternion, QuaternionSign};
