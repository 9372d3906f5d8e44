//! A whole fit as the CLI runs it: the training loop with its outputs (`fit.json`,
//! `losses.csv`, `losses.png`, `gaussians.json`, renders), a checkpoint every N iterations
//! (written and read back by `run`), exact `--resume`, and the evaluation of the test images
//! at the end (rendered by `eval`).

use crate::avatar::Avatar;
use crate::backend::Backend;
use crate::fit_error::{io, FitError};
use crate::fit_report::{FitReport, Stage};
use crate::messages::{StepStats, TrainMessage};
use crate::plot::{Chart, Series};
pub use crate::run::{albedo_scale, existing_checkpoint, restore, resume_checkpoint, save_checkpoint_until, save_png, CHECKPOINT, SCHEDULE_COPY};
use crate::run::{apply_recorded_field, load_checkpoint, losses_csv, save_checkpoint, write_text, OLD_CHECKPOINT};
use crate::run_lock::RunLock;
use crate::scene::{Scene, Split};
use crate::schedule::Schedule;
use crate::scoring::{evaluate, light_error};
use crate::shading::LightKind;
use crate::train::Trainer;
use serde_json::json;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Clone, Debug)]
pub struct FitOptions {
    pub scene: PathBuf,
    pub out: PathBuf,
    pub schedule: PathBuf,
    pub iterations: Option<usize>,
    pub seed: u64,
    pub resume: bool,
    /// Replace an earlier run's checkpoint and outputs in `out`.
    pub force: bool,
    /// With `resume`: continue even though the schedule or the iteration count differs from
    /// the run's (otherwise refused: it would not be the continuation it claims).
    pub force_schedule: bool,
    pub backend: Backend,
    /// Render and score the test images at the end.
    pub evaluate: bool,
}

/// The three segments of the schedule, for timing and reporting.
fn segment(schedule: &Schedule, iteration: usize, fit_light: bool) -> &'static str {
    let density_start = schedule.weights.get("density").map(|r| r.hold as usize).unwrap_or(usize::MAX);
    if iteration < density_start.min(schedule.light_from) {
        "density fitting"
    } else if iteration < schedule.light_from {
        "Gaussian fitting"
    } else if fit_light {
        "light and RGB fitting"
    } else {
        "RGB fitting"
    }
}

/// Running mean over `window` points: per-batch losses are noisy, trends are what one reads.
fn smooth(points: Vec<(f64, f64)>, window: usize) -> Vec<(f64, f64)> {
    (0..points.len())
        .map(|k| {
            let lo = k.saturating_sub(window - 1);
            let mean = points[lo..=k].iter().map(|p| p.1).sum::<f64>() / (k + 1 - lo) as f64;
            (points[k].0, mean)
        })
        .collect()
}

fn losses_chart(history: &[(usize, StepStats)]) -> Chart {
    let window = (history.len() / 60).max(1);
    let mut series = vec![Series {
        name: "total (weighted)".into(),
        points: smooth(history.iter().map(|(i, s)| (*i as f64 + 1.0, s.total)).collect(), window),
        lines: true,
    }];
    for term in crate::schedule::TERMS {
        let points: Vec<(f64, f64)> = history.iter().filter_map(|(i, s)| s.terms.get(term).map(|v| (*i as f64 + 1.0, *v))).collect();
        if !points.is_empty() {
            series.push(Series { name: term.into(), points: smooth(points, window), lines: true });
        }
    }
    Chart { title: format!("losses (running mean of {window})"), x_label: "iteration".into(), y_label: "loss".into(), log_x: false, log_y: true, series }
}

