//! One view of a fitted avatar rendered as the capture's images are made: every pixel's centre
//! traced and shaded in the light asked for, and over an area capture the pixels that may hold
//! an edge rendered over their 3 x 3 strata, found as `Strata` says.

use super::strata::*;
use super::*;
use crate::scene::Camera;
use crate::shading::FittedLight;
use crate::shadow::tensor::GaussianTensors;

/// What shading a view in one light needs besides its surface: the light, and the casters and
/// sky sampler that light uses.
struct Shader<'a> {
    lighting: &'a Lighting<'a>,
    fitted: &'a FittedLight,
    casters: GaussianTensors,
    /// Sky light per pixel: MIS of the map and the cosine lobe, each pixel its own stream.
    sampler: Option<MisEstimator<'a>>,
}

impl<'a> Shader<'a> {
    fn new(model: &'a Avatar, lighting: &'a Lighting<'a>, gaussians: &GaussianTensors, view_seed: u64) -> Self {
        let fitted = match lighting {
            Lighting::Fitted(k) => model.light_at(*k),
            _ => &model.light,
        };
        let casters = fitted.shadow_casters(gaussians);
        let sampler = match lighting {
            Lighting::Known { light: Light::Environment { map, scale, .. }, samples, .. } => {
                Some(MisEstimator::new(map, *scale, *samples, view_seed).with_shadow_start(model.light.shadow_start))
            }
            Lighting::Known { light: Light::Uniform { radiance }, samples, .. } => {
                Some(MisEstimator::uniform(*radiance, *samples, view_seed).with_shadow_start(model.light.shadow_start))
            }
            _ => None,
        };
        Shader { lighting, fitted, casters, sampler }
    }

    fn needs_normals(&self, model: &Avatar) -> bool {
        match self.lighting {
            Lighting::Fitted(_) => model.light.kind != LightKind::Uniform,
            Lighting::Albedo { .. } => false,
            Lighting::Known { .. } => true,
        }
    }
}

/// A posed avatar seen through one camera in one or more lights (at most `LIGHTS_PER_TRACE`):
/// what every ray of the view shares.
struct View<'a> {
    model: &'a Avatar,
    camera: &'a Camera,
    device: &'a Device,
    shaders: Vec<Shader<'a>>,
    albedo_scale: Option<DVec3>,
    pose_tensors: PoseTensors,
    /// The posed Gaussians on the host, for `strata` and for the sky's shadows.
    posed: Vec<PosedGaussian>,
    gaussians: GaussianTensors,
    sky_casters: Vec<PosedGaussian>,
    needs_normals: bool,
}

