//! What a fitted avatar looks like under a light it was not fitted in: a sun or a point light
//! (the training image formation with a known light), uniform light or an HDR environment map
//! (per pixel, `environment::MisEstimator`, with visibility from the Gaussians), in the scene's
//! cameras or a turntable around the body (`orbit_cameras`), directly or through a visibility
//! basis precomputed per view (`basis`, timed and checked against the direct estimator).

use crate::backend::Backend;
use crate::eval::{render_view, Lighting};
use crate::fit_error::{io, FitError};
use crate::imageio::RgbImage;
use crate::light::{uv_to_direction, EnvironmentMap, Light};
use crate::messages::TrainMessage;
use crate::random::Stream;
use crate::scene::Scene;
use crate::shading::SHADOW_START;
use crate::shadow::PosedGaussian;
use crate::shadow::{ShadowCaster, ShadowRay};
use burn::module::Module;
use glam::DVec3;
use rayon::prelude::*;
use std::f64::consts::PI;
use std::path::{Path, PathBuf};

pub use crate::light::albedo_scale;

/// A fixed set of directions drawn from an environment's radiance (times texel solid angle),
/// stratified, with their radiance over pdf, shared by every pixel of a view (its error is that
/// of a `count`-point quadrature of the sky, the same in every pixel). Renders now use the
/// per-pixel `environment::MisEstimator`; this one stays as the environment benchmark's
/// baseline.
pub struct EnvironmentSampler {
    directions: Vec<DVec3>,
    /// Radiance divided by the pdf (per steradian) of each direction.
    weights: Vec<DVec3>,
}

impl EnvironmentSampler {
    pub fn new(map: &EnvironmentMap, scale: f64, count: usize, seed: u64) -> Self {
        let (w, h) = (map.image.width, map.image.height);
        let luminance = |p: [f32; 3]| (0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]).max(0.0) as f64;
        let mean = (0..w * h).map(|k| luminance(map.image.pixels[k])).sum::<f64>() / (w * h) as f64;
        // A floor so that dim texels are still sampled now and then (no direction has pdf 0).
        let mass: Vec<f64> = (0..w * h).map(|k| (luminance(map.image.pixels[k]) + 0.05 * mean + 1e-12) * map.texel_solid_angle(k / w)).collect();
        let total: f64 = mass.iter().sum();
        let mut cumulative = Vec::with_capacity(mass.len());
        let mut running = 0.0;
        for m in &mass {
            running += m / total;
            cumulative.push(running);
        }
        let mut stream = Stream::new(seed, 0xE4F, 1);
        let mut directions = Vec::with_capacity(count);
        let mut weights = Vec::with_capacity(count);
        for k in 0..count {
            let target = (k as f64 + stream.uniform()) / count as f64;
            let texel = cumulative.partition_point(|&c| c < target).min(mass.len() - 1);
            let (x, y) = (texel % w, texel / w);
            // Uniform in solid angle within the texel: uniform in u and in cos(theta).
            let u = (x as f64 + stream.uniform()) / w as f64;
            let (c0, c1) = ((y as f64 / h as f64 * PI).cos(), ((y + 1) as f64 / h as f64 * PI).cos());
            let cosine = c0 + (c1 - c0) * stream.uniform();
            let direction = uv_to_direction(u, cosine.clamp(-1.0, 1.0).acos() / PI);
            let pdf = mass[texel] / total / map.texel_solid_angle(y);
            directions.push(direction);
            weights.push(map.lookup(direction) * scale / pdf);
        }
        Self { directions, weights }
    }

    /// Uniform radiance from every direction, as a sampler: a spherical Fibonacci lattice
    /// (even in every direction, so any normal's hemisphere gets its share), randomly turned.
    pub fn uniform(radiance: DVec3, count: usize, seed: u64) -> Self {
        let mut stream = Stream::new(seed, 0xE4F, 2);
        let directions = crate::light::fibonacci_sphere(count, 2.0 * PI * stream.uniform());
        Self { weights: vec![radiance * 4.0 * PI; count], directions }
    }

    pub fn len(&self) -> usize {
        self.directions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.directions.is_empty()
    }

    /// Outgoing radiance over albedo at each surface point (Lambertian, `1/pi` BRDF):
    /// `(1 / (pi N)) sum_i L_i max(0, n . w_i) T(x, w_i) / p_i`, T from the Gaussians.
    pub fn shade(&self, points: &[DVec3], normals: &[DVec3], casters: &[PosedGaussian]) -> Vec<DVec3> {
        let caster = ShadowCaster::new(casters, 1e-4);
        points
            .par_iter()
            .zip(normals)
            .map(|(&x, &n)| {
                let origin = (x + n * SHADOW_START as f64).as_vec3().to_array();
                let shares = caster.shares_at(x.as_vec3().to_array());
                let mut sum = DVec3::ZERO;
                for (d, weight) in self.directions.iter().zip(&self.weights) {
                    let cosine = n.dot(*d);
                    if cosine <= 0.0 {
                        continue;
                    }
                    let ray = ShadowRay { origin, direction: d.as_vec3().to_array(), t0: SHADOW_START, t1: f32::INFINITY };
                    sum += *weight * cosine * caster.transmittance_from(&shares, &ray, true) as f64;
                }
                sum / (PI * self.len().max(1) as f64)
            })
            .collect()
    }
}

