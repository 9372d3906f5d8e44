//! Entry points for coverage-guided fuzzing (`fuzz/`, driven by `cargo fuzz`): everything
//! umbra reads from a user, fed from bytes. A scene, a light file or a checkpoint is a folder
//! of files, so its target reads the bytes as a small archive (`Folder`), writes it into a
//! scratch folder and reads it back with the same code `umbra` runs. Each target asserts what
//! must hold whatever the input: no panic outside a third-party decoder's guard, and a refusal
//! that names a file of the input. `cargo test` runs them on seed inputs
//! (`tests/fuzz_targets.rs`), so they keep compiling and keep passing on every finding kept in
//! `fuzz/regressions/`.

use crate::backend::Backend;
use crate::fit_error::FitError;
use crate::scene::Scene;
use crate::schedule::Schedule;
use crate::train::Trainer;
use std::path::{Component, Path, PathBuf};

/// What a target made of its input: read and accepted, or refused with an error (a harness
/// that could not even write its scratch files says `Refused` too). libFuzzer ignores it; the
/// tests use it to check that seed inputs reach the readers and are accepted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    Accepted,
    Refused,
}

/// A folder as bytes: entries of a little-endian `u16` name length, the name (a relative path,
/// `/`-separated), a little-endian `u32` content length and the content. A truncated entry
/// ends the folder; a name that is absolute, climbs out (`..`) or is not UTF-8 is skipped, so
/// the harness writes only inside its scratch folder (the readers' own refusal of such paths
/// in a scene is tested elsewhere, on the scene's JSON, which is fuzzed as is).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Folder {
    pub files: Vec<(String, Vec<u8>)>,
}

impl Folder {
    pub fn decode(mut data: &[u8]) -> Folder {
        let mut files = Vec::new();
        let take = |n: usize, data: &mut &[u8]| -> Option<Vec<u8>> {
            let (head, rest) = (data.get(..n)?, data.get(n..)?);
            *data = rest;
            Some(head.to_vec())
        };
        while let Some(len) = take(2, &mut data) {
            let Some(name) = take(u16::from_le_bytes([len[0], len[1]]) as usize, &mut data) else { break };
            let Some(len) = take(4, &mut data) else { break };
            let Some(content) = take(u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize, &mut data) else { break };
            if let Ok(name) = String::from_utf8(name) {
                if safe_name(&name) {
                    files.push((name, content));
                }
            }
        }
        Folder { files }
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        for (name, content) in &self.files {
            out.extend_from_slice(&(name.len() as u16).to_le_bytes());
            out.extend_from_slice(name.as_bytes());
            out.extend_from_slice(&(content.len() as u32).to_le_bytes());
            out.extend_from_slice(content);
        }
        out
    }

    /// Every file under `dir` (for seed inputs), names relative to it, in a fixed order.
    pub fn read_dir(dir: &Path) -> std::io::Result<Folder> {
        let mut files = Vec::new();
        let mut stack = vec![dir.to_path_buf()];
        while let Some(d) = stack.pop() {
            let mut entries: Vec<PathBuf> = std::fs::read_dir(&d)?.map(|e| e.map(|e| e.path())).collect::<Result<_, _>>()?;
            entries.sort();
            for path in entries {
                if path.is_dir() {
                    stack.push(path);
                } else if let Ok(relative) = path.strip_prefix(dir) {
                    let name = relative.components().map(|c| c.as_os_str().to_string_lossy().into_owned()).collect::<Vec<_>>().join("/");
                    files.push((name, std::fs::read(&path)?));
                }
            }
        }
        Ok(Folder { files })
    }

    /// Writes the files into `dir` (emptied first). A name that cannot be written (a file where
    /// a folder is needed, say) is left out, as a folder could not hold it either.
    pub fn write_into(&self, dir: &Path) -> std::io::Result<()> {
        let _ = std::fs::remove_dir_all(dir);
        std::fs::create_dir_all(dir)?;
        for (name, content) in &self.files {
            let path = dir.join(name);
            if let Some(parent) = path.parent() {
                if std::fs::create_dir_all(parent).is_err() {
                    continue;
                }
            }
            let _ = std::fs::write(&path, content);
        }
        Ok(())
    }
}

