//! A fitted avatar driven by a new motion (`umbra render RUN --motion CLIP`): the clip's frames
//! turned into poses of the fitted bones (`capture::retarget`), each rendered through one
//! camera of the scene or a camera turning around the body, under the fitted light or a stated
//! one, as `fNNNN.png` (the frame's position in the clip) and an animated PNG.

use crate::backend::Backend;
use crate::capture::retarget::{self, Driven};
use crate::capture::Units;
use crate::eval::Lighting;
use crate::fit_error::{io, FitError};
use crate::messages::TrainMessage;
use crate::relight::ground::Rendered;
use crate::scene::{Frame, Scene};
use burn::module::Module;
use rayon::prelude::*;
use std::path::PathBuf;

/// What `umbra render --motion` renders.
pub struct AnimateOptions {
    pub run: PathBuf,
    /// The scene whose cameras and first pose are used (default: the run's).
    pub scene: Option<PathBuf>,
    /// A BVH, or per-frame joint transforms as JSON (`capture::joints`).
    pub motion: PathBuf,
    /// The clip's length unit (inferred from its skeleton's size when absent).
    pub units: Option<Units>,
    /// The scene's camera to look through (default 0).
    pub camera: Option<usize>,
    /// A camera going once around the body every this many frames, instead of a scene camera.
    pub orbit: Option<usize>,
    /// A light of the scene, a light .json or an environment .exr (default: the fitted light).
    pub light: Option<String>,
    pub size: Option<(usize, usize)>,
    pub samples: usize,
    pub out: PathBuf,
    pub backend: Backend,
    /// Render over a ground that receives the shadow (RGBA PNGs).
    pub ground: Option<crate::relight::ground::GroundOptions>,
}

/// The file of the clip's frame `k`.
fn frame_file(k: usize) -> String {
    format!("f{k:04}.png")
}

/// The animated PNG a motion render writes.
pub const ANIMATION: &str = "animation.png";

/// What the clip did: how it drove the bones, and what it left unmatched.
pub struct Animated {
    pub out: PathBuf,
    pub frames: usize,
    pub direct: bool,
    pub unmatched: Vec<String>,
    pub scale: f64,
    pub units: Units,
}

/// The scene with the clip's poses appended as frames (after the scene's own), the camera each
/// clip frame is seen through, and the clip's frames' positions in it.
fn animated_scene(scene: &Scene, driven: &Driven, options: &AnimateOptions) -> Result<(Scene, Vec<usize>, Vec<usize>), FitError> {
    // Read before the scene is copied, so the copy keeps it (it reads every training image).
    let _ = scene.footprint();
    let mut animated = scene.clone();
    let first = animated.frames.len();
    let last_index = animated.frames.iter().map(|f| f.index).max().unwrap_or(-1);
    animated.frames.extend(driven.poses.iter().enumerate().map(|(k, pose)| Frame {
        index: last_index + 1 + k as i64,
        time: Some(k as f64 * driven.frame_time),
        pose: pose.clone(),
        mesh: None,
    }));
    let frames: Vec<usize> = (first..animated.frames.len()).collect();
    let cameras: Vec<usize> = match (options.orbit, options.camera) {
        (Some(count), _) => {
            let count = crate::relight::orbit_views(count)?;
            let at = animated.cameras.len();
            // Only the views the clip's frames look through are made (one per frame at most).
            let orbit: Vec<_> = crate::relight::orbit_cameras(&animated, first, count).take(frames.len()).collect();
            animated.cameras.extend(orbit);
            (0..frames.len()).map(|k| at + k % count).collect()
        }
        (None, camera) => {
            let camera = camera.unwrap_or(0);
            if camera >= scene.cameras.len() {
                return Err(FitError::Input(format!("--camera {camera}: out of range, the scene has {}", scene.cameras.len())));
            }
            vec![camera; frames.len()]
        }
    };
    if let Some((w, h)) = options.size {
        let mut used = cameras.clone();
        used.sort_unstable();
        used.dedup();
        for c in used {
            animated.cameras[c] = animated.cameras[c].resized(w, h);
        }
    }
    Ok((animated, cameras, frames))
}

