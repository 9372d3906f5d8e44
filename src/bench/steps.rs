//! Training-step cost (`umbra bench steps`): milliseconds per step on a real scene for the
//! field kinds, with and without the work a step need not do (rendering rays that miss every
//! Gaussian bound; encoding a point in every bone instead of its nearest; the grid's lookup as
//! a composite of tensor ops instead of one fused op; the batch rendered on one thread instead
//! of split over every thread; the split render's backward passes one after the other instead of
//! at once; burn's Adam instead of the fused pass), in the schedule's first stage (silhouette
//! and grey albedo) and
//! its light stage (normals and shadow rays).
//! Baseline: the `mlp` field as it was (every ray rendered, one thread), measured in the same run.

use super::time;
use crate::backend::Backend;
use crate::fit_error::FitError;
use crate::plot::{Chart, Series};
use crate::scene::Scene;
use crate::schedule::{FieldKind, FieldSettings, Schedule};
use crate::train::Trainer;
use std::path::Path;

struct Variant {
    name: &'static str,
    field: FieldSettings,
    render_missed_rays: bool,
    /// The grid's lookup as the composite of tensor ops (before the fused op).
    composite_lookup: bool,
    /// The batch rendered on one thread (before `render::render_in_parts`), not on every one.
    one_render_thread: bool,
    /// Every sample through the differentiable pass (before `render::Sampling::cull`).
    every_sample: bool,
    /// The training motion as given, not refined (before `train::motion`; the light stage is
    /// where it is refined).
    motion_given: bool,
    /// The training cameras refined too (`train::camera_pose`, from 400 with the motion).
    cameras_refined: bool,
    /// The render's parts differentiated one after the other on one thread (before
    /// `render::Parts::backward` ran them at once).
    parts_backward_in_turn: bool,
}

/// Milliseconds per step of `variant` from `iteration` (its stage), over `budget` seconds.
fn step_ms(scene: &Scene, schedule: &Schedule, variant: &Variant, iteration: usize, budget: f64) -> Result<f64, FitError> {
    let mut schedule = schedule.clone();
    schedule.field = variant.field.clone();
    schedule.cull_samples &= !variant.every_sample;
    // The motion refined whatever the scene (`auto` refines an imported capture's only).
    schedule.refine_motion = crate::schedule::Switch::Fixed(!variant.motion_given);
    schedule.refine_cameras = crate::schedule::Switch::Fixed(variant.cameras_refined);
    let mut trainer = Trainer::new(scene.clone(), schedule, Backend::Flex, 0)?;
    trainer.render_missed_rays = variant.render_missed_rays;
    trainer.set_composite_lookup(variant.composite_lookup);
    if variant.one_render_thread {
        trainer.render_threads = 1;
    }
    trainer.parts_backward_at_once = !variant.parts_backward_in_turn;
    trainer.set_iteration(iteration)?;
    time_steps(&mut trainer, budget)
}

/// Milliseconds per step of `trainer` from where it is, over `budget` seconds.
fn time_steps(trainer: &mut Trainer, budget: f64) -> Result<f64, FitError> {
    let mut failure = None;
    let seconds = time(budget, || {
        if let Err(e) = trainer.iterate() {
            failure = Some(e);
        }
    });
    match failure {
        Some(e) => Err(e),
        None => Ok(seconds * 1e3),
    }
}

/// The stages a step is timed in: from the start, and 200 iterations into the light's.
const STAGES: [&str; 2] = ["silhouette stage", "light stage"];

/// The step variants timed, the first each stage's baseline.
fn variants(scene: &Scene) -> Vec<Variant> {
    let grid = |top_bones: Option<usize>| FieldSettings { top_bones, ..FieldSettings::of(FieldKind::Grid) };
    let mlp = FieldSettings::of(FieldKind::Mlp);
    // [render missed rays, composite lookup, one render thread, every sample differentiated,
    // the motion as given, the cameras refined, the parts' backward passes in turn]
    let v = |name: &'static str, field: FieldSettings, flags: [bool; 7]| {
        let [render_missed_rays, composite_lookup, one_render_thread, every_sample, motion_given, cameras_refined, parts_backward_in_turn] = flags;
        Variant { name, field, render_missed_rays, composite_lookup, one_render_thread, every_sample, motion_given, cameras_refined, parts_backward_in_turn }
    };
    vec![
        v("mlp, every ray rendered (before), one render thread", mlp.clone(), [true, false, true, false, false, false, false]),
        v("mlp, missed rays skipped, one render thread", mlp.clone(), [false, false, true, false, false, false, false]),
        v("mlp, missed rays skipped", mlp, [false, false, false, false, false, false, false]),
        v(
            "grid, nearest 8 bones (the most a lookup takes), composite lookup",
            grid(Some(scene.skeleton.len().min(crate::field::grid::MAX_TOP_BONES))),
            [false, true, false, false, false, false, false],
        ),
        v("grid, nearest 3 bones, composite lookup", grid(None), [false, true, false, false, false, false, false]),
        v("grid, nearest 3 bones, fused lookup op, one render thread", grid(None), [false, false, true, false, false, false, false]),
        v("grid, nearest 3 bones, fused lookup op, every sample differentiated", grid(None), [false, false, false, true, false, false, false]),
        v(
            "grid, nearest 3 bones, fused lookup op, the motion as given, the parts' backward passes in turn",
            grid(None),
            [false, false, false, false, true, false, true],
        ),
        v("grid, nearest 3 bones, fused lookup op, the motion as given", grid(None), [false, false, false, false, true, false, false]),
        v("grid, nearest 3 bones, fused lookup op (the motion refined from 400)", grid(None), [false, false, false, false, false, false, false]),
        v("grid, nearest 3 bones, fused lookup op, the motion and the cameras refined", grid(None), [false, false, false, false, false, true, false]),
    ]
}

