//! Fuzz target `colmap_binary`: see `posediff::fuzzing::colmap_binary`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| posediff::fuzzing::colmap_binary(data));
