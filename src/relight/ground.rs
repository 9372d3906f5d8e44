//! A ground that receives the avatar's shadow (`--ground`): a horizontal plane (the world's up
//! is +Y) under the body, at the lowest point of the posed Gaussians' 2-sigma ellipsoids in each
//! frame or at a stated height, darkened where the Gaussians block the light. A render becomes
//! RGBA to composite over a plate: alpha is the body's coverage plus, where the body does not
//! cover, the shadow's opacity; the shadow itself is black.
//!
//! The shadow's opacity at a ground point is one less its transmittance toward the light, by the
//! same closed-form integral of the Gaussians that shades the body (`ShadowCaster`): along the
//! sun's direction, along the segment to a point light, and for uniform light or an environment
//! one less the ratio of the sky's cosine-weighted irradiance with the Gaussians to without
//! (`EnvironmentSampler`, a fixed set of sky directions for every ground point).

use super::EnvironmentSampler;
use crate::eval::Lighting;
use crate::light::Light;
use crate::scene::Camera;
use crate::shading::{LightKind, SHADOW_START};
use crate::shadow::{PosedGaussian, ShadowCaster, ShadowRay};
use glam::DVec3;
use rayon::prelude::*;

/// `--ground`: a plane under the body at `height` (m), or at the posed Gaussians' lowest point.
#[derive(Clone, Copy, Debug, Default)]
pub struct GroundOptions {
    pub height: Option<f64>,
}

impl GroundOptions {
    /// Refuses a stated height no render can show: not finite, more than `GROUND_REACH` body
    /// heights from the body's feet in `frames`, or above every camera in `cameras` (they would
    /// see the ground from below, where it holds no shadow).
    pub fn check(&self, scene: &crate::scene::Scene, cameras: &[usize], frames: &[usize]) -> Result<(), crate::fit_error::FitError> {
        let Some(height) = self.height else { return Ok(()) };
        let say = |what: String| Err(crate::fit_error::FitError::Input(format!("--ground-height {height}: {what}")));
        if !height.is_finite() {
            return say("not a finite height (m)".into());
        }
        let (lo, hi) = frames
            .iter()
            .map(|&f| scene.frames[f].pose.bounds(&scene.skeleton))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (a, b)| (lo.min(a.y), hi.max(b.y)));
        let reach = GROUND_REACH * (hi - lo).max(1e-3);
        if (height - lo).abs() > reach {
            return say(format!("{:.1} m from the body's lowest joint ({lo:.3} m): a ground that far ({GROUND_REACH} body heights, {reach:.1} m, at most) shows nothing of the body's shadow", (height - lo).abs()));
        }
        if cameras.iter().all(|&c| scene.cameras[c].centre().y <= height) {
            return say("above every camera: they would see the ground from below".into());
        }
        Ok(())
    }
}

/// How far, in body heights, a stated ground may lie from the body.
pub const GROUND_REACH: f64 = 100.0;

/// A rendered view: the picture, and its RGBA over the ground when there is one.
pub struct Rendered {
    /// The render, or with a ground the render over a grey backdrop (for sheets, animations).
    pub image: crate::imageio::RgbImage,
    pub rgba: Option<Vec<[f32; 4]>>,
}

impl Rendered {
    /// Renders a view, over the ground when `ground` says.
    pub fn view(
        model: &crate::avatar::Avatar,
        scene: &crate::scene::Scene,
        (camera, frame): (usize, usize),
        device: &burn::tensor::Device,
        lighting: &Lighting,
        ground: Option<GroundOptions>,
    ) -> Rendered {
        match ground {
            None => Rendered { image: crate::eval::render_view(model, scene, camera, frame, crate::eval::VIEW_SAMPLING, device, lighting), rgba: None },
            Some(g) => {
                let on = render_on_ground(model, scene, camera, frame, device, lighting, g.height);
                Rendered { image: on.preview, rgba: Some(on.rgba) }
            }
        }
    }

    /// Writes the view as a PNG (RGBA over the ground), atomically.
    pub fn save(&self, path: &std::path::Path) -> Result<(), crate::fit_error::FitError> {
        match &self.rgba {
            None => crate::run::save_png(path, &self.image),
            Some(rgba) => {
                let bytes = encode_rgba(rgba, self.image.width, self.image.height).map_err(|e| crate::fit_error::io(path, e))?;
                crate::imageio::write_atomic(path, &bytes).map_err(|e| crate::fit_error::io(path, e))
            }
        }
    }
}

