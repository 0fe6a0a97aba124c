//! Geometry-guided sampling (GGS) for PoseDiffusion: the official five-phase SGD on the mean
//! Sampson error of keypoint matches, with analytic gradients in plain Rust.
//!
//! - [`MatchSet`]: matches grouped by ordered frame pair, structure of arrays.
//! - [`SampsonObjective`]: loss and gradient with respect to the 9-D pose encodings.
//! - [`GgsSolver`] / [`geometry_guided_sampling`]: the official schedule ([`GgsConfig`]'s
//!   `Default` is the official configuration).
//! - `synthetic` (feature `synthetic`, test support): ring problems with known cameras.
//!
//! The checkpoint-free mapper (averaging, Sampson refinement to convergence, bundle
//! adjustment) is `posediff-sfm`.
#![deny(missing_docs)]
// Unsafe only for runtime SIMD dispatch (`sampson::pair_sums`), with the check beside it.
#![deny(unsafe_code)]

pub mod error;
pub mod ggs;
pub mod matches;
pub mod sampson;
#[cfg(feature = "synthetic")]
pub mod synthetic;

pub use error::{GuidanceError, Result};
pub use ggs::{GgsConfig, GgsReport, GgsSolver, IterationRecord, geometry_guided_sampling};
pub use matches::{MatchSet, PairGroup};
pub use sampson::{Evaluation, SampsonObjective, UpdateMask};