/// What `umbra relight` renders.
pub struct RelightOptions {
    pub run: PathBuf,
    /// The scene whose cameras and poses are rendered (default: the one the run was fitted on).
    pub scene: Option<PathBuf>,
    /// A light of the scene by name, a JSON file holding one light in the scene format, or an
    /// equirectangular EXR (an environment light of scale 1).
    pub light: String,
    /// Camera indices (default: every camera).
    pub cameras: Option<Vec<usize>>,
    /// Frame positions in the scene's `frames` (default: every frame).
    pub frames: Option<Vec<usize>>,
    /// Sky directions per pixel for uniform and environment lights.
    pub samples: usize,
    /// Output folder (default: RUN/relit/LIGHT).
    pub out: Option<PathBuf>,
    pub backend: Backend,
    /// Relight through a visibility basis of this many directions per view (`basis`) instead of
    /// the per-pixel MIS estimator; `basis.md` then gives the precompute and relight times and,
    /// for the first view, the error against the direct estimator.
    pub basis: Option<usize>,
    /// Render a turntable of this many views around the body instead of the scene's cameras
    /// (`orbit_cameras`): `orbitVVV_fFFFF.png` per view and `orbit_fFFFF.png`, an animated PNG
    /// per frame (default: the first frame).
    pub orbit: Option<usize>,
}

/// The contact sheet of a relight's folder (cameras down, frames across).
const SHEET: &str = "sheet.png";

/// A light's name as one plain folder name: letters, digits, `-`, `_` and `.` kept, anything
/// else (a separator, `..`, a drive) replaced by `_`, so no name writes outside `relit/`.
pub fn folder_label(name: &str) -> String {
    let label: String = name.chars().map(|c| if c.is_alphanumeric() || matches!(c, '-' | '_' | '.') { c } else { '_' }).collect();
    let label = label.trim_start_matches('.');
    if label.is_empty() {
        "light".into()
    } else {
        label.to_string()
    }
}

/// The light `options.light` names and the folder label its renders go under: a scene light's
/// name (made a plain folder name), a file's stem prefixed `file-` when a scene light has that
/// label, so the two never share a folder.
fn resolve_light(scene: &Scene, spec: &str) -> Result<(Light, String), FitError> {
    if let Some(light) = scene.lights.get(spec) {
        return Ok((light.clone(), folder_label(spec)));
    }
    let path = Path::new(spec);
    let stem = folder_label(&path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default());
    let taken = |label: &str| scene.lights.keys().any(|name| folder_label(name) == label);
    let mut label = stem;
    while taken(&label) {
        label = format!("file-{label}");
    }
    let is_exr = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    if is_exr {
        let image = crate::imageio::read_rgb(path).map_err(|e| io(path, e))?;
        if let Some(message) = crate::scene::environment_problem(&image) {
            return Err(io(path, message));
        }
        return Ok((Light::Environment { path: path.to_path_buf(), scale: 1.0, map: EnvironmentMap { image } }, label));
    }
    if !path.exists() {
        let names: Vec<&String> = scene.lights.keys().collect();
        return Err(FitError::Input(format!("--light {spec:?}: neither a light of the scene ({names:?}) nor an existing .json or .exr file")));
    }
    Ok((crate::scene::load_light(path)?, label))
}

