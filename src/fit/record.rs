//! What a fit says of itself when it ends: fit.json's stages with their seconds, its light
//! searches, the capture's choices, the light's path and the field, and the losses' chart.

use super::*;

/// Running mean over `window` points: per-batch losses are noisy, trends are what one reads.
pub(super) fn smooth(points: Vec<(f64, f64)>, window: usize) -> Vec<(f64, f64)> {
    (0..points.len())
        .map(|k| {
            let lo = k.saturating_sub(window - 1);
            let mean = points[lo..=k].iter().map(|p| p.1).sum::<f64>() / (k + 1 - lo) as f64;
            (points[k].0, mean)
        })
        .collect()
}

pub(super) fn losses_chart(history: &[(usize, StepStats)], schedule: &Schedule, fit_light: bool) -> Chart {
    let window = (history.len() / 60).max(1);
    let mut series = vec![Series {
        name: "total (weighted)".into(),
        points: smooth(history.iter().map(|(i, s)| (*i as f64 + 1.0, s.total)).collect(), window),
        lines: true,
    }];
    for term in crate::losses::names() {
        let points: Vec<(f64, f64)> = history.iter().filter_map(|(i, s)| s.terms.get(term).map(|v| (*i as f64 + 1.0, *v))).collect();
        if !points.is_empty() {
            series.push(Series { name: term.into(), points: smooth(points, window), lines: true });
        }
    }
    Chart {
        title: format!("losses (running mean of {window})"),
        x_label: "iteration".into(),
        y_label: "loss".into(),
        log_x: false,
        log_y: true,
        series,
        marks: stage_marks(schedule, fit_light),
    }
}

/// Where the schedule's stages begin, as fit.json names them, and where the field's learning
/// rates start to fall.
fn stage_marks(schedule: &Schedule, fit_light: bool) -> Vec<Mark> {
    let mut marks = Vec::new();
    let density = &schedule.weights["density"];
    if density.ever_active(schedule.iterations) && density.hold > 0.0 {
        marks.push(Mark { x: density.hold + 1.0, label: "Gaussians".into() });
    }
    if schedule.light_from > 0 && schedule.light_from < schedule.iterations {
        let label = if fit_light { "light and RGB" } else { "RGB" };
        marks.push(Mark { x: schedule.light_from as f64 + 1.0, label: label.into() });
    }
    if schedule.field_lr_decay < 1.0 && schedule.field_lr_decay_from > 0 && schedule.field_lr_decay_from < schedule.iterations {
        marks.push(Mark { x: schedule.field_lr_decay_from as f64 + 1.0, label: "rates fall".into() });
    }
    marks
}

/// fit.json's stages, each with the seconds it took; a stage that did not run says why.
pub(super) fn stages(trainer: &Trainer, schedule: &Schedule, segment_seconds: &BTreeMap<&str, f64>, saved: usize) -> Vec<Stage> {
    let mut stages = Vec::new();
    let density_hold = schedule.weights.get("density").map(|r| r.hold).unwrap_or(0.0);
    let seconds = |name: &str| Some(segment_seconds.get(name).copied().unwrap_or(0.0));
    let stage = |name: &str, ran: bool, from: Option<f64>| Stage { name: name.into(), ran, from, seconds: seconds(name), ..Stage::default() };
    stages.push(stage("density fitting", true, None));
    stages.push(stage("Gaussian fitting", schedule.weights["density"].ever_active(schedule.iterations), Some(density_hold)));
    let light_stage = if trainer.fit_light {
        stage("light and RGB fitting", schedule.iterations > schedule.light_from, Some(schedule.light_from as f64))
    } else {
        let why = if trainer.light_kind == LightKind::Uniform && schedule.light != crate::schedule::LightPolicy::Off {
            "every training image is uniformly lit: no light direction, no shadow rays; RGB fits the albedo directly"
        } else {
            "the schedule sets light = \"off\""
        };
        Stage { name: "light fitting".into(), skipped_because: Some(why.into()), iterations_saved: Some(saved), ..Stage::default() }
    };
    stages.push(light_stage);
    // Without a light the colour is still fitted after light_from: its time is accounted too.
    if !trainer.fit_light && schedule.iterations > schedule.light_from {
        stages.push(stage("RGB fitting", true, Some(schedule.light_from as f64)));
    }
    stages
}

/// Each light search's start, with its own error against the scene's light when it has one.
pub(super) fn light_searches(trainer: &Trainer) -> Vec<serde_json::Value> {
    trainer
        .searches
        .iter()
        .enumerate()
        .map(|(k, search)| match search {
            None => json!(null),
            Some(r) => {
                let mut value = serde_json::to_value(r).unwrap_or(json!(null));
                let start = match r.best.position {
                    Some(position) => json!({"position": position}),
                    None => json!({"direction": r.best.direction}),
                };
                value["error_against_scene"] = light_error(&trainer.scene, trainer.fit_light, k, &start);
                value
            }
        })
        .collect()
}

