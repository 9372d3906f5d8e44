//! Where a fit's and a render's time goes (`umbra bench breakdown`), as Table 2 of the
//! relightable-characters supplement does: milliseconds per part of a training iteration
//! (`messages::PHASES`: batch sampling, field forward and normals, shading with shadows, the
//! losses, the SDF gradients of the regularisers, backward, optimiser) in the silhouette and
//! the light stage (also with the training motion refined), and of rendering one test view (the field alone, with sun shading and
//! shadows, with sky sampling), with the process's peak memory after each. burn's CPU
//! backends run eagerly, so each part's tensor work is done within its span.

use super::fit::peak_rss_mib;
use crate::backend::Backend;
use crate::eval::{render_view, render_view_layers, Lighting, VIEW_SAMPLING};
use crate::fit_error::{io, FitError};
use crate::messages::PHASES;
use crate::plot::BarChart;
use crate::scene::Scene;
use crate::schedule::Schedule;
use crate::train::Trainer;
use burn::module::Module;
use std::path::Path;
use std::time::Instant;

/// One measured part.
struct Part {
    stage: String,
    part: String,
    ms: f64,
    peak_mib: Option<f64>,
    /// How many cores the part kept busy: the process's CPU time over its wall time (a training
    /// step's parts only, where the CPU time can be read).
    cores: Option<f64>,
}

/// Mean milliseconds per phase over `steps` training steps from `iteration`.
fn training_parts(scene: &Scene, schedule: &Schedule, stage: &str, iteration: usize, steps: usize) -> Result<Vec<Part>, FitError> {
    let mut trainer = Trainer::new(scene.clone(), schedule.clone(), Backend::Flex, 0)?;
    // Past the sun search (a one-off, timed on its own below).
    trainer.set_iteration(iteration + 1)?;
    trainer_parts(&mut trainer, stage, steps)
}

/// Mean milliseconds per phase over `steps` steps of `trainer` from where it is, after one
/// step to warm up.
fn trainer_parts(trainer: &mut Trainer, stage: &str, steps: usize) -> Result<Vec<Part>, FitError> {
    trainer.iterate()?;
    let mut sums = vec![0.0; PHASES.len()];
    let mut cpu_sums = vec![0.0; PHASES.len()];
    let (mut whole, mut whole_cpu) = (0.0, 0.0);
    let mut cpu_read = true;
    for _ in 0..steps {
        let stats = trainer.iterate()?;
        whole += stats.seconds;
        cpu_read &= !stats.phase_cpu.is_empty() && stats.cpu_seconds.is_some();
        for (into, spans) in [(&mut sums, &stats.phases), (&mut cpu_sums, &stats.phase_cpu)] {
            for (name, seconds) in spans {
                if let Some(k) = PHASES.iter().position(|p| p == name) {
                    into[k] += seconds;
                }
            }
        }
        whole_cpu += stats.cpu_seconds.unwrap_or(0.0);
    }
    let peak = peak_rss_mib();
    let cores = |cpu: f64, wall: f64| (cpu_read && wall > 0.0).then_some(cpu / wall);
    let mut parts: Vec<Part> = PHASES
        .iter()
        .zip(sums.iter().zip(&cpu_sums))
        .filter(|(_, (s, _))| **s > 0.0)
        .map(|(name, (s, cpu))| Part { stage: stage.into(), part: name.to_string(), ms: s / steps as f64 * 1e3, peak_mib: peak, cores: cores(*cpu, *s) })
        .collect();
    parts.push(Part { stage: stage.into(), part: "whole step".into(), ms: whole / steps as f64 * 1e3, peak_mib: peak, cores: cores(whole_cpu, whole) });
    Ok(parts)
}

