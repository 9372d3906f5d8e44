//! The fit's trainer: the scene data a fit draws from, what the steps only read (the schedule,
//! the body's measures, the light search's cones) and the `TrainState` a step takes and gives
//! back (model, named optimisers, iteration, the field's average, error maps); the seeded stream
//! is the batches'. Each job has a room: `setup` (the body measured, the model placed), `body`
//! (loose body from the masks), `batch` (drawing a batch and every random number a step uses),
//! `step` (`step(batch, state) -> (state, stats)`: forward, losses, backward, updates), `rebind`
//! (Gaussians to the bones that carry them) and `light_search`. `iterate` runs one iteration:
//! the stage's events, a batch, a step.
//!
//! It skips what a scene does not need: a uniformly lit capture gets no light, no shadow rays and
//! no light-fitting stage. A capture under several lights of one kind fits them jointly, each
//! batch under one of them.

mod batch;
pub mod body;
pub mod camera_colour;
pub mod camera_pose;
mod fused_adam;
mod host_adam;
mod light_search;
pub mod motion;
pub mod motion_noise;
mod phase_clock;
mod pixels;
mod rebind;
mod setup;
mod step;

pub use batch::Batch;
pub use body::{masked_body_beyond_bones, masked_reach_beyond_bones, seeds_on_loose_body};
pub use light_search::SUN_CONE_SPACINGS;
pub use setup::{body_centre, field_config, new_avatar, training_lights, TrainingLights};

use crate::avatar::Avatar;
use crate::field::{GradientMethod, PoseTensors};
use crate::fit_error::FitError;
use crate::messages::StepStats;
use crate::random::Stream;
use crate::scene::Scene;
use crate::schedule::Schedule;
use crate::shading::LightKind;
use burn::optim::ModuleOptimizer;
use burn::tensor::{Device, Tensor};
use fused_adam::FusedAdam;
use std::time::Instant;

/// Adam's guard against a zero second moment (burn's default).
const EPSILON: f32 = 1e-5;

/// The feature tables' guard: their gradients are tiny and sparse, so it must not swamp them
/// (instant-NGP uses 1e-15).
const FEATURES_EPSILON: f32 = 1e-15;

/// One Adam optimiser per parameter group (`schedule::GROUPS`), by name.
#[derive(Clone)]
pub struct Optimisers {
    pub field: ModuleOptimizer,
    pub gaussians: ModuleOptimizer,
    pub light: ModuleOptimizer,
    /// A grid's feature tables, with their own guard (`FEATURES_EPSILON`).
    pub features: ModuleOptimizer,
}

impl Optimisers {
    pub fn new() -> Self {
        Self {
            field: FusedAdam::new(EPSILON).init(),
            gaussians: FusedAdam::new(EPSILON).init(),
            light: FusedAdam::new(EPSILON).init(),
            features: FusedAdam::new(FEATURES_EPSILON).init(),
        }
    }

