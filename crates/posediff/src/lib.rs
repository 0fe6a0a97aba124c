//! posediff: camera poses from a handful of photos.
//!
//! - [`augment`]: the official training augmentation (jittered crops, colour jitter).
//! - [`bench`](mod@bench): accuracy benchmarks (real sets over subsets, the CO3D test protocol).
//! - [`co3d`]: CO3Dv2 annotations and the official test protocol's frame choice.
//! - [`geometric`]: cameras without a checkpoint (two-view geometry, averaging, refinement).
//! - [`loader`]: the official image loader (sorted files, centre crop, 224 px).
//! - [`export`]: cameras.json, COLMAP text, nerfstudio and PyTorch3D writers and readers.
//! - [`pipeline`]: [`Estimator`], images to cameras.
//! - [`train`]: training on CO3D-layout data (frozen backbone, cached features).
//! - [`plot`]: camera frusta from above and from the side, against the ground truth.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod augment;
pub mod bench;
pub mod co3d;
pub mod error;
pub mod export;
pub mod geometric;
pub mod loader;
pub mod pipeline;
pub mod plot;
pub mod train;

pub use error::{PosediffError, Result};
pub use pipeline::{Estimate, EstimateConfig, Estimator, GgsHook, Progress, Silent, StageTimes};
