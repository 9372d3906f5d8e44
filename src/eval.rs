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
use crate::fit_error::FitError;
use crate::imageio::RgbImage;
use crate::isosurface::{bisect, extract, Grid, Mesh};
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

/// The distances along the rays within pixel `p` that hold the surface, from the centre rays
/// of its 3 x 3 neighbourhood (`pixels`, `w x h`, focal length `fx` in pixels): when every
/// one of them is wholly covered and their depths differ by at most `WINDOW_SLOPE` pixels'
/// width at that depth (no silhouette, no step in depth, no grazing surface), the surface
/// under any point of the pixel lies between their depths (a smooth surface between the
/// centres it passes through), and the window is that span widened on each side by itself or
/// one pixel's width, whichever is more. `None` otherwise: the rays search their whole bound.
fn surface_window(pixels: &[Traced], w: usize, h: usize, p: usize, fx: f64) -> Option<(f64, f64)> {
    let depths = neighbourhood(w, h, p).map(|q| {
        let q = &pixels[q];
        (q.coverage >= 1.0 - 1.0 / 255.0 && q.depth.is_finite()).then_some(q.depth as f64)
    });
    window_of(depths.collect::<Option<Vec<f64>>>()?, fx, WINDOW_SLOPE)
}

/// A window for a pixel along a silhouette (`surface_window` refuses it): where the centres
/// around it that meet the body at all (coverage above an 8-bit step) meet it within
/// `SILHOUETTE_SLOPE` pixels' widths of each other, the surface any ray through the pixel can meet
/// lies between their depths, as inside the body; the centres that miss it say only that a ray
/// there may miss it too. `None` where none meets it or where they lie on surfaces at
/// different depths (a limb before the body): those rays search their whole bound.
fn silhouette_window(pixels: &[Traced], w: usize, h: usize, p: usize, fx: f64) -> Option<(f64, f64)> {
    let depths: Vec<f64> =
        neighbourhood(w, h, p).map(|q| &pixels[q]).filter(|q| q.coverage > 1.0 / 255.0 && q.depth.is_finite()).map(|q| q.depth as f64).collect();
    window_of(depths, fx, SILHOUETTE_SLOPE)
}

/// The pixels of `p`'s 3 x 3 neighbourhood inside the image, `p` among them.
fn neighbourhood(w: usize, h: usize, p: usize) -> impl Iterator<Item = usize> {
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    (-1..=1)
        .flat_map(move |dy| (-1..=1).map(move |dx| (x + dx, y + dy)))
        .filter(move |&(i, j)| i >= 0 && j >= 0 && (i as usize) < w && (j as usize) < h)
        .map(move |(i, j)| j as usize * w + i as usize)
}

/// The window of a neighbourhood's surface depths (`surface_window`): their span widened on each
/// side by itself or one pixel's width (focal length `fx` in pixels), whichever is more, when it
/// is at most `slope` pixels' widths; `None` otherwise or without depths.
fn window_of(depths: Vec<f64>, fx: f64, slope: f64) -> Option<(f64, f64)> {
    let lo = depths.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = depths.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if depths.is_empty() {
        return None;
    }
    let pixel = hi / fx.max(1e-9);
    (hi - lo <= slope * pixel).then(|| {
        let margin = (hi - lo).max(pixel);
        (lo - margin, hi + margin)
    })
}

/// The most a window's neighbourhood's depths may differ, in pixels' widths at that depth
/// (`surface_window`): a surface tilted up to about 70 degrees from facing the camera.
const WINDOW_SLOPE: f64 = 3.0;

/// How far the depths of the four centres around a stratum may differ, in pixels' widths, for
/// the stratum to be read off them where its pixel's whole neighbourhood does not allow it
/// (`quadrant_interpolates`, along silhouettes and depth steps): a surface turned at most 14
/// degrees from the camera. Nearer grazing, a traced ray's colour is a composite over a longer
/// stretch of the surface than one lookup sees, and the fitted albedo has learnt the
/// composite: at 1 (45 degrees) `human-sun-128-aa`'s novel views lost 0.06 dB over the
/// foreground and `quadruped-tiny`'s novel poses 0.03 dB; at 0.25 neither lost 0.01 dB, and
/// the 148 images below took as long (49 s against 51).
const QUADRANT_SLOPE: f64 = 0.25;

