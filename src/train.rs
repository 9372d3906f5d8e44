//! The fit: one explicit loop of `step(batch, state) -> stats` (forward, weighted losses from the
//! schedule, backward, one Adam step per parameter group), atomic checkpoints with exact resume,
//! and typed messages that the CLI turns into a progress bar. It skips what a scene does not
//! need: a uniformly lit capture gets no light, no shadow rays and no light-fitting stage. A
//! capture under several lights of one kind fits them jointly, each batch under one of them.

use crate::field::{AvatarField, FieldConfig, GradientMethod, PoseTensors};
use crate::gaussians::{GaussianParams, GaussianSet};
use crate::light::Light;
use crate::random::Stream;
use crate::render::{ray_bounds, render, render_in_parts, sum_gradients, Deferred, RaySet};
use crate::scene::{Scene, Split};
use crate::schedule::Schedule;
use crate::shading::{FittedLight, LightKind};
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Int, Tensor, TensorData};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// burn's pure-Rust CPU backend (default; the faster one here).
    Flex,
    /// burn-ndarray.
    Ndarray,
}

impl Backend {
    pub fn device(self) -> Device {
        match self {
            Backend::Flex => Device::flex().autodiff(),
            #[allow(deprecated)]
            Backend::Ndarray => Device::ndarray().autodiff(),
        }
    }
}

/// The whole learnable avatar.
#[derive(Module, Debug)]
pub struct Avatar {
    pub field: AvatarField,
    pub gaussians: GaussianParams,
    /// The first training light (in the order of `Scene::training_lights`).
    pub light: FittedLight,
    /// The other training lights of a capture lit by several (none for one light, so a
    /// one-light checkpoint holds exactly what it did before there could be more).
    pub other_lights: Vec<FittedLight>,
}

impl Avatar {
    /// Training light `k` (0: `light`).
    pub fn light_at(&self, k: usize) -> &FittedLight {
        if k == 0 {
            &self.light
        } else {
            self.other_lights.get(k - 1).unwrap_or(&self.light)
        }
    }

    fn light_at_mut(&mut self, k: usize) -> &mut FittedLight {
        if k == 0 || k > self.other_lights.len() {
            &mut self.light
        } else {
            &mut self.other_lights[k - 1]
        }
    }

    /// How many training lights the avatar was fitted under.
    pub fn light_count(&self) -> usize {
        1 + self.other_lights.len()
    }
}

#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error("{0}")]
    Scene(#[from] crate::scene::SceneError),
    #[error("{0}")]
    Schedule(#[from] crate::schedule::ScheduleError),
    #[error("{0}")]
    Input(String),
    #[error("{path}: {message}")]
    Io { path: PathBuf, message: String },
    #[error("the fit diverged at iteration {iteration}: {what} is not finite; {checkpoint}")]
    NonFinite {
        iteration: usize,
        what: String,
        /// What became of the checkpoint, as a sentence for the user.
        checkpoint: String,
    },
}

pub fn io(path: &Path, e: impl std::fmt::Display) -> FitError {
    FitError::Io { path: path.to_path_buf(), message: e.to_string() }
}

/// What the fit tells whoever runs it.
#[derive(Clone, Debug)]
pub enum TrainMessage {
    Loaded {
        scene: String,
        training_images: usize,
        frames: usize,
        light: LightKind,
    },
    Started {
        first: usize,
        iterations: usize,
    },
    Step {
        iteration: usize,
        stats: StepStats,
    },
    Checkpoint {
        iteration: usize,
    },
    Evaluating {
        images: usize,
    },
    /// One image rendered, with its PSNR when there is a ground truth to score it against.
    Rendered {
        done: usize,
        total: usize,
        name: String,
        psnr: Option<f64>,
    },
    Done,
}

/// The losses of one step (unweighted) and the weighted total.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct StepStats {
    pub total: f64,
    pub terms: BTreeMap<String, f64>,
    pub seconds: f64,
    /// Wall seconds per part of the step, in order (`PHASES`; the sun search only when it ran).
    /// burn's CPU backends run eagerly, so each part's tensor work is done within its span.
    #[serde(skip)]
    pub phases: Vec<(&'static str, f64)>,
    /// The first training light after the step (`FittedLight::location`): a sun's unit
    /// direction or a point light's position (m); none when no light is fitted. Kept in
    /// `losses.csv`, so a run's path of the light survives `--resume` (`fit.json`: `light_path`).
    pub light: Option<[f64; 3]>,
}

/// The parts of a training step `StepStats::phases` times.
pub const PHASES: [&str; 10] = [
    "sun search",
    "batch sampling (CPU)",
    crate::render::RENDER_PARTS[0],
    crate::render::RENDER_PARTS[1],
    crate::render::RENDER_PARTS[2],
    "shading + shadows",
    "mask, grey, density and Gaussian losses",
    "Eikonal + curvature (SDF gradients)",
    "backward",
    "optimiser step",
];

/// Splits a step's wall time into `PHASES`.
struct PhaseClock {
    last: Instant,
    spans: Vec<(&'static str, f64)>,
}

impl PhaseClock {
    fn start() -> Self {
        Self { last: Instant::now(), spans: Vec::new() }
    }

    /// Ends the current part of the step as the render's three parts, timed by `render`.
    fn mark_render(&mut self, deferred: &Deferred) {
        for (k, seconds) in deferred.seconds.iter().enumerate() {
            self.spans.push((PHASES[2 + k], *seconds));
        }
        self.last = Instant::now();
    }

    /// Ends the current part of the step as `PHASES[k]`.
    fn mark(&mut self, k: usize) {
        let now = Instant::now();
        self.spans.push((PHASES[k], (now - self.last).as_secs_f64()));
        self.last = now;
    }
}

#[derive(Clone, Debug)]
pub struct FitOptions {
    pub scene: PathBuf,
    pub out: PathBuf,
    pub schedule: PathBuf,
    pub iterations: Option<usize>,
    pub seed: u64,
    pub resume: bool,
    /// Replace an earlier run's checkpoint and outputs in `out`.
    pub force: bool,
    /// With `resume`: continue even though the schedule or the iteration count differs from
    /// the run's (otherwise refused: it would not be the continuation it claims).
    pub force_schedule: bool,
    pub backend: Backend,
    /// Render and score the test images at the end.
    pub evaluate: bool,
}

/// Training data of one frame: its pose and the views that see it.
struct FrameData {
    position: usize,
    pose_tensors: PoseTensors,
    views: Vec<usize>,
}

/// Per training view: pixel indices for balanced ray sampling.
struct ViewData {
    foreground: Vec<usize>,
    /// Pixels within `BOUNDARY_BAND` pixels of the silhouette's edge, on either side.
    boundary: Vec<usize>,
    /// Where the fit is still wrong in this view, when the schedule draws rays by it
    /// (`Schedule::error_rays`; training views with a mask only).
    error_map: Option<crate::error_map::ErrorMap>,
}

/// How far above the body's centre a point light starts, in body extents (2.5 m for a walking
/// human, as before the start was derived from the body).
const LAMP_START_PER_EXTENT: f64 = 1.3;

/// Half-width (pixels) of the band around a silhouette that a third of each batch samples:
/// there the surface's position is decided, and uniform sampling hits it rarely (a few
/// percent of a view's pixels).
const BOUNDARY_BAND: usize = 2;

/// The pixels of `mask` within `band` pixels (Chebyshev) of a pixel of the other kind.
fn boundary_pixels(mask: &crate::imageio::Mask, band: usize) -> Vec<usize> {
    let (w, h) = (mask.width, mask.height);
    let b = band as i64;
    (0..w * h)
        .filter(|&p| {
            let (x, y) = ((p % w) as i64, (p / w) as i64);
            let inside = mask.foreground[p];
            (-b..=b).any(|dy| {
                (-b..=b).any(|dx| {
                    let (u, v) = (x + dx, y + dy);
                    u >= 0 && v >= 0 && (u as usize) < w && (v as usize) < h && mask.foreground[v as usize * w + u as usize] != inside
                })
            })
        })
        .collect()
}

pub struct Trainer {
    pub scene: Scene,
    pub schedule: Schedule,
    pub device: Device,
    pub model: Option<Avatar>,
    pub optimizers: Vec<(String, ModuleOptimizer)>,
    frames: Vec<FrameData>,
    views: Vec<ViewData>,
    pub fit_light: bool,
    pub light_kind: LightKind,
    pub iteration: usize,
    /// The seed the fit was started with (a resumed fit keeps it).
    pub seed: u64,
    pub stream: Stream,
    /// How SDF gradients (normals, Eikonal, curvature) are taken; `GRADIENT` unless a
    /// benchmark compares methods.
    pub gradient: GradientMethod,
    /// Render rays that miss every Gaussian bound too (as before they were skipped): only
    /// for the benchmark that measures what skipping them saves.
    pub render_missed_rays: bool,
    /// Threads a step's render is split over (`render::render_in_parts`): every thread by
    /// default; 1 renders the batch on one (a benchmark's baseline). The parts' matrix products
    /// round differently, so a fit is the same to the bit for a seed and a thread count.
    pub render_threads: usize,
    /// The centre of the skeleton's bounds over the capture and the body's extent (m): where
    /// and at what distances a point light is searched.
    body_centre: glam::DVec3,
    body_extent: f64,
    /// Where the mean regulariser pulls each Gaussian, bone-local (`mean_targets`).
    mean_targets: Tensor<2>,
    /// Per Gaussian, its seed (root-local) when it was seeded on loose body
    /// (`seeds_on_loose_body`): the mean regulariser pulls it there, not to its bone's centre.
    anchors: Vec<Option<glam::DVec3>>,
    /// The root bone when the body is loose (its grids reach body beyond every bone's).
    loose_root: Option<usize>,
    /// What the light search found for each training light, once it has run (`sun_search`).
    pub searches: Vec<Option<crate::sun_search::SearchReport>>,
    /// Per training light, the cone (axis, half-angle in radians) a sun's direction stays in
    /// after the search.
    pub cones: Vec<Option<(glam::DVec3, f64)>>,
    /// The training light of each of the scene's views (its index in `Scene::training_lights`;
    /// `None` for a view not in training).
    view_light: Vec<Option<usize>>,
    /// The training data's fingerprint (`Scene::training_identity`, every training pixel
    /// hashed), computed once for all the checkpoints a fit writes.
    training_identity: std::sync::OnceLock<String>,
    /// What the training images say of their pixel footprint (`scene::footprint`), and the
    /// footprint the fit models (the schedule's, else that).
    pub footprint_estimate: crate::scene::FootprintEstimate,
    pub footprint: crate::scene::Footprint,
    /// The moving average of the field's parameters, once the schedule's
    /// `field_average_half_life` has started it (`fitted_model`).
    pub average: Option<crate::averaging::ParameterAverage>,
    /// The share of the anywhere-third drawn by the error maps: the schedule's, or under
    /// `auto` what the body's looseness asks (`ErrorRays::share`).
    pub error_rays: f64,
    /// Whether the Gaussians also fit the density at the shadows' scale (the schedule's
    /// `density_at_shadow_scale`, `auto` resolved by the body's looseness).
    pub density_at_shadow_scale: bool,
}

/// Whether the `j`-th draw of a part of the batch is one of the evenly spread `share` of its
/// draws (every (1 / share)-th: 0 takes none, 1 every one).
fn takes_share(j: usize, share: f64) -> bool {
    let j = j as f64;
    (j * share).floor() != ((j + 1.0) * share).floor()
}

/// A training batch: pixels of one frame's views under one training light.
struct Batch {
    frame: usize,
    light: usize,
    /// Rays that meet a Gaussian's bound first (`hits` of them, only they enter the field),
    /// then the others, which are background: colour and accumulation zero.
    rays: RaySet,
    hits: usize,
    /// Per pixel, its colour (linear RGB) and mask.
    colours: Vec<f32>,
    masks: Vec<f32>,
    /// Per pixel, its view, its index in the view, and whether it was drawn by the view's
    /// error map (`Schedule::error_rays`).
    sources: Vec<(usize, usize, bool)>,
}

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
                if let Some(root) = grid.root.as_mut() {
                    root.prior_knee = root.prior_capped && settings.prior_knee;
                }
            }
            config
        }
    };
    FieldConfig { albedo_layers: settings.albedo_layers.unwrap_or(config.albedo_layers), ..config }
}

