//! A whole fit as the CLI runs it: the training loop with its outputs (`fit.json`,
//! `losses.csv`, `losses.png`, `gaussians.json`, renders), a checkpoint every N iterations
//! (written and read back by `run`), exact `--resume`, and the evaluation of the test images
//! at the end (rendered by `eval`).

use crate::avatar::Avatar;
use crate::backend::Backend;
use crate::fit_error::{io, FitError};
use crate::fit_report::{FitReport, Stage};
use crate::messages::{StepStats, TrainMessage};
use crate::plot::{Chart, Mark, Series};
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

mod record;

use record::{capture_report, field_report, light_path, light_searches, losses_chart, stages};

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
    check_out_folder(options)?;
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
    let first_iteration_here = trainer.iteration();
    crate::imageio::write_atomic(&out.join(SCHEDULE_COPY), schedule_text.as_bytes()).map_err(|e| io(&out.join(SCHEDULE_COPY), e))?;
    history.retain(|(i, _)| *i < trainer.iteration());
    let training_images = trainer.scene.views_in(Split::Train).count();
    on(TrainMessage::Loaded { scene: trainer.scene.display_name(), training_images, frames: trainer.scene.frames.len(), light: trainer.light_kind });
    on(TrainMessage::Started { first: trainer.iteration(), iterations: schedule.iterations });
    let segment_seconds = train(&mut trainer, &schedule, out, &mut history, &mut on)?;
    write_results(&trainer, out, &history)?;
    write_refined_motion(&trainer, out)?;
    write_refined_cameras(&trainer, out)?;
    let (evaluation, evaluation_skipped) = evaluation(&trainer, options, trainer.iteration() > first_iteration_here, &mut on)?;
    let model: &Avatar = trainer.model()?;
    let light = model.light.report();
    let stages = stages(&trainer, &schedule, &segment_seconds, saved);
    let last = history.last().map(|(_, s)| s.clone()).unwrap_or_default();
    let searches = light_searches(&trainer);
    let names = trainer.scene.training_lights();
    let by_name = |values: Vec<serde_json::Value>| -> serde_json::Map<String, serde_json::Value> { names.iter().map(|n| n.to_string()).zip(values).collect() };
    let reports: Vec<serde_json::Value> = (0..model.light_count()).map(|k| model.light_at(k).report()).collect();
    let errors: Vec<serde_json::Value> = reports.iter().enumerate().map(|(k, r)| light_error(&trainer.scene, trainer.fit_light, k, r)).collect();
    let light_error = errors.first().cloned().unwrap_or(json!(null));
    let capture = capture_report(&trainer);
    let report = FitReport {
        scene: std::fs::canonicalize(&options.scene).unwrap_or_else(|_| options.scene.clone()).display().to_string(),
        // The first training light under the one-light keys; every light by name after.
        light,
        lights: by_name(reports),
        stages,
        iterations: schedule.iterations,
        seed: options.seed,
        schedule: options.schedule.display().to_string(),
        backend: options.backend.to_string(),
        threads: rayon::current_num_threads(),
        final_losses: last.terms,
        final_total: last.total,
        wall_seconds: wall.elapsed().as_secs_f64(),
        peak_memory_bytes: crate::files::peak_memory_bytes(),
        peak_device_memory_bytes: history.iter().filter_map(|(_, stats)| stats.device_memory_bytes).max(),
        evaluation,
        evaluation_skipped,
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

/// The fitted Gaussians, the losses as a table and as a chart.
fn write_results(trainer: &Trainer, out: &Path, history: &[(usize, StepStats)]) -> Result<(), FitError> {
    let set = trainer.model()?.gaussians.to_set();
    set.save(&out.join("gaussians.json")).map_err(|e| io(&out.join("gaussians.json"), e))?;
    write_text(&out.join("losses.csv"), &losses_csv(history))?;
    losses_chart(history, &trainer.schedule, trainer.fit_light).render(900, 520).save_png(&out.join("losses.png")).map_err(|e| io(&out.join("losses.png"), e))
}

/// The training motion as the fit refined it (`train::motion`), as a BVH of the scene's bones
/// (an imported capture's joints), one frame per training frame in time order: in the capture's
/// units and world when `umbra import` wrote the scene (`Scene::capture`), else in metres in
/// the scene's; nothing when the fit does not refine the motion.
fn write_refined_motion(trainer: &Trainer, out: &Path) -> Result<(), FitError> {
    let Some(motion) = trainer.state()?.motion.as_ref().filter(|_| trainer.motion_moved().is_some()) else { return Ok(()) };
    let path = out.join(crate::run::REFINED_MOTION);
    let text = motion_bvh(&trainer.scene, &motion.refined(&trainer.scene)).map_err(|e| io(&path, e))?;
    write_text(&path, &text)
}

/// The training cameras as the fit refined them (`train::camera_pose`), as nerfstudio's
/// `transforms.json` of the training images (their paths in the scene's folder): in the
/// capture's units and world when `umbra import` wrote the scene, else in metres in the
/// scene's; nothing when the fit does not refine the cameras.
fn write_refined_cameras(trainer: &Trainer, out: &Path) -> Result<(), FitError> {
    if trainer.cameras_moved().is_none() {
        return Ok(());
    }
    let path = out.join(crate::run::REFINED_CAMERAS);
    let text = serde_json::to_string_pretty(&cameras_transforms(&trainer.scene, &trainer.corrected_cameras())).map_err(|e| io(&path, e))?;
    write_text(&path, &text)
}

/// The training images of `scene` seen through `cameras` (one per scene camera) as nerfstudio's
/// `transforms.json`, in the capture's units and world when the scene has one.
pub fn cameras_transforms(scene: &crate::scene::Scene, cameras: &[crate::scene::Camera]) -> serde_json::Value {
    let (to_capture, units) = match &scene.capture {
        Some(capture) => (capture.to_scene.inverse(), 1.0 / capture.metres_per_unit),
        None => (glam::DMat4::IDENTITY, 1.0),
    };
    let seen: Vec<crate::scene::Camera> =
        cameras.iter().map(|c| crate::scene::Camera { camera_to_world: to_capture * c.camera_to_world, ..c.clone() }).collect();
    let train: Vec<usize> = (0..scene.views.len()).filter(|&k| scene.views[k].split == Split::Train).collect();
    let name = |k: usize| {
        let path = &scene.views[k].path;
        (path.strip_prefix(&scene.root).unwrap_or(path).to_string_lossy().into_owned(), None)
    };
    let times: Vec<Option<f64>> = scene.frames.iter().map(|f| f.time).collect();
    let mut transforms = crate::capture::nerfstudio::write(scene, &seen, &train, units, 1.0, name);
    // Each image's time as the scene states it (the writer's is its frame's index).
    if let Some(frames) = transforms["frames"].as_array_mut() {
        for (frame, &k) in frames.iter_mut().zip(&train) {
            match times.get(scene.views[k].frame).copied().flatten() {
                Some(time) => frame["time"] = serde_json::json!(time),
                None => frame["time"] = serde_json::json!(scene.views[k].frame),
            }
        }
    }
    transforms
}

/// `poses` (scene frames with a pose each, in time order) as a BVH of the scene's bones: in the
/// capture's units and world when `umbra import` wrote the scene (`Scene::capture`), else in
/// metres in the scene's; the frames evenly spaced by their mean spacing in time (a thirtieth
/// of a second when they have no times).
pub fn motion_bvh(scene: &crate::scene::Scene, poses: &[(usize, crate::skeleton::Pose)]) -> Result<String, String> {
    let (to_capture, units) = match &scene.capture {
        Some(capture) => (capture.to_scene.inverse(), 1.0 / capture.metres_per_unit),
        None => (glam::DMat4::IDENTITY, 1.0),
    };
    let frames: Vec<Vec<glam::DMat4>> = poses.iter().map(|(_, pose)| pose.bone_to_world.iter().map(|m| to_capture * *m).collect()).collect();
    let times: Vec<f64> = poses.iter().filter_map(|(f, _)| scene.frames.get(*f).and_then(|frame| frame.time)).collect();
    let frame_time = match (times.len() == poses.len() && times.len() > 1, times.first(), times.last()) {
        (true, Some(first), Some(last)) if last > first => (last - first) / (times.len() - 1) as f64,
        _ => 1.0 / 30.0,
    };
    crate::capture::bvh::write(&scene.skeleton, &frames, frame_time, units)
}

/// The fit's evaluation on the scene's test images (fit.json's `evaluation`), or why there is
/// none. A run that trained nothing keeps its own; one that trained without evaluating loses
/// the renders and report of its fewer iterations, which would describe another fit.
fn evaluation(
    trainer: &Trainer,
    options: &FitOptions,
    trained: bool,
    on: &mut impl FnMut(TrainMessage),
) -> Result<(serde_json::Value, Option<String>), FitError> {
    let out = &options.out;
    let has_tests = trainer.scene.views_in(Split::Test).next().is_some();
    let evaluation = if options.evaluate && has_tests {
        evaluate(&trainer.shown_scene(), &trainer.fitted()?, out, on)?
    } else if !trained {
        previous_evaluation(out)
    } else {
        crate::run::clear_run_outputs(out, false)?;
        json!(null)
    };
    let skipped = match (options.evaluate, has_tests) {
        (_, false) => Some("the scene has no test images (split \"test\"): nothing to evaluate"),
        (false, true) => Some("--no-eval"),
        (true, true) => None,
    };
    Ok((evaluation, skipped.map(String::from)))
}

/// Refuses an `--out` that a fit must not write into, before anything is written.
fn check_out_folder(options: &FitOptions) -> Result<(), FitError> {
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
    Ok(())
}

/// Trains from the trainer's iteration to the schedule's last, checkpointing as the schedule
/// says; returns the seconds spent in each of the schedule's segments.
fn train(
    trainer: &mut Trainer,
    schedule: &Schedule,
    out: &Path,
    history: &mut Vec<(usize, StepStats)>,
    on: &mut impl FnMut(TrainMessage),
) -> Result<BTreeMap<&'static str, f64>, FitError> {
    let mut segment_seconds: BTreeMap<&'static str, f64> = BTreeMap::new();
    while trainer.iteration() < schedule.iterations {
        let it = trainer.iteration();
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
        *segment_seconds.entry(segment(schedule, it, trainer.fit_light)).or_default() += stats.seconds;
        history.push((it, stats.clone()));
        on(TrainMessage::Step { iteration: it, stats });
        if trainer.iteration() % schedule.checkpoint_every == 0 || trainer.iteration() == schedule.iterations {
            save_checkpoint(trainer, out, history)?;
            on(TrainMessage::Checkpoint { iteration: trainer.iteration() });
        }
    }
    Ok(segment_seconds)
}
