//! A schedule file as written: every TOML key a typed, optional field read by serde with
//! unknown keys refused, then a validation pass that fills the defaults and checks what types
//! cannot say (ranges, keys that go together, a loss that must be active). Every error names
//! the file and the key's TOML path.

use std::collections::BTreeMap;
use std::path::Path;

use serde::de::{self, Deserializer, MapAccess, Visitor};
use serde::Deserialize;

use super::{err, ErrorRays, FieldKind, FieldSettings, LightPolicy, Ramp, Schedule, ScheduleError, Switch, GROUPS, MAX_COUNT};
use crate::scene::Footprint;

/// The top level of a schedule file.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct ScheduleFile {
    iterations: Option<Count>,
    rays_per_batch: Option<Count>,
    samples_per_ray: Option<Count>,
    fine_samples_per_ray: Option<Count>,
    early_fine_samples_per_ray: Option<Count>,
    early_samples_until: Option<Count>,
    probe_samples_per_ray: Option<Count>,
    early_probe_samples_per_ray: Option<Count>,
    cull_samples: Option<bool>,
    density_points: Option<Count>,
    regulariser_points: Option<Count>,
    lazy_regularisation: Option<Switch>,
    checkpoint_every: Option<Count>,
    light: Option<LightPolicy>,
    light_from: Option<Count>,
    light_stage_iterations: Option<Count>,
    ambient_target: Option<f64>,
    curvature_epsilon: Option<f64>,
    light_lr_decay: Option<f64>,
    field_lr_decay: Option<f64>,
    field_lr_decay_from: Option<Count>,
    field_average_half_life: Option<f64>,
    sun_search: Option<Count>,
    rebind_every: Option<Count>,
    density_at_shadow_scale: Option<Switch>,
    refine_motion: Option<Switch>,
    refine_cameras: Option<Switch>,
    error_rays: Option<ErrorRays>,
    footprint: Option<FootprintChoice>,
    learning_rates: Option<LearningRates>,
    losses: Option<Losses>,
    field: Option<FieldFile>,
}

