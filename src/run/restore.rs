//! A finished run rebuilt from its folder (`restore`): the scene it was fitted on, its
//! schedule and the fitted model, without anything of the training.

use super::*;
use crate::avatar::{Avatar, Fitted};
use crate::fit_error::{io, FitError};
use crate::scene::Scene;
use crate::schedule::Schedule;
use crate::shading::LightKind;
use crate::train::Trainer;
use burn::module::Module;
use std::path::Path;

/// A finished (or checkpointed) run as `restore` rebuilds it: the scene it is rendered on (its
/// frames posed as the avatar is shown in them: `train::motion::show_in`), its schedule copy
/// and the fitted avatar.
pub struct FittedRun {
    pub scene: Scene,
    pub schedule: Schedule,
    pub fitted: Fitted,
    /// Each bone's turn every refined training frame shares (radians, in its parent's frame;
    /// empty when the motion was not refined, zeros where nothing is shared): the scene's frames
    /// and new motion are shown with it.
    pub shared_turns: Vec<[f64; 3]>,
}

impl FittedRun {
    /// `pose` of new motion (a clip driving the bones) as the avatar is shown in it.
    pub fn shown_motion(&self, pose: crate::skeleton::Pose) -> crate::skeleton::Pose {
        crate::train::motion::shown_pose(&self.scene.skeleton, &pose, &self.shared_turns)
    }
}

/// The turns every refined training frame shares (`MotionCorrections::shared_turns`), from a
/// checkpoint's state; none when the motion was not refined.
fn shared_turns(state: &serde_json::Value, state_path: &Path) -> Result<Vec<[f64; 3]>, FitError> {
    match state.get("motion").filter(|m| !m.is_null()) {
        Some(value) => crate::train::motion::MotionCorrections::shared_turns_in(value).map_err(|e| io(state_path, format!("motion: {e}"))),
        None => Ok(Vec::new()),
    }
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
    let mut scene = Scene::load(&scene_path)?;
    apply_recorded_field(run, scene.skeleton.len(), &mut schedule.field)?;
    let checkpoint = existing_checkpoint(run).ok_or_else(|| io(run, "holds no checkpoint"))?;
    let state = verified_state(&checkpoint, &scene, None)?;
    let state_path = checkpoint.join("state.json");
    let shared_turns = shared_turns(&state, &state_path)?;
    crate::train::motion::show_in(&mut scene, &shared_turns);
    let lights = crate::train::training_lights(&scene, &schedule)?;
    let device = backend.open().map_err(|e| FitError::Input(e.to_string()))?;
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
    Ok(FittedRun { scene, schedule, fitted, shared_turns })
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
pub(super) fn recorded_scene(run: &Path) -> Result<std::path::PathBuf, FitError> {
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
