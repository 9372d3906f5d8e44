//! `umbra synth`: synthetic scenes with exact ground truth in the `scene/1` format. A
//! procedural human or quadruped walks (or trots) a cycle in front of a ring of cameras under a
//! sun, a point light or uniform light; test images hold novel poses, a novel view and
//! relighting by a second sun, a point light and an environment map the generator synthesises.

pub mod character;
pub mod clothing;
pub mod mesh;
pub mod trace;

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

/// One image the generator will render.
#[derive(Clone, Debug)]
pub struct PlannedView {
    pub camera: usize,
    pub frame: usize,
    pub light: String,
    pub split: Split,
    pub name: String,
}

/// The scene before rendering: cameras, poses, lights and the images to make.
pub struct Plan {
    pub character: Character,
    pub cameras: Vec<Camera>,
    /// (frame index written to JSON, time, pose)
    pub frames: Vec<(i64, f64, Pose)>,
    pub lights: Vec<(String, Light)>,
    pub views: Vec<PlannedView>,
}

/// The training suns after the first of a capture lit by several (`--suns`): name, direction,
/// irradiance and ambient, spread over the sky and in colour.
#[allow(clippy::type_complexity)]
const EXTRA_SUNS: [(&str, [f64; 3], [f64; 3], [f64; 3]); 3] = [
    ("sun-b", [-0.7, 0.6, 0.3], [0.7, 0.75, 0.9], [0.12, 0.12, 0.14]),
    ("sun-c", [0.1, 0.7, -0.7], [1.0, 0.9, 0.75], [0.15, 0.14, 0.12]),
    ("sun-d", [0.8, 0.35, -0.3], [0.8, 0.8, 0.8], [0.1, 0.1, 0.1]),
];

fn sun(direction: [f64; 3], irradiance: [f64; 3], ambient: [f64; 3]) -> Light {
    Light::Directional { direction: DVec3::from_array(direction).normalize(), irradiance: DVec3::from_array(irradiance), ambient: DVec3::from_array(ambient) }
}

/// A sky for relighting: blue above, warm horizon, dark ground and a bright sun disc.
pub fn synthetic_sky(width: usize, height: usize) -> EnvironmentMap {
    let sun_direction = DVec3::new(0.5, 0.55, -0.67).normalize();
    let mut image = RgbImage::new(width, height);
    for y in 0..height {
        for x in 0..width {
            let d = uv_to_direction((x as f64 + 0.5) / width as f64, (y as f64 + 0.5) / height as f64);
            let up = d.y;
            let sky = if up >= 0.0 {
                DVec3::new(0.35, 0.5, 0.9).lerp(DVec3::new(0.9, 0.85, 0.75), (1.0 - up).powi(4))
            } else {
                DVec3::new(0.25, 0.2, 0.15) * (1.0 + up * 0.5)
            };
            let angle = d.dot(sun_direction).clamp(-1.0, 1.0).acos();
            let disc = DVec3::new(30.0, 27.0, 22.0) * (-(angle / 0.08).powi(2)).exp();
            let c = (sky * 0.6 + disc).as_vec3().to_array();
            image.set(x, y, c);
        }
    }
    EnvironmentMap { image }
}

