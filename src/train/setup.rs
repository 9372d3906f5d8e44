//! Setting up a fit: the scene's training lights checked, frames and views indexed for drawing,
//! the body measured, the field shaped to it, Gaussians placed along the bones (and on loose
//! body), the light started above or beside it.

use super::batch::BOUNDARY_BAND;
use super::body::{masked_body_beyond_bones, reach_of, seeds_on_loose_body};
use super::rebind::mean_targets;
use super::{FrameData, Trainer, ViewData};
use crate::avatar::Avatar;
use crate::backend::Backend;
use crate::field::{FieldConfig, PoseTensors};
use crate::fit_error::FitError;
use crate::gaussians::{GaussianParams, GaussianSet};
use crate::light::{Light, UnknownLight};
use crate::random::Stream;
use crate::scene::{Scene, Split};
use crate::schedule::Schedule;
use crate::shading::{FittedLight, LightKind};
use burn::tensor::Device;

/// How far above the body's centre a point light starts, in body extents (2.5 m for a walking
/// human, as before the start was derived from the body).
const LAMP_START_PER_EXTENT: f64 = 1.3;

/// The Gaussians' starting width (m on the reference human).
const GAUSSIAN_START_WIDTH: f64 = 0.05;

/// Spacing (m on the reference human) of the Gaussians seeded on loose body, and how many at
/// most per bone of the skeleton. A bone's Gaussians regularised toward its centre cannot
/// reach a skirt's hem half a metre from the pelvis: the pelvis's grew to cover it (13 cm
/// wide) and their tails shadowed the legs below the hem (human-dressed: 92% of the fitted
/// Gaussians' false shadow on the lit legs came from the pelvis's). Three starting widths
/// apart: human-dressed seeds 20 (the cap is far). Measured there with the default's density
/// at the shadows' scale (seeds 0 / 1): 26.55 / 26.80 dB foreground novel pose, sun 0.88 /
/// 1.03 degrees; at two widths (37 seeds, the bones' own spacing along a thigh) 26.56 / 25.90
/// dB, 1.13 / 1.18 degrees, the skirt's albedo streaked by the denser shell's self-shadow.
const LOOSE_SEED_SPACING: f64 = 3.0 * GAUSSIAN_START_WIDTH;

const LOOSE_SEEDS_PER_BONE: usize = 4;

/// The field the schedule asks for: the Fourier `mlp` field, or feature grids shaped by the
/// body's `extent` (the diagonal of the posed skeleton's bounds, m) with the schedule's overrides.
/// `loose` says how far the body reaches beyond every bone's grid box as the training masks
/// show it (`masked_reach_beyond_bones`): the root's grids then reach that far.
pub fn field_config(
    settings: &crate::schedule::FieldSettings,
    skeleton: &crate::skeleton::Skeleton,
    extent: f32,
    loose: impl Fn(f32, usize) -> Option<f32>,
) -> FieldConfig {
    if let Some(recorded) = &settings.recorded {
        return recorded.clone();
    }
    // The field's lengths (tuned in metres on the reference human) follow the body's size.
    let scaled = |config: FieldConfig| {
        let unit = crate::skeleton::body_length(1.0, extent as f64) as f32;
        FieldConfig {
            min_beta: extent * crate::field::MIN_BETA_PER_EXTENT,
            skinning_width: config.skinning_width * unit,
            prior_radius: config.prior_radius * unit,
            initial_beta: config.initial_beta * unit,
            residual_scale: config.residual_scale * unit,
            frequencies: config.frequencies.iter().map(|f| f / unit).collect(),
            ..config
        }
    };
    let config = match settings.kind {
        crate::schedule::FieldKind::Mlp => scaled(FieldConfig::for_bones(skeleton.len())),
        crate::schedule::FieldKind::Grid => {
            let mut config = scaled(FieldConfig::with_grid(skeleton.bones.iter().map(|b| b.length as f32).collect(), extent));
            let root = skeleton.bones.iter().position(|b| b.parent.is_none()).filter(|_| settings.root_skinning.unwrap_or(true));
            let cap = crate::field::ROOT_REACH_PER_WIDTH * config.skinning_width;
            if let Some(grid) = config.grid.as_mut() {
                grid.levels = settings.levels.unwrap_or(grid.levels);
                grid.table_log2 = settings.table_log2.unwrap_or(grid.table_log2);
                grid.top_bones = settings.top_bones.unwrap_or(grid.top_bones);
                grid.features = settings.features.unwrap_or(grid.features);
                if let Some(cells) = settings.finest_per_extent {
                    grid.finest_cell = extent / cells as f32;
                }
                if let Some(reach) = settings.reach_per_extent {
                    grid.reach = extent * reach as f32;
                }
                grid.root = root.map(|bone| crate::field::grid::RootSkinning::for_body(bone, cap, grid.reach, loose(grid.reach, bone), extent));
            }
            config
        }
    };
    FieldConfig { albedo_layers: settings.albedo_layers.unwrap_or(config.albedo_layers), ..config }
}

