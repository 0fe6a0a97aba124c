//! The matchers (moved to `posediff-pipeline`; re-exported under the old path).

pub use posediff_pipeline::correspondences::*;