/// What fit.json says of the capture and the choices made for it.
pub(super) fn capture_report(trainer: &Trainer) -> serde_json::Value {
    // One schedule serves every capture: with one camera the sun search is what keeps the
    // light from sliding behind the body (fit.json says which case this was).
    let training_cameras: std::collections::BTreeSet<usize> = trainer.scene.views_in(crate::scene::Split::Train).map(|v| v.camera).collect();
    json!({
        "pixel_footprint": {
            "modelled": trainer.footprint,
            "read_off_the_images": trainer.footprint_estimate,
        },
        // Rays drawn where the fit is wrong: the share of each batch's anywhere-third
        // (`Schedule::error_rays`; under `auto`, half for a loose body, none for a tight one).
        "error_rays": trainer.error_rays,
        // Every how many steps the Eikonal and curvature terms were evaluated, at that many
        // times their weight (`Schedule::lazy_regularisation`; under `auto`, 2 for a tight body).
        "regularise_every": trainer.schedule.regularise_every,
        // The Gaussians' density also fitted at the shadows' scale (`Schedule::density_at_shadow_scale`;
        // under `auto`, for a loose body alone).
        "density_at_shadow_scale": trainer.density_at_shadow_scale,
        // Gaussians seeded on the body the masks show beyond every bone (a loose body's root).
        "gaussians_on_loose_body": trainer.loose_gaussians(),
        "training_cameras": training_cameras.len(),
        // Each training camera's learned gain per channel (its exposure and white balance),
        // normalised to a mean of 1 over the cameras: renders are of the mean camera.
        "camera_colours": trainer.camera_gains().iter().map(|(c, gain)| json!({"camera": trainer.scene.cameras[*c].name, "gain": gain})).collect::<Vec<_>>(),
        // How far the refinement moved the training motion (each bone's turn, degrees; the
        // skeleton's shift, cm), when the schedule refines it.
        "motion_refined": trainer.motion_moved(),
        // How far the refinement turned each training camera about its centre (degrees), when
        // the schedule refines them.
        "cameras_refined": trainer.cameras_moved(),
        "monocular": training_cameras.len() == 1,
        "light_start": match trainer.searches.first().and_then(|s| s.as_ref()) {
            Some(r) if r.best.position.is_some() => "point light search over directions and distances around the body, then gradient descent",
            Some(_) => "sun search over the sphere, then gradient descent within a cone around its best",
            None => "the schedule's initial light, then gradient descent",
        },
    })
}

/// Points of `light_path` over a whole fit (about).
pub(super) const LIGHT_PATH_POINTS: usize = 50;

/// The first training light about `LIGHT_PATH_POINTS` times over the fit and after its last step (a
/// sun's direction or a point light's position, with its error against the scene's light when
/// the scene states it): where the light went, e.g. whether it settled or passed the truth on
/// its way to a biased rest. Empty when no light is fitted.
pub(super) fn light_path(trainer: &Trainer, history: &[(usize, StepStats)]) -> serde_json::Value {
    let key = if trainer.light_kind == LightKind::Point { "position" } else { "direction" };
    let last = history.last().map(|(it, _)| *it);
    let every = (trainer.schedule.iterations / LIGHT_PATH_POINTS).max(1);
    let points: Vec<serde_json::Value> = history
        .iter()
        .filter(|(it, _)| (it + 1) % every == 0 || Some(*it) == last)
        .filter_map(|(it, stats)| {
            let location = json!({ key: stats.light? });
            let mut point = json!({"after_iteration": it + 1, key: location[key]});
            let error = light_error(&trainer.scene, trainer.fit_light, 0, &location);
            if !error.is_null() {
                point["error_against_scene"] = error;
            }
            Some(point)
        })
        .collect();
    json!(points)
}

/// The fitted field's kind and its VolSDF beta (m): how sharp its surface ended.
pub(super) fn field_report(trainer: &Trainer) -> serde_json::Value {
    let Ok(model) = trainer.fitted_model() else { return serde_json::Value::Null };
    let beta = Some(crate::backend::host_scalar(model.field.beta())).filter(|b| b.is_finite());
    // Where the training masks put body beyond every bone's grid box (loose clothing), the
    // root's grids reach it: how far from the root's segment, m (null: a body tight on its bones).
    let root = model.field.grid.as_ref().and_then(|g| g.config.root);
    let loose = root.filter(|r| r.features_reach_body).map(|r| r.reach);
    // And the capsule prior stops at the root's cap (m, null: uncapped).
    let skinning = model.field.config.skinning();
    json!({"kind": if model.field.grid.is_some() { "grid" } else { "mlp" }, "beta": beta, "root_grids_reach_loose_body": loose, "prior_capped_at": skinning.prior_cap})
}
