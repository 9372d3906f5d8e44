//! `fit.json`: what a finished fit reports, written and read by this one type. The parts whose
//! shape follows the capture (the light by its kind, the evaluation's groups, the searches) stay
//! JSON values inside it.

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
    /// The backend's name (`Backend`'s): kept as written, so that a run fitted on a GPU build
    /// reads in a build without the `gpu` feature.
    pub backend: String,
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
    /// The most the device's allocator held after a step of this process's training (a GPU's
    /// memory; `None` on the CPU backends, whose memory is `peak_memory_bytes`).
    #[serde(default)]
    pub peak_device_memory_bytes: Option<u64>,
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

/// The cameras' learned colours (fit.json's `capture.camera_colours`) in a line: how far the
/// gains spread, and the camera farthest from the mean; none for one camera.
pub fn camera_colours_line(capture: &serde_json::Value) -> Option<String> {
    let cameras = capture.get("camera_colours")?.as_array().filter(|c| !c.is_empty())?;
    let gains: Vec<(String, [f64; 3])> =
        cameras.iter().filter_map(|c| Some((c["camera"].as_str()?.to_string(), serde_json::from_value(c["gain"].clone()).ok()?))).collect();
    let all = gains.iter().flat_map(|(_, g)| g.iter().copied());
    let (lo, hi) = all.clone().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), g| (lo.min(g), hi.max(g)));
    let (name, gain) = gains.iter().max_by(|a, b| spread(&a.1).total_cmp(&spread(&b.1)))?;
    Some(format!("camera colours: {} cameras, gains {lo:.3} to {hi:.3} (mean 1); farthest {name} at {:.3} {:.3} {:.3}", gains.len(), gain[0], gain[1], gain[2]))
}

/// How far the fit moved the training motion (fit.json's `capture.motion_refined`) in a line;
/// none when it was not refined.
pub fn motion_line(capture: &serde_json::Value) -> Option<String> {
    let moved = capture.get("motion_refined").filter(|m| m.is_object())?;
    let number = |key: &str| moved[key].as_f64();
    let line = format!(
        "motion refined: {} training frames, bones turned {:.2} degrees on average (at most {:.2}), the root moved {:.2} cm (at most {:.2})",
        moved["frames"].as_u64()?,
        number("mean_degrees")?,
        number("largest_degrees")?,
        number("mean_shift_cm")?,
        number("largest_shift_cm")?,
    );
    // Runs from before the shared turns were shown in other poses, or the smoothness was
    // weighed by the capture, do not record them.
    let line = match (number("shared_mean_degrees"), number("shared_largest_degrees")) {
        (Some(mean), Some(largest)) => {
            format!("{line}; turned alike in every frame {mean:.2} degrees on average (at most {largest:.2}), which every pose is shown with")
        }
        _ => line,
    };
    let line = match (number("given_noise_share"), number("smoothness_scale")) {
        (Some(noise), Some(scale)) => {
            format!("{line}; the given motion's second differences {:.0}% noise, smoothed {scale:.3}x the schedule's weight", noise * 100.0)
        }
        _ => line,
    };
    // Runs from before the prior was weighed by the capture do not record it.
    let line = match (number("given_noise_degrees"), number("prior_scale")) {
        (Some(noise), Some(scale)) => format!("{line}; its noise {noise:.2} degrees a frame, held to it {scale:.3}x the schedule's weight"),
        _ => line,
    };
    Some(match number("given_bias_degrees") {
        Some(bias) => format!("{line}; that noise leaves about {bias:.2} degrees a bone alike in every training frame, which the images cannot tell from the body: the avatar keeps it"),
        None => line,
    })
}

/// How far the fit moved the training cameras (fit.json's `capture.cameras_refined`) in a line;
/// none when they were not refined.
pub fn cameras_line(capture: &serde_json::Value) -> Option<String> {
    let moved = capture.get("cameras_refined").filter(|m| m.is_object())?;
    let number = |key: &str| moved[key].as_f64();
    Some(format!(
        "cameras refined: {} training cameras, turned {:.3} degrees on average (at most {:.3}) about their centres",
        moved["cameras"].as_array()?.len(),
        number("mean_degrees")?,
        number("largest_degrees")?,
    ))
}

