//! Fuzz target `checkpoint`: see `posediff::fuzzing::checkpoint`.
//!
//! `read_tensors` catches the panics of candle's pickle reader (a malformed pickle is an
//! error). libfuzzer-sys's panic hook would abort on those caught panics too, so this target
//! restores the default hook: a panic that is not caught still unwinds into libfuzzer-sys,
//! which aborts, and the fuzzer reports it.
#![no_main]

libfuzzer_sys::fuzz_target!(
    init: {
        let _ = std::panic::take_hook();
    },
    |data: &[u8]| posediff::fuzzing::checkpoint(data)
);
