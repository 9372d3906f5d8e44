//! Transmittance of a posed Gaussian set along many rays on the CPU (f32, threads over rays),
//! for rendering and relighting. Gaussians that cannot change a ray's optical depth by more
//! than a stated tolerance are skipped by a bounding-sphere test, and the rest are integrated
//! eight at a time by the vector kernel of `lanes` (the scalar integral takes the pairs that
//! kernel cannot do to the same accuracy).

use super::integral::{optical_depth_whitened, WhitenedGaussian};
use super::lanes::{self, Block, Collected, Group, LANES};
use super::ray::{segment_within, ShadowRay};
use crate::shadow::PosedGaussian;
use rayon::prelude::*;

/// A posed Gaussian set prepared for fast shadow queries.
pub struct ShadowCaster {
    gaussians: Vec<WhitenedGaussian<f32>>,
    /// Squared radius beyond which a Gaussian adds less than `tolerance / n` optical depth.
    cull_radius_squared: Vec<f32>,
    /// The same Gaussians, eight to a block, for the vector kernel.
    blocks: Vec<Block>,
    /// The blocks in groups under bounding spheres, for culling.
    groups: Vec<Group>,
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
    /// `tolerance` bounds the total error culling and the f32 vector kernel may add to any
    /// ray's optical depth (and so to its transmittance, since |exp(-x) - exp(-y)| <= |x - y|
    /// for x, y >= 0): each Gaussian gets half of `tolerance / n` for each.
    /// The Gaussians are kept in Morton order of their means, so that the eight in a block sit
    /// near each other and a ray that misses the block's bounding sphere skips all eight.
    pub fn new(gaussians: &[PosedGaussian], tolerance: f64) -> Self {
        let budget = tolerance / (2 * gaussians.len().max(1)) as f64;
        let order = morton_order(gaussians);
        let whitened: Vec<WhitenedGaussian<f32>> = order
            .iter()
            .map(|&i| &gaussians[i])
            .map(|g| WhitenedGaussian::new(g.mean.to_array(), g.rotation_columns(), g.scales.to_array(), g.amplitude))
            .collect();
        let cull_radius_squared: Vec<f32> = order.iter().map(|&i| cull_radius_squared(&gaussians[i], budget) as f32).collect();
        let blocks: Vec<Block> = whitened.chunks(LANES).zip(cull_radius_squared.chunks(LANES)).map(|(g, r)| Block::pack(g, r)).collect();
        let groups = lanes::group(&blocks, lanes::group_size(blocks.len()));
        Self { gaussians: whitened, cull_radius_squared, blocks, groups, tolerance }
    }

    /// The same caster with its blocks in groups of `size` (1: every block's sphere tested on
    /// its own, as before there were groups), for the benchmark and the tests.
    pub fn with_group_size(mut self, size: usize) -> Self {
        self.groups = lanes::group(&self.blocks, size);
        self
    }

