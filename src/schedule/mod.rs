//! Staged loss schedules read from `schedules/*.toml`: each loss weight is a piecewise-linear
//! `alpha(t) = (1 - tau) from + tau to`, `tau = clamp((t - hold) / ramp, 0, 1)`, plus learning
//! rates per parameter group, the batch sizes and the iteration count. Errors name the file and
//! the TOML key; a schedule that asks for something the scene cannot feed is an error too.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

mod file;

/// Parameter groups with their own learning rate: the field's decoder (and the whole `mlp`
/// field), the Gaussians, the light, and a `grid` field's feature tables.
pub const GROUPS: [&str; 4] = ["field", "gaussians", "light", "features"];

/// Which encoding the field uses (`field::FieldConfig`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum FieldKind {
    /// Fourier features in every bone's frame into a 3 x 64 MLP.
    Mlp,
    /// Multiresolution feature grids in the nearest bones' frames into a small decoder.
    Grid,
}

/// The `[field]` table: the kind and, for a grid, optional overrides of its shape.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct FieldSettings {
    pub kind: FieldKind,
    pub levels: Option<usize>,
    pub table_log2: Option<u32>,
    pub top_bones: Option<usize>,
    /// Features per table entry (none: the grid's default, 2).
    pub features: Option<usize>,
    /// The finest level's cells per body extent (none: the grid's default, 160).
    pub finest_per_extent: Option<usize>,
    /// Hidden layers of the albedo's own decoder (0: it shares the SDF's; none: the field's
    /// default).
    pub albedo_layers: Option<usize>,
    /// How far (per body extent) each bone's grid box reaches beyond its segment (none: the
    /// grid's default, 1/8).
    pub reach_per_extent: Option<f64>,
    /// Coarse-to-fine: only the coarser half of a grid's levels until `fine_levels_from`, the
    /// rest faded in one after another until `fine_levels_until` (none: all levels throughout).
    pub fine_levels: Option<(usize, usize)>,
    /// Whether a grid's skinning lets points far from every bone follow the root
    /// (`FieldConfig::root_bone`; none: the field's default, yes).
    pub root_skinning: Option<bool>,
    /// The whole field a run's checkpoint was fitted with (from its `state.json`, never from a
    /// schedule file): when set, it is the field, whatever the settings above and the defaults.
    #[serde(skip)]
    pub recorded: Option<crate::field::FieldConfig>,
}

