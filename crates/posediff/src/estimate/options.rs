//! The options tree and the run's intrinsics and refinement (`posediff-pipeline`;
//! re-exported under the old path).

pub use posediff_pipeline::options::*;
