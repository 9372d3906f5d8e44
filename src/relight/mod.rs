//! What a fitted avatar looks like under a light it was not fitted in: a sun or a point light
//! (the training image formation with a known light), uniform light or an HDR environment map
//! (per pixel, `environment::MisEstimator`, with visibility from the Gaussians), in the scene's
//! cameras or a turntable around the body (`orbit_cameras`), directly or through a visibility
//! basis precomputed per view (`basis`, timed and checked against the direct estimator).

mod adjust;
mod basis_view;
mod cameras;
pub mod ground;
mod sampler;

pub use crate::light::albedo_scale;
pub use adjust::{adjusted, turned_map};
pub use basis_view::{basis_table, BasisTiming};
pub use cameras::{orbit_cameras, world_up};
pub use sampler::EnvironmentSampler;

use crate::backend::Backend;
use crate::eval::{render_view, Lighting};
use crate::fit_error::{io, FitError};
use crate::imageio::RgbImage;
use crate::light::{EnvironmentMap, Light};
use crate::messages::TrainMessage;
use crate::scene::Scene;
use basis_view::{relight_by_basis, BASIS_BYTES_LIMIT};
use burn::module::Module;
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// What `umbra relight` (and `umbra render` with views of its own choosing) renders.
pub struct RelightOptions {
    pub run: PathBuf,
    /// The scene whose cameras and poses are rendered (default: the one the run was fitted on).
    pub scene: Option<PathBuf>,
    /// A light of the scene by name, a JSON file holding one light in the scene format, or an
    /// equirectangular EXR (an environment light of scale 1); `None`: the fitted light (the
    /// fitted albedo for a uniformly lit fit).
    pub light: Option<String>,
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
    /// Render at this image size (width, height), the cameras' intrinsics scaled.
    pub size: Option<(usize, usize)>,
    /// Turn the light by this many degrees about the world's up axis (`adjust`).
    pub rotate: f64,
    /// Multiply the light's strength by this.
    pub intensity: f64,
    /// Render over a ground that receives the shadow (RGBA PNGs).
    pub ground: Option<ground::GroundOptions>,
}

/// Reads `WxH` (`512x512`, `1920x1080`) as an image size of at least 1 x 1 and at most
/// `MAX_SIDE` on a side.
pub fn parse_size(text: &str) -> Result<(usize, usize), String> {
    let (w, h) = text.split_once(['x', 'X']).ok_or_else(|| format!("{text:?}: expected WIDTHxHEIGHT, e.g. 512x512"))?;
    let side = |s: &str| s.trim().parse::<usize>().ok().filter(|&v| (1..=MAX_SIDE).contains(&v));
    match (side(w), side(h)) {
        (Some(w), Some(h)) => Ok((w, h)),
        _ => Err(format!("{text:?}: each side must be a whole number from 1 to {MAX_SIDE}")),
    }
}

/// Reads `--orbit N`: a whole number of views from 1 to `MAX_ORBIT`.
pub fn parse_orbit(text: &str) -> Result<usize, String> {
    text.trim().parse::<usize>().ok().and_then(|n| orbit_views(n).ok()).ok_or_else(|| format!("{text:?}: {ORBIT_RANGE}"))
}

const ORBIT_RANGE: &str = "the number of --orbit views must be a whole number from 1 to 3600";

/// `n` when it is a number of orbit views `--orbit` accepts.
pub fn orbit_views(n: usize) -> Result<usize, FitError> {
    match (1..=MAX_ORBIT).contains(&n) {
        true => Ok(n),
        false => Err(FitError::Input(format!("--orbit {n}: {ORBIT_RANGE}"))),
    }
}

/// The most views `--orbit` takes: one every tenth of a degree.
pub const MAX_ORBIT: usize = 3600;

/// The largest side `--size` accepts: an 8K image.
pub const MAX_SIDE: usize = 8192;

/// The contact sheet of a relight (cameras down, frames across).
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