    /// The absolute error the vector kernel may add per Gaussian.
    fn lane_budget(&self) -> f32 {
        (self.tolerance / (2 * self.gaussians.len().max(1)) as f64) as f32
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

    /// Sum of every Gaussian's optical depth along the ray, culling when `cull` is set, by the
    /// vector kernel. Returns the depth and the number of Gaussians actually integrated.
    pub fn optical_depth(&self, ray: &ShadowRay, cull: bool) -> (f32, usize) {
        let c = self.collect(ray, cull);
        (c.depth, c.integrated)
    }

    /// The vector kernel's sum with its counts (how many pairs went to the scalar integral).
    pub fn collect(&self, ray: &ShadowRay, cull: bool) -> Collected {
        lanes::optical_depth(&self.blocks, &self.groups, &self.gaussians, ray, cull, self.lane_budget())
    }

    /// The same sum by one build of the kernel (`None` where this CPU lacks it), to pin the
    /// builds to each other and time them.
    pub fn collect_built(&self, build: lanes::Build, ray: &ShadowRay, cull: bool) -> Option<Collected> {
        lanes::optical_depth_built(build, &self.blocks, &self.groups, &self.gaussians, ray, cull, self.lane_budget())
    }

    /// The same sum one Gaussian at a time by the scalar integral (f64 geometry, libm erfc):
    /// the reference the vector kernel is measured against.
    pub fn optical_depth_scalar(&self, ray: &ShadowRay, cull: bool) -> (f32, usize) {
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

    /// The Gaussians that make the density at a surface point `x`, each with its share of the
    /// mixture's density there (shares below `OWN_SHARE_FLOOR` left out): what
    /// `transmittance_from` does not let shadow `x` (`own_shares`).
    pub fn shares_at(&self, x: [f32; 3]) -> Vec<(usize, f32)> {
        own_shares(self.gaussians.iter().map(|g| g.log_density(x) as f64)).into_iter().map(|(g, s)| (g, s as f32)).collect()
    }

    /// Transmittance along a shadow ray from the surface point whose `shares_at` are `shares`:
    /// each Gaussian's optical depth weighted by one less its share there, so a body part does
    /// not shadow the surface it makes (`own_shares`). The kernel's sum (culled when `cull`)
    /// less the owners' weighted integrals, which the scalar integral takes exactly.
    pub fn transmittance_from(&self, shares: &[(usize, f32)], ray: &ShadowRay, cull: bool) -> f32 {
        let depth = self.optical_depth(ray, cull).0;
        let own: f32 = shares.iter().map(|&(g, share)| share * optical_depth_whitened(&self.gaussians[g], ray.origin, ray.direction, ray.t0, ray.t1)).sum();
        (-(depth - own).max(0.0)).exp()
    }

    /// Transmittance along every ray, in parallel.
    pub fn transmittance_all(&self, rays: &[ShadowRay], cull: bool) -> Vec<f32> {
        rays.par_iter().with_min_len(64).map(|r| self.transmittance(r, cull)).collect()
    }

    /// The Gaussians (whitened, f32) whose cull sphere the ray's segment passes through: the
    /// set the closed form integrates with culling on, for a ray marcher to use the same one.
    pub fn touching(&self, ray: &ShadowRay) -> Vec<&WhitenedGaussian<f32>> {
        self.gaussians.iter().zip(&self.cull_radius_squared).filter(|(g, &r2)| segment_within(g.mean, ray, r2)).map(|(g, _)| g).collect()
    }

    /// Every Gaussian, whitened in f32.
    pub fn whitened(&self) -> &[WhitenedGaussian<f32>] {
        &self.gaussians
    }

    /// Transmittance along every ray by the scalar integral, in parallel.
    pub fn transmittance_all_scalar(&self, rays: &[ShadowRay], cull: bool) -> Vec<f32> {
        rays.par_iter().with_min_len(64).map(|r| (-self.optical_depth_scalar(r, cull).0).exp()).collect()
    }
}

/// Indices of `gaussians` sorted along a Z-order curve through their means' bounding box
/// (10 bits per axis).
fn morton_order(gaussians: &[PosedGaussian]) -> Vec<usize> {
    let (lo, hi) =
        gaussians.iter().fold((glam::DVec3::splat(f64::INFINITY), glam::DVec3::splat(f64::NEG_INFINITY)), |(lo, hi), g| (lo.min(g.mean), hi.max(g.mean)));
    let size = (hi - lo).max(glam::DVec3::splat(1e-12));
    let spread = |v: u32| (0..10).fold(0u32, |code, bit| code | (((v >> bit) & 1) << (3 * bit)));
    let code = |g: &PosedGaussian| {
        let q = ((g.mean - lo) / size * 1023.0).clamp(glam::DVec3::ZERO, glam::DVec3::splat(1023.0));
        spread(q.x as u32) | (spread(q.y as u32) << 1) | (spread(q.z as u32) << 2)
    };
    let mut order: Vec<usize> = (0..gaussians.len()).collect();
    order.sort_by_key(|&i| (code(&gaussians[i]), i));
    order
}

/// Shares below this are left out of `own_shares`: they would change an optical depth by
/// less than a millionth of the owner's.
pub const OWN_SHARE_FLOOR: f64 = 1e-6;

/// Each Gaussian's share of the mixture's density at a surface point, from the logarithms of
/// their densities there (a softmax, so that no share is lost to underflow far from every
/// Gaussian): (index, share), shares below `OWN_SHARE_FLOOR` left out. A Gaussian is a convex
/// blob: a ray leaving the surface it makes toward a light in front of that surface leaves it
/// and never re-enters, so whatever optical depth it still adds is the blur of a soft
/// occupancy, not a shadow. Weighting each Gaussian's depth by one less its share lets the
/// other body parts shadow the point (an arm on the torso, however close) and not the part it
/// lies on, which is what the shadow ray's start off the surface did before, at the cost of
/// every contact shadow nearer than it.
pub fn own_shares(log_densities: impl Iterator<Item = f64>) -> Vec<(usize, f64)> {
    let logs: Vec<f64> = log_densities.collect();
    let top = logs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !top.is_finite() {
        return Vec::new();
    }
    let weights: Vec<f64> = logs.iter().map(|l| (l - top).exp()).collect();
    let total: f64 = weights.iter().sum();
    weights.iter().enumerate().map(|(g, &w)| (g, w / total)).filter(|&(_, share)| share >= OWN_SHARE_FLOOR).collect()
}

/// `transmittance_f64` from a surface point `x`: each Gaussian's optical depth weighted by one
/// less its share of the density at `x` (`own_shares`), every integral in f64, no culling.
pub fn transmittance_f64_from(gaussians: &[PosedGaussian], x: glam::DVec3, ray: &ShadowRay) -> f64 {
    let origin = ray.origin.map(f64::from);
    let direction = ray.direction.map(f64::from);
    let mut weights = vec![1.0; gaussians.len()];
    for (g, share) in own_shares(gaussians.iter().map(|g| g.log_density(x))) {
        weights[g] -= share;
    }
    let tau: f64 = gaussians
        .iter()
        .zip(&weights)
        .map(|(g, w)| {
            w * super::optical_depth(g.mean.to_array(), g.rotation_columns(), g.scales.to_array(), g.amplitude, origin, direction, ray.t0 as f64, ray.t1 as f64)
        })
        .sum();
    (-tau).exp()
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