/// Renders every frame of the clip; returns what was written and how the clip drove the bones.
pub fn animate_run(options: &AnimateOptions, mut on: impl FnMut(TrainMessage)) -> Result<Animated, FitError> {
    let restored = crate::run::restore(&options.run, options.scene.as_deref(), options.backend)?;
    let scene = &restored.scene;
    let motion = crate::capture::read_clip(&options.motion).map_err(|e| FitError::Input(e.to_string()))?;
    let units = options.units.unwrap_or_else(|| Units::for_extent(crate::capture::joint_extent(&motion)));
    let mut driven = retarget::drive(&scene.skeleton, &scene.frames[0].pose, &motion, units.metres())
        .map_err(|e| io(&options.motion, format!("{e} (nothing was written)")))?;
    driven.poses = driven.poses.into_iter().map(|pose| restored.shown_motion(pose)).collect();
    let (animated, cameras, frames) = animated_scene(scene, &driven, options)?;
    if let Some(ground) = options.ground {
        ground.check(&animated, &cameras, &frames)?;
    }
    if options.samples == 0 {
        return Err(FitError::Input("--samples must be at least 1".into()));
    }
    let light = match &options.light {
        None => None,
        Some(spec) => Some(crate::relight::stated_light(&animated, spec)?),
    };
    let total = frames.len();
    let planned: Vec<String> = (0..total).map(frame_file).chain([ANIMATION.to_string()]).collect();
    let folder = crate::written::OutputFolder::claim(&options.out, "render --motion", &planned).map_err(FitError::Input)?;
    let _lock = crate::run_lock::RunLock::for_output(&options.run, &options.out, "render")?;
    folder.begin(&planned).map_err(|e| io(&options.out, e))?;
    let model = restored.fitted.model.valid();
    let device = restored.fitted.device.clone().without_autodiff();
    let lighting = match &light {
        Some(light) => Lighting::Known { light, albedo_scale: crate::run::albedo_scale(&animated, &model), samples: options.samples },
        None => Lighting::Fitted(0),
    };
    on(TrainMessage::Evaluating { images: total });
    on(TrainMessage::Planned { views: total, width: animated.cameras[cameras[0]].width, height: animated.cameras[cameras[0]].height });
    let at_once = rayon::current_num_threads().max(1);
    let views: Vec<usize> = (0..total).collect();
    let rendered = views.chunks(at_once).flat_map(|batch| {
        batch.par_iter().map(|&k| Rendered::view(&model, &animated, (cameras[k], frames[k]), &device, &lighting, options.ground)).collect::<Vec<_>>()
    });
    // The animation is streamed a frame at a time: a long clip at a large size never sits in
    // memory whole.
    let frame_ms = (driven.frame_time * 1000.0).round().clamp(1.0, u16::MAX as f64) as u16;
    let animation_path = options.out.join(ANIMATION);
    let mut animation = None;
    for (k, rendered) in rendered.enumerate() {
        let name = frame_file(k);
        rendered.save(&options.out.join(&name))?;
        let image = &rendered.image;
        let stream = match &mut animation {
            Some(stream) => stream,
            None => animation
                .insert(crate::apng::ApngFile::create(&animation_path, (image.width, image.height), total, frame_ms).map_err(|e| io(&animation_path, e))?),
        };
        stream.push(image).map_err(|e| io(&animation_path, e))?;
        on(TrainMessage::Rendered { done: k + 1, total, name, psnr: None });
    }
    if let Some(stream) = animation {
        stream.finish().map_err(|e| io(&animation_path, e))?;
    }
    folder.finish(&planned).map_err(|e| io(&options.out, e))?;
    Ok(Animated { out: options.out.clone(), frames: total, direct: driven.direct, unmatched: driven.unmatched, scale: driven.scale, units })
}

/// What a motion render says when it is done: the folder, the frames, how the clip drove the
/// bones and which of its joints drove none.
pub fn describe(animated: &Animated) -> String {
    let how = match animated.direct {
        true => "its joints carry the fitted bones: the bones follow the clip's frames directly".to_string(),
        false => format!("retargeted: bones turned by the clip's bones (import's bone rule), the root's travel scaled by {:.3}", animated.scale),
    };
    let mut text = format!("rendered {} frames into {} ({}; units {})", animated.frames, animated.out.display(), how, animated.units.name());
    if !animated.unmatched.is_empty() {
        text.push_str(&format!("\nthe clip's joints {:?} match no bone and were ignored", animated.unmatched));
    }
    text
}