impl SynthOptions {
    fn check(&self) -> Result<(), SynthError> {
        let bad = |m: &str| Err(SynthError::Options(m.into()));
        if !(8..=1024).contains(&self.size) {
            return bad("--size must be within 8..=1024");
        }
        if self.cameras == 0 || self.cameras > 64 {
            return bad("--cameras must be within 1..=64");
        }
        if self.frames == 0 || self.frames > 1000 {
            return bad("--frames must be within 1..=1000");
        }
        if self.test_frames > 100 {
            return bad("--test-frames must be at most 100");
        }
        if self.samples == 0 {
            return bad("--samples must be positive");
        }
        if !(1..=16).contains(&self.pixel_samples) {
            return bad("--pixel-samples must be within 1..=16");
        }
        if !(self.mesh_cell >= 0.002 && self.mesh_cell <= 0.5) {
            return bad("--mesh-cell must be within 0.002..=0.5 metres");
        }
        if !(self.scale >= 0.05 && self.scale <= 20.0) {
            return bad("--scale must be within 0.05..=20");
        }
        if self.suns == 0 || self.suns > EXTRA_SUNS.len() + 1 {
            return bad(&format!("--suns must be within 1..={}", EXTRA_SUNS.len() + 1));
        }
        if self.suns > 1 && self.light != TrainingLight::Sun {
            return bad("--suns needs --light sun");
        }
        if let Some(d) = &self.sun_direction {
            if self.light != TrainingLight::Sun {
                return bad("--sun-direction needs --light sun");
            }
            let length = d.iter().map(|v| v * v).sum::<f64>().sqrt();
            if d.len() != 3 || !length.is_finite() || length < 1e-6 {
                return bad("--sun-direction must be three finite numbers x,y,z, not all zero");
            }
        }
        if let Some(d) = self.lamp_distance {
            if self.light != TrainingLight::Point {
                return bad("--lamp-distance needs --light point");
            }
            if !(d >= 0.5 && d <= 20.0) {
                return bad("--lamp-distance must be within 0.5..=20 metres (nearer, the lamp would sit inside the body)");
            }
        }
        Ok(())
    }

