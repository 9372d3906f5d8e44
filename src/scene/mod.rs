//! Reading and validating `scene/1` captures: cameras, skeleton, frames, lights and images.
//! This module is the only one that opens the files of a capture; every problem it finds is
//! reported with the file and the JSON path of the offending value.

mod camera;
pub mod footprint;
pub mod identity;
pub mod json;
mod reader;

pub use camera::{world_up, Camera, Ray};
pub use footprint::{Footprint, FootprintEstimate};
pub use json::SceneError;

use crate::imageio::{Mask, RgbImage};
use crate::light::Light;
use crate::skeleton::{Pose, Skeleton};
use json::At;
use reader::Reader;
use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};

pub const FORMAT: &str = "scene/1";

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub index: i64,
    pub time: Option<f64>,
    pub pose: Pose,
    pub mesh: Option<PathBuf>,
}

/// One image of the capture, decoded: colour in linear RGB, mask and albedo if given.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    pub camera: usize,
    /// Position in `Scene::frames` (not `Frame::index`).
    pub frame: usize,
    pub light: String,
    pub split: Split,
    pub path: PathBuf,
    pub colour: crate::photo::Photo,
    pub mask: Option<Mask>,
    pub albedo: Option<RgbImage>,
    /// What the camera saw behind the body (`images[*].plate`, umbra's own key, written by
    /// `umbra import` for a static camera's training images): the image then keeps the photo
    /// within `silhouette::EDGE_BAND` of its mask's edge where the plate is known, and a fit
    /// composites over the plate there. Shared by the images of one camera.
    pub plate: Option<std::sync::Arc<crate::silhouette::Plate>>,
}

/// The capture a scene was converted from by `umbra import` (`capture`, umbra's own key): its
/// units and its world turned into scene/1's, so that what a fit gives back of the capture (the
/// refined motion) can be in the capture's terms.
#[derive(Clone, Debug, PartialEq)]
pub struct CaptureWorld {
    /// Metres per capture unit.
    pub metres_per_unit: f64,
    /// The capture's world to scene/1's: a rotation.
    pub to_scene: glam::DMat4,
}

#[derive(Clone, Debug)]
pub struct Scene {
    /// The folder holding `scene.json`.
    pub root: PathBuf,
    pub name: Option<String>,
    /// The capture it was imported from, when `umbra import` wrote it.
    pub capture: Option<CaptureWorld>,
    pub skeleton: Skeleton,
    pub cameras: Vec<Camera>,
    pub frames: Vec<Frame>,
    pub lights: BTreeMap<String, Light>,
    pub views: Vec<View>,
    /// `footprint`'s estimate, made once: it reads every training image, and every rendered
    /// view asks for it (2% of a 148-image evaluation when it was read again per view).
    footprint: std::sync::OnceLock<FootprintEstimate>,
}

/// Where a scene lives: a folder with `scene.json`, or the JSON file itself.
pub fn scene_file(path: &Path) -> PathBuf {
    if path.is_dir() {
        path.join("scene.json")
    } else {
        path.to_path_buf()
    }
}

impl Scene {
    /// Reads, validates and decodes a whole scene (every image, mask and environment map).
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        Scene::load_reporting(path, &|_, _| {})
    }

    /// `load`, telling `on(done, total)` as each image is decoded (from the decoding threads).
    pub fn load_reporting(path: &Path, on: &(dyn Fn(usize, usize) + Sync)) -> Result<Scene, SceneError> {
        let file = scene_file(path);
        let root = file.parent().map(Path::to_path_buf).unwrap_or_default();
        let text = crate::files::read_text(&file, crate::files::SCENE_BYTES).map_err(|e| SceneError {
            file: file.clone(),
            path: String::new(),
            message: read_message(e),
        })?;
        let value = json::parse(&text, &file)?;
        let doc = At::root(&value, &file);
        Reader { root: &root, file: &file, on_image: Some(on) }.scene(&doc)
    }

    pub fn views_in(&self, split: Split) -> impl Iterator<Item = &View> {
        self.views.iter().filter(move |v| v.split == split)
    }

    /// The frames (positions) with a training image, in order.
    pub fn training_frames(&self) -> Vec<usize> {
        let mut frames: Vec<usize> = self.views_in(Split::Train).map(|v| v.frame).collect();
        frames.sort_unstable();
        frames.dedup();
        frames
    }

    /// The names of the lights used by training views.
    pub fn training_lights(&self) -> Vec<&str> {
        let mut names: Vec<&str> = self.views_in(Split::Train).map(|v| v.light.as_str()).collect();
        names.sort();
        names.dedup();
        names
    }

    /// The body's extent (m): the largest diagonal of the posed bones' box over the frames (a
    /// character that walks across the scene is no bigger for it). The fit's and the
    /// renderer's lengths are fractions of it (`skeleton::body_length`).
    pub fn body_extent(&self) -> f64 {
        self.frames.iter().map(|f| f.pose.bounds(&self.skeleton)).map(|(a, b)| (b - a).length()).fold(0.0, f64::max)
    }

    /// Whether the training images sample pixels at their centres or over their area
    /// (`footprint::estimate`), from the images as loaded.
    pub fn footprint(&self) -> FootprintEstimate {
        *self.footprint.get_or_init(|| footprint::estimate(self))
    }

    pub fn display_name(&self) -> String {
        self.name.clone().unwrap_or_else(|| self.root.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default())
    }
}

