//! Rendering whole views of a fitted avatar and scoring them: PSNR over the whole image in
//! 8-bit sRGB, as the evaluation of novel poses, views and lighting uses it.

use crate::imageio::{linear_to_srgb8, RgbImage};
use crate::render::{ray_bounds, render, RaySet};
use crate::scene::Scene;
use crate::train::Avatar;
use burn::tensor::{Device, Tensor};

/// PSNR (dB) between two images after 8-bit sRGB encoding, over every pixel and channel.
pub fn psnr_srgb8(a: &RgbImage, b: &RgbImage) -> f64 {
    let mut sum = 0.0;
    for (p, q) in a.pixels.iter().zip(&b.pixels) {
        for c in 0..3 {
            let d = linear_to_srgb8(p[c]) as f64 - linear_to_srgb8(q[c]) as f64;
            sum += d * d;
        }
    }
    let mse = sum / (a.pixels.len() * 3) as f64;
    if mse == 0.0 {
        return f64::INFINITY;
    }
    10.0 * (255.0f64 * 255.0 / mse).log10()
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default()
}

/// Renders view `view` of the scene's camera and frame, shaded by the fitted light (or albedo).
pub fn render_view(model: &Avatar, scene: &Scene, camera: usize, frame: usize, samples: usize, device: &Device, shaded: bool) -> RgbImage {
    let camera = &scene.cameras[camera];
    let pose = &scene.frames[frame].pose;
    let pose_tensors = crate::field::PoseTensors::new(pose, &scene.skeleton, device);
    let set = model.gaussians.to_set();
    let posed = set.pose(pose);
    let gaussians = model.gaussians.posed(&pose_tensors);
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
        let jitter = vec![0.5; rays.len() * samples];
        let deferred = render(&model.field, &pose_tensors, &rays, samples, &jitter, shaded.then_some(crate::field::GRADIENT), device);
        let colour = match deferred.normal {
            Some(normal) if shaded => model.light.shade(deferred.albedo, deferred.surface, normal, &gaussians),
            _ => deferred.albedo,
        };
        let colour = values(colour.detach());
        for (k, &p) in hit.iter().enumerate() {
            image.pixels[p] = [colour[k * 3], colour[k * 3 + 1], colour[k * 3 + 2]];
        }
    }
    image
}