#[derive(Deserialize, Clone, Copy)]
#[serde(rename_all = "lowercase")]
enum FootprintChoice {
    Auto,
    Area,
    Centre,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct LearningRates {
    field: Option<f64>,
    gaussians: Option<f64>,
    light: Option<f64>,
    features: Option<f64>,
    /// The motion's corrections (radians a step, and the skeleton's shift in levers:
    /// `train::motion`), not a parameter group of the model.
    motion: Option<f64>,
    /// The cameras' turns (radians a step: `train::camera_pose`), not a parameter group of the
    /// model.
    cameras: Option<f64>,
}

/// The motion's learning rate unless a schedule gives one: Adam's step in radians (0.3
/// degrees), so that a tracker's few degrees are crossed within a frame's first dozen visits.
/// Against 2e-3 on a 64-pixel human whose training motion is 2.5 degrees and 1 cm off (seed 0):
/// the refined joints' error 2.12 -> 1.90 degrees (given 3.46), foreground novel pose 20.56 ->
/// 22.03 dB; on the exact human-sun 27.71 -> 28.03 dB.
pub const MOTION_LEARNING_RATE: f64 = 5e-3;

/// The cameras' learning rate unless a schedule gives one: Adam's step in radians (0.01
/// degrees), a tenth of a calibration's error of 0.1 degrees: every batch moves every camera
/// it draws from, about a thousand times over a fit, so a small rate still crosses a degree
/// and leaves little jitter at the end.
pub const CAMERA_LEARNING_RATE: f64 = 2e-4;

impl LearningRates {
    /// Each group (`GROUPS`'s order) with its rate, or its default.
    fn rates(&self) -> [(&'static str, f64); 4] {
        let given = [self.field, self.gaussians, self.light, self.features];
        let defaults = [2e-3, 5e-3, 1e-2, 1e-2];
        std::array::from_fn(|k| (GROUPS[k], given[k].unwrap_or(defaults[k])))
    }
}

/// `[losses]`: a weight per term, by the term's name (`losses::TERMS`).
type Losses = BTreeMap<String, Weight>;

/// The terms given, in `losses::TERMS`' order; a name that is no term is refused.
fn given(losses: &Losses, file: &Path) -> Result<Vec<(&'static str, Weight)>, ScheduleError> {
    if let Some(unknown) = losses.keys().find(|name| crate::losses::term(name).is_none()) {
        let names: Vec<&str> = crate::losses::names().collect();
        return Err(err(file, &format!("losses.{unknown}"), format!("unknown loss term (the terms are {})", names.join(", "))));
    }
    Ok(crate::losses::TERMS.iter().filter_map(|t| losses.get(t.name).map(|w| (t.name, *w))).collect())
}

/// A loss weight as written: `term = w`, or a `[losses.term]` table of a ramp.
#[derive(Clone, Copy)]
enum Weight {
    Constant(f64),
    Ramp(RampTable),
}

#[derive(Deserialize, Clone, Copy)]
#[serde(deny_unknown_fields)]
struct RampTable {
    from: f64,
    to: Option<f64>,
    hold: Option<f64>,
    ramp: Option<f64>,
}

/// A count as written: a whole number, or a float with no fraction (`2e3`), checked against its
/// range by the validation (so the error says the range).
#[derive(Clone, Copy)]
struct Count(f64);

impl<'de> Deserialize<'de> for Count {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_any(OneOf { number: Some(Count), ..OneOf::new("a whole number") })
    }
}

impl Count {
    /// The count when it is whole and within `min..=max`.
    fn within(self, min: usize, max: usize) -> Option<usize> {
        let v = self.0;
        (v.fract() == 0.0 && v >= min as f64 && v <= max as f64).then_some(v as usize)
    }
}

/// A visitor for the values a schedule writes as one of a few TOML types: each reading that is
/// `None` refuses its type with `expecting` in the message.
struct OneOf<T> {
    expecting: &'static str,
    number: Option<fn(f64) -> T>,
    boolean: Option<fn(bool) -> T>,
    text: Option<fn(&str) -> Option<T>>,
    ramp: Option<fn(RampTable) -> T>,
}

impl<T> OneOf<T> {
    fn new(expecting: &'static str) -> Self {
        Self { expecting, number: None, boolean: None, text: None, ramp: None }
    }
}

impl<'de, T> Visitor<'de> for OneOf<T> {
    type Value = T;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str(self.expecting)
    }
    fn visit_i64<E: de::Error>(self, v: i64) -> Result<T, E> {
        self.number.map(|read| read(v as f64)).ok_or_else(|| E::invalid_type(de::Unexpected::Signed(v), &self))
    }
    fn visit_u64<E: de::Error>(self, v: u64) -> Result<T, E> {
        self.number.map(|read| read(v as f64)).ok_or_else(|| E::invalid_type(de::Unexpected::Unsigned(v), &self))
    }
    fn visit_f64<E: de::Error>(self, v: f64) -> Result<T, E> {
        self.number.map(|read| read(v)).ok_or_else(|| E::invalid_type(de::Unexpected::Float(v), &self))
    }
    fn visit_bool<E: de::Error>(self, v: bool) -> Result<T, E> {
        self.boolean.map(|read| read(v)).ok_or_else(|| E::invalid_type(de::Unexpected::Bool(v), &self))
    }
    fn visit_str<E: de::Error>(self, v: &str) -> Result<T, E> {
        self.text.and_then(|read| read(v)).ok_or_else(|| E::invalid_value(de::Unexpected::Str(v), &self))
    }
    fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<T, A::Error> {
        let Some(read) = self.ramp else {
            return Err(de::Error::invalid_type(de::Unexpected::Map, &self));
        };
        RampTable::deserialize(de::value::MapAccessDeserializer::new(map)).map(read)
    }
}

impl<'de> Deserialize<'de> for Weight {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let visitor = OneOf { number: Some(Weight::Constant), ramp: Some(Weight::Ramp), ..OneOf::new("a number or a table of from, to, hold and ramp") };
        d.deserialize_any(visitor)
    }
}

impl<'de> Deserialize<'de> for Switch {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let auto = |s: &str| (s == "auto").then_some(Switch::Auto);
        d.deserialize_any(OneOf { boolean: Some(Switch::Fixed), text: Some(auto), ..OneOf::new("true, false or \"auto\"") })
    }
}

impl<'de> Deserialize<'de> for ErrorRays {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let auto = |s: &str| (s == "auto").then_some(ErrorRays::Auto);
        d.deserialize_any(OneOf { number: Some(ErrorRays::Share), text: Some(auto), ..OneOf::new("\"auto\" or a share within [0, 1]") })
    }
}

/// `[field]`.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct FieldFile {
    kind: Option<FieldKind>,
    levels: Option<Count>,
    table_log2: Option<Count>,
    top_bones: Option<Count>,
    features: Option<Count>,
    finest_per_extent: Option<Count>,
    albedo_layers: Option<Count>,
    reach_per_extent: Option<f64>,
    fine_levels_from: Option<Count>,
    fine_levels_until: Option<Count>,
    root_skinning: Option<bool>,
}