/// Indices from a flag, checked against how many there are.
fn chosen(flag: &str, picked: &Option<Vec<usize>>, count: usize) -> Result<Vec<usize>, FitError> {
    match picked {
        None => Ok((0..count).collect()),
        Some(list) => match list.iter().find(|&&k| k >= count) {
            Some(bad) => Err(FitError::Input(format!("{flag} {bad}: out of range, the scene has {count}"))),
            None => Ok(list.clone()),
        },
    }
}

/// Renders a fitted avatar under a new light for every chosen camera and frame; writes one PNG
/// per view (`cCC_fFFFF.png`, the frame's position) and `sheet.png` (cameras down, frames
/// across). Returns the output folder.
pub fn relight_run(options: &RelightOptions, mut on: impl FnMut(TrainMessage)) -> Result<PathBuf, FitError> {
    let restored = crate::run::restore(&options.run, options.scene.as_deref(), options.backend)?;
    let (light, label) = resolve_light(&restored.scene, &options.light)?;
    if !light.is_known() {
        return Err(FitError::Input(format!(
            "--light {:?}: an unknown light (the capture states no {}): it cannot relight; name a stated light of the scene, a light .json or an environment .exr",
            options.light,
            if light.type_name() == "point" { "position" } else { "direction" }
        )));
    }
    // A turntable renders cameras of its own (after the scene's), by default in the first frame.
    let (scene, cameras, frames) = match options.orbit {
        Some(0) => return Err(FitError::Input("--orbit needs at least 1 view".into())),
        Some(count) => {
            let frames = chosen("--frame", &Some(options.frames.clone().unwrap_or(vec![0])), restored.scene.frames.len())?;
            let mut scene = restored.scene.clone();
            let first = scene.cameras.len();
            scene.cameras.extend(orbit_cameras(&restored.scene, frames[0], count));
            (std::borrow::Cow::Owned(scene), (first..first + count).collect::<Vec<_>>(), frames)
        }
        None => {
            let scene = &restored.scene;
            (
                std::borrow::Cow::Borrowed(scene),
                chosen("--camera", &options.cameras, scene.cameras.len())?,
                chosen("--frame", &options.frames, scene.frames.len())?,
            )
        }
    };
    let scene = scene.as_ref();
    // A basis holds 4 bytes per drawn pixel and direction: bound it before any work.
    if let Some(directions) = options.basis {
        let pixels = cameras.iter().map(|&c| scene.cameras[c].width * scene.cameras[c].height).max().unwrap_or(0);
        let bytes = (pixels as f64) * (directions as f64) * 4.0;
        if bytes > BASIS_BYTES_LIMIT {
            return Err(FitError::Input(format!(
                "--basis {directions}: a {pixels}-pixel view could need {:.1} GiB (limit {:.0} GiB); use fewer directions",
                bytes / (1u64 << 30) as f64,
                BASIS_BYTES_LIMIT / (1u64 << 30) as f64
            )));
        }
    }
    if options.basis == Some(0) {
        return Err(FitError::Input("--basis needs at least 1 direction".into()));
    }
    if options.samples == 0 {
        return Err(FitError::Input("--samples must be at least 1".into()));
    }
    let out = options.out.clone().unwrap_or_else(|| options.run.join("relit").join(&label));
    if out.exists() && !out.is_dir() {
        return Err(io(&out, "exists and is not a folder: --out names a folder for the renders (nothing was written)"));
    }
    // Renders replace only an earlier relight's (its contact sheet marks it).
    let holds_files = std::fs::read_dir(&out).is_ok_and(|mut entries| entries.next().is_some());
    if holds_files && !out.join(SHEET).is_file() {
        return Err(io(&out, format!("holds files but no {SHEET} of an earlier relight: choose a new or empty --out folder (nothing was written)")));
    }
    let _lock = crate::run_lock::RunLock::for_output(&options.run, &out, "relight")?;
    std::fs::create_dir_all(&out).map_err(|e| io(&out, e))?;
    let model = restored.fitted.model.valid();
    let device = restored.fitted.device.clone().without_autodiff();
    let lighting = Lighting::Known { light: &light, albedo_scale: crate::run::albedo_scale(scene, &model), samples: options.samples };
    let total = cameras.len() * frames.len();
    on(TrainMessage::Evaluating { images: total });
    let (cell_w, cell_h) = cameras.iter().map(|&c| (scene.cameras[c].width, scene.cameras[c].height)).fold((0, 0), |a, b| (a.0.max(b.0), a.1.max(b.1)));
    let mut sheet = RgbImage::new(cell_w * frames.len(), cell_h * cameras.len());
    let mut timings = Vec::new();
    let mut turntables: Vec<Vec<RgbImage>> = vec![Vec::new(); frames.len()];
    let views: Vec<(usize, usize, usize, usize)> =
        cameras.iter().enumerate().flat_map(|(row, &camera)| frames.iter().enumerate().map(move |(column, &frame)| (row, column, camera, frame))).collect();
    // Direct renders of as many views at once as there are threads (a basis keeps every thread
    // busy by itself, and its timings must not share the cores).
    let at_once = if options.basis.is_some() { 1 } else { rayon::current_num_threads().max(1) };
    let rendered = views.chunks(at_once).flat_map(|batch| {
        batch
            .par_iter()
            .map(|&(_, _, camera, frame)| match options.basis {
                None => (render_view(&model, scene, camera, frame, crate::eval::VIEW_SAMPLING, &device, &lighting), None),
                Some(directions) => {
                    let (image, timing) = relight_by_basis(&model, scene, camera, frame, &light, directions, &device);
                    (image, Some(timing))
                }
            })
            .collect::<Vec<_>>()
    });
    for (done, (&(row, column, camera, frame), (image, timing))) in views.iter().zip(rendered).enumerate() {
        if let Some(mut timing) = timing {
            if timings.is_empty() {
                // The first view also through the direct estimator, as the reference.
                let direct = render_view(&model, scene, camera, frame, crate::eval::VIEW_SAMPLING, &device, &lighting);
                timing.against_direct = Some(crate::metrics::score(&image, &direct, None));
            }
            timings.push(timing);
        }
        let name = match options.orbit {
            Some(_) => format!("orbit{row:03}_f{frame:04}.png"),
            None => format!("c{camera:02}_f{frame:04}.png"),
        };
        crate::run::save_png(&out.join(&name), &image)?;
        sheet.blit(&image, column * cell_w, row * cell_h);
        if options.orbit.is_some() {
            turntables[column].push(image);
        }
        on(TrainMessage::Rendered { done: done + 1, total, name, psnr: None });
    }
    crate::run::save_png(&out.join(SHEET), &sheet)?;
    for (views, frame) in turntables.iter().zip(&frames).filter(|(views, _)| !views.is_empty()) {
        let path = out.join(format!("orbit_f{frame:04}.png"));
        let apng = crate::imageio::encode_apng_rgb(views, TURNTABLE_FRAME_MS).map_err(|e| io(&path, e))?;
        crate::imageio::write_atomic(&path, &apng).map_err(|e| io(&path, e))?;
    }
    if let Some(directions) = options.basis {
        let table = basis_table(&label, directions, &timings);
        let path = out.join("basis.md");
        crate::imageio::write_atomic(&path, table.as_bytes()).map_err(|e| io(&path, e))?;
    }
    Ok(out)
}

