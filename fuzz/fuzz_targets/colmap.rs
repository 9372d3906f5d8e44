//! Fuzz target: `umbra::fuzzing::colmap`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    umbra::fuzzing::install_panic_hook();
    let _ = umbra::fuzzing::colmap(data);
});