/// Reads and checks a schedule's text; `file` names it in errors.
pub(super) fn parse(text: &str, file: &Path) -> Result<Schedule, ScheduleError> {
    let document = toml::Deserializer::parse(text).map_err(|e| err(file, "(syntax)", located(text, e.message(), e.span())))?;
    let written: ScheduleFile = serde_path_to_error::deserialize(document).map_err(|e| {
        let key = key_of(e.path(), e.inner().message());
        err(file, &key, located(text, e.inner().message(), e.inner().span()))
    })?;
    validate(written, file)
}

/// The TOML path of a deserialisation error: the path serde reached, and for an unknown key
/// the key itself.
fn key_of(path: &serde_path_to_error::Path, message: &str) -> String {
    let reached = path.to_string();
    let unknown = message.strip_prefix("unknown field `").and_then(|rest| rest.split('`').next());
    match unknown {
        Some(key) if reached == "." || reached.is_empty() => key.to_string(),
        Some(key) if !reached.ends_with(key) => format!("{reached}.{key}"),
        _ => reached,
    }
}

/// `message`, with the line it points at when the span is known.
fn located(text: &str, message: &str, span: Option<std::ops::Range<usize>>) -> String {
    // serde's words for Rust's types, in a schedule's.
    let message = message
        .trim_end()
        .replace("unknown field", "unknown key")
        .replace("expected usize", "expected a whole number")
        .replace("expected u32", "expected a whole number")
        .replace("expected f64", "expected a number")
        .replace("expected a boolean", "expected true or false");
    match span {
        Some(span) if span.start <= text.len() => format!("{message} (line {})", text[..span.start].matches('\n').count() + 1),
        _ => message.to_string(),
    }
}

/// The schedule a file asks for, its defaults filled in and its values checked.
fn validate(written: ScheduleFile, file: &Path) -> Result<Schedule, ScheduleError> {
    let count = |key: &str, value: Option<Count>, default: usize, min: usize| match value {
        None => Ok(default),
        Some(v) => v.within(min, MAX_COUNT).ok_or_else(|| err(file, key, format!("must be a whole number from {min} to {MAX_COUNT}, found {}", v.0))),
    };
    let finite = |key: &str, value: Option<f64>| match value {
        Some(v) if !v.is_finite() => Err(err(file, key, format!("must be finite, found {v}"))),
        other => Ok(other),
    };
    let fraction = |key: &str, value: Option<f64>| match finite(key, value)? {
        None => Ok(1.0),
        Some(v) if v > 0.0 && v <= 1.0 => Ok(v),
        Some(v) => Err(err(file, key, format!("must be within (0, 1], found {v}"))),
    };
    let iterations = count("iterations", written.iterations, 2000, 1)?;
    let fine = count("fine_samples_per_ray", written.fine_samples_per_ray, 0, 0)?;
    let probe = count("probe_samples_per_ray", written.probe_samples_per_ray, 0, 0)?;
    let schedule = Schedule {
        file: file.to_path_buf(),
        iterations,
        rays_per_batch: count("rays_per_batch", written.rays_per_batch, 512, 1)?,
        samples_per_ray: count("samples_per_ray", written.samples_per_ray, 24, 2)?,
        fine_samples_per_ray: fine,
        early_fine_samples_per_ray: count("early_fine_samples_per_ray", written.early_fine_samples_per_ray, fine, 0)?,
        early_samples_until: count("early_samples_until", written.early_samples_until, 0, 0)?,
        probe_samples_per_ray: probe,
        early_probe_samples_per_ray: count("early_probe_samples_per_ray", written.early_probe_samples_per_ray, probe, 0)?,
        cull_samples: written.cull_samples.unwrap_or(true),
        density_points: count("density_points", written.density_points, 256, 0)?,
        regulariser_points: count("regulariser_points", written.regulariser_points, 128, 0)?,
        lazy_regularisation: written.lazy_regularisation.unwrap_or(Switch::Fixed(false)),
        // Unresolved until a fit knows its body (`Schedule::with_lazy_regularisation`).
        regularise_every: super::regularise_every(written.lazy_regularisation.unwrap_or(Switch::Fixed(false)), false),
        checkpoint_every: count("checkpoint_every", written.checkpoint_every, 250, 1)?,
        light: written.light.unwrap_or(LightPolicy::Auto),
        light_from: count("light_from", written.light_from, 0, 0)?,
        light_stage_iterations: count("light_stage_iterations", written.light_stage_iterations, 0, 0)?,
        ambient_target: finite("ambient_target", written.ambient_target)?.unwrap_or(0.1),
        curvature_epsilon: finite("curvature_epsilon", written.curvature_epsilon)?.unwrap_or(0.02),
        light_lr_decay: fraction("light_lr_decay", written.light_lr_decay)?,
        field_lr_decay: fraction("field_lr_decay", written.field_lr_decay)?,
        field_lr_decay_from: count("field_lr_decay_from", written.field_lr_decay_from, 0, 0)?,
        field_average_half_life: match finite("field_average_half_life", written.field_average_half_life)? {
            None => 0.0,
            Some(v) if v >= 0.0 => v,
            Some(v) => return Err(err(file, "field_average_half_life", format!("must be a non-negative number of iterations, found {v}"))),
        },
        sun_search: count("sun_search", written.sun_search, 0, 0)?,
        rebind_every: count("rebind_every", written.rebind_every, 0, 0)?,
        density_at_shadow_scale: written.density_at_shadow_scale.unwrap_or(Switch::Fixed(false)),
        refine_motion: written.refine_motion.unwrap_or(Switch::Fixed(false)),
        refine_cameras: written.refine_cameras.unwrap_or(Switch::Fixed(false)),
        error_rays: match written.error_rays {
            None => ErrorRays::Share(0.0),
            Some(ErrorRays::Share(v)) if !(0.0..=1.0).contains(&v) => {
                return Err(err(file, "error_rays", format!("must be \"auto\" or a share within [0, 1], found {v}")))
            }
            Some(rays) => rays,
        },
        footprint: match written.footprint {
            None | Some(FootprintChoice::Auto) => None,
            Some(FootprintChoice::Area) => Some(Footprint::Area),
            Some(FootprintChoice::Centre) => Some(Footprint::Centre),
        },
        learning_rates: learning_rates(written.learning_rates.unwrap_or_default(), file)?,
        weights: weights(written.losses, iterations, file)?,
        field: field(written.field.unwrap_or_default(), file)?,
    };
    check_points(&schedule)?;
    Ok(schedule)
}

