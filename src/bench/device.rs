//! The CPU against the GPU (`umbra bench device`, built with `--features gpu`): milliseconds per
//! training step in the schedule's first stage and in its light stage, and the seconds of a
//! short fit from the start, on flex and on the wgpu device, each as a ratio to flex measured
//! in the same run. On a machine without a GPU the device is Mesa's software driver (lavapipe),
//! whose figures say what the device path costs, not what a GPU gives.

use super::time;
use crate::backend::Backend;
use crate::fit_error::FitError;
use crate::scene::Scene;
use crate::schedule::Schedule;
use crate::train::Trainer;
use std::path::Path;
use std::time::Instant;

/// The backends compared: flex, then the device when the build has one.
fn backends() -> Vec<Backend> {
    #[cfg(feature = "gpu")]
    return vec![Backend::Flex, Backend::Wgpu];
    #[cfg(not(feature = "gpu"))]
    vec![Backend::Flex]
}

/// Milliseconds per step on `backend` from `iteration`, over `budget` seconds.
fn step_ms(scene: &Scene, schedule: &Schedule, backend: Backend, iteration: usize, budget: f64) -> Result<f64, FitError> {
    let mut trainer = Trainer::new(scene.clone(), schedule.clone(), backend, 0)?;
    trainer.set_iteration(iteration)?;
    let mut failure = None;
    let seconds = time(budget, || {
        if let Err(e) = trainer.iterate() {
            failure = Some(e);
        }
    });
    failure.map_or(Ok(seconds * 1e3), Err)
}

/// Seconds of `iterations` steps from the start on `backend`.
fn fit_seconds(scene: &Scene, schedule: &Schedule, backend: Backend, iterations: usize) -> Result<f64, FitError> {
    let mut trainer = Trainer::new(scene.clone(), schedule.clone(), backend, 0)?;
    let start = Instant::now();
    for _ in 0..iterations {
        trainer.iterate()?;
    }
    Ok(start.elapsed().as_secs_f64())
}

/// Times each backend on `scene`; writes `device.{md,csv}` into `out`, returns the table.
pub fn device(scene_path: &Path, schedule_path: &Path, out: &Path, quick: bool, log: impl Fn(&str)) -> Result<String, FitError> {
    if backends().len() < 2 {
        return Err(FitError::Input("umbra bench device compares the CPU with a GPU: build umbra with `--features gpu`".into()));
    }
    let scene = Scene::load(scene_path)?;
    let schedule = Schedule::load(schedule_path)?;
    let budget = if quick { 2.0 } else { 10.0 };
    let iterations = if quick { 20 } else { 200 };
    std::fs::create_dir_all(out).map_err(|e| crate::fit_error::io(out, e))?;
    let measures = [
        ("ms per step, silhouette stage".to_string(), Some(0)),
        ("ms per step, light stage".to_string(), Some(schedule.light_from + 200)),
        (format!("s for the first {iterations} steps"), None),
    ];
    let mut rows = Vec::new();
    for (what, iteration) in &measures {
        let mut baseline = None;
        for backend in backends() {
            log(&format!("bench device: {what} on {backend}"));
            let value = match iteration {
                Some(i) => step_ms(&scene, &schedule, backend, *i, budget)?,
                None => fit_seconds(&scene, &schedule, backend, iterations)?,
            };
            let base = *baseline.get_or_insert(value);
            rows.push((what.clone(), backend.to_string(), value, value / base));
        }
    }
    let mut md = format!(
        "## The CPU against the device: {} ({} rays per batch)\n\n| measure | backend | value | vs flex |\n|---|---|---|---|\n",
        scene_path.display(),
        schedule.rays_per_batch
    );
    for (what, backend, value, ratio) in &rows {
        md += &format!("| {what} | {backend} | {value:.1} | {ratio:.2}x |\n");
    }
    md += "\nBaseline: flex on this machine's CPU cores, measured in the same run. Where the machine has no GPU the device is a software driver: its figures are the device path's overhead, not a GPU's speed.\n";
    let csv = crate::table::to_csv(
        &["measure", "backend", "value", "ratio"],
        rows.iter().map(|(what, backend, value, ratio)| [what.clone(), backend.clone(), format!("{value:.3}"), format!("{ratio:.4}")]),
    );
    let write = |name: &str, text: &str| crate::imageio::write_atomic(&out.join(name), text.as_bytes()).map_err(|e| crate::fit_error::io(&out.join(name), e));
    write("device.md", &md)?;
    write("device.csv", &csv)?;
    Ok(md)
}
