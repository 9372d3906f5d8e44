//! The fuzz targets (`umbra::fuzzing`, driven by `cargo fuzz` in `fuzz/`) on seed inputs made
//! here from the shipped scenes and a short fit, and on every input a fuzzing run found and
//! `fuzz/regressions/<target>/` keeps: seeds are read and accepted (the harness reaches the
//! readers), broken copies are refused, nothing panics.

mod common;

use common::TempDir;
use std::path::{Path, PathBuf};
use umbra::fuzzing::{CheckpointTarget, Folder, Outcome};

/// Every kept finding of `target`.
fn regressions(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/regressions").join(target);
    let mut found: Vec<(PathBuf, Vec<u8>)> = std::fs::read_dir(&dir)
        .map(|entries| entries.flatten().map(|e| e.path()).filter(|p| p.is_file()).map(|p| (p.clone(), std::fs::read(&p).unwrap())).collect())
        .unwrap_or_default();
    found.sort();
    found
}

/// The bytes cut to `n` of them, and with a run of bytes in the middle overwritten.
fn broken(bytes: &[u8]) -> Vec<Vec<u8>> {
    let mut overwritten = bytes.to_vec();
    let middle = overwritten.len() / 2;
    let end = (middle + 64).min(overwritten.len());
    overwritten[middle..end].iter_mut().for_each(|b| *b = b'{');
    vec![bytes[..bytes.len() / 2].to_vec(), bytes[..bytes.len() / 7].to_vec(), overwritten]
}

#[test]
fn a_folder_survives_its_encoding_and_unsafe_names_are_dropped() {
    let folder = Folder { files: vec![("scene.json".into(), b"{}".to_vec()), ("images/a.png".into(), vec![0, 1, 2, 255])] };
    assert_eq!(Folder::decode(&folder.encode()), folder);
    let hostile = Folder { files: vec![("../escape".into(), vec![1]), ("/etc/x".into(), vec![2]), ("ok".into(), vec![3])] };
    assert_eq!(Folder::decode(&hostile.encode()).files, vec![("ok".to_string(), vec![3])]);
    // A truncated entry ends the folder.
    let bytes = folder.encode();
    assert_eq!(Folder::decode(&bytes[..bytes.len() - 1]).files.len(), 1);
}

#[test]
fn the_scene_light_image_and_schedule_targets_accept_their_seeds_and_refuse_broken_copies() {
    let example = common::example_scene();
    let scene = Folder::read_dir(&example).unwrap();
    assert_eq!(umbra::fuzzing::scene(&scene.encode()), Outcome::Accepted);
    let json = &scene.files.iter().find(|(n, _)| n == "scene.json").unwrap().1;
    for bad in broken(json) {
        let files = scene.files.iter().map(|(n, b)| (n.clone(), if n == "scene.json" { bad.clone() } else { b.clone() })).collect();
        assert_eq!(umbra::fuzzing::scene(&Folder { files }.encode()), Outcome::Refused);
    }

    let text = std::fs::read_to_string(example.join("scene.json")).unwrap();
    let doc: serde_json::Value = serde_json::from_str(&text).unwrap();
    for (name, light) in doc["lights"].as_object().unwrap() {
        let mut files = vec![("light.json".to_string(), serde_json::to_vec(light).unwrap())];
        if let Some(path) = light["path"].as_str() {
            files.push((path.to_string(), std::fs::read(example.join(path)).unwrap()));
        }
        assert_eq!(umbra::fuzzing::light(&Folder { files: files.clone() }.encode()), Outcome::Accepted, "{name}");
        let half = files[0].1.len() / 2;
        files[0].1.truncate(half);
        assert_eq!(umbra::fuzzing::light(&Folder { files }.encode()), Outcome::Refused, "{name}");
    }

    for image in ["images/c00_f0000_sun.png", "masks/c00_f0000_sun.png", "lights/dusk.exr"] {
        let bytes = std::fs::read(example.join(image)).unwrap();
        assert_eq!(umbra::fuzzing::image(&bytes), Outcome::Accepted, "{image}");
        for bad in broken(&bytes).into_iter().take(2) {
            assert_eq!(umbra::fuzzing::image(&bad), Outcome::Refused, "{image} cut short");
        }
    }

    let schedule = umbra::schedule::DEFAULT_TEXT.as_bytes();
    assert_eq!(umbra::fuzzing::schedule(schedule), Outcome::Accepted);
    assert_eq!(umbra::fuzzing::schedule(b"iterations = -3"), Outcome::Refused);

    for (path, bytes) in regressions("scene") {
        eprintln!("{}: {:?}", path.display(), umbra::fuzzing::scene(&bytes));
    }
    for (path, bytes) in regressions("light") {
        eprintln!("{}: {:?}", path.display(), umbra::fuzzing::light(&bytes));
    }
    for (path, bytes) in regressions("image") {
        eprintln!("{}: {:?}", path.display(), umbra::fuzzing::image(&bytes));
    }
    for (path, bytes) in regressions("schedule") {
        eprintln!("{}: {:?}", path.display(), umbra::fuzzing::schedule(&bytes));
    }
}

