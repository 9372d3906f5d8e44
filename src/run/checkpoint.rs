//! A run's checkpoint: written atomically with its checksums, verified against the scene and
//! the schedule it was fitted with, and loaded to resume a fit.

use super::*;
use crate::fit_error::{io, FitError};
use crate::messages::StepStats;
use crate::random::Stream;
use crate::scene::identity::file_checksum;
use crate::scene::Scene;
use crate::train::Trainer;
use burn::module::Module;
use serde_json::json;
use std::path::{Path, PathBuf};

pub(crate) fn save_checkpoint(trainer: &Trainer, out: &Path, history: &[(usize, StepStats)]) -> Result<(), FitError> {
    save_checkpoint_until(trainer, out, history, usize::MAX).map(|_| ())
}

/// `save_checkpoint` stopped after its first `steps` file-system steps, as a kill there
/// would leave the run folder (for the test that interrupts it at every step); returns whether
/// it finished.
#[doc(hidden)]
pub fn save_checkpoint_until(trainer: &Trainer, out: &Path, history: &[(usize, StepStats)], steps: usize) -> Result<bool, FitError> {
    let mut done = 0usize;
    // One step taken; true when the budget is spent (the "kill").
    let mut step = || {
        done += 1;
        done >= steps
    };
    let temp = out.join(".checkpoint.tmp");
    let _ = std::fs::remove_dir_all(&temp);
    if step() {
        return Ok(false);
    }
    std::fs::create_dir_all(&temp).map_err(|e| io(&temp, e))?;
    if step() {
        return Ok(false);
    }
    // `model.bpk` is the fitted model (what renders and evaluations load); while the field's
    // parameters are averaged, the last step's, which training resumes from, go beside it.
    trainer.fitted_model()?.save_file(temp.join("model.bpk")).map_err(|e| io(&temp.join("model.bpk"), format!("{e}")))?;
    if trainer.state()?.average.is_some() {
        trainer.model()?.clone().save_file(temp.join(TRAINING_MODEL)).map_err(|e| io(&temp.join(TRAINING_MODEL), format!("{e}")))?;
    }
    if step() {
        return Ok(false);
    }
    for (name, optimizer) in trainer.state()?.optimisers.named() {
        let path = temp.join(format!("optimizer-{name}.bpk"));
        optimizer.save(&path).map_err(|e| io(&path, format!("{e}")))?;
        if step() {
            return Ok(false);
        }
    }
    let mut checksums = serde_json::Map::new();
    for file in checkpoint_files(trainer) {
        let sum = file_checksum(&temp.join(&file)).map_err(|e| io(&temp.join(&file), e))?;
        checksums.insert(file, json!(sum));
    }
    // The sun search and its cone are part of the state: a resumed fit keeps the same cone.
    // The scene's identity and the files' checksums let a load refuse another scene's run or
    // a damaged file.
    let state = json!({
        "skeleton": trainer.scene.skeleton_identity(),
        "training_data": trainer.training_identity(),
        "checksums": checksums,
        "iteration": trainer.iteration(),
        "seed": trainer.seed,
        "iterations_total": trainer.schedule.iterations,
        "stream": trainer.stream.state().to_string(),
        // The first light's search and cone under their one-light keys, the others' after.
        "sun_search": trainer.searches.first().cloned().flatten(),
        "sun_cone": cone_json(trainer.cones.first().copied().flatten()),
        "light_searches": trainer.searches.iter().skip(1).collect::<Vec<_>>(),
        "light_cones": trainer.cones.iter().skip(1).map(|c| cone_json(*c)).collect::<Vec<_>>(),
        "albedo_layers": trainer.model()?.field.config.albedo_layers,
        "field": trainer.model()?.field.config,
        "gaussian_bones": trainer.model()?.gaussians.bones,
        "error_maps": trainer.error_maps().into_iter().map(|(view, errors)| json!({"view": view, "errors": errors})).collect::<Vec<_>>(),
        "camera_colours": trainer.camera_colours_json(),
        "motion": trainer.motion_json(),
        "cameras": trainer.cameras_json(),
    });
    write_text(&temp.join("state.json"), &state.to_string())?;
    let sum = file_checksum(&temp.join("state.json")).map_err(|e| io(&temp.join("state.json"), e))?;
    write_text(&temp.join(STATE_CHECKSUM), &sum)?;
    if step() {
        return Ok(false);
    }
    write_text(&temp.join("losses.csv"), &losses_csv(history))?;
    if step() {
        return Ok(false);
    }
    // Some complete checkpoint is on disk at every moment: the previous one is set aside (and
    // an older one set aside before deleted) only while a complete one sits in `checkpoint/`,
    // and a kill between the two renames leaves `.checkpoint.old`, which `existing_checkpoint`
    // finds.
    let target = out.join(CHECKPOINT);
    let old = out.join(OLD_CHECKPOINT);
    if target.join("state.json").is_file() {
        let _ = std::fs::remove_dir_all(&old);
        if step() {
            return Ok(false);
        }
        std::fs::rename(&target, &old).map_err(|e| io(&target, e))?;
    } else {
        let _ = std::fs::remove_dir_all(&target);
    }
    if step() {
        return Ok(false);
    }
    std::fs::rename(&temp, &target).map_err(|e| io(&target, e))?;
    if step() {
        return Ok(false);
    }
    let _ = std::fs::remove_dir_all(&old);
    Ok(true)
}