/// The training lights as a fit sees them: their kind (uniform when the schedule fits no light),
/// whether a light is fitted, how many, and each view's (its index in `Scene::training_lights`;
/// `None` for a view not in training).
pub struct TrainingLights {
    pub kind: LightKind,
    pub fit: bool,
    pub count: usize,
    pub view_light: Vec<Option<usize>>,
}

/// The scene's training lights checked for what umbra can fit: one kind (suns or point lights,
/// or one uniform light), no environment map.
pub fn training_lights(scene: &Scene, schedule: &Schedule) -> Result<TrainingLights, FitError> {
    let lights = scene.training_lights();
    let Some(first_name) = lights.first() else {
        return Err(FitError::Input(format!("{}: no training images (split \"train\")", scene.root.join("scene.json").display())));
    };
    let kind_of = |light: &Light| match light {
        Light::Directional { .. } | Light::Unknown { kind: UnknownLight::Sun, .. } => LightKind::Directional,
        Light::Point { .. } | Light::Unknown { kind: UnknownLight::Point, .. } => LightKind::Point,
        Light::Uniform { .. } | Light::Environment { .. } => LightKind::Uniform,
    };
    for name in &lights {
        // An environment map lights a body unevenly (a bright sky above, a dark ground
        // below); fitted as uniform light its shading would be painted into the albedo, and
        // the report would call the capture uniformly lit. Refused until it is fitted for
        // what it is.
        if let Light::Environment { .. } = &scene.lights[*name] {
            return Err(FitError::Input(format!(
                "{}: lights.{name}: the training images are lit by the environment map {name:?}; umbra cannot fit an environment-lit capture yet (treated as uniform light, the map's shading would end up in the albedo): fit a capture lit by suns, point lights or uniform light",
                scene.root.join("scene.json").display(),
            )));
        }
        // Several lights are fitted jointly when they are of one kind: several suns, or
        // several point lights (a light stage), each image under its own.
        let first = kind_of(&scene.lights[*first_name]);
        if lights.len() > 1 && first == LightKind::Uniform && kind_of(&scene.lights[*name]) == first {
            return Err(FitError::Input(format!(
                "{}: training images use the uniform lights {lights:?}; umbra fits one uniform light (uniform lights differ only in strength, which the albedo absorbs): give them one light",
                scene.root.join("scene.json").display(),
            )));
        }
        if kind_of(&scene.lights[*name]) != first {
            return Err(FitError::Input(format!(
                "{}: training images use the lights {lights:?} of different kinds ({} and {}); umbra fits several training lights only when all are suns or all are point lights",
                scene.root.join("scene.json").display(),
                scene.lights[*first_name].type_name(),
                scene.lights[*name].type_name(),
            )));
        }
    }
    let light = &scene.lights[*first_name];
    let view_light = scene.views.iter().map(|v| if v.split == Split::Train { lights.iter().position(|n| *n == v.light) } else { None }).collect();
    let fit = schedule.check_against(light.casts_shadows())?;
    let kind = if fit { kind_of(light) } else { LightKind::Uniform };
    Ok(TrainingLights { kind, fit, count: lights.len(), view_light })
}

/// The centre of the skeleton's bounds over the capture: where a point light is searched
/// around and what its position is expressed from.
pub fn body_centre(scene: &Scene) -> glam::DVec3 {
    let (lo, hi) = scene
        .frames
        .iter()
        .map(|f| f.pose.bounds(&scene.skeleton))
        .fold((glam::DVec3::splat(f64::INFINITY), glam::DVec3::splat(f64::NEG_INFINITY)), |a, b| (a.0.min(b.0), a.1.max(b.1)));
    (lo + hi) * 0.5
}