/// Milliseconds to render one view of the scene's first test image's camera and frame.
fn render_parts(scene: &Scene, schedule: &Schedule, repeats: usize) -> Result<Vec<Part>, FitError> {
    let trainer = Trainer::new(scene.clone(), schedule.clone(), Backend::Flex, 0)?;
    let model = trainer.model()?.valid();
    let device = trainer.device.clone().without_autodiff();
    let view = scene.views.first().ok_or_else(|| FitError::Input("the scene has no images".into()))?;
    let sky = crate::light::Light::Uniform { radiance: glam::DVec3::ONE };
    let scale = glam::DVec3::ONE;
    let cases: [(&str, Lighting); 3] = [
        ("field only (albedo, no normals)", Lighting::Albedo { albedo_scale: scale }),
        ("field + normals + sun shading with Gaussian shadows", Lighting::Fitted(0)),
        (
            "field + normals + sky: 256 sampled directions with Gaussian visibility",
            Lighting::Known { light: &sky, albedo_scale: scale, samples: crate::scoring::SKY_SAMPLES },
        ),
    ];
    // A first render warms caches and allocations up, so the first case is not charged for it.
    render_view(&model, scene, view.camera, view.frame, VIEW_SAMPLING, &device, &Lighting::Albedo { albedo_scale: scale });
    let mut parts = Vec::new();
    for (name, lighting) in cases {
        let start = Instant::now();
        for _ in 0..repeats {
            render_view(&model, scene, view.camera, view.frame, VIEW_SAMPLING, &device, &lighting);
        }
        let ms = start.elapsed().as_secs_f64() / repeats as f64 * 1e3;
        parts.push(Part { stage: "render one view".into(), part: name.into(), ms, peak_mib: peak_rss_mib(), cores: None });
    }
    // A test image and its albedo, as the evaluation scores them: two renders, or one trace.
    let sun = Lighting::Fitted(0);
    let start = Instant::now();
    for _ in 0..repeats {
        render_view(&model, scene, view.camera, view.frame, VIEW_SAMPLING, &device, &sun);
        render_view(&model, scene, view.camera, view.frame, VIEW_SAMPLING, &device, &Lighting::Albedo { albedo_scale: scale });
    }
    let apart = start.elapsed().as_secs_f64() / repeats as f64 * 1e3;
    let start = Instant::now();
    for _ in 0..repeats {
        render_view_layers(&model, scene, view.camera, view.frame, VIEW_SAMPLING, &device, &sun, Some(scale), crate::eval::Strata::Shortcuts);
    }
    let together = start.elapsed().as_secs_f64() / repeats as f64 * 1e3;
    for (part, ms) in [("sun-lit image and its albedo, two renders", apart), ("sun-lit image and its albedo, one trace (as the evaluation does)", together)] {
        parts.push(Part { stage: "render one test image".into(), part: part.into(), ms, peak_mib: peak_rss_mib(), cores: None });
    }
    Ok(parts)
}

