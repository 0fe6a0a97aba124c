//! Fuzz target `image`: see `posediff::fuzzing::image`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| posediff::fuzzing::image(data));
