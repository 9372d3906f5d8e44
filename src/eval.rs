//! Rendering whole views of a fitted avatar, in its fitted light, in any light of the scene or
//! as albedo; `metrics` scores them.

use crate::gaussians::PosedGaussian;
use crate::imageio::RgbImage;
use crate::light::Light;
use crate::relight::EnvironmentSampler;
use crate::render::{ray_bounds, render, RaySet, Sampling};
use crate::scene::Scene;
use crate::shading::{shade_lambertian, Emitter, LightKind};
use crate::train::Avatar;
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;

pub use crate::metrics::psnr_srgb8;

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default()
}

/// The light a view is rendered in.
pub enum Lighting<'a> {
    /// The fitted light (the albedo, for a uniformly lit fit).
    Fitted,
    /// Shadow-free reflectance: the fitted albedo times `albedo_scale`.
    Albedo { albedo_scale: DVec3 },
    /// A light of the scene the avatar was not fitted in, with the scale that turns the fitted
    /// albedo into reflectance (`relight::albedo_scale`).
    Known { light: &'a Light, albedo_scale: DVec3, samples: usize },
}

/// How whole views are sampled for evaluation and relighting: twice a training step's.
pub const VIEW_SAMPLING: Sampling = Sampling { coarse: 48, probe: 0, fine: 32 };

/// Renders the scene's `camera` in `frame`, sampled as `samples` says, under `lighting`.
pub fn render_view(model: &Avatar, scene: &Scene, camera: usize, frame: usize, samples: Sampling, device: &Device, lighting: &Lighting) -> RgbImage {
    let camera = &scene.cameras[camera];
    let pose = &scene.frames[frame].pose;
    let pose_tensors = crate::field::PoseTensors::new(pose, &scene.skeleton, device);
    let set = model.gaussians.to_set();
    let posed = set.pose(pose);
    let gaussians = model.gaussians.posed(&pose_tensors);
    let casters = model.light.shadow_casters(&gaussians);
    let needs_normals = match lighting {
        Lighting::Fitted => model.light.kind != LightKind::Uniform,
        Lighting::Albedo { .. } => false,
        Lighting::Known { .. } => true,
    };
    // The sky's directions are drawn once per view, shared by all its pixels.
    let sampler = match lighting {
        Lighting::Known { light: Light::Environment { map, scale, .. }, samples, .. } => Some(EnvironmentSampler::new(map, *scale, *samples, frame as u64)),
        Lighting::Known { light: Light::Uniform { radiance }, samples, .. } => Some(EnvironmentSampler::uniform(*radiance, *samples, frame as u64)),
        _ => None,
    };
    let sky_casters: Vec<PosedGaussian> = model.light.shadow_casters_posed(&posed);
    let mut image = RgbImage::new(camera.width, camera.height);
    let pixels: Vec<usize> = (0..camera.width * camera.height).collect();
    for chunk in pixels.chunks(1024) {
        let mut rays = RaySet::default();
        let mut hit = Vec::new();
        for &p in chunk {
            let ray = camera.pixel_ray(p % camera.width, p / camera.width);
            if let Some(bounds) = ray_bounds(ray.origin, ray.direction, &posed) {
                rays.push(ray.origin, ray.direction, Some(bounds));
                hit.push(p);
            }
        }
        if rays.is_empty() {
            continue;
        }
        let r = rays.len();
        let jitter = vec![0.5; r * samples.draws()];
        let deferred = render(&model.field, &pose_tensors, &rays, samples, &jitter, needs_normals.then_some(crate::field::GRADIENT), device);
        let scaled =
            |scale: &DVec3| deferred.albedo.clone() * Tensor::<1>::from_data(TensorData::new(scale.as_vec3().to_array().to_vec(), [3]), device).reshape([1, 3]);
        let colour = match (lighting, &deferred.normal) {
            (Lighting::Fitted, Some(normal)) => values(model.light.shade(deferred.albedo.clone(), deferred.surface.clone(), normal.clone(), &gaussians)),
            (Lighting::Albedo { albedo_scale }, _) => values(scaled(albedo_scale)),
            (Lighting::Known { light, albedo_scale, .. }, Some(normal)) => match (emitter(light, device), &sampler) {
                (Some((emitter, ambient)), _) => {
                    values(shade_lambertian(scaled(albedo_scale), deferred.surface.clone(), normal.clone(), &casters, ambient, &emitter))
                }
                (None, Some(sampler)) => {
                    let points = vectors(values(deferred.surface.clone()));
                    let normals = vectors(values(normal.clone()));
                    let reflectance = vectors(values(scaled(albedo_scale)));
                    let radiance = sampler.shade(&points, &normals, &sky_casters);
                    reflectance.iter().zip(radiance).flat_map(|(a, l)| (*a * l).as_vec3().to_array()).collect()
                }
                (None, None) => values(deferred.albedo.clone()),
            },
            _ => values(deferred.albedo.clone()),
        };
        for (k, &p) in hit.iter().enumerate() {
            image.pixels[p] = [colour[k * 3], colour[k * 3 + 1], colour[k * 3 + 2]];
        }
    }
    image
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
        Light::Uniform { .. } | Light::Environment { .. } => None,
    }
}