/// Measures the breakdown on `scene` with `schedule`; writes `breakdown.{md,csv,png}` into
/// `out` and returns the Markdown table.
pub fn breakdown(scene_path: &Path, schedule_path: &Path, out: &Path, quick: bool, run: Option<&Path>) -> Result<String, FitError> {
    let scene = Scene::load(scene_path)?;
    let schedule = Schedule::load(schedule_path)?;
    let steps = if quick { 3 } else { 20 };
    std::fs::create_dir_all(out).map_err(|e| io(out, e))?;
    let mut parts = training_parts(&scene, &schedule, "silhouette stage", 0, steps)?;
    parts.extend(training_parts(&scene, &schedule, "light stage", schedule.light_from + 200, steps)?);
    // The same stage with the training motion refined whatever the scene (`auto` refines an
    // imported capture's only): what the refinement adds to a step, part by part.
    let mut refined = schedule.clone();
    refined.refine_motion = crate::schedule::Switch::Fixed(true);
    parts.extend(training_parts(&scene, &refined, "light stage, motion refined", schedule.light_from + 200, steps)?);
    if let Some(run) = run {
        let mut trainer = super::fitted_trainer(run)?;
        parts.extend(trainer_parts(&mut trainer, "fitted field", steps)?);
    }
    // The sun search runs once per fit, at light_from.
    let mut trainer = Trainer::new(scene.clone(), schedule.clone(), Backend::Flex, 0)?;
    trainer.set_iteration(schedule.light_from)?;
    let stats = trainer.iterate()?;
    if let Some((_, seconds)) = stats.phases.iter().find(|(name, _)| *name == PHASES[0]) {
        parts.push(Part { stage: "once per fit".into(), part: "sun search".into(), ms: seconds * 1e3, peak_mib: peak_rss_mib(), cores: None });
    }
    parts.extend(render_parts(&scene, &schedule, if quick { 1 } else { 3 })?);

    let mut md = format!(
        "## Where the time goes: {} ({} rays per step, {} + {} + {} samples per ray, mean of {steps} steps)\n\n| stage | part | ms | share of its stage | cores busy | peak memory (MiB) |\n|---|---|---|---|---|---|\n",
        scene_path.display(),
        schedule.rays_per_batch,
        schedule.samples_per_ray,
        schedule.probe_samples_label(),
        schedule.fine_samples_label()
    );
    let mut csv_rows = Vec::new();
    for p in &parts {
        let whole = parts.iter().find(|q| q.stage == p.stage && q.part == "whole step").map(|q| q.ms);
        let share = whole.filter(|_| p.part != "whole step").map(|w| p.ms / w);
        let peak = p.peak_mib.map(|m| format!("{m:.0}")).unwrap_or_else(|| "-".into());
        let cores = p.cores.map(|c| format!("{c:.2}")).unwrap_or_else(|| "-".into());
        md += &format!(
            "| {} | {} | {:.1} | {} | {cores} | {peak} |\n",
            p.stage,
            p.part,
            p.ms,
            share.map(|s| format!("{:.0}%", s * 100.0)).unwrap_or_else(|| "-".into())
        );
        csv_rows.push([
            p.stage.clone(),
            p.part.clone(),
            format!("{:.3}", p.ms),
            share.map(|s| format!("{s:.4}")).unwrap_or_default(),
            p.cores.map(|c| format!("{c:.3}")).unwrap_or_default(),
            p.peak_mib.map(|m| format!("{m:.1}")).unwrap_or_default(),
        ]);
    }
    let csv = crate::table::to_csv(&["stage", "part", "ms", "share", "cores_busy", "peak_mib"], csv_rows);
    md += "\nCores busy: the process's CPU time over the part's wall time (the render's three parts share one figure: they run together). Peak memory is the process's high-water mark after each stage (it only grows).\n";
    let whole = |stage: &str| parts.iter().find(|p| p.stage == stage && p.part == "whole step").map(|p| p.ms);
    if let (Some(given), Some(refined)) = (whole("light stage"), whole("light stage, motion refined")) {
        md += &format!("A light-stage step with the training motion refined costs {:.2}x one with it as given.\n", refined / given);
    }
    let write = |name: &str, text: &str| crate::imageio::write_atomic(&out.join(name), text.as_bytes()).map_err(|e| io(&out.join(name), e));
    write("breakdown.md", &md)?;
    write("breakdown.csv", &csv)?;
    let stages = ["silhouette stage", "light stage", "light stage, motion refined"];
    let chart = BarChart {
        title: "ms per part of a training step".into(),
        unit: "ms".into(),
        labels: PHASES[1..].iter().map(|s| s.to_string()).collect(),
        series: stages
            .iter()
            .map(|stage| {
                (
                    stage.to_string(),
                    PHASES[1..].iter().map(|name| parts.iter().find(|p| p.stage == *stage && p.part == *name).map(|p| p.ms).unwrap_or(0.0)).collect(),
                )
            })
            .collect(),
    };
    chart.render(900).save_png(&out.join("breakdown.png")).map_err(|e| io(&out.join("breakdown.png"), e))?;
    Ok(md)
}
