//! Environment light on a Lambertian point, estimated per pixel without bias: directions drawn
//! from the map itself (a piecewise-constant distribution over its full-resolution texels, by
//! luminance above the map's mean times solid angle: MIS compensation) and from the cosine
//! lobe around the normal, combined by multiple importance sampling with the balance
//! heuristic, both on randomly shifted rank-1 lattices; visibility is the Gaussians' closed-form transmittance (`ShadowCaster`,
//! culled). Every pixel draws from its own stream, so a view's error is noise that falls as
//! 1/sqrt(samples), never a pattern shared by all its pixels. Uniform light is the same
//! estimator on a one-texel map.

use crate::imageio::RgbImage;
use crate::light::{direction_to_uv, uv_to_direction, EnvironmentMap};
use crate::random::Stream;
use crate::shading::SHADOW_START;
use crate::shadow::PosedGaussian;
use crate::shadow::{ShadowCaster, ShadowRay};
use glam::DVec3;
use rayon::prelude::*;
use std::borrow::Cow;
use std::f64::consts::PI;

fn luminance(p: [f32; 3]) -> f64 {
    (0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64).max(0.0)
}

/// The map's texels as a distribution over directions: probability of a texel proportional to
/// its luminance times its solid angle, uniform in solid angle within it.
pub struct SkyDistribution {
    width: usize,
    height: usize,
    /// Cumulative probability over the texels in row-major order (one 1D distribution, so a
    /// stratified first number stratifies the whole sphere, as the shared sampler did).
    cumulative: Vec<f64>,
    /// Probability of each texel.
    texel: Vec<f64>,
    solid_angle: Vec<f64>,
    /// The share of the map's light (luminance times solid angle) this distribution holds.
    pub share: f64,
}

impl SkyDistribution {
    /// `None` when the map has no light at all (every texel black).
    pub fn new(map: &EnvironmentMap) -> Option<Self> {
        Self::build(map, false)
    }

    /// MIS compensation (Karlik et al. 2019): texels by their luminance above the map's mean,
    /// so the map's samples go where it is brighter than average and the cosine lobe, which
    /// MIS combines with it, covers the rest. `None` for a map with nothing above its mean
    /// (uniform light): the cosine lobe alone is then the better technique.
    pub fn compensated(map: &EnvironmentMap) -> Option<Self> {
        Self::build(map, true)
    }

    fn build(map: &EnvironmentMap, compensate: bool) -> Option<Self> {
        let (w, h) = (map.image.width, map.image.height);
        let solid_angle: Vec<f64> = (0..h).map(|y| map.texel_solid_angle(y)).collect();
        let light: f64 = (0..w * h).map(|k| luminance(map.image.pixels[k]) * solid_angle[k / w]).sum();
        let floor = if compensate { light / (4.0 * PI) } else { 0.0 };
        // The floor is relative, so rounding cannot leave a uniform map a speck of mass.
        let mass: Vec<f64> = (0..w * h).map(|k| (luminance(map.image.pixels[k]) - floor * (1.0 + 1e-9)).max(0.0) * solid_angle[k / w]).collect();
        let total: f64 = mass.iter().sum();
        if !(total > 0.0) || !total.is_finite() {
            return None;
        }
        let mut cumulative = Vec::with_capacity(w * h);
        let mut running = 0.0;
        for m in &mass {
            running += m / total;
            cumulative.push(running);
        }
        Some(Self { width: w, height: h, cumulative, texel: mass.iter().map(|m| m / total).collect(), solid_angle, share: total / light })
    }

    /// A direction for three uniform numbers (the first picks the texel, the other two the
    /// point within it, uniform in solid angle), and its pdf per steradian.
    pub fn sample(&self, u: [f64; 3]) -> (DVec3, f64) {
        let texel = self.cumulative.partition_point(|&c| c < u[0]).min(self.texel.len() - 1);
        let (x, y) = (texel % self.width, texel / self.width);
        let h = self.height as f64;
        let (c0, c1) = ((y as f64 / h * PI).cos(), ((y + 1) as f64 / h * PI).cos());
        let cosine = (c0 + (c1 - c0) * u[2]).clamp(-1.0, 1.0);
        let direction = uv_to_direction((x as f64 + u[1]) / self.width as f64, cosine.acos() / PI);
        (direction, self.texel[texel] / self.solid_angle[y])
    }

    /// The pdf per steradian of drawing `direction`.
    pub fn pdf(&self, direction: DVec3) -> f64 {
        let (u, v) = direction_to_uv(direction);
        let x = ((u * self.width as f64) as usize).min(self.width - 1);
        let y = ((v * self.height as f64) as usize).min(self.height - 1);
        self.texel[y * self.width + x] / self.solid_angle[y]
    }
}