impl FieldSettings {
    /// A field of `kind` with every override left at the field's default.
    pub fn of(kind: FieldKind) -> Self {
        Self {
            kind,
            levels: None,
            table_log2: None,
            top_bones: None,
            features: None,
            finest_per_extent: None,
            albedo_layers: None,
            reach_per_extent: None,
            fine_levels: None,
            root_skinning: None,
            recorded: None,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Ramp {
    pub from: f64,
    pub to: f64,
    pub hold: f64,
    pub ramp: f64,
}

impl Ramp {
    pub fn constant(v: f64) -> Self {
        Self { from: v, to: v, hold: 0.0, ramp: 0.0 }
    }

    pub fn at(&self, iteration: usize) -> f64 {
        let t = iteration as f64;
        let tau = if self.ramp <= 0.0 {
            if t >= self.hold {
                1.0
            } else {
                0.0
            }
        } else {
            ((t - self.hold) / self.ramp).clamp(0.0, 1.0)
        };
        (1.0 - tau) * self.from + tau * self.to
    }

    /// Whether the weight is ever non-zero within `iterations`.
    pub fn ever_active(&self, iterations: usize) -> bool {
        self.from != 0.0 || (self.to != 0.0 && (self.hold as usize) < iterations)
    }
}

/// How much of each batch's anywhere-third is drawn where the fit is still wrong
/// (`Schedule::error_rays`).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ErrorRays {
    /// This share of the third.
    Share(f64),
    /// `LOOSE_ERROR_RAYS` when the training masks show body beyond every bone's reach (loose
    /// clothing: `train::masked_reach_beyond_bones`), else none.
    Auto,
}

/// The share of the anywhere-third drawn by the error maps for a loose body under `auto`.
/// Measured on `human-dressed` (seeds 0 / 1, foreground novel pose): 25.52 / 25.76 dB without,
/// 27.18 / 26.81 at 0.5, 26.65 / 26.74 at 1. On the tight bodies it does not help: `human-sun`
/// 28.13 / 28.97 -> 28.89 / 28.57 at 0.5 (27.74 / 28.08 at 1, its training images 3.6 dB better:
/// what stays wrong on a tight body is the pose's own detail, and drawing there overfits it),
/// `dog-sun` 30.03 -> 29.61, `quadruped-tiny` 20.89 -> 20.57 (its sun 1.50 -> 2.42 degrees).
/// A loose body's persistent errors are its shape (half of `human-dressed`'s training error
/// lies outside its masks: the hem, the backpack's edges), which every pose shares.
pub const LOOSE_ERROR_RAYS: f64 = 0.5;

impl ErrorRays {
    /// The share for a body that is loose or not.
    pub fn share(self, loose: bool) -> f64 {
        match self {
            ErrorRays::Share(share) => share,
            ErrorRays::Auto if loose => LOOSE_ERROR_RAYS,
            ErrorRays::Auto => 0.0,
        }
    }
}

/// A schedule switch that is on, off, or on for a loose body alone (`"auto"`: the training
/// masks show body beyond every bone's reach, `train::masked_reach_beyond_bones`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Switch {
    Fixed(bool),
    Auto,
}

impl Switch {
    /// Whether it is on, `auto` as `condition` says (a loose body, an imported capture).
    pub fn on(self, condition: bool) -> bool {
        match self {
            Switch::Fixed(on) => on,
            Switch::Auto => condition,
        }
    }
}

/// Whether the light (direction or position, and ambient) is fitted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LightPolicy {
    /// Fit it when a training light casts shadows (sun or point), skip it for uniform light.
    Auto,
    /// Always fit it: an error for a uniformly lit scene.
    Fit,
    /// Never: shading is albedo only.
    Off,
}

/// Every how many steps lazy regularisation evaluates the Eikonal and curvature terms (at that
/// many times their weight). Means over seeds 0-2, foreground novel pose / sun, against every
/// step: `human-sun-128` 27.16 dB / 0.92 degrees against 27.24 / 0.91, the 240-image capture
/// (`umbra synth --size 128 --cameras 8 --frames 30`) 29.61 / 1.02 against 29.48 / 0.87, `dog-sun`
/// 29.49 / 2.36 against 28.86 / 2.26, `human-lamp` 28.27 dB / 6.4 cm against 28.47 / 5.6, in
/// about 0.9x the training time; but `human-dressed` 26.56 / 1.09 against 27.02 / 1.23: a
/// loose body's cloth wants its curvature term every step, so `auto` is off for it.
pub const LAZY_EVERY: usize = 2;

/// Every how many steps the regulariser terms are evaluated under `lazy` for a body tight or
/// not (an unresolved `auto` reads as off).
pub(super) fn regularise_every(lazy: Switch, tight: bool) -> usize {
    if lazy.on(tight) {
        LAZY_EVERY
    } else {
        1
    }
}

