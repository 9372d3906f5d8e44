//! Test helpers: unique temp folders and a small valid scene written from code.
#![allow(dead_code)]

use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use umbra::imageio::{self, Mask, RgbImage};

static COUNTER: AtomicUsize = AtomicUsize::new(0);

/// A fresh empty folder under the system temp dir, removed when dropped.
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        let n = COUNTER.fetch_add(1, Ordering::SeqCst);
        let path = std::env::temp_dir().join(format!("umbra-test-{tag}-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).unwrap();
        TempDir(path)
    }

    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

pub fn identity_rows(ty: f64) -> Value {
    json!([[1, 0, 0, 0], [0, 1, 0, ty], [0, 0, 1, 0], [0, 0, 0, 1]])
}

/// An 8-bit sRGB PNG with codes ((k % 7) * 36, 128, 64) at pixel k.
fn write_png(path: &Path, w: usize, h: usize) {
    let raw: Vec<u8> = (0..w * h).flat_map(|k| [(k % 7) as u8 * 36, 128, 64]).collect();
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, imageio::encode_png_raw(&raw, w, h, image::ExtendedColorType::Rgb8).unwrap()).unwrap();
}

fn write_mask(path: &Path, w: usize, h: usize) {
    let mask = Mask { width: w, height: h, foreground: (0..w * h).map(|k| k % 3 == 0).collect() };
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, imageio::encode_png_mask(&mask).unwrap()).unwrap();
}

/// A valid scene: 2 bones, two cameras of different sizes, 2 frames, all four light types,
/// a train image (with mask), a test image (with albedo) and a val image without mask.
pub fn valid_scene(dir: &Path) -> Value {
    write_png(&dir.join("images/a.png"), 8, 8);
    write_mask(&dir.join("masks/a.png"), 8, 8);
    write_png(&dir.join("images/b.png"), 6, 4);
    write_png(&dir.join("albedo/b.png"), 6, 4);
    write_png(&dir.join("images/c.png"), 8, 8);
    let mut env = RgbImage::new(8, 4);
    env.pixels.iter_mut().for_each(|p| *p = [2.0, 1.5, 1.0]);
    std::fs::create_dir_all(dir.join("lights")).unwrap();
    imageio::write_exr_atomic(&dir.join("lights/sky.exr"), &env).unwrap();
    std::fs::create_dir_all(dir.join("meshes")).unwrap();
    std::fs::write(dir.join("meshes/f0.obj"), "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
    let scene = json!({
        "format": "scene/1",
        "name": "tiny",
        "skeleton": {"bones": [
            {"name": "root", "parent": null, "length": 0.5},
            {"name": "child", "parent": 0, "length": 0.3}
        ]},
        "cameras": [
            {"name": "a", "width": 8, "height": 8, "fx": 10.0, "fy": 10.0, "cx": 4.0, "cy": 4.0,
             "camera_to_world": [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 3], [0, 0, 0, 1]]},
            {"name": "b", "width": 6, "height": 4, "fx": 12.0, "fy": 11.0, "cx": 3.0, "cy": 2.0,
             "camera_to_world": [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 4], [0, 0, 0, 1]]}
        ],
        "frames": [
            {"index": 5, "time": 0.0, "bone_to_world": [identity_rows(0.0), identity_rows(0.5)], "mesh": "meshes/f0.obj"},
            {"index": 2, "bone_to_world": [identity_rows(0.1), identity_rows(0.6)]}
        ],
        "lights": {
            "sun": {"type": "directional", "direction": [0.0, 2.0, 0.0], "irradiance": [1, 1, 1], "ambient": [0.1, 0.1, 0.1]},
            "studio": {"type": "uniform", "radiance": [1, 1, 1]},
            "sky": {"type": "environment", "path": "lights/sky.exr", "scale": 0.5},
            "lamp": {"type": "point", "position": [1, 2, 0.5], "intensity": [8, 8, 8], "ambient": [0.05, 0.05, 0.05]}
        },
        "images": [
            {"camera": 0, "frame": 1, "light": "sun", "split": "train", "path": "images/a.png", "mask": "masks/a.png"},
            {"camera": 1, "frame": 0, "light": "sky", "split": "test", "path": "images/b.png", "albedo": "albedo/b.png"},
            {"camera": 0, "frame": 0, "light": "lamp", "split": "val", "path": "images/c.png", "future_key": {"x": 1}}
        ],
        "some_future_field": [1, 2, 3]
    });
    write_scene_json(dir, &scene);
    scene
}

pub fn write_scene_json(dir: &Path, scene: &Value) {
    std::fs::write(dir.join("scene.json"), serde_json::to_string_pretty(scene).unwrap()).unwrap();
}

pub fn shared_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared")
}