/// A `--resume` must continue the run as it was scheduled: the same schedule text and the same
/// iteration count (the learning-rate decays and the stages depend on both), unless
/// `force_schedule`; and never fewer iterations than are done.
fn check_continuation(out: &Path, schedule_text: &str, iterations: usize, seed: u64, force_schedule: bool) -> Result<(), FitError> {
    let checkpoint = existing_checkpoint(out).ok_or_else(|| io(out, "holds no checkpoint to resume"))?;
    let state_path = checkpoint.join("state.json");
    let text = crate::files::read_text(&state_path, crate::files::STATE_BYTES).map_err(|e| io(&state_path, e))?;
    let state: serde_json::Value = serde_json::from_str(&text).map_err(|e| io(&state_path, e))?;
    let done = state["iteration"].as_u64().ok_or_else(|| io(&state_path, "iteration: missing"))? as usize;
    if iterations < done {
        return Err(io(out, format!("has {done} iterations done; resuming to {iterations} would run nothing (nothing was written)")));
    }
    if let Some(recorded) = recorded_seed(out) {
        if recorded != seed {
            return Err(io(
                out,
                format!("was fitted with --seed {recorded}: a resumed fit keeps its seed; leave --seed out or pass --seed {recorded} (nothing was written)"),
            ));
        }
    }
    if force_schedule {
        return Ok(());
    }
    let mut changes = Vec::new();
    if let Some(total) = state["iterations_total"].as_u64() {
        if total as usize != iterations {
            changes.push(format!("the iteration count ({total} -> {iterations})"));
        }
    }
    // Compared as parsed: a comment or `0.10` for `0.1` changes no fit.
    let copy = out.join(SCHEDULE_COPY);
    if let Ok(previous) = crate::files::read_text(&copy, crate::files::SMALL_TEXT_BYTES) {
        let parsed = |text: &str| Schedule::parse(text, Path::new(SCHEDULE_COPY)).ok().and_then(|s| serde_json::to_value(s).ok());
        let differences = match (parsed(&previous), parsed(schedule_text)) {
            (Some(old), Some(new)) => value_differences(&old, &new, ""),
            _ => vec!["its text (the run's copy no longer parses)".to_string()],
        };
        if !differences.is_empty() {
            let shown: Vec<&str> = differences.iter().take(4).map(String::as_str).collect();
            let more = if differences.len() > 4 { format!(" and {} more", differences.len() - 4) } else { String::new() };
            changes.push(format!("the schedule against the run's {} ({}{more})", copy.display(), shown.join(", ")));
        }
    }
    if changes.is_empty() {
        return Ok(());
    }
    Err(io(
        out,
        format!(
            "--resume would change {}: it would not continue the same fit; pass --force-schedule to continue anyway (nothing was written)",
            changes.join(" and ")
        ),
    ))
}

/// Where two parsed schedules differ, as `path: old -> new` (the file they were read from
/// aside).
fn value_differences(old: &serde_json::Value, new: &serde_json::Value, at: &str) -> Vec<String> {
    use serde_json::Value;
    match (old, new) {
        (Value::Object(a), Value::Object(b)) => {
            let keys: std::collections::BTreeSet<&String> = a.keys().chain(b.keys()).filter(|k| !(at.is_empty() && k.as_str() == "file")).collect();
            let null = Value::Null;
            keys.into_iter()
                .flat_map(|k| {
                    value_differences(a.get(k).unwrap_or(&null), b.get(k).unwrap_or(&null), &if at.is_empty() { k.clone() } else { format!("{at}.{k}") })
                })
                .collect()
        }
        _ if old == new => Vec::new(),
        _ => vec![format!("{at}: {old} -> {new}")],
    }
}

/// The evaluation a run's fit.json records (null when it has none).
fn previous_evaluation(run: &Path) -> serde_json::Value {
    FitReport::read(&run.join("fit.json")).map(|report| report.evaluation).unwrap_or(json!(null))
}

/// Loads the scene on a thread of its own, telling `on` how many images are decoded as they are
/// (the decoding threads report over a channel; `on` runs here).
fn load_scene(path: &Path, on: &mut impl FnMut(TrainMessage)) -> Result<Scene, FitError> {
    let (send, receive) = std::sync::mpsc::channel();
    std::thread::scope(|scope| {
        let loading = scope.spawn(move || {
            Scene::load_reporting(path, &move |done, total| {
                // A closed receiver only means nobody watches.
                let _ = send.send((done, total));
            })
        });
        for (done, total) in receive {
            on(TrainMessage::Loading { done, total });
        }
        match loading.join() {
            Ok(scene) => Ok(scene?),
            Err(_) => Err(FitError::Input(format!("{}: loading the scene failed (a decoding thread stopped)", path.display()))),
        }
    })
}

/// The seed a run was started with, from its checkpoint (or, for checkpoints that predate
/// recording it, its fit.json); `None` when neither says.
pub fn recorded_seed(run: &Path) -> Option<u64> {
    let from_state = |file: PathBuf| {
        let text = crate::files::read_text(&file, crate::files::STATE_BYTES).ok()?;
        serde_json::from_str::<serde_json::Value>(&text).ok()?["seed"].as_u64()
    };
    existing_checkpoint(run).and_then(|c| from_state(c.join("state.json"))).or_else(|| FitReport::read(&run.join("fit.json")).ok().map(|r| r.seed))
}