/// The most a view's basis may hold (bytes, every pixel drawn): 2 GiB, the memory budget of
/// a fit on this project's 2-core machines.
const BASIS_BYTES_LIMIT: f64 = 2.0 * (1u64 << 30) as f64;

/// How long each view of a turntable shows (ms): a 36-view orbit turns once in 3.6 s.
const TURNTABLE_FRAME_MS: u16 = 100;

/// `count` cameras evenly on a circle around the body in `frame`, looking at the centre of its
/// bones' box, for a turntable: the circle lies at the scene's cameras' mean height above
/// that centre and their mean distance from the vertical through it (`world_up`), starts at the first camera's side, and every camera has the first one's image
/// size and focal length.
pub fn orbit_cameras(scene: &Scene, frame: usize, count: usize) -> Vec<crate::scene::Camera> {
    let (lo, hi) = scene.frames[frame].pose.bounds(&scene.skeleton);
    let centre = (lo + hi) * 0.5;
    let up = world_up(&scene.cameras);
    let n = scene.cameras.len().max(1) as f64;
    let offsets: Vec<DVec3> = scene.cameras.iter().map(|c| c.centre() - centre).collect();
    let height = offsets.iter().map(|o| o.dot(up)).sum::<f64>() / n;
    let across = |o: &DVec3| *o - up * o.dot(up);
    let radius = offsets.iter().map(|o| across(o).length()).sum::<f64>() / n;
    let start = offsets.first().and_then(|o| across(o).try_normalize()).unwrap_or_else(|| up.any_orthonormal_vector());
    let (width, image_height, focal) = scene.cameras.first().map_or((128, 128, 128.0), |c| (c.width, c.height, c.fx));
    (0..count)
        .map(|k| {
            let turn = glam::DQuat::from_axis_angle(up, 2.0 * PI * k as f64 / count as f64);
            let eye = centre + up * height + turn * start * radius.max(1e-6);
            crate::scene::Camera::look_at(&format!("orbit{k:03}"), eye, centre, up, width, image_height, focal)
        })
        .collect()
}