/// A direction about `normal` drawn with pdf cos(theta) / pi.
pub fn cosine_sample(normal: DVec3, u: [f64; 2]) -> DVec3 {
    let (tangent, bitangent) = normal.any_orthonormal_pair();
    let r = u[0].sqrt();
    let phi = 2.0 * PI * u[1];
    (tangent * (r * phi.cos()) + bitangent * (r * phi.sin()) + normal * (1.0 - u[0]).max(0.0).sqrt()).normalize()
}

/// The per-pixel estimator of an environment (or uniform) light. It borrows the scene's map
/// (a full-resolution sky is tens of megabytes: not copied per view).
pub struct MisEstimator<'a> {
    map: Cow<'a, EnvironmentMap>,
    scale: f64,
    /// The map's compensated distribution; `None`: cosine sampling alone.
    distribution: Option<SkyDistribution>,
    /// False for a black map (nothing to estimate).
    lit: bool,
    samples: usize,
    seed: u64,
    /// Where visibility rays start off the surface (m).
    shadow_start: f32,
}

impl<'a> MisEstimator<'a> {
    /// `samples` directions per point, split between the map and the cosine lobe.
    pub fn new(map: &'a EnvironmentMap, scale: f64, samples: usize, seed: u64) -> Self {
        Self::over(Cow::Borrowed(map), scale, samples, seed)
    }

    /// Uniform radiance from every direction: a one-texel map.
    pub fn uniform(radiance: DVec3, samples: usize, seed: u64) -> Self {
        let image = RgbImage { width: 1, height: 1, pixels: vec![radiance.as_vec3().to_array()] };
        Self::over(Cow::Owned(EnvironmentMap { image }), 1.0, samples, seed)
    }

    fn over(map: Cow<'a, EnvironmentMap>, scale: f64, samples: usize, seed: u64) -> Self {
        let lit = map.image.pixels.iter().any(|p| luminance(*p) > 0.0);
        let distribution = SkyDistribution::compensated(&map);
        Self { map, scale, distribution, lit, samples: samples.max(1), seed, shadow_start: SHADOW_START }
    }

    /// Visibility rays start `start` (m) off the surface instead of the reference human's
    /// `SHADOW_START` (a fitted body's own, `FittedLight::shadow_start`).
    pub fn with_shadow_start(self, start: f32) -> Self {
        Self { shadow_start: start, ..self }
    }

    /// Outgoing radiance over albedo at each point (Lambertian, `1/pi` BRDF):
    /// `(1/pi) integral L(w) max(0, n.w) T(x, w) dw`. `ids` name each point's stream (the pixel
    /// index), so an image is the same whatever the order or chunking of its pixels.
    pub fn shade(&self, points: &[DVec3], normals: &[DVec3], ids: &[u64], casters: &[PosedGaussian]) -> Vec<DVec3> {
        let caster = ShadowCaster::new(casters, 1e-4);
        points.par_iter().zip(normals).zip(ids).map(|((&x, &n), &id)| self.estimate(x, n, id, &caster)).collect()
    }

    fn estimate(&self, x: DVec3, n: DVec3, id: u64, caster: &ShadowCaster) -> DVec3 {
        let mut stream = Stream::new(self.seed, id, 0x315);
        if !self.lit {
            return DVec3::ZERO;
        }
        // The map's technique gets the share of the samples that its distribution holds of the
        // map's light (above the mean: most of a sunny sky's, little of an overcast one's),
        // within [1/4, 3/4] so that neither technique starves.
        let light_count = match &self.distribution {
            Some(d) => ((self.samples as f64 * d.share.clamp(0.25, 0.75)).round() as usize).min(self.samples),
            None => 0,
        };
        let cosine_count = self.samples - light_count;
        let origin = (x + n * self.shadow_start as f64).as_vec3().to_array();
        let shares = caster.shares_at(x.as_vec3().to_array());
        let visible = |d: DVec3| {
            let ray = ShadowRay { origin, direction: d.as_vec3().to_array(), t0: self.shadow_start, t1: f32::INFINITY };
            caster.transmittance_from(&shares, &ray, true) as f64
        };
        let (nl, nc) = (light_count as f64, cosine_count as f64);
        let mut sum = DVec3::ZERO;
        // Each sample of either technique adds f / (n_l p_l + n_c p_c): the balance heuristic.
        let mut add = |d: DVec3, p_light: f64| {
            let cosine = n.dot(d);
            if cosine <= 0.0 {
                return;
            }
            let denominator = nl * p_light + nc * cosine / PI;
            if denominator > 0.0 {
                sum += self.map.lookup(d) * (self.scale * cosine / PI * visible(d) / denominator);
            }
        };
        // Both techniques on rank-1 lattices (golden-ratio steps) turned by this pixel's random
        // shift: stratified in every dimension, still unbiased.
        let shift = [stream.uniform(), stream.uniform(), stream.uniform()];
        if let Some(distribution) = &self.distribution {
            for k in 0..light_count {
                let (d, p) = distribution.sample(lattice(k, light_count, shift));
                add(d, p);
            }
        }
        let shift = [stream.uniform(), stream.uniform(), stream.uniform()];
        for k in 0..cosine_count {
            let u = lattice(k, cosine_count, shift);
            let d = cosine_sample(n, [u[0], u[1]]);
            add(d, self.distribution.as_ref().map_or(0.0, |distribution| distribution.pdf(d)));
        }
        sum
    }
}