/// Whether `dir` exists and holds entries but none of a run's (checkpoint, fit.json, the
/// schedule copy, an interrupted checkpoint swap).
fn holds_foreign_files(dir: &Path) -> bool {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    let names: Vec<String> = entries.filter_map(|e| e.ok()).map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    let run_marks = [CHECKPOINT, "fit.json", SCHEDULE_COPY, OLD_CHECKPOINT, ".checkpoint.tmp"];
    !names.is_empty() && !names.iter().any(|n| run_marks.contains(&n.as_str()))
}

/// Runs the fit described by `options`, reporting through `on`; returns fit.json's content.
pub fn fit(options: &FitOptions, mut on: impl FnMut(TrainMessage)) -> Result<FitReport, FitError> {
    let wall = Instant::now();
    // The schedule is read first: a mistake in it is found before the images are decoded.
    let (mut schedule, schedule_text) = Schedule::read(&options.schedule)?;
    if let Some(n) = options.iterations {
        schedule.iterations = crate::schedule::check_iterations(n).map_err(FitError::Input)?;
    }
    let scene = load_scene(&options.scene, &mut on)?;
    let out = &options.out;
    if out.exists() && !out.is_dir() {
        return Err(io(out, "exists and is not a folder: --out names the run's folder (nothing was written)"));
    }
    if existing_checkpoint(out).is_some() && !options.resume && !options.force {
        return Err(io(out, "holds a checkpoint of an earlier fit: pass --resume to continue it, --force to replace it, or choose another --out"));
    }
    if options.resume && existing_checkpoint(out).is_none() {
        return Err(io(out, "holds no checkpoint to resume (nothing was written)"));
    }
    // A folder holding files but no run is the user's: it is not written into without --force.
    if !options.resume && !options.force && holds_foreign_files(out) {
        return Err(io(out, "exists, is not empty and is not an umbra run (no checkpoint, fit.json or schedule.toml): pass --force to write into it anyway, or choose another --out"));
    }
    // A resumed run keeps the field it was fitted with (the schedule text is compared below).
    let mut built = schedule.clone();
    if options.resume {
        apply_recorded_field(out, scene.skeleton.len(), &mut built.field)?;
    }
    // Everything is validated before the run folder is touched: a refused fit writes nothing.
    let mut trainer = Trainer::new(scene, built, options.backend, options.seed)?;
    // Without a light to fit the light-only iterations are not run (unless --iterations says).
    let saved = if options.iterations.is_some() { 0 } else { schedule.iterations - schedule.iterations_for(trainer.fit_light) };
    schedule.iterations -= saved;
    trainer.schedule.iterations = schedule.iterations;
    // The checkpoint is loaded (and so validated) before the run's schedule copy is replaced.
    if options.resume {
        check_continuation(out, &schedule_text, schedule.iterations, options.seed, options.force_schedule)?;
    }
    // The folder is locked before anything in it changes: a forced fit must not delete the
    // checkpoint of a fit that is still running there.
    std::fs::create_dir_all(out).map_err(|e| io(out, e))?;
    let _lock = RunLock::acquire(out, "fit")?;
    if options.force && !options.resume {
        let _ = std::fs::remove_dir_all(out.join(CHECKPOINT));
        let _ = std::fs::remove_dir_all(out.join(OLD_CHECKPOINT));
        crate::run::clear_run_outputs(out, true)?;
    }
    let mut history = if options.resume { load_checkpoint(&mut trainer, out)? } else { Vec::new() };
    let first_iteration_here = trainer.iteration;
    crate::imageio::write_atomic(&out.join(SCHEDULE_COPY), schedule_text.as_bytes()).map_err(|e| io(&out.join(SCHEDULE_COPY), e))?;
    history.retain(|(i, _)| *i < trainer.iteration);
    let training_images = trainer.scene.views_in(Split::Train).count();
    on(TrainMessage::Loaded { scene: trainer.scene.display_name(), training_images, frames: trainer.scene.frames.len(), light: trainer.light_kind });
    on(TrainMessage::Started { first: trainer.iteration, iterations: schedule.iterations });
    let mut segment_seconds: BTreeMap<&str, f64> = BTreeMap::new();
    while trainer.iteration < schedule.iterations {
        let it = trainer.iteration;
        let stats = trainer.iterate().map_err(|e| match e {
            FitError::NonFinite { iteration, what, .. } => {
                let saved = std::fs::read_to_string(out.join(CHECKPOINT).join("state.json"))
                    .ok()
                    .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
                    .and_then(|state| state["iteration"].as_u64());
                let checkpoint = match saved {
                    Some(at) => format!("the last good checkpoint (iteration {at}) is kept in {}", out.join(CHECKPOINT).display()),
                    None => "no checkpoint had been written yet".into(),
                };
                FitError::NonFinite { iteration, what, checkpoint }
            }
            other => other,
        })?;
        *segment_seconds.entry(segment(&schedule, it, trainer.fit_light)).or_default() += stats.seconds;
        history.push((it, stats.clone()));
        on(TrainMessage::Step { iteration: it, stats });
        if trainer.iteration % schedule.checkpoint_every == 0 || trainer.iteration == schedule.iterations {
            save_checkpoint(&trainer, out, &history)?;
            on(TrainMessage::Checkpoint { iteration: trainer.iteration });
        }
    }
    let set = trainer.model()?.gaussians.to_set();
    set.save(&out.join("gaussians.json")).map_err(|e| io(&out.join("gaussians.json"), e))?;
    write_text(&out.join("losses.csv"), &losses_csv(&history))?;
    losses_chart(&history).render(800, 500).save_png(&out.join("losses.png")).map_err(|e| io(&out.join("losses.png"), e))?;
    let has_tests = trainer.scene.views_in(Split::Test).next().is_some();
    let evaluation = if options.evaluate && has_tests {
        evaluate(&trainer.scene, &trainer.fitted()?, out, &mut on)?
    } else if trainer.iteration == first_iteration_here {
        // Nothing was trained: the run's own evaluation (if any) still describes it.
        previous_evaluation(out)
    } else {
        // Renders and a report of fewer iterations would describe another fit.
        crate::run::clear_run_outputs(out, false)?;
        json!(null)
    };
    let evaluation_skipped = match (options.evaluate, has_tests) {
        (_, false) => Some("the scene has no test images (split \"test\"): nothing to evaluate"),
        (false, true) => Some("--no-eval"),
        (true, true) => None,
    };
    let model: &Avatar = trainer.model()?;
    let light = model.light.report();
    let mut stages = Vec::new();
    let density_hold = schedule.weights.get("density").map(|r| r.hold).unwrap_or(0.0);
    let seconds = |name: &str| Some(segment_seconds.get(name).copied().unwrap_or(0.0));
    let stage = |name: &str, ran: bool, from: Option<f64>| Stage { name: name.into(), ran, from, seconds: seconds(name), ..Stage::default() };
    stages.push(stage("density fitting", true, None));
    stages.push(stage("Gaussian fitting", schedule.weights["density"].ever_active(schedule.iterations), Some(density_hold)));
    let light_stage = if trainer.fit_light {
        stage("light and RGB fitting", schedule.iterations > schedule.light_from, Some(schedule.light_from as f64))
    } else {
        let why = if trainer.light_kind == LightKind::Uniform && schedule.light != crate::schedule::LightPolicy::Off {
            "every training image is uniformly lit: no light direction, no shadow rays; RGB fits the albedo directly"
        } else {
            "the schedule sets light = \"off\""
        };
        Stage { name: "light fitting".into(), skipped_because: Some(why.into()), iterations_saved: Some(saved), ..Stage::default() }
    };
    stages.push(light_stage);
    // Without a light the colour is still fitted after light_from: its time is accounted too.
    if !trainer.fit_light && schedule.iterations > schedule.light_from {
        stages.push(stage("RGB fitting", true, Some(schedule.light_from as f64)));
    }
    let last = history.last().map(|(_, s)| s.clone()).unwrap_or_default();
    // Each light search's start, with its own error against the scene's light when it has one.
    let searches: Vec<serde_json::Value> = trainer
        .searches
        .iter()
        .enumerate()
        .map(|(k, search)| match search {
            None => json!(null),
            Some(r) => {
                let mut value = serde_json::to_value(r).unwrap_or(json!(null));
                let start = match r.best.position {
                    Some(position) => json!({"position": position}),
                    None => json!({"direction": r.best.direction}),
                };
                value["error_against_scene"] = light_error(&trainer.scene, trainer.fit_light, k, &start);
                value
            }
        })
        .collect();
    let names = trainer.scene.training_lights();
    let by_name = |values: Vec<serde_json::Value>| -> serde_json::Map<String, serde_json::Value> { names.iter().map(|n| n.to_string()).zip(values).collect() };
    let reports: Vec<serde_json::Value> = (0..model.light_count()).map(|k| model.light_at(k).report()).collect();
    let errors: Vec<serde_json::Value> = reports.iter().enumerate().map(|(k, r)| light_error(&trainer.scene, trainer.fit_light, k, r)).collect();
    let light_error = errors.first().cloned().unwrap_or(json!(null));
    // One schedule serves every capture: with one camera the sun search is what keeps the
    // light from sliding behind the body (fit.json says which case this was).
    let training_cameras: std::collections::BTreeSet<usize> = trainer.scene.views_in(crate::scene::Split::Train).map(|v| v.camera).collect();
    let capture = json!({
        "pixel_footprint": {
            "modelled": trainer.footprint,
            "read_off_the_images": trainer.footprint_estimate,
        },
        // Rays drawn where the fit is wrong: the share of each batch's anywhere-third
        // (`Schedule::error_rays`; under `auto`, half for a loose body, none for a tight one).
        "error_rays": trainer.error_rays,
        // The Gaussians' density also fitted at the shadows' scale (`Schedule::density_at_shadow_scale`;
        // under `auto`, for a loose body alone).
        "density_at_shadow_scale": trainer.density_at_shadow_scale,
        // Gaussians seeded on the body the masks show beyond every bone (a loose body's root).
        "gaussians_on_loose_body": trainer.loose_gaussians(),
        "training_cameras": training_cameras.len(),
        "monocular": training_cameras.len() == 1,
        "light_start": match trainer.searches.first().and_then(|s| s.as_ref()) {
            Some(r) if r.best.position.is_some() => "point light search over directions and distances around the body, then gradient descent",
            Some(_) => "sun search over the sphere, then gradient descent within a cone around its best",
            None => "the schedule's initial light, then gradient descent",
        },
    });
    let report = FitReport {
        scene: std::fs::canonicalize(&options.scene).unwrap_or_else(|_| options.scene.clone()).display().to_string(),
        // The first training light under the one-light keys; every light by name after.
        light,
        lights: by_name(reports),
        stages,
        iterations: schedule.iterations,
        seed: options.seed,
        schedule: options.schedule.display().to_string(),
        backend: options.backend,
        threads: rayon::current_num_threads(),
        final_losses: last.terms,
        final_total: last.total,
        wall_seconds: wall.elapsed().as_secs_f64(),
        peak_memory_bytes: crate::files::peak_memory_bytes(),
        evaluation,
        evaluation_skipped: evaluation_skipped.map(String::from),
        light_error_against_scene: light_error,
        light_errors_against_scene: by_name(errors),
        sun_search: searches.first().cloned().unwrap_or(json!(null)),
        light_searches: by_name(searches),
        light_path: light_path(&trainer, &history),
        capture,
        field: field_report(&trainer),
    };
    report.write(&out.join("fit.json"))?;
    on(TrainMessage::Done);
    Ok(report)
}

