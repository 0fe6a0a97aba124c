//! The checkpoint-free pipeline of posediff as a library, composed the way GLOMAP's global
//! mapper controller and COLMAP's controllers compose their stages:
//!
//! - [`correspondences`]: the [`correspondences::Correspondences`] trait, features of images
//!   and verified matches of requested pairs, implemented by OpenCV's SIFT/ORB
//!   (`posediff-matching`) and by ALIKED/DISK + LightGlue (`posediff-learned`).
//! - [`geometric`]: the controller: extraction, the pair plan, matching, the orientation check,
//!   the mapper of `posediff-sfm` with OpenCV's two-view geometry behind its `GeometrySolver`,
//!   the second pass, the turned retry; the refinement of given cameras.
//! - [`orientation`]: a learned matcher's orientation check before the map and turned retry
//!   after it.
//! - [`ggs`] (`--refine official`) and [`bundle_refine`] (`--refine bundle` after the
//!   network): the refinements of cameras from elsewhere.
//! - [`options`]: [`options::PipelineOptions`], every threshold in one tree (run.json,
//!   `--config`, `--set`, Python).
//! - [`report`]: what the controller reports (run.json's method report, warnings).
//! - [`store`]: features and verified matches kept between runs (`--database`), and the
//!   matcher wrapper that resumes from them.
//! - [`progress`]: the step counter of the stages.
//! - [`error`]: posediff's error type.
//!
//! The mapper crate never sees an image, OpenCV or candle: this crate hands it verified
//! [`posediff_geometry::PairMatches`] and a solver.

pub mod bundle_refine;
pub mod correspondences;
pub mod error;
pub mod geometric;
pub mod ggs;
pub mod options;
pub mod orientation;
pub mod progress;
pub mod report;
pub mod store;
mod two_view;

pub use error::{PosediffError, Result};
