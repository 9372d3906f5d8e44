//! Fuzz target: `umbra::fuzzing::clip`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    umbra::fuzzing::install_panic_hook();
    let _ = umbra::fuzzing::clip(data);
});