#[test]
fn the_checkpoint_target_resumes_a_real_checkpoint_and_refuses_damaged_ones() {
    let dir = TempDir::new("fuzz-checkpoint");
    let scene = common::example_scene();
    let run = dir.path().join("run");
    // A small grid, as the fuzzing seed run has (`examples/fuzz_corpus.rs`).
    let schedule = dir.path().join("small.toml");
    std::fs::write(&schedule, umbra::schedule::DEFAULT_TEXT.replacen("[field]\n", "[field]\nlevels = 4\ntable_log2 = 8\n", 1)).unwrap();
    let options = umbra::fit::FitOptions {
        scene: scene.clone(),
        out: run.clone(),
        schedule,
        iterations: Some(2),
        seed: 0,
        resume: false,
        force: false,
        force_schedule: false,
        backend: umbra::backend::Backend::Flex,
        evaluate: false,
    };
    umbra::fit::fit(&options, |_| {}).unwrap();
    let target = CheckpointTarget::new(&run, &scene).unwrap();
    let checkpoint = Folder::read_dir(&run.join(umbra::fit::CHECKPOINT)).unwrap();
    assert_eq!(target.run(&checkpoint.encode()), Outcome::Accepted);
    // Each file damaged in turn (the checksums catch the model's and optimizers'), and the
    // model damaged with the checksums gone, which burn's reader must refuse by itself.
    for (k, (name, bytes)) in checkpoint.files.iter().enumerate() {
        if name == "losses.csv" {
            continue;
        }
        for bad in broken(bytes) {
            let mut files = checkpoint.files.clone();
            files[k].1 = bad;
            assert_eq!(target.run(&Folder { files }.encode()), Outcome::Refused, "{name}");
        }
    }
    // A checkpoint from before checksums: none for its files in state.json, none for the state.
    let unchecked: Vec<(String, Vec<u8>)> = checkpoint
        .files
        .iter()
        .filter(|(name, _)| name != "state.checksum")
        .map(|(name, bytes)| {
            if name == "state.json" {
                let mut state: serde_json::Value = serde_json::from_slice(bytes).unwrap();
                state.as_object_mut().unwrap().remove("checksums");
                (name.clone(), serde_json::to_vec(&state).unwrap())
            } else {
                (name.clone(), bytes.clone())
            }
        })
        .collect();
    assert_eq!(target.run(&Folder { files: unchecked.clone() }.encode()), Outcome::Accepted);
    let model = unchecked.iter().position(|(n, _)| n == "model.bpk").unwrap();
    for bad in broken(&unchecked[model].1).into_iter().take(2) {
        let mut files = unchecked.clone();
        files[model].1 = bad;
        assert_eq!(target.run(&Folder { files }.encode()), Outcome::Refused, "a cut model.bpk");
    }
    for (path, bytes) in regressions("checkpoint") {
        eprintln!("{}: {:?}", path.display(), target.run(&bytes));
    }
}

#[test]
fn the_clip_colmap_and_transforms_targets_accept_their_seeds_and_refuse_broken_copies() {
    let dir = TempDir::new("fuzz-capture");
    let options = umbra::synth::SynthOptions {
        size: 24,
        cameras: 2,
        frames: 2,
        test_frames: 0,
        test: vec![],
        samples: 2,
        export: Some(umbra::synth::Export::Nerfstudio),
        ..umbra::synth::SynthOptions::default()
    };
    let capture = dir.path().join("capture");
    umbra::synth::generate(&options, &capture, false, |_, _| {}).unwrap();
    let bvh = std::fs::read(capture.join("motion.bvh")).unwrap();
    assert_eq!(umbra::fuzzing::clip(&bvh), Outcome::Accepted);
    for bad in broken(&bvh) {
        assert_eq!(umbra::fuzzing::clip(&bad), Outcome::Refused);
    }
    let transforms = std::fs::read(capture.join("transforms.json")).unwrap();
    assert_eq!(umbra::fuzzing::transforms(&transforms), Outcome::Accepted);
    for bad in broken(&transforms) {
        assert_eq!(umbra::fuzzing::transforms(&bad), Outcome::Refused);
    }
    let cameras = b"1 PINHOLE 24 24 30 30 12 12\n2 OPENCV 24 24 30 30 12 12 0.01 0 0 0\n".to_vec();
    let images = b"1 1 0 0 0 0 0 3 1 a.png\n\n2 1 0 0 0 0 0 3 2 cam2/b.png\n10.5 3 -1\n".to_vec();
    let model = Folder { files: vec![("cameras.txt".into(), cameras), ("images.txt".into(), images.clone())] };
    assert_eq!(umbra::fuzzing::colmap(&model.encode()), Outcome::Accepted);
    for bad in broken(&images) {
        let files = vec![model.files[0].clone(), ("images.txt".into(), bad)];
        assert_eq!(umbra::fuzzing::colmap(&Folder { files }.encode()), Outcome::Refused);
    }
    for target in ["clip", "colmap", "transforms"] {
        for (path, bytes) in regressions(target) {
            let outcome = match target {
                "clip" => umbra::fuzzing::clip(&bytes),
                "colmap" => umbra::fuzzing::colmap(&bytes),
                _ => umbra::fuzzing::transforms(&bytes),
            };
            eprintln!("{}: {outcome:?}", path.display());
        }
    }
}
