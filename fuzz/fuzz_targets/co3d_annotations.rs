//! Fuzz target `co3d_annotations`: see `posediff::fuzzing::co3d_annotations`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| posediff::fuzzing::co3d_annotations(data));