/// Where `umbra` looks for its default schedule, relative to the working folder...
pub const DEFAULT_PATH: &str = "schedules/default.toml";
/// ...and the copy compiled in, used when that file is not there.
pub const DEFAULT_TEXT: &str = include_str!("../../schedules/default.toml");

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Schedule {
    pub file: PathBuf,
    pub iterations: usize,
    pub rays_per_batch: usize,
    pub samples_per_ray: usize,
    /// Samples per ray added where the coarse ones found density (hierarchical sampling).
    pub fine_samples_per_ray: usize,
    /// Fine samples per ray before `early_samples_until` (absent: `fine_samples_per_ray`).
    pub early_fine_samples_per_ray: usize,
    pub early_samples_until: usize,
    /// Samples per ray, without gradients, that locate the surface between the coarse and the
    /// fine samples (`render::Sampling::probe`).
    pub probe_samples_per_ray: usize,
    /// Probe samples per ray before `early_samples_until` (absent: `probe_samples_per_ray`).
    pub early_probe_samples_per_ray: usize,
    /// Whether the differentiable pass evaluates the field only where a sample can change a ray
    /// (`render::Sampling::cull`); absent: yes.
    pub cull_samples: bool,
    /// Points per step for the Gaussian density fit, and for Eikonal and curvature.
    pub density_points: usize,
    pub regulariser_points: usize,
    /// Whether the terms on the regulariser points (Eikonal, curvature) are evaluated every
    /// `LAZY_EVERY` steps at that many times their weight (lazy regularisation); `auto`: for a
    /// tight body (`with_lazy_regularisation`).
    pub lazy_regularisation: Switch,
    /// Every how many steps those terms are evaluated (`weight`, `needs`): `LAZY_EVERY` when
    /// `lazy_regularisation` is on, 1 when off or not yet resolved for a body.
    pub regularise_every: usize,
    pub checkpoint_every: usize,
    pub light: LightPolicy,
    /// Iteration from which the light is fitted (before it, shading uses the initial light).
    pub light_from: usize,
    /// Iterations of the last segment that only the light needs: a scene whose light is not
    /// fitted (uniformly lit) runs that many fewer.
    pub light_stage_iterations: usize,
    pub ambient_target: f64,
    /// The curvature term's perturbation (m on the reference human of `skeleton::HUMAN_EXTENT`;
    /// a fit scales it with its body).
    pub curvature_epsilon: f64,
    /// The light's learning rate falls exponentially to this fraction between `light_from` and
    /// the end, so the direction settles instead of jittering with the batch noise (the field
    /// keeps its rate: it is still learning colour then).
    pub light_lr_decay: f64,
    /// The field's and the feature tables' learning rates fall exponentially to this fraction
    /// between `field_lr_decay_from` and the end: Adam's steps at a constant rate keep the
    /// fine features jittering with the batch noise, which blurs the detail they hold.
    pub field_lr_decay: f64,
    pub field_lr_decay_from: usize,
    /// From `field_lr_decay_from` on, what the fit shows (checkpoints, renders, evaluation) is an
    /// exponential moving average of the field's parameters with this half-life in iterations
    /// (`averaging`); training goes on from the last step's. 0: the last step's (off).
    pub field_average_half_life: f64,
    /// Sun directions scored over the sphere when a sun starts to be fitted (`sun_search`); 0
    /// leaves the start to the initial direction and gradient descent alone.
    pub sun_search: usize,
    /// Every this many iterations while the Gaussians fit the field's density (up to
    /// `light_from`), each is moved to the bone that carries it (`Trainer::rebind_gaussians`);
    /// 0: never.
    pub rebind_every: usize,
    /// Whether the Gaussians also fit the field's density as their shadows use it: a second
    /// density term with both densities times the light's fitted shadow density scale before
    /// the loss's `tanh` (`losses::density`). The first term saturates at an optical depth of
    /// about one per body unit, so a Gaussian's faint tail outside the body costs it almost
    /// nothing there while the shadows see it ten to thirty times denser (false shadows: the
    /// legs under `human-dressed`'s skirt); the second saturates where a shadow turns opaque
    /// and fits those tails away, the first still keeping the body opaque. `"auto"`: for a
    /// loose body alone (the default's choice; the measurements are in the default schedule).
    /// Schedules from before it: false.
    pub density_at_shadow_scale: Switch,
    /// Whether the training motion is refined while fitting (`train::motion`, by the schedule's
    /// motion terms), or `auto`: for a scene `umbra import` converted from a capture, whose
    /// motion a tracker made, not for one that states its poses (a renderer's: refining exact
    /// poses only moves them). Schedules from before it: false.
    pub refine_motion: Switch,
    /// Whether each training camera's pose is refined while fitting (`train::camera_pose`, by
    /// the schedule's `camera_prior` term), or `auto`: for a scene `umbra import` converted
    /// from a capture of two or more cameras, whose poses a calibration estimated, not for one
    /// that states them. Schedules from before it: false.
    pub refine_cameras: Switch,
    /// The share of the batch's third drawn anywhere in a view that is drawn instead where the
    /// fit is still wrong (`error_map`: tiles in proportion to their recent error), or `auto`
    /// (`ErrorRays::Auto`). These rays teach the field, the albedo and the Gaussians but not
    /// the light, which learns from the same pixels as without them. 0 (schedules from before
    /// it): the third is drawn uniformly.
    pub error_rays: ErrorRays,
    /// The captures' pixel footprint (`scene::footprint`): `None` reads it off the training
    /// images, else as given.
    pub footprint: Option<crate::scene::Footprint>,
    pub learning_rates: BTreeMap<String, f64>,
    pub weights: BTreeMap<String, Ramp>,
    pub field: FieldSettings,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}: {key}: {message}", file.display())]