impl<'a> View<'a> {
    fn new(
        model: &'a Avatar,
        scene: &'a Scene,
        camera: usize,
        frame: usize,
        device: &'a Device,
        lightings: &'a [Lighting<'a>],
        albedo_scale: Option<DVec3>,
    ) -> Self {
        let pose = &scene.frames[frame].pose;
        let pose_tensors = crate::skeleton::PoseTensors::new(pose, &scene.skeleton, device);
        let posed = model.gaussians.to_set().pose(pose);
        let gaussians = model.gaussians.posed(&pose_tensors);
        // Every light's sky samples from the view's own stream: a view's render in a light does
        // not depend on which other lights it is rendered in.
        let view_seed = (frame as u64) << 16 | camera as u64;
        let shaders: Vec<Shader> = lightings.iter().map(|lighting| Shader::new(model, lighting, &gaussians, view_seed)).collect();
        let needs_normals = shaders.iter().any(|s| s.needs_normals(model));
        let sky_casters = model.light.shadow_casters_posed(&posed);
        let camera = &scene.cameras[camera];
        View { model, camera, device, shaders, albedo_scale, pose_tensors, posed, gaussians, sky_casters, needs_normals }
    }

    fn scaled(&self, albedo: Tensor<2>, scale: &DVec3) -> Tensor<2> {
        albedo * Tensor::<1>::from_data(TensorData::new(scale.as_vec3().to_array().to_vec(), [3]), self.device).reshape([1, 3])
    }

    /// The colour `[N * 3]` of surface points of (premultiplied) fitted albedo `albedo` and unit
    /// normals `normal` (when the light needs them) in `shader`'s light, each with its own
    /// stream id for the sky's samples.
    fn shade_all(&self, shader: &Shader, albedo: Tensor<2>, surface: Tensor<2>, normal: Option<Tensor<2>>, ids: &[u64]) -> Vec<f32> {
        let model = self.model;
        match (shader.lighting, normal) {
            (Lighting::Fitted(_), Some(normal)) => values(shader.fitted.shade(albedo, surface, normal, &self.gaussians)),
            (Lighting::Albedo { albedo_scale }, _) => values(self.scaled(albedo, albedo_scale)),
            (Lighting::Known { light, albedo_scale, .. }, Some(normal)) => match (emitter(light, self.device), &shader.sampler) {
                (Some((emitter, ambient)), _) => {
                    let reflectance = self.scaled(albedo, albedo_scale);
                    values(shade_lambertian(reflectance, surface, normal, &shader.casters, ambient, &emitter, model.light.shadow_start, None))
                }
                (None, Some(sampler)) => {
                    let points = vectors(values(surface));
                    let normals = vectors(values(normal));
                    let reflectance = vectors(values(self.scaled(albedo, albedo_scale)));
                    let radiance = sampler.shade(&points, &normals, ids, &self.sky_casters);
                    reflectance.iter().zip(radiance).flat_map(|(a, l)| (*a * l).as_vec3().to_array()).collect()
                }
                (None, None) => values(albedo),
            },
            (_, _) => values(albedo),
        }
    }

    /// Every light's colour is the albedo times the light it receives: a ray that carries no
    /// albedo (no sample of weight `albedo_floor` or more, `render_still`) is black under any
    /// light, so only the others are shaded (on a view, half its bounded rays miss the body).
    /// `raw`: the albedo's values, `[N * 3]`. One `[N * 3]` colour per light of the view.
    fn shade(&self, albedo: Tensor<2>, raw: &[f32], surface: Tensor<2>, normal: Option<Tensor<2>>, ids: &[u64]) -> Vec<Vec<f32>> {
        let lit: Vec<usize> = (0..ids.len()).filter(|&i| raw[3 * i..3 * i + 3].iter().any(|&a| a != 0.0)).collect();
        if lit.len() == ids.len() {
            return self.shaders.iter().map(|shader| self.shade_all(shader, albedo.clone(), surface.clone(), normal.clone(), ids)).collect();
        }
        let mut colours = vec![vec![0.0f32; 3 * ids.len()]; self.shaders.len()];
        if !lit.is_empty() {
            let index = crate::render::row_index(lit.iter().copied(), self.device);
            let pick = |t: Tensor<2>| t.select(0, index.clone());
            let lit_ids: Vec<u64> = lit.iter().map(|&i| ids[i]).collect();
            let (albedo, surface, normal) = (pick(albedo), pick(surface), normal.map(pick));
            for (shader, colour) in self.shaders.iter().zip(&mut colours) {
                let shaded = self.shade_all(shader, albedo.clone(), surface.clone(), normal.clone(), &lit_ids);
                for (j, &i) in lit.iter().enumerate() {
                    colour[3 * i..3 * i + 3].copy_from_slice(shaded.get(3 * j..3 * j + 3).unwrap_or(&[f32::NAN; 3]));
                }
            }
        }
        colours
    }

    /// The colours, albedo (when asked) and coverage of rays through continuous pixel
    /// positions, each with its own stream id for the sky's samples. A target may carry a
    /// window of distances that holds its surface (`surface_window`): its ray is then sampled
    /// there only, as `samples` says.
    fn trace(&self, targets: &[([f64; 2], u64)], windows: &[Option<(f64, f64)>], samples: Sampling) -> Vec<Traced> {
        // Chunks of a view on every thread (views are rendered several at once too; rayon
        // shares the threads between both levels), each chunk's samples its own.
        let chunks: Vec<Vec<(usize, Traced)>> =
            targets.par_chunks(TRACE_CHUNK).enumerate().map(|(k, chunk)| self.trace_chunk(k * TRACE_CHUNK, chunk, windows, samples)).collect();
        let mut out = vec![Traced::default(); targets.len()];
        for (k, traced) in chunks.into_iter().flatten() {
            out[k] = traced;
        }
        out
    }

    /// The rays of `chunk`, the targets from `first` on, that meet the body, by their index.
    fn trace_chunk(&self, first: usize, chunk: &[([f64; 2], u64)], windows: &[Option<(f64, f64)>], samples: Sampling) -> Vec<(usize, Traced)> {
        let at: Vec<[f64; 2]> = chunk.iter().map(|t| t.0).collect();
        let windows = windows.get(first..(first + chunk.len()).min(windows.len())).unwrap_or(&[]);
        let traced = trace_deferred(self.model, self.camera, &self.posed, &self.pose_tensors, &at, windows, samples, self.needs_normals, self.device);
        let Some((hit, deferred)) = traced else {
            return Vec::new();
        };
        let ids: Vec<u64> = hit.iter().map(|&k| chunk[k].1).collect();
        let raw = values(deferred.albedo.clone());
        let colours = self.shade(deferred.albedo.clone(), &raw, deferred.surface.clone(), deferred.normal.clone(), &ids);
        let coverage = values(deferred.accumulation.clone());
        let depth = values(deferred.depth.clone());
        let albedo = self.albedo_scale.as_ref().map(|scale| values(self.scaled(deferred.albedo.clone(), scale)));
        let three = |v: &[f32], j: usize| [v[j * 3], v[j * 3 + 1], v[j * 3 + 2]];
        hit.iter()
            .enumerate()
            .map(|(j, &k)| {
                let albedo = albedo.as_ref().map_or([0.0; 3], |a| three(a, j));
                let mut each = [[0.0; 3]; LIGHTS_PER_TRACE];
                for (light, colour) in colours.iter().enumerate() {
                    each[light] = three(colour, j);
                }
                (first + k, Traced { colours: each, albedo, raw: three(&raw, j), coverage: coverage[j], depth: depth[j] })
            })
            .collect()
    }
}