/// Lattice steps per body extent (the posed bones' diagonal) when the training masks are
/// searched for body beyond the bones' grids (`masked_reach_beyond_bones`): 3 cm on a human,
/// a tenth of what a box reaches beyond its bone.
const HULL_STEPS_PER_EXTENT: f64 = 64.0;

/// The points of the `root` bone's frame (root-local, m, one per lattice cell) where the body
/// lies farther than `reach` from every bone, as the training masks show it; none for a body
/// tight on its bones.
///
/// Each training frame's visual hull (a lattice over the frame's bones widened by twice
/// `reach`; a point is in it when every masked training view of the frame sees it inside its
/// mask) proposes the points farther than `reach` from every bone that some view shows beyond
/// the bones: the ray through the point's pixel passes farther than `reach` from every bone,
/// so that pixel's body is not the bones'. A few views leave phantoms in a hull (inside every
/// mask, no body there: under a dog's belly, where no camera looks), and a tight body explains
/// every one of their pixels; dog-sun's 7-view hull reached 0.44 m from its bones without this
/// test. Phantoms beside real clothing (behind a skirt, along one camera's cone) can still pass
/// it; they lie wherever the cameras' cones cross the body, so they move with the pose, while
/// clothing the root carries stays put in the root's frame: a proposal counts only when, in the
/// root's frame, the hull holds it in at least half of the frames where it lies beyond every
/// bone (`LOOSE_CONSENSUS`).
pub fn masked_body_beyond_bones(scene: &Scene, reach: f64, root: usize) -> Vec<glam::DVec3> {
    use rayon::prelude::*;
    let skeleton = &scene.skeleton;
    let distance = crate::skeleton::distance_to_segment;
    // Per masked training frame: the frame, its bones' segments (asked for at every lattice
    // point) and its masked training views.
    type Segments = Vec<(glam::DVec3, glam::DVec3)>;
    let frames: Vec<(&crate::scene::Frame, Segments, Vec<&crate::scene::View>)> = scene
        .frames
        .iter()
        .enumerate()
        .map(|(position, frame)| {
            let segments = (0..skeleton.len()).map(|b| frame.pose.segment(skeleton, b)).collect();
            (frame, segments, scene.views.iter().filter(|v| v.frame == position && v.split == Split::Train && v.mask.is_some()).collect())
        })
        .filter(|(_, _, views): &(_, _, Vec<_>)| !views.is_empty())
        .collect();
    let inside_every_mask = |views: &[&crate::scene::View], p: glam::DVec3| {
        views.iter().all(|v| {
            let camera = &scene.cameras[v.camera];
            let Some(mask) = v.mask.as_ref() else { return false };
            camera.project(p).is_some_and(|px| {
                let (x, y) = (px.x.floor(), px.y.floor());
                x >= 0.0 && y >= 0.0 && (x as usize) < mask.width && (y as usize) < mask.height && mask.foreground[y as usize * mask.width + x as usize]
            })
        })
    };
    let beyond_every_bone = |segments: &[(glam::DVec3, glam::DVec3)], p: glam::DVec3| segments.iter().all(|&s| distance(p, s) > reach);
    // A view shows body beyond the bones at `p` when the ray through p's pixel passes farther
    // than `reach` from every bone: a body tight on its bones explains every mask pixel, so a
    // phantom of the hull (inside every mask, yet no body there) never passes this test.
    let far_beyond = 4.0 * (scene.body_extent() + reach);
    let shown_beyond_bones = |segments: &[(glam::DVec3, glam::DVec3)], views: &[&crate::scene::View], p: glam::DVec3| {
        views.iter().any(|v| {
            let camera = &scene.cameras[v.camera];
            camera.project(p).is_some_and(|px| {
                let ray = camera.ray_through(px.floor() + glam::DVec2::splat(0.5));
                let ray = (ray.origin, ray.at((p - ray.origin).length() + far_beyond));
                segments.iter().all(|&s| crate::skeleton::segment_distance(ray, s) > reach)
            })
        })
    };
    // Proposals, root-local, from every frame's hull.
    let proposals: Vec<glam::DVec3> = frames
        .par_iter()
        .flat_map_iter(|(frame, segments, views)| {
            let (lo, hi) = frame.pose.bounds(skeleton);
            let step = (hi - lo).length() / HULL_STEPS_PER_EXTENT;
            let (lo, hi) = (lo - glam::DVec3::splat(2.0 * reach), hi + glam::DVec3::splat(2.0 * reach));
            let counts = ((hi - lo) / step).ceil().as_uvec3();
            let mut found = Vec::new();
            for k in 0..counts.z {
                for j in 0..counts.y {
                    for i in 0..counts.x {
                        let p = lo + glam::DVec3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5) * step;
                        if beyond_every_bone(segments, p) && inside_every_mask(views, p) && shown_beyond_bones(segments, views, p) {
                            found.push(frame.pose.to_local(root, p));
                        }
                    }
                }
            }
            found
        })
        .collect();
    // One proposal per cell of a root-local lattice (frames propose the same points over and over).
    let cell = scene.body_extent() / HULL_STEPS_PER_EXTENT;
    let proposals: Vec<glam::DVec3> =
        proposals.into_iter().map(|p| ((p / cell).round().as_i64vec3().to_array(), p)).collect::<std::collections::HashMap<_, _>>().into_values().collect();
    // The consensus over frames, in the root's frame.
    let held = |local: &glam::DVec3| {
        let (mut beyond, mut inside) = (0usize, 0usize);
        for (frame, segments, views) in &frames {
            let p = frame.pose.to_world(root, *local);
            if beyond_every_bone(segments, p) {
                beyond += 1;
                inside += inside_every_mask(views, p) as usize;
            }
        }
        inside as f64 >= LOOSE_CONSENSUS * beyond as f64
    };
    let mut held: Vec<glam::DVec3> = proposals.into_par_iter().filter(|p| held(p)).collect();
    // The map's order is arbitrary: sorted, so whatever is seeded from the points is the same
    // in every run (a resumed fit rebuilds it).
    held.sort_by(|a, b| a.to_array().partial_cmp(&b.to_array()).unwrap_or(std::cmp::Ordering::Equal));
    held
}

