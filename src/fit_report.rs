//! `fit.json`: what a finished fit reports, written and read by this one type. The parts whose
//! shape follows the capture (the light by its kind, the evaluation's groups, the searches) stay
//! JSON values inside it.

use crate::backend::Backend;
use crate::fit_error::{io, FitError};
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};
use std::collections::BTreeMap;
use std::path::Path;

/// One stage of the schedule: whether it ran, from which iteration, for how long.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Stage {
    pub name: String,
    pub ran: bool,
    /// The iteration it starts at (a share of the iterations for a hold).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skipped_because: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub iterations_saved: Option<usize>,
}

/// The whole of `fit.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FitReport {
    /// The scene's folder, absolute, so the run renders from any working folder.
    pub scene: String,
    /// The first training light as fitted (`FittedLight::report`).
    pub light: Value,
    /// Every fitted light by the scene's name for it.
    #[serde(default)]
    pub lights: Map<String, Value>,
    #[serde(default)]
    pub stages: Vec<Stage>,
    pub iterations: usize,
    pub seed: u64,
    #[serde(default)]
    pub schedule: String,
    pub backend: Backend,
    #[serde(default)]
    pub threads: usize,
    #[serde(default)]
    pub final_losses: BTreeMap<String, f64>,
    #[serde(default)]
    pub final_total: f64,
    pub wall_seconds: f64,
    /// The most memory the fit held at once (`None` where the system does not say).
    #[serde(default)]
    pub peak_memory_bytes: Option<u64>,
    /// `scoring::evaluate`'s figures, or null when nothing was evaluated.
    #[serde(default)]
    pub evaluation: Value,
    #[serde(default)]
    pub evaluation_skipped: Option<String>,
    /// The first light's error against the scene's (null for an unknown light).
    #[serde(default)]
    pub light_error_against_scene: Value,
    #[serde(default)]
    pub light_errors_against_scene: Map<String, Value>,
    #[serde(default)]
    pub sun_search: Value,
    #[serde(default)]
    pub light_searches: Map<String, Value>,
    #[serde(default)]
    pub light_path: Value,
    /// What was read off the capture and chosen for it.
    #[serde(default)]
    pub capture: Value,
    #[serde(default)]
    pub field: Value,
}

impl FitReport {
    /// Reads `path` (a run's `fit.json`).
    pub fn read(path: &Path) -> Result<FitReport, FitError> {
        let text = crate::files::read_text(path, crate::files::SCENE_BYTES).map_err(|e| io(path, e))?;
        serde_json::from_str(&text).map_err(|e| io(path, e))
    }

    /// Writes it to `path`, atomically.
    pub fn write(&self, path: &Path) -> Result<(), FitError> {
        let text = serde_json::to_string_pretty(self).map_err(|e| io(path, e))?;
        crate::imageio::write_atomic(path, text.as_bytes()).map_err(|e| io(path, e))
    }

    /// The first light's direction error against the scene's (degrees), when it has one.
    pub fn direction_error(&self) -> Option<f64> {
        self.light_error_against_scene["direction_degrees"].as_f64()
    }

    /// The first light's position error against the scene's (m), when it has one.
    pub fn position_error(&self) -> Option<f64> {
        self.light_error_against_scene["position_metres"].as_f64()
    }
}