/// The last step's parameters in a checkpoint whose `model.bpk` holds the field's average.
pub(super) const TRAINING_MODEL: &str = "training-model.bpk";

/// The files of a checkpoint that hold parameters: the model (and the last step's, while the
/// field is averaged) and one per optimizer.
pub(super) fn checkpoint_files(trainer: &Trainer) -> Vec<String> {
    let averaged = trainer.state().is_ok_and(|s| s.average.is_some());
    let training = averaged.then(|| TRAINING_MODEL.to_string());
    // The optimisers are named after the parameter groups (`Optimisers::named`).
    std::iter::once("model.bpk".to_string()).chain(training).chain(crate::schedule::GROUPS.iter().map(|name| format!("optimizer-{name}.bpk"))).collect()
}

/// The checksum of a checkpoint's `state.json`, beside it: state.json holds the others.
pub(super) const STATE_CHECKSUM: &str = "state.checksum";

/// A checkpoint's `state.json`, read bounded and checked against the checksum beside it (a
/// checkpoint that records its files' checksums must have one for its state too), with the
/// types of the keys that guard a load: an edited or damaged state is refused, not trusted.
pub(crate) fn read_state(dir: &Path) -> Result<serde_json::Value, FitError> {
    let state_path = dir.join("state.json");
    let text = crate::files::read_text(&state_path, crate::files::STATE_BYTES).map_err(|e| io(&state_path, format!("cannot read the checkpoint: {e}")))?;
    let state: serde_json::Value = serde_json::from_str(&text).map_err(|e| io(&state_path, e))?;
    if !state.is_object() {
        return Err(io(&state_path, "not a checkpoint's state (expected a JSON object)"));
    }
    let sum_path = dir.join(STATE_CHECKSUM);
    match crate::files::read_text(&sum_path, 256) {
        Ok(expected) => {
            let found = file_checksum(&state_path).map_err(|e| io(&state_path, e))?;
            if found != expected.trim() {
                return Err(io(
                    &state_path,
                    format!("checksum {found} differs from {} recorded in {STATE_CHECKSUM}: the file is damaged or was edited", expected.trim()),
                ));
            }
        }
        Err(_) if state.get("checksums").is_some() => {
            return Err(io(
                &sum_path,
                "missing or unreadable: a checkpoint that records its files' checksums records its state's too; the checkpoint is incomplete",
            ));
        }
        // Checkpoints from before checksums were recorded.
        Err(_) => {}
    }
    for key in ["skeleton", "training_data", "stream"] {
        if state.get(key).is_some_and(|v| !v.is_string()) {
            return Err(io(&state_path, format!("{key}: expected a string, found {}", state[key])));
        }
    }
    if state.get("checksums").is_some_and(|v| !v.is_object()) {
        return Err(io(&state_path, "checksums: expected an object of file names to checksums"));
    }
    Ok(state)
}

