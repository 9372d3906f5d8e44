//! Light sources of the scene format (directional sun, point, uniform, environment map) and
//! the equirectangular environment map with its exact direction <-> (u, v) mapping.
//!
//! umbra's light vocabulary, one word per idea:
//! - `Light` (here): a light as a scene states it, data, in the scene's units.
//! - `shading::LightKind`: which light a fit models (sun, point, uniform).
//! - `shading::FittedLight`: the learnable light of a fit (a burn module) and its report.
//! - `shading::Emitter`: a shadow-casting light as tensors, for the image formation.
//! - `eval::Lighting`: how a view is rendered: in fitted light k, as albedo, or in a `Light`.
//! - `schedule::LightPolicy`: whether a fit fits its light (`light = "auto" | "fit" | "off"`).

use crate::imageio::RgbImage;
use glam::DVec3;
use std::f64::consts::PI;
use std::path::PathBuf;

/// `count` directions spread evenly over the sphere (a spherical Fibonacci lattice: equal
/// bands in height, golden-angle steps around), turned by `turn` radians about +Y.
pub fn fibonacci_sphere(count: usize, turn: f64) -> Vec<DVec3> {
    let golden = PI * (3.0 - 5.0f64.sqrt());
    (0..count)
        .map(|k| {
            let y = 1.0 - (2 * k + 1) as f64 / count as f64;
            let r = (1.0 - y * y).max(0.0).sqrt();
            let phi = turn + golden * k as f64;
            DVec3::new(r * phi.cos(), y, r * phi.sin())
        })
        .collect()
}

/// How the fitted albedo maps to reflectance: the fit cannot separate the albedo's scale from
/// the training light's strength (a sun is fitted with irradiance 1), so the light the scene
/// states for its training images fixes it. `fitted_intensity` is a fitted point light's.
pub fn albedo_scale(training: &Light, fitted_intensity: Option<f64>) -> DVec3 {
    let inverse = |v: DVec3| DVec3::ONE / v.max(DVec3::splat(1e-8));
    match training {
        Light::Directional { irradiance, .. } => inverse(*irradiance),
        Light::Point { intensity, .. } => inverse(*intensity) * fitted_intensity.unwrap_or(1.0),
        Light::Uniform { radiance } => inverse(*radiance),
        Light::Environment { map, scale, .. } => inverse(map.mean_radiance() * *scale),
        // Unstated, the fitted light's strength is taken as the capture's: the albedo as fitted.
        Light::Unknown { strength, kind, .. } => match (strength, kind) {
            (Some(s), UnknownLight::Sun) => inverse(*s),
            (Some(s), UnknownLight::Point) => inverse(*s) * fitted_intensity.unwrap_or(1.0),
            (None, _) => DVec3::ONE,
        },
    }
}

/// What kind of light a capture's unknown light is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UnknownLight {
    /// A sun whose direction the capture does not state.
    Sun,
    /// A lamp whose position the capture does not state.
    Point,
}

#[derive(Clone, Debug, PartialEq)]
pub enum Light {
    /// A sun: `direction` is a unit vector from the scene toward the light.
    Directional { direction: DVec3, irradiance: DVec3, ambient: DVec3 },
    /// Equal radiance from every direction.
    Uniform { radiance: DVec3 },
    /// An equirectangular map times `scale`.
    Environment { path: PathBuf, scale: f64, map: EnvironmentMap },
    /// A near-field light: irradiance `intensity / r^2` on a surface facing it.
    Point { position: DVec3, intensity: DVec3, ambient: DVec3 },
    /// A real capture's sun or lamp, unstated (`directional` without `direction`, `point`
    /// without `position`): a fit recovers it and is scored against nothing; it lights only the
    /// images of its capture, never a relighting. `strength` is its irradiance or intensity
    /// when stated.
    Unknown { kind: UnknownLight, strength: Option<DVec3>, ambient: DVec3 },
}

impl Light {
    pub fn type_name(&self) -> &'static str {
        match self {
            Light::Directional { .. } => "directional",
            Light::Uniform { .. } => "uniform",
            Light::Environment { .. } => "environment",
            Light::Point { .. } => "point",
            Light::Unknown { kind: UnknownLight::Sun, .. } => "directional",
            Light::Unknown { kind: UnknownLight::Point, .. } => "point",
        }
    }

    /// Whether the light is stated (everything but an unknown light): only a stated light
    /// relights a fit or scores a fitted light.
    pub fn is_known(&self) -> bool {
        !matches!(self, Light::Unknown { .. })
    }

    /// Whether the light casts shadows a fitter must model (a sun or a point light).
    pub fn casts_shadows(&self) -> bool {
        matches!(self, Light::Directional { .. } | Light::Point { .. } | Light::Unknown { .. })
    }
}

/// An equirectangular environment map, linear RGB, top row looking up (+Y).
#[derive(Clone, Debug, PartialEq)]
pub struct EnvironmentMap {
    pub image: RgbImage,
}

