//! Rendering whole views of a fitted avatar, in its fitted light, in any light of the scene or
//! as albedo (`metrics` scores them) as the capture's images are made (a pixel is its centre or
//! the mean over its area, as `scene::footprint` reads off the training images, where a pixel
//! covered by half or less is black), and extracting its surface in a pose as a mesh: the
//! fitted SDF sampled on a grid whose cell follows the body's size (the grid field's finest
//! cell, 1/160 of the body's extent) over the posed bones' box widened by the grid's reach,
//! its zero level set by marching tetrahedra (`isosurface`), each crossing bisected on the
//! field itself.

use crate::avatar::Avatar;
use crate::environment::MisEstimator;
use crate::imageio::RgbImage;

use crate::light::Light;
use crate::render::{ray_bounds, render_still, RaySet, Sampling};
use crate::scene::{Footprint, Scene};
use crate::shading::{shade_lambertian, Emitter, LightKind};
use crate::shadow::PosedGaussian;
use crate::skeleton::PoseTensors;
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;
use rayon::prelude::*;

pub use crate::metrics::psnr_srgb8;

mod strata;
mod surface;
mod view;

pub use view::{render_view_layers, render_view_lights};

pub use surface::{coloured_frame_surface, frame_surface, surface_mesh, vertex_albedo_and_normals};

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    crate::backend::host_values(t)
}

/// The light a view is rendered in.
#[derive(Clone, Copy)]
pub enum Lighting<'a> {
    /// Fitted training light `k` (the albedo, for a uniformly lit fit).
    Fitted(usize),
    /// Shadow-free reflectance: the fitted albedo times `albedo_scale`.
    Albedo { albedo_scale: DVec3 },
    /// A light of the scene the avatar was not fitted in, with the scale that turns the fitted
    /// albedo into reflectance (`relight::albedo_scale`).
    Known { light: &'a Light, albedo_scale: DVec3, samples: usize },
}

/// How whole views are sampled for evaluation and relighting: 24 coarse samples, 8 probes
/// where they found density (the probe round that lets training find a surface as sharp as
/// beta's floor) and 16 fine ones, 48 field evaluations a ray. The 80 of 48 coarse and 32
/// fine without probes cost 1.6x the time for the same picture: on a fit of human-sun-128
/// (seed 0) foreground novel pose 26.08 against 26.09 dB, novel view 24.09 against 24.01,
/// relit 24.54 / 24.55, albedo 21.91 / 21.92; 16 coarse (as training) lost 0.07-0.09 dB.
pub const VIEW_SAMPLING: Sampling = Sampling { coarse: 24, probe: 8, fine: 16, albedo_floor: crate::render::ALBEDO_WEIGHT_FLOOR, cull: false };

/// How the rays of a refined pixel inside the body or on a silhouette are sampled within the
/// window that holds its surface (`surface_window`, `silhouette_window`): 8 coarse samples
/// (a few millimetres apart inside the body, at most about 4 cm along a silhouette), 8 probes
/// where they found density and 8 fine ones, half a whole ray's evaluations.
pub const WINDOW_SAMPLING: Sampling = Sampling { coarse: 8, probe: 8, fine: 8, albedo_floor: crate::render::ALBEDO_WEIGHT_FLOOR, cull: false };

/// Rays a view traces through the field at once: a view's chunks go to every thread.
const TRACE_CHUNK: usize = 1024;

/// Rays per pixel of a view of a capture whose pixels average their area, where the pixel may
/// hold an edge: the centres of 3 x 3 strata. Fewer rays than the 4 x 4 before, and better
/// pictures: on a fit of human-sun-128-aa (seed 0) foreground novel pose / novel view / albedo
/// 28.34 / 26.47 / 23.56 dB against 27.89 / 25.92 / 23.22 with 16 rays, and on the independent
/// renderer's quadruped-tiny 20.80 / 20.86 / 17.41 against 20.42 / 20.82 / 17.22. Grids with a
/// centre stratum do better than those without (2 x 2: 25.98, 5 x 5: 28.49 on human-sun-128-aa);
/// it is not the tie at half covered, which an even grid can hit: drawing those pixels made
/// 4 x 4 worse (26.85). 9 rays cost 0.56x the 16.
pub const VIEW_PIXEL_RAYS: usize = 9;