/// `WINDOW_SLOPE` for a silhouette's window (`silhouette_window`): there the centres that meet
/// the body partly have their depth on its far, grazed side, so the depths around a pixel spread
/// more than on a surface facing the camera (on the 148 images below, most silhouette pixels
/// refused at 3 spread 3 to 16 pixels' widths). A window of 8 pixels' widths, widened by as
/// much on each side, holds 24 at most, about 30 cm on a 2 m human at 128 x 128, which the
/// window's 8 coarse samples then space no wider than a whole ray's 24 do over its bound.
/// Measured on the 148 novel-pose images of an area capture: the same scores (27.43 / 22.89
/// dB foreground image / albedo; each image within 0.3 dB), 61 s against 72 s with 3.
const SILHOUETTE_SLOPE: f64 = 8.0;

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

/// The 3 x 3 strata of a refined pixel (row-major, as `subpixel_offsets` lays them out): the
/// four corners and the middles of the four sides; the centre, 4, is the pixel's centre ray,
/// traced already.
const CORNER_STRATA: [usize; 4] = [0, 2, 6, 8];
const SIDE_STRATA: [usize; 4] = [1, 3, 5, 7];
const _: () = assert!(VIEW_PIXEL_RAYS == 9);
/// The two corners (places in `CORNER_STRATA`) each side stratum lies midway between.
const SIDE_CORNERS: [(usize, usize); 4] = [(0, 1), (0, 2), (1, 3), (2, 3)];

/// The stratum midway between strata `a` and `b`, as their mean.
fn midway(a: &Traced, b: &Traced) -> Traced {
    let mean = |x: [f32; 3], y: [f32; 3]| [0, 1, 2].map(|c| 0.5 * (x[c] + y[c]));
    Traced {
        colour: mean(a.colour, b.colour),
        albedo: mean(a.albedo, b.albedo),
        raw: mean(a.raw, b.raw),
        coverage: 0.5 * (a.coverage + b.coverage),
        depth: 0.5 * (a.depth + b.depth),
    }
}

/// How far (sRGB, every channel) a refined pixel's centre ray may lie from its four corner
/// rays' mean for its sides to be taken as their corners' means (`strata_agree`).
const STRATA_AGREE: f32 = 1.0 / 255.0;

/// Whether a refined pixel's sides may be taken from its corners: its centre ray and four
/// corner rays agree on coverage within an 8-bit step, and its colour (and albedo, when it is
/// rendered) is bilinear over the pixel to within `STRATA_AGREE`: the centre lies that close
/// to the corners' mean. A ramp (a shading gradient, a blurred border) passes; a straight
/// sharp edge (a silhouette, a checker's border, a shadow's) that crosses any of the 3 x 3
/// strata does not: it splits the corners from each other (one from three leaves the centre
/// a quarter of the contrast from their mean, two from two half of it) or from the centre.
fn strata_agree(centre: &Traced, corners: &[Traced], albedo: bool) -> bool {
    let (lo, hi) = std::iter::once(centre).chain(corners).fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), t| (lo.min(t.coverage), hi.max(t.coverage)));
    let srgb = |v: f32| crate::imageio::linear_to_srgb(v.max(0.0));
    let bilinear = |of: &dyn Fn(&Traced) -> [f32; 3]| {
        (0..3).all(|c| (srgb(of(centre)[c]) - corners.iter().map(|t| srgb(of(t)[c])).sum::<f32>() / corners.len() as f32).abs() <= STRATA_AGREE)
    };
    hi - lo <= 1.0 / 255.0 && bilinear(&|t| t.colour) && (!albedo || bilinear(&|t| t.albedo))
}

/// A refined pixel as the mean of its 3 x 3 strata: the centre, the corners and the sides'
/// middles, or where the sides were not found (`strata_agree`) each side as its two corners'
/// mean (`midway`), so every corner counts twice. The depth stays the centre's.
fn strata_mean(centre: &Traced, corners: &[Traced], sides: Option<&[Traced]>) -> Traced {
    let midways: Vec<Traced>;
    let sides = match sides {
        Some(sides) => sides,
        None => {
            midways = SIDE_CORNERS.iter().map(|&(a, b)| midway(&corners[a], &corners[b])).collect();
            &midways
        }
    };
    let ninth = 1.0 / 9.0;
    let strata = || std::iter::once(centre).chain(corners).chain(sides);
    let mean = |of: fn(&Traced) -> [f32; 3]| strata().fold([0.0f32; 3], |a, t| [a[0] + of(t)[0] * ninth, a[1] + of(t)[1] * ninth, a[2] + of(t)[2] * ninth]);
    Traced {
        colour: mean(|t| t.colour),
        albedo: mean(|t| t.albedo),
        raw: mean(|t| t.raw),
        coverage: strata().map(|t| t.coverage * ninth).sum(),
        depth: centre.depth,
    }
}

