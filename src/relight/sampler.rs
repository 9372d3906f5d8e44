//! The environment benchmark's baseline estimator: one stratified set of sky directions shared by
//! every pixel of a view.

use crate::light::{uv_to_direction, EnvironmentMap};
use crate::random::Stream;
use crate::shading::SHADOW_START;
use crate::shadow::PosedGaussian;
use crate::shadow::{ShadowCaster, ShadowRay};
use glam::DVec3;
use rayon::prelude::*;
use std::f64::consts::PI;

/// A fixed set of directions drawn from an environment's radiance (times texel solid angle),
/// stratified, with their radiance over pdf, shared by every pixel of a view (its error is that
/// of a `count`-point quadrature of the sky, the same in every pixel). Renders now use the
/// per-pixel `environment::MisEstimator`; this one stays as the environment benchmark's
/// baseline.
pub struct EnvironmentSampler {
    directions: Vec<DVec3>,
    /// Radiance divided by the pdf (per steradian) of each direction.
    weights: Vec<DVec3>,
}

impl EnvironmentSampler {
    pub fn new(map: &EnvironmentMap, scale: f64, count: usize, seed: u64) -> Self {
        let (w, h) = (map.image.width, map.image.height);
        let luminance = |p: [f32; 3]| (0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]).max(0.0) as f64;
        let mean = (0..w * h).map(|k| luminance(map.image.pixels[k])).sum::<f64>() / (w * h) as f64;
        // A floor so that dim texels are still sampled now and then (no direction has pdf 0).
        let mass: Vec<f64> = (0..w * h).map(|k| (luminance(map.image.pixels[k]) + 0.05 * mean + 1e-12) * map.texel_solid_angle(k / w)).collect();
        let total: f64 = mass.iter().sum();
        let mut cumulative = Vec::with_capacity(mass.len());
        let mut running = 0.0;
        for m in &mass {
            running += m / total;
            cumulative.push(running);
        }
        let mut stream = Stream::new(seed, 0xE4F, 1);
        let mut directions = Vec::with_capacity(count);
        let mut weights = Vec::with_capacity(count);
        for k in 0..count {
            let target = (k as f64 + stream.uniform()) / count as f64;
            let texel = cumulative.partition_point(|&c| c < target).min(mass.len() - 1);
            let (x, y) = (texel % w, texel / w);
            // Uniform in solid angle within the texel: uniform in u and in cos(theta).
            let u = (x as f64 + stream.uniform()) / w as f64;
            let (c0, c1) = ((y as f64 / h as f64 * PI).cos(), ((y + 1) as f64 / h as f64 * PI).cos());
            let cosine = c0 + (c1 - c0) * stream.uniform();
            let direction = uv_to_direction(u, cosine.clamp(-1.0, 1.0).acos() / PI);
            let pdf = mass[texel] / total / map.texel_solid_angle(y);
            directions.push(direction);
            weights.push(map.lookup(direction) * scale / pdf);
        }
        Self { directions, weights }
    }

    /// Uniform radiance from every direction, as a sampler: a spherical Fibonacci lattice
    /// (even in every direction, so any normal's hemisphere gets its share), randomly turned.
    pub fn uniform(radiance: DVec3, count: usize, seed: u64) -> Self {
        let mut stream = Stream::new(seed, 0xE4F, 2);
        let directions = crate::light::fibonacci_sphere(count, 2.0 * PI * stream.uniform());
        Self { weights: vec![radiance * 4.0 * PI; count], directions }
    }

    pub fn len(&self) -> usize {
        self.directions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.directions.is_empty()
    }

    /// `shade` at a point of a surface outside the Gaussians (a ground): every Gaussian may
    /// shadow it (none is its own), and with no `caster` nothing does.
    pub fn shade_outside(&self, x: DVec3, n: DVec3, caster: Option<&ShadowCaster>) -> DVec3 {
        let origin = (x + n * SHADOW_START as f64).as_vec3().to_array();
        let mut sum = DVec3::ZERO;
        for (d, weight) in self.directions.iter().zip(&self.weights) {
            let cosine = n.dot(*d);
            if cosine <= 0.0 {
                continue;
            }
            let ray = ShadowRay { origin, direction: d.as_vec3().to_array(), t0: 0.0, t1: f32::INFINITY };
            sum += *weight * cosine * caster.map_or(1.0, |c| c.transmittance(&ray, true) as f64);
        }
        sum / (PI * self.len().max(1) as f64)
    }

    /// Outgoing radiance over albedo at each surface point (Lambertian, `1/pi` BRDF):
    /// `(1 / (pi N)) sum_i L_i max(0, n . w_i) T(x, w_i) / p_i`, T from the Gaussians.
    pub fn shade(&self, points: &[DVec3], normals: &[DVec3], casters: &[PosedGaussian]) -> Vec<DVec3> {
        let caster = ShadowCaster::new(casters, 1e-4);
        points
            .par_iter()
            .zip(normals)
            .map(|(&x, &n)| {
                let origin = (x + n * SHADOW_START as f64).as_vec3().to_array();
                let shares = caster.shares_at(x.as_vec3().to_array());
                let mut sum = DVec3::ZERO;
                for (d, weight) in self.directions.iter().zip(&self.weights) {
                    let cosine = n.dot(*d);
                    if cosine <= 0.0 {
                        continue;
                    }
                    let ray = ShadowRay { origin, direction: d.as_vec3().to_array(), t0: SHADOW_START, t1: f32::INFINITY };
                    sum += *weight * cosine * caster.transmittance_from(&shares, &ray, true) as f64;
                }
                sum / (PI * self.len().max(1) as f64)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imageio::RgbImage;
    use crate::light::{albedo_scale, Light};
    use glam::DMat3;

    fn constant_map(value: f32) -> EnvironmentMap {
        let mut image = RgbImage::new(16, 8);
        image.pixels.iter_mut().for_each(|p| *p = [value, value * 0.5, value * 0.25]);
        EnvironmentMap { image }
    }

    /// Dense quadrature over every texel of `(1/pi) sum L max(0, n.d) T(d) dOmega`, T by the f64
    /// closed form from `x` (less its own Gaussians' shares): the reference the sampled estimate
    /// must approach.
    fn quadrature(map: &EnvironmentMap, scale: f64, x: DVec3, n: DVec3, casters: &[PosedGaussian]) -> DVec3 {
        let (w, h) = (map.image.width, map.image.height);
        let mut sum = DVec3::ZERO;
        for y in 0..h {
            for column in 0..w {
                let d = map.texel_direction(column, y);
                let cosine = n.dot(d);
                if cosine <= 0.0 {
                    continue;
                }
                let origin = (x + n * SHADOW_START as f64).as_vec3().to_array();
                let ray = ShadowRay { origin, direction: d.as_vec3().to_array(), t0: SHADOW_START, t1: f32::INFINITY };
                let t = crate::shadow::transmittance_f64_from(casters, x, &ray);
                let p = map.image.get(column, y);
                sum += DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) * cosine * t * map.texel_solid_angle(y);
            }
        }
        sum * scale / PI
    }

    fn close(a: DVec3, b: DVec3, tolerance: f64) {
        assert!((a - b).abs().max_element() <= tolerance * b.abs().max_element().max(1e-3), "{a} vs {b}");
    }

    #[test]
    fn uniform_light_gives_its_radiance_on_an_open_surface() {
        let radiance = DVec3::new(0.8, 0.4, 0.2);
        let normals = [DVec3::Y, DVec3::X, DVec3::new(0.3, -0.5, 0.8).normalize()];
        let points = [DVec3::ZERO; 3];
        for sampler in [EnvironmentSampler::uniform(radiance, 512, 1), EnvironmentSampler::new(&constant_map(0.8), 1.0, 512, 1)] {
            for value in sampler.shade(&points, &normals, &[]) {
                close(value, radiance, 0.02);
            }
        }
    }

    /// The body the test points lie on: a 5 cm Gaussian just under the origin, whose share of
    /// the density there is all but 1, so it shadows none of them (`shadow::own_shares`).
    fn surface() -> PosedGaussian {
        PosedGaussian { mean: DVec3::new(0.0, -0.05, 0.0), axes: DMat3::IDENTITY, scales: DVec3::splat(0.05), amplitude: 20.0 }
    }

    #[test]
    fn sampled_sky_matches_dense_quadrature_with_and_without_an_occluder() {
        let map = crate::synth::synthetic_sky(64, 32);
        let sampler = EnvironmentSampler::new(&map, 1.5, 4096, 7);
        let blob = PosedGaussian { mean: DVec3::new(0.1, 0.6, -0.2), axes: DMat3::IDENTITY, scales: DVec3::new(0.3, 0.1, 0.3), amplitude: 20.0 };
        let normals = [DVec3::Y, DVec3::new(0.5, 0.55, -0.67).normalize(), DVec3::new(-0.7, 0.2, 0.3).normalize()];
        let points = [DVec3::ZERO; 3];
        for casters in [vec![surface()], vec![surface(), blob]] {
            let sampled = sampler.shade(&points, &normals, &casters);
            for (k, n) in normals.iter().enumerate() {
                close(sampled[k], quadrature(&map, 1.5, points[k], *n, &casters), 0.05);
            }
        }
        // The occluder must matter, or the second pass tested nothing.
        let open = sampler.shade(&points[..1], &normals[..1], &[])[0];
        let shaded = sampler.shade(&points[..1], &normals[..1], &[surface(), blob])[0];
        assert!(shaded.x < 0.7 * open.x, "{shaded} vs {open}");
        // And the body the point lies on does not shadow it.
        let on_body = sampler.shade(&points[..1], &normals[..1], &[surface()])[0];
        close(on_body, open, 1e-6);
    }

    #[test]
    fn per_pixel_mis_matches_dense_quadrature_and_converges_with_samples() {
        let map = crate::synth::synthetic_sky(64, 32);
        let blob = PosedGaussian { mean: DVec3::new(0.1, 0.6, -0.2), axes: DMat3::IDENTITY, scales: DVec3::new(0.3, 0.1, 0.3), amplitude: 20.0 };
        let n = DVec3::new(0.5, 0.55, -0.67).normalize();
        let pixels = 256;
        let ids: Vec<u64> = (0..pixels as u64).collect();
        let (points, normals) = (vec![DVec3::ZERO; pixels], vec![n; pixels]);
        for casters in [vec![surface()], vec![surface(), blob]] {
            let exact = quadrature(&map, 1.5, DVec3::ZERO, n, &casters);
            let mut errors = Vec::new();
            for spp in [16, 64, 256] {
                let values = crate::environment::MisEstimator::new(&map, 1.5, spp, 3).shade(&points, &normals, &ids, &casters);
                let mean = values.iter().sum::<DVec3>() / pixels as f64;
                // Unbiased: the mean over pixels lands on the quadrature (which integrates the
                // texels at their centres, so a percent or two apart at this resolution).
                close(mean, exact, 0.03);
                errors.push((values.iter().map(|v| (*v - exact).length_squared()).sum::<f64>() / pixels as f64).sqrt() / exact.length());
            }
            // Per-pixel noise falls about as 1/sqrt(samples): 4x the samples, about half the error.
            assert!(errors[1] < 0.65 * errors[0] && errors[2] < 0.65 * errors[1], "{errors:?}");
        }
    }

    #[test]
    fn albedo_scale_undoes_the_training_light_strength() {
        let sun = Light::Directional { direction: DVec3::Y, irradiance: DVec3::new(0.5, 1.0, 2.0), ambient: DVec3::ZERO };
        close(albedo_scale(&sun, None), DVec3::new(2.0, 1.0, 0.5), 1e-12);
        let lamp = Light::Point { position: DVec3::ZERO, intensity: DVec3::splat(4.0), ambient: DVec3::ZERO };
        close(albedo_scale(&lamp, Some(8.0)), DVec3::splat(2.0), 1e-12);
        let sky = Light::Environment { path: "sky.exr".into(), scale: 2.0, map: constant_map(0.8) };
        close(albedo_scale(&sky, None), DVec3::new(1.0 / 1.6, 1.0 / 0.8, 1.0 / 0.4), 1e-6);
    }
}