    /// Lays out cameras, frames, lights and views.
    pub fn plan(&self) -> Result<Plan, SynthError> {
        self.check()?;
        let character = Character::new(self.character).with_pattern(self.pattern).scaled(self.scale);
        let mut stream = Stream::new(self.seed, 0xCA3E_4A5, 0);
        let (target, extent) = match self.character {
            Kind::Human | Kind::Dressed => (DVec3::new(0.0, 0.9, 0.0), 1.05),
            Kind::Quadruped => (DVec3::new(0.0, 0.45, 0.0), 0.75),
        };
        let (target, extent) = (target * self.scale, extent * self.scale);
        // A lamp scaled with the body, its intensity with the square of its distance.
        let lamp = |position: [f64; 3], intensity: [f64; 3], ambient: [f64; 3]| Light::Point {
            position: DVec3::from_array(position) * self.scale,
            intensity: DVec3::from_array(intensity) * (self.scale * self.scale),
            ambient: DVec3::from_array(ambient),
        };
        let focal = 1.2 * self.size as f64;
        let distance = focal * extent / (0.45 * self.size as f64);
        let ring = |name: String, azimuth: f64, elevation: f64| {
            let eye = target + DVec3::new(azimuth.sin() * elevation.cos(), elevation.sin(), azimuth.cos() * elevation.cos()) * distance;
            Camera::look_at(&name, eye, target, DVec3::Y, self.size, self.size, focal)
        };
        let mut cameras = Vec::new();
        for c in 0..self.cameras {
            let azimuth = 2.0 * std::f64::consts::PI * (c as f64 + 0.3 * (stream.uniform() - 0.5)) / self.cameras as f64 + 0.35;
            let elevation = (8.0 + 14.0 * stream.uniform()).to_radians();
            cameras.push(ring(format!("cam{c:02}"), azimuth, elevation));
        }
        let novel_view = self.test.contains(&TestKind::Views);
        if novel_view {
            let azimuth = 0.35 + std::f64::consts::PI / self.cameras as f64;
            cameras.push(ring("heldout".into(), azimuth, 32f64.to_radians()));
        }
        // A monocular capture needs the character to turn so the one camera sees all sides.
        let turns = if self.cameras == 1 { 1.0 } else { 0.0 };
        let pose_at = |phase: f64| character.pose(phase, 2.0 * std::f64::consts::PI * turns * phase, DVec3::ZERO);
        let mut frames = Vec::new();
        for k in 0..self.frames {
            let phase = k as f64 / self.frames as f64;
            frames.push((10 * k as i64, phase, pose_at(phase)));
        }
        let test_poses = self.test.contains(&TestKind::Poses) || self.test.contains(&TestKind::Relight);
        let first_test_frame = frames.len();
        if test_poses {
            for j in 0..self.test_frames {
                // Halfway between training phases: a pose never seen in training.
                let phase = ((j * self.frames) as f64 / self.test_frames.max(1) as f64).floor() / self.frames as f64 + 0.5 / self.frames as f64;
                frames.push((1000 + j as i64, phase, pose_at(phase)));
            }
        }
        let (train_name, train_light) = match self.light {
            TrainingLight::Sun => {
                let direction = match self.sun_direction.as_deref() {
                    Some(&[x, y, z]) => [x, y, z],
                    _ => [0.45, 0.8, 0.4],
                };
                ("sun", sun(direction, [0.85, 0.82, 0.78], [0.2, 0.21, 0.24]))
            }
            TrainingLight::Uniform => ("studio", Light::Uniform { radiance: DVec3::new(0.9, 0.9, 0.88) }),
            TrainingLight::Point => {
                let (position, intensity) = (DVec3::new(1.1, 2.3, 1.4), DVec3::new(4.6, 4.4, 4.1));
                let centre = target / self.scale;
                let (position, intensity) = match self.lamp_distance {
                    None => (position, intensity),
                    Some(d) => {
                        let away = position - centre;
                        let ratio = d / away.length();
                        (centre + away * ratio, intensity * (ratio * ratio))
                    }
                };
                ("lamp", lamp(position.to_array(), intensity.to_array(), [0.15, 0.15, 0.17]))
            }
        };
        let mut lights = vec![(train_name.to_string(), train_light)];
        for (name, direction, irradiance, ambient) in EXTRA_SUNS.iter().take(self.suns - 1) {
            lights.push((name.to_string(), sun(*direction, *irradiance, *ambient)));
        }
        let training_lights: Vec<String> = lights.iter().map(|(n, _)| n.clone()).collect();
        let lit_by = |camera: usize, frame: usize| training_lights[(camera + frame) % training_lights.len()].clone();
        let relight = self.test.contains(&TestKind::Relight);
        if relight {
            lights.push(("sun2".into(), sun([-0.6, 0.55, -0.35], [0.9, 0.75, 0.6], [0.15, 0.17, 0.25])));
            if self.light != TrainingLight::Point {
                lights.push(("lamp".into(), lamp([-1.3, 2.0, 1.2], [4.2, 4.2, 4.6], [0.1, 0.1, 0.12])));
            }
            lights.push(("sky".into(), Light::Environment { path: PathBuf::from("lights/sky.exr"), scale: 1.0, map: synthetic_sky(64, 32) }));
        }
        let mut views = Vec::new();
        let mut add = |camera: usize, frame: usize, light: &str, split: Split| {
            let name = format!("c{camera:02}_f{:04}_{light}", frames[frame].0);
            views.push(PlannedView { camera, frame, light: light.to_string(), split, name });
        };
        for frame in 0..self.frames {
            for camera in 0..self.cameras {
                add(camera, frame, &lit_by(camera, frame), Split::Train);
            }
        }
        let test_frames: Vec<usize> = (first_test_frame..frames.len()).collect();
        if self.test.contains(&TestKind::Poses) {
            for (j, &frame) in test_frames.iter().enumerate() {
                for camera in [j % self.cameras, (j + self.cameras / 2) % self.cameras] {
                    add(camera, frame, &lit_by(camera, frame), Split::Test);
                    if self.cameras == 1 {
                        break;
                    }
                }
            }
        }
        if novel_view {
            let heldout = self.cameras;
            for k in [0, self.frames / 2] {
                add(heldout, k, &lit_by(heldout, k), Split::Test);
                if self.frames == 1 {
                    break;
                }
            }
        }
        if relight {
            let light_names: Vec<String> = lights.iter().skip(self.suns).map(|(n, _)| n.clone()).collect();
            for (j, name) in light_names.iter().enumerate() {
                let frame = test_frames.get(j % test_frames.len().max(1)).copied().unwrap_or(0);
                add(j % self.cameras, frame, name, Split::Test);
            }
        }
        Ok(Plan { character, cameras, frames, lights, views })
    }
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
    let rows: Vec<Vec<([f32; 3], bool, [f32; 3])>> = (0..h)
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

fn matrix_rows(m: &DMat4) -> Value {
    json!((0..4).map(|r| m.row(r).to_array().to_vec()).collect::<Vec<_>>())
}

fn light_json(light: &Light) -> Value {
    let v = |d: &DVec3| json!(d.to_array());
    match light {
        Light::Directional { direction, irradiance, ambient } => {
            json!({"type": "directional", "direction": v(direction), "irradiance": v(irradiance), "ambient": v(ambient)})
        }
        Light::Uniform { radiance } => json!({"type": "uniform", "radiance": v(radiance)}),
        Light::Environment { path, scale, .. } => {
            json!({"type": "environment", "path": path.to_string_lossy(), "scale": scale})
        }
        Light::Point { position, intensity, ambient } => {
            json!({"type": "point", "position": v(position), "intensity": v(intensity), "ambient": v(ambient)})
        }
        Light::Unknown { kind, strength, ambient } => {
            let (kind, key) = match kind {
                crate::light::UnknownLight::Sun => ("directional", "irradiance"),
                crate::light::UnknownLight::Point => ("point", "intensity"),
            };
            let mut light = json!({"type": kind, "ambient": v(ambient)});
            if let Some(s) = strength {
                light[key] = v(s);
            }
            light
        }
    }
}

/// What `generate` made.
pub struct Report {
    pub images: usize,
    pub bytes: u64,
}

/// Writes the whole scene into `out`, atomically: everything goes to a temp folder beside it
/// that is renamed into place at the end. An existing `out` is replaced only with `force`, and
/// only when it is a scene `umbra synth` wrote holding nothing but the files it lists
/// (`check_replaceable`): the generator never removes what it did not write.
pub fn generate(options: &SynthOptions, out: &Path, force: bool, mut progress: impl FnMut(usize, usize)) -> Result<Report, SynthError> {
    let plan = options.plan()?;
    let out = &check_replaceable(out, force)?;
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).map_err(|e| io_error(parent, e))?;
    let temp = imageio::temp_path(out);
    if temp.exists() {
        std::fs::remove_dir_all(&temp).map_err(|e| io_error(&temp, e))?;
    }
    // The scene is named after its folder (`datasets-synthetic/human-mono` is "human-mono").
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned());
    let result = write_scene(options, &plan, &temp, name, &mut progress);
    let result = match (result, options.export) {
        (Ok(report), Some(Export::Nerfstudio)) => export_capture(&temp, report),
        (result, _) => result,
    };
    match result {
        Ok(report) => {
            if out.exists() {
                // Checked again: the folder may have changed while the scene was rendered.
                check_replaceable(out, force)?;
                std::fs::remove_dir_all(out).map_err(|e| io_error(out, e))?;
            }
            std::fs::rename(&temp, out).map_err(|e| io_error(out, e))?;
            Ok(report)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&temp);
            Err(e)
        }
    }
}