fn spread(gain: &[f64; 3]) -> f64 {
    gain.iter().map(|g| (g - 1.0).abs()).sum()
}

#[cfg(test)]
mod tests {
    use super::{camera_colours_line, cameras_line, motion_line};
    use serde_json::json;

    #[test]
    fn the_cameras_colours_are_one_line_naming_the_farthest() {
        let capture = json!({"camera_colours": [{"camera": "cam00", "gain": [0.98, 1.0, 1.01]}, {"camera": "cam01", "gain": [1.02, 1.0, 0.99]}, {"camera": "cam02", "gain": [1.0, 1.1, 1.0]}]});
        assert_eq!(camera_colours_line(&capture).unwrap(), "camera colours: 3 cameras, gains 0.980 to 1.100 (mean 1); farthest cam02 at 1.000 1.100 1.000");
        assert_eq!(camera_colours_line(&json!({"camera_colours": []})), None);
        assert_eq!(camera_colours_line(&json!(null)), None);
    }

    #[test]
    fn the_motions_refinement_is_one_line() {
        let capture = json!({"motion_refined": {"frames": 12, "mean_degrees": 1.234, "largest_degrees": 6.5, "mean_shift_cm": 0.71, "largest_shift_cm": 1.9}});
        assert_eq!(
            motion_line(&capture).unwrap(),
            "motion refined: 12 training frames, bones turned 1.23 degrees on average (at most 6.50), the root moved 0.71 cm (at most 1.90)"
        );
        let capture = json!({"motion_refined": {"frames": 12, "mean_degrees": 1.234, "largest_degrees": 6.5, "mean_shift_cm": 0.71, "largest_shift_cm": 1.9, "shared_mean_degrees": 0.414, "shared_largest_degrees": 0.9}});
        assert_eq!(
            motion_line(&capture).unwrap(),
            "motion refined: 12 training frames, bones turned 1.23 degrees on average (at most 6.50), the root moved 0.71 cm (at most 1.90); turned alike in every frame 0.41 degrees on average (at most 0.90), which every pose is shown with"
        );
        let capture = json!({"motion_refined": {"frames": 30, "mean_degrees": 1.234, "largest_degrees": 6.5, "mean_shift_cm": 0.71, "largest_shift_cm": 1.9, "shared_mean_degrees": 0.414, "shared_largest_degrees": 0.9, "given_noise_share": 0.9, "smoothness_scale": 9.0}});
        assert!(motion_line(&capture).unwrap().ends_with("; the given motion's second differences 90% noise, smoothed 9.000x the schedule's weight"));
        let capture = json!({"motion_refined": {"frames": 30, "mean_degrees": 1.234, "largest_degrees": 6.5, "mean_shift_cm": 0.71, "largest_shift_cm": 1.9, "shared_mean_degrees": 0.414, "shared_largest_degrees": 0.9, "given_noise_share": 0.26, "smoothness_scale": 1.0, "given_noise_degrees": 0.1, "prior_scale": 625.0}});
        assert!(motion_line(&capture)
            .unwrap()
            .ends_with("smoothed 1.000x the schedule's weight; its noise 0.10 degrees a frame, held to it 625.000x the schedule's weight"));
        let capture = json!({"motion_refined": {"frames": 30, "mean_degrees": 1.234, "largest_degrees": 6.5, "mean_shift_cm": 0.71, "largest_shift_cm": 1.9, "given_noise_degrees": 2.5, "prior_scale": 1.0, "given_bias_degrees": 0.7284}});
        assert!(motion_line(&capture).unwrap().ends_with(
            "held to it 1.000x the schedule's weight; that noise leaves about 0.73 degrees a bone alike in every training frame, which the images cannot tell from the body: the avatar keeps it"
        ));
        assert_eq!(motion_line(&json!({"motion_refined": null})), None);
    }

    #[test]
    fn the_cameras_refinement_is_one_line() {
        let capture = json!({"cameras_refined": {"cameras": [{}, {}, {}], "mean_degrees": 0.0812, "largest_degrees": 0.15}});
        assert_eq!(cameras_line(&capture).unwrap(), "cameras refined: 3 training cameras, turned 0.081 degrees on average (at most 0.150) about their centres");
        assert_eq!(cameras_line(&json!({"cameras_refined": null})), None);
    }
}