/// The world's up as the cameras show it. A camera that looks down at a body is pitched, so
/// its own up leans toward the body, but its image rows stay level (no roll): every camera's
/// right axis is horizontal, and up is the direction across all of them (the cross products of
/// pairs of right axes, each turned to the cameras' mean up, summed). With one camera, or all
/// facing one way, the cameras' mean up (a camera's image +Y points down).
pub fn world_up(cameras: &[crate::scene::Camera]) -> DVec3 {
    let mean_up = cameras.iter().map(|c| -c.camera_to_world.y_axis.truncate()).sum::<DVec3>().try_normalize().unwrap_or(DVec3::Y);
    let rights: Vec<DVec3> = cameras.iter().filter_map(|c| c.camera_to_world.x_axis.truncate().try_normalize()).collect();
    let mut across = DVec3::ZERO;
    for (i, a) in rights.iter().enumerate() {
        for b in &rights[i + 1..] {
            let c = a.cross(*b);
            across += if c.dot(mean_up) < 0.0 { -c } else { c };
        }
    }
    if across.length() > 1e-3 * rights.len().max(1) as f64 {
        across.normalize()
    } else {
        mean_up
    }
}

/// What relighting one view through its basis cost, and how far it is from the direct estimator.
pub struct BasisTiming {
    pub camera: usize,
    pub frame: usize,
    pub pixels: usize,
    pub precompute_seconds: f64,
    /// The fastest of `RELIGHT_REPEATS` relights (the light's binning included).
    pub relight_seconds: f64,
    pub against_direct: Option<crate::metrics::ImageScores>,
}

/// Relights timed per view, the fastest kept (the first pays for cold caches).
const RELIGHT_REPEATS: usize = 5;

/// One view relit through a visibility basis of `directions` directions built for it.
fn relight_by_basis(
    model: &crate::avatar::Avatar,
    scene: &Scene,
    camera: usize,
    frame: usize,
    light: &Light,
    directions: usize,
    device: &burn::tensor::Device,
) -> (RgbImage, BasisTiming) {
    let started = std::time::Instant::now();
    let basis = crate::basis::TransferBasis::of_view(model, scene, camera, frame, directions, device);
    let (w, h) = (basis.width, basis.height);
    let precompute_seconds = started.elapsed().as_secs_f64();
    let mut relight_seconds = f64::INFINITY;
    let mut image = RgbImage::new(w, h);
    for _ in 0..RELIGHT_REPEATS {
        let started = std::time::Instant::now();
        image = basis.relight(light);
        relight_seconds = relight_seconds.min(started.elapsed().as_secs_f64());
    }
    (image, BasisTiming { camera, frame, pixels: basis.len(), precompute_seconds, relight_seconds, against_direct: None })
}

