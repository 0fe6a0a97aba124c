//! Fuzz target `cameras_json`: see `posediff::fuzzing::cameras_json`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| posediff::fuzzing::cameras_json(data));