/// Renders the scene's `camera` in `frame`, sampled as `samples` says, under `lighting`.
pub fn render_view(model: &Avatar, scene: &Scene, camera: usize, frame: usize, samples: Sampling, device: &Device, lighting: &Lighting) -> RgbImage {
    render_view_layers(model, scene, camera, frame, samples, device, lighting, None, Strata::Shortcuts).image
}

/// A view's render, its albedo when asked, and each pixel's coverage by the body (0 where the
/// image is background: the image is the body over black, its colour premultiplied by it).
pub struct ViewLayers {
    pub image: RgbImage,
    pub albedo: Option<RgbImage>,
    pub coverage: Vec<f32>,
}

/// `ViewLayers` of a view rendered in several lights (`render_view_lights`): an image per light.
pub struct LitLayers {
    pub images: Vec<RgbImage>,
    pub albedo: Option<RgbImage>,
    pub coverage: Vec<f32>,
}

/// How a view of a capture whose pixels average their area finds the 3 x 3 strata of the pixels
/// it renders over their area (`needs_area`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Strata {
    /// Every stratum traced: inside the body within its neighbours' depths (`surface_window`),
    /// elsewhere over its ray's whole bound.
    Traced,
    /// Inside the body, where the centres around a pixel lie on one smooth surface, its strata
    /// are interpolated from them and only their albedo is looked up (`strata_from_centres`),
    /// and so are a silhouette's strata whose quadrant's centres lie wholly on the body
    /// (`quadrant_interpolates`); along silhouettes the other strata search the depths of the
    /// centres around them that meet the body (`silhouette_window`). The same pictures as
    /// `Traced` (the 148 novel-pose images of an area capture: foreground 27.43 / 22.90 dB image
    /// / albedo against 27.43 / 22.89) at 0.47x its time, before silhouettes' windows widened
    /// to `SILHOUETTE_SLOPE` and strata were read off their quadrants. What every render does.
    Shortcuts,
}

/// The rays through continuous pixel positions `at` that meet a Gaussian's bound (their
/// indices in `at`) and the field's deferred buffers along them, with unit normals when asked:
/// what every view render and the transfer basis (`basis`) start from. `None` when no ray
/// meets the body.
#[allow(clippy::too_many_arguments)]
pub fn trace_deferred(
    model: &Avatar,
    camera: &crate::scene::Camera,
    posed: &[PosedGaussian],
    pose_tensors: &PoseTensors,
    at: &[[f64; 2]],
    windows: &[Option<(f64, f64)>],
    samples: Sampling,
    normals: bool,
    device: &Device,
) -> Option<(Vec<usize>, crate::render::Deferred)> {
    let mut rays = RaySet::default();
    let mut hit = Vec::new();
    for (k, at) in at.iter().enumerate() {
        let ray = camera.ray_through(glam::DVec2::new(at[0], at[1]));
        let bounds = ray_bounds(ray.origin, ray.direction, posed, crate::render::MIN_BOUND_RADIUS * model.light.unit as f64);
        let bounds = match (bounds, windows.get(k).copied().flatten()) {
            (Some((near, far)), Some((lo, hi))) => Some((near.max(lo), far.min(hi))).filter(|(near, far)| far > near),
            (bounds, _) => bounds,
        };
        if let Some(bounds) = bounds {
            rays.push(ray.origin, ray.direction, Some(bounds));
            hit.push(k);
        }
    }
    if rays.is_empty() {
        return None;
    }
    let jitter = vec![0.5; rays.len() * samples.draws()];
    let deferred = render_still(&model.field, pose_tensors, &rays, samples, &jitter, normals.then_some(crate::field::GRADIENT), device);
    Some((hit, deferred))
}

/// One pixel's surface as a view render sees it: the composited surface point, unit normal and
/// reflectance (the fitted albedo, already weighted by the pixel's coverage, times the albedo
/// scale), and the coverage its shaded value is composited with
/// (`imageio::composite_centre_sample`): a centre sample's, or 1 for a pixel of a capture whose
/// pixels average their area (drawn as it is once covered by more than half).
#[derive(Clone, Copy, Debug)]
pub struct Surfel {
    pub point: DVec3,
    pub normal: DVec3,
    pub reflectance: DVec3,
    pub coverage: f64,
}

