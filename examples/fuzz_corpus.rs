//! Seed inputs for the fuzz targets in `fuzz/`, from the shipped scenes (`cargo run --example
//! fuzz_corpus -- [OUT]`, default `fuzz/`): writes `OUT/corpus/<target>/` and the small fit
//! `OUT/seed-run/` whose checkpoint seeds the checkpoint target (and whose scene and schedule
//! that target resumes on).
//!
//! Scenes are trimmed to one training and one test image each (with every file those and the
//! lights name), so a fuzzed scene decodes in milliseconds; every shipped scene's JSON is kept.

use serde_json::Value;
use std::path::{Path, PathBuf};
use umbra::fuzzing::Folder;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = PathBuf::from(std::env::args().nth(1).unwrap_or_else(|| "fuzz".into()));
    let corpus = out.join("corpus");
    let mut scenes: Vec<PathBuf> =
        std::fs::read_dir("datasets-synthetic")?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.join("scene.json").is_file()).collect();
    scenes.sort();
    let example = PathBuf::from("../shared/examples/quadruped-tiny");
    scenes.push(example.clone());

    let write = |target: &str, name: &str, bytes: &[u8]| -> std::io::Result<()> {
        let dir = corpus.join(target);
        std::fs::create_dir_all(&dir)?;
        std::fs::write(dir.join(name), bytes)
    };
    for scene in &scenes {
        let name = scene.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let json: Value = serde_json::from_str(&std::fs::read_to_string(scene.join("scene.json"))?)?;
        let trimmed = trim(json.clone());
        write("scene", &name, &folder_of(scene, &trimmed)?.encode())?;
        // Each light alone, as `umbra relight --light FILE.json` reads it.
        if let Some(lights) = json["lights"].as_object() {
            for (light_name, light) in lights {
                let mut files = vec![("light.json".to_string(), serde_json::to_vec_pretty(light)?)];
                if let Some(path) = light["path"].as_str() {
                    files.push((path.to_string(), std::fs::read(scene.join(path))?));
                    write("image", &format!("{name}-{light_name}.exr"), &std::fs::read(scene.join(path))?)?;
                }
                write("light", &format!("{name}-{light_name}"), &Folder { files }.encode())?;
            }
        }
        // One training image and its mask of every scene, one test albedo.
        for image in trimmed["images"].as_array().into_iter().flatten() {
            for key in ["path", "mask", "albedo"] {
                if let Some(path) = image[key].as_str() {
                    write("image", &format!("{name}-{}", path.replace('/', "-")), &std::fs::read(scene.join(path))?)?;
                }
            }
        }
    }
    for entry in std::fs::read_dir("schedules")?.chain(std::fs::read_dir("schedules/ablations")?) {
        let path = entry?.path();
        if path.extension().is_some_and(|e| e == "toml") {
            write("schedule", &path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(), &std::fs::read(&path)?)?;
        }
    }

    // A capture as people deliver one: its clip, its transforms.json, and a COLMAP model of
    // three cameras in a folder each (with and without lines of 2D points).
    let capture = out.join("seed-capture");
    let options = umbra::synth::SynthOptions {
        size: 24,
        cameras: 2,
        frames: 2,
        test_frames: 1,
        samples: 2,
        export: Some(umbra::synth::Export::Nerfstudio),
        ..umbra::synth::SynthOptions::default()
    };
    umbra::synth::generate(&options, &capture, true, |_, _| {})?;
    write("clip", "motion.bvh", &std::fs::read(capture.join("motion.bvh"))?)?;
    write("transforms", "transforms.json", &std::fs::read(capture.join("transforms.json"))?)?;
    let cameras = b"# CAMERA_ID MODEL WIDTH HEIGHT PARAMS\n1 PINHOLE 24 24 30 30 12 12\n2 OPENCV 24 24 30 30 12 12 -0.05 0.01 0.001 0\n3 SIMPLE_RADIAL 24 24 28 12 12 0.02\n";
    let images = b"# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n1 1 0 0 0 0 0 3 1 cam01/000000.png\n10.5 3.25 -1 4 5 17\n2 0.7071068 0 0.7071068 0 0 0 3 2 cam02/000000.png\n\n3 1 0 0 0 0.1 0 3 3 cam03/000001.png\n";
    let model = Folder { files: vec![("cameras.txt".into(), cameras.to_vec()), ("images.txt".into(), images.to_vec())] };
    write("colmap", "rig", &model.encode())?;

    // A two-iteration fit of the independent fixture: its checkpoint, with and without the
    // checksums (without, a damaged model file reaches burn's reader instead of the checksum).
    // Its grid is small (4 levels of 2^8 entries: a checkpoint of 0.2 MB, not 25), so that
    // libFuzzer's mutations of it stay quick; the format is the same.
    let run = out.join("seed-run");
    std::fs::create_dir_all(&out)?;
    let schedule = out.join("seed-schedule.toml");
    std::fs::write(&schedule, umbra::schedule::DEFAULT_TEXT.replacen("[field]\n", "[field]\nlevels = 4\ntable_log2 = 8\n", 1))?;
    let options = umbra::fit::FitOptions {
        scene: example.clone(),
        out: run.clone(),
        schedule,
        iterations: Some(2),
        seed: 0,
        resume: false,
        force: true,
        force_schedule: false,
        backend: umbra::backend::Backend::Flex,
        evaluate: false,
    };
    umbra::fit::fit(&options, |_| {})?;
    let checkpoint = Folder::read_dir(&run.join(umbra::fit::CHECKPOINT))?;
    write("checkpoint", "fixture-2-iterations", &checkpoint.encode())?;
    let unchecked = Folder {
        files: checkpoint
            .files
            .iter()
            .map(|(name, bytes)| {
                if name != "state.json" {
                    return Ok((name.clone(), bytes.clone()));
                }
                let mut state: Value = serde_json::from_slice(bytes)?;
                if let Some(state) = state.as_object_mut() {
                    state.remove("checksums");
                }
                Ok((name.clone(), serde_json::to_vec(&state)?))
            })
            .collect::<Result<_, serde_json::Error>>()?,
    };
    write("checkpoint", "fixture-2-iterations-unchecked", &unchecked.encode())?;
    println!("wrote {} and {}", corpus.display(), run.display());
    Ok(())
}

/// The scene with its first training image and its first test image only.
fn trim(mut json: Value) -> Value {
    if let Some(images) = json["images"].as_array() {
        let first = |split: &str| images.iter().find(|i| i["split"] == split).cloned();
        json["images"] = Value::Array([first("train"), first("test")].into_iter().flatten().collect());
    }
    json
}

/// `scene.json` (the trimmed document) and every file of the scene its strings name.
fn folder_of(scene: &Path, json: &Value) -> std::io::Result<Folder> {
    let mut names = Vec::new();
    collect_strings(json, &mut names);
    names.sort();
    names.dedup();
    let mut files = vec![("scene.json".to_string(), serde_json::to_vec_pretty(json).map_err(std::io::Error::other)?)];
    for name in names {
        let path = scene.join(&name);
        if path.is_file() && name != "scene.json" {
            files.push((name, std::fs::read(path)?));
        }
    }
    Ok(Folder { files })
}

fn collect_strings(value: &Value, out: &mut Vec<String>) {
    match value {
        Value::String(s) => out.push(s.clone()),
        Value::Array(items) => items.iter().for_each(|v| collect_strings(v, out)),
        Value::Object(map) => map.values().for_each(|v| collect_strings(v, out)),
        _ => {}
    }
}
