//! `umbra synth`: synthetic scenes with exact ground truth in the `scene/1` format. A
//! procedural human or quadruped walks (or trots) a cycle in front of a ring of cameras under a
//! sun, a point light or uniform light; test images hold novel poses, a novel view and
//! relighting by a second sun, a point light and an environment map the generator synthesises.

pub mod character;
pub mod clothing;
pub mod mesh;
mod plan;
pub mod trace;
mod write;

pub use plan::{synthetic_sky, Plan, PlannedView};
pub use write::{generate, Report};

use crate::imageio::{self, Mask, RgbImage};
use crate::light::{uv_to_direction, EnvironmentMap, Light};
use crate::scene::{Camera, Split};
use crate::skeleton::Pose;
pub use character::{Character, Kind, Pattern};
use glam::{DMat4, DVec3};
use rayon::prelude::*;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use trace::{shade, Stream, Traced};

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TrainingLight {
    /// A directional sun with ambient: shadows to recover.
    Sun,
    /// Uniform light from every direction: albedo only.
    Uniform,
    /// A point light with ambient.
    Point,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TestKind {
    /// Frames whose pose never appears in training, seen by training cameras.
    Poses,
    /// A camera never used in training.
    Views,
    /// A second sun, a point light and an environment map.
    Relight,
}

/// Everything that determines a synthetic scene; the same options give the same bytes.
#[derive(Clone, Debug, clap::Args, serde::Serialize, serde::Deserialize)]
pub struct SynthOptions {
    /// The character.
    #[arg(long, value_enum, default_value_t = Kind::Human)]
    pub character: Kind,
    /// The light of the training images.
    #[arg(long, value_enum, default_value_t = TrainingLight::Sun)]
    pub light: TrainingLight,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 64)]
    pub size: usize,
    /// Training cameras (1 makes a monocular capture in which the character turns around).
    #[arg(long, default_value_t = 6)]
    pub cameras: usize,
    /// Training frames over one motion cycle.
    #[arg(long, default_value_t = 12)]
    pub frames: usize,
    /// Test frames (novel poses, between the training ones).
    #[arg(long, default_value_t = 3)]
    pub test_frames: usize,
    /// Which test images to make.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "poses,views,relight")]
    pub test: Vec<TestKind>,
    /// With `--test relight`: how many test views (camera and novel pose) each relighting light
    /// is rendered in, the same views as the novel-pose images where there are that many, so
    /// one geometry is seen under several lights as a light-stage capture's test set has it.
    #[arg(long, default_value_t = 1)]
    #[serde(default = "one_relit_view", skip_serializing_if = "is_one_relit_view")]
    pub relit_views: usize,
    /// Monte Carlo samples per pixel for uniform and environment light.
    #[arg(long, default_value_t = 256)]
    pub samples: usize,
    /// The clothing's albedo pattern.
    #[arg(long, value_enum, default_value_t = Pattern::Plain)]
    #[serde(default, skip_serializing_if = "Pattern::is_plain")]
    pub pattern: Pattern,
    /// Seed of camera placement and Monte Carlo sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Scale of the character, its motion, the cameras' distance and the lamps' positions (a
    /// lamp's intensity with its distance squared, so the body is lit the same): 0.3 for a
    /// cat-sized human, 3 for a giant.
    #[arg(long, default_value_t = 1.0)]
    #[serde(default = "unit_scale", skip_serializing_if = "is_unit_scale")]
    pub scale: f64,
    /// With `--light point`: put the training lamp this far (metres, before `--scale`) from the
    /// body's centre, in the direction of its usual place 2.3 m away, its intensity with the
    /// square of the distance so the body is lit as brightly (a near lamp: 1).
    #[arg(long)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lamp_distance: Option<f64>,
    /// With `--light sun`: this many training suns (1-4) of different directions and colours,
    /// a light-stage-like capture: camera c in frame f is lit by sun (c + f) mod N.
    #[arg(long, default_value_t = 1)]
    #[serde(default = "one_sun", skip_serializing_if = "is_one_sun")]
    pub suns: usize,
    /// With `--light sun`: the training sun's direction (toward the sun, normalised; default
    /// 0.45,0.8,0.4: high, on the side of the first camera), to see a fit under other suns: low,
    /// from the side, from behind the character.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sun_direction: Option<Vec<f64>>,
    /// Anti-aliasing as a path tracer does it: N x N stratified rays per pixel, averaged (a box
    /// filter over the pixel); the mask is coverage above one half and pixels outside it are
    /// black, as the scene format asks. 1: one ray through the pixel's centre.
    #[arg(long, default_value_t = 1)]
    #[serde(default = "one_pixel_sample", skip_serializing_if = "is_one_pixel_sample")]
    pub pixel_samples: usize,
    /// Also write a ground-truth OBJ mesh per frame (marching tetrahedra of the exact SDF).
    #[arg(long)]
    #[serde(default)]
    pub meshes: bool,
    /// Grid cell of the meshes, metres.
    #[arg(long, default_value_t = 0.02)]
    #[serde(default = "default_mesh_cell")]
    pub mesh_cell: f64,
    /// Write the scene as a capture as people have them instead: `nerfstudio` writes
    /// transforms.json (OpenGL camera axes, centimetres), motion.bvh (centimetres) and plates
    /// with a background, of the images under the training light (what `umbra import` reads).
    #[arg(long, value_enum)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub export: Option<Export>,
    /// With --export: put the errors a real pipeline leaves into the capture's training images,
    /// frames and cameras, keeping the exact cameras and motion in truth/: `real` (a tracker's
    /// 2.5 degrees per joint channel and 1 cm at the root, masks a pixel off with two blobs,
    /// cameras off by 0.1 degrees and 3 mm, 6% gain and 3% white balance per camera, JPEG 88),
    /// or KEY=VALUE,... of joints, root, masks, blobs, camera_turn, camera_move, gain,
    /// white_balance, jpeg (after `real,` to change some).
    #[arg(long, value_name = "SPEC", value_parser = crate::capture::flaws::CaptureErrors::parse, requires = "export")]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub errors: Option<crate::capture::flaws::CaptureErrors>,
}