fn safe_name(name: &str) -> bool {
    let path = Path::new(name);
    !name.is_empty() && !name.contains('\\') && path.components().all(|c| matches!(c, Component::Normal(_)))
}

/// A scratch folder for one target in this process, under the system's temp folder.
pub fn scratch(target: &str) -> PathBuf {
    std::env::temp_dir().join(format!("umbra-fuzz-{target}-{}", std::process::id()))
}

/// A panic hook for fuzzing: a panic inside a third-party decoder's guard
/// (`imageio::inside_decoder_guard`) is the decoder's, caught and reported as a corrupt file,
/// so it unwinds to the guard; any other panic is a finding and aborts the process, as
/// libFuzzer's own hook does.
pub fn install_panic_hook() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        std::panic::set_hook(Box::new(|info| {
            if crate::imageio::inside_decoder_guard() {
                return;
            }
            eprintln!("{info}");
            std::process::abort();
        }))
    });
}

/// The scene reader on a folder: `scene.json` and the files it names. A scene that loads is
/// also summarised and its footprint estimated (both read every training image); a refused
/// one must name a file inside the folder.
pub fn scene(data: &[u8]) -> Outcome {
    let dir = scratch("scene");
    if Folder::decode(data).write_into(&dir).is_err() {
        return Outcome::Refused;
    }
    match Scene::load(&dir) {
        Ok(scene) => {
            let _ = crate::scene::summary(&scene);
            let _ = scene.footprint();
            let _ = scene.body_extent();
            Outcome::Accepted
        }
        Err(e) => {
            assert!(e.file.starts_with(&dir), "a refused scene names a file outside it: {e}");
            Outcome::Refused
        }
    }
}

/// The image readers on one file's bytes, as a PNG and as an EXR: colour, mask and header.
/// Whatever they decode has the size its header declared.
pub fn image(data: &[u8]) -> Outcome {
    let dir = scratch("image");
    if std::fs::create_dir_all(&dir).is_err() {
        return Outcome::Refused;
    }
    let mut outcome = Outcome::Refused;
    for name in ["image.png", "image.exr"] {
        let path = dir.join(name);
        if std::fs::write(&path, data).is_err() {
            return Outcome::Refused;
        }
        let header = crate::imageio::dimensions(&path).ok();
        if let Ok(image) = crate::imageio::read_rgb(&path) {
            assert_eq!(image.pixels.len(), image.width * image.height);
            assert_eq!(header, Some((image.width, image.height)), "{name}: decoded size differs from the header's");
            outcome = Outcome::Accepted;
        }
        if let Ok(mask) = crate::imageio::read_mask(&path) {
            assert_eq!(mask.foreground.len(), mask.width * mask.height);
            assert_eq!(header, Some((mask.width, mask.height)), "{name}: decoded mask size differs from the header's");
        }
    }
    outcome
}

/// The schedule parser on a text: a refusal names the file it was given.
pub fn schedule(data: &[u8]) -> Outcome {
    let text = String::from_utf8_lossy(data);
    let file = Path::new("fuzzed.toml");
    match Schedule::parse(&text, file) {
        Ok(_) => Outcome::Accepted,
        Err(e) => {
            assert_eq!(e.file, file);
            Outcome::Refused
        }
    }
}

/// The light-file reader (`umbra relight --light FILE.json`) on a folder: `light.json` and
/// what it names (an environment map).
pub fn light(data: &[u8]) -> Outcome {
    let dir = scratch("light");
    if Folder::decode(data).write_into(&dir).is_err() {
        return Outcome::Refused;
    }
    match crate::scene::load_light(&dir.join("light.json")) {
        Ok(_) => Outcome::Accepted,
        Err(e) => {
            assert!(e.file.starts_with(&dir), "a refused light names a file outside it: {e}");
            Outcome::Refused
        }
    }
}