/// The scene just written in `dir` replaced by its capture (`capture::export`).
fn export_capture(dir: &Path, report: Report) -> Result<Report, SynthError> {
    let scene = crate::scene::Scene::load(dir).map_err(|e| SynthError::Options(e.to_string()))?;
    let capture = dir.with_extension("capture");
    let _ = std::fs::remove_dir_all(&capture);
    let written = crate::capture::export::write_capture(&scene, &capture, EXPORT_UNITS).map_err(|e| SynthError::Options(e.to_string()));
    let images = match written {
        Ok(images) => images,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&capture);
            return Err(e);
        }
    };
    std::fs::remove_dir_all(dir).map_err(|e| io_error(dir, e))?;
    std::fs::rename(&capture, dir).map_err(|e| io_error(dir, e))?;
    Ok(Report { images, ..report })
}

/// The folders a scene of `umbra synth` holds its files in.
const SCENE_FOLDERS: [&str; 5] = ["images", "masks", "albedo", "lights", "meshes"];

/// `out` as the scene will be written to it (absolute, so `.` and `..` name real folders), once
/// it is known that writing there removes nothing the generator did not write: `out` does not
/// exist, is an empty folder, or (with `force`) is a scene `umbra synth` wrote that holds no file
/// its `scene.json` does not list. The working folder and its ancestors are never replaced.
fn check_replaceable(out: &Path, force: bool) -> Result<PathBuf, SynthError> {
    if out.as_os_str().is_empty() {
        return Err(SynthError::Options("--out: an empty path".into()));
    }
    let absolute = std::path::absolute(out).map_err(|e| io_error(out, e))?;
    let Ok(meta) = std::fs::symlink_metadata(&absolute) else { return Ok(absolute) };
    if meta.file_type().is_symlink() {
        return Err(io_error(out, "is a link: name the folder itself, or choose another --out (nothing was written)"));
    }
    if !meta.is_dir() {
        return Err(io_error(out, "exists and is not a folder: choose another --out (nothing was written)"));
    }
    let resolved = std::fs::canonicalize(&absolute).map_err(|e| io_error(out, e))?;
    if std::env::current_dir().is_ok_and(|cwd| cwd.starts_with(&resolved)) {
        return Err(io_error(out, "is the working folder or holds it: choose a new folder for --out (nothing was written)"));
    }
    let mut entries = std::fs::read_dir(&resolved).map_err(|e| io_error(out, e))?;
    if entries.next().is_none() {
        return Ok(resolved);
    }
    if !force {
        return Err(io_error(out, "already exists (pass --force to replace a scene umbra synth wrote; nothing was written)"));
    }
    let listed = synth_scene_files(&resolved).map_err(|why| {
        io_error(out, format!("{why}: --force replaces only a scene umbra synth wrote; remove it yourself or choose another --out (nothing was written)"))
    })?;
    if let Some(foreign) = unlisted_file(&resolved, Path::new(""), &listed) {
        return Err(io_error(
            &resolved.join(&foreign),
            "is not a file of the scene umbra synth wrote here: --force replaces only what it wrote; move it away or choose another --out (nothing was written)",
        ));
    }
    Ok(resolved)
}