/// The scene's `camera` in `frame` under `lighting` (`ViewLayers`), and with `albedo_scale`
/// also its albedo (as `Lighting::Albedo` renders it) from the same rays: the field is traced
/// once for both. Over an area capture's pixels the two share the pixels rendered over their
/// area, those either needs (`needs_area`), whose strata are found as `strata` says (`bench
/// render` times both ways; a test pins one to the other).
#[allow(clippy::too_many_arguments)]
pub fn render_view_layers(
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
    let lit = render_view_lights(model, scene, camera, frame, samples, device, std::slice::from_ref(lighting), albedo_scale, strata);
    let image = lit.images.into_iter().next().unwrap_or_else(|| RgbImage::new(0, 0));
    ViewLayers { image, albedo: lit.albedo, coverage: lit.coverage }
}

/// `render_view_layers` in several lights at once: the view's geometry is traced once (up to
/// `LIGHTS_PER_TRACE` lights a trace) and shaded in each light; over an area capture a pixel is
/// rendered over its area where any light's image (or the albedo) needs it. An image, in the
/// order of `lightings`, per light.
#[allow(clippy::too_many_arguments)]
pub fn render_view_lights(
    model: &Avatar,
    scene: &Scene,
    camera: usize,
    frame: usize,
    samples: Sampling,
    device: &Device,
    lightings: &[Lighting],
    albedo_scale: Option<DVec3>,
    strata: Strata,
) -> LitLayers {
    let area = scene.footprint().footprint == Footprint::Area;
    let mut images = Vec::with_capacity(lightings.len());
    let (w, h) = (scene.cameras[camera].width, scene.cameras[camera].height);
    let (mut albedo, mut coverage) = (None, vec![0.0; w * h]);
    for (k, group) in lightings.chunks(LIGHTS_PER_TRACE).enumerate() {
        // The albedo from the first trace only.
        let view = View::new(model, scene, camera, frame, device, group, albedo_scale.filter(|_| k == 0));
        let (w, h) = (view.camera.width, view.camera.height);
        let centre = |p: usize| [(p % w) as f64 + 0.5, (p / w) as f64 + 0.5];
        let mut pixels = view.trace(&(0..w * h).map(|p| (centre(p), p as u64)).collect::<Vec<_>>(), &[], samples);
        // A capture whose pixels average their area: every pixel that may hold an edge is the
        // mean of the centres of its 3 x 3 strata instead (`needs_area`); elsewhere the centre
        // is that mean already, to within half an 8-bit step.
        if area {
            for (p, traced) in over_area(&view, &pixels, samples, strata) {
                pixels[p] = traced;
            }
        }
        let traced = compose(pixels, w, h, area, group.len(), view.albedo_scale.is_some());
        images.extend(traced.images);
        if k == 0 {
            (albedo, coverage) = (traced.albedo, traced.coverage);
        }
    }
    LitLayers { images, albedo, coverage }
}

