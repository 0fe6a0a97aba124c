//! Fuzz target `colmap_text`: see `posediff::fuzzing::colmap_text`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| posediff::fuzzing::colmap_text(data));