/// Every pixel centre's `Surfel` of one view, row by row (`None` where the ray meets no
/// Gaussian's bound, or, on a capture whose pixels average their area, where the body covers
/// half of it or less: background, as `render_view` draws it): what a view's shading needs
/// besides the light, for relighting it many times. Edges are not refined over the pixel's
/// area here.
pub fn surfels(model: &Avatar, scene: &Scene, camera: usize, frame: usize, samples: Sampling, albedo_scale: DVec3, device: &Device) -> Vec<Option<Surfel>> {
    let camera = &scene.cameras[camera];
    let pose = &scene.frames[frame].pose;
    let pose_tensors = PoseTensors::new(pose, &scene.skeleton, device);
    let posed = model.gaussians.to_set().pose(pose);
    let (w, h) = (camera.width, camera.height);
    let mut out = vec![None; w * h];
    let area = scene.footprint().footprint == Footprint::Area;
    let centres: Vec<[f64; 2]> = (0..w * h).map(|p| [(p % w) as f64 + 0.5, (p / w) as f64 + 0.5]).collect();
    for (first, chunk) in centres.chunks(1024).enumerate().map(|(k, c)| (k * 1024, c)) {
        let Some((hit, deferred)) = trace_deferred(model, camera, &posed, &pose_tensors, chunk, &[], samples, true, device) else {
            continue;
        };
        let (points, albedo, coverage) = (vectors(values(deferred.surface)), vectors(values(deferred.albedo)), values(deferred.accumulation));
        let normals = deferred.normal.map(|n| vectors(values(n))).unwrap_or_default();
        for (j, &k) in hit.iter().enumerate().filter(|(j, _)| !area || coverage[*j] > 0.5) {
            let normal = normals.get(j).copied().unwrap_or(DVec3::Z);
            let coverage = if area { 1.0 } else { coverage[j] as f64 };
            out[first + k] = Some(Surfel { point: points[j], normal, reflectance: albedo[j] * albedo_scale, coverage });
        }
    }
    out
}

/// The most lights a view's one trace is shaded in (`render_view_lights` traces again for more):
/// a test set's view is seen in a few (the training light, a second sun, a lamp, a sky).
pub const LIGHTS_PER_TRACE: usize = 4;

/// What a ray through a view brings back: its shaded colour in each light of the view (zero
/// past the view's lights), its albedo (scaled; zero when not asked for) and its coverage.
#[derive(Clone, Copy, Default)]
pub(super) struct Traced {
    pub(super) colours: [[f32; 3]; LIGHTS_PER_TRACE],
    pub(super) albedo: [f32; 3],
    /// The fitted albedo as composited along the ray (unscaled, weighted by the coverage): each
    /// colour is it times a shading term that does not depend on it (every light is Lambertian).
    pub(super) raw: [f32; 3],
    pub(super) coverage: f32,
    /// Distance along the ray to the composited surface.
    pub(super) depth: f32,
}

fn vectors(flat: Vec<f32>) -> Vec<DVec3> {
    flat.chunks(3).map(|c| DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64)).collect()
}

/// A sun or point light of the scene as an `Emitter` and its ambient; `None` for lights that
/// are not a single direction (uniform, environment).
fn emitter(light: &Light, device: &Device) -> Option<(Emitter, Tensor<1>)> {
    let t = |v: DVec3| Tensor::<1>::from_data(TensorData::new(v.as_vec3().to_array().to_vec(), [3]), device);
    match light {
        Light::Directional { direction, irradiance, ambient } => Some((Emitter::Sun { direction: t(*direction), irradiance: t(*irradiance) }, t(*ambient))),
        Light::Point { position, intensity, ambient } => Some((Emitter::Point { position: t(*position), intensity: t(*intensity) }, t(*ambient))),
        Light::Uniform { .. } | Light::Environment { .. } | Light::Unknown { .. } => None,
    }
}