pub struct ScheduleError {
    pub file: PathBuf,
    pub key: String,
    pub message: String,
}

fn err(file: &Path, key: &str, message: impl Into<String>) -> ScheduleError {
    ScheduleError { file: file.to_path_buf(), key: key.to_string(), message: message.into() }
}

/// The largest count a schedule or `--iterations` may give (a billion iterations is weeks of
/// fitting; a larger number is a typo).
pub const MAX_COUNT: usize = 1_000_000_000;

/// Checks an iteration count given on the command line (`--iterations`) against the bounds a
/// schedule's `iterations` has.
pub fn check_iterations(n: usize) -> Result<usize, String> {
    if (1..=MAX_COUNT).contains(&n) {
        Ok(n)
    } else {
        Err(format!("--iterations {n}: must be a whole number from 1 to {MAX_COUNT}"))
    }
}

impl Schedule {
    /// The fine samples a ray as a table's heading says them: `16 (8 from 1200)`, or `8`.
    pub fn fine_samples_label(&self) -> String {
        self.dropping_label(self.early_fine_samples_per_ray, self.fine_samples_per_ray)
    }

    /// The probe samples a ray as `fine_samples_label` says the fine ones.
    pub fn probe_samples_label(&self) -> String {
        self.dropping_label(self.early_probe_samples_per_ray, self.probe_samples_per_ray)
    }

    fn dropping_label(&self, early: usize, late: usize) -> String {
        match self.early_samples_until > 0 && early != late {
            true => format!("{early} ({late} from {})", self.early_samples_until),
            false => late.to_string(),
        }
    }

    /// How a training step at `iteration` samples its rays.
    pub fn sampling(&self, iteration: usize) -> crate::render::Sampling {
        let early = iteration < self.early_samples_until;
        crate::render::Sampling {
            coarse: self.samples_per_ray,
            probe: if early { self.early_probe_samples_per_ray } else { self.probe_samples_per_ray },
            fine: if early { self.early_fine_samples_per_ray } else { self.fine_samples_per_ray },
            // Training decodes the albedo at every sample: a sample without weight still tells
            // the geometry, through its colour, whether density there would match the image
            // (dropping them cost human-sun-128 0.8 dB foreground at seed 0).
            albedo_floor: 0.0,
            cull: self.cull_samples,
        }
    }

    pub fn load(path: &Path) -> Result<Self, ScheduleError> {
        Self::read(path).map(|(schedule, _)| schedule)
    }