/// Reads a checkpoint's `state.json` and checks it against `scene` (the skeleton, and the
/// training data when `resuming`) and the checksums of the files it lists. Checkpoints written
/// before these were recorded pass unchecked.
pub(super) fn verified_state(dir: &Path, scene: &Scene, training_identity: Option<&str>) -> Result<serde_json::Value, FitError> {
    let state_path = dir.join("state.json");
    let state = read_state(dir)?;
    let scene_file = crate::scene::scene_file(&scene.root);
    if let Some(skeleton) = state["skeleton"].as_str() {
        if skeleton != scene.skeleton_identity() {
            return Err(io(
                &state_path,
                format!("skeleton: this run was fitted on another skeleton than {}'s (bone names, parents or lengths differ)", scene_file.display()),
            ));
        }
    }
    if let Some(identity) = training_identity {
        if let Some(data) = state["training_data"].as_str() {
            if !scene.is_training_identity(data, identity) {
                return Err(io(
                    &state_path,
                    format!(
                        "training_data: this run was fitted on other training images, cameras or poses than {}'s: resume it on its own scene",
                        scene_file.display()
                    ),
                ));
            }
        }
    }
    if let Some(sums) = state["checksums"].as_object() {
        for (file, expected) in sums {
            let path = dir.join(file);
            let found = file_checksum(&path).map_err(|e| io(&path, format!("listed in the checkpoint but unreadable: {e}")))?;
            if Some(found.as_str()) != expected.as_str() {
                return Err(io(
                    &path,
                    format!("checksum {found} differs from {} recorded in state.json: the file is damaged", expected.as_str().unwrap_or("?")),
                ));
            }
        }
    }
    Ok(state)
}

/// Sets `settings` to the field a run's checkpoint was fitted with, so that a run is rebuilt as
/// it was fitted whatever today's defaults: `state.json` records the whole field. A checkpoint
/// from before that records at most its albedo decoder's depth (none: it shared the SDF's
/// decoder) and predates the root's skinning. Nothing changes without a readable checkpoint
/// (its loading reports that).
pub(crate) fn apply_recorded_field(run: &Path, bones: usize, settings: &mut crate::schedule::FieldSettings) -> Result<(), FitError> {
    let Some(checkpoint) = existing_checkpoint(run) else { return Ok(()) };
    let state_path = checkpoint.join("state.json");
    let state = read_state(&checkpoint)?;
    if let Some(field) = state.get("field") {
        let config: crate::field::FieldConfig = serde_json::from_value(field.clone()).map_err(|e| io(&state_path, format!("field: {e}")))?;
        config.check(bones).map_err(|e| io(&state_path, format!("field.{e}")))?;
        settings.recorded = Some(config);
        return Ok(());
    }
    settings.root_skinning = Some(false);
    settings.albedo_layers = Some(match state.get("albedo_layers") {
        None => 0,
        Some(value) => {
            value.as_u64().filter(|&n| n <= 4).ok_or_else(|| io(&state_path, format!("albedo_layers: expected a whole number up to 4, found {value}")))?
                as usize
        }
    });
    Ok(())
}

/// The run's last complete checkpoint folder: `checkpoint/`, or the one an interrupted swap
/// left aside.
pub fn existing_checkpoint(out: &Path) -> Option<PathBuf> {
    [CHECKPOINT, OLD_CHECKPOINT].iter().map(|name| out.join(name)).find(|dir| dir.join("state.json").is_file())
}