/// How a ground point is lit, for its shadow.
pub enum GroundLight {
    /// A unit direction toward a sun.
    Sun(DVec3),
    /// A point light's position.
    Lamp(DVec3),
    /// A sky: uniform light or an environment.
    Sky(EnvironmentSampler),
}

/// Sky directions for a ground point's shadow under uniform light or an environment.
const SKY_DIRECTIONS: usize = 256;

/// The light a render's ground is shadowed by: a stated light, or the fitted light `k`.
pub fn ground_light(lighting: &Lighting, model: &crate::avatar::Avatar) -> Option<GroundLight> {
    match lighting {
        Lighting::Known { light, .. } => match light {
            Light::Directional { direction, .. } => Some(GroundLight::Sun(direction.normalize())),
            Light::Point { position, .. } => Some(GroundLight::Lamp(*position)),
            Light::Uniform { radiance } => Some(GroundLight::Sky(EnvironmentSampler::uniform(*radiance, SKY_DIRECTIONS, 7))),
            Light::Environment { map, scale, .. } => Some(GroundLight::Sky(EnvironmentSampler::new(map, *scale, SKY_DIRECTIONS, 7))),
            Light::Unknown { .. } => None,
        },
        Lighting::Fitted(k) => {
            let fitted = model.light_at(*k);
            let location = fitted.location().map(DVec3::from_array);
            match (fitted.kind, location) {
                (LightKind::Directional, Some(d)) => Some(GroundLight::Sun(d.normalize())),
                (LightKind::Point, Some(p)) => Some(GroundLight::Lamp(p)),
                _ => Some(GroundLight::Sky(EnvironmentSampler::uniform(DVec3::ONE, SKY_DIRECTIONS, 7))),
            }
        }
        Lighting::Albedo { .. } => None,
    }
}

/// The height of the lowest point of `gaussians`' 2-sigma ellipsoids.
pub fn lowest_point(gaussians: &[PosedGaussian]) -> f64 {
    let reach = |g: &PosedGaussian| {
        // The standard deviation along +Y: sqrt of (A diag(s^2) A^T)_yy.
        let var: f64 = (0..3).map(|i| (g.axes.col(i).y * g.scales[i]).powi(2)).sum();
        g.mean.y - 2.0 * var.sqrt()
    };
    gaussians.iter().map(reach).fold(f64::INFINITY, f64::min)
}

/// The opacity of the shadow at ground point `x`.
pub fn shadow_opacity(caster: &ShadowCaster, light: &GroundLight, x: DVec3) -> f64 {
    // Rays leave from just above the ground, as shadow rays leave a surface.
    let start = x + DVec3::Y * SHADOW_START as f64;
    let along = |direction: DVec3, t1: f32| {
        let ray = ShadowRay { origin: start.as_vec3().to_array(), direction: direction.as_vec3().to_array(), t0: 0.0, t1 };
        1.0 - caster.transmittance(&ray, true) as f64
    };
    match light {
        GroundLight::Sun(d) if d.y > 0.0 => along(*d, f32::INFINITY),
        GroundLight::Sun(_) => 0.0,
        GroundLight::Lamp(p) if p.y > start.y => along((*p - start).normalize(), (*p - start).length() as f32),
        GroundLight::Lamp(_) => 0.0,
        GroundLight::Sky(sky) => {
            let open = sky.shade_outside(x, DVec3::Y, None);
            let seen = sky.shade_outside(x, DVec3::Y, Some(caster));
            let (open, seen) = (open.element_sum(), seen.element_sum());
            if open > 0.0 {
                (1.0 - seen / open).clamp(0.0, 1.0)
            } else {
                0.0
            }
        }
    }
}

