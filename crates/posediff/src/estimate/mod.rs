//! Cameras from images, by either path, and what a run reports.
//!
//! - [`run`]: one estimation run for every front end (CLI, Python): inputs checked and named,
//!   typed options, the cameras, the points, one result.
//! - [`estimator`]: [`estimator::Estimator`], PoseDiffusion with GGS: images → matches in the
//!   224 crops → DINO features → reverse diffusion → cameras; the model's pose encodings.
//! - [`geometric`]: cameras without a checkpoint (matching, then `posediff_sfm`'s mapper).
//! - [`run_report`]: run.json, one typed record for both paths.

pub mod estimator;
pub mod geometric;
pub mod geometric_report;
pub mod options;
pub mod run;
pub mod run_report;