/// Resumes `trainer` from the last complete checkpoint in the run folder `out`, as `umbra fit
/// --resume` does (the entry the checkpoint fuzz target drives); returns the iteration reached.
pub fn resume_checkpoint(trainer: &mut Trainer, out: &Path) -> Result<usize, FitError> {
    load_checkpoint(trainer, out)?;
    Ok(trainer.iteration())
}

pub(crate) fn load_checkpoint(trainer: &mut Trainer, out: &Path) -> Result<Vec<(usize, StepStats)>, FitError> {
    let dir = existing_checkpoint(out).ok_or_else(|| io(out, "holds no checkpoint to resume"))?;
    let state_path = dir.join("state.json");
    let state = verified_state(&dir, &trainer.scene, Some(trainer.training_identity()))?;
    let iteration = state["iteration"].as_u64().ok_or_else(|| io(&state_path, "iteration: missing"))? as usize;
    let stream: u64 = state["stream"].as_str().and_then(|s| s.parse().ok()).ok_or_else(|| io(&state_path, "stream: missing"))?;
    load_model(trainer, &dir)?;
    // A checkpoint taken while the field was averaged: `model.bpk` holds the average, the
    // last step's parameters are beside it.
    let training = trainer.state_mut()?;
    training.average = None;
    if dir.join(TRAINING_MODEL).is_file() {
        let fitted = training.model.clone();
        training.average = Some(crate::averaging::ParameterAverage::start(&fitted.field));
        let path = dir.join(TRAINING_MODEL);
        training.model = fitted.try_load_file(&path).map_err(|e| io(&path, format!("cannot load the model being trained: {e}")))?;
    }
    for (name, optimizer) in training.optimisers.named_mut() {
        let path = dir.join(format!("optimizer-{name}.bpk"));
        // Checkpoints from before the feature tables had their own optimizer have no file for it.
        if name == "features" && !path.exists() {
            continue;
        }
        *optimizer = optimizer.clone().load(&path).map_err(|e| io(&path, format!("{e}")))?;
    }
    trainer.set_iteration(iteration)?;
    trainer.stream = Stream::from_state(stream);
    let lights = trainer.cones.len();
    let mut searches = vec![serde_json::from_value(state["sun_search"].clone()).map_err(|e| io(&state_path, format!("sun_search: {e}")))?];
    let mut cones = vec![parse_cone(&state["sun_cone"], &state_path, "sun_cone")?];
    // Checkpoints from before several lights could be fitted have neither list.
    let others = |key: &str| state[key].as_array().cloned().unwrap_or_default();
    for (k, value) in others("light_searches").iter().enumerate() {
        searches.push(serde_json::from_value(value.clone()).map_err(|e| io(&state_path, format!("light_searches[{k}]: {e}")))?);
    }
    for (k, value) in others("light_cones").iter().enumerate() {
        cones.push(parse_cone(value, &state_path, &format!("light_cones[{k}]"))?);
    }
    if searches.len() != lights || cones.len() != lights {
        return Err(io(
            &state_path,
            format!(
                "light_searches, light_cones: the checkpoint holds {} training lights' searches and {} cones, the scene has {lights} training lights",
                searches.len(),
                cones.len()
            ),
        ));
    }
    trainer.searches = searches;
    trainer.cones = cones;
    // Checkpoints from before the error maps, or of fits without them, have none.
    let mut maps = Vec::new();
    for (k, entry) in state["error_maps"].as_array().cloned().unwrap_or_default().into_iter().enumerate() {
        let view = entry["view"].as_u64().ok_or_else(|| io(&state_path, format!("error_maps[{k}].view: missing")))? as usize;
        let errors: Vec<f32> = serde_json::from_value(entry["errors"].clone()).map_err(|e| io(&state_path, format!("error_maps[{k}].errors: {e}")))?;
        maps.push((view, errors));
    }
    trainer.set_error_maps(maps).map_err(|e| io(&state_path, format!("error_maps: {e}")))?;
    // Checkpoints from before the cameras' colours were learned have none: they start at 1.
    let colours = state.get("camera_colours").cloned().unwrap_or(serde_json::Value::Null);
    trainer.restore_camera_colours(&colours).map_err(|e| io(&state_path, format!("camera_colours: {e}")))?;
    // Checkpoints from before the motion was refined have none: the given motion.
    let motion = state.get("motion").cloned().unwrap_or(serde_json::Value::Null);
    trainer.restore_motion(&motion).map_err(|e| io(&state_path, format!("motion: {e}")))?;
    // Checkpoints from before the cameras were refined have none: the given poses.
    let cameras = state.get("cameras").cloned().unwrap_or(serde_json::Value::Null);
    trainer.restore_cameras(&cameras).map_err(|e| io(&state_path, format!("cameras: {e}")))?;
    let csv = crate::files::read_text(&dir.join("losses.csv"), crate::files::STATE_BYTES).map_err(|e| io(&dir.join("losses.csv"), e))?;
    Ok(parse_losses_csv(&csv))
}