pub fn example_scene() -> PathBuf {
    let p = shared_dir().join("examples/quadruped-tiny");
    assert!(p.join("scene.json").is_file(), "the fixture {} is missing: ../shared must sit beside the repository", p.display());
    p
}

/// A tiny synthetic walking human (`size` pixels square, `cameras` cameras, two frames and one
/// test frame), written into `dir/scene`.
pub fn tiny_synth(dir: &Path, light: umbra::synth::TrainingLight, size: usize, cameras: usize, test: Vec<umbra::synth::TestKind>, seed: u64) -> PathBuf {
    let options = umbra::synth::SynthOptions {
        character: umbra::synth::Kind::Human,
        light,
        size,
        cameras,
        frames: 2,
        test_frames: 1,
        test,
        samples: 8,
        seed,
        meshes: false,
        mesh_cell: 0.02,
        ..umbra::synth::SynthOptions::default()
    };
    let out = dir.join("scene");
    umbra::synth::generate(&options, &out, false, |_, _| {}).unwrap();
    out
}

pub fn umbra(cwd: &Path, args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_umbra")).current_dir(cwd).args(args).output().unwrap()
}

/// Runs `umbra args` in `cwd` and requires it to succeed.
pub fn succeeds(cwd: &Path, args: &[&str]) {
    let out = umbra(cwd, args);
    assert!(out.status.success(), "umbra {args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

/// Runs `umbra args` in `cwd`, requires it to fail and returns its standard error.
pub fn fails(cwd: &Path, args: &[&str]) -> String {
    let out = umbra(cwd, args);
    assert!(!out.status.success(), "umbra {args:?} should have failed");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A tiny scene and a two-iteration run of it (no evaluation), in a fresh folder.
pub fn short_run(tag: &str) -> (TempDir, PathBuf, PathBuf) {
    let dir = TempDir::new(tag);
    let scene = tiny_synth(dir.path(), umbra::synth::TrainingLight::Sun, 24, 3, vec![umbra::synth::TestKind::Poses], 9);
    let run = dir.path().join("run");
    succeeds(&std::env::current_dir().unwrap(), &["fit", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "2", "--no-eval"]);
    (dir, scene, run)
}

/// Every file under `dir` with its bytes, to prove a refused command wrote nothing.
pub fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        if let Ok(entries) = std::fs::read_dir(&d) {
            for e in entries.flatten() {
                let p = e.path();
                if p.is_dir() {
                    stack.push(p);
                } else {
                    out.push((p.clone(), std::fs::read(&p).unwrap_or_default()));
                }
            }
        }
    }
    out.sort();
    out
}

/// Writes a checkpoint's `state.json` as an editor would who also updates the checksum beside
/// it (`state.checksum`).
pub fn rewrite_state(state_path: &Path, state: &Value) {
    std::fs::write(state_path, state.to_string()).unwrap();
    let sum = umbra::scene::identity::file_checksum(state_path).unwrap();
    std::fs::write(state_path.with_file_name("state.checksum"), sum).unwrap();
}

/// Makes a checkpoint look as one from before checksums were recorded: none for its files in
/// `state.json`, none for the state.
pub fn without_checksums(state_path: &Path, state: &mut Value) {
    state.as_object_mut().unwrap().remove("checksums");
    std::fs::write(state_path, state.to_string()).unwrap();
    let _ = std::fs::remove_file(state_path.with_file_name("state.checksum"));
}

/// A small sunlit synthetic scene's options (32 pixels, three cameras, three frames and a test
/// frame), exported as a capture when `export` says.
pub fn small_capture_options(export: Option<umbra::synth::Export>) -> umbra::synth::SynthOptions {
    umbra::synth::SynthOptions {
        light: umbra::synth::TrainingLight::Sun,
        size: 32,
        cameras: 3,
        frames: 3,
        test_frames: 1,
        test: vec![umbra::synth::TestKind::Poses],
        samples: 4,
        seed: 5,
        export,
        ..umbra::synth::SynthOptions::default()
    }
}

/// Import `capture` into `out` as a sunlit capture, everything else inferred.
pub fn import_options(capture: &Path, out: PathBuf) -> umbra::capture::ImportOptions {
    umbra::capture::ImportOptions {
        capture: capture.to_path_buf(),
        out,
        light: umbra::capture::CaptureLight::Sun,
        units: None,
        up: umbra::capture::Up::PlusY,
        cameras: None,
        motion: None,
        masks: None,
        max_size: None,
    }
}

/// A short schedule for tiny scenes: 60 iterations of small batches, the light fitted from the start.
pub const QUICK: &str = r#"
iterations = 60
rays_per_batch = 256
samples_per_ray = 16
density_points = 64
regulariser_points = 32
checkpoint_every = 20
light_from = 0
[learning_rates]
field = 3e-3
gaussians = 5e-3
light = 5e-2
[losses]
mask = 1.0
rgb = 1.0
eikonal = 0.05
density = 0.5
"#;
