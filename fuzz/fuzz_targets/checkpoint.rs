//! Fuzz target: `umbra::fuzzing::CheckpointTarget`, resuming on the seed run's scene and
//! schedule (`UMBRA_FUZZ_RUN`, default `fuzz/seed-run`, made by `cargo run --example
//! fuzz_corpus`; its scene `UMBRA_FUZZ_SCENE`, default `../shared/examples/quadruped-tiny`).
#![no_main]

use std::sync::OnceLock;
use umbra::fuzzing::CheckpointTarget;

static TARGET: OnceLock<CheckpointTarget> = OnceLock::new();

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    umbra::fuzzing::install_panic_hook();
    let target = TARGET.get_or_init(|| {
        let run = std::env::var("UMBRA_FUZZ_RUN").unwrap_or_else(|_| "fuzz/seed-run".into());
        let scene = std::env::var("UMBRA_FUZZ_SCENE").unwrap_or_else(|_| "../shared/examples/quadruped-tiny".into());
        CheckpointTarget::new(run.as_ref(), scene.as_ref()).unwrap_or_else(|e| panic!("the seed run {run}: {e} (make it with `cargo run --example fuzz_corpus`)"))
    });
    let _ = target.run(data);
});
