//! The checkpoint-free path's report (`posediff-pipeline`; re-exported under the old path).

pub use posediff_pipeline::report::*;
