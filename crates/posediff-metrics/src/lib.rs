//! Camera pose metrics exactly as the official PoseDiffusion evaluation computes them
//! (`util/metric.py`, `test.py`), plus RelPose++'s camera-centre accuracy.
//!
//! - [`relative`]: per-pair rotation and translation-direction errors (`camera_to_rel_deg`),
//!   with a mode that charges a failed camera in every pair.
//! - [`accuracy`]: RRA / RTA at 5/15/30°, mAA(30) as `test.py` (and `train.py`) compute it,
//!   per-category pooling and the unweighted mean.
//! - [`centers`]: camera-centre accuracy after Umeyama, and the demo's absolute rotation error.
//!
//! Inputs are [`posediff_geometry`] cameras and poses in the OpenCV convention.
//!
//! ```
//! use posediff_geometry::Pose;
//! use posediff_metrics::{PoseAccuracy, relative_pose_errors};
//! use nalgebra::Vector3;
//!
//! let gt: Vec<Pose> = (0..3)
//!     .map(|i| Pose::new(nalgebra::Matrix3::identity(), Vector3::new(i as f64, 0.0, 1.0)))
//!     .collect();
//! let pairs = relative_pose_errors(&gt, &gt)?;
//! let acc = PoseAccuracy::from_pairs(&pairs)?;
//! assert_eq!(acc.rra, [1.0, 1.0, 1.0]);
//! # Ok::<(), posediff_metrics::MetricsError>(())
//! ```
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod accuracy;
pub mod centers;
pub mod error;
pub mod numpy_rng;
pub mod relative;

pub use accuracy::{CategoryPool, CategoryReport, PoseAccuracy, maa_test_py, maa_train_py};
pub use centers::{RELPOSE_CENTER_THRESHOLD, absolute_rotation_errors_deg, camera_center_accuracy};
pub use error::{MetricsError, Result};
pub use relative::{
    PairError, relative_pose_errors, relative_pose_errors_with_failures, rotation_angle_deg,
    translation_angle_deg,
};