/// The clip readers on a text, as a BVH and as `joints.json`: a clip read is checked as every
/// command checks one (`Motion::problem`) and, when it passes, posed in every frame and rigged;
/// its poses are finite. A refusal names the file it was given.
pub fn clip(data: &[u8]) -> Outcome {
    let text = String::from_utf8_lossy(data);
    let file = Path::new("fuzzed.bvh");
    let bvh = crate::capture::bvh::parse(&text, file).map_err(|e| assert_eq!(e.file, file));
    let dir = scratch("clip");
    let json = std::fs::create_dir_all(&dir)
        .ok()
        .and_then(|_| std::fs::write(dir.join("joints.json"), data).ok())
        .and_then(|_| crate::capture::joints::read(&dir.join("joints.json")).map_err(|e| assert!(e.to_string().contains("joints.json"), "{e}")).ok());
    let mut outcome = Outcome::Refused;
    for motion in bvh.ok().into_iter().chain(json) {
        if motion.problem().is_some() {
            continue;
        }
        for k in 0..motion.frames.len() {
            let joints = motion.joint_to_world(k);
            assert!(joints.iter().all(|m| m.is_finite()), "frame {k}: a clip that passed its checks poses a joint nowhere");
        }
        let _ = crate::capture::bones::rig(&motion);
        outcome = Outcome::Accepted;
    }
    outcome
}

/// The COLMAP text model reader on a folder (`cameras.txt`, `images.txt`): every image it
/// accepts has a camera no check refuses; a refusal names a file inside the folder.
pub fn colmap(data: &[u8]) -> Outcome {
    let dir = scratch("colmap");
    if Folder::decode(data).write_into(&dir).is_err() {
        return Outcome::Refused;
    }
    match crate::capture::colmap::read(&dir, &dir.join("images")) {
        Ok(images) => {
            for image in &images {
                assert!(image.intrinsics.problem(&image.distortion).is_none() && image.camera_to_world.is_finite());
                assert!(image.path.starts_with(dir.join("images")), "an image outside the capture: {}", image.path.display());
            }
            Outcome::Accepted
        }
        Err(e) => {
            assert!(e.to_string().contains(&dir.display().to_string()), "a refused model names a file inside it: {e}");
            Outcome::Refused
        }
    }
}

/// The nerfstudio `transforms.json` reader on a text: the same promises as `colmap`.
pub fn transforms(data: &[u8]) -> Outcome {
    let dir = scratch("transforms");
    let file = dir.join("transforms.json");
    if std::fs::create_dir_all(&dir).and_then(|_| std::fs::write(&file, data)).is_err() {
        return Outcome::Refused;
    }
    match crate::capture::nerfstudio::read(&file) {
        Ok(images) => {
            for image in &images {
                assert!(image.intrinsics.problem(&image.distortion).is_none() && image.camera_to_world.is_finite());
                assert!(image.path.starts_with(&dir), "an image outside the capture: {}", image.path.display());
            }
            Outcome::Accepted
        }
        Err(e) => {
            assert_eq!(e.file, file);
            Outcome::Refused
        }
    }
}

/// The checkpoint loader: a fresh trainer (the scene and schedule of the run the seed
/// checkpoint came from) resumed from a fuzzed checkpoint folder (`state.json`, `model.bpk`,
/// `optimizer-*.bpk`), as `umbra fit --resume` and `umbra render` load one.
pub struct CheckpointTarget {
    scene: Scene,
    schedule: Schedule,
}

impl CheckpointTarget {
    /// The scene and schedule of `run` (a finished `umbra fit` folder), with its field as its
    /// checkpoint records it (so a trainer is built without looking at the training masks).
    pub fn new(run: &Path, scene: &Path) -> Result<Self, FitError> {
        let restored = crate::run::restore(run, Some(scene), Backend::Flex)?;
        Ok(Self { scene: restored.scene.clone(), schedule: restored.schedule.clone() })
    }

    pub fn run(&self, data: &[u8]) -> Outcome {
        let dir = scratch("checkpoint");
        let checkpoint = dir.join(crate::run::CHECKPOINT);
        if Folder::decode(data).write_into(&checkpoint).is_err() {
            return Outcome::Refused;
        }
        let Ok(mut trainer) = Trainer::new(self.scene.clone(), self.schedule.clone(), Backend::Flex, 0) else { return Outcome::Refused };
        match crate::run::resume_checkpoint(&mut trainer, &dir) {
            Ok(_) => Outcome::Accepted,
            Err(e) => {
                let text = e.to_string();
                assert!(text.contains(&dir.display().to_string()), "a refused checkpoint names a file inside it: {text}");
                Outcome::Refused
            }
        }
    }
}