    /// Each optimiser with its group's name (`schedule::GROUPS`, in its order; a checkpoint's
    /// `optimizer-NAME.bpk`).
    pub fn named(&self) -> [(&'static str, &ModuleOptimizer); 4] {
        let [field, gaussians, light, features] = crate::schedule::GROUPS;
        [(field, &self.field), (gaussians, &self.gaussians), (light, &self.light), (features, &self.features)]
    }

    pub fn named_mut(&mut self) -> [(&'static str, &mut ModuleOptimizer); 4] {
        let [field, gaussians, light, features] = crate::schedule::GROUPS;
        [(field, &mut self.field), (gaussians, &mut self.gaussians), (light, &mut self.light), (features, &mut self.features)]
    }

    /// The same optimisers in burn's own Adam, their state carried over (`train::fused_adam` is
    /// burn's Adam to the bit, one pass instead of thirteen): a benchmark's baseline.
    pub fn in_burns_adam(&self) -> Self {
        let burns = |epsilon: f32, optimiser: &ModuleOptimizer| burn::optim::AdamConfig::new().with_epsilon(epsilon).init().load_record(optimiser.to_record());
        Self {
            field: burns(EPSILON, &self.field),
            gaussians: burns(EPSILON, &self.gaussians),
            light: burns(EPSILON, &self.light),
            features: burns(FEATURES_EPSILON, &self.features),
        }
    }
}

impl Default for Optimisers {
    fn default() -> Self {
        Self::new()
    }
}

/// Training data of one frame: its pose and the views that see it.
struct FrameData {
    position: usize,
    pose_tensors: PoseTensors,
    views: Vec<usize>,
}

/// Per training view: pixel indices for balanced ray sampling.
struct ViewData {
    foreground: pixels::PixelRuns,
    /// Pixels within `BOUNDARY_BAND` pixels of the silhouette's edge, on either side.
    boundary: pixels::PixelRuns,
    /// Pixels within `silhouette::EDGE_BAND` of the mask's edge where the view's plate is
    /// known: there the render is composited over the plate, and the mask trusted less.
    near_edge: pixels::PixelRuns,
}

/// What one training step changes (`Trainer::step` takes it and gives it back): the model, its
/// named optimisers, the iteration, the field's moving average and the error maps.
#[derive(Clone)]
pub struct TrainState {
    pub model: Avatar,
    pub optimisers: Optimisers,
    pub iteration: usize,
    /// The moving average of the field's parameters, once the schedule's
    /// `field_average_half_life` has started it (`fitted_model`).
    pub average: Option<crate::averaging::ParameterAverage>,
    /// Per scene view, where the fit is still wrong in it, when the schedule draws rays by it
    /// (`Schedule::error_rays`; training views with a mask only).
    pub error_maps: Vec<Option<crate::error_map::ErrorMap>>,
    /// Each training camera's learned colour, for a scene of two or more training cameras.
    pub camera_colours: Option<camera_colour::CameraColours>,
    /// The training motion's corrections (a grid field's fit).
    pub motion: Option<motion::MotionCorrections>,
    /// The training cameras' pose corrections (a grid field's fit of two or more cameras).
    pub cameras: Option<camera_pose::CameraPoses>,
    /// The Gaussians as the last step left them, read with its check after the update, for the
    /// next batch's ray bounds (a GPU then waits once less a step); dropped by anything else
    /// that may change them.
    pub gaussians_read: Option<crate::gaussians::GaussianSet>,
}

pub struct Trainer {
    pub scene: Scene,
    pub schedule: Schedule,
    pub device: Device,
    /// What the steps change; out of the trainer only while a step runs.
    state: Option<TrainState>,
    frames: Vec<FrameData>,
    views: Vec<ViewData>,
    /// Whether some training view has a plate (`ViewData::near_edge`): batches then carry each
    /// pixel's background and mask weight.
    plates: bool,
    pub fit_light: bool,
    pub light_kind: LightKind,
    /// The seed the fit was started with (a resumed fit keeps it).
    pub seed: u64,
    pub stream: Stream,
    /// How SDF gradients (normals, Eikonal, curvature) are taken; `GRADIENT` unless a
    /// benchmark compares methods.
    pub gradient: GradientMethod,
    /// Render rays that miss every Gaussian bound too (as before they were skipped): only
    /// for the benchmark that measures what skipping them saves.
    pub render_missed_rays: bool,
    /// Threads a step's render is split over (`render::render_in_parts`): every thread by
    /// default; 1 renders the batch on one (a benchmark's baseline). The parts' matrix products
    /// round differently, so a fit is the same to the bit for a seed and a thread count.
    pub render_threads: usize,
    /// Each render part's backward pass on its own thread (`render::Parts::backward`); false runs
    /// them one after the other on the step's thread: only for a benchmark's baseline.
    pub parts_backward_at_once: bool,
    /// The centre of the skeleton's bounds over the capture and the body's extent (m): where
    /// and at what distances a point light is searched.
    body_centre: glam::DVec3,
    body_extent: f64,
    /// Where the mean regulariser pulls each Gaussian, bone-local (`mean_targets`).
    mean_targets: Tensor<2>,
    /// Per Gaussian, its seed (root-local) when it was seeded on loose body
    /// (`seeds_on_loose_body`): the mean regulariser pulls it there, not to its bone's centre.
    anchors: Vec<Option<glam::DVec3>>,
    /// The root bone when the body is loose (its grids reach body beyond every bone's).
    loose_root: Option<usize>,
    /// What the light search found for each training light, once it has run (`sun_search`).
    pub searches: Vec<Option<crate::sun_search::SearchReport>>,
    /// Per training light, the cone (axis, half-angle in radians) a sun's direction stays in
    /// after the search.
    pub cones: Vec<Option<(glam::DVec3, f64)>>,
    /// The training light of each of the scene's views (its index in `Scene::training_lights`;
    /// `None` for a view not in training).
    view_light: Vec<Option<usize>>,
    /// The training data's fingerprint (`Scene::training_identity`, every training pixel
    /// hashed), computed once for all the checkpoints a fit writes.
    training_identity: std::sync::OnceLock<String>,
    /// What the training images say of their pixel footprint (`scene::footprint`), and the
    /// footprint the fit models (the schedule's, else that).
    pub footprint_estimate: crate::scene::FootprintEstimate,
    pub footprint: crate::scene::Footprint,
    /// The share of the anywhere-third drawn by the error maps: the schedule's, or under
    /// `auto` what the body's looseness asks (`ErrorRays::share`).
    pub error_rays: f64,
    /// Whether the Gaussians also fit the density at the shadows' scale (the schedule's
    /// `density_at_shadow_scale`, `auto` resolved by the body's looseness).
    pub density_at_shadow_scale: bool,
}

impl Trainer {
    /// Each training view's error map (`Schedule::error_rays`) by the view's index: what a
    /// checkpoint keeps so that a resumed fit draws its rays as the uninterrupted one does.
    pub fn error_maps(&self) -> Vec<(usize, Vec<f32>)> {
        let maps = self.state.as_ref().map(|s| s.error_maps.as_slice()).unwrap_or_default();
        maps.iter().enumerate().filter_map(|(v, m)| m.as_ref().map(|m| (v, m.errors().to_vec()))).collect()
    }

    /// Each training camera (scene index) with its learned, normalised gain per channel.
    pub fn camera_gains(&self) -> Vec<(usize, [f64; 3])> {
        self.state.as_ref().and_then(|s| s.camera_colours.as_ref()).map(|c| c.gains()).unwrap_or_default()
    }

    /// The cameras' colours as a checkpoint keeps them (null for none).
    pub fn camera_colours_json(&self) -> serde_json::Value {
        self.state.as_ref().and_then(|s| s.camera_colours.as_ref()).map(|c| c.to_json()).unwrap_or(serde_json::Value::Null)
    }

    /// Restores `camera_colours_json`'s output; null (a checkpoint before cameras' colours
    /// were learned) keeps them where they start.
    pub fn restore_camera_colours(&mut self, value: &serde_json::Value) -> Result<(), String> {
        let state = self.state_mut().map_err(|e| e.to_string())?;
        match (state.camera_colours.as_mut(), value.is_null()) {
            (_, true) => Ok(()),
            (Some(colours), false) => colours.restore(value),
            (None, false) => Err("this scene has one training camera: no colours to restore".into()),
        }
    }

    /// Restores `error_maps`' output; refused when a view has no map or a map's size differs.
    pub fn set_error_maps(&mut self, maps: Vec<(usize, Vec<f32>)>) -> Result<(), String> {
        let state = self.state_mut().map_err(|e| e.to_string())?;
        for (v, errors) in maps {
            let map = state.error_maps.get_mut(v).and_then(|m| m.as_mut()).ok_or_else(|| format!("view {v} has no error map in this fit"))?;
            map.set_errors(errors).map_err(|e| format!("view {v}: {e}"))?;
        }
        Ok(())
    }

    /// Runs the grid's lookup as the composite of tensor ops instead of the fused op (for the
    /// step benchmark's comparison; a no-op for the `mlp` field).
    pub fn set_composite_lookup(&mut self, composite: bool) {
        if let Some(grid) = self.state.as_mut().and_then(|s| s.model.field.grid.as_mut()) {
            grid.route = if composite { crate::field::grid::Route::Composite } else { crate::field::grid::Route::Fused };
        }
    }

    /// `Scene::training_identity` of the trainer's scene, hashed on first use.
    pub fn training_identity(&self) -> &str {
        self.training_identity.get_or_init(|| self.scene.training_identity())
    }

    /// What the steps change.
    pub fn state(&self) -> Result<&TrainState, FitError> {
        self.state.as_ref().ok_or_else(|| FitError::Input("the training state was lost by an interrupted step".into()))
    }

    pub fn state_mut(&mut self) -> Result<&mut TrainState, FitError> {
        let state = self.state.as_mut().ok_or_else(|| FitError::Input("the training state was lost by an interrupted step".into()))?;
        // Whoever holds the state may change the Gaussians.
        state.gaussians_read = None;
        Ok(state)
    }

    /// The model being trained: the last step's parameters.
    pub fn model(&self) -> Result<&Avatar, FitError> {
        self.state().map(|s| &s.model)
    }

    pub fn model_mut(&mut self) -> Result<&mut Avatar, FitError> {
        self.state_mut().map(|s| &mut s.model)
    }

    /// The iteration the next step takes.
    pub fn iteration(&self) -> usize {
        self.state.as_ref().map_or(0, |s| s.iteration)
    }

    /// Sets the iteration the next step takes (a resumed fit's, or a benchmark's stage).
    pub fn set_iteration(&mut self, iteration: usize) -> Result<(), FitError> {
        self.state_mut().map(|s| s.iteration = iteration)
    }

    /// The fit as it stands, for rendering and scoring (`fitted_model`).
    pub fn fitted(&self) -> Result<crate::avatar::Fitted, FitError> {
        Ok(crate::avatar::Fitted {
            model: self.fitted_model()?,
            device: self.device.clone(),
            light_kind: self.light_kind,
            fit_light: self.fit_light,
            footprint: self.footprint,
            iteration: self.iteration(),
        })
    }

    /// The model a fit shows (checkpoint, renders, evaluation): the last step's, its field's
    /// parameters replaced by their moving average once that has started.
    pub fn fitted_model(&self) -> Result<Avatar, FitError> {
        let mut model = self.model()?.clone();
        if let Some(average) = &self.state()?.average {
            model.field =
                average.applied(model.field).ok_or_else(|| FitError::Input("the field's parameter average does not match the field's layout".into()))?;
        }
        Ok(model)
    }

    /// Scene frame `position`'s pose as the motion's refinement has corrected it so far.
    pub fn corrected_pose(&self, position: usize) -> crate::skeleton::Pose {
        let given = &self.scene.frames[position].pose;
        match self.state.as_ref().and_then(|s| s.motion.as_ref()) {
            Some(motion) => motion.pose(&self.scene.skeleton, position, given),
            None => given.clone(),
        }
    }

    /// The scene with its frames posed as the fitted avatar is shown in them
    /// (`motion::show_in`: turned by what every training frame's correction shares); the scene
    /// itself when the motion is not refined.
    pub fn shown_scene(&self) -> std::borrow::Cow<'_, crate::scene::Scene> {
        let shared = self.state.as_ref().and_then(|s| s.motion.as_ref()).map(|m| m.shared_turns()).unwrap_or_default();
        if !motion::turns_any(&shared) {
            return std::borrow::Cow::Borrowed(&self.scene);
        }
        let mut scene = self.scene.clone();
        motion::show_in(&mut scene, &shared);
        std::borrow::Cow::Owned(scene)
    }

    /// How far the refinement has moved the training motion (none for a fit that does not
    /// refine it).
    pub fn motion_moved(&self) -> Option<motion::MotionMoved> {
        let refines = self.schedule.weights.iter().any(|(name, ramp)| name.starts_with("motion") && (ramp.from > 0.0 || ramp.to > 0.0));
        self.state.as_ref().and_then(|s| s.motion.as_ref()).filter(|_| refines).map(|m| m.moved(&self.scene.skeleton))
    }

    /// The motion's corrections as a checkpoint keeps them (null for none).
    pub fn motion_json(&self) -> serde_json::Value {
        self.state.as_ref().and_then(|s| s.motion.as_ref()).map(|m| m.to_json()).unwrap_or(serde_json::Value::Null)
    }

    /// Restores `motion_json`'s output; null (a checkpoint before the motion was refined) keeps
    /// the given motion.
    pub fn restore_motion(&mut self, value: &serde_json::Value) -> Result<(), String> {
        let state = self.state_mut().map_err(|e| e.to_string())?;
        match (state.motion.as_mut(), value.is_null()) {
            (_, true) => Ok(()),
            (Some(motion), false) => motion.restore(value),
            (None, false) => Err("this fit does not refine the motion".into()),
        }
    }

    /// How far the refinement has moved the training cameras (none for a fit that does not
    /// refine them).
    pub fn cameras_moved(&self) -> Option<camera_pose::CamerasMoved> {
        let refines = self.schedule.weights.get("camera_prior").is_some_and(|ramp| ramp.from > 0.0 || ramp.to > 0.0);
        self.state.as_ref().and_then(|s| s.cameras.as_ref()).filter(|_| refines).map(|c| c.moved(&self.scene.cameras))
    }

    /// The training cameras as refined so far (each as given where it is not refined).
    pub fn corrected_cameras(&self) -> Vec<crate::scene::Camera> {
        let poses = self.state.as_ref().and_then(|s| s.cameras.as_ref());
        self.scene.cameras.iter().enumerate().map(|(c, given)| poses.map_or_else(|| given.clone(), |p| p.corrected_camera(c, given))).collect()
    }

    /// The cameras' corrections as a checkpoint keeps them (null for none).
    pub fn cameras_json(&self) -> serde_json::Value {
        self.state.as_ref().and_then(|s| s.cameras.as_ref()).map(|c| c.to_json()).unwrap_or(serde_json::Value::Null)
    }

    /// Restores `cameras_json`'s output; null (a checkpoint before the cameras were refined)
    /// keeps the given poses.
    pub fn restore_cameras(&mut self, value: &serde_json::Value) -> Result<(), String> {
        let state = self.state_mut().map_err(|e| e.to_string())?;
        match (state.cameras.as_mut(), value.is_null()) {
            (_, true) => Ok(()),
            (Some(cameras), false) => cameras.restore(value),
            (None, false) => Err("this fit does not refine the cameras".into()),
        }
    }

    /// The body's length unit: `skeleton::body_length(1, extent)`.
    fn body_unit(&self) -> f64 {
        crate::skeleton::body_length(1.0, self.body_extent)
    }

    /// The least radius of a Gaussian's bound on this body.
    fn min_bound_radius(&self) -> f64 {
        crate::render::MIN_BOUND_RADIUS * self.body_unit()
    }
}

impl Trainer {
    /// One iteration: the stage's events (the light search when the light stage starts,
    /// rebinding while the Gaussians fit the density), a batch drawn, a step taken on it.
    pub fn iterate(&mut self) -> Result<StepStats, FitError> {
        let (start, cpu_start) = (Instant::now(), crate::threads::process_cpu_seconds());
        let mut phases = Vec::new();
        if self.searches_lights_now() {
            self.search_lights()?;
            phases.push((crate::messages::PHASES[0], start.elapsed().as_secs_f64()));
        }
        if self.rebinds_now() {
            self.rebind_gaussians()?;
        }
        let (drawing, drawing_cpu) = (Instant::now(), crate::threads::process_cpu_seconds());
        let batch = self.draw_batch()?;
        phases.push((crate::messages::PHASES[1], drawing.elapsed().as_secs_f64()));
        let batch_cpu = crate::threads::process_cpu_seconds().zip(drawing_cpu).map(|(now, then)| (crate::messages::PHASES[1], now - then));
        let state = self.state.take().ok_or_else(|| FitError::Input("the training state was lost by an interrupted step".into()))?;
        let (state, stats) = self.step(batch, state);
        self.state = Some(state);
        let mut stats = stats?;
        phases.append(&mut stats.phases);
        stats.phases = phases;
        stats.phase_cpu = batch_cpu.into_iter().chain(std::mem::take(&mut stats.phase_cpu)).collect();
        stats.seconds = start.elapsed().as_secs_f64();
        stats.cpu_seconds = crate::threads::process_cpu_seconds().zip(cpu_start).map(|(now, then)| now - then);
        stats.device_memory_bytes = crate::backend::device_memory_bytes(&self.device);
        Ok(stats)
    }

    /// Whether this iteration starts the light stage with a search for the training lights.
    fn searches_lights_now(&self) -> bool {
        let it = self.iteration();
        it == self.schedule.light_from && self.fit_light && self.light_kind != LightKind::Uniform && self.schedule.sun_search > 0
    }

    /// Whether the Gaussians are rebound to their bones before this iteration's batch.
    fn rebinds_now(&self) -> bool {
        let (it, every) = (self.iteration(), self.schedule.rebind_every);
        every > 0 && it > 0 && it % every == 0 && it <= self.schedule.light_from && self.schedule.weight("density", it) > 0.0
    }
}
