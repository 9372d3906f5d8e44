//! The scene `synth` will make, before anything is rendered: cameras on a ring, the walk's
//! poses, the lights and the list of images with their splits.

use super::*;

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
        if self.relit_views == 0 || self.relit_views > 200 {
            return bad("--relit-views must be within 1..=200");
        }
        if self.relit_views > 1 && !self.test.contains(&TestKind::Relight) {
            return bad("--relit-views needs the relighting tests (--test relight)");
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
            if !(0.5..=20.0).contains(&d) {
                return bad("--lamp-distance must be within 0.5..=20 metres (nearer, the lamp would sit inside the body)");
            }
        }
        Ok(())
    }

    /// Lays out cameras, frames, lights and views.
    pub fn plan(&self) -> Result<Plan, SynthError> {
        self.check()?;
        let character = Character::new(self.character).with_pattern(self.pattern).scaled(self.scale);
        let (target, extent) = match self.character {
            Kind::Human | Kind::Dressed => (DVec3::new(0.0, 0.9, 0.0), 1.05),
            Kind::Quadruped => (DVec3::new(0.0, 0.45, 0.0), 0.75),
        };
        let (target, extent) = (target * self.scale, extent * self.scale);
        let cameras = self.cameras(target, extent);
        let frames = self.frames(&character);
        let lights = self.lights(target);
        let views = self.views(&frames, &lights);
        Ok(Plan { character, cameras, frames, lights, views })
    }

    /// The ring of training cameras around `target`, seeded, and the held-out one.
    fn cameras(&self, target: DVec3, extent: f64) -> Vec<Camera> {
        let mut stream = Stream::new(self.seed, 0x0CA3_E4A5, 0);
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
        cameras
    }

    /// The training frames (JSON frame `10 k`) and the test poses after them (`1000 + j`).
    fn frames(&self, character: &Character) -> Vec<(i64, f64, Pose)> {
        // A monocular capture needs the character to turn so the one camera sees all sides.
        let turns = if self.cameras == 1 { 1.0 } else { 0.0 };
        let pose_at = |phase: f64| character.pose(phase, 2.0 * std::f64::consts::PI * turns * phase, DVec3::ZERO);
        let mut frames = Vec::new();
        for k in 0..self.frames {
            let phase = k as f64 / self.frames as f64;
            frames.push((10 * k as i64, phase, pose_at(phase)));
        }
        let test_poses = self.test.contains(&TestKind::Poses) || self.test.contains(&TestKind::Relight);
        if test_poses {
            for j in 0..self.test_frames {
                // Halfway between training phases: a pose never seen in training.
                let phase = ((j * self.frames) as f64 / self.test_frames.max(1) as f64).floor() / self.frames as f64 + 0.5 / self.frames as f64;
                frames.push((1000 + j as i64, phase, pose_at(phase)));
            }
        }
        frames
    }

    /// The training lights, then those the relighting tests use.
    fn lights(&self, target: DVec3) -> Vec<(String, Light)> {
        // A lamp scaled with the body, its intensity with the square of its distance.
        let lamp = |position: [f64; 3], intensity: [f64; 3], ambient: [f64; 3]| Light::Point {
            position: DVec3::from_array(position) * self.scale,
            intensity: DVec3::from_array(intensity) * (self.scale * self.scale),
            ambient: DVec3::from_array(ambient),
        };
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
        if self.test.contains(&TestKind::Relight) {
            lights.push(("sun2".into(), sun([-0.6, 0.55, -0.35], [0.9, 0.75, 0.6], [0.15, 0.17, 0.25])));
            if self.light != TrainingLight::Point {
                lights.push(("lamp".into(), lamp([-1.3, 2.0, 1.2], [4.2, 4.2, 4.6], [0.1, 0.1, 0.12])));
            }
            lights.push(("sky".into(), Light::Environment { path: PathBuf::from("lights/sky.exr"), scale: 1.0, map: synthetic_sky(64, 32) }));
        }
        lights
    }

    /// The images to render: every training camera in every training frame, then the tests.
    fn views(&self, frames: &[(i64, f64, Pose)], lights: &[(String, Light)]) -> Vec<PlannedView> {
        let novel_view = self.test.contains(&TestKind::Views);
        let relight = self.test.contains(&TestKind::Relight);
        let first_test_frame = self.frames;
        let training_lights: Vec<String> = lights.iter().take(self.suns).map(|(n, _)| n.clone()).collect();
        let lit_by = |camera: usize, frame: usize| training_lights[(camera + frame) % training_lights.len()].clone();
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
        // The novel-pose views (camera, frame): two cameras half the ring apart per test frame.
        let pose_views: Vec<(usize, usize)> = test_frames
            .iter()
            .enumerate()
            .flat_map(|(j, &frame)| {
                let cameras = [j % self.cameras, (j + self.cameras / 2) % self.cameras];
                cameras.into_iter().take(if self.cameras == 1 { 1 } else { 2 }).map(move |camera| (camera, frame))
            })
            .collect();
        if self.test.contains(&TestKind::Poses) {
            for &(camera, frame) in &pose_views {
                add(camera, frame, &lit_by(camera, frame), Split::Test);
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
                // The next novel-pose views after this one, as many as asked and as there are.
                let stride = if self.cameras == 1 { 1 } else { 2 };
                let first = (j % self.cameras, frame);
                let more = pose_views.iter().cycle().skip(stride * j + 1).take((self.relit_views - 1).min(pose_views.len().saturating_sub(1)));
                for &(camera, frame) in more.filter(|&&view| view != first) {
                    add(camera, frame, name, Split::Test);
                }
            }
        }
        views
    }
}