/// The light a relight renders in, turned and scaled as asked, and the label of its folder;
/// `None` for the fitted light.
fn chosen_light(scene: &Scene, options: &RelightOptions, pivot: glam::DVec3) -> Result<Option<(Light, String)>, FitError> {
    if !options.rotate.is_finite() || !options.intensity.is_finite() || options.intensity < 0.0 {
        return Err(FitError::Input(format!("--rotate {} --intensity {}: need a finite angle and an intensity >= 0", options.rotate, options.intensity)));
    }
    let Some(spec) = &options.light else {
        if options.rotate != 0.0 || options.intensity != 1.0 {
            return Err(FitError::Input("--rotate and --intensity turn and scale a stated light: give --light".into()));
        }
        return Ok(None);
    };
    let (light, label) = resolve_light(scene, spec)?;
    known(&light, spec)?;
    let adjusted = adjust::adjusted(&light, options.rotate, options.intensity, pivot);
    let peak = adjust::peak_strength(&adjusted);
    let bound = crate::scene::json::MAX_MAGNITUDE;
    if !(peak <= bound) {
        return Err(FitError::Input(format!(
            "--intensity {}: the light's strength becomes {peak:e}, beyond the {bound:e} a light may have (umbra renders in f32)",
            options.intensity
        )));
    }
    Ok(Some((adjusted, label)))
}

/// Refuses an unknown light: it lights its capture's images only.
fn known(light: &Light, spec: &str) -> Result<(), FitError> {
    match light.is_known() {
        true => Ok(()),
        false => Err(FitError::Input(format!(
            "--light {spec:?}: an unknown light (the capture states no {}): it cannot relight; name a stated light of the scene, a light .json or an environment .exr",
            if light.type_name() == "point" { "position" } else { "direction" }
        ))),
    }
}

/// The stated light `spec` names (`resolve_light`): a light of the scene, a light .json or an
/// environment .exr.
pub fn stated_light(scene: &Scene, spec: &str) -> Result<Light, FitError> {
    let (light, _) = resolve_light(scene, spec)?;
    known(&light, spec)?;
    Ok(light)
}

/// The scene to render (with a turntable's cameras added, every camera resized to `--size`),
/// the chosen cameras and the chosen frames.
fn chosen_views(scene: &Scene, options: &RelightOptions) -> Result<(Scene, Vec<usize>, Vec<usize>), FitError> {
    // Read before the scene is copied, so the copy keeps it (it reads every training image).
    let _ = scene.footprint();
    let mut scene = scene.clone();
    // A turntable renders cameras of its own (after the scene's), by default in the first frame.
    let (cameras, frames) = match options.orbit {
        Some(count) => {
            let count = orbit_views(count)?;
            let frames = chosen("--frame", &Some(options.frames.clone().unwrap_or(vec![0])), scene.frames.len())?;
            let first = scene.cameras.len();
            let orbit = orbit_cameras(&scene, frames[0], count);
            scene.cameras.extend(orbit);
            ((first..first + count).collect(), frames)
        }
        None => (chosen("--camera", &options.cameras, scene.cameras.len())?, chosen("--frame", &options.frames, scene.frames.len())?),
    };
    if cameras.len().saturating_mul(frames.len()) > MAX_VIEWS {
        return Err(FitError::Input(format!(
            "{} views ({} cameras times {} frames): more than the {MAX_VIEWS} one relight renders; choose fewer with --frame, --camera or --orbit",
            cameras.len().saturating_mul(frames.len()),
            cameras.len(),
            frames.len()
        )));
    }
    if let Some((w, h)) = options.size {
        for &c in &cameras {
            scene.cameras[c] = scene.cameras[c].resized(w, h);
        }
    }
    Ok((scene, cameras, frames))
}

