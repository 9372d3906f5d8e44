//! The run folder: where a fit's checkpoint lives and how it is written (atomically, swapped
//! in whole) and read back (verified against the scene and schedule it came from), the model
//! restored from it for rendering, the losses it records, and the images written into it.
//! Below every command that reads a run (fit, eval, relight, report, export).

use crate::avatar::{Avatar, Fitted};
use crate::fit_error::{io, FitError};
use crate::messages::StepStats;
use crate::random::Stream;
use crate::scene::identity::file_checksum;
use crate::scene::Scene;
use crate::schedule::Schedule;
use crate::shading::LightKind;
use crate::train::Trainer;
use burn::module::Module;
use serde_json::json;
use std::path::{Path, PathBuf};

pub const CHECKPOINT: &str = "checkpoint";

/// Where the previous checkpoint waits while a new one is swapped in.
pub(crate) const OLD_CHECKPOINT: &str = ".checkpoint.old";

/// The schedule a run was fitted with, copied into the run (rendering rebuilds the model
/// from it; the original file may have moved).
pub const SCHEDULE_COPY: &str = "schedule.toml";

/// What a run's report writes into the run folder.
pub const REPORT_FILES: [&str; 3] = ["report.html", "report.md", "report-relit.png"];

/// What a fit writes beside its checkpoint (besides the evaluation's folders and the report).
pub const FIT_FILES: [&str; 4] = ["fit.json", "gaussians.json", "losses.csv", "losses.png"];

/// The folders an evaluation renders into.
pub const RENDER_FOLDERS: [&str; 2] = ["renders", "renders-train"];

/// Removes from `dir` what an earlier evaluation wrote there (the images its `metrics.csv`
/// lists with their albedos, `compare.png`, `metrics.*`), and `dir` itself when that leaves it
/// empty: another scene's or an earlier fit's renders must not stand beside a new table. Any
/// other file, a user's, stays.
pub fn clear_renders(dir: &Path) -> Result<(), FitError> {
    let listed = crate::files::read_text(&dir.join("metrics.csv"), crate::files::STATE_BYTES)
        .ok()
        .and_then(|text| crate::table::read_csv(&text).ok())
        .map(|(_, rows)| rows.into_iter().filter_map(|row| row.into_iter().next()).collect::<Vec<String>>())
        .unwrap_or_default();
    // A render's name is one plain file name (`render_name`); anything else is not ours.
    let plain = |name: &String| !name.is_empty() && !name.starts_with('.') && !name.contains(['/', '\\']) && name.ends_with(".png");
    let renders = listed.iter().filter(|n| plain(n)).flat_map(|n| [n.clone(), n.replace(".png", "-albedo.png")]);
    let own = ["compare.png", "metrics.csv", "metrics.md", "metrics.json"].map(String::from);
    for name in renders.chain(own) {
        let path = dir.join(&name);
        if std::fs::symlink_metadata(&path).is_ok_and(|m| m.is_file()) {
            std::fs::remove_file(&path).map_err(|e| io(&path, e))?;
        }
    }
    let _ = std::fs::remove_dir(dir);
    Ok(())
}

/// Removes what an earlier fit's evaluation and report left in `run` (its renders, report,
/// and with `fit_outputs` also fit.json, gaussians.json and the losses), so that a fit that
/// replaces it or ends without evaluating leaves nothing that describes another fit.
pub fn clear_run_outputs(run: &Path, fit_outputs: bool) -> Result<(), FitError> {
    for folder in RENDER_FOLDERS {
        clear_renders(&run.join(folder))?;
    }
    let files = REPORT_FILES.iter().chain(if fit_outputs { FIT_FILES.iter() } else { [].iter() });
    for name in files {
        let path = run.join(name);
        if path.is_file() {
            std::fs::remove_file(&path).map_err(|e| io(&path, e))?;
        }
    }
    Ok(())
}

