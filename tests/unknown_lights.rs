//! A real capture's light is unknown (scene-format.md, "Unknown lights"): a `directional` light
//! without `direction`, a `point` light without `position`. The reader accepts it, a fit recovers
//! it and reports no error against it, evaluation scores the test images it lights, and nothing
//! relights by it.

mod common;

use common::{fails, succeeds, tiny_synth, TempDir};
use serde_json::{json, Value};
use umbra::light::{Light, UnknownLight};
use umbra::scene::Scene;
use umbra::synth::{TestKind, TrainingLight};

fn read_json(path: &std::path::Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// `scene`'s training light with its direction (or position) and strength taken out, or, with
/// `null`, given as null.
fn unstate_training_light(scene: &std::path::Path, null: bool) -> String {
    let file = scene.join("scene.json");
    let mut value = read_json(&file);
    let name = value["images"].as_array().unwrap().iter().find(|i| i["split"] == "train").unwrap()["light"].as_str().unwrap().to_string();
    let light = value["lights"][&name].as_object_mut().unwrap();
    for key in ["direction", "position", "irradiance", "intensity"] {
        if light.contains_key(key) {
            if null && (key == "direction" || key == "position") {
                light.insert(key.into(), Value::Null);
            } else {
                light.remove(key);
            }
        }
    }
    common::write_scene_json(scene, &value);
    name
}

#[test]
fn a_sun_or_lamp_without_direction_or_position_reads_as_unknown_and_the_rest_stays_valid() {
    let dir = TempDir::new("unknown-read");
    for (light, null, kind) in
        [(TrainingLight::Sun, false, UnknownLight::Sun), (TrainingLight::Sun, true, UnknownLight::Sun), (TrainingLight::Point, false, UnknownLight::Point)]
    {
        let scene = tiny_synth(&dir.path().join(format!("{light:?}-{null}")), light, 16, 2, vec![TestKind::Poses], 3);
        let name = unstate_training_light(&scene, null);
        let loaded = Scene::load(&scene).unwrap_or_else(|e| panic!("{light:?}: {e}"));
        assert!(matches!(loaded.lights[&name], Light::Unknown { kind: k, strength: None, .. } if k == kind), "{:?}", loaded.lights[&name]);
        assert!(loaded.lights[&name].casts_shadows());
    }
    // A stated strength is kept; a stated sun still needs its irradiance.
    let scene = tiny_synth(&dir.path().join("strength"), TrainingLight::Sun, 16, 2, vec![TestKind::Poses], 3);
    let mut value = read_json(&scene.join("scene.json"));
    let name = value["images"][0]["light"].as_str().unwrap().to_string();
    value["lights"][&name].as_object_mut().unwrap().remove("direction");
    common::write_scene_json(&scene, &value);
    match &Scene::load(&scene).unwrap().lights[&name] {
        Light::Unknown { strength: Some(s), .. } => assert!(s.x > 0.0),
        other => panic!("{other:?}"),
    }
    value["lights"][&name]["direction"] = json!([0, 1, 0]);
    value["lights"][&name].as_object_mut().unwrap().remove("irradiance");
    common::write_scene_json(&scene, &value);
    let err = Scene::load(&scene).unwrap_err().to_string();
    assert!(err.contains(&format!("lights.{name}.irradiance")), "{err}");
}

#[test]
fn an_unknown_light_that_lights_no_training_image_is_refused_naming_the_image() {
    let dir = TempDir::new("unknown-relit");
    let scene = tiny_synth(dir.path(), TrainingLight::Sun, 16, 2, vec![TestKind::Relight], 3);
    let mut value = read_json(&scene.join("scene.json"));
    let training = value["images"].as_array().unwrap().iter().find(|i| i["split"] == "train").unwrap()["light"].as_str().unwrap().to_string();
    let (k, other) = value["images"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
        .find(|(_, i)| i["light"] != training.as_str() && value["lights"][i["light"].as_str().unwrap()]["type"] == "directional")
        .map(|(k, i)| (k, i["light"].as_str().unwrap().to_string()))
        .expect("a test image relit by another sun");
    value["lights"][&other].as_object_mut().unwrap().remove("direction");
    common::write_scene_json(&scene, &value);
    let err = Scene::load(&scene).unwrap_err().to_string();
    assert!(err.contains(&format!("images[{k}].light")) && err.contains("unknown light"), "{err}");
}

#[test]
fn a_fit_under_an_unknown_sun_recovers_it_scores_its_test_images_and_refuses_to_relight_by_it() {
    let dir = TempDir::new("unknown-fit");
    let scene = tiny_synth(dir.path(), TrainingLight::Sun, 24, 3, vec![TestKind::Poses], 9);
    let name = unstate_training_light(&scene, false);
    let run = dir.path().join("run");
    let cwd = std::env::current_dir().unwrap();
    let (scene_arg, run_arg) = (scene.to_str().unwrap(), run.to_str().unwrap());
    // A few steps past the light search.
    let schedule = dir.path().join("short.toml");
    let text = "iterations = 8\nrays_per_batch = 256\nsamples_per_ray = 16\ndensity_points = 64\nregulariser_points = 32\nlight_from = 3\nsun_search = 64\n\
                [losses]\nmask = 1.0\nrgb = 1.0\neikonal = 0.05\ndensity = 0.5\n";
    std::fs::write(&schedule, text).unwrap();
    succeeds(&cwd, &["fit", scene_arg, "--out", run_arg, "--schedule", schedule.to_str().unwrap()]);
    let report = read_json(&run.join("fit.json"));
    assert!(report["light_error_against_scene"].is_null(), "{}", report["light_error_against_scene"]);
    assert!(report["lights"][&name]["direction"].is_array(), "the recovered sun: {}", report["lights"]);
    assert!(report["sun_search"]["best"].is_object(), "the sun was searched for: {}", report["sun_search"]);
    assert!(report["evaluation"]["novel_pose_psnr"].as_f64().is_some_and(|p| p.is_finite()), "{}", report["evaluation"]);
    let err = fails(&cwd, &["relight", run_arg, "--light", &name, "--out", dir.path().join("relit").to_str().unwrap()]);
    assert!(err.contains("unknown light") && err.contains(&name), "{err}");
    assert!(!dir.path().join("relit").exists());
    succeeds(&cwd, &["report", run_arg]);
}