/// How far from the `root` bone's segment the body reaches where it lies farther than `reach`
/// from every bone, as the training masks show it (`masked_body_beyond_bones`), plus a quarter
/// of `reach` so the surface is inside the grid; `None` when nowhere (a body tight on its
/// bones: the grids hold it already).
pub fn masked_reach_beyond_bones(scene: &Scene, reach: f64, root: usize) -> Option<f64> {
    let points = masked_body_beyond_bones(scene, reach, root);
    reach_of(&points, scene.skeleton.bones[root].length, reach)
}

/// The farthest of `points` (root-local) from the root's segment of `length`, plus a quarter
/// of `reach`.
fn reach_of(points: &[glam::DVec3], length: f64, reach: f64) -> Option<f64> {
    let segment = (glam::DVec3::ZERO, glam::DVec3::new(0.0, length, 0.0));
    points.iter().map(|&p| crate::skeleton::distance_to_segment(p, segment)).reduce(f64::max).map(|d| d + 0.25 * reach)
}

/// The share of the frames (where a point lies beyond every bone) whose visual hull must hold
/// a point of the root's frame for it to count as loose body (`masked_reach_beyond_bones`).
const LOOSE_CONSENSUS: f64 = 0.5;

/// The bones `chosen` for Gaussians now on bones `current`, except that every bone that has a
/// Gaussian keeps one: of a bone all of whose Gaussians would leave, the one its own motion
/// carries best (least `outside[g][bone]`, the mean distance outside the surface) stays. The
/// density fit pulls the Gaussians of a hand hanging beside a skirt into the skirt, and
/// rebinding them all to the pelvis or a thigh left the hand with none, casting no shadow in
/// any pose (human-dressed seed 2: the right hand); the one kept is pulled back by the mean
/// regulariser toward its bone. A Gaussian sent back stays, so this ends.
fn keep_every_bone(mut chosen: Vec<usize>, current: &[usize], outside: &[Vec<f64>]) -> Vec<usize> {
    loop {
        let emptied = current.iter().copied().find(|&b| !chosen.contains(&b));
        let Some(bone) = emptied else { return chosen };
        let best = (0..current.len()).filter(|&g| current[g] == bone).min_by(|&x, &y| outside[x][bone].total_cmp(&outside[y][bone]));
        match best {
            Some(g) => chosen[g] = bone,
            None => return chosen,
        }
    }
}

/// How much farther outside the surface (m on the reference human, on average over the frames)
/// than the best bone a Gaussian's own bone may carry it before the Gaussian moves
/// (`Trainer::rebind_gaussians`): a few millimetres, below the surface's own noise, so that
/// bones that carry it equally well (spine and chest for a point of the back) do not trade it.
const REBIND_TOLERANCE: f64 = 0.005;

/// Where the mean regulariser pulls each Gaussian, bone-local (m): a Gaussian seeded on loose
/// body (`seeds_on_loose_body`) toward its seed, the `root`-local `anchors[g]`, also after
/// rebinding moved it to another bone (the seed re-expressed in that bone's frame in the
/// rebinding's `reference` pose, where the move kept the Gaussian in place); any other toward
/// its bone's centre. A rule of the Gaussian's index and bone alone, so a resumed fit pulls as
/// the straight one does.
fn mean_targets(
    bones: &[usize],
    anchors: &[Option<glam::DVec3>],
    root: Option<usize>,
    reference: Option<&crate::skeleton::Pose>,
    skeleton: &crate::skeleton::Skeleton,
    device: &Device,
) -> Tensor<2> {
    let centres: Vec<f32> = bones
        .iter()
        .enumerate()
        .flat_map(|(g, &b)| match (anchors.get(g).copied().flatten(), root, reference) {
            (Some(anchor), Some(root), _) if b == root => anchor.as_vec3().to_array(),
            (Some(anchor), Some(root), Some(pose)) => pose.to_local(b, pose.to_world(root, anchor)).as_vec3().to_array(),
            _ => [0.0, skeleton.bones[b].length as f32 / 2.0, 0.0],
        })
        .collect();
    Tensor::from_data(TensorData::new(centres, [bones.len(), 3]), device)
}

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

/// Farthest-point samples of `points` (the loose body, root-local) until every point lies
/// within `spacing` of a sample or there are `most`: Gaussians' means that cover it evenly.
/// The first is the point farthest from the others' centre, so the spread is the same for
/// the same points.
pub fn seeds_on_loose_body(points: &[glam::DVec3], spacing: f64, most: usize) -> Vec<glam::DVec3> {
    if points.is_empty() || most == 0 {
        return Vec::new();
    }
    let centre = points.iter().copied().sum::<glam::DVec3>() / points.len() as f64;
    let first = (0..points.len()).max_by(|&a, &b| points[a].distance_squared(centre).total_cmp(&points[b].distance_squared(centre))).unwrap_or(0);
    let mut seeds = vec![points[first]];
    let mut nearest: Vec<f64> = points.iter().map(|p| p.distance(points[first])).collect();
    while seeds.len() < most {
        let Some((next, &gap)) = nearest.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)) else { break };
        if gap <= spacing {
            break;
        }
        seeds.push(points[next]);
        for (d, p) in nearest.iter_mut().zip(points) {
            *d = d.min(p.distance(points[next]));
        }
    }
    seeds
}

/// How far (in the search lattice's spacings, 7.2 degrees at 256 directions) gradient descent
/// may take the sun from the search's best. The search scores directions with the albedo still
/// grey and the geometry early, so it can be off by more than its lattice's spacing (dog-sun:
/// 14 degrees), and the gradient must be free to correct that; with one camera the gradient
/// also drifts wherever it is free to. Measured at 1, 2 and 3 spacings: human-mono (seed 0)
/// 0.90 / 2.71 / 5.09 degrees, dog-sun 7.51 / 2.72 / 2.60; at 2, human-mono seeds 1 and 2:
/// 1.02 and 1.01.
pub const SUN_CONE_SPACINGS: f64 = 2.0;

/// The light with its sun direction rotated back onto the cone of half-angle `angle` around
/// `axis` when a step took it outside (ambient and shadow density untouched).
fn keep_in_cone(mut light: FittedLight, axis: glam::DVec3, angle: f64, device: &Device) -> FittedLight {
    let values = light.vector.val().into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default();
    if values.len() != 3 {
        return light;
    }
    let v = glam::DVec3::new(values[0] as f64, values[1] as f64, values[2] as f64);
    let axis = axis.normalize();
    if v.length() < 1e-12 || v.normalize().dot(axis) >= angle.cos() {
        return light;
    }
    // Rotate within the plane of axis and v, to the cone's edge, keeping v's length.
    let across = v - axis * v.dot(axis);
    let side = if across.length() > 1e-12 { across.normalize() } else { axis.any_orthonormal_vector() };
    let clamped = (axis * angle.cos() + side * angle.sin()) * v.length();
    let device = device.clone();
    light.vector = light.vector.map(|_| Tensor::from_data(TensorData::new(clamped.as_vec3().to_array().to_vec(), [3]), &device).require_grad());
    light
}

fn scalar(t: &Tensor<1>) -> f64 {
    t.clone().into_data().convert::<f32>().try_to_vec::<f32>().ok().and_then(|v| v.first().copied()).unwrap_or(f32::NAN) as f64
}