pub(crate) fn write_text(path: &Path, text: &str) -> Result<(), FitError> {
    crate::imageio::write_atomic(path, text.as_bytes()).map_err(|e| io(path, e))
}

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
    if trainer.average.is_some() {
        trainer.model()?.clone().save_file(temp.join(TRAINING_MODEL)).map_err(|e| io(&temp.join(TRAINING_MODEL), format!("{e}")))?;
    }
    if step() {
        return Ok(false);
    }
    for (name, optimizer) in trainer.optimisers.named() {
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
        "iteration": trainer.iteration,
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
const TRAINING_MODEL: &str = "training-model.bpk";

/// The files of a checkpoint that hold parameters: the model (and the last step's, while the
/// field is averaged) and one per optimizer.
fn checkpoint_files(trainer: &Trainer) -> Vec<String> {
    let training = trainer.average.is_some().then(|| TRAINING_MODEL.to_string());
    std::iter::once("model.bpk".to_string())
        .chain(training)
        .chain(trainer.optimisers.named().into_iter().map(|(name, _)| format!("optimizer-{name}.bpk")))
        .collect()
}

/// The checksum of a checkpoint's `state.json`, beside it: state.json holds the others.
const STATE_CHECKSUM: &str = "state.checksum";

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
fn verified_state(dir: &Path, scene: &Scene, training_identity: Option<&str>) -> Result<serde_json::Value, FitError> {
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
        // A run fitted with the removed knee in its capped prior cannot be rebuilt as it was.
        if field["grid"]["root"]["prior_knee"] == serde_json::Value::Bool(true) {
            return Err(io(
                &state_path,
                "field.grid.root.prior_knee: this run was fitted with [field] prior_knee, which was removed (docs/measurements.md): fit it again",
            ));
        }
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
    Ok(trainer.iteration)
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
    trainer.average = None;
    if dir.join(TRAINING_MODEL).is_file() {
        let fitted = trainer.model.take().ok_or_else(|| FitError::Input("no model".into()))?;
        trainer.average = Some(crate::averaging::ParameterAverage::start(&fitted.field));
        let path = dir.join(TRAINING_MODEL);
        trainer.model = Some(fitted.try_load_file(&path).map_err(|e| io(&path, format!("cannot load the model being trained: {e}")))?);
    }
    for (name, optimizer) in trainer.optimisers.named_mut() {
        let path = dir.join(format!("optimizer-{name}.bpk"));
        // Checkpoints from before the feature tables had their own optimizer have no file for it.
        if name == "features" && !path.exists() {
            continue;
        }
        *optimizer = optimizer.clone().load(&path).map_err(|e| io(&path, format!("{e}")))?;
    }
    trainer.iteration = iteration;
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
    let csv = crate::files::read_text(&dir.join("losses.csv"), crate::files::STATE_BYTES).map_err(|e| io(&dir.join("losses.csv"), e))?;
    Ok(parse_losses_csv(&csv))
}

fn cone_json(cone: Option<(glam::DVec3, f64)>) -> serde_json::Value {
    cone.map_or(json!(null), |(axis, angle)| json!({"axis": axis.to_array(), "angle_radians": angle}))
}

/// A sun's cone from a checkpoint's `state.json` (`key` names it in errors); null: none.
fn parse_cone(cone: &serde_json::Value, state_path: &Path, key: &str) -> Result<Option<(glam::DVec3, f64)>, FitError> {
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
fn load_model(trainer: &mut Trainer, dir: &Path) -> Result<(), FitError> {
    let state_path = dir.join("state.json");
    let state = read_state(dir)?;
    // A loose body fitted before Gaussians were seeded on it has only the bones' Gaussians.
    let recorded = state.get("gaussian_bones").and_then(|b| b.as_array()).map(|b| b.len());
    let starts = trainer.model()?.gaussians.len();
    if let Some(count) = recorded.filter(|&n| trainer.loose_gaussians() > 0 && n < starts) {
        trainer.without_loose_gaussians(count).map_err(|e| io(&state_path, format!("gaussian_bones: {e}")))?;
    }
    let model = trainer.model.take().ok_or_else(|| FitError::Input("no model".into()))?;
    let model = model.try_load_file(dir.join("model.bpk")).map_err(|e| io(&dir.join("model.bpk"), format!("cannot load the fitted model: {e}")))?;
    trainer.model = Some(model);
    // The Gaussians' bones, when the fit moved them (`Trainer::rebind_gaussians`); before they
    // were recorded, each stayed on the bone it started on.
    if let Some(bones) = state.get("gaussian_bones") {
        let bones: Vec<usize> = serde_json::from_value(bones.clone()).map_err(|e| io(&state_path, format!("gaussian_bones: {e}")))?;
        trainer.set_gaussian_bones(&bones).map_err(|e| io(&state_path, format!("gaussian_bones: {e}")))?;
    }
    Ok(())
}

/// A finished (or checkpointed) run as `restore` rebuilds it: the scene it is rendered on, its
/// schedule copy and the fitted avatar.
pub struct FittedRun {
    pub scene: Scene,
    pub schedule: Schedule,
    pub fitted: Fitted,
}

/// A run rebuilt from its folder (its schedule copy and last checkpoint), on the scene it was
/// fitted on (from `fit.json`) or on `scene`: the avatar's shape from what the checkpoint
/// records (the field, the Gaussians' bones), its parameters from `model.bpk`. Nothing of the
/// training (optimisers, error maps, the body's analysis) is rebuilt.
pub fn restore(run: &Path, scene: Option<&Path>, backend: crate::backend::Backend) -> Result<FittedRun, FitError> {
    if !run.join(SCHEDULE_COPY).is_file() {
        let what = if run.is_dir() { "is not an umbra run (it has no schedule.toml)" } else { "does not exist" };
        return Err(io(run, format!("{what}: name the --out folder of an `umbra fit`")));
    }
    let mut schedule = Schedule::load(&run.join(SCHEDULE_COPY))?;
    let scene_path = match scene {
        Some(path) => path.to_path_buf(),
        None => recorded_scene(run)?,
    };
    let scene = Scene::load(&scene_path)?;
    apply_recorded_field(run, scene.skeleton.len(), &mut schedule.field)?;
    let checkpoint = existing_checkpoint(run).ok_or_else(|| io(run, "holds no checkpoint"))?;
    let state = verified_state(&checkpoint, &scene, None)?;
    let state_path = checkpoint.join("state.json");
    let lights = crate::train::training_lights(&scene, &schedule)?;
    let device = backend.device();
    device.seed(0);
    let extent = scene.body_extent();
    // The field is recorded (or predates the root's skinning): the masks are never searched.
    let config = crate::train::field_config(&schedule.field, &scene.skeleton, extent as f32, |_, _| None);
    // The Gaussians' bones, when recorded; before, each stayed on its bone, four a bone.
    let bones: Vec<usize> = match state.get("gaussian_bones") {
        Some(bones) => serde_json::from_value(bones.clone()).map_err(|e| io(&state_path, format!("gaussian_bones: {e}")))?,
        None => (0..scene.skeleton.len()).flat_map(|b| [b; 4]).collect(),
    };
    if let Some(b) = bones.iter().find(|&&b| b >= scene.skeleton.len()) {
        return Err(io(&state_path, format!("gaussian_bones: bone {b} is not in the skeleton's {}", scene.skeleton.len())));
    }
    let unit = crate::skeleton::body_length(1.0, extent);
    let gaussian = |bone: usize| crate::gaussians::Gaussian { bone, mean: [0.0; 3], rotation: [0.0, 0.0, 0.0, 1.0], scales: [unit; 3], amplitude: 1.0 };
    let set = crate::gaussians::GaussianSet { gaussians: bones.iter().map(|&b| gaussian(b)).collect() };
    let shell = crate::train::new_avatar(&scene, &config, &set, lights.kind, lights.count, &device, 0);
    let model_path = checkpoint.join("model.bpk");
    // burn checks every tensor's shape against the shell's: a wrong count of bones is refused.
    let model = shell.try_load_file(&model_path).map_err(|e| {
        io(
            &model_path,
            format!("cannot load the fitted model as {}'s gaussian_bones ({} Gaussians) and field describe it: {e}", state_path.display(), bones.len()),
        )
    })?;
    let iteration = state["iteration"].as_u64().unwrap_or(0) as usize;
    let footprint = schedule.footprint.unwrap_or_else(|| scene.footprint().footprint);
    let fitted = Fitted { model, device, light_kind: lights.kind, fit_light: lights.fit, footprint, iteration };
    Ok(FittedRun { scene, schedule, fitted })
}

/// A trainer rebuilt from a run folder on the scene it was fitted on, its model loaded from the
/// last checkpoint (optimisers fresh): what the step benchmarks time on a formed surface.
pub fn restore_trainer(run: &Path, backend: crate::backend::Backend) -> Result<Trainer, FitError> {
    let mut schedule = Schedule::load(&run.join(SCHEDULE_COPY))?;
    let scene = Scene::load(&recorded_scene(run)?)?;
    apply_recorded_field(run, scene.skeleton.len(), &mut schedule.field)?;
    let mut trainer = Trainer::new(scene, schedule, backend, 0)?;
    let checkpoint = existing_checkpoint(run).ok_or_else(|| io(run, "holds no checkpoint"))?;
    verified_state(&checkpoint, &trainer.scene, None)?;
    load_model(&mut trainer, &checkpoint)?;
    Ok(trainer)
}

/// The scene a run was fitted on, as its `fit.json` records it.
fn recorded_scene(run: &Path) -> Result<std::path::PathBuf, FitError> {
    let report = run.join("fit.json");
    if !report.exists() && crate::run_lock::held_elsewhere(run) {
        return Err(io(run, "a fit is in progress in this run folder (it has no fit.json yet): wait for it to finish"));
    }
    let fitted = crate::fit_report::FitReport::read(&report).map_err(|e| FitError::Input(format!("{e} (pass --scene to name the scene)")))?;
    Ok(std::path::PathBuf::from(fitted.scene))
}

/// The factor from the fitted albedo to reflectance (`relight::albedo_scale`) for a model
/// fitted on `scene`.
pub fn albedo_scale(scene: &Scene, model: &Avatar) -> glam::DVec3 {
    let fitted_intensity = (model.light.kind == LightKind::Point).then(|| model.light.intensity().into_scalar::<f32>() as f64);
    scene.training_lights().first().map(|name| crate::light::albedo_scale(&scene.lights[*name], fitted_intensity)).unwrap_or(glam::DVec3::ONE)
}

/// The columns of `losses.csv` after the loss terms: the first training light's direction or
/// position (`StepStats::light`), empty when none is fitted.
const LIGHT_COLUMNS: [&str; 3] = ["light_x", "light_y", "light_z"];

pub(crate) fn losses_csv(history: &[(usize, StepStats)]) -> String {
    let header: Vec<&str> = ["iteration", "total", "seconds"].into_iter().chain(crate::schedule::TERMS).chain(LIGHT_COLUMNS).collect();
    let rows = history.iter().map(|(it, s)| {
        let mut row = vec![it.to_string(), format!("{:.6e}", s.total), format!("{:.4}", s.seconds)];
        row.extend(crate::schedule::TERMS.iter().map(|t| s.terms.get(*t).map(|v| format!("{v:.6e}")).unwrap_or_default()));
        row.extend((0..3).map(|k| s.light.map(|v| format!("{:.7}", v[k])).unwrap_or_default()));
        row
    });
    crate::table::to_csv(&header, rows)
}

fn parse_losses_csv(text: &str) -> Vec<(usize, StepStats)> {
    let mut rows = Vec::new();
    let table = crate::table::read_csv(text).map(|(_, rows)| rows).unwrap_or_default();
    for line in &table {
        let cells: Vec<&str> = line.iter().map(String::as_str).collect();
        let (Some(it), Some(total), Some(seconds)) =
            (cells.first().and_then(|c| c.parse().ok()), cells.get(1).and_then(|c| c.parse().ok()), cells.get(2).and_then(|c| c.parse().ok()))
        else {
            continue;
        };
        let terms =
            crate::schedule::TERMS.iter().enumerate().filter_map(|(k, t)| cells.get(3 + k).and_then(|c| c.parse().ok()).map(|v| (t.to_string(), v))).collect();
        // Runs before the light's columns have none: their rows read back without it.
        let light_cell = |k: usize| cells.get(3 + crate::schedule::TERMS.len() + k).and_then(|c| c.parse::<f64>().ok());
        let light = match (light_cell(0), light_cell(1), light_cell(2)) {
            (Some(x), Some(y), Some(z)) => Some([x, y, z]),
            _ => None,
        };
        rows.push((it, StepStats { total, terms, seconds, phases: Vec::new(), light }));
    }
    rows
}

pub fn save_png(path: &Path, image: &crate::imageio::RgbImage) -> Result<(), FitError> {
    let png = crate::imageio::encode_png_rgb(image).map_err(|e| io(path, e))?;
    crate::imageio::write_atomic(path, &png).map_err(|e| io(path, e))
}
