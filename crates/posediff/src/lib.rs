//! posediff: camera poses from a handful of photos.
//!
//! - [`estimate`]: cameras from images: [`estimate::run`] (one run, either path),
//!   [`estimate::estimator`] (PoseDiffusion with GGS), [`estimate::geometric`] (the
//!   checkpoint-free mapper), [`estimate::run_report`] (run.json).
//! - [`reconstruction`]: the result every writer reads: cameras, keypoints, coloured points.
//! - [`io`]: images, per-image records, cameras.json, COLMAP, nerfstudio, PyTorch3D, CO3D, the
//!   output folder and the viewer.
//! - [`train`]: training on CO3D-layout data (frozen backbone with cached features, or
//!   augmented batches), its loss log and plot.
//! - [`bench`](mod@bench): accuracy benchmarks (real sets over subsets, the CO3D test protocol).
//! - [`plot`]: camera frusta from above and from the side, against the ground truth.
//! - [`fuzzing`]: the harnesses of the fuzz targets (`fuzz/`) and of the corpus replay test.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod bench;
pub mod correspondences;
pub mod error;
pub mod estimate;
pub mod fuzzing;
pub mod io;
pub mod plot;
pub mod progress;
pub mod reconstruction;
pub mod train;

pub use error::{PosediffError, Result};
pub use estimate::estimator::{
    Estimate, EstimateConfig, EstimateInput, Estimator, GgsHook, Progress, SamplingInput, Silent,
    StageTimes,
};
