//! posediff's error type (`posediff-pipeline`; re-exported under the old path).

pub use posediff_pipeline::error::*;
