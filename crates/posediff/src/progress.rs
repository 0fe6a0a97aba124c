//! The stages' step counter (`posediff-pipeline`; re-exported under the old path).

pub use posediff_pipeline::progress::*;