/// Refuses a basis that would not fit in memory, or sample counts of 0, before any work.
fn check_sampling(options: &RelightOptions, scene: &Scene, cameras: &[usize], light: Option<&Light>) -> Result<(), FitError> {
    if let Some(directions) = options.basis {
        if directions == 0 {
            return Err(FitError::Input("--basis needs at least 1 direction".into()));
        }
        if light.is_none() {
            return Err(FitError::Input("--basis relights by a stated light: give --light".into()));
        }
        if options.ground.is_some() {
            return Err(FitError::Input("--basis renders the avatar alone: leave out --ground".into()));
        }
        // A basis holds 4 bytes per drawn pixel and direction.
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
    if options.samples == 0 {
        return Err(FitError::Input("--samples must be at least 1".into()));
    }
    Ok(())
}

/// Renders a fitted avatar for every chosen camera and frame, under a new light or its fitted
/// one; writes one PNG per view (`cCC_fFFFF.png`, the frame's position) and `sheet.png`
/// (cameras down, frames across). Returns the output folder.
pub fn relight_run(options: &RelightOptions, mut on: impl FnMut(TrainMessage)) -> Result<PathBuf, FitError> {
    let restored = crate::run::restore(&options.run, options.scene.as_deref(), options.backend)?;
    let (scene, cameras, frames) = chosen_views(&restored.scene, options)?;
    let (lo, hi) = scene.frames[frames[0]].pose.bounds(&scene.skeleton);
    let light = chosen_light(&scene, options, (lo + hi) * 0.5)?;
    check_sampling(options, &scene, &cameras, light.as_ref().map(|(l, _)| l))?;
    if let Some(ground) = options.ground {
        ground.check(&scene, &cameras, &frames)?;
    }
    let label = light.as_ref().map_or("fitted".to_string(), |(_, label)| label.clone());
    let out = options.out.clone().unwrap_or_else(|| options.run.join("relit").join(&label));
    let views = view_order(options, &cameras, &frames);
    let planned = planned_files(options, &views, &frames);
    let folder = crate::written::OutputFolder::claim(&out, "relight", &planned).map_err(FitError::Input)?;
    let _lock = crate::run_lock::RunLock::for_output(&options.run, &out, "relight")?;
    folder.begin(&planned).map_err(|e| io(&out, e))?;
    let model = restored.fitted.model.valid();
    let device = restored.fitted.device.clone().without_autodiff();
    let lighting = match &light {
        Some((light, _)) => Lighting::Known { light, albedo_scale: crate::run::albedo_scale(&scene, &model), samples: options.samples },
        None => Lighting::Fitted(0),
    };
    let total = cameras.len() * frames.len();
    on(TrainMessage::Evaluating { images: total });
    on(TrainMessage::Planned { views: total, width: scene.cameras[cameras[0]].width, height: scene.cameras[cameras[0]].height });
    let render = |camera: usize, frame: usize| match (options.basis, &light) {
        (Some(directions), Some((light, _))) => {
            let (image, timing) = relight_by_basis(&model, &scene, camera, frame, light, directions, &device);
            (ground::Rendered { image, rgba: None }, Some(timing))
        }
        _ => (ground::Rendered::view(&model, &scene, (camera, frame), &device, &lighting, options.ground), None),
    };
    // Direct renders of as many views at once as there are threads (a basis keeps every thread
    // busy by itself, and its timings must not share the cores).
    let at_once = if options.basis.is_some() { 1 } else { rayon::current_num_threads().max(1) };
    let rendered = views.chunks(at_once).flat_map(|batch| batch.par_iter().map(|&(_, _, camera, frame)| render(camera, frame)).collect::<Vec<_>>());
    // The sheet keeps thumbnails, and a turntable is streamed: memory stays bounded however
    // many views at whatever size.
    let mut cells: Vec<Vec<Option<RgbImage>>> = vec![vec![None; frames.len()]; cameras.len()];
    let cell_side = sheet_cell_side(total);
    let mut timings = Vec::new();
    let mut turntable: Option<(usize, crate::apng::ApngFile)> = None;
    for (done, (&(row, column, camera, frame), (rendered, timing))) in views.iter().zip(rendered).enumerate() {
        if let Some(mut timing) = timing {
            if timings.is_empty() {
                // The first view also through the direct estimator, as the reference.
                let direct = render_view(&model, &scene, camera, frame, crate::eval::VIEW_SAMPLING, &device, &lighting);
                timing.against_direct = Some(crate::metrics::score(&rendered.image, &direct, None));
            }
            timings.push(timing);
        }
        let name = view_file(options, row, camera, frame);
        rendered.save(&out.join(&name))?;
        if options.orbit.is_some() {
            turntable_push(&mut turntable, &out, (column, frames[column]), cameras.len(), &rendered.image)?;
        }
        cells[row][column] = Some(rendered.image.thumbnail(cell_side));
        on(TrainMessage::Rendered { done: done + 1, total, name, psnr: None });
    }
    let row_label = |row: usize, camera: usize| match options.orbit {
        Some(_) => format!("orbit {row}"),
        None => scene.cameras[camera].name.clone(),
    };
    let sheet = crate::plot::Sheet {
        title: format!("{label}: cameras down, frames across"),
        columns: frames.iter().map(|f| format!("frame {f}")).collect(),
        rows: cameras.iter().enumerate().map(|(row, &camera)| (row_label(row, camera), cells[row].iter().map(Option::as_ref).collect())).collect(),
    };
    sheet.render().save_png(&out.join(SHEET)).map_err(FitError::Input)?;
    if let Some((column, file)) = turntable {
        file.finish().map_err(|e| io(&out.join(turntable_file(frames[column])), e))?;
    }
    if let Some(directions) = options.basis {
        let table = basis_table(&label, directions, &timings);
        let path = out.join(BASIS_TABLE);
        crate::imageio::write_atomic(&path, table.as_bytes()).map_err(|e| io(&path, e))?;
    }
    folder.finish(&planned).map_err(|e| io(&out, e))?;
    Ok(out)
}

/// The views of a relight as (row, column, camera, frame), cameras down and frames across;
/// frame by frame on an orbit, so that one turntable is written at a time.
fn view_order(options: &RelightOptions, cameras: &[usize], frames: &[usize]) -> Vec<(usize, usize, usize, usize)> {
    let grid = |row: usize, column: usize| (row, column, cameras[row], frames[column]);
    match options.orbit {
        Some(_) => (0..frames.len()).flat_map(|c| (0..cameras.len()).map(move |r| grid(r, c))).collect(),
        None => (0..cameras.len()).flat_map(|r| (0..frames.len()).map(move |c| grid(r, c))).collect(),
    }
}

/// Appends `image` to the turntable of `(column, frame)`, ending the previous frame's (whole
/// after its `views` views) when this is a new one.
fn turntable_push(
    current: &mut Option<(usize, crate::apng::ApngFile)>,
    out: &Path,
    (column, frame): (usize, usize),
    views: usize,
    image: &RgbImage,
) -> Result<(), FitError> {
    let path = out.join(turntable_file(frame));
    if current.as_ref().is_some_and(|(c, _)| *c != column) {
        if let Some((_, done)) = current.take() {
            done.finish().map_err(|e| io(&path, e))?;
        }
    }
    let file = match current {
        Some((_, file)) => file,
        None => {
            &mut current
                .insert((column, crate::apng::ApngFile::create(&path, (image.width, image.height), views, TURNTABLE_FRAME_MS).map_err(|e| io(&path, e))?))
                .1
        }
    };
    file.push(image).map_err(|e| io(&path, e))
}

/// The longest side of a contact sheet's cell for `views` views: the whole sheet stays within
/// about 16 million pixels (a cell from 16 to 512 pixels).
fn sheet_cell_side(views: usize) -> usize {
    ((16e6 / views.max(1) as f64).sqrt() as usize).clamp(16, 512)
}

/// The most views one relight renders (an orbit's views times its frames, or cameras times
/// frames): more is several runs, chosen with --frame.
pub const MAX_VIEWS: usize = 10_000;

/// The file of one view: `cCC_fFFFF.png` (camera, frame), or `orbitRRR_fFFFF.png` on an orbit.
fn view_file(options: &RelightOptions, row: usize, camera: usize, frame: usize) -> String {
    match options.orbit {
        Some(_) => format!("orbit{row:03}_f{frame:04}.png"),
        None => format!("c{camera:02}_f{frame:04}.png"),
    }
}

/// The turntable of one frame of an orbit.
fn turntable_file(frame: usize) -> String {
    format!("orbit_f{frame:04}.png")
}

/// The timings of a relight through a basis.
const BASIS_TABLE: &str = "basis.md";

/// Every file a relight of `views` writes, known before it starts.
fn planned_files(options: &RelightOptions, views: &[(usize, usize, usize, usize)], frames: &[usize]) -> Vec<String> {
    let mut files: Vec<String> = views.iter().map(|&(row, _, camera, frame)| view_file(options, row, camera, frame)).collect();
    files.push(SHEET.into());
    if options.orbit.is_some() {
        files.extend(frames.iter().map(|&f| turntable_file(f)));
    }
    if options.basis.is_some() {
        files.push(BASIS_TABLE.into());
    }
    files
}

/// How long each view of a turntable shows (ms): a 36-view orbit turns once in 3.6 s.
const TURNTABLE_FRAME_MS: u16 = 100;