/// The images (one per light), albedo and coverage of a view's traced pixels. Over a pixel's
/// area, one the body covers by half or less is background, black, as the scene format's images
/// and masks have it. At a centre sample the coverage is the chance the ray meets the body: the
/// pixel is its expected value in the image's encoding (`imageio::composite_centre_sample`; the
/// area's rule there cost human-sun 0.85 dB over the foreground).
fn compose(pixels: Vec<Traced>, w: usize, h: usize, area: bool, lights: usize, with_albedo: bool) -> LitLayers {
    let mut images = vec![RgbImage::new(w, h); lights];
    let mut albedo = with_albedo.then(|| RgbImage::new(w, h));
    let pixel = |c: [f32; 3], coverage: f32| if area { c } else { crate::imageio::composite_centre_sample(c, coverage) };
    let mut coverage = vec![0.0; w * h];
    for (p, traced) in pixels.into_iter().enumerate() {
        if !area || traced.coverage > 0.5 {
            for (image, colour) in images.iter_mut().zip(traced.colours) {
                image.pixels[p] = pixel(colour, traced.coverage);
            }
            coverage[p] = if area { 1.0 } else { traced.coverage };
            if let Some(albedo) = albedo.as_mut() {
                albedo.pixels[p] = pixel(traced.albedo, traced.coverage);
            }
        }
    }
    LitLayers { images, albedo, coverage }
}

/// The pixels of an area capture that may hold an edge, and what they are over their area.
struct AreaPass<'v> {
    view: &'v View<'v>,
    pixels: &'v [Traced],
    samples: Sampling,
    strata: Strata,
    offsets: Vec<[f64; 2]>,
    /// The pixels rendered over their area (`needs_area`).
    refine: Vec<usize>,
    /// Each refined pixel's window of depths to search, if any.
    search: Vec<Option<(f64, f64)>>,
    /// Whether its whole neighbourhood lies on one smooth surface.
    smooth: Vec<bool>,
}

impl AreaPass<'_> {
    /// Whether stratum `s` of refined pixel `r` is read off the centres around it
    /// (`strata_from_centres`: its surface point, coverage and shading interpolated, only its
    /// albedo, where a pattern's edge lies, looked up: one field evaluation instead of about 50):
    /// where its pixel's neighbourhood lies on one smooth surface (`surface_window`) or, along a
    /// silhouette or a step, where the four centres of its quadrant lie wholly on the body, on a
    /// surface nearly facing the camera (`quadrant_interpolates`).
    fn readable(&self, r: usize, s: usize) -> bool {
        let (w, h) = (self.view.camera.width, self.view.camera.height);
        self.strata == Strata::Shortcuts && (self.smooth[r] || quadrant_interpolates(self.pixels, w, h, self.refine[r], self.offsets[s], self.view.camera.fx))
    }

    /// The rays of the strata `pairs` (a refined pixel's index into `refine`, a stratum), in
    /// that order: in their pixel's window where it has one, through their whole bound if not.
    fn trace_pairs(&self, pairs: &[(usize, usize)]) -> Vec<Traced> {
        let (w, h) = (self.view.camera.width, self.view.camera.height);
        let (windowed, searched): (Vec<usize>, Vec<usize>) = (0..pairs.len()).partition(|&j| self.search[pairs[j].0].is_some());
        let targets = |part: &[usize]| -> Vec<([f64; 2], u64)> {
            part.iter()
                .map(|&j| {
                    let (p, s) = (self.refine[pairs[j].0], pairs[j].1);
                    ([(p % w) as f64 + self.offsets[s][0], (p / w) as f64 + self.offsets[s][1]], (w * h + p * VIEW_PIXEL_RAYS + s) as u64)
                })
                .collect()
        };
        let windows_of: Vec<Option<(f64, f64)>> = windowed.iter().map(|&j| self.search[pairs[j].0]).collect();
        let mut out = vec![Traced::default(); pairs.len()];
        let windowed_rays = self.view.trace(&targets(&windowed), &windows_of, WINDOW_SAMPLING);
        let searched_rays = self.view.trace(&targets(&searched), &[], self.samples);
        for (part, traced) in [(&windowed, windowed_rays), (&searched, searched_rays)] {
            for (&j, ray) in part.iter().zip(traced) {
                out[j] = ray;
            }
        }
        out
    }

    /// The strata `pairs` (as `trace_pairs` takes them), each read off its centres where
    /// `readable`, traced where not.
    fn strata_at(&self, pairs: &[(usize, usize)]) -> Vec<Traced> {
        let view = self.view;
        let (read, traced): (Vec<usize>, Vec<usize>) = (0..pairs.len()).partition(|&j| self.readable(pairs[j].0, pairs[j].1));
        let mut out = vec![Traced::default(); pairs.len()];
        let at: Vec<(usize, usize)> = read.iter().map(|&j| (self.refine[pairs[j].0], pairs[j].1)).collect();
        let w = view.camera.width;
        let read_off = strata_from_centres(view.model, view.camera, &view.pose_tensors, self.pixels, w, &self.offsets, &at, view.albedo_scale, view.device);
        for (&j, stratum) in read.iter().zip(read_off) {
            out[j] = stratum;
        }
        for (&j, ray) in traced.iter().zip(self.trace_pairs(&traced.iter().map(|&j| pairs[j]).collect::<Vec<_>>())) {
            out[j] = ray;
        }
        out
    }
}