/// Point `k` of `n` of a randomly shifted rank-1 lattice in [0, 1)^3: `k / n` in the first
/// coordinate, steps by the generalised golden ratio's powers in the others (the R3 sequence).
fn lattice(k: usize, n: usize, shift: [f64; 3]) -> [f64; 3] {
    // 1/g, 1/g^2 for g the real root of x^4 = x + 1 (Roberts' R-sequence in three dimensions).
    const A: [f64; 2] = [0.819_172_513_396_164_4, 0.671_043_606_703_789_1];
    let frac = |v: f64| v - v.floor();
    [frac(k as f64 / n as f64 + shift[0]), frac(k as f64 * A[0] + shift[1]), frac(k as f64 * A[1] + shift[2])]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(width: usize, height: usize, f: impl Fn(DVec3) -> f32) -> EnvironmentMap {
        let mut image = RgbImage::new(width, height);
        let probe = EnvironmentMap { image: RgbImage::new(width, height) };
        for y in 0..height {
            for x in 0..width {
                let v = f(probe.texel_direction(x, y));
                image.pixels[y * width + x] = [v, v * 0.8, v * 0.6];
            }
        }
        EnvironmentMap { image }
    }

    #[test]
    fn the_distribution_samples_what_its_pdf_says() {
        let sky = map(32, 16, |d| 0.2 + (d.y.max(0.0) as f32).powi(8) * 50.0);
        let distribution = SkyDistribution::new(&sky).unwrap();
        let mut stream = Stream::new(1, 2, 3);
        // E[1 / pdf] over the distribution is the measure of its support: 4 pi.
        let n = 200_000;
        let mut mean = 0.0;
        for _ in 0..n {
            let (d, p) = distribution.sample([stream.uniform(), stream.uniform(), stream.uniform()]);
            assert!((distribution.pdf(d) / p - 1.0).abs() < 1e-6 || (d.y.abs() > 0.999), "pdf of a sample");
            mean += 1.0 / p;
        }
        assert!((mean / n as f64 / (4.0 * PI) - 1.0).abs() < 0.01, "{}", mean / n as f64);
        assert!(SkyDistribution::new(&map(8, 4, |_| 0.0)).is_none());
    }

    #[test]
    fn furnace_a_white_sky_and_no_occluder_give_back_its_radiance() {
        // Uniform radiance 1: (1/pi) integral cos = 1 whatever the normal. Unbiased: the mean
        // over many pixels' independent estimates is 1 (the standard error at 16 samples and
        // 2,000 pixels is below 0.3%).
        let estimator = MisEstimator::uniform(DVec3::ONE, 16, 4);
        let ids: Vec<u64> = (0..2000).collect();
        for normal in [DVec3::Y, DVec3::new(0.3, -0.9, 0.2).normalize(), DVec3::X] {
            let values = estimator.shade(&vec![DVec3::ZERO; 2000], &vec![normal; 2000], &ids, &[]);
            let mean = values.iter().sum::<DVec3>() / 2000.0;
            assert!((mean - DVec3::ONE).abs().max_element() < 0.01, "{normal}: {mean}");
        }
        // A map with structure and no occluder: the estimate converges to the quadrature.
        let sky = map(64, 32, |d| 0.3 + (d.dot(DVec3::new(0.3, 0.8, 0.5).normalize()).max(0.0) as f32).powi(200) * 400.0);
        let n = DVec3::new(0.2, 0.9, -0.1).normalize();
        let mut exact = DVec3::ZERO;
        for y in 0..32 {
            for x in 0..64 {
                // The bilinear lookup, integrated per texel by a 4x4 sub-grid.
                for (i, j) in (0..16).map(|k| (k % 4, k / 4)) {
                    let d = uv_to_direction((x as f64 + (i as f64 + 0.5) / 4.0) / 64.0, (y as f64 + (j as f64 + 0.5) / 4.0) / 32.0);
                    exact += sky.lookup(d) * n.dot(d).max(0.0) / PI * sky.texel_solid_angle(y) / 16.0;
                }
            }
        }
        let estimator = MisEstimator::new(&sky, 1.0, 256, 7);
        let ids: Vec<u64> = (0..400).collect();
        let values = estimator.shade(&vec![DVec3::ZERO; 400], &vec![n; 400], &ids, &[]);
        let mean = values.iter().sum::<DVec3>() / 400.0;
        assert!(((mean - exact) / exact).abs().max_element() < 0.01, "{mean} against {exact}");
    }
}
