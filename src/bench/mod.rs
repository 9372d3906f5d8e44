//! Benchmarks behind `umbra bench` and `cargo bench`: each prints ratios against a baseline
//! measured in the same run and writes a Markdown table, a CSV and a PNG plot.

mod breakdown;
mod device;
mod environment;
mod fit;
mod gradients;
mod memory;
mod render;
mod scenes;
pub mod shadows;
mod steps;

pub use breakdown::breakdown;
pub use device::device;
pub use environment::environment;
pub use fit::{fit_curves, CurvePoint, FitBenchOptions};
pub use gradients::gradients;
pub use memory::{memory, MemoryBenchOptions};
pub use render::render;
pub use scenes::{scenes, shipped_scenes, ScenesBenchOptions};
pub use shadows::{body_cloud, shadows, sun_rays, Row, FLOPS_PER_PAIR};
pub use steps::steps;

use std::time::Instant;

/// The shipped scene benchmarks train on when none is named.
pub const DEFAULT_SCENE: &str = "datasets-synthetic/human-sun";

/// Seconds per call of `f`, repeated until at least `budget` seconds have passed.
pub(crate) fn time(budget: f64, mut f: impl FnMut()) -> f64 {
    f();
    let start = Instant::now();
    let mut calls = 0;
    while calls == 0 || start.elapsed().as_secs_f64() < budget {
        f();
        calls += 1;
    }
    start.elapsed().as_secs_f64() / calls as f64
}

pub(crate) fn machine_peak_flops() -> (f64, String) {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let mhz = info.lines().find(|l| l.starts_with("cpu MHz")).and_then(|l| l.split(':').nth(1)).and_then(|v| v.trim().parse::<f64>().ok()).unwrap_or(2500.0);
    let flags = info.lines().find(|l| l.starts_with("flags")).unwrap_or("");
    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1) as f64;
    let (per_cycle, isa) = if flags.contains(" avx512f") {
        (64.0, "AVX-512 FMA")
    } else if flags.contains(" avx2") && flags.contains(" fma") {
        (32.0, "AVX2 FMA")
    } else {
        (8.0, "SSE")
    };
    (cores * mhz * 1e6 * per_cycle, format!("{cores} cores x {mhz:.0} MHz x {per_cycle} f32 flop/cycle ({isa})"))
}

/// The fit in the run folder `run`, rebuilt from its checkpoint and set 100 iterations before its
/// end (every grid level in, the light fitted): what most of a fit's steps look like once the
/// surface has formed, where a fresh field's is as soft as its starting beta.
fn fitted_trainer(run: &std::path::Path) -> Result<crate::train::Trainer, crate::fit_error::FitError> {
    let mut trainer = crate::run::restore_trainer(run, crate::backend::Backend::Flex)?;
    trainer.set_iteration(trainer.schedule.iterations.saturating_sub(100).max(trainer.schedule.light_from + 1))?;
    Ok(trainer)
}