/// A new avatar for `scene`: the field `config` initialised from `seed`, the Gaussians `set`,
/// `light_count` training lights of `kind` (a point light above the body, where the light
/// search moves it from; a sun overhead).
pub fn new_avatar(scene: &Scene, config: &FieldConfig, set: &GaussianSet, kind: LightKind, light_count: usize, device: &Device, seed: u64) -> Avatar {
    let extent = scene.body_extent();
    let unit = crate::skeleton::body_length(1.0, extent);
    let centre = body_centre(scene);
    let initial = match kind {
        LightKind::Point => (centre + glam::DVec3::Y * (LAMP_START_PER_EXTENT * extent)).as_vec3().to_array(),
        _ => [0.0, 1.0, 0.0],
    };
    let light = || FittedLight::new(kind, initial, centre.as_vec3().to_array(), extent, 0.3, device);
    Avatar {
        field: config.init(device, seed),
        gaussians: GaussianParams::from_set(set, unit as f32, device),
        light: light(),
        // The first light fixes the scale the albedo cannot be told apart from (a sun's
        // irradiance 1, the ambient's target): the others' strengths are learned relative to it.
        other_lights: (1..light_count).map(|_| light().with_learned_strength()).collect(),
    }
}

/// The scene's training views, refused when there are none or none of their masks marks any
/// body (a segmenter that found nothing, inverted masks saved as black would fit an empty
/// avatar without a word).
fn training_views(scene: &Scene) -> Result<Vec<usize>, FitError> {
    let training: Vec<usize> = (0..scene.views.len()).filter(|&i| scene.views[i].split == Split::Train).collect();
    if training.is_empty() {
        return Err(FitError::Input(format!("{}: no training images (split \"train\")", scene.root.join("scene.json").display())));
    }
    let masked = |i: &usize| scene.views[*i].mask.as_ref().is_some_and(|m| m.foreground.iter().any(|&f| f));
    if !training.iter().any(masked) {
        return Err(FitError::Input(format!(
            "{}: images[*].mask: none of the {} training masks marks any pixel as body (value > 127): check the masks (inverted? empty?)",
            scene.root.join("scene.json").display(),
            training.len()
        )));
    }
    Ok(training)
}

/// The training frames with their views, and per view of the scene the pixels a batch draws
/// from (training views only; indices fit in 32 bits, a scene's images being at most
/// `imageio::MAX_PIXELS`).
fn index_training(scene: &Scene, training: &[usize], device: &Device) -> (Vec<FrameData>, Vec<ViewData>) {
    use rayon::prelude::*;
    let mut frames: Vec<FrameData> = Vec::new();
    for &v in training {
        let f = scene.views[v].frame;
        match frames.iter_mut().find(|d| d.position == f) {
            Some(d) => d.views.push(v),
            None => frames.push(FrameData { position: f, pose_tensors: PoseTensors::new(&scene.frames[f].pose, &scene.skeleton, device), views: vec![v] }),
        }
    }
    let views = scene
        .views
        .par_iter()
        .map(|v| {
            let mask = v.mask.as_ref().filter(|_| v.split == Split::Train);
            ViewData {
                foreground: mask.map(|m| (0..m.foreground.len() as u32).filter(|&k| m.foreground[k as usize]).collect()).unwrap_or_default(),
                boundary: mask.map(|m| crate::silhouette::edge_pixels(m, BOUNDARY_BAND).into_iter().collect()).unwrap_or_default(),
                near_edge: match (mask, &v.plate) {
                    (Some(m), Some(plate)) => {
                        crate::silhouette::edge_pixels(m, crate::silhouette::EDGE_BAND).into_iter().filter(|&p| plate.known.foreground[p as usize]).collect()
                    }
                    _ => Default::default(),
                },
            }
        })
        .collect();
    (frames, views)
}