/// Whether pixel `p` of a centre-sampled render (sRGB `encoded`, `coverage`, `w x h`) must be
/// rendered over its area to stand for its mean there: where its 3 x 3 neighbourhood's
/// coverage differs by more than an 8-bit step (a silhouette), or where its colour is curved:
/// over a box the mean of a smooth image is its centre plus a ninth of how far the centre lies
/// from its 8 neighbours' mean (both `(f_xx + f_yy) / 24` and `3 (f_xx + f_yy) / 8` on a
/// quadratic; taken over opposite pairs of neighbours, so that a linear image gives 0 at the
/// image's border too), so a pixel whose centre is within `REFINE_CURVATURE` of that mean is within
/// half an 8-bit step of its area's mean already. A linear shading ramp is never refined; an
/// edge through the pixel (a checker, a stripe, a shadow's border) is.
fn needs_area(encoded: &[[f32; 3]], coverage: &[f32], w: usize, h: usize, p: usize) -> bool {
    let step = 1.0 / 255.0;
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    let neighbours: Vec<usize> = (-1..=1)
        .flat_map(|dy| (-1..=1).map(move |dx| (x + dx, y + dy)))
        .filter(|&(i, j)| (i, j) != (x, y) && i >= 0 && j >= 0 && (i as usize) < w && (j as usize) < h)
        .map(|(i, j)| j as usize * w + i as usize)
        .collect();
    if neighbours.iter().any(|&q| (coverage[p] - coverage[q]).abs() > step) {
        return true;
    }
    // The neighbours in opposite pairs (both inside the image, so a linear image gives zero at
    // its border too): how far the centre lies from the pairs' mean.
    let at = |dx: isize, dy: isize| {
        let (i, j) = (x + dx, y + dy);
        (i >= 0 && j >= 0 && (i as usize) < w && (j as usize) < h).then(|| j as usize * w + i as usize)
    };
    let pairs: Vec<(usize, usize)> = [(1, 0), (0, 1), (1, 1), (1, -1)].into_iter().filter_map(|(dx, dy)| Some((at(dx, dy)?, at(-dx, -dy)?))).collect();
    if pairs.is_empty() {
        return false;
    }
    let n = pairs.len() as f32;
    (0..3).any(|c| (pairs.iter().map(|&(a, b)| (encoded[a][c] + encoded[b][c]) / 2.0).sum::<f32>() / n - encoded[p][c]).abs() > REFINE_CURVATURE)
}

/// How far (sRGB) a pixel's centre may lie from its 8 neighbours' mean before it is rendered
/// over its area (`needs_area`): nine times half an 8-bit step.
const REFINE_CURVATURE: f32 = 4.5 / 255.0;

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

/// The least fitted albedo (linear, every channel) a centre may have for its shading term, its
/// colour over its albedo, to be read off it (`quadrant_interpolates`).
const SHADING_ALBEDO_FLOOR: f32 = 1e-3;

/// Whether every centre of pixel `p`'s 3 x 3 neighbourhood lies in the image and has an albedo
/// above `SHADING_ALBEDO_FLOOR` in every channel.
fn albedo_above_floor(pixels: &[Traced], w: usize, h: usize, p: usize) -> bool {
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (x + dx, y + dy))).all(|(i, j)| {
        i >= 0 && j >= 0 && (i as usize) < w && (j as usize) < h && pixels[j as usize * w + i as usize].raw.iter().all(|&a| a > SHADING_ALBEDO_FLOOR)
    })
}

/// The centres of the quadrant of a pixel that its stratum `offset` lies in, as steps `(dx,
/// dy)` from the pixel (its own first; -1 or 1 on each axis, the side of its middle the stratum
/// lies on), with their bilinear weights at the stratum.
fn quadrant(offset: [f64; 2]) -> [((isize, isize), f32); 4] {
    let (ox, oy) = (offset[0] - 0.5, offset[1] - 0.5);
    let (sx, sy) = (if ox < 0.0 { -1 } else { 1 }, if oy < 0.0 { -1 } else { 1 });
    let (fx, fy) = (ox.abs() as f32, oy.abs() as f32);
    [((0, 0), (1.0 - fx) * (1.0 - fy)), ((sx, 0), fx * (1.0 - fy)), ((0, sy), (1.0 - fx) * fy), ((sx, sy), fx * fy)]
}