/// The path (`field.hidden.0.weight`, ...) of the first parameter holding a NaN or an
/// infinity: the update that put it there must not reach a checkpoint.
pub fn first_non_finite<M: Module>(module: &M) -> Option<String> {
    #[derive(Default)]
    struct Finder {
        path: Vec<String>,
        found: Option<String>,
    }
    impl burn::module::ModuleVisitor for Finder {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            if self.found.is_some() {
                return;
            }
            let values = param.val().into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default();
            if values.iter().any(|v| !v.is_finite()) {
                self.found = Some(self.path.iter().filter(|p| !p.is_empty()).cloned().collect::<Vec<_>>().join("."));
            }
        }
    }
    let mut finder = Finder::default();
    module.visit(&mut finder);
    finder.found
}

impl Trainer {
    pub fn new(scene: Scene, schedule: Schedule, backend: Backend, seed: u64) -> Result<Self, FitError> {
        let device = backend.device();
        device.seed(seed);
        let training: Vec<usize> = (0..scene.views.len()).filter(|&i| scene.views[i].split == Split::Train).collect();
        if training.is_empty() {
            return Err(FitError::Input(format!("{}: no training images (split \"train\")", scene.root.join("scene.json").display())));
        }
        // Masks that hold no body anywhere (a segmenter that found nothing, inverted masks
        // saved as black) would fit an empty avatar without a word.
        let masked = |i: &usize| scene.views[*i].mask.as_ref().is_some_and(|m| m.foreground.iter().any(|&f| f));
        if !training.iter().any(masked) {
            return Err(FitError::Input(format!(
                "{}: images[*].mask: none of the {} training masks marks any pixel as body (value > 127): check the masks (inverted? empty?)",
                scene.root.join("scene.json").display(),
                training.len()
            )));
        }
        let lights = scene.training_lights();
        let kind_of = |light: &Light| match light {
            Light::Directional { .. } => LightKind::Directional,
            Light::Point { .. } => LightKind::Point,
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
            let first = kind_of(&scene.lights[lights[0]]);
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
                    scene.lights[lights[0]].type_name(),
                    scene.lights[*name].type_name(),
                )));
            }
        }
        let light = &scene.lights[lights[0]];
        let light_kind = kind_of(light);
        let view_light: Vec<Option<usize>> =
            scene.views.iter().map(|v| if v.split == Split::Train { lights.iter().position(|n| *n == v.light) } else { None }).collect();
        let light_count = lights.len();
        let fit_light = schedule.check_against(light.casts_shadows())?;
        let light_kind = if fit_light { light_kind } else { LightKind::Uniform };
        let mut frames: Vec<FrameData> = Vec::new();
        for &v in &training {
            let f = scene.views[v].frame;
            match frames.iter_mut().find(|d| d.position == f) {
                Some(d) => d.views.push(v),
                None => frames.push(FrameData { position: f, pose_tensors: PoseTensors::new(&scene.frames[f].pose, &scene.skeleton, &device), views: vec![v] }),
            }
        }
        let mut views: Vec<ViewData> = scene
            .views
            .iter()
            .map(|v| ViewData {
                foreground: v.mask.as_ref().map(|m| (0..m.foreground.len()).filter(|&k| m.foreground[k]).collect()).unwrap_or_default(),
                boundary: v.mask.as_ref().map(|m| boundary_pixels(m, BOUNDARY_BAND)).unwrap_or_default(),
                error_map: None,
            })
            .collect();
        let extent = scene.body_extent();
        let unit = crate::skeleton::body_length(1.0, extent);
        // Four Gaussians per bone, 5 cm wide on the reference human.
        let mut set = GaussianSet::along_bones(&scene.skeleton, 4, GAUSSIAN_START_WIDTH * unit, 10.0);
        let (lo, hi) = scene
            .frames
            .iter()
            .map(|f| f.pose.bounds(&scene.skeleton))
            .fold((glam::DVec3::splat(f64::INFINITY), glam::DVec3::splat(f64::NEG_INFINITY)), |a, b| (a.0.min(b.0), a.1.max(b.1)));
        let centre = (lo + hi) * 0.5;
        // A point light starts above the body (the light search moves it before it is used).
        let initial = match light_kind {
            LightKind::Point => (centre + glam::DVec3::Y * (LAMP_START_PER_EXTENT * extent)).as_vec3().to_array(),
            _ => [0.0, 1.0, 0.0],
        };
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
        if error_rays > 0.0 {
            for (data, view) in views.iter_mut().zip(&scene.views) {
                if let (Some(mask), Split::Train) = (&view.mask, view.split) {
                    data.error_map = Some(crate::error_map::ErrorMap::new(mask.width, mask.height));
                }
            }
        }
        let model = Avatar {
            field: field_config.init(&device, seed),
            gaussians: GaussianParams::from_set(&set, unit as f32, &device),
            light: FittedLight::new(light_kind, initial, centre.as_vec3().to_array(), extent, 0.3, &device),
            // The first light fixes the scale the albedo cannot be told apart from (a sun's
            // irradiance 1, the ambient's target): the others' strengths are learned relative
            // to it.
            other_lights: (1..light_count)
                .map(|_| FittedLight::new(light_kind, initial, centre.as_vec3().to_array(), extent, 0.3, &device).with_learned_strength())
                .collect(),
        };
        let reference = frames.first().map(|f| &scene.frames[f.position].pose);
        let mean_targets = mean_targets(&set.gaussians.iter().map(|g| g.bone).collect::<Vec<_>>(), &anchors, root, reference, &scene.skeleton, &device);
        // Feature tables get tiny, sparse gradients: Adam's epsilon must not swamp them
        // (instant-NGP uses 1e-15).
        let optimizers = crate::schedule::GROUPS
            .iter()
            .map(|&g| (g.to_string(), if g == "features" { AdamConfig::new().with_epsilon(1e-15).init() } else { AdamConfig::new().init() }))
            .collect();
        let footprint_estimate = scene.footprint();
        let footprint = schedule.footprint.unwrap_or(footprint_estimate.footprint);
        Ok(Self {
            scene,
            schedule,
            device,
            model: Some(model),
            optimizers,
            frames,
            views,
            fit_light,
            light_kind,
            iteration: 0,
            seed,
            stream: Stream::new(seed, 0x7AA1, 0),
            gradient: crate::field::GRADIENT,
            render_missed_rays: false,
            render_threads: rayon::current_num_threads(),
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
            average: None,
            error_rays,
            density_at_shadow_scale,
        })
    }

    /// Each training view's error map (`Schedule::error_rays`) by the view's index: what a
    /// checkpoint keeps so that a resumed fit draws its rays as the uninterrupted one does.
    pub fn error_maps(&self) -> Vec<(usize, Vec<f32>)> {
        self.views.iter().enumerate().filter_map(|(v, d)| d.error_map.as_ref().map(|m| (v, m.errors().to_vec()))).collect()
    }

    /// Restores `error_maps`' output; refused when a view has no map or a map's size differs.
    pub fn set_error_maps(&mut self, maps: Vec<(usize, Vec<f32>)>) -> Result<(), String> {
        for (v, errors) in maps {
            let map = self.views.get_mut(v).and_then(|d| d.error_map.as_mut()).ok_or_else(|| format!("view {v} has no error map in this fit"))?;
            map.set_errors(errors).map_err(|e| format!("view {v}: {e}"))?;
        }
        Ok(())
    }

    /// Runs the grid's lookup as the composite of tensor ops instead of the fused op (for the
    /// step benchmark's comparison; a no-op for the `mlp` field).
    pub fn set_composite_lookup(&mut self, composite: bool) {
        if let Some(grid) = self.model.as_mut().and_then(|m| m.field.grid.as_mut()) {
            grid.composite = composite;
        }
    }

    /// The current model (it is only out of the trainer while a step runs).
    /// `Scene::training_identity` of the trainer's scene, hashed on first use.
    pub fn training_identity(&self) -> &str {
        self.training_identity.get_or_init(|| self.scene.training_identity())
    }

    /// The model being trained: the last step's parameters.
    pub fn model(&self) -> Result<&Avatar, FitError> {
        self.model.as_ref().ok_or_else(|| FitError::Input("the model was lost by an interrupted step".into()))
    }

    /// The model a fit shows (checkpoint, renders, evaluation): the last step's, its field's
    /// parameters replaced by their moving average once that has started.
    pub fn fitted_model(&self) -> Result<Avatar, FitError> {
        let mut model = self.model()?.clone();
        if let Some(average) = &self.average {
            model.field =
                average.applied(model.field).ok_or_else(|| FitError::Input("the field's parameter average does not match the field's layout".into()))?;
        }
        Ok(model)
    }

    /// Moves the field's average toward the parameters of the step just taken, or starts it at
    /// them on the first step of the learning rates' decay (`field_average_half_life`).
    fn update_average(&mut self) {
        let half_life = self.schedule.field_average_half_life;
        let Some(model) = self.model.as_ref() else { return };
        if half_life <= 0.0 || self.iteration <= self.schedule.field_lr_decay_from {
            return;
        }
        match &mut self.average {
            Some(average) => average.update(&model.field, crate::averaging::ParameterAverage::keep_for_half_life(half_life)),
            None => self.average = Some(crate::averaging::ParameterAverage::start(&model.field)),
        }
    }

    /// Moves every Gaussian to the bone that keeps it inside the body. A Gaussian starts on a
    /// bone and fits the field's density wherever that is, so loose clothing is first reached
    /// by the Gaussians of whatever bone is near (a skirt's by the hands' and thighs'); bound
    /// to a bone that does not carry it, it swings off the body in other poses, casting
    /// shadows and bounding samples where the body is not. Each Gaussian's mean, as placed in
    /// the first training frame, is carried rigidly by every bone in turn through up to
    /// `SEARCH_FRAMES` training frames, and scored by how far outside the field's surface it
    /// ends on average. Among the bones within `REBIND_TOLERANCE` of the best, it stays on its
    /// own if it is one, else goes to the one nearest it; but a bone keeps at least one of its
    /// Gaussians (`keep_every_bone`). Returns how many moved.
    pub fn rebind_gaussians(&mut self) -> Result<usize, FitError> {
        let model = self.model.as_ref().ok_or_else(|| FitError::Input("the model was lost by an interrupted step".into()))?;
        let set = model.gaussians.to_set();
        let bone_count = self.scene.skeleton.len();
        let count = self.frames.len().clamp(1, Self::SEARCH_FRAMES);
        let reference = self.rebinding_reference().cloned().ok_or_else(|| FitError::Input("no training frame to rebind the Gaussians in".into()))?;
        let placed: Vec<glam::DVec3> = set.pose(&reference).iter().map(|g| g.mean).collect();
        // outside[g][b]: the mean distance outside the surface of Gaussian g carried by bone b.
        let mut outside = vec![vec![0.0f64; bone_count]; set.len()];
        for k in 0..count {
            let data = &self.frames[k * self.frames.len() / count];
            let pose = &self.scene.frames[data.position].pose;
            // Each bone's motion from the reference frame to this one.
            let motion: Vec<glam::DMat4> = (0..bone_count).map(|b| pose.bone_to_world[b] * reference.bone_to_world[b].inverse()).collect();
            let carried: Vec<f32> = placed.iter().flat_map(|&x| motion.iter().flat_map(move |m| m.transform_point3(x).as_vec3().to_array())).collect();
            let n = carried.len() / 3;
            let points = Tensor::<2>::from_data(TensorData::new(carried, [n, 3]), &self.device);
            let sdf = model.field.sdf(points, &data.pose_tensors).into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default();
            for (i, d) in sdf.iter().enumerate() {
                outside[i / bone_count][i % bone_count] += (*d as f64).max(0.0) / count as f64;
            }
        }
        let tolerance = REBIND_TOLERANCE * self.body_unit();
        let bones: Vec<usize> = set
            .gaussians
            .iter()
            .enumerate()
            .map(|(g, gaussian)| {
                let best = outside[g].iter().copied().fold(f64::INFINITY, f64::min);
                let near_best = |b: usize| outside[g][b] <= best + tolerance;
                if near_best(gaussian.bone) {
                    return gaussian.bone;
                }
                let distance = |b: usize| reference.distance_to_bone(&self.scene.skeleton, b, placed[g]);
                (0..bone_count).filter(|&b| near_best(b)).min_by(|&a, &b| distance(a).total_cmp(&distance(b))).unwrap_or(gaussian.bone)
            })
            .collect();
        let current: Vec<usize> = set.gaussians.iter().map(|g| g.bone).collect();
        let bones = keep_every_bone(bones, &current, &outside);
        let moved = bones.iter().zip(&set.gaussians).filter(|(b, g)| **b != g.bone).count();
        if moved > 0 {
            if let Some(model) = self.model.as_mut() {
                model.gaussians.rebind(&bones, &reference);
            }
            self.mean_targets = mean_targets(&bones, &self.anchors, self.loose_root, self.rebinding_reference(), &self.scene.skeleton, &self.device);
        }
        Ok(moved)
    }

    /// Sets the Gaussians' bones (from a checkpoint's `state.json`), checked against the set's
    /// size and the skeleton.
    pub fn set_gaussian_bones(&mut self, bones: &[usize]) -> Result<(), String> {
        let bone_count = self.scene.skeleton.len();
        let model = self.model.as_mut().ok_or("no model")?;
        if bones.len() != model.gaussians.len() {
            return Err(format!("expected {} Gaussians' bones, found {}", model.gaussians.len(), bones.len()));
        }
        if let Some(b) = bones.iter().find(|&&b| b >= bone_count) {
            return Err(format!("bone {b} is not in the skeleton's {bone_count}"));
        }
        model.gaussians.bones = bones.to_vec();
        self.mean_targets = mean_targets(bones, &self.anchors, self.loose_root, self.rebinding_reference(), &self.scene.skeleton, &self.device);
        Ok(())
    }

    /// Samples a batch of pixels from one random training frame, all from its views under one
    /// training light, each pixel as the ray through its centre.
    fn batch(&mut self, set: &GaussianSet) -> Batch {
        let frame = self.stream.below(self.frames.len());
        let data = &self.frames[frame];
        // With several lights, the light of a random view of the frame (so each light is drawn
        // as often as it lights training images), and only its views.
        let (light, same_light): (usize, Vec<usize>) = if self.cones.len() > 1 {
            let first = data.views[self.stream.below(data.views.len())];
            let light = self.view_light[first].unwrap_or(0);
            (light, data.views.iter().copied().filter(|&v| self.view_light[v] == Some(light)).collect())
        } else {
            (0, data.views.clone())
        };
        let pose = &self.scene.frames[data.position].pose;
        let posed = set.pose(pose);
        let pixel_count = self.schedule.rays_per_batch.max(1);
        let mut drawn = Vec::with_capacity(pixel_count);
        let mut colours = Vec::with_capacity(pixel_count * 3);
        let mut masks = Vec::with_capacity(pixel_count);
        let mut sources = Vec::with_capacity(pixel_count);
        for k in 0..pixel_count {
            let v = same_light[self.stream.below(same_light.len())];
            let view = &self.scene.views[v];
            let camera = &self.scene.cameras[view.camera];
            let pixels = camera.width * camera.height;
            // A third each from the foreground, the silhouette's band and the whole view.
            let pool = match k % 3 {
                0 => &self.views[v].foreground,
                1 => &self.views[v].boundary,
                _ => &Vec::new(),
            };
            let j = k / 3;
            // Of the third drawn anywhere, every (1 / error_rays)-th where the fit is wrong.
            let by_error = k % 3 == 2 && takes_share(j, self.error_rays);
            let wrong = match &self.views[v].error_map {
                Some(map) if by_error => Some(map.draw(self.stream.uniform(), self.stream.uniform())),
                _ => None,
            };
            let pixel = match wrong {
                Some(p) => p,
                None if pool.is_empty() => self.stream.below(pixels),
                None => pool[self.stream.below(pool.len())],
            };
            let mask = view.mask.as_ref().map(|m| m.foreground[pixel] as u8 as f32).unwrap_or(0.0);
            let ray = camera.pixel_ray(pixel % camera.width, pixel / camera.width);
            let bounds = ray_bounds(ray.origin, ray.direction, &posed, self.min_bound_radius());
            drawn.push((ray, bounds, view.colour.pixels[pixel], mask));
            sources.push((v, pixel, wrong.is_some()));
        }
        // A stable partition: hits first, in the order drawn.
        let hits = drawn.iter().filter(|d| d.1.is_some()).count();
        let mut order: Vec<usize> = (0..drawn.len()).collect();
        order.sort_by_key(|&d| drawn[d].1.is_none());
        let mut rays = RaySet::default();
        for &d in &order {
            let (ray, bounds, _, _) = &drawn[d];
            rays.push(ray.origin, ray.direction, *bounds);
        }
        // One ray per pixel: the targets follow the rays' order.
        for &d in &order {
            colours.extend(drawn[d].2);
            masks.push(drawn[d].3);
        }
        let sources = order.iter().map(|&d| sources[d]).collect();
        Batch { frame, light, rays, hits, colours, masks, sources }
    }

    /// The body's length unit: `skeleton::body_length(1, extent)`.
    fn body_unit(&self) -> f64 {
        crate::skeleton::body_length(1.0, self.body_extent)
    }

    /// The pose the Gaussians are rebound in (`rebind_gaussians`): the first training frame's.
    fn rebinding_reference(&self) -> Option<&crate::skeleton::Pose> {
        self.frames.first().map(|f| &self.scene.frames[f.position].pose)
    }

    /// How many Gaussians were seeded on loose body (`seeds_on_loose_body`).
    pub fn loose_gaussians(&self) -> usize {
        self.anchors.iter().filter(|a| a.is_some()).count()
    }

    /// Drops the Gaussians seeded on loose body: a run fitted before they were seeded has
    /// only the bones' (`count` of them).
    pub fn without_loose_gaussians(&mut self, count: usize) -> Result<(), String> {
        let seeded = self.loose_gaussians();
        let model = self.model.as_mut().ok_or("no model")?;
        if count + seeded != model.gaussians.len() {
            return Err(format!("{count} Gaussians recorded, this scene starts {} ({seeded} on loose body)", model.gaussians.len()));
        }
        let mut set = model.gaussians.to_set();
        set.gaussians.truncate(count);
        model.gaussians = GaussianParams::from_set(&set, model.gaussians.unit, &self.device);
        self.anchors.truncate(count);
        let bones = model.gaussians.bones.clone();
        self.mean_targets = mean_targets(&bones, &self.anchors, self.loose_root, self.rebinding_reference(), &self.scene.skeleton, &self.device);
        Ok(())
    }

    /// The least radius of a Gaussian's bound on this body.
    fn min_bound_radius(&self) -> f64 {
        crate::render::MIN_BOUND_RADIUS * self.body_unit()
    }

    fn random_indices(&mut self, count: usize, below: usize) -> Tensor<1, Int> {
        let idx: Vec<i64> = (0..count).map(|_| self.stream.below(below) as i64).collect();
        Tensor::from_data(TensorData::new(idx, [count]), &self.device)
    }

    /// Training frames for the sun search: up to this many, evenly spread over the capture.
    const SEARCH_FRAMES: usize = 8;
    /// Foreground rays per search frame.
    const SEARCH_RAYS: usize = 256;

    /// Searches every training light (`search_one`).
    fn search_lights(&mut self) -> Result<(), FitError> {
        for k in 0..self.cones.len() {
            self.search_one(k)?;
        }
        Ok(())
    }

    /// Scores sun directions over the sphere (or point light positions around the body) on
    /// surface samples of several frames under training light `k` (with the Gaussians' cast
    /// shadows) and starts that light from the best (`sun_search`).
    fn search_one(&mut self, light: usize) -> Result<(), FitError> {
        let model = self.model()?.valid();
        let device = self.device.clone().without_autodiff();
        let set = model.gaussians.to_set();
        let count = self.frames.len().clamp(1, Self::SEARCH_FRAMES);
        let mut samples = Vec::new();
        let mut casters = Vec::new();
        for k in 0..count {
            let data = &self.frames[k * self.frames.len() / count];
            let pose = &self.scene.frames[data.position].pose;
            // Bounds and shadows from the Gaussians as the light casts them (density scaled).
            let posed = model.light_at(light).shadow_casters_posed(&set.pose(pose));
            let views: Vec<usize> = data.views.iter().copied().filter(|&v| self.view_light[v] == Some(light)).collect();
            if views.is_empty() {
                continue;
            }
            let mut rays = RaySet::default();
            let mut colours = Vec::new();
            for _ in 0..Self::SEARCH_RAYS {
                let v = views[self.stream.below(views.len())];
                let pool = &self.views[v].foreground;
                if pool.is_empty() {
                    continue;
                }
                let pixel = pool[self.stream.below(pool.len())];
                let view = &self.scene.views[v];
                let camera = &self.scene.cameras[view.camera];
                let ray = camera.pixel_ray(pixel % camera.width, pixel / camera.width);
                if let Some(bounds) = ray_bounds(ray.origin, ray.direction, &posed, self.min_bound_radius()) {
                    rays.push(ray.origin, ray.direction, Some(bounds));
                    colours.push(view.colour.pixels[pixel]);
                }
            }
            if rays.is_empty() {
                continue;
            }
            let sampling = self.schedule.sampling();
            let jitter: Vec<f32> = (0..rays.len() * sampling.draws()).map(|_| self.stream.uniform() as f32).collect();
            let pose_tensors = PoseTensors::new(pose, &self.scene.skeleton, &device);
            let deferred = render(&model.field, &pose_tensors, &rays, sampling, &jitter, Some(self.gradient), &device);
            let host = |t: Tensor<2>| t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default();
            let accumulation = deferred.accumulation.into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default();
            let (points, albedo) = (host(deferred.surface), host(deferred.albedo));
            let normals = deferred.normal.map(host).unwrap_or_default();
            let frame = casters.len();
            for (i, colour) in colours.iter().enumerate() {
                // Only rays that found the surface: a grazing ray's point and normal are blends.
                if accumulation.get(i).is_none_or(|a| *a < 0.9) || normals.len() < 3 * (i + 1) || points.len() < 3 * (i + 1) {
                    continue;
                }
                let three = |v: &[f32]| [v[3 * i], v[3 * i + 1], v[3 * i + 2]];
                let n = three(&normals);
                let length = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                if length.is_nan() || length <= 1e-6 {
                    continue;
                }
                samples.push(crate::sun_search::SurfaceSample {
                    frame,
                    point: three(&points),
                    normal: n.map(|c| c / length),
                    albedo: three(&albedo),
                    colour: *colour,
                });
            }
            casters.push(crate::shadow::ShadowCaster::new(&posed, 1e-3));
        }
        if samples.is_empty() {
            return Ok(());
        }
        let start = model.light_at(light).shadow_start;
        let report = match self.light_kind {
            LightKind::Point => {
                let directions = (self.schedule.sun_search / 2).max(1);
                crate::sun_search::search_point(&samples, &casters, self.body_centre, self.body_extent, directions, 32, start)
            }
            _ => crate::sun_search::search(&samples, &casters, self.schedule.sun_search, 64, start),
        };
        let mut model = self.model.take().ok_or_else(|| FitError::Input("the model was lost by an interrupted step".into()))?;
        let device = self.device.clone();
        let vector = match report.best.position {
            Some(position) => position.map(|c| (c / self.body_unit()) as f32),
            None => report.best.direction.map(|c| c as f32),
        };
        // The search's strength as the light's: a point light's as its irradiance at the
        // body's centre; a sun's (after the first, whose irradiance is the scale) relative to
        // the first sun's.
        let log_strength = match (report.best.position, self.searches.first().and_then(|s| s.as_ref())) {
            (Some(p), _) => Some(report.best.strength / (glam::DVec3::from_array(p) - self.body_centre).length().max(1e-6).powi(2)),
            (None, Some(first)) if light > 0 => Some(report.best.strength / first.best.strength),
            _ => None,
        }
        .filter(|s| s.is_finite() && *s > 0.0)
        .map(|s| s.ln() as f32);
        let target = model.light_at_mut(light);
        // The same parameter (its id keys the optimizer's state), a new value.
        target.vector = target.vector.clone().map(|_| Tensor::from_data(TensorData::new(vector.to_vec(), [3]), &device).require_grad());
        if let Some(log) = log_strength {
            target.log_intensity = target.log_intensity.clone().map(|_| Tensor::from_data(TensorData::new(vec![log], [1]), &device).require_grad());
        }
        self.model = Some(model);
        if self.light_kind == LightKind::Directional {
            // Gradient descent refines the direction within SUN_CONE_SPACINGS lattice spacings
            // of the search's best and no farther: with one camera it otherwise slides back to
            // the minimum the search escaped.
            let spacing = (4.0 / self.schedule.sun_search as f64).sqrt();
            self.cones[light] = Some((glam::DVec3::from_array(report.best.direction), spacing * SUN_CONE_SPACINGS));
        }
        self.searches[light] = Some(report);
        Ok(())
    }

    /// One iteration: forward, losses, backward, an Adam step per group.
    pub fn step(&mut self) -> Result<StepStats, FitError> {
        let start = Instant::now();
        let mut clock = PhaseClock::start();
        let it = self.iteration;
        if it == self.schedule.light_from && self.fit_light && self.light_kind != LightKind::Uniform && self.schedule.sun_search > 0 {
            self.search_lights()?;
            clock.mark(0);
        }
        let every = self.schedule.rebind_every;
        if every > 0 && it > 0 && it % every == 0 && it <= self.schedule.light_from && self.schedule.weight("density", it) > 0.0 {
            self.rebind_gaussians()?;
        }
        let set = self.model()?.gaussians.to_set();
        let Batch { frame, light: light_index, rays, hits, colours, masks, sources } = self.batch(&set);
        clock.mark(1);
        let r = rays.len();
        // Only rays that meet a bound are rendered (at least one, so the graph is never empty);
        // the rest are appended as background.
        let rendered = if self.render_missed_rays { r } else { hits.max(1) };
        let sampling = self.schedule.sampling();
        let s = sampling.total();
        let jitter: Vec<f32> = (0..rendered * sampling.draws()).map(|_| self.stream.uniform() as f32).collect();
        let device = self.device.clone();
        let pose = self.frames[frame].pose_tensors.clone();
        let schedule = self.schedule.clone();
        let w = |name: &str| schedule.weight(name, it);
        let mut model = self.model.take().ok_or_else(|| FitError::Input("the model was lost by an interrupted step".into()))?;
        // Coarse-to-fine protects the light's recovery: without a light to fit, every level
        // works from the start.
        if let Some(grid) = model.field.grid.as_mut() {
            grid.active_levels = if self.fit_light { self.schedule.active_levels(grid.config.levels, it) } else { grid.config.levels as f32 };
        }
        let shading = self.fit_light && w("rgb") > 0.0;
        let (deferred, forks) =
            render_in_parts(&model.field, &pose, &rays.first(rendered), sampling, &jitter, shading.then_some(self.gradient), &device, self.render_threads);
        clock.mark_render(&deferred);
        let background = |t: Tensor<2>| if rendered < r { Tensor::cat(vec![t, Tensor::zeros([r - rendered, 3], &device)], 0) } else { t };
        let accumulation = if rendered < r {
            Tensor::cat(vec![deferred.accumulation.clone(), Tensor::zeros([r - rendered], &device)], 0)
        } else {
            deferred.accumulation.clone()
        };
        // One ray a pixel, in the targets' order.
        let pixels = masks.len();
        let albedo = background(deferred.albedo.clone());
        let target: Tensor<2> = Tensor::from_data(TensorData::new(colours, [pixels, 3]), &device);
        let mask: Tensor<1> = Tensor::from_data(TensorData::new(masks.clone(), [pixels]), &device);
        // The Gaussians posed in the graph only when a loss reaches them: burn registers every
        // operation on a parameter in the parameter's graph, and what no backward consumes stays
        // there, swept at every backward: 300 steps of an unused posing piled up 18,000 nodes,
        // and the first stage's steps took up to twice as long.
        let density = w("density") > 0.0 && self.schedule.density_points > 0;
        let posed = density.then(|| model.gaussians.posed(&pose));
        let mut terms: Vec<(&str, f64, Tensor<1>)> = Vec::new();
        let mut colour_error: Option<Tensor<1>> = None;
        if w("rgb") > 0.0 {
            let colour = match &deferred.normal {
                // The shadows cast by the Gaussians' values: they learn only from their fit to
                // the field's density.
                Some(normal) => {
                    let casters = model.gaussians.posed_values(&pose);
                    let batch_light = model.light_at(light_index);
                    // The pixels drawn where the fit is wrong teach the light nothing: it learns
                    // from the same pixels as a batch without them.
                    let error_drawn = sources.iter().any(|s| s.2);
                    let weights = error_drawn.then(|| {
                        let ray_weights: Vec<f32> = sources.iter().take(rendered).map(|source| if source.2 { 0.0 } else { 1.0 }).collect();
                        Tensor::<1>::from_data(TensorData::new(ray_weights, [rendered]), &device)
                    });
                    background(batch_light.shade_weighted(deferred.albedo.clone(), deferred.surface.clone(), normal.clone(), &casters, weights.as_ref()))
                }
                None => albedo.clone(),
            };
            if self.error_rays > 0.0 {
                colour_error = Some((colour.clone().detach() - target.clone()).abs().mean_dim(1).reshape([pixels]));
            }
            terms.push(("rgb", w("rgb"), crate::losses::rgb(colour, target)));
        }
        clock.mark(5);
        if self.error_rays > 0.0 {
            // Each pixel's error (coverage, and colour once it is fitted) into its view's map.
            let coverage = (accumulation.clone().detach() - mask.clone()).abs();
            let error = match colour_error {
                Some(c) => coverage + c,
                None => coverage,
            };
            let error = error.into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default();
            for (&(v, pixel, _), e) in sources.iter().zip(error) {
                if let Some(map) = self.views.get_mut(v).and_then(|d| d.error_map.as_mut()) {
                    map.record(pixel, e);
                }
            }
        }
        terms.push(("mask", w("mask"), crate::losses::mask(accumulation, mask.clone())));
        if w("grey") > 0.0 {
            terms.push(("grey", w("grey"), crate::losses::grey(albedo, mask)));
        }
        if let Some(posed) = &posed {
            let idx = self.random_indices(self.schedule.density_points, rendered * s);
            let points = deferred.sample_points.clone().detach().select(0, idx.clone());
            // The Gaussians' amplitudes are optical density per body unit.
            let field_density = deferred.sample_density.clone().detach().select(0, idx) * model.light.unit;
            let mixture = GaussianParams::mixture_density(posed, points);
            // Also at the density the shadows are cast with, when asked (the first light's
            // scale, detached: the light does not learn from how well the Gaussians fit): the
            // first term keeps the body opaque to them, the second fits away the faint tails
            // outside it that a shadow sees at the light's scale.
            let fit = if self.density_at_shadow_scale {
                let scale = model.light.density_scale().detach();
                crate::losses::density(mixture.clone(), field_density.clone()) + crate::losses::density(mixture * scale.clone(), field_density * scale)
            } else {
                crate::losses::density(mixture, field_density)
            };
            terms.push(("density", w("density"), fit));
        }
        if w("sigma") > 0.0 {
            terms.push(("sigma", w("sigma"), crate::losses::sigma(model.gaussians.scales() / model.light.unit)));
        }
        if w("mean") > 0.0 {
            terms.push(("mean", w("mean"), crate::losses::mean(model.gaussians.means.val(), self.mean_targets.clone() / model.light.unit)));
        }
        if w("ambient") > 0.0 && self.fit_light {
            // The ambient target is a fraction of the batch light's irradiance: for the first
            // light (irradiance 1, or a point light whose strength is free) its ambient itself;
            // for another sun, whose irradiance is learned, its ambient over that irradiance.
            // (The same prior on every light at every step did no better on human-suns.)
            let batch_light = model.light_at(light_index);
            let ambient = match (light_index, batch_light.kind) {
                (k, LightKind::Directional) if k > 0 => batch_light.ambient() / batch_light.irradiance(),
                _ => model.light.ambient(),
            };
            terms.push(("ambient", w("ambient"), crate::losses::ambient(ambient, self.schedule.ambient_target)));
        }
        clock.mark(6);
        let curvature = w("curvature");
        if (w("eikonal") > 0.0 || curvature > 0.0) && self.schedule.regulariser_points > 0 {
            let q = self.schedule.regulariser_points;
            let idx = self.random_indices(q, rendered * s);
            let points = deferred.sample_points.clone().detach().select(0, idx);
            let gradient = model.field.sdf_gradient(points.clone(), &pose, self.gradient);
            if w("eikonal") > 0.0 {
                terms.push(("eikonal", w("eikonal"), crate::losses::eikonal(gradient.clone())));
            }
            if curvature > 0.0 {
                let noise: Vec<f32> =
                    (0..q * 3).map(|_| ((self.stream.uniform() - 0.5) * 2.0 * self.schedule.curvature_epsilon * self.body_unit()) as f32).collect();
                let perturbed = points + Tensor::<2>::from_data(TensorData::new(noise, [q, 3]), &device);
                let g2 = model.field.sdf_gradient(perturbed, &pose, self.gradient);
                let unit = crate::render::unit_rows;
                terms.push(("curvature", curvature, crate::losses::curvature(unit(gradient), unit(g2))));
            }
        }
        let mut total = terms[0].2.clone() * terms[0].1;
        for (_, weight, value) in terms.iter().skip(1) {
            total = total + value.clone() * *weight;
        }
        let mut stats = StepStats { total: scalar(&total), terms: terms.iter().map(|(n, _, v)| (n.to_string(), scalar(v))).collect(), ..StepStats::default() };
        clock.mark(7);
        if !stats.total.is_finite() {
            let bad = stats.terms.iter().find(|(_, v)| !v.is_finite()).map(|(n, _)| format!("the {n} loss")).unwrap_or_else(|| "the total loss".into());
            self.model = Some(model);
            return Err(FitError::NonFinite { iteration: it, what: bad, checkpoint: String::new() });
        }
        let mut grads = total.backward();
        clock.mark(8);
        let light_active = self.fit_light && it >= self.schedule.light_from;
        let Avatar { mut field, gaussians, light, mut other_lights } = model;
        // Only the batch's light was in the graph: it alone takes a step.
        let mut light = if light_index == 0 { light } else { std::mem::replace(&mut other_lights[light_index - 1], light) };
        // A grid's feature tables have their own learning rate and optimizer.
        let grid = field.grid.take();
        // The forks that rendered parts of the batch on other threads hold gradients of the
        // same parameters: summed into the field's.
        let mut fork_grids = Vec::new();
        let fork_fields: Vec<AvatarField> = forks
            .into_iter()
            .map(|mut fork| {
                fork_grids.extend(fork.grid.take());
                fork
            })
            .collect();
        let g_grid = grid.as_ref().map(|g| sum_gradients(&mut grads, g, &fork_grids));
        let g_field = sum_gradients(&mut grads, &field, &fork_fields);
        let g_gaussians = GradientsParams::from_module(&mut grads, &gaussians);
        let g_light = GradientsParams::from_module(&mut grads, &light);
        let lr = |g: &str| self.schedule.learning_rate(g, it);
        let (lr_field, lr_gaussians, lr_light, lr_features) = (lr("field"), lr("gaussians"), lr("light"), lr("features"));
        let mut field = self.optimizers[0].1.step(lr_field, field, g_field);
        field.grid = match (grid, g_grid) {
            (Some(grid), Some(g)) => Some(self.optimizers[3].1.step(lr_features, grid, g)),
            (grid, _) => grid,
        };
        let gaussians = self.optimizers[1].1.step(lr_gaussians, gaussians, g_gaussians);
        light = if light_active { self.optimizers[2].1.step(lr_light, light, g_light) } else { light };
        light = match self.cones[light_index] {
            Some((axis, angle)) if light_active => keep_in_cone(light, axis, angle, &self.device),
            _ => light,
        };
        if light_index > 0 {
            light = std::mem::replace(&mut other_lights[light_index - 1], light);
        }
        let model = Avatar { field, gaussians, light, other_lights };
        if self.fit_light {
            stats.light = model.light.location();
        }
        let poisoned = first_non_finite(&model);
        self.model = Some(model);
        if let Some(name) = poisoned {
            return Err(FitError::NonFinite { iteration: it, what: format!("the parameter {name} after the update"), checkpoint: String::new() });
        }
        self.iteration += 1;
        self.update_average();
        clock.mark(9);
        stats.phases = clock.spans;
        stats.seconds = start.elapsed().as_secs_f64();
        Ok(stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bone all of whose Gaussians would move keeps the one its motion carries best; bones
    /// that keep one, and moves between them, are left alone; a chain of emptied bones is
    /// undone link by link.
    #[test]
    fn rebinding_leaves_every_bone_a_gaussian() {
        // Gaussians on bones 0, 0, 1, 1, 2 (outside[g][b]: how far outside bone b carries g).
        let current = [0, 0, 1, 1, 2];
        let outside = vec![vec![0.0, 0.1, 0.2], vec![0.0, 0.1, 0.2], vec![0.1, 0.03, 0.0], vec![0.1, 0.02, 0.0], vec![0.0, 0.1, 0.1]];
        // Bone 1 would lose both: the second (0.02 outside on bone 1) stays.
        assert_eq!(keep_every_bone(vec![0, 0, 2, 2, 2], &current, &outside), vec![0, 0, 2, 1, 2]);
        // One of bone 0's moves to bone 2 and bone 2's to bone 0: each still has one.
        assert_eq!(keep_every_bone(vec![0, 2, 1, 1, 0], &current, &outside), vec![0, 2, 1, 1, 0]);
        // Bone 1's go to 2 and bone 2's to 0: bone 2 still has one (bone 1's that stays not).
        assert_eq!(keep_every_bone(vec![0, 0, 2, 2, 0], &current, &outside), vec![0, 0, 2, 1, 0]);
        // A chain: one Gaussian a bone, bone 1's to 2 and bone 2's to 0. Keeping bone 1's
        // empties bone 2, which then keeps its own.
        let outside = vec![vec![0.0; 3]; 3];
        assert_eq!(keep_every_bone(vec![0, 2, 0], &[0, 1, 2], &outside), vec![0, 1, 2]);
    }

    #[test]
    fn a_share_of_draws_is_spread_evenly() {
        for (share, expected) in [(0.0, 0), (0.25, 25), (0.5, 50), (1.0, 100)] {
            let taken: Vec<usize> = (0..100).filter(|&j| takes_share(j, share)).collect();
            assert_eq!(taken.len(), expected, "{share}");
            // Evenly: no two taken draws closer than 1 / share - 1 apart.
            if share > 0.0 {
                assert!(taken.windows(2).all(|w| (w[1] - w[0]) as f64 >= (1.0 / share).floor()), "{share}: {taken:?}");
            }
        }
    }

    #[test]
    fn seeds_cover_the_loose_body_within_their_spacing_or_stop_at_the_most() {
        // A shell of lattice points, like a skirt's hem beyond the bones.
        let points: Vec<glam::DVec3> = (0..40)
            .flat_map(|a| (0..8).map(move |h| glam::DVec3::new((a as f64 * 0.157).cos() * 0.4, -0.1 - 0.04 * h as f64, (a as f64 * 0.157).sin() * 0.4)))
            .collect();
        let spacing = 0.15;
        let seeds = seeds_on_loose_body(&points, spacing, 100);
        let gap = |p: &glam::DVec3| seeds.iter().map(|s| s.distance(*p)).fold(f64::INFINITY, f64::min);
        assert!(points.iter().all(|p| gap(p) <= spacing), "every point within the spacing of a seed");
        // No two seeds nearer than the spacing: each was the farthest point left.
        assert!(seeds.iter().enumerate().all(|(i, a)| seeds[..i].iter().all(|b| a.distance(*b) > spacing)));
        assert!(seeds.len() > 5 && seeds.iter().all(|s| points.contains(s)));
        // Capped, and the same points give the same seeds.
        assert_eq!(seeds_on_loose_body(&points, spacing, 3), seeds[..3].to_vec());
        assert!(seeds_on_loose_body(&[], spacing, 10).is_empty());
    }

    #[test]
    fn a_seeded_gaussian_is_pulled_toward_its_seed_on_whatever_bone_carries_it() {
        let schedule = crate::schedule::Schedule::parse(crate::schedule::DEFAULT_TEXT, std::path::Path::new("default.toml")).unwrap();
        let scene = Scene::load(std::path::Path::new("datasets-synthetic/human-dressed")).unwrap();
        let mut trainer = Trainer::new(scene, schedule, Backend::Flex, 0).unwrap();
        let root = trainer.loose_root.unwrap();
        let seeded = trainer.anchors.iter().position(|a| a.is_some()).unwrap();
        let anchor = trainer.anchors[seeded].unwrap();
        let target = |trainer: &Trainer, g: usize| {
            let rows = trainer.mean_targets.clone().into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
            glam::DVec3::new(rows[3 * g] as f64, rows[3 * g + 1] as f64, rows[3 * g + 2] as f64)
        };
        assert!(target(&trainer, seeded).distance(anchor) < 1e-6, "on the root: its seed");
        // Moved to the chest: the same point of space in the rebinding's pose, chest-local.
        let chest = trainer.scene.skeleton.bones.iter().position(|b| b.name == "chest").unwrap();
        let mut bones = trainer.model().unwrap().gaussians.bones.clone();
        bones[seeded] = chest;
        trainer.set_gaussian_bones(&bones).unwrap();
        let pose = trainer.rebinding_reference().unwrap().clone();
        let moved = target(&trainer, seeded);
        assert!(pose.to_world(chest, moved).distance(pose.to_world(root, anchor)) < 1e-5, "the seed's place, now on the chest");
        assert!(moved.distance(glam::DVec3::new(0.0, trainer.scene.skeleton.bones[chest].length / 2.0, 0.0)) > 0.05, "not the chest's centre");
        // A bone's own Gaussian: its bone's centre.
        let own = (0..bones.len()).find(|&g| trainer.anchors[g].is_none() && bones[g] == chest).unwrap();
        assert!(target(&trainer, own).distance(glam::DVec3::new(0.0, trainer.scene.skeleton.bones[chest].length / 2.0, 0.0)) < 1e-6);
    }
}
