//! Cameras without a checkpoint: the controller of `posediff-pipeline`, re-exported under the
//! old path (the umbrella only wires it to its inputs and writers).

pub use posediff_pipeline::geometric::*;