/// A render (`image`, premultiplied by `coverage`) over a ground at `height` that receives
/// the shadow of `casters` under `light`: straight-alpha linear RGBA per pixel.
pub fn over_ground(
    image: &crate::imageio::RgbImage,
    coverage: &[f32],
    camera: &Camera,
    height: f64,
    casters: &[PosedGaussian],
    light: &GroundLight,
) -> Vec<[f32; 4]> {
    let caster = ShadowCaster::new(casters, 1e-4);
    (0..image.pixels.len())
        .into_par_iter()
        .map(|p| {
            let (colour, cover) = (image.pixels[p], coverage[p].clamp(0.0, 1.0));
            let ray = camera.pixel_ray(p % image.width, p / image.width);
            // Where the pixel's ray meets the ground in front of the camera.
            let t = (height - ray.origin.y) / ray.direction.y;
            let shadow = if cover < 1.0 && ray.direction.y.abs() > 1e-9 && t > 0.0 { shadow_opacity(&caster, light, ray.at(t)) as f32 } else { 0.0 };
            let alpha = cover + (1.0 - cover) * shadow;
            match alpha > 0.0 {
                true => [colour[0] / alpha, colour[1] / alpha, colour[2] / alpha, alpha],
                false => [0.0; 4],
            }
        })
        .collect()
}

/// A view rendered over the ground: its RGBA pixels, and the same over a grey backdrop.
pub struct OnGround {
    pub rgba: Vec<[f32; 4]>,
    pub preview: crate::imageio::RgbImage,
}

/// Renders `camera` in `frame` over a ground at `height` (default: the posed Gaussians'
/// `lowest_point`) shadowed by the render's light; `None` when the light casts no shadow here
/// (the albedo).
#[allow(clippy::too_many_arguments)]
pub fn render_on_ground(
    model: &crate::avatar::Avatar,
    scene: &crate::scene::Scene,
    camera: usize,
    frame: usize,
    device: &burn::tensor::Device,
    lighting: &Lighting,
    height: Option<f64>,
) -> OnGround {
    let layers =
        crate::eval::render_view_layers(model, scene, camera, frame, crate::eval::VIEW_SAMPLING, device, lighting, None, crate::eval::Strata::Shortcuts);
    let (image, coverage) = (layers.image, layers.coverage);
    let posed = model.gaussians.to_set().pose(&scene.frames[frame].pose);
    let fitted = match lighting {
        Lighting::Fitted(k) => model.light_at(*k),
        _ => &model.light,
    };
    let casters = fitted.shadow_casters_posed(&posed);
    let height = height.unwrap_or_else(|| lowest_point(&casters));
    let (w, h) = (image.width, image.height);
    let rgba = match ground_light(lighting, model) {
        Some(light) => over_ground(&image, &coverage, &scene.cameras[camera], height, &casters, &light),
        None => image.pixels.iter().zip(&coverage).map(|(c, &a)| if a > 0.0 { [c[0] / a, c[1] / a, c[2] / a, a] } else { [0.0; 4] }).collect(),
    };
    let preview = over_grey(&rgba, w, h);
    OnGround { rgba, preview }
}

/// Straight-alpha RGBA over a grey backdrop, for contact sheets and animations.
pub fn over_grey(pixels: &[[f32; 4]], width: usize, height: usize) -> crate::imageio::RgbImage {
    let mut image = crate::imageio::RgbImage::new(width, height);
    for (out, p) in image.pixels.iter_mut().zip(pixels) {
        *out = [0, 1, 2].map(|c| p[c] * p[3] + BACKDROP * (1.0 - p[3]));
    }
    image
}

/// The backdrop's linear grey in `over_grey`.
const BACKDROP: f32 = 0.5;