/// The pixels of an area capture's view that may hold an edge (`needs_area`), each the mean of
/// its 3 x 3 strata.
fn over_area(view: &View, pixels: &[Traced], samples: Sampling, strata: Strata) -> Vec<(usize, Traced)> {
    let (w, h, fx) = (view.camera.width, view.camera.height, view.camera.fx);
    let coverage: Vec<f32> = pixels.iter().map(|p| p.coverage).collect();
    let encode = |c: [f32; 3]| c.map(|v| crate::imageio::linear_to_srgb(v.max(0.0)));
    // Each light's image and the albedo, encoded: a pixel any of them needs is refined.
    let mut images: Vec<Vec<[f32; 3]>> = (0..view.shaders.len()).map(|light| pixels.iter().map(|p| encode(p.colours[light])).collect()).collect();
    images.extend(view.albedo_scale.map(|_| pixels.iter().map(|p| encode(p.albedo)).collect()));
    let refine: Vec<usize> = (0..w * h).filter(|&p| images.iter().any(|image| needs_area(image, &coverage, w, h, p))).collect();
    // Inside the body the surface a pixel's rays meet lies within its neighbours' depths: those
    // rays are sampled there, at half the cost; at a depth step the rays search their whole
    // bound as the centres did. Along silhouettes too, where the centres around a pixel that
    // meet the body agree on its depth (`silhouette_window`).
    let windows: Vec<Option<(f64, f64)>> = refine.iter().map(|&p| surface_window(pixels, w, h, p, fx)).collect();
    let search = refine
        .iter()
        .zip(&windows)
        .map(|(&p, window)| window.or_else(|| (strata == Strata::Shortcuts).then(|| silhouette_window(pixels, w, h, p, fx)).flatten()))
        .collect();
    let smooth = refine.iter().zip(&windows).map(|(&p, window)| window.is_some() && albedo_above_floor(pixels, w, h, p)).collect();
    let offsets = crate::scene::footprint::subpixel_offsets(VIEW_PIXEL_RAYS, None);
    let pass = AreaPass { view, pixels, samples, strata, offsets, refine, search, smooth };
    let refine = &pass.refine;
    // First the four corner strata: with the centre (already traced) they bound every straight
    // edge through the pixel, so where the five agree the pixel holds none and a side stratum
    // that would have to be traced is its two corners' mean instead.
    let corners = pass.strata_at(&(0..refine.len()).flat_map(|r| CORNER_STRATA.map(|s| (r, s))).collect::<Vec<_>>());
    let agree: Vec<bool> = (0..refine.len()).map(|k| strata_agree(&pixels[refine[k]], &corners[k * 4..k * 4 + 4], view.albedo_scale.is_some())).collect();
    let mut sides: Vec<Traced> = (0..refine.len()).flat_map(|k| SIDE_CORNERS.map(|(a, b)| midway(&corners[k * 4 + a], &corners[k * 4 + b]))).collect();
    // The sides found after all (a place in `sides`, a stratum): where the five disagree, and
    // wherever one is read off its centres, which costs less than a corners' mean errs.
    let found: Vec<(usize, usize)> = (0..refine.len())
        .flat_map(|r| SIDE_STRATA.into_iter().enumerate().map(move |(j, s)| (r, j, s)))
        .filter(|&(r, _, s)| !agree[r] || pass.readable(r, s))
        .map(|(r, j, s)| (r * 4 + j, s))
        .collect();
    let pairs: Vec<(usize, usize)> = found.iter().map(|&(k, s)| (k / 4, s)).collect();
    for (&(k, _), side) in found.iter().zip(pass.strata_at(&pairs)) {
        sides[k] = side;
    }
    (0..refine.len()).map(|k| (refine[k], strata_mean(&pixels[refine[k]], &corners[k * 4..k * 4 + 4], Some(&sides[k * 4..k * 4 + 4])))).collect()
}