    /// The schedule at `path` and its text. The default schedule's path works from any folder:
    /// when `schedules/default.toml` is not there, the copy compiled into the binary is used.
    pub fn read(path: &Path) -> Result<(Self, String), ScheduleError> {
        let text = match crate::files::read_text(path, crate::files::SMALL_TEXT_BYTES) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound && path == Path::new(DEFAULT_PATH) => DEFAULT_TEXT.to_string(),
            Err(e) => return Err(err(path, "(file)", e.to_string())),
        };
        Ok((Self::parse(&text, path)?, text))
    }

    /// Reads a schedule's text (`file` names it in errors): `file.rs` holds the format.
    pub fn parse(text: &str, file: &Path) -> Result<Self, ScheduleError> {
        file::parse(text, file)
    }

    /// The schedule with `lazy_regularisation` resolved for a body tight (no loose clothing:
    /// `train::masked_reach_beyond_bones`) or not.
    pub fn with_lazy_regularisation(self, tight: bool) -> Self {
        Self { regularise_every: regularise_every(self.lazy_regularisation, tight), ..self }
    }

    /// A term's weight at an iteration: its ramp's, times `regularise_every` for a term on the
    /// regulariser points (evaluated only every that many steps).
    pub fn weight(&self, term: &str, iteration: usize) -> f64 {
        let ramp = self.weights.get(term).map(|r| r.at(iteration)).unwrap_or(0.0);
        match self.regularise_every > 1 && Self::regularises(term) {
            true => ramp * self.regularise_every as f64,
            false => ramp,
        }
    }

    /// Whether `term` is evaluated on the regulariser points alone.
    fn regularises(term: &str) -> bool {
        use crate::losses::{REGULARISER_INPUTS, TERMS};
        TERMS.iter().find(|t| t.name == term).is_some_and(|t| !t.needs.is_empty() && t.needs.iter().all(|n| REGULARISER_INPUTS.contains(n)))
    }

    /// Whether a term weighted at an iteration needs `input` (`losses::Term::needs`); the
    /// regulariser points' inputs only every `regularise_every` steps.
    pub fn needs(&self, input: crate::losses::Input, iteration: usize) -> bool {
        let lazy = crate::losses::REGULARISER_INPUTS.contains(&input) && iteration % self.regularise_every != 0;
        !lazy && crate::losses::TERMS.iter().any(|t| t.needs.contains(&input) && self.weight(t.name, iteration) > 0.0)
    }

    /// How many of a grid's `levels` are active at an iteration (`FieldSettings::fine_levels`).
    pub fn active_levels(&self, levels: usize, iteration: usize) -> f32 {
        let Some((from, until)) = self.field.fine_levels else {
            return levels as f32;
        };
        let coarse = levels.div_ceil(2) as f32;
        let progress = if until > from {
            ((iteration as f32 - from as f32) / (until - from) as f32).clamp(0.0, 1.0)
        } else if iteration >= from {
            1.0
        } else {
            0.0
        };
        coarse + (levels as f32 - coarse) * progress
    }

    /// The learning rate of a group at an iteration (with the light's decay in the last segment).
    pub fn learning_rate(&self, group: &str, iteration: usize) -> f64 {
        let base = self.learning_rates.get(group).copied().unwrap_or(1e-3);
        let (decay, from) = match group {
            "light" => (self.light_lr_decay, self.light_from),
            "field" | "features" | "motion" | "cameras" => (self.field_lr_decay, self.field_lr_decay_from),
            _ => return base,
        };
        let span = self.iterations.saturating_sub(from).max(1) as f64;
        let progress = (iteration.saturating_sub(from) as f64 / span).clamp(0.0, 1.0);
        base * decay.powf(progress)
    }

    /// The schedule run for `iterations` instead: the field's learning rates start to fall at
    /// the same fraction of the fit (the constant-rate segment and the decay both longer), the
    /// earlier stages (silhouette, Gaussians, light) where they were. `schedules/detail.toml` is
    /// the default stretched to 4,700 iterations (to the nearest hundred).
    pub fn stretched(&self, iterations: usize) -> Schedule {
        let mut schedule = self.clone();
        let fraction = self.field_lr_decay_from as f64 / self.iterations.max(1) as f64;
        schedule.iterations = iterations;
        schedule.field_lr_decay_from = ((fraction * iterations as f64).round() as usize).max(self.field_lr_decay_from.min(iterations));
        schedule
    }

    /// The iteration count for a scene whose light is (or is not) fitted.
    pub fn iterations_for(&self, fit_light: bool) -> usize {
        if fit_light {
            self.iterations
        } else {
            self.iterations.saturating_sub(self.light_stage_iterations).max(1)
        }
    }

    /// Checks the schedule against what the scene can feed; returns whether the light is fitted.
    pub fn check_against(&self, scene_casts_shadows: bool) -> Result<bool, ScheduleError> {
        match (self.light, scene_casts_shadows) {
            (LightPolicy::Fit, false) => Err(err(
                &self.file,
                "light",
                "\"fit\" asks for a light-fitting stage, but every training image of this scene is uniformly lit: there is no light direction or shadow to recover (use \"auto\" or \"off\")",
            )),
            (LightPolicy::Off, _) => Ok(false),
            (_, shadows) => Ok(shadows),
        }
    }
}

#[cfg(test)]
mod tests;