/// Straight-alpha linear RGBA as an 8-bit sRGB PNG with alpha.
pub fn encode_rgba(pixels: &[[f32; 4]], width: usize, height: usize) -> Result<Vec<u8>, crate::imageio::ImageError> {
    let raw: Vec<u8> = pixels
        .iter()
        .flat_map(|p| {
            [
                crate::imageio::linear_to_srgb8(p[0]),
                crate::imageio::linear_to_srgb8(p[1]),
                crate::imageio::linear_to_srgb8(p[2]),
                (p[3].clamp(0.0, 1.0) * 255.0).round() as u8,
            ]
        })
        .collect();
    crate::imageio::encode_png_raw(&raw, width, height, image::ExtendedColorType::Rgba8)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat3;

    /// One axis-aligned Gaussian of peak density `a` (per metre) at `centre`.
    fn blob(centre: DVec3, scales: DVec3, a: f64) -> PosedGaussian {
        PosedGaussian { mean: centre, axes: DMat3::IDENTITY, scales, amplitude: a }
    }

    #[test]
    fn a_gaussians_shadow_on_the_ground_is_its_analytic_line_integral() {
        // Under a sun straight overhead, the ground point at horizontal offset r from the
        // centre sees an optical depth a sqrt(2 pi) s_y exp(-r^2 / (2 s_x^2)).
        let (s, a) = (DVec3::new(0.1, 0.2, 0.15), 6.0);
        let g = blob(DVec3::new(0.0, 1.0, 0.0), s, a);
        let casters = [g];
        let caster = ShadowCaster::new(&casters, 1e-4);
        let sun = GroundLight::Sun(DVec3::Y);
        for r in [0.0, 0.05, 0.1, 0.2] {
            let tau = a * (2.0 * std::f64::consts::PI).sqrt() * s.y * (-r * r / (2.0 * s.x * s.x)).exp();
            let opacity = shadow_opacity(&caster, &sun, DVec3::new(r, 0.0, 0.0));
            assert!((opacity - (1.0 - (-tau).exp())).abs() < 1e-4, "r {r}: {opacity} against {}", 1.0 - (-tau).exp());
        }
        // A lamp straight above the centre, beyond the Gaussian, sees the same whole integral;
        // a lamp below the Gaussian's reach sees none of it.
        let lamp = GroundLight::Lamp(DVec3::new(0.0, 3.0, 0.0));
        let tau = a * (2.0 * std::f64::consts::PI).sqrt() * s.y;
        assert!((shadow_opacity(&caster, &lamp, DVec3::ZERO) - (1.0 - (-tau).exp())).abs() < 1e-4);
        // A lamp inside the Gaussian's lower tail sees the tail between it and the ray's start
        // (SHADOW_START above the ground) only: a sqrt(2 pi) s_y (Phi((0.2 - 1) / s_y) -
        // Phi((start - 1) / s_y)).
        let low = GroundLight::Lamp(DVec3::new(0.0, 0.2, 0.0));
        let normal = statrs::distribution::Normal::new(0.0, 1.0).unwrap();
        use statrs::distribution::ContinuousCDF;
        let tail = a * (2.0 * std::f64::consts::PI).sqrt() * s.y * (normal.cdf(-0.8 / s.y) - normal.cdf((SHADOW_START as f64 - 1.0) / s.y));
        let opacity = shadow_opacity(&caster, &low, DVec3::ZERO);
        assert!((opacity - (1.0 - (-tail).exp())).abs() < 1e-6 && tail > 1e-5, "{opacity} against the tail's {tail}");
        // A slanted sun moves the shadow: the point whose ray (from SHADOW_START above it) runs
        // through the centre.
        let slant = DVec3::new(1.0, 1.0, 0.0).normalize();
        let under = DVec3::new(-1.0 + SHADOW_START as f64, 0.0, 0.0);
        let along = a * (2.0 * std::f64::consts::PI).sqrt() / (slant.x * slant.x / (s.x * s.x) + slant.y * slant.y / (s.y * s.y)).sqrt();
        let opacity = shadow_opacity(&caster, &GroundLight::Sun(slant), under);
        assert!((opacity - (1.0 - (-along).exp())).abs() < 1e-4, "{opacity}");
    }

    #[test]
    fn an_open_sky_casts_no_shadow_and_a_blob_overhead_darkens_it() {
        let sky = GroundLight::Sky(EnvironmentSampler::uniform(DVec3::ONE, 256, 3));
        let casters = [blob(DVec3::new(0.0, 0.5, 0.0), DVec3::splat(0.2), 20.0)];
        let caster = ShadowCaster::new(&casters, 1e-4);
        let far = shadow_opacity(&caster, &sky, DVec3::new(50.0, 0.0, 0.0));
        let under = shadow_opacity(&caster, &sky, DVec3::ZERO);
        assert!(far < 1e-3, "{far}");
        assert!(under > 0.2 && under < 1.0, "{under}");
    }

    #[test]
    fn the_ground_lies_at_the_lowest_two_sigma_reach() {
        let turned = PosedGaussian {
            mean: DVec3::new(0.0, 1.0, 0.0),
            axes: DMat3::from_rotation_z(std::f64::consts::FRAC_PI_2),
            scales: DVec3::new(0.3, 0.1, 0.1),
            amplitude: 1.0,
        };
        // Turned a quarter about Z, its 0.3 axis points along Y.
        assert!((lowest_point(&[turned, blob(DVec3::new(0.0, 2.0, 0.0), DVec3::splat(0.1), 1.0)]) - 0.4).abs() < 1e-12);
    }
}