/// Reads one light in the scene format from a JSON file (an environment's `path` is relative
/// to that file's folder), e.g. for `umbra relight --light sunset.json`.
pub fn load_light(file: &Path) -> Result<Light, SceneError> {
    let root = file.parent().map(Path::to_path_buf).unwrap_or_default();
    let text = crate::files::read_text(file, crate::files::SMALL_TEXT_BYTES).map_err(|e| SceneError {
        file: file.to_path_buf(),
        path: String::new(),
        message: read_message(e),
    })?;
    let value = json::parse(&text, file)?;
    Reader { root: &root, file, on_image: None }.light(&At::root(&value, file))
}

/// What is wrong with an environment map's radiance, if anything: a value not finite, or
/// negative (light cannot be negative; the irradiance it gives would be refused).
pub fn environment_problem(image: &RgbImage) -> Option<String> {
    if let Some(bad) = image.pixels.iter().find(|p| p.iter().any(|c| !c.is_finite())) {
        return Some(format!("environment map holds a non-finite value {bad:?}"));
    }
    let (k, bad) = image.pixels.iter().enumerate().find(|(_, p)| p.iter().any(|&c| c < 0.0))?;
    Some(format!("environment map holds a negative radiance {bad:?} at pixel ({}, {})", k % image.width.max(1), k / image.width.max(1)))
}

/// What a failed bounded read says (the file is named beside it).
pub(super) fn read_message(e: std::io::Error) -> String {
    match e.kind() {
        std::io::ErrorKind::NotFound | std::io::ErrorKind::InvalidInput => e.to_string(),
        _ => format!("cannot read: {e}"),
    }
}

/// Reads a scene's `scene.json`, or another JSON file a capture holds, as bounded text.
pub fn read_capped(file: &Path) -> Result<String, SceneError> {
    crate::files::read_text(file, crate::files::SCENE_BYTES).map_err(|e| SceneError { file: file.to_path_buf(), path: String::new(), message: read_message(e) })
}

/// A human-readable summary: cameras, frames, bones, images per split and light, bounds.
pub fn summary(scene: &Scene) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(out, "scene {:?} ({})", scene.display_name(), scene.root.display());
    let mut sizes: BTreeMap<(usize, usize), usize> = BTreeMap::new();
    for c in &scene.cameras {
        *sizes.entry((c.width, c.height)).or_default() += 1;
    }
    let sizes: Vec<String> = sizes.iter().map(|((w, h), n)| format!("{n} x {w}x{h}")).collect();
    let _ = writeln!(out, "cameras: {} ({})", scene.cameras.len(), sizes.join(", "));
    let _ = writeln!(out, "frames:  {}", scene.frames.len());
    let roots = scene.skeleton.bones.iter().filter(|b| b.parent.is_none()).count();
    let _ = writeln!(out, "bones:   {} ({} root{})", scene.skeleton.len(), roots, if roots == 1 { "" } else { "s" });
    let _ = writeln!(out, "lights:");
    for (name, light) in &scene.lights {
        let _ = writeln!(out, "  {name}: {}", light.type_name());
    }
    let _ = writeln!(out, "images:");
    let mut counts: BTreeMap<(Split, &str), usize> = BTreeMap::new();
    for v in &scene.views {
        *counts.entry((v.split, v.light.as_str())).or_default() += 1;
    }
    for ((split, light), n) in &counts {
        let _ = writeln!(out, "  {:<5} {light}: {n}", split.name());
    }
    let train_frames: HashSet<usize> = scene.views_in(Split::Train).map(|v| v.frame).collect();
    let train_cameras: HashSet<usize> = scene.views_in(Split::Train).map(|v| v.camera).collect();
    let train_lights: HashSet<&str> = scene.training_lights().into_iter().collect();
    let test: Vec<&View> = scene.views_in(Split::Test).collect();
    let _ = writeln!(
        out,
        "test:    {} novel pose, {} novel view, {} relit",
        test.iter().filter(|v| !train_frames.contains(&v.frame)).count(),
        test.iter().filter(|v| !train_cameras.contains(&v.camera)).count(),
        test.iter().filter(|v| !train_lights.contains(v.light.as_str())).count()
    );
    let mut lo = glam::DVec3::splat(f64::INFINITY);
    let mut hi = glam::DVec3::splat(f64::NEG_INFINITY);
    for f in &scene.frames {
        let (a, b) = f.pose.bounds(&scene.skeleton);
        lo = lo.min(a);
        hi = hi.max(b);
    }
    let _ = writeln!(out, "skeleton bounds over all frames: [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}] m", lo.x, lo.y, lo.z, hi.x, hi.y, hi.z);
    out
}