/// The direction a map coordinate (u, v) in [0, 1) looks toward, per the scene format:
/// `theta = v pi`, `phi = (u - 0.5) 2 pi`, `d = (sin theta sin phi, cos theta, -sin theta cos phi)`.
pub fn uv_to_direction(u: f64, v: f64) -> DVec3 {
    let theta = v * PI;
    let phi = (u - 0.5) * 2.0 * PI;
    DVec3::new(theta.sin() * phi.sin(), theta.cos(), -theta.sin() * phi.cos())
}

/// The inverse of [`uv_to_direction`] for a unit direction; u in [0, 1), v in [0, 1].
pub fn direction_to_uv(d: DVec3) -> (f64, f64) {
    let theta = d.y.clamp(-1.0, 1.0).acos();
    let phi = d.x.atan2(-d.z);
    let mut u = phi / (2.0 * PI) + 0.5;
    if u >= 1.0 {
        u -= 1.0;
    }
    (u, theta / PI)
}

impl EnvironmentMap {
    /// Bilinear lookup of the radiance toward unit direction `d`; wraps in u, clamps in v.
    pub fn lookup(&self, d: DVec3) -> DVec3 {
        let (u, v) = direction_to_uv(d);
        let (w, h) = (self.image.width, self.image.height);
        let x = u * w as f64 - 0.5;
        let y = (v * h as f64 - 0.5).clamp(0.0, (h - 1) as f64);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let xi = |k: f64| (k as i64).rem_euclid(w as i64) as usize;
        let yi = |k: f64| (k as usize).min(h - 1);
        let texel = |xx: usize, yy: usize| {
            let p = self.image.get(xx, yy);
            DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64)
        };
        let top = texel(xi(x0), yi(y0)).lerp(texel(xi(x0 + 1.0), yi(y0)), fx);
        let bottom = texel(xi(x0), yi(y0 + 1.0)).lerp(texel(xi(x0 + 1.0), yi(y0 + 1.0)), fx);
        top.lerp(bottom, fy)
    }

    /// The direction through the centre of texel (x, y).
    pub fn texel_direction(&self, x: usize, y: usize) -> DVec3 {
        uv_to_direction((x as f64 + 0.5) / self.image.width as f64, (y as f64 + 0.5) / self.image.height as f64)
    }

    /// The mean radiance over the sphere (texels weighted by their solid angle).
    pub fn mean_radiance(&self) -> DVec3 {
        let (w, h) = (self.image.width, self.image.height);
        let mut sum = DVec3::ZERO;
        for y in 0..h {
            for x in 0..w {
                let p = self.image.get(x, y);
                sum += DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) * self.texel_solid_angle(y);
            }
        }
        sum / (4.0 * PI)
    }

    /// Solid angle of a texel in row `y` (rows near the poles are smaller).
    pub fn texel_solid_angle(&self, y: usize) -> f64 {
        let h = self.image.height as f64;
        let (t0, t1) = (y as f64 / h * PI, (y as f64 + 1.0) / h * PI);
        (2.0 * PI / self.image.width as f64) * (t0.cos() - t1.cos())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mapping_follows_the_spec() {
        assert!((uv_to_direction(0.5, 0.0) - DVec3::Y).length() < 1e-12, "top row is +Y");
        assert!((uv_to_direction(0.5, 0.5) - DVec3::NEG_Z).length() < 1e-12, "centre column looks to -Z");
        assert!((uv_to_direction(0.75, 0.5) - DVec3::X).length() < 1e-12, "u = 0.75 is +X");
        assert!((uv_to_direction(0.25, 0.5) - DVec3::NEG_X).length() < 1e-12);
        assert!((uv_to_direction(0.0, 0.5) - DVec3::Z).length() < 1e-12);
        assert!((uv_to_direction(0.3, 1.0) - DVec3::NEG_Y).length() < 1e-12);
    }

    #[test]
    fn direction_to_uv_inverts_the_mapping() {
        for i in 0..50 {
            for j in 1..25 {
                let (u, v) = (i as f64 / 50.0, j as f64 / 25.0);
                let (u2, v2) = direction_to_uv(uv_to_direction(u, v));
                assert!((u - u2).abs() < 1e-9 && (v - v2).abs() < 1e-9, "{u} {v} -> {u2} {v2}");
            }
        }
    }

    #[test]
    fn bilinear_lookup_hits_texel_centres_and_wraps() {
        let mut image = RgbImage::new(8, 4);
        for y in 0..4 {
            for x in 0..8 {
                image.set(x, y, [x as f32, y as f32, 1.0]);
            }
        }
        let map = EnvironmentMap { image };
        let at = map.lookup(map.texel_direction(5, 2));
        assert!((at - DVec3::new(5.0, 2.0, 1.0)).length() < 1e-9);
        // Halfway between the last and first column wraps around: mean of 7 and 0.
        let wrap = map.lookup(uv_to_direction(1.0 - 1e-12, (2.5) / 4.0));
        assert!((wrap.x - 3.5).abs() < 1e-6, "{wrap}");
        let solid: f64 = (0..4).map(|y| map.texel_solid_angle(y) * 8.0).sum();
        assert!((solid - 4.0 * PI).abs() < 1e-12);
    }
}
