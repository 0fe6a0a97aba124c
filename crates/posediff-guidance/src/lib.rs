//! Geometry-guided sampling (GGS) for PoseDiffusion: the official five-phase SGD on the mean
//! Sampson error of keypoint matches, with analytic gradients in plain Rust.
//!
//! - [`MatchSet`]: matches grouped by ordered frame pair, structure of arrays.
//! - [`SampsonObjective`]: loss and gradient with respect to the 9-D pose encodings.
//! - [`GgsSolver`] / [`geometry_guided_sampling`]: the official schedule ([`GgsConfig`]'s
//!   `Default` is the official configuration).
//! - Without a checkpoint: [`averaging`] (view graph, rotation and translation averaging),
//!   [`selfcal`] (a shared focal from pairwise fundamental matrices) and [`refine`] (the
//!   Sampson objective run to convergence by Levenberg–Marquardt), [`bundle`] (tracks,
//!   triangulation and bundle adjustment).
#![deny(missing_docs)]
// Unsafe only for runtime SIMD dispatch (`sampson::pair_sums`), with the check beside it.
#![deny(unsafe_code)]

pub mod averaging;
pub mod bundle;
pub mod error;
pub mod ggs;
pub mod matches;
pub mod refine;
pub mod sampson;
pub mod selfcal;
pub mod synthetic;

pub use error::{GuidanceError, Result};
pub use ggs::{GgsConfig, GgsReport, GgsSolver, IterationRecord, geometry_guided_sampling};
pub use matches::{MatchSet, PairGroup};
pub use refine::{ImageIntrinsics, RefineCamera, RefineConfig, RefineReport, refine_cameras};
pub use sampson::{Evaluation, SampsonObjective, UpdateMask};
