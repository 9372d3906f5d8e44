//! Staged loss schedules read from `schedules/*.toml`: each loss weight is a piecewise-linear
//! `alpha(t) = (1 - tau) from + tau to`, `tau = clamp((t - hold) / ramp, 0, 1)`, plus learning
//! rates per parameter group, the batch sizes and the iteration count. Errors name the file and
//! the TOML key; a schedule that asks for something the scene cannot feed is an error too.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Every loss term a schedule can weight.
pub const TERMS: [&str; 9] = ["rgb", "mask", "grey", "density", "sigma", "mean", "ambient", "eikonal", "curvature"];
/// Parameter groups with their own learning rate: the field's decoder (and the whole `mlp`
/// field), the Gaussians, the light, and a `grid` field's feature tables.
pub const GROUPS: [&str; 4] = ["field", "gaussians", "light", "features"];

/// Which encoding the field uses (`field::FieldConfig`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, clap::ValueEnum)]
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
    /// Whether it is on for a body that is loose or not.
    pub fn on(self, loose: bool) -> bool {
        match self {
            Switch::Fixed(on) => on,
            Switch::Auto => loose,
        }
    }
}

/// Whether the light (direction or position, and ambient) is fitted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LightPolicy {
    /// Fit it when a training light casts shadows (sun or point), skip it for uniform light.
    Auto,
    /// Always fit it: an error for a uniformly lit scene.
    Fit,
    /// Never: shading is albedo only.
    Off,
}

