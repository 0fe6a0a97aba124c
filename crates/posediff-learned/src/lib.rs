//! Learned keypoints and matching on candle: ALIKED (Zhao et al., 2023) and LightGlue
//! (Lindenberger et al., 2023) as the reference code runs them, with the released weights
//! loaded unchanged.
//!
//! - [`aliked`]: the ALIKED n16 network, its detector (NMS, top-k, soft-argmax) and its sparse
//!   deformable descriptor head;
//! - [`disk`]: DISK's U-Net and detector (kornia's), descriptors computed at the keypoints only;
//! - [`lightglue`]: LightGlue for ALIKED or DISK features, with adaptive depth and point pruning;
//! - [`weights`]: which files, where they are found, `.pth` → safetensors;
//! - [`deform`]: the deformable 3×3 convolution ALIKED's last two blocks use.
//!
//! This crate is separate from `posediff-matching` so that the OpenCV matcher builds without
//! candle; the umbrella crate composes the two (images → ALIKED → LightGlue → the same MAGSAC
//! verification as SIFT). Keypoints are in pixels of the image the network ran on, OpenCV
//! convention (the centre of the top-left pixel is `(0, 0)`).
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod aliked;
mod conv;
pub mod deform;
pub mod disk;
pub mod error;
pub mod lightglue;
mod sampling;
pub mod weights;

pub use aliked::{Aliked, AlikedConfig, DenseMaps, Keypoints, RgbImage};
pub use disk::{Disk, DiskConfig};
pub use error::{LearnedError, Result};
pub use lightglue::{LightGlue, LightGlueConfig, LightGlueMatches, MatcherInput, PreparedImage};
pub use weights::{StateDict, WeightSet};