/// The capture formats `synth --export` writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Export {
    Nerfstudio,
}

/// Centimetres per metre: the unit of `synth --export`'s capture, as motion capture writes it.
pub const EXPORT_UNITS: f64 = 100.0;

fn default_mesh_cell() -> f64 {
    0.02
}

fn one_pixel_sample() -> usize {
    1
}

fn is_one_pixel_sample(n: &usize) -> bool {
    *n == 1
}

fn one_relit_view() -> usize {
    1
}

fn is_one_relit_view(n: &usize) -> bool {
    *n == 1
}

fn one_sun() -> usize {
    1
}

fn is_one_sun(suns: &usize) -> bool {
    *suns == 1
}

fn unit_scale() -> f64 {
    1.0
}

fn is_unit_scale(scale: &f64) -> bool {
    *scale == 1.0
}

impl Default for SynthOptions {
    fn default() -> Self {
        Self {
            character: Kind::Human,
            light: TrainingLight::Sun,
            size: 64,
            cameras: 6,
            frames: 12,
            test_frames: 3,
            test: vec![TestKind::Poses, TestKind::Views, TestKind::Relight],
            relit_views: 1,
            samples: 256,
            pattern: Pattern::Plain,
            seed: 0,
            scale: 1.0,
            lamp_distance: None,
            suns: 1,
            sun_direction: None,
            pixel_samples: 1,
            meshes: false,
            mesh_cell: 0.02,
            export: None,
            errors: None,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error("{0}")]
    Options(String),
    #[error("{path}: {message}")]
    Io { path: PathBuf, message: String },
}

fn io_error(path: &Path, e: impl std::fmt::Display) -> SynthError {
    SynthError::Io { path: path.to_path_buf(), message: e.to_string() }
}

/// Linear colour, mask and albedo of one view.
pub struct Rendered {
    pub colour: RgbImage,
    pub mask: Mask,
    pub albedo: RgbImage,
}

/// Renders one view of a posed character exactly per the scene format's image formation, with
/// `pixel_samples` x `pixel_samples` stratified rays per pixel (1: the pixel's centre) whose
/// colour and albedo are averaged; the mask is coverage above one half, and pixels outside it
/// are black in colour and albedo.
/// A traced pixel: colour, mask, albedo.
type TracedPixel = ([f32; 3], bool, [f32; 3]);

#[allow(clippy::too_many_arguments)] // what a view needs and the two seeds of its noise
pub fn render_view(
    character: &Character,
    pose: &Pose,
    camera: &Camera,
    light: &Light,
    samples: usize,
    pixel_samples: usize,
    seed: u64,
    view_id: u64,
) -> Rendered {
    let traced = Traced::new(character, pose);
    let (w, h) = (camera.width, camera.height);
    let n = pixel_samples.max(1);
    let rows: Vec<Vec<TracedPixel>> = (0..h)
        .into_par_iter()
        .map(|j| {
            (0..w)
                .map(|i| {
                    let (mut colour, mut albedo, mut covered) = (DVec3::ZERO, DVec3::ZERO, 0usize);
                    for s in 0..n * n {
                        let at = glam::DVec2::new(i as f64 + ((s % n) as f64 + 0.5) / n as f64, j as f64 + ((s / n) as f64 + 0.5) / n as f64);
                        let ray = camera.ray_through(at);
                        if let Some(hit) = traced.intersect(&ray, f64::INFINITY) {
                            let a = character.albedo(pose, hit.point);
                            let mut stream = Stream::new(seed, view_id, ((j * w + i) * n * n + s) as u64);
                            colour += shade(&traced, &hit, a, light, samples, &mut stream);
                            albedo += a;
                            covered += 1;
                        }
                    }
                    if 2 * covered <= n * n {
                        return ([0.0; 3], false, [0.0; 3]);
                    }
                    let share = 1.0 / (n * n) as f64;
                    ((colour * share).as_vec3().to_array(), true, (albedo * share).as_vec3().to_array())
                })
                .collect()
        })
        .collect();
    let mut colour = RgbImage::new(w, h);
    let mut albedo = RgbImage::new(w, h);
    let mut foreground = Vec::with_capacity(w * h);
    for (j, row) in rows.into_iter().enumerate() {
        for (i, (c, m, a)) in row.into_iter().enumerate() {
            colour.set(i, j, c);
            albedo.set(i, j, a);
            foreground.push(m);
        }
    }
    Rendered { colour, mask: Mask { width: w, height: h, foreground: foreground.into() }, albedo }
}
