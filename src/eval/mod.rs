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

use strata::*;
pub use surface::{frame_surface, surface_mesh};

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    crate::backend::host_values(t)
}

/// The light a view is rendered in.
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
    render_view_and_albedo(model, scene, camera, frame, samples, device, lighting, None, Strata::Shortcuts).0
}

/// `render_view` with each pixel's coverage by the body (0 where the image is background):
/// the image is the body over black, its colour premultiplied by that coverage.
pub fn render_view_with_coverage(
    model: &Avatar,
    scene: &Scene,
    camera: usize,
    frame: usize,
    samples: Sampling,
    device: &Device,
    lighting: &Lighting,
) -> (RgbImage, Vec<f32>) {
    let layers = render_layers(model, scene, camera, frame, samples, device, lighting, None, Strata::Shortcuts);
    (layers.image, layers.coverage)
}

/// A view's render, its albedo when asked, and each pixel's coverage by the body.
pub struct ViewLayers {
    pub image: RgbImage,
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

/// `render_view`, and with `albedo_scale` also the view's albedo (as `Lighting::Albedo` renders
/// it) from the same rays: the field is traced once for both. Over an area capture's pixels
/// the two share the pixels rendered over their area, those either needs (`needs_area`), whose
/// strata are found as `strata` says (`bench render` times both ways; a test pins one to the
/// other).
#[allow(clippy::too_many_arguments)]
pub fn render_view_and_albedo(
    model: &Avatar,
    scene: &Scene,
    camera: usize,
    frame: usize,
    samples: Sampling,
    device: &Device,
    lighting: &Lighting,
    albedo_scale: Option<DVec3>,
    strata: Strata,
) -> (RgbImage, Option<RgbImage>) {
    let layers = render_layers(model, scene, camera, frame, samples, device, lighting, albedo_scale, strata);
    (layers.image, layers.albedo)
}

/// `render_view_and_albedo` with the coverage (`ViewLayers`).
#[allow(clippy::too_many_arguments)]
fn render_layers(
    model: &Avatar,
    scene: &Scene,
    camera: usize,
    frame: usize,
    samples: Sampling,
    device: &Device,
    lighting: &Lighting,
    albedo_scale: Option<DVec3>,
    strata: Strata,
) -> ViewLayers {
    let camera_index = camera;
    let camera = &scene.cameras[camera];
    let pose = &scene.frames[frame].pose;
    let pose_tensors = crate::skeleton::PoseTensors::new(pose, &scene.skeleton, device);
    let set = model.gaussians.to_set();
    let posed = set.pose(pose);
    let gaussians = model.gaussians.posed(&pose_tensors);
    let fitted = match lighting {
        Lighting::Fitted(k) => model.light_at(*k),
        _ => &model.light,
    };
    let casters = fitted.shadow_casters(&gaussians);
    let needs_normals = match lighting {
        Lighting::Fitted(_) => model.light.kind != LightKind::Uniform,
        Lighting::Albedo { .. } => false,
        Lighting::Known { .. } => true,
    };
    // Sky light per pixel: MIS of the map and the cosine lobe, each pixel its own stream.
    let view_seed = (frame as u64) << 16 | camera_index as u64;
    let sampler = match lighting {
        Lighting::Known { light: Light::Environment { map, scale, .. }, samples, .. } => {
            Some(MisEstimator::new(map, *scale, *samples, view_seed).with_shadow_start(model.light.shadow_start))
        }
        Lighting::Known { light: Light::Uniform { radiance }, samples, .. } => {
            Some(MisEstimator::uniform(*radiance, *samples, view_seed).with_shadow_start(model.light.shadow_start))
        }
        _ => None,
    };
    let sky_casters: Vec<PosedGaussian> = model.light.shadow_casters_posed(&posed);
    let scaled =
        |albedo: Tensor<2>, scale: &DVec3| albedo * Tensor::<1>::from_data(TensorData::new(scale.as_vec3().to_array().to_vec(), [3]), device).reshape([1, 3]);
    // The colour `[N * 3]` of surface points of (premultiplied) fitted albedo `albedo` and unit
    // normals `normal` (when the light needs them) in the light asked for, each with its own
    // stream id for the sky's samples.
    let shade_all = |albedo: Tensor<2>, surface: Tensor<2>, normal: Option<Tensor<2>>, ids: &[u64]| -> Vec<f32> {
        match (lighting, normal) {
            (Lighting::Fitted(_), Some(normal)) => values(fitted.shade(albedo, surface, normal, &gaussians)),
            (Lighting::Albedo { albedo_scale }, _) => values(scaled(albedo, albedo_scale)),
            (Lighting::Known { light, albedo_scale, .. }, Some(normal)) => match (emitter(light, device), &sampler) {
                (Some((emitter, ambient)), _) => {
                    values(shade_lambertian(scaled(albedo, albedo_scale), surface, normal, &casters, ambient, &emitter, model.light.shadow_start, None))
                }
                (None, Some(sampler)) => {
                    let points = vectors(values(surface));
                    let normals = vectors(values(normal));
                    let reflectance = vectors(values(scaled(albedo, albedo_scale)));
                    let radiance = sampler.shade(&points, &normals, ids, &sky_casters);
                    reflectance.iter().zip(radiance).flat_map(|(a, l)| (*a * l).as_vec3().to_array()).collect()
                }
                (None, None) => values(albedo),
            },
            (_, _) => values(albedo),
        }
    };
    // Every light's colour is the albedo times the light it receives: a ray that carries no
    // albedo (no sample of weight `albedo_floor` or more, `render_still`) is black under any
    // light, so only the others are shaded (on a view, half its bounded rays miss the body).
    // `raw`: the albedo's values, `[N * 3]`.
    let shade = |albedo: Tensor<2>, raw: &[f32], surface: Tensor<2>, normal: Option<Tensor<2>>, ids: &[u64]| -> Vec<f32> {
        let lit: Vec<usize> = (0..ids.len()).filter(|&i| raw[3 * i..3 * i + 3].iter().any(|&a| a != 0.0)).collect();
        if lit.len() == ids.len() {
            return shade_all(albedo, surface, normal, ids);
        }
        let mut colour = vec![0.0f32; 3 * ids.len()];
        if !lit.is_empty() {
            let index = crate::render::row_index(lit.iter().copied(), device);
            let pick = |t: Tensor<2>| t.select(0, index.clone());
            let lit_ids: Vec<u64> = lit.iter().map(|&i| ids[i]).collect();
            let shaded = shade_all(pick(albedo), pick(surface), normal.map(pick), &lit_ids);
            for (j, &i) in lit.iter().enumerate() {
                colour[3 * i..3 * i + 3].copy_from_slice(shaded.get(3 * j..3 * j + 3).unwrap_or(&[f32::NAN; 3]));
            }
        }
        colour
    };
    // The colour, albedo (when asked) and coverage of rays through continuous pixel
    // positions, each with its own stream id for the sky's samples.
    // A target may carry a window of distances that holds its surface (`surface_window`): its
    // ray is then sampled there only, as `samples` says.
    let trace = |targets: &[([f64; 2], u64)], windows: &[Option<(f64, f64)>], samples: Sampling| -> Vec<Traced> {
        // Chunks of a view on every thread (views are rendered several at once too; rayon
        // shares the threads between both levels), each chunk's samples its own as before.
        let chunks: Vec<Vec<(usize, Traced)>> = targets
            .par_chunks(TRACE_CHUNK)
            .enumerate()
            .map(|(k, chunk)| {
                let first = k * TRACE_CHUNK;
                let mut out = Vec::new();
                let at: Vec<[f64; 2]> = chunk.iter().map(|t| t.0).collect();
                let windows = windows.get(first..(first + chunk.len()).min(windows.len())).unwrap_or(&[]);
                let Some((hit, deferred)) = trace_deferred(model, camera, &posed, &pose_tensors, &at, windows, samples, needs_normals, device) else {
                    return out;
                };
                let hit: Vec<usize> = hit.into_iter().map(|k| first + k).collect();
                let ids: Vec<u64> = hit.iter().map(|&k| targets[k].1).collect();
                let raw = values(deferred.albedo.clone());
                let colour = shade(deferred.albedo.clone(), &raw, deferred.surface.clone(), deferred.normal.clone(), &ids);
                let coverage = values(deferred.accumulation.clone());
                let depth = values(deferred.depth.clone());
                let albedo = albedo_scale.as_ref().map(|scale| values(scaled(deferred.albedo.clone(), scale)));
                for (j, &k) in hit.iter().enumerate() {
                    let albedo = albedo.as_ref().map_or([0.0; 3], |a| [a[j * 3], a[j * 3 + 1], a[j * 3 + 2]]);
                    let three = |v: &[f32]| [v[j * 3], v[j * 3 + 1], v[j * 3 + 2]];
                    out.push((k, Traced { colour: three(&colour), albedo, raw: three(&raw), coverage: coverage[j], depth: depth[j] }));
                }
                out
            })
            .collect();
        let mut out = vec![Traced::default(); targets.len()];
        for (k, traced) in chunks.into_iter().flatten() {
            out[k] = traced;
        }
        out
    };
    let (w, h) = (camera.width, camera.height);
    let centre = |p: usize| [(p % w) as f64 + 0.5, (p / w) as f64 + 0.5];
    let mut pixels = trace(&(0..w * h).map(|p| (centre(p), p as u64)).collect::<Vec<_>>(), &[], samples);
    // A capture whose pixels average their area: every pixel that may hold an edge is the mean
    // of the centres of its 3 x 3 strata instead (`needs_area`); elsewhere the centre is that
    // mean already, to within half an 8-bit step.
    let area = scene.footprint().footprint == Footprint::Area;
    if area {
        let offsets = crate::scene::footprint::subpixel_offsets(VIEW_PIXEL_RAYS, None);
        let coverage: Vec<f32> = pixels.iter().map(|p| p.coverage).collect();
        let encode = |c: [f32; 3]| c.map(|v| crate::imageio::linear_to_srgb(v.max(0.0)));
        let colours: Vec<[f32; 3]> = pixels.iter().map(|p| encode(p.colour)).collect();
        let albedos: Option<Vec<[f32; 3]>> = albedo_scale.map(|_| pixels.iter().map(|p| encode(p.albedo)).collect());
        let refine: Vec<usize> =
            (0..w * h).filter(|&p| needs_area(&colours, &coverage, w, h, p) || albedos.as_ref().is_some_and(|a| needs_area(a, &coverage, w, h, p))).collect();
        // Inside the body the surface a pixel's rays meet lies within its neighbours' depths:
        // those rays are sampled there, at half the cost (where they are traced at all: below);
        // at a depth step the rays search their whole bound as the centres did.
        let windows: Vec<Option<(f64, f64)>> = refine.iter().map(|&p| surface_window(&pixels, w, h, p, camera.fx)).collect();
        // Along silhouettes too, where the centres around a pixel that meet the body agree on
        // its depth (`silhouette_window`).
        let search: Vec<Option<(f64, f64)>> = refine
            .iter()
            .zip(&windows)
            .map(|(&p, window)| window.or_else(|| (strata == Strata::Shortcuts).then(|| silhouette_window(&pixels, w, h, p, camera.fx)).flatten()))
            .collect();
        // The rays of the strata `pairs` (a refined pixel's index into `refine`, a stratum), in
        // that order: in their pixel's window where it has one, through their whole bound if not.
        let trace_pairs = |pairs: &[(usize, usize)]| -> Vec<Traced> {
            let (windowed, searched): (Vec<usize>, Vec<usize>) = (0..pairs.len()).partition(|&j| search[pairs[j].0].is_some());
            let targets = |part: &[usize]| -> Vec<([f64; 2], u64)> {
                part.iter()
                    .map(|&j| {
                        let (p, s) = (refine[pairs[j].0], pairs[j].1);
                        ([(p % w) as f64 + offsets[s][0], (p / w) as f64 + offsets[s][1]], (w * h + p * VIEW_PIXEL_RAYS + s) as u64)
                    })
                    .collect()
            };
            let windows_of: Vec<Option<(f64, f64)>> = windowed.iter().map(|&j| search[pairs[j].0]).collect();
            let mut out = vec![Traced::default(); pairs.len()];
            for (part, traced) in [(&windowed, trace(&targets(&windowed), &windows_of, WINDOW_SAMPLING)), (&searched, trace(&targets(&searched), &[], samples))]
            {
                for (&j, ray) in part.iter().zip(traced) {
                    out[j] = ray;
                }
            }
            out
        };
        // A stratum is read off the centres around it (`strata_from_centres`: its surface
        // point, coverage and shading interpolated, only its albedo, where a pattern's edge
        // lies, looked up: one field evaluation instead of about 50) where its pixel's whole
        // neighbourhood lies on one smooth surface (`surface_window`, inside the body) or, along
        // a silhouette or a step, where the four centres of its quadrant lie wholly on the body,
        // on a surface nearly facing the camera (`quadrant_interpolates`).
        let smooth: Vec<bool> = refine.iter().zip(&windows).map(|(&p, window)| window.is_some() && albedo_above_floor(&pixels, w, h, p)).collect();
        let readable =
            |r: usize, s: usize| strata == Strata::Shortcuts && (smooth[r] || quadrant_interpolates(&pixels, w, h, refine[r], offsets[s], camera.fx));
        // The strata `pairs` (as `trace_pairs` takes them), each read off its centres where
        // `readable`, traced where not.
        let strata_at = |pairs: &[(usize, usize)]| -> Vec<Traced> {
            let (read, traced): (Vec<usize>, Vec<usize>) = (0..pairs.len()).partition(|&j| readable(pairs[j].0, pairs[j].1));
            let mut out = vec![Traced::default(); pairs.len()];
            let at: Vec<(usize, usize)> = read.iter().map(|&j| (refine[pairs[j].0], pairs[j].1)).collect();
            let read_off = strata_from_centres(model, camera, &pose_tensors, &pixels, w, &offsets, &at, albedo_scale, device);
            for (&j, stratum) in read.iter().zip(read_off) {
                out[j] = stratum;
            }
            for (&j, ray) in traced.iter().zip(trace_pairs(&traced.iter().map(|&j| pairs[j]).collect::<Vec<_>>())) {
                out[j] = ray;
            }
            out
        };
        // First the four corner strata: with the centre (already traced) they bound every
        // straight edge through the pixel, so where the five agree the pixel holds none and a
        // side stratum that would have to be traced is its two corners' mean instead.
        let corners = strata_at(&(0..refine.len()).flat_map(|r| CORNER_STRATA.map(|s| (r, s))).collect::<Vec<_>>());
        let agree: Vec<bool> = (0..refine.len()).map(|k| strata_agree(&pixels[refine[k]], &corners[k * 4..k * 4 + 4], albedos.is_some())).collect();
        let mut sides: Vec<Traced> = (0..refine.len()).flat_map(|k| SIDE_CORNERS.map(|(a, b)| midway(&corners[k * 4 + a], &corners[k * 4 + b]))).collect();
        // The sides found after all (a place in `sides`, a stratum): where the five disagree,
        // and wherever one is read off its centres, which costs less than a corners' mean errs.
        let found: Vec<(usize, usize)> = (0..refine.len())
            .flat_map(|r| SIDE_STRATA.into_iter().enumerate().map(move |(j, s)| (r, j, s)))
            .filter(|&(r, _, s)| !agree[r] || readable(r, s))
            .map(|(r, j, s)| (r * 4 + j, s))
            .collect();
        let pairs: Vec<(usize, usize)> = found.iter().map(|&(k, s)| (k / 4, s)).collect();
        for (&(k, _), side) in found.iter().zip(strata_at(&pairs)) {
            sides[k] = side;
        }
        let means: Vec<(usize, Traced)> =
            (0..refine.len()).map(|k| (refine[k], strata_mean(&pixels[refine[k]], &corners[k * 4..k * 4 + 4], Some(&sides[k * 4..k * 4 + 4])))).collect();
        for (p, traced) in means {
            pixels[p] = traced;
        }
    }
    // Over a pixel's area, one the body covers by half or less is background, black, as the
    // scene format's images and masks have it. (At a centre sample the opacity is not a
    // coverage but the chance the ray meets the body: there the same rule cost human-sun 0.85 dB
    // over the foreground. The expected value below gains on human-sun-128, dog-sun and
    // human-lamp and loses 0.4 dB on the 64x64 human-sun.)
    let mut image = RgbImage::new(w, h);
    let mut albedo = albedo_scale.map(|_| RgbImage::new(w, h));
    // At a centre sample the coverage is the chance the ray meets the body: the pixel is its
    // expected value in the image's encoding (`imageio::composite_centre_sample`).
    let pixel = |c: [f32; 3], coverage: f32| if area { c } else { crate::imageio::composite_centre_sample(c, coverage) };
    let mut coverage = vec![0.0; w * h];
    for (p, traced) in pixels.into_iter().enumerate() {
        if !area || traced.coverage > 0.5 {
            image.pixels[p] = pixel(traced.colour, traced.coverage);
            coverage[p] = if area { 1.0 } else { traced.coverage };
            if let Some(albedo) = albedo.as_mut() {
                albedo.pixels[p] = pixel(traced.albedo, traced.coverage);
            }
        }
    }
    ViewLayers { image, albedo, coverage }
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

/// What a ray through a view brings back: its shaded colour, its albedo (scaled; zero when not
/// asked for) and its coverage.
#[derive(Clone, Copy, Default)]
pub(super) struct Traced {
    pub(super) colour: [f32; 3],
    pub(super) albedo: [f32; 3],
    /// The fitted albedo as composited along the ray (unscaled, weighted by the coverage): the
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