/// Whether stratum `offset` of pixel `p` can be read off the centres of its quadrant
/// (`stratum_from_centres`; `w x h` centres, focal length `fx` in pixels): each one that weighs
/// in lies in the image, is wholly covered, has an albedo above `SHADING_ALBEDO_FLOOR` in every
/// channel (its shading term is its colour over its albedo) and a depth within `QUADRANT_SLOPE`
/// pixels' widths of the others (`window_of`: one smooth surface, no step, no silhouette
/// between them). Along a silhouette the quadrants facing into the body pass, those facing out
/// do not.
fn quadrant_interpolates(pixels: &[Traced], w: usize, h: usize, p: usize, offset: [f64; 2], fx: f64) -> bool {
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    let mut depths = Vec::with_capacity(4);
    for ((dx, dy), weight) in quadrant(offset) {
        if weight == 0.0 {
            continue;
        }
        let (i, j) = (x + dx, y + dy);
        if i < 0 || j < 0 || i as usize >= w || j as usize >= h {
            return false;
        }
        let q = &pixels[j as usize * w + i as usize];
        if q.coverage < 1.0 - 1.0 / 255.0 || !q.depth.is_finite() || !q.raw.iter().all(|&a| a > SHADING_ALBEDO_FLOOR) {
            return false;
        }
        depths.push(q.depth as f64);
    }
    window_of(depths, fx, QUADRANT_SLOPE).is_some()
}

/// Stratum `offset` (within the pixel, `[0, 1)^2`) of pixel `p` from the centres around it:
/// the four centres of its quadrant, bilinearly, give its depth, coverage and shading term
/// (colour over albedo, per channel). Returns `(depth, coverage, shading)`.
fn stratum_from_centres(pixels: &[Traced], w: usize, p: usize, offset: [f64; 2]) -> (f32, f32, [f32; 3]) {
    // A centre of zero weight is never read: it may lie outside the image.
    let corners: Vec<(&Traced, f32)> =
        quadrant(offset).into_iter().filter(|&(_, k)| k > 0.0).map(|((dx, dy), k)| (&pixels[(p as isize + dy * w as isize + dx) as usize], k)).collect();
    let blend = |of: &dyn Fn(&Traced) -> f32| corners.iter().map(|(t, k)| of(t) * k).sum::<f32>();
    let shading = [0, 1, 2].map(|c| blend(&|t| t.colour[c] / t.raw[c]));
    (blend(&|t| t.depth), blend(&|t| t.coverage), shading)
}