/// Times the variants on `scene`; writes `steps.{md,csv,png}` into `out`, returns the table.
pub fn steps(scene_path: &Path, schedule_path: &Path, out: &Path, quick: bool, run: Option<&Path>) -> Result<String, FitError> {
    let scene = Scene::load(scene_path)?;
    let schedule = Schedule::load(schedule_path)?;
    let variants = variants(&scene);
    let stages = [(STAGES[0], 0), (STAGES[1], schedule.light_from + 200)];
    let budget = if quick { 1.0 } else { 8.0 };
    std::fs::create_dir_all(out).map_err(|e| crate::fit_error::io(out, e))?;
    let mut rows = Vec::new();
    for (stage, iteration) in stages {
        let mut baseline = None;
        for v in &variants {
            let ms = step_ms(&scene, &schedule, v, iteration, budget)?;
            let base = *baseline.get_or_insert(ms);
            rows.push((stage, v.name, ms, ms / base));
        }
    }
    // A fresh field's surface is as soft as its starting beta, so the samples culling leaves out
    // are fewer than in the steps of a fit: a fitted field shows what culling saves (and what the
    // parts' backward passes at once save, on most of a fit's steps).
    if let Some(run) = run {
        let mut baseline = None;
        let mut trainer = super::fitted_trainer(run)?;
        let fitted = "fitted field";
        // Late in a fit: the schedule's late probe and fine samples, and the 16 and 16 every
        // step took before.
        let (probe, fine) = (schedule.probe_samples_per_ray, schedule.fine_samples_per_ray);
        let fused = trainer.state()?.optimisers.clone();
        let burns = fused.in_burns_adam();
        for (name, cull, at_once, probe, fine, burns_adam) in [
            ("every sample differentiated", false, true, probe, fine, false),
            ("culled, the parts' backward passes in turn", true, false, probe, fine, false),
            ("culled, 16 probe and 16 fine samples a ray (before)", true, true, 16, 16, false),
            ("culled, 16 probe samples a ray (before)", true, true, 16, fine, false),
            ("culled, burn's Adam (before the fused pass)", true, true, probe, fine, true),
            ("culled", true, true, probe, fine, false),
        ] {
            // Each Adam continues from the fitted run's state (the two are the same Adam).
            trainer.state_mut()?.optimisers = if burns_adam { burns.clone() } else { fused.clone() };
            trainer.schedule.cull_samples = cull;
            trainer.parts_backward_at_once = at_once;
            trainer.schedule.probe_samples_per_ray = probe;
            trainer.schedule.fine_samples_per_ray = fine;
            let ms = time_steps(&mut trainer, budget)?;
            let base = *baseline.get_or_insert(ms);
            rows.push((fitted, name, ms, ms / base));
        }
    }
    write_tables(out, scene_path, &schedule, &rows, run)
}

/// steps.md, steps.csv and steps.png of the rows (stage, variant, ms per step, ratio); the Markdown.
fn write_tables(out: &Path, scene_path: &Path, schedule: &Schedule, rows: &[(&str, &str, f64, f64)], run: Option<&Path>) -> Result<String, FitError> {
    let stages = STAGES;
    let mut md = format!(
        "## Training step cost: {} ({} rays per batch, {} coarse + {} probe + {} fine samples per ray)\n\n| stage | variant | ms per step | vs baseline |\n|---|---|---|---|\n",
        scene_path.display(),
        schedule.rays_per_batch,
        schedule.samples_per_ray,
        schedule.probe_samples_label(),
        schedule.fine_samples_label()
    );
    for (stage, name, ms, ratio) in rows {
        md += &format!("| {stage} | {name} | {ms:.1} | {ratio:.2}x |\n");
    }
    let csv = crate::table::to_csv(
        &["stage", "variant", "ms_per_step", "ratio"],
        rows.iter().map(|(stage, name, ms, ratio)| [stage.to_string(), name.to_string(), format!("{ms:.3}"), format!("{ratio:.4}")]),
    );
    md += "\nBaseline: the first row of each stage (the mlp field rendering every ray), measured in the same run.\n";
    if let Some(run) = run {
        md += &format!("The fitted field's rows: the fit in `{}` continued from its checkpoint, 100 iterations before its end.\n", run.display());
    }
    let write = |name: &str, text: &str| crate::imageio::write_atomic(&out.join(name), text.as_bytes()).map_err(|e| crate::fit_error::io(&out.join(name), e));
    write("steps.md", &md)?;
    write("steps.csv", &csv)?;
    let mut names: Vec<&str> = stages.to_vec();
    if run.is_some() {
        names.push("fitted field");
    }
    let series = names
        .iter()
        .map(|stage| Series {
            name: stage.to_string(),
            points: rows.iter().filter(|r| r.0 == *stage).enumerate().map(|(k, r)| (k as f64 + 1.0, r.2)).collect(),
            lines: true,
        })
        .collect();
    let chart = Chart {
        title: "ms per training step by variant (numbered as in steps.md)".into(),
        x_label: "variant".into(),
        y_label: "ms per step".into(),
        log_x: false,
        log_y: false,
        series,
        marks: Vec::new(),
    };
    chart.render(800, 500).save_png(&out.join("steps.png")).map_err(|e| crate::fit_error::io(&out.join("steps.png"), e))?;
    Ok(md)
}
