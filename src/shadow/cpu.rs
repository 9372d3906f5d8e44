//! Transmittance of a posed Gaussian set along many rays on the CPU (f32, threads over rays),
//! for rendering and relighting. Gaussians that cannot change a ray's optical depth by more
//! than a stated tolerance are skipped by a bounding-sphere test.

use super::integral::{optical_depth_whitened, WhitenedGaussian};
use crate::gaussians::PosedGaussian;
use rayon::prelude::*;

/// A ray segment `origin + t direction`, `t` in `[t0, t1]` (`t1` may be infinite).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShadowRay {
    pub origin: [f32; 3],
    pub direction: [f32; 3],
    pub t0: f32,
    pub t1: f32,
}

/// A posed Gaussian set prepared for fast shadow queries.
pub struct ShadowCaster {
    gaussians: Vec<WhitenedGaussian<f32>>,
    /// Squared radius beyond which a Gaussian adds less than `tolerance / n` optical depth.
    cull_radius_squared: Vec<f32>,
    tolerance: f64,
}

/// Optical depth a Gaussian can add to any segment whose closest point is `r` from its mean:
/// `A s sqrt(2 pi) exp(-r^2 / (2 s^2))`, s its largest scale. Solved for r at `budget`.
fn cull_radius_squared(g: &PosedGaussian, budget: f64) -> f64 {
    let s = g.scales.max_element().max(super::MIN_SCALE);
    let peak = g.amplitude * s * (2.0 * std::f64::consts::PI).sqrt();
    if peak <= budget {
        return -1.0; // never contributes more than the budget: always skipped
    }
    2.0 * s * s * (peak / budget).ln()
}

impl ShadowCaster {
    /// `tolerance` bounds the total error culling may add to any ray's optical depth (and so to
    /// its transmittance, since |exp(-x) - exp(-y)| <= |x - y| for x, y >= 0).
    pub fn new(gaussians: &[PosedGaussian], tolerance: f64) -> Self {
        let budget = tolerance / gaussians.len().max(1) as f64;
        Self {
            gaussians: gaussians.iter().map(|g| WhitenedGaussian::new(g.mean.to_array(), g.rotation_columns(), g.scales.to_array(), g.amplitude)).collect(),
            cull_radius_squared: gaussians.iter().map(|g| cull_radius_squared(g, budget) as f32).collect(),
            tolerance,
        }
    }

    pub fn tolerance(&self) -> f64 {
        self.tolerance
    }

    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

    /// Sum of every Gaussian's optical depth along the ray, culling when `cull` is set.
    /// Returns the depth and the number of Gaussians actually integrated.
    pub fn optical_depth(&self, ray: &ShadowRay, cull: bool) -> (f32, usize) {
        let mut total = 0.0f32;
        let mut integrated = 0;
        for (g, &radius2) in self.gaussians.iter().zip(&self.cull_radius_squared) {
            if cull && !segment_within(g.mean, ray, radius2) {
                continue;
            }
            integrated += 1;
            total += optical_depth_whitened(g, ray.origin, ray.direction, ray.t0, ray.t1);
        }
        (total, integrated)
    }

    pub fn transmittance(&self, ray: &ShadowRay, cull: bool) -> f32 {
        (-self.optical_depth(ray, cull).0).exp()
    }

    /// Transmittance along every ray, in parallel.
    pub fn transmittance_all(&self, rays: &[ShadowRay], cull: bool) -> Vec<f32> {
        rays.par_iter().with_min_len(64).map(|r| self.transmittance(r, cull)).collect()
    }
}

/// Whether the segment comes within `sqrt(radius2)` of `centre`.
#[inline]
fn segment_within(centre: [f32; 3], ray: &ShadowRay, radius2: f32) -> bool {
    if radius2 < 0.0 {
        return false;
    }
    let v = [centre[0] - ray.origin[0], centre[1] - ray.origin[1], centre[2] - ray.origin[2]];
    let along = (v[0] * ray.direction[0] + v[1] * ray.direction[1] + v[2] * ray.direction[2]).clamp(ray.t0, ray.t1);
    let d = [v[0] - along * ray.direction[0], v[1] - along * ray.direction[1], v[2] - along * ray.direction[2]];
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= radius2
}

/// Transmittance of a ray through posed Gaussians with every integral in f64 and no culling:
/// the reference the f32 paths are measured against.
pub fn transmittance_f64(gaussians: &[PosedGaussian], ray: &ShadowRay) -> f64 {
    let origin = ray.origin.map(f64::from);
    let direction = ray.direction.map(f64::from);
    let tau: f64 = gaussians
        .iter()
        .map(|g| {
            super::optical_depth(g.mean.to_array(), g.rotation_columns(), g.scales.to_array(), g.amplitude, origin, direction, ray.t0 as f64, ray.t1 as f64)
        })
        .sum();
    (-tau).exp()
}