/// The files (relative, `/`-separated) a scene written by `umbra synth` lists, or why `dir`
/// holds no such scene.
fn synth_scene_files(dir: &Path) -> Result<std::collections::BTreeSet<String>, String> {
    let path = dir.join("scene.json");
    if !path.exists() {
        return Err("is not a scene umbra synth wrote (it holds no scene.json)".into());
    }
    let text = crate::scene::read_capped(&path).map_err(|e| format!("is not a scene umbra synth wrote ({e})"))?;
    let scene: Value = serde_json::from_str(&text).map_err(|e| format!("is not a scene umbra synth wrote (its scene.json is not JSON: {e})"))?;
    if scene["generator"]["program"].as_str() != Some("umbra synth") {
        return Err("is not a scene umbra synth wrote (its scene.json names no generator \"umbra synth\")".into());
    }
    let mut files: std::collections::BTreeSet<String> = ["scene.json".to_string()].into();
    let strings = |values: Vec<&Value>| values.into_iter().filter_map(|v| v.as_str().map(String::from)).collect::<Vec<_>>();
    let images = scene["images"].as_array().map(|a| a.iter().flat_map(|i| [&i["path"], &i["mask"], &i["albedo"]]).collect()).unwrap_or_default();
    let meshes = scene["frames"].as_array().map(|a| a.iter().map(|f| &f["mesh"]).collect()).unwrap_or_default();
    let maps = scene["lights"].as_object().map(|m| m.values().map(|l| &l["path"]).collect()).unwrap_or_default();
    files.extend(strings(images));
    files.extend(strings(meshes));
    files.extend(strings(maps));
    Ok(files)
}

/// The first file or folder below `dir` (walked from `relative`) that is neither in `listed` nor
/// one of the scene's folders.
fn unlisted_file(dir: &Path, relative: &Path, listed: &std::collections::BTreeSet<String>) -> Option<PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir.join(relative)) else { return Some(relative.to_path_buf()) };
    for entry in entries {
        let Ok(entry) = entry else { return Some(relative.to_path_buf()) };
        let name = relative.join(entry.file_name());
        let key = name.to_string_lossy().replace('\\', "/");
        let is_folder = entry.file_type().is_ok_and(|t| t.is_dir());
        if is_folder && relative.as_os_str().is_empty() && SCENE_FOLDERS.contains(&key.as_str()) {
            if let Some(found) = unlisted_file(dir, &name, listed) {
                return Some(found);
            }
        } else if is_folder || !listed.contains(&key) {
            return Some(name);
        }
    }
    None
}