/// Points of `light_path` over a whole fit (about).
const LIGHT_PATH_POINTS: usize = 50;

/// The first training light about `LIGHT_PATH_POINTS` times over the fit and after its last step (a
/// sun's direction or a point light's position, with its error against the scene's light when
/// the scene states it): where the light went, e.g. whether it settled or passed the truth on
/// its way to a biased rest. Empty when no light is fitted.
fn light_path(trainer: &Trainer, history: &[(usize, StepStats)]) -> serde_json::Value {
    let key = if trainer.light_kind == LightKind::Point { "position" } else { "direction" };
    let last = history.last().map(|(it, _)| *it);
    let every = (trainer.schedule.iterations / LIGHT_PATH_POINTS).max(1);
    let points: Vec<serde_json::Value> = history
        .iter()
        .filter(|(it, _)| (it + 1) % every == 0 || Some(*it) == last)
        .filter_map(|(it, stats)| {
            let location = json!({ key: stats.light? });
            let mut point = json!({"after_iteration": it + 1, key: location[key]});
            let error = light_error(&trainer.scene, trainer.fit_light, 0, &location);
            if !error.is_null() {
                point["error_against_scene"] = error;
            }
            Some(point)
        })
        .collect();
    json!(points)
}

/// The fitted field's kind and its VolSDF beta (m): how sharp its surface ended.
fn field_report(trainer: &Trainer) -> serde_json::Value {
    let Ok(model) = trainer.fitted_model() else { return serde_json::Value::Null };
    let beta = Some(crate::backend::host_scalar(model.field.beta())).filter(|b| b.is_finite());
    // Where the training masks put body beyond every bone's grid box (loose clothing), the
    // root's grids reach it: how far from the root's segment, m (null: a body tight on its bones).
    let root = model.field.grid.as_ref().and_then(|g| g.config.root);
    let loose = root.filter(|r| r.features_reach_body).map(|r| r.reach);
    // And the capsule prior stops at the root's cap (m, null: uncapped).
    let skinning = model.field.config.skinning();
    json!({"kind": if model.field.grid.is_some() { "grid" } else { "mlp" }, "beta": beta, "root_grids_reach_loose_body": loose, "prior_capped_at": skinning.prior_cap})
}
