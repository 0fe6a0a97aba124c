//! posediff: camera poses from a handful of photos.
//!
//! - [`augment`]: the official training augmentation (jittered crops, colour jitter).
//! - [`bench`](mod@bench): accuracy benchmarks (real sets over subsets, the CO3D test protocol).
//! - [`co3d`]: CO3Dv2 annotations and the official test protocol's frame choice.
//! - [`geometric`]: cameras without a checkpoint (two-view geometry, averaging, refinement).
//! - [`loader`]: the official image loader (sorted files, centre crop, 224 px).
//! - [`reconstruction`]: the result every writer reads: cameras, keypoints, coloured points.
//! - [`export`]: cameras.json, nerfstudio (+ PLY) and PyTorch3D writers and readers.
//! - [`colmap`]: COLMAP sparse models, text and binary, with points.
//! - [`fuzzing`]: the harnesses of the fuzz targets (`fuzz/`) and of the corpus replay test.
//! - [`records`]: per-image records matched to the images by name, never by position.
//! - [`run`]: one estimation run, either path: inputs checked, cameras, points, one result.
//! - [`run_report`]: run.json, one typed record for both estimation paths.
//! - [`outputs`]: the output folder (COLMAP sparse/0, images, nerfstudio, PLY, viewer).
//! - [`viewer`]: view.html, a self-contained three.js page.
//! - [`pipeline`]: [`Estimator`], images to cameras.
//! - [`train`]: training on CO3D-layout data (frozen backbone, cached features).
//! - [`plot`]: camera frusta from above and from the side, against the ground truth.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod augment;
pub mod bench;
pub mod co3d;
pub mod colmap;
pub mod error;
pub mod export;
pub mod fuzzing;
pub mod geometric;
pub mod loader;
pub mod outputs;
pub mod pipeline;
pub mod plot;
pub mod reconstruction;
pub mod records;
pub mod run;
pub mod run_report;
pub mod train;
pub mod viewer;

pub use error::{PosediffError, Result};
pub use pipeline::{
    Estimate, EstimateConfig, EstimateInput, Estimator, GgsHook, Progress, SamplingInput, Silent,
    StageTimes,
};