/// Where `umbra` looks for its default schedule, relative to the working folder...
pub const DEFAULT_PATH: &str = "schedules/default.toml";
/// ...and the copy compiled in, used when that file is not there.
pub const DEFAULT_TEXT: &str = include_str!("../schedules/default.toml");

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Schedule {
    pub file: PathBuf,
    pub iterations: usize,
    pub rays_per_batch: usize,
    pub samples_per_ray: usize,
    /// Samples per ray added where the coarse ones found density (hierarchical sampling).
    pub fine_samples_per_ray: usize,
    /// Samples per ray, without gradients, that locate the surface between the coarse and the
    /// fine samples (`render::Sampling::probe`).
    pub probe_samples_per_ray: usize,
    /// Whether the differentiable pass evaluates the field only where a sample can change a ray
    /// (`render::Sampling::cull`); absent: yes.
    pub cull_samples: bool,
    /// Points per step for the Gaussian density fit, and for Eikonal and curvature.
    pub density_points: usize,
    pub regulariser_points: usize,
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

/// A decay factor in (0, 1] (1, no decay, when absent).
fn fraction(file: &Path, table: &toml::Table, key: &str) -> Result<f64, ScheduleError> {
    match number(file, table, key, "")? {
        None => Ok(1.0),
        Some(v) if v > 0.0 && v <= 1.0 => Ok(v),
        Some(v) => Err(err(file, key, format!("must be within (0, 1], found {v}"))),
    }
}

fn number(file: &Path, table: &toml::Table, key: &str, prefix: &str) -> Result<Option<f64>, ScheduleError> {
    let full = if prefix.is_empty() { key.to_string() } else { format!("{prefix}.{key}") };
    match table.get(key) {
        None => Ok(None),
        Some(toml::Value::Integer(i)) => Ok(Some(*i as f64)),
        Some(toml::Value::Float(f)) if f.is_finite() => Ok(Some(*f)),
        Some(toml::Value::Float(f)) => Err(err(file, &full, format!("must be finite, found {f}"))),
        Some(other) => Err(err(file, &full, format!("expected a number, found {}", other.type_str()))),
    }
}

/// The largest count a schedule or `--iterations` may give (a billion iterations is weeks of
/// fitting; a larger number is a typo).
pub const MAX_COUNT: usize = 1_000_000_000;

/// Top-level settings since removed (each measured no better: docs/measurements.md), with the
/// value at which each did nothing. A run fitted before keeps them in its schedule copy: read
/// there as nothing; any other value is refused, since the fit it asks for no longer exists.
const REMOVED_SETTINGS: [(&str, &str); 7] = [
    ("gaussians_lr_decay", "1"),
    ("sample_masked_misses", "false"),
    ("loose_body_curvature", "1"),
    ("contrast_rays", "0"),
    ("light_robustness", "0"),
    ("rgb_space", "\"linear\""),
    ("pixel_rays", "1"),
];

/// `table` without the removed settings that hold the value at which they did nothing.
fn without_removed_settings(file: &Path, mut table: toml::Table) -> Result<toml::Table, ScheduleError> {
    for (key, inert) in REMOVED_SETTINGS {
        let Some(value) = table.get(key) else { continue };
        let same = match (value, inert.parse::<f64>()) {
            (toml::Value::Integer(i), Ok(v)) => *i as f64 == v,
            (toml::Value::Float(f), Ok(v)) => *f == v,
            (other, _) => other.to_string() == inert,
        };
        if !same {
            return Err(err(file, key, format!("was removed (it measured no better, docs/measurements.md); only {inert}, its old default, is still read")));
        }
        table.remove(key);
    }
    Ok(table)
}

fn count(file: &Path, table: &toml::Table, key: &str, default: usize, min: usize) -> Result<usize, ScheduleError> {
    match number(file, table, key, "")? {
        None => Ok(default),
        Some(v) if v.fract() == 0.0 && v >= min as f64 && v <= MAX_COUNT as f64 => Ok(v as usize),
        Some(v) => Err(err(file, key, format!("must be a whole number from {min} to {MAX_COUNT}, found {v}"))),
    }
}

/// Checks an iteration count given on the command line (`--iterations`) against the bounds a
/// schedule's `iterations` has.
pub fn check_iterations(n: usize) -> Result<usize, String> {
    if (1..=MAX_COUNT).contains(&n) {
        Ok(n)
    } else {
        Err(format!("--iterations {n}: must be a whole number from 1 to {MAX_COUNT}"))
    }
}

fn boolean(file: &Path, table: &toml::Table, key: &str, default: bool) -> Result<bool, ScheduleError> {
    match table.get(key) {
        None => Ok(default),
        Some(toml::Value::Boolean(b)) => Ok(*b),
        Some(other) => Err(err(file, key, format!("expected true or false, found {other}"))),
    }
}

fn parse_field(file: &Path, table: &toml::Table) -> Result<FieldSettings, ScheduleError> {
    let field = match table.get("field") {
        None => toml::Table::new(),
        Some(toml::Value::Table(t)) => t.clone(),
        Some(other) => return Err(err(file, "field", format!("expected a table, found {}", other.type_str()))),
    };
    let known = [
        "kind",
        "levels",
        "table_log2",
        "top_bones",
        "features",
        "finest_per_extent",
        "albedo_layers",
        "reach_per_extent",
        "fine_levels_from",
        "fine_levels_until",
        "root_skinning",
    ];
    // Removed (it measured no better, docs/measurements.md): read only at its old default.
    match field.get("prior_knee") {
        None | Some(toml::Value::Boolean(false)) => {}
        Some(_) => {
            return Err(err(file, "field.prior_knee", "was removed (it measured no better, docs/measurements.md); only false, its old default, is still read"))
        }
    }
    for key in field.keys().filter(|k| *k != "prior_knee") {
        if !known.contains(&key.as_str()) {
            return Err(err(file, &format!("field.{key}"), format!("unknown key (known: {})", known.join(", "))));
        }
    }
    let kind = match field.get("kind") {
        None => FieldKind::Mlp,
        Some(toml::Value::String(s)) if s == "mlp" => FieldKind::Mlp,
        Some(toml::Value::String(s)) if s == "grid" => FieldKind::Grid,
        Some(other) => return Err(err(file, "field.kind", format!("expected \"mlp\" or \"grid\", found {other}"))),
    };
    let bounded = |key: &str, lo: f64, hi: f64| -> Result<Option<f64>, ScheduleError> {
        match number(file, &field, key, "field")? {
            Some(v) if v.fract() != 0.0 || v < lo || v > hi => {
                Err(err(file, &format!("field.{key}"), format!("must be a whole number within {lo}..={hi}, found {v}")))
            }
            other => Ok(other),
        }
    };
    let settings = FieldSettings {
        kind,
        levels: bounded("levels", 1.0, 16.0)?.map(|v| v as usize),
        table_log2: bounded("table_log2", 8.0, 22.0)?.map(|v| v as u32),
        top_bones: bounded("top_bones", 1.0, 8.0)?.map(|v| v as usize),
        features: bounded("features", 1.0, 8.0)?.map(|v| v as usize),
        finest_per_extent: bounded("finest_per_extent", 10.0, 4096.0)?.map(|v| v as usize),
        albedo_layers: bounded("albedo_layers", 0.0, 4.0)?.map(|v| v as usize),
        reach_per_extent: match number(file, &field, "reach_per_extent", "field")? {
            Some(v) if !(v > 0.0 && v <= 1.0) => return Err(err(file, "field.reach_per_extent", format!("must be within (0, 1], found {v}"))),
            other => other,
        },
        fine_levels: match (bounded("fine_levels_from", 0.0, 1e9)?, bounded("fine_levels_until", 0.0, 1e9)?) {
            (None, None) => None,
            (Some(from), Some(until)) if until >= from => Some((from as usize, until as usize)),
            (Some(_), Some(_)) => return Err(err(file, "field.fine_levels_until", "must not come before fine_levels_from")),
            _ => return Err(err(file, "field.fine_levels_from", "fine_levels_from and fine_levels_until go together")),
        },
        root_skinning: match field.get("root_skinning") {
            None => None,
            Some(toml::Value::Boolean(b)) => Some(*b),
            Some(other) => return Err(err(file, "field.root_skinning", format!("expected true or false, found {other}"))),
        },
        recorded: None,
    };
    if kind == FieldKind::Mlp {
        if let Some(key) =
            ["levels", "table_log2", "top_bones", "features", "finest_per_extent", "reach_per_extent", "fine_levels_from", "fine_levels_until", "root_skinning"]
                .into_iter()
                .find(|k| field.contains_key(*k))
        {
            return Err(err(file, &format!("field.{key}"), "applies to kind = \"grid\" only"));
        }
    }
    Ok(settings)
}

impl Schedule {
    /// How a training step samples its rays.
    pub fn sampling(&self) -> crate::render::Sampling {
        crate::render::Sampling {
            coarse: self.samples_per_ray,
            probe: self.probe_samples_per_ray,
            fine: self.fine_samples_per_ray,
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

    pub fn parse(text: &str, file: &Path) -> Result<Self, ScheduleError> {
        let table: toml::Table = text.parse().map_err(|e: toml::de::Error| err(file, "(syntax)", e.to_string()))?;
        let known = [
            "iterations",
            "rays_per_batch",
            "samples_per_ray",
            "fine_samples_per_ray",
            "probe_samples_per_ray",
            "cull_samples",
            "density_points",
            "regulariser_points",
            "checkpoint_every",
            "light",
            "light_from",
            "light_stage_iterations",
            "ambient_target",
            "curvature_epsilon",
            "light_lr_decay",
            "field_lr_decay",
            "field_lr_decay_from",
            "field_average_half_life",
            "sun_search",
            "rebind_every",
            "density_at_shadow_scale",
            "error_rays",
            "footprint",
            "learning_rates",
            "losses",
            "field",
        ];
        let table = without_removed_settings(file, table)?;
        for key in table.keys() {
            if !known.contains(&key.as_str()) {
                return Err(err(file, key, format!("unknown key (known: {})", known.join(", "))));
            }
        }
        let iterations = count(file, &table, "iterations", 2000, 1)?;
        let light = match table.get("light") {
            None => LightPolicy::Auto,
            Some(toml::Value::String(s)) => match s.as_str() {
                "auto" => LightPolicy::Auto,
                "fit" => LightPolicy::Fit,
                "off" => LightPolicy::Off,
                other => return Err(err(file, "light", format!("expected \"auto\", \"fit\" or \"off\", found {other:?}"))),
            },
            Some(other) => return Err(err(file, "light", format!("expected a string, found {}", other.type_str()))),
        };
        let mut learning_rates = BTreeMap::new();
        let lr_table = match table.get("learning_rates") {
            Some(toml::Value::Table(t)) => t.clone(),
            Some(_) => return Err(err(file, "learning_rates", "expected a table")),
            None => toml::Table::new(),
        };
        for key in lr_table.keys() {
            if !GROUPS.contains(&key.as_str()) {
                return Err(err(file, &format!("learning_rates.{key}"), format!("unknown parameter group (known: {})", GROUPS.join(", "))));
            }
        }
        for (group, default) in GROUPS.iter().zip([2e-3, 5e-3, 1e-2, 1e-2]) {
            let v = number(file, &lr_table, group, "learning_rates")?.unwrap_or(default);
            if !(v > 0.0 && v < 10.0) {
                return Err(err(file, &format!("learning_rates.{group}"), format!("must be within (0, 10), found {v}")));
            }
            learning_rates.insert(group.to_string(), v);
        }
        let losses = match table.get("losses") {
            Some(toml::Value::Table(t)) => t.clone(),
            Some(_) => return Err(err(file, "losses", "expected a table of [losses.NAME] tables")),
            None => return Err(err(file, "losses", "missing: a schedule must weight at least the mask loss")),
        };
        let mut weights = BTreeMap::new();
        for (name, value) in &losses {
            if !TERMS.contains(&name.as_str()) {
                return Err(err(file, &format!("losses.{name}"), format!("unknown loss (known: {})", TERMS.join(", "))));
            }
            let key = format!("losses.{name}");
            let ramp = match value {
                // The shorthand `term = w`: errors name the key as written.
                toml::Value::Integer(i) => Ramp::constant(*i as f64),
                toml::Value::Float(f) if f.is_finite() => Ramp::constant(*f),
                toml::Value::Float(f) => return Err(err(file, &key, format!("must be finite, found {f}"))),
                toml::Value::Table(t) => {
                    for k in t.keys() {
                        if !["from", "to", "hold", "ramp"].contains(&k.as_str()) {
                            return Err(err(file, &format!("{key}.{k}"), "unknown key (known: from, to, hold, ramp)"));
                        }
                    }
                    let from = number(file, t, "from", &key)?.ok_or_else(|| err(file, &format!("{key}.from"), "missing"))?;
                    let to = number(file, t, "to", &key)?.unwrap_or(from);
                    let hold = number(file, t, "hold", &key)?.unwrap_or(0.0);
                    let ramp = number(file, t, "ramp", &key)?.unwrap_or(0.0);
                    Ramp { from, to, hold, ramp }
                }
                other => return Err(err(file, &key, format!("expected a number or a table, found {}", other.type_str()))),
            };
            let shorthand = !value.is_table();
            for (field, v) in [("from", ramp.from), ("to", ramp.to), ("hold", ramp.hold), ("ramp", ramp.ramp)] {
                if v < 0.0 {
                    let at = if shorthand { key.clone() } else { format!("{key}.{field}") };
                    return Err(err(file, &at, format!("must be >= 0, found {v}")));
                }
            }
            if ramp.hold >= iterations as f64 && ramp.from == 0.0 && ramp.to != 0.0 {
                return Err(err(file, &format!("{key}.hold"), format!("{} is past the last iteration ({iterations}): the loss would never start", ramp.hold)));
            }
            weights.insert(name.clone(), ramp);
        }
        if !weights.get("mask").map(|r| r.ever_active(iterations)).unwrap_or(false) {
            return Err(err(file, "losses.mask", "the mask loss must be active: nothing else fits the silhouette"));
        }
        for term in TERMS {
            weights.entry(term.to_string()).or_insert(Ramp::constant(0.0));
        }
        let field = parse_field(file, &table)?;
        let schedule = Schedule {
            file: file.to_path_buf(),
            iterations,
            rays_per_batch: count(file, &table, "rays_per_batch", 512, 1)?,
            samples_per_ray: count(file, &table, "samples_per_ray", 24, 2)?,
            fine_samples_per_ray: count(file, &table, "fine_samples_per_ray", 0, 0)?,
            probe_samples_per_ray: count(file, &table, "probe_samples_per_ray", 0, 0)?,
            cull_samples: boolean(file, &table, "cull_samples", true)?,
            density_points: count(file, &table, "density_points", 256, 0)?,
            regulariser_points: count(file, &table, "regulariser_points", 128, 0)?,
            checkpoint_every: count(file, &table, "checkpoint_every", 250, 1)?,
            light,
            light_from: count(file, &table, "light_from", 0, 0)?,
            light_stage_iterations: count(file, &table, "light_stage_iterations", 0, 0)?,
            ambient_target: number(file, &table, "ambient_target", "")?.unwrap_or(0.1),
            curvature_epsilon: number(file, &table, "curvature_epsilon", "")?.unwrap_or(0.02),
            light_lr_decay: fraction(file, &table, "light_lr_decay")?,
            field_lr_decay: fraction(file, &table, "field_lr_decay")?,
            field_lr_decay_from: count(file, &table, "field_lr_decay_from", 0, 0)?,
            field_average_half_life: match number(file, &table, "field_average_half_life", "")? {
                None => 0.0,
                Some(v) if v >= 0.0 && v.is_finite() => v,
                Some(v) => return Err(err(file, "field_average_half_life", format!("must be a non-negative number of iterations, found {v}"))),
            },
            sun_search: count(file, &table, "sun_search", 0, 0)?,
            rebind_every: count(file, &table, "rebind_every", 0, 0)?,
            density_at_shadow_scale: match table.get("density_at_shadow_scale") {
                Some(toml::Value::String(s)) if s == "auto" => Switch::Auto,
                Some(toml::Value::String(s)) => return Err(err(file, "density_at_shadow_scale", format!("must be true, false or \"auto\", found \"{s}\""))),
                _ => Switch::Fixed(boolean(file, &table, "density_at_shadow_scale", false)?),
            },
            error_rays: match table.get("error_rays") {
                Some(toml::Value::String(s)) if s == "auto" => ErrorRays::Auto,
                Some(toml::Value::String(s)) => return Err(err(file, "error_rays", format!("must be \"auto\" or a share within [0, 1], found \"{s}\""))),
                _ => match number(file, &table, "error_rays", "")? {
                    None => ErrorRays::Share(0.0),
                    Some(v) if (0.0..=1.0).contains(&v) => ErrorRays::Share(v),
                    Some(v) => return Err(err(file, "error_rays", format!("must be \"auto\" or a share within [0, 1], found {v}"))),
                },
            },
            footprint: match table.get("footprint") {
                None => None,
                Some(toml::Value::String(s)) if s == "auto" => None,
                Some(toml::Value::String(s)) if s == "area" => Some(crate::scene::Footprint::Area),
                Some(toml::Value::String(s)) if s == "centre" => Some(crate::scene::Footprint::Centre),
                Some(other) => return Err(err(file, "footprint", format!("expected \"auto\", \"area\" or \"centre\", found {other}"))),
            },
            learning_rates,
            weights,
            field,
        };
        // A weighted loss with no points to evaluate it on would be dropped silently.
        for (points, key, terms) in
            [(schedule.density_points, "density_points", &["density"][..]), (schedule.regulariser_points, "regulariser_points", &["eikonal", "curvature"][..])]
        {
            if let Some(term) = terms.iter().find(|t| schedule.weights.get(**t).is_some_and(|r| r.ever_active(iterations))) {
                if points == 0 {
                    return Err(err(
                        file,
                        key,
                        format!("is 0 while losses.{term} has weight: the {term} loss would silently do nothing (set its weight to 0 instead)"),
                    ));
                }
            }
        }
        Ok(schedule)
    }

    pub fn weight(&self, term: &str, iteration: usize) -> f64 {
        self.weights.get(term).map(|r| r.at(iteration)).unwrap_or(0.0)
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
            "field" | "features" => (self.field_lr_decay, self.field_lr_decay_from),
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
mod tests {
    use super::*;

    const DEFAULT: &str = DEFAULT_TEXT;

    #[test]
    fn default_schedule_parses_and_stages_in_order() {
        let s = Schedule::parse(DEFAULT, Path::new("schedules/default.toml")).unwrap();
        assert!(s.weight("grey", 0) > 0.0 && s.weight("rgb", 0) == 0.0, "segment 1 fits a grey silhouette");
        assert_eq!(s.weight("density", 0), 0.0);
        let late = s.iterations - 1;
        assert!(s.weight("rgb", late) > 0.9 && s.weight("grey", late) < 1e-9, "segment 3 fits colour");
        assert!(s.weight("density", late) > 0.0);
    }

    #[test]
    fn ramps_interpolate_between_hold_and_hold_plus_ramp() {
        let r = Ramp { from: 1.0, to: 0.0, hold: 100.0, ramp: 50.0 };
        assert_eq!(r.at(0), 1.0);
        assert_eq!(r.at(100), 1.0);
        assert_eq!(r.at(125), 0.5);
        assert_eq!(r.at(150), 0.0);
        assert_eq!(r.at(1000), 0.0);
    }

    fn error_of(text: &str) -> ScheduleError {
        Schedule::parse(text, Path::new("s.toml")).unwrap_err()
    }

    #[test]
    fn errors_name_the_file_and_key() {
        assert_eq!(error_of("iterations = -3\n[losses]\nmask = 1.0").key, "iterations");
        assert_eq!(error_of("iterations = 10\nbogus = 1\n[losses]\nmask = 1.0").key, "bogus");
        assert_eq!(error_of("[losses]\nmask = 1.0\nshine = 2.0").key, "losses.shine");
        assert_eq!(error_of("[losses]\nmask = 1.0\n[losses.rgb]\nfrom = 0.0\nto = 1.0\nhold = -5").key, "losses.rgb.hold");
        assert_eq!(error_of("iterations = 100\n[losses]\nmask = 1.0\n[losses.rgb]\nfrom = 0.0\nto = 1.0\nhold = 500").key, "losses.rgb.hold");
        assert_eq!(error_of("[losses]\nrgb = 1.0").key, "losses.mask");
        assert_eq!(error_of("[learning_rates]\nfield = 0\n[losses]\nmask = 1.0").key, "learning_rates.field");
        assert_eq!(error_of("[learning_rates]\nbrain = 1e-3\n[losses]\nmask = 1.0").key, "learning_rates.brain");
        assert_eq!(error_of("light = \"sometimes\"\n[losses]\nmask = 1.0").key, "light");
        assert_eq!(error_of("footprint = \"blurry\"\n[losses]\nmask = 1.0").key, "footprint");
        assert_eq!(error_of("[losses]\nmask = \"lots\"").key, "losses.mask");
        assert_eq!(error_of("[field]\nkind = \"voxels\"\n[losses]\nmask = 1.0").key, "field.kind");
        assert_eq!(error_of("[field]\nkind = \"grid\"\nlevels = 0\n[losses]\nmask = 1.0").key, "field.levels");
        assert_eq!(error_of("[field]\nlevels = 4\n[losses]\nmask = 1.0").key, "field.levels");
        assert_eq!(error_of("[field]\nkind = \"grid\"\ncells = 4\n[losses]\nmask = 1.0").key, "field.cells");
        assert_eq!(error_of("[losses]\nmask = nan").key, "losses.mask");
        assert_eq!(error_of("[losses]\nmask = 1\neikonal = -1").key, "losses.eikonal", "a shorthand's error names the key as written");
        assert_eq!(error_of("density_points = 0\n[losses]\nmask = 1.0\ndensity = 0.5").key, "density_points");
        assert_eq!(error_of("regulariser_points = 0\n[losses]\nmask = 1.0\ncurvature = 0.1").key, "regulariser_points");
        assert!(Schedule::parse("regulariser_points = 0\n[losses]\nmask = 1.0", Path::new("s.toml")).is_ok(), "no weight, no points needed");
        assert_eq!(error_of("[field]\nkind = \"grid\"\nreach_per_extent = 0\n[losses]\nmask = 1.0").key, "field.reach_per_extent");
        assert_eq!(error_of("[field]\nreach_per_extent = 0.2\n[losses]\nmask = 1.0").key, "field.reach_per_extent");
        assert_eq!(error_of("density_at_shadow_scale = \"yes\"\n[losses]\nmask = 1.0").key, "density_at_shadow_scale");
        let shadow_scale = |text: &str| Schedule::parse(text, Path::new("s.toml")).map(|s| (s.density_at_shadow_scale, s.error_rays)).ok();
        assert_eq!(shadow_scale("[losses]\nmask = 1.0"), Some((Switch::Fixed(false), ErrorRays::Share(0.0))), "both off unless a schedule asks");
        assert_eq!(shadow_scale("density_at_shadow_scale = true\nerror_rays = 0.5\n[losses]\nmask = 1.0"), Some((Switch::Fixed(true), ErrorRays::Share(0.5))));
        assert_eq!(shadow_scale("density_at_shadow_scale = \"auto\"\nerror_rays = \"auto\"\n[losses]\nmask = 1.0"), Some((Switch::Auto, ErrorRays::Auto)));
        assert_eq!((Switch::Auto.on(true), Switch::Auto.on(false), Switch::Fixed(true).on(false), Switch::Fixed(false).on(true)), (true, false, true, false));
        assert_eq!(error_of("error_rays = \"many\"\n[losses]\nmask = 1.0").key, "error_rays");
        assert_eq!((ErrorRays::Auto.share(true), ErrorRays::Auto.share(false), ErrorRays::Share(0.2).share(true)), (LOOSE_ERROR_RAYS, 0.0, 0.2));
        assert_eq!(error_of("cull_samples = \"yes\"\n[losses]\nmask = 1.0").key, "cull_samples");
        let parsed = |text: &str| Schedule::parse(text, Path::new("s.toml")).map(|s| s.cull_samples).ok();
        assert_eq!(parsed("[losses]\nmask = 1.0"), Some(true), "culling is on unless a schedule turns it off");
        assert_eq!(parsed("cull_samples = false\n[losses]\nmask = 1.0"), Some(false));
        assert_eq!(error_of("error_rays = -0.5\n[losses]\nmask = 1.0").key, "error_rays");
        // Settings removed since: read as nothing in a run's copy at the value that did nothing,
        // refused at any other.
        assert!(Schedule::parse("contrast_rays = 0.0\nrgb_space = \"linear\"\n[losses]\nmask = 1.0", Path::new("s.toml")).is_ok());
        let removed = error_of("contrast_rays = 0.5\n[losses]\nmask = 1.0");
        assert!(removed.key == "contrast_rays" && removed.message.contains("removed"), "{removed}");
        assert_eq!(error_of("[field]\nkind = \"grid\"\nfeatures = 0\n[losses]\nmask = 1.0").key, "field.features");
        assert_eq!(error_of("[field]\nkind = \"grid\"\nfinest_per_extent = 2.5\n[losses]\nmask = 1.0").key, "field.finest_per_extent");
        assert_eq!(error_of("[field]\nfinest_per_extent = 320\n[losses]\nmask = 1.0").key, "field.finest_per_extent");
        assert_eq!(error_of("[field]\nalbedo_layers = 9\n[losses]\nmask = 1.0").key, "field.albedo_layers");
        let shaped =
            Schedule::parse("[field]\nkind = \"grid\"\nfeatures = 4\nfinest_per_extent = 320\nalbedo_layers = 0\n[losses]\nmask = 1.0", Path::new("s.toml"))
                .unwrap();
        assert_eq!((shaped.field.features, shaped.field.finest_per_extent, shaped.field.albedo_layers), (Some(4), Some(320), Some(0)));
        let mlp = Schedule::parse("[field]\nkind = \"mlp\"\nalbedo_layers = 1\n[losses]\nmask = 1.0", Path::new("s.toml")).unwrap();
        assert_eq!(mlp.field.albedo_layers, Some(1), "either field may decode the albedo on its own");
        let loose = Schedule::parse("[field]\nkind = \"grid\"\nreach_per_extent = 0.2\n[losses]\nmask = 1.0", Path::new("s.toml")).unwrap();
        assert!(loose.field.reach_per_extent == Some(0.2));
        let e = error_of("iterations = [");
        assert!(e.to_string().starts_with("s.toml: (syntax)"), "{e}");
    }

    #[test]
    fn coarse_to_fine_opens_the_finer_half_of_the_levels_between_its_iterations() {
        let s =
            Schedule::parse("[field]\nkind = \"grid\"\nfine_levels_from = 100\nfine_levels_until = 200\n[losses]\nmask = 1.0", Path::new("c.toml")).unwrap();
        assert_eq!(s.active_levels(8, 0), 4.0);
        assert_eq!(s.active_levels(8, 100), 4.0);
        assert_eq!(s.active_levels(8, 150), 6.0);
        assert_eq!(s.active_levels(8, 500), 8.0);
        let all = Schedule::parse("[field]\nkind = \"grid\"\n[losses]\nmask = 1.0", Path::new("a.toml")).unwrap();
        assert_eq!(all.active_levels(8, 0), 8.0);
        assert_eq!(error_of("[field]\nkind = \"grid\"\nfine_levels_from = 100\n[losses]\nmask = 1.0").key, "field.fine_levels_from");
        assert_eq!(error_of("[field]\nkind = \"grid\"\nfine_levels_from = 100\nfine_levels_until = 50\n[losses]\nmask = 1.0").key, "field.fine_levels_until");
        // The prior's knee: a grid's, true or false.
        // The removed knee is read at its old default, refused otherwise.
        assert!(Schedule::parse("[field]\nkind = \"grid\"\nprior_knee = false\n[losses]\nmask = 1.0", Path::new("k.toml")).is_ok());
        assert_eq!(error_of("[field]\nkind = \"grid\"\nprior_knee = true\n[losses]\nmask = 1.0").key, "field.prior_knee");
    }

    #[test]
    fn light_fitting_on_a_uniform_scene_is_an_error_that_says_why() {
        let fit = Schedule::parse("light = \"fit\"\n[losses]\nmask = 1.0", Path::new("fit.toml")).unwrap();
        let e = fit.check_against(false).unwrap_err();
        assert!(e.to_string().contains("fit.toml: light:") && e.to_string().contains("uniformly lit"), "{e}");
        assert!(fit.check_against(true).unwrap());
        let auto = Schedule::parse("[losses]\nmask = 1.0", Path::new("a.toml")).unwrap();
        assert!(!auto.check_against(false).unwrap());
        assert!(auto.check_against(true).unwrap());
    }

    #[test]
    fn learning_rates_decay_exponentially_over_their_segment() {
        let s = Schedule::parse(
            "iterations = 1000\nlight_from = 200\nlight_lr_decay = 0.1\nfield_lr_decay = 0.01\nfield_lr_decay_from = 600\n[learning_rates]\nfield = 1.0\nfeatures = 1.0\nlight = 1.0\ngaussians = 1.0\n[losses]\nmask = 1.0",
            Path::new("d.toml"),
        )
        .unwrap();
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        assert!(close(s.learning_rate("field", 600), 1.0) && close(s.learning_rate("field", 800), 0.1) && close(s.learning_rate("field", 1000), 0.01));
        assert!(close(s.learning_rate("features", 800), 0.1), "the feature tables decay with the field");
        assert!(close(s.learning_rate("light", 200), 1.0) && close(s.learning_rate("light", 600), 0.1f64.sqrt()));
        assert!(close(s.learning_rate("gaussians", 999), 1.0), "the Gaussians keep their rate");
        assert_eq!(error_of("field_lr_decay = 0\n[losses]\nmask = 1.0").key, "field_lr_decay");
        assert_eq!(error_of("sun_search = -1\n[losses]\nmask = 1.0").key, "sun_search");
    }

    /// The top-level settings in which two schedules differ, in name order.
    fn differing_settings(a: &Schedule, b: &Schedule) -> Vec<String> {
        let (a, b) = (serde_json::to_value(a).unwrap(), serde_json::to_value(b).unwrap());
        a.as_object().unwrap().iter().filter(|(k, v)| b.get(k.as_str()) != Some(v)).map(|(k, _)| k.clone()).collect()
    }

    /// The shipped longer schedule is the default but for its length and where the field's
    /// learning rates start to fall (a stale copy of an older default would differ in more).
    #[test]
    fn the_detail_schedule_is_the_default_made_longer() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("schedules/detail.toml");
        let detail = Schedule::parse(&std::fs::read_to_string(&path).unwrap(), Path::new("x.toml")).unwrap();
        let default = Schedule::parse(DEFAULT, Path::new("x.toml")).unwrap();
        assert!(detail.iterations > default.iterations && detail.field_lr_decay_from > default.field_lr_decay_from);
        assert!(detail.iterations - detail.field_lr_decay_from >= default.iterations - default.field_lr_decay_from, "a tail no shorter");
        assert_eq!(differing_settings(&detail, &default), ["field_lr_decay_from", "iterations"]);
        // It is the default stretched to its length, to the nearest hundred.
        let stretched = default.stretched(detail.iterations);
        assert_eq!(stretched.iterations, detail.iterations);
        assert!(
            stretched.field_lr_decay_from.abs_diff(detail.field_lr_decay_from) <= 50,
            "{} vs {}",
            stretched.field_lr_decay_from,
            detail.field_lr_decay_from
        );
        assert!(differing_settings(&stretched, &detail).iter().all(|s| *s == "field_lr_decay_from"));
    }

    /// Every shipped ablation parses and differs from the default schedule (in its settings,
    /// not only its comments).
    #[test]
    fn shipped_ablations_parse_and_differ_from_the_default() {
        let folder = Path::new(env!("CARGO_MANIFEST_DIR")).join("schedules/ablations");
        let default = Schedule::parse(DEFAULT, Path::new("x.toml")).unwrap();
        let mut count = 0;
        for entry in std::fs::read_dir(&folder).unwrap().flatten() {
            let path = entry.path();
            let text = std::fs::read_to_string(&path).unwrap();
            let ablation = Schedule::parse(&text, Path::new("x.toml")).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            assert_ne!(ablation, default, "{} is the default schedule", path.display());
            // One respect: the settings that differ share one top-level key (a stale copy of
            // an older default would differ in more).
            let keys = differing_settings(&ablation, &default);
            assert_eq!(keys.len(), 1, "{} differs from the default in {keys:?}", path.display());
            count += 1;
        }
        assert!(count >= 8, "{count} ablations in {}", folder.display());
    }
}