fn write_scene(options: &SynthOptions, plan: &Plan, dir: &Path, name: Option<String>, progress: &mut impl FnMut(usize, usize)) -> Result<Report, SynthError> {
    for sub in SCENE_FOLDERS {
        if sub == "meshes" && !options.meshes {
            continue;
        }
        let p = dir.join(sub);
        std::fs::create_dir_all(&p).map_err(|e| io_error(&p, e))?;
    }
    let mut bytes = 0u64;
    let mut write = |relative: &str, data: &[u8]| -> Result<(), SynthError> {
        let path = dir.join(relative);
        bytes += data.len() as u64;
        std::fs::write(&path, data).map_err(|e| io_error(&path, e))
    };
    let lights: std::collections::BTreeMap<&str, &Light> = plan.lights.iter().map(|(n, l)| (n.as_str(), l)).collect();
    for (_, light) in &plan.lights {
        if let Light::Environment { path, map, .. } = light {
            imageio::write_exr_atomic(&dir.join(path), &map.image).map_err(|e| io_error(path, e))?;
        }
    }
    let mut images = Vec::new();
    for (k, view) in plan.views.iter().enumerate() {
        progress(k, plan.views.len());
        let (_, _, pose) = &plan.frames[view.frame];
        let light = lights[view.light.as_str()];
        let r = render_view(&plan.character, pose, &plan.cameras[view.camera], light, options.samples, options.pixel_samples, options.seed, k as u64);
        let png = |e: imageio::ImageError| io_error(Path::new(&view.name), e);
        let path = format!("images/{}.png", view.name);
        let mask = format!("masks/{}.png", view.name);
        write(&path, &imageio::encode_png_rgb(&r.colour).map_err(png)?)?;
        write(&mask, &imageio::encode_png_mask(&r.mask).map_err(png)?)?;
        let mut entry = json!({"camera": view.camera, "frame": view.frame, "light": view.light, "split": view.split.name(), "path": path, "mask": mask});
        if view.split != Split::Train {
            let albedo = format!("albedo/{}.png", view.name);
            write(&albedo, &imageio::encode_png_rgb(&r.albedo).map_err(png)?)?;
            entry["albedo"] = json!(albedo);
        }
        images.push(entry);
    }
    progress(plan.views.len(), plan.views.len());
    let skeleton: Vec<Value> = plan.character.skeleton.bones.iter().map(|b| json!({"name": b.name, "parent": b.parent, "length": b.length})).collect();
    let cameras: Vec<Value> = plan
        .cameras
        .iter()
        .map(|c| json!({"name": c.name, "width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "camera_to_world": matrix_rows(&c.camera_to_world)}))
        .collect();
    let mut frames: Vec<Value> = Vec::new();
    for (index, time, pose) in &plan.frames {
        let mut frame = json!({"index": index, "time": time, "bone_to_world": pose.bone_to_world.iter().map(matrix_rows).collect::<Vec<_>>()});
        if options.meshes {
            let (vertices, triangles) = mesh::extract(&plan.character, pose, options.mesh_cell);
            let relative = format!("meshes/f{index:04}.obj");
            write(&relative, mesh::to_obj(&vertices, &triangles).as_bytes())?;
            frame["mesh"] = json!(relative);
        }
        frames.push(frame);
    }
    let lights_json: serde_json::Map<String, Value> = plan.lights.iter().map(|(n, l)| (n.clone(), light_json(l))).collect();
    let name = name.unwrap_or_else(|| {
        format!(
            "{}-{}",
            serde_json::to_value(options.character).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default(),
            serde_json::to_value(options.light).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default()
        )
    });
    let scene = json!({
        "format": crate::scene::FORMAT,
        "name": name,
        "generator": {"program": "umbra synth", "version": env!("CARGO_PKG_VERSION"), "options": options},
        "skeleton": {"bones": skeleton},
        "cameras": cameras,
        "frames": frames,
        "lights": lights_json,
        "images": images,
    });
    let text = serde_json::to_string_pretty(&scene).map_err(|e| io_error(Path::new("scene.json"), e))?;
    write("scene.json", text.as_bytes())?;
    Ok(Report { images: plan.views.len(), bytes })
}