fn learning_rates(written: LearningRates, file: &Path) -> Result<BTreeMap<String, f64>, ScheduleError> {
    let mut rates = BTreeMap::new();
    for (group, rate) in written.rates() {
        if !(rate > 0.0 && rate < 10.0) {
            return Err(err(file, &format!("learning_rates.{group}"), format!("must be within (0, 10), found {rate}")));
        }
        rates.insert(group.to_string(), rate);
    }
    let motion = written.motion.unwrap_or(MOTION_LEARNING_RATE);
    if !(motion > 0.0 && motion < 1.0) {
        return Err(err(file, "learning_rates.motion", format!("must be within (0, 1), found {motion}")));
    }
    rates.insert("motion".into(), motion);
    let cameras = written.cameras.unwrap_or(CAMERA_LEARNING_RATE);
    if !(cameras > 0.0 && cameras < 1.0) {
        return Err(err(file, "learning_rates.cameras", format!("must be within (0, 1), found {cameras}")));
    }
    rates.insert("cameras".into(), cameras);
    Ok(rates)
}

/// Every term's ramp (absent ones at zero), checked.
fn weights(losses: Option<Losses>, iterations: usize, file: &Path) -> Result<BTreeMap<String, Ramp>, ScheduleError> {
    let losses = losses.ok_or_else(|| err(file, "losses", "missing: a schedule must weight at least the mask loss"))?;
    let mut weights = BTreeMap::new();
    for (name, weight) in given(&losses, file)? {
        let key = format!("losses.{name}");
        let (ramp, shorthand) = match weight {
            Weight::Constant(v) => (Ramp::constant(v), true),
            Weight::Ramp(t) => (Ramp { from: t.from, to: t.to.unwrap_or(t.from), hold: t.hold.unwrap_or(0.0), ramp: t.ramp.unwrap_or(0.0) }, false),
        };
        for (part, v) in [("from", ramp.from), ("to", ramp.to), ("hold", ramp.hold), ("ramp", ramp.ramp)] {
            // A shorthand's error names the key as written.
            let at = if shorthand { key.clone() } else { format!("{key}.{part}") };
            if !v.is_finite() {
                return Err(err(file, &at, format!("must be finite, found {v}")));
            }
            if v < 0.0 {
                return Err(err(file, &at, format!("must be >= 0, found {v}")));
            }
        }
        if ramp.hold >= iterations as f64 && ramp.from == 0.0 && ramp.to != 0.0 {
            return Err(err(file, &format!("{key}.hold"), format!("{} is past the last iteration ({iterations}): the loss would never start", ramp.hold)));
        }
        weights.insert(name.to_string(), ramp);
    }
    if !weights.get("mask").is_some_and(|r| r.ever_active(iterations)) {
        return Err(err(file, "losses.mask", "the mask loss must be active: nothing else fits the silhouette"));
    }
    for term in crate::losses::names() {
        weights.entry(term.to_string()).or_insert(Ramp::constant(0.0));
    }
    Ok(weights)
}