/// `basis.md`: per view the precompute and relight times, and the first view's scores against
/// the direct estimator.
pub fn basis_table(label: &str, directions: usize, timings: &[BasisTiming]) -> String {
    let mut table = format!(
        "# Relit through a visibility basis: {label}\n\n{directions} directions per view. Relight time: the fastest of {RELIGHT_REPEATS}.\n\n\
         | view | covered pixels | precompute (s) | relight (ms) | against the direct estimator (PSNR / foreground / SSIM) |\n|---|---|---|---|---|\n"
    );
    for t in timings {
        let against = t.against_direct.map_or("".to_string(), |s| format!("{:.2} / {:.2} dB / {:.4}", s.psnr, s.foreground_psnr, s.ssim));
        table.push_str(&format!(
            "| c{:02} f{:04} | {} | {:.2} | {:.1} | {} |\n",
            t.camera,
            t.frame,
            t.pixels,
            t.precompute_seconds,
            t.relight_seconds * 1e3,
            against
        ));
    }
    table
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat3;

    fn constant_map(value: f32) -> EnvironmentMap {
        let mut image = RgbImage::new(16, 8);
        image.pixels.iter_mut().for_each(|p| *p = [value, value * 0.5, value * 0.25]);
        EnvironmentMap { image }
    }

    /// Dense quadrature over every texel of `(1/pi) sum L max(0, n.d) T(d) dOmega`, T by the f64
    /// closed form from `x` (less its own Gaussians' shares): the reference the sampled estimate
    /// must approach.
    fn quadrature(map: &EnvironmentMap, scale: f64, x: DVec3, n: DVec3, casters: &[PosedGaussian]) -> DVec3 {
        let (w, h) = (map.image.width, map.image.height);
        let mut sum = DVec3::ZERO;
        for y in 0..h {
            for column in 0..w {
                let d = map.texel_direction(column, y);
                let cosine = n.dot(d);
                if cosine <= 0.0 {
                    continue;
                }
                let origin = (x + n * SHADOW_START as f64).as_vec3().to_array();
                let ray = ShadowRay { origin, direction: d.as_vec3().to_array(), t0: SHADOW_START, t1: f32::INFINITY };
                let t = crate::shadow::transmittance_f64_from(casters, x, &ray);
                let p = map.image.get(column, y);
                sum += DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) * cosine * t * map.texel_solid_angle(y);
            }
        }
        sum * scale / PI
    }

    fn close(a: DVec3, b: DVec3, tolerance: f64) {
        assert!((a - b).abs().max_element() <= tolerance * b.abs().max_element().max(1e-3), "{a} vs {b}");
    }

    #[test]
    fn uniform_light_gives_its_radiance_on_an_open_surface() {
        let radiance = DVec3::new(0.8, 0.4, 0.2);
        let normals = [DVec3::Y, DVec3::X, DVec3::new(0.3, -0.5, 0.8).normalize()];
        let points = [DVec3::ZERO; 3];
        for sampler in [EnvironmentSampler::uniform(radiance, 512, 1), EnvironmentSampler::new(&constant_map(0.8), 1.0, 512, 1)] {
            for value in sampler.shade(&points, &normals, &[]) {
                close(value, radiance, 0.02);
            }
        }
    }

    /// The body the test points lie on: a 5 cm Gaussian just under the origin, whose share of
    /// the density there is all but 1, so it shadows none of them (`shadow::own_shares`).
    fn surface() -> PosedGaussian {
        PosedGaussian { mean: DVec3::new(0.0, -0.05, 0.0), axes: DMat3::IDENTITY, scales: DVec3::splat(0.05), amplitude: 20.0 }
    }

    #[test]
    fn sampled_sky_matches_dense_quadrature_with_and_without_an_occluder() {
        let map = crate::synth::synthetic_sky(64, 32);
        let sampler = EnvironmentSampler::new(&map, 1.5, 4096, 7);
        let blob = PosedGaussian { mean: DVec3::new(0.1, 0.6, -0.2), axes: DMat3::IDENTITY, scales: DVec3::new(0.3, 0.1, 0.3), amplitude: 20.0 };
        let normals = [DVec3::Y, DVec3::new(0.5, 0.55, -0.67).normalize(), DVec3::new(-0.7, 0.2, 0.3).normalize()];
        let points = [DVec3::ZERO; 3];
        for casters in [vec![surface()], vec![surface(), blob]] {
            let sampled = sampler.shade(&points, &normals, &casters);
            for (k, n) in normals.iter().enumerate() {
                close(sampled[k], quadrature(&map, 1.5, points[k], *n, &casters), 0.05);
            }
        }
        // The occluder must matter, or the second pass tested nothing.
        let open = sampler.shade(&points[..1], &normals[..1], &[])[0];
        let shaded = sampler.shade(&points[..1], &normals[..1], &[surface(), blob])[0];
        assert!(shaded.x < 0.7 * open.x, "{shaded} vs {open}");
        // And the body the point lies on does not shadow it.
        let on_body = sampler.shade(&points[..1], &normals[..1], &[surface()])[0];
        close(on_body, open, 1e-6);
    }

    #[test]
    fn per_pixel_mis_matches_dense_quadrature_and_converges_with_samples() {
        let map = crate::synth::synthetic_sky(64, 32);
        let blob = PosedGaussian { mean: DVec3::new(0.1, 0.6, -0.2), axes: DMat3::IDENTITY, scales: DVec3::new(0.3, 0.1, 0.3), amplitude: 20.0 };
        let n = DVec3::new(0.5, 0.55, -0.67).normalize();
        let pixels = 256;
        let ids: Vec<u64> = (0..pixels as u64).collect();
        let (points, normals) = (vec![DVec3::ZERO; pixels], vec![n; pixels]);
        for casters in [vec![surface()], vec![surface(), blob]] {
            let exact = quadrature(&map, 1.5, DVec3::ZERO, n, &casters);
            let mut errors = Vec::new();
            for spp in [16, 64, 256] {
                let values = crate::environment::MisEstimator::new(&map, 1.5, spp, 3).shade(&points, &normals, &ids, &casters);
                let mean = values.iter().sum::<DVec3>() / pixels as f64;
                // Unbiased: the mean over pixels lands on the quadrature (which integrates the
                // texels at their centres, so a percent or two apart at this resolution).
                close(mean, exact, 0.03);
                errors.push((values.iter().map(|v| (*v - exact).length_squared()).sum::<f64>() / pixels as f64).sqrt() / exact.length());
            }
            // Per-pixel noise falls about as 1/sqrt(samples): 4x the samples, about half the error.
            assert!(errors[1] < 0.65 * errors[0] && errors[2] < 0.65 * errors[1], "{errors:?}");
        }
    }

    #[test]
    fn albedo_scale_undoes_the_training_light_strength() {
        let sun = Light::Directional { direction: DVec3::Y, irradiance: DVec3::new(0.5, 1.0, 2.0), ambient: DVec3::ZERO };
        close(albedo_scale(&sun, None), DVec3::new(2.0, 1.0, 0.5), 1e-12);
        let lamp = Light::Point { position: DVec3::ZERO, intensity: DVec3::splat(4.0), ambient: DVec3::ZERO };
        close(albedo_scale(&lamp, Some(8.0)), DVec3::splat(2.0), 1e-12);
        let sky = Light::Environment { path: "sky.exr".into(), scale: 2.0, map: constant_map(0.8) };
        close(albedo_scale(&sky, None), DVec3::new(1.0 / 1.6, 1.0 / 0.8, 1.0 / 0.4), 1e-6);
    }
}