/// Strata `at` (a pixel, its stratum `offsets[s]` within it) read off the centres around them
/// (`quadrant_interpolates` holds): each one's depth, coverage and shading term are its
/// quadrant's centres' interpolated (`stratum_from_centres`), and its albedo is looked up at
/// its own surface point (that depth along its own ray). What varies there within a pixel is
/// the albedo's pattern; the surface, its light and its shadows are smooth across the centres,
/// so tracing the stratum would find what interpolation does, at about 50 field evaluations
/// instead of one.
#[allow(clippy::too_many_arguments)]
fn strata_from_centres(
    model: &Avatar,
    camera: &crate::scene::Camera,
    pose: &PoseTensors,
    pixels: &[Traced],
    w: usize,
    offsets: &[[f64; 2]],
    at: &[(usize, usize)],
    albedo_scale: Option<DVec3>,
    device: &Device,
) -> Vec<Traced> {
    let located: Vec<(f32, f32, [f32; 3], DVec3)> = at
        .iter()
        .map(|&(p, s)| {
            let offset = offsets[s];
            let (depth, coverage, shading) = stratum_from_centres(pixels, w, p, offset);
            let ray = camera.ray_through(glam::DVec2::new((p % w) as f64 + offset[0], (p / w) as f64 + offset[1]));
            (depth, coverage, shading, ray.origin + ray.direction * depth as f64)
        })
        .collect();
    let albedos: Vec<f32> = located
        .par_chunks(TRACE_CHUNK)
        .flat_map_iter(|chunk| {
            let points: Vec<f32> = chunk.iter().flat_map(|l| l.3.as_vec3().to_array()).collect();
            let points = Tensor::<2>::from_data(TensorData::new(points, [chunk.len(), 3]), device);
            let decoded = model.field.decode(points, pose);
            let albedo = crate::backend::host_values(model.field.albedo_at(&decoded, None));
            albedo.into_iter()
        })
        .collect();
    let scale = albedo_scale.map(|s| s.as_vec3().to_array());
    located
        .iter()
        .enumerate()
        .map(|(j, &(depth, coverage, shading, _))| {
            let raw = [0, 1, 2].map(|c| albedos.get(3 * j + c).copied().unwrap_or(f32::NAN) * coverage);
            Traced {
                colour: [0, 1, 2].map(|c| raw[c] * shading[c]),
                albedo: scale.map_or([0.0; 3], |s| [0, 1, 2].map(|c| raw[c] * s[c])),
                raw,
                coverage,
                depth,
            }
        })
        .collect()
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
struct Traced {
    colour: [f32; 3],
    albedo: [f32; 3],
    /// The fitted albedo as composited along the ray (unscaled, weighted by the coverage): the
    /// colour is it times a shading term that does not depend on it (every light is Lambertian).
    raw: [f32; 3],
    coverage: f32,
    /// Distance along the ray to the composited surface.
    depth: f32,
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

/// Bisection rounds per crossing: the cell / 2^10, about 10 micrometres for a human.
const BISECTIONS: usize = 10;
/// Points per field evaluation.
const CHUNK: usize = 1 << 15;

/// The fitted surface in one pose (`bones`: the posed bones' box; `extent`: the body's, from
/// `Scene::body_extent`), with per-vertex albedo (times `scale`) and unit normals.
#[allow(clippy::type_complexity)]
pub fn surface_mesh(
    model: &Avatar,
    pose: &PoseTensors,
    bones: (DVec3, DVec3),
    extent: f64,
    scale: DVec3,
    device: &Device,
) -> Result<(Mesh, Vec<DVec3>, Vec<DVec3>), FitError> {
    // As far as the field's grids reach (a loose body's root farther), so no surface the field
    // can hold is cut, at their finest cell.
    let (reach, cell) = model.field.surface_reach_and_cell(extent);
    let reach = DVec3::splat(reach);
    let grid = Grid::covering(bones.0 - reach, bones.1 + reach, cell);
    let values: Vec<f64> = sdf(model, pose, &grid.points(), device)?.into_iter().map(f64::from).collect();
    let mut failed = None;
    let mesh = extract(&grid, &values, |crossings| {
        bisect(crossings, BISECTIONS, |points| match sdf(model, pose, points, device) {
            Ok(values) => values.into_iter().map(|v| v < 0.0).collect(),
            Err(e) => {
                failed = Some(e);
                vec![false; points.len()]
            }
        })
    });
    if let Some(e) = failed {
        return Err(e);
    }
    let mut colours = Vec::with_capacity(mesh.vertices.len());
    let mut normals = Vec::with_capacity(mesh.vertices.len());
    for chunk in mesh.vertices.chunks(CHUNK) {
        let points = tensor(chunk, device);
        let albedo = read(model.field.forward(points.clone(), pose).albedo, 3 * chunk.len())?;
        let (_, gradient) = model.field.sdf_and_gradient(points, pose);
        let gradient = read(gradient, 3 * chunk.len())?;
        for (a, g) in albedo.chunks(3).zip(gradient.chunks(3)) {
            colours.push(DVec3::new(a[0] as f64, a[1] as f64, a[2] as f64) * scale);
            normals.push(DVec3::new(g[0] as f64, g[1] as f64, g[2] as f64).normalize_or(DVec3::Y));
        }
    }
    Ok((mesh, colours, normals))
}

/// A tensor's values, which must number `expected`.
/// The fitted surface in `scene`'s frame `frame` (`surface_mesh`, colours times `scale`), cut
/// to the frame's visual hull (`carve`): the mesh, its colours and normals, and what the cut
/// removed.
pub fn frame_surface(
    model: &Avatar,
    scene: &Scene,
    frame: usize,
    scale: DVec3,
    device: &Device,
) -> Result<(Mesh, Vec<DVec3>, Vec<DVec3>, crate::carve::Carved), FitError> {
    let pose = &scene.frames[frame].pose;
    let tensors = PoseTensors::new(pose, &scene.skeleton, device);
    let (mesh, colours, normals) = surface_mesh(model, &tensors, pose.bounds(&scene.skeleton), scene.body_extent(), scale, device)?;
    let carved = crate::carve::carve(&mesh, scene, frame);
    let (colours, normals) = (carved.keep(&colours), carved.keep(&normals));
    Ok((carved.mesh.clone(), colours, normals, carved))
}

fn read<const D: usize>(values: Tensor<D>, expected: usize) -> Result<Vec<f32>, FitError> {
    let values = crate::backend::to_host(values).map_err(|e| FitError::Input(format!("reading the field's output: {e}")))?;
    if values.len() != expected {
        return Err(FitError::Input(format!("the field returned {} values for {expected}", values.len())));
    }
    Ok(values)
}

fn tensor(points: &[DVec3], device: &Device) -> Tensor<2> {
    let flat: Vec<f32> = points.iter().flat_map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect();
    Tensor::from_data(TensorData::new(flat, [points.len(), 3]), device)
}

/// The fitted SDF at world points, in chunks.
fn sdf(model: &Avatar, pose: &PoseTensors, points: &[DVec3], device: &Device) -> Result<Vec<f32>, FitError> {
    let mut out = Vec::with_capacity(points.len());
    for chunk in points.chunks(CHUNK) {
        out.extend(read(model.field.sdf(tensor(chunk, device), pose), chunk.len())?);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Which pixels of an 8 x 8 image `needs_area` picks, as (x, y).
    fn picked(image: impl Fn(usize, usize) -> [f32; 3], coverage: impl Fn(usize, usize) -> f32) -> Vec<(usize, usize)> {
        let (w, h) = (8, 8);
        let encoded: Vec<[f32; 3]> = (0..w * h).map(|p| image(p % w, p / w)).collect();
        let cover: Vec<f32> = (0..w * h).map(|p| coverage(p % w, p / w)).collect();
        (0..w * h).filter(|&p| needs_area(&encoded, &cover, w, h, p)).map(|p| (p % w, p / w)).collect()
    }

    /// The 3 x 3 strata of a pixel traced through `image(x, y)` (x, y in [0, 1]), in
    /// `subpixel_offsets` order, colour and albedo alike, wholly covered.
    fn strata(image: &dyn Fn(f64, f64) -> f32) -> Vec<Traced> {
        crate::scene::footprint::subpixel_offsets(9, None)
            .iter()
            .map(|o| {
                let v = image(o[0], o[1]);
                Traced { colour: [v; 3], albedo: [v; 3], raw: [v; 3], coverage: 1.0, depth: 1.0 }
            })
            .collect()
    }

    #[test]
    fn the_corners_stand_for_the_sides_on_ramps_and_never_across_a_straight_edge() {
        let pick = |s: &[Traced], which: &[usize]| which.iter().map(|&k| s[k]).collect::<Vec<_>>();
        let nine_mean = |s: &[Traced]| s.iter().map(|t| t.colour[0]).sum::<f32>() / 9.0;
        // A bilinear ramp (dim, where sRGB is steepest, and bright): the five agree and give the
        // nine strata's mean.
        for (base, slope) in [(0.02f32, 0.01f32), (0.4, 0.2)] {
            let ramp = |x: f64, y: f64| base + slope * (x as f32 - 0.3 * y as f32 + 0.5 * (x * y) as f32);
            let s = strata(&ramp);
            let corners = pick(&s, &CORNER_STRATA);
            assert!(strata_agree(&s[4], &corners, true), "ramp {base} {slope}");
            let mean = strata_mean(&s[4], &corners, None);
            assert!((mean.colour[0] - nine_mean(&s)).abs() < 1e-6, "{} against {}", mean.colour[0], nine_mean(&s));
            let traced = strata_mean(&s[4], &corners, Some(&pick(&s, &SIDE_STRATA)));
            assert!((traced.colour[0] - mean.colour[0]).abs() < 1e-6 && (traced.coverage - 1.0).abs() < 1e-6);
        }
        // Any straight edge of a few 8-bit steps' contrast that splits the nine strata is seen by
        // the centre and corners: lines at 64 angles, through 64 offsets across the pixel.
        let (dark, light) = (crate::imageio::srgb_to_linear(0.40), crate::imageio::srgb_to_linear(0.40 + 6.0 / 255.0));
        let mut split = 0;
        for a in 0..64 {
            let angle = a as f64 * std::f64::consts::TAU / 64.0 + 0.01;
            let (nx, ny) = (angle.cos(), angle.sin());
            for o in 0..64 {
                let offset = -0.75 + 1.5 * o as f64 / 63.0;
                let edge = |x: f64, y: f64| if (x - 0.5) * nx + (y - 0.5) * ny > offset { light } else { dark };
                let s = strata(&edge);
                if s.iter().all(|t| t.colour[0] == s[0].colour[0]) {
                    continue;
                }
                split += 1;
                assert!(!strata_agree(&s[4], &pick(&s, &CORNER_STRATA), false), "angle {angle} offset {offset}");
            }
        }
        assert!(split > 1000, "{split} lines split the strata");
        // A silhouette: coverage that differs between the five.
        let mut s = strata(&|_, _| 0.3);
        s[8].coverage = 0.0;
        assert!(!strata_agree(&s[4], &pick(&s, &CORNER_STRATA), false));
    }

    #[test]
    fn a_window_holds_a_smooth_surface_and_is_refused_at_silhouettes_and_steps() {
        // 8 x 8 centres of a plane tilted along x, 2 m away, 100 pixels of focal length: a
        // pixel is 2 cm wide there; the plane recedes `slope` pixels' widths a pixel.
        let (w, h, fx) = (8, 8, 100.0);
        let plane = |slope: f32, covered: &dyn Fn(usize, usize) -> bool| -> Vec<Traced> {
            (0..w * h)
                .map(|p| {
                    let (x, y) = (p % w, p / w);
                    let coverage = if covered(x, y) { 1.0 } else { 0.0 };
                    Traced { colour: [0.5; 3], albedo: [0.5; 3], raw: [0.5; 3], coverage, depth: 2.0 + slope * 0.02 * x as f32 }
                })
                .collect()
        };
        let all = |_: usize, _: usize| true;
        let gentle = plane(0.5, &all);
        let (lo, hi) = surface_window(&gentle, w, h, 3 * w + 3, fx).expect("inside a gently tilted plane");
        // The pixel's own points lie between its neighbours' centres, and within the window.
        for x in [2.5f64, 3.0, 3.5, 4.0, 4.5] {
            let depth = 2.0 + 0.5 * 0.02 * (x - 0.5);
            assert!(lo < depth && depth < hi, "{depth} outside {lo}..{hi}");
        }
        assert!(hi - lo < 0.1, "a window, not the whole ray: {lo}..{hi}");
        // A corner pixel has fewer neighbours and still gets one.
        assert!(surface_window(&gentle, w, h, 0, fx).is_some());
        // Grazing: the depths differ by more than WINDOW_SLOPE pixels across the neighbourhood.
        assert!(surface_window(&plane(2.0, &all), w, h, 3 * w + 3, fx).is_none());
        // A silhouette: a neighbour not wholly covered.
        assert!(surface_window(&plane(0.5, &|x, _| x < 4), w, h, 3 * w + 3, fx).is_none());
        assert!(surface_window(&plane(0.5, &|x, _| x < 4), w, h, 3 * w + 1, fx).is_some());
        // A step in depth (an arm in front of the body) next to the pixel.
        let mut step = plane(0.0, &all);
        step[3 * w + 4].depth -= 0.2;
        assert!(surface_window(&step, w, h, 3 * w + 3, fx).is_none());
    }

    #[test]
    fn only_edges_and_silhouettes_are_rendered_over_their_area() {
        // A steep linear ramp (ten 8-bit steps a pixel) on a covered image: nothing, since a
        // box's mean of a linear image is its centre.
        let ramp = |x: usize, y: usize| [0.1 + 0.04 * x as f32, 0.3 + 0.02 * y as f32, 0.5];
        assert!(picked(ramp, |_, _| 1.0).is_empty());
        // A checker edge between columns 3 and 4: the two columns beside it.
        let edge = |x: usize, _: usize| if x < 4 { [0.2; 3] } else { [0.8; 3] };
        let cols: std::collections::BTreeSet<usize> = picked(edge, |_, _| 1.0).into_iter().map(|p| p.0).collect();
        assert_eq!(cols, [3, 4].into_iter().collect());
        // A silhouette (coverage 1 above row 5, 0 below) on a flat colour: rows 4 and 5.
        let rows: std::collections::BTreeSet<usize> = picked(|_, _| [0.5; 3], |_, y| if y < 5 { 1.0 } else { 0.0 }).into_iter().map(|p| p.1).collect();
        assert_eq!(rows, [4, 5].into_iter().collect());
        // A gentle curve along x (a quadratic of 0.5 steps over the neighbourhood) is left
        // alone; a strong one is not, except in the first and last columns, which have no
        // neighbours on one side to tell a curve from a ramp.
        let curve = |k: f32| move |x: usize, _: usize| [0.5 + k * (x as f32 - 3.5).powi(2), 0.5, 0.5];
        assert!(picked(curve(0.5 / 255.0), |_, _| 1.0).is_empty());
        let strong = picked(curve(20.0 / 255.0), |_, _| 1.0);
        assert!(strong.len() == 48 && strong.iter().all(|p| p.0 > 0 && p.0 < 7), "{strong:?}");
    }

    #[test]
    fn strata_take_the_centres_depth_coverage_and_shading_bilinearly() {
        // Centres whose depth, coverage and shading (colour over albedo) are bilinear in the
        // pixel's position: every stratum gets the value at its own position exactly.
        let (w, h) = (5, 5);
        let value =
            |x: f64, y: f64| (2.0 + 0.01 * x - 0.02 * y + 0.003 * x * y, 0.9 + 0.01 * x + 0.005 * y, [0.3 + 0.02 * x, 0.5 - 0.01 * y, 0.2 + 0.01 * x * y]);
        let pixels: Vec<Traced> = (0..w * h)
            .map(|p| {
                let (depth, coverage, shading) = value((p % w) as f64, (p / w) as f64);
                let raw = [0.4f32, 0.6, 0.2];
                Traced { colour: [0, 1, 2].map(|c| raw[c] * shading[c] as f32), albedo: raw, raw, coverage: coverage as f32, depth: depth as f32 }
            })
            .collect();
        let p = 2 * w + 2;
        for offset in crate::scene::footprint::subpixel_offsets(VIEW_PIXEL_RAYS, None) {
            let (depth, coverage, shading) = stratum_from_centres(&pixels, w, p, offset);
            let (d, c, s) = value(2.0 + offset[0] - 0.5, 2.0 + offset[1] - 0.5);
            assert!((depth as f64 - d).abs() < 1e-5 && (coverage as f64 - c).abs() < 1e-5, "{offset:?}: {depth} {d}, {coverage} {c}");
            for k in 0..3 {
                assert!((shading[k] as f64 - s[k]).abs() < 1e-5, "{offset:?}: {shading:?} {s:?}");
            }
        }
        // Its shading is read off its neighbours only where each has some albedo in every
        // channel, and never at the image's border.
        assert!(albedo_above_floor(&pixels, w, h, p));
        assert!(!albedo_above_floor(&pixels, w, h, 2));
        let mut dark = pixels.clone();
        dark[3 * w + 3].raw[1] = 0.0;
        assert!(!albedo_above_floor(&dark, w, h, p));
        assert!(albedo_above_floor(&dark, w, h, w + 1));
        // Stratum by stratum: a quadrant is read off where its centres are wholly covered and
        // within a quarter of a pixel's width of depth of each other (here 2 mm apart, a pixel 2
        // cm wide at 2 m with a focal length of 100 pixels); the dark centre at (3, 3) spoils
        // only the quadrant towards it, as does a centre the body leaves partly uncovered.
        let fx = 100.0;
        let pixels: Vec<Traced> = pixels.iter().enumerate().map(|(q, t)| Traced { coverage: 1.0, depth: 2.0 + 0.002 * (q % w) as f32, ..*t }).collect();
        let mut dark = pixels.clone();
        dark[3 * w + 3].raw[1] = 0.0;
        let [top_left, top_right, bottom_left, bottom_right] = [[1.0 / 6.0, 1.0 / 6.0], [5.0 / 6.0, 1.0 / 6.0], [1.0 / 6.0, 5.0 / 6.0], [5.0 / 6.0, 5.0 / 6.0]];
        for offset in [top_left, top_right, bottom_left, bottom_right] {
            assert!(quadrant_interpolates(&pixels, w, h, p, offset, fx), "{offset:?}");
            assert_eq!(quadrant_interpolates(&dark, w, h, p, offset, fx), offset != bottom_right, "{offset:?}");
        }
        let mut edge = pixels.clone();
        edge[w + 1].coverage = 0.5;
        assert!(!quadrant_interpolates(&edge, w, h, p, top_left, fx));
        assert!(quadrant_interpolates(&edge, w, h, p, bottom_right, fx));
        // A side's stratum weighs two centres only: the other two may lie outside the image.
        assert!(!quadrant_interpolates(&pixels, w, h, 2 * w, [1.0 / 6.0, 0.5], fx));
        assert!(quadrant_interpolates(&pixels, w, h, 2 * w, [5.0 / 6.0, 0.5], fx));
        // A step in depth between the centres (a limb before the body) spoils the quadrants
        // across it.
        let mut step = pixels.clone();
        step[3 * w + 3].depth += 0.1;
        assert!(!quadrant_interpolates(&step, w, h, p, bottom_right, fx));
        assert!(quadrant_interpolates(&step, w, h, p, top_left, fx));
    }
}