/// A weighted loss with no points to evaluate it on would be dropped silently.
fn check_points(schedule: &Schedule) -> Result<(), ScheduleError> {
    use crate::losses::Input;
    let needs = [
        (schedule.density_points, "density_points", &[Input::Density][..]),
        (schedule.regulariser_points, "regulariser_points", &crate::losses::REGULARISER_INPUTS[..]),
    ];
    for (points, key, inputs) in needs {
        let active = crate::losses::TERMS
            .iter()
            .find(|t| t.needs.iter().any(|n| inputs.contains(n)) && schedule.weights.get(t.name).is_some_and(|r| r.ever_active(schedule.iterations)));
        if let (Some(term), 0) = (active, points) {
            let term = term.name;
            return Err(err(
                &schedule.file,
                key,
                format!("is 0 while losses.{term} has weight: the {term} loss would silently do nothing (set its weight to 0 instead)"),
            ));
        }
    }
    Ok(())
}

/// `[field]`, checked: shapes within bounds, the grid's keys only on a grid.
fn field(written: FieldFile, file: &Path) -> Result<FieldSettings, ScheduleError> {
    let kind = written.kind.unwrap_or(FieldKind::Mlp);
    let within = |key: &str, value: Option<Count>, lo: usize, hi: usize| match value {
        None => Ok(None),
        Some(v) => {
            v.within(lo, hi).map(Some).ok_or_else(|| err(file, &format!("field.{key}"), format!("must be a whole number within {lo}..={hi}, found {}", v.0)))
        }
    };
    if kind == FieldKind::Mlp {
        let grid_only = [
            ("levels", written.levels.is_some()),
            ("table_log2", written.table_log2.is_some()),
            ("top_bones", written.top_bones.is_some()),
            ("features", written.features.is_some()),
            ("finest_per_extent", written.finest_per_extent.is_some()),
            ("reach_per_extent", written.reach_per_extent.is_some()),
            ("fine_levels_from", written.fine_levels_from.is_some()),
            ("fine_levels_until", written.fine_levels_until.is_some()),
            ("root_skinning", written.root_skinning.is_some()),
        ];
        if let Some((key, _)) = grid_only.into_iter().find(|(_, given)| *given) {
            return Err(err(file, &format!("field.{key}"), "applies to kind = \"grid\" only"));
        }
    }
    Ok(FieldSettings {
        kind,
        levels: within("levels", written.levels, 1, 16)?,
        table_log2: within("table_log2", written.table_log2, 8, 22)?.map(|v| v as u32),
        top_bones: within("top_bones", written.top_bones, 1, 8)?,
        features: within("features", written.features, 1, 8)?,
        finest_per_extent: within("finest_per_extent", written.finest_per_extent, 10, 4096)?,
        albedo_layers: within("albedo_layers", written.albedo_layers, 0, 4)?,
        reach_per_extent: match written.reach_per_extent {
            Some(v) if !(v > 0.0 && v <= 1.0) => return Err(err(file, "field.reach_per_extent", format!("must be within (0, 1], found {v}"))),
            other => other,
        },
        fine_levels: match (
            within("fine_levels_from", written.fine_levels_from, 0, MAX_COUNT)?,
            within("fine_levels_until", written.fine_levels_until, 0, MAX_COUNT)?,
        ) {
            (None, None) => None,
            (Some(from), Some(until)) if until >= from => Some((from, until)),
            (Some(_), Some(_)) => return Err(err(file, "field.fine_levels_until", "must not come before fine_levels_from")),
            _ => return Err(err(file, "field.fine_levels_from", "fine_levels_from and fine_levels_until go together")),
        },
        root_skinning: written.root_skinning,
        recorded: None,
    })
}