impl Trainer {
    pub fn new(scene: Scene, schedule: Schedule, backend: Backend, seed: u64) -> Result<Self, FitError> {
        let device = backend.open().map_err(|e| FitError::Input(e.to_string()))?;
        device.seed(seed);
        let training = training_views(&scene)?;
        let TrainingLights { kind: light_kind, fit: fit_light, count: light_count, view_light } = training_lights(&scene, &schedule)?;
        let (frames, views) = index_training(&scene, &training, &device);
        let extent = scene.body_extent();
        let unit = crate::skeleton::body_length(1.0, extent);
        // Four Gaussians per bone, 5 cm wide on the reference human.
        let mut set = GaussianSet::along_bones(&scene.skeleton, 4, GAUSSIAN_START_WIDTH * unit, 10.0);
        let centre = body_centre(&scene);
        // Where the masks show body beyond every bone (root-local points): the root's grids
        // reach it, and Gaussians are seeded on it.
        let loose_body = std::cell::RefCell::new(Vec::new());
        let field_config = field_config(&schedule.field, &scene.skeleton, extent as f32, |reach, root| {
            let points = masked_body_beyond_bones(&scene, reach as f64, root);
            let far = reach_of(&points, scene.skeleton.bones[root].length, reach as f64).map(|r| r as f32);
            *loose_body.borrow_mut() = points;
            far
        });
        let grid = field_config.grid.as_ref();
        let root = grid.and_then(|g| g.root).filter(|r| r.features_reach_body).map(|r| r.bone);
        let mut anchors = vec![None; set.len()];
        if let (Some(root), Some(grid)) = (root, grid) {
            // A run rebuilt from its checkpoint records its field, so the masks were not searched.
            let mut points = loose_body.take();
            if points.is_empty() {
                points = masked_body_beyond_bones(&scene, grid.reach as f64, root);
            }
            let seeds = seeds_on_loose_body(&points, LOOSE_SEED_SPACING * unit, LOOSE_SEEDS_PER_BONE * scene.skeleton.len());
            for seed in seeds {
                set.gaussians.push(crate::gaussians::Gaussian {
                    bone: root,
                    mean: seed.to_array(),
                    rotation: [0.0, 0.0, 0.0, 1.0],
                    scales: [GAUSSIAN_START_WIDTH * unit; 3],
                    amplitude: 10.0,
                });
                anchors.push(Some(seed));
            }
        }
        // A loose body (the root's grids reach body beyond every bone's) draws rays by error
        // under `auto`; each training view with a mask then keeps an error map.
        let error_rays = schedule.error_rays.share(root.is_some());
        let density_at_shadow_scale = schedule.density_at_shadow_scale.on(root.is_some());
        let schedule = schedule.with_lazy_regularisation(root.is_none());
        let error_maps = scene
            .views
            .iter()
            .map(|view| match (&view.mask, view.split) {
                (Some(mask), Split::Train) if error_rays > 0.0 => Some(crate::error_map::ErrorMap::new(mask.width, mask.height)),
                _ => None,
            })
            .collect();
        let model = new_avatar(&scene, &field_config, &set, light_kind, light_count, &device, seed);
        let reference = frames.first().map(|f| &scene.frames[f.position].pose);
        let mean_targets = mean_targets(&set.gaussians.iter().map(|g| g.bone).collect::<Vec<_>>(), &anchors, root, reference, &scene.skeleton, &device);

        let footprint_estimate = scene.footprint();
        let camera_colours = super::camera_colour::CameraColours::new(&scene);
        // The motion is refined through the grid's lookups (the `mlp` field has no way in).
        let refine = schedule.refine_motion.on(scene.capture.is_some());
        let motion = model.field.grid.as_ref().filter(|_| refine).and_then(|_| super::motion::MotionCorrections::new(&scene));
        let refine_cameras = schedule.refine_cameras.on(scene.capture.is_some());
        let cameras = model.field.grid.as_ref().filter(|_| refine_cameras).and_then(|_| super::camera_pose::CameraPoses::new(&scene));
        let footprint = schedule.footprint.unwrap_or(footprint_estimate.footprint);
        Ok(Self {
            scene,
            schedule,
            device,
            state: Some(super::TrainState {
                model,
                optimisers: super::Optimisers::new(),
                iteration: 0,
                average: None,
                error_maps,
                camera_colours,
                motion,
                cameras,
                gaussians_read: None,
            }),
            frames,
            plates: views.iter().any(|v| !v.near_edge.is_empty()),
            views,
            fit_light,
            light_kind,
            seed,
            stream: Stream::new(seed, 0x7AA1, 0),
            gradient: crate::field::GRADIENT,
            render_missed_rays: false,
            render_threads: rayon::current_num_threads(),
            parts_backward_at_once: true,
            body_centre: centre,
            body_extent: extent,
            searches: vec![None; light_count],
            cones: vec![None; light_count],
            view_light,
            training_identity: std::sync::OnceLock::new(),
            mean_targets,
            anchors,
            loose_root: root,
            footprint_estimate,
            footprint,
            error_rays,
            density_at_shadow_scale,
        })
    }
}