pub(super) fn cone_json(cone: Option<(glam::DVec3, f64)>) -> serde_json::Value {
    cone.map_or(json!(null), |(axis, angle)| json!({"axis": axis.to_array(), "angle_radians": angle}))
}

/// A sun's cone from a checkpoint's `state.json` (`key` names it in errors); null: none.
pub(super) fn parse_cone(cone: &serde_json::Value, state_path: &Path, key: &str) -> Result<Option<(glam::DVec3, f64)>, FitError> {
    if cone.is_null() {
        return Ok(None);
    }
    let axis: [f64; 3] = serde_json::from_value(cone["axis"].clone()).map_err(|e| io(state_path, format!("{key}.axis: {e}")))?;
    let angle = cone["angle_radians"]
        .as_f64()
        .filter(|a| a.is_finite() && *a >= 0.0)
        .ok_or_else(|| io(state_path, format!("{key}.angle_radians: missing or not a finite angle")))?;
    if !axis.iter().all(|c| c.is_finite()) || glam::DVec3::from_array(axis).length() < 1e-9 {
        return Err(io(state_path, format!("{key}.axis: not a finite non-zero vector")));
    }
    Ok(Some((glam::DVec3::from_array(axis), angle)))
}

/// Replaces the trainer's model by the one saved in checkpoint folder `dir`.
pub(super) fn load_model(trainer: &mut Trainer, dir: &Path) -> Result<(), FitError> {
    let state_path = dir.join("state.json");
    let state = read_state(dir)?;
    // A loose body fitted before Gaussians were seeded on it has only the bones' Gaussians.
    let recorded = state.get("gaussian_bones").and_then(|b| b.as_array()).map(|b| b.len());
    let starts = trainer.model()?.gaussians.len();
    if let Some(count) = recorded.filter(|&n| trainer.loose_gaussians() > 0 && n < starts) {
        trainer.without_loose_gaussians(count).map_err(|e| io(&state_path, format!("gaussian_bones: {e}")))?;
    }
    let model = trainer.model()?.clone();
    let model = model.try_load_file(dir.join("model.bpk")).map_err(|e| io(&dir.join("model.bpk"), format!("cannot load the fitted model: {e}")))?;
    *trainer.model_mut()? = model;
    // The Gaussians' bones, when the fit moved them (`Trainer::rebind_gaussians`); before they
    // were recorded, each stayed on the bone it started on.
    if let Some(bones) = state.get("gaussian_bones") {
        let bones: Vec<usize> = serde_json::from_value(bones.clone()).map_err(|e| io(&state_path, format!("gaussian_bones: {e}")))?;
        trainer.set_gaussian_bones(&bones).map_err(|e| io(&state_path, format!("gaussian_bones: {e}")))?;
    }
    Ok(())
}
