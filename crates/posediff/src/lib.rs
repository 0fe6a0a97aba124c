//! posediff: camera poses from a handful of photos.
//!
//! - [`loader`]: the official image loader (sorted files, centre crop, 224 px).
//! - [`export`]: cameras.json, COLMAP text, nerfstudio and PyTorch3D writers and readers.
//! - [`pipeline`]: [`Estimator`], images to cameras.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod error;
pub mod export;
pub mod loader;
pub mod pipeline;

pub use error::{PosediffError, Result};
pub use pipeline::{Estimate, EstimateConfig, Estimator, GgsHook, Progress, Silent, StageTimes};
