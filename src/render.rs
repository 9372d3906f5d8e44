//! The differentiable deferred renderer: samples along camera rays only inside the posed
//! Gaussians' bounding spheres (rays that miss every one cost nothing and stay background),
//! volume-renders the field's VolSDF density into accumulation, depth and albedo, and finds the
//! surface point and its normal for deferred shading. Also renders whole views for evaluation.
//!
//! Sampling is hierarchical: a coarse pass of stratified samples, without gradients, finds
//! where the density is; fine samples are drawn there by inverse transform of the coarse
//! weights, and the differentiable pass renders coarse and fine samples together. A surface as
//! thin as VolSDF's beta is then resolved along every ray, also the grazing rays of a
//! silhouette, which coarse samples alone integrate into a halo.

use crate::field::{AvatarField, GradientMethod, PoseTensors};
use crate::gaussians::PosedGaussian;
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;

/// Radius of a Gaussian's bounding sphere in units of its largest scale, and the least radius
/// (m): outside it the body cannot be, so no samples are spent there.
pub const BOUND_SIGMAS: f64 = 3.0;
pub const MIN_BOUND_RADIUS: f64 = 0.08;

/// Step (m) of the central differences that give surface normals.
pub const NORMAL_STEP: f32 = 0.004;

/// The `[near, far]` interval where a ray meets any Gaussian's bounding sphere; `None` misses.
pub fn ray_bounds(origin: DVec3, direction: DVec3, gaussians: &[PosedGaussian]) -> Option<(f64, f64)> {
    let mut near = f64::INFINITY;
    let mut far = f64::NEG_INFINITY;
    for g in gaussians {
        let radius = (g.scales.max_element() * BOUND_SIGMAS).max(MIN_BOUND_RADIUS);
        let oc = origin - g.mean;
        let b = oc.dot(direction);
        let disc = b * b - (oc.length_squared() - radius * radius);
        if disc > 0.0 {
            let root = disc.sqrt();
            near = near.min((-b - root).max(0.0));
            far = far.max(-b + root);
        }
    }
    (far > near).then_some((near, far))
}

/// Camera rays with their sampling intervals (CPU side).
#[derive(Clone, Debug, Default)]
pub struct RaySet {
    pub origins: Vec<f32>,
    pub directions: Vec<f32>,
    pub near: Vec<f32>,
    pub far: Vec<f32>,
}

impl RaySet {
    pub fn push(&mut self, origin: DVec3, direction: DVec3, bounds: Option<(f64, f64)>) {
        self.origins.extend(origin.as_vec3().to_array());
        self.directions.extend(direction.as_vec3().to_array());
        let (n, f) = bounds.unwrap_or((0.0, 0.0));
        self.near.push(n as f32);
        self.far.push(f as f32);
    }

    pub fn len(&self) -> usize {
        self.near.len()
    }

    /// The first `n` rays.
    pub fn first(&self, n: usize) -> RaySet {
        let n = n.min(self.len());
        RaySet {
            origins: self.origins[..3 * n].to_vec(),
            directions: self.directions[..3 * n].to_vec(),
            near: self.near[..n].to_vec(),
            far: self.far[..n].to_vec(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.near.is_empty()
    }
}

/// What the renderer produces per ray.
pub struct Deferred {
    pub accumulation: Tensor<1>,
    pub albedo: Tensor<2>,
    pub depth: Tensor<1>,
    pub surface: Tensor<2>,
    /// Unit surface normals, when asked for (shading needs them; albedo-only fits do not).
    pub normal: Option<Tensor<2>>,
    /// Every sample point `[R * S, 3]` and the field's density there `[R * S]`.
    pub sample_points: Tensor<2>,
    pub sample_density: Tensor<1>,
}

/// Samples per ray: `coarse` stratified over the ray's bound; `probe` more, without gradients,
/// where the coarse pass found density, only to locate the surface more finely; `fine` more
/// where coarse and probe samples together found density (none: the coarse samples alone,
/// rendered with gradients). The differentiable pass renders `coarse + fine`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sampling {
    pub coarse: usize,
    pub probe: usize,
    pub fine: usize,
}

impl Sampling {
    /// Samples per ray in the differentiable pass.
    pub fn total(&self) -> usize {
        self.coarse + self.fine
    }

    /// Uniform numbers in [0, 1) a ray's sampling consumes (`render`'s `jitter` per ray).
    pub fn draws(&self) -> usize {
        if self.fine == 0 {
            self.coarse
        } else {
            self.coarse + self.probe + self.fine
        }
    }
}

/// Where each ray is sampled: distances `t`, and the intervals they stand for by their start
/// `lo` and length `delta` (`[R * S]` each, ray-major, ascending along each ray).
#[derive(Clone)]
struct Samples {
    t: Vec<f32>,
    lo: Vec<f32>,
    delta: Vec<f32>,
}

/// Stratified samples over `[near, far]`: sample `k` at `near + (k + jitter) step`.
fn stratified(rays: &RaySet, samples: usize, jitter: &[f32]) -> Samples {
    let n = rays.len() * samples;
    let mut out = Samples { t: Vec::with_capacity(n), lo: Vec::with_capacity(n), delta: Vec::with_capacity(n) };
    for i in 0..rays.len() {
        let step = (rays.far[i] - rays.near[i]) / samples as f32;
        for k in 0..samples {
            out.t.push(rays.near[i] + step * (k as f32 + jitter[i * samples + k]));
            out.lo.push(rays.near[i] + step * k as f32);
            out.delta.push(step);
        }
    }
    out
}

/// The interval `[lo, hi]` each of a ray's ascending samples `t` stands for: from the midpoint
/// to its predecessor to the midpoint to its successor, the ends at `near` and `far`.
fn intervals(t: &[f32], near: f32, far: f32) -> impl Iterator<Item = (f32, f32)> + '_ {
    let s = t.len();
    (0..s).map(move |k| {
        let lo = if k == 0 { near } else { 0.5 * (t[k - 1] + t[k]) };
        let hi = if k + 1 == s { far } else { 0.5 * (t[k] + t[k + 1]) };
        (lo, hi.max(lo))
    })
}

/// `count` distances drawn by stratified inverse transform from the piecewise-constant density
/// whose mass over interval `[lo_k, hi_k]` is `w_k` plus a small uniform floor (so a ray the
/// samples found empty is still sampled), appended to `out`.
fn importance(bins: &[(f32, f32)], weights: &[f32], count: usize, jitter: &[f32], out: &mut Vec<f32>) {
    let n = bins.len();
    let floor = 1e-2 * weights.iter().sum::<f32>().max(1e-3) / n as f32;
    let mut cdf = Vec::with_capacity(n + 1);
    cdf.push(0.0f32);
    for &w in weights {
        cdf.push(cdf.last().copied().unwrap_or(0.0) + w.max(0.0) + floor);
    }
    let total = cdf[n];
    let mut bin = 0;
    for (j, &u) in jitter.iter().enumerate().take(count) {
        let target = (j as f32 + u) / count as f32 * total;
        while bin + 1 < n && cdf[bin + 1] < target {
            bin += 1;
        }
        let inside = ((target - cdf[bin]) / (cdf[bin + 1] - cdf[bin]).max(1e-12)).clamp(0.0, 1.0);
        let (lo, hi) = bins[bin];
        out.push(lo + (hi - lo) * inside);
    }
}

/// For every ray, `count` distances drawn by `importance` from its samples' weights
/// (`[R * S]`) over their intervals, merged with the samples in order: each merged sample's
/// interval runs between the midpoints to its neighbours. The merged set holds `base` (the
/// coarse samples) and the draws, not necessarily the samples the weights belong to.
fn refine(rays: &RaySet, samples: &Samples, weights: &[f32], count: usize, jitter: &[f32], base: &Samples) -> Samples {
    let r = rays.len();
    let s = samples.t.len() / r.max(1);
    let sb = base.t.len() / r.max(1);
    let n = r * (sb + count);
    let mut out = Samples { t: Vec::with_capacity(n), lo: Vec::with_capacity(n), delta: Vec::with_capacity(n) };
    let mut merged = Vec::with_capacity(sb + count);
    for i in 0..r {
        let (near, far) = (rays.near[i], rays.far[i]);
        let bins: Vec<(f32, f32)> = (i * s..(i + 1) * s).map(|k| (samples.lo[k], samples.lo[k] + samples.delta[k])).collect();
        merged.clear();
        merged.extend_from_slice(&base.t[i * sb..(i + 1) * sb]);
        importance(&bins, &weights[i * s..(i + 1) * s], count, &jitter[i * count..(i + 1) * count], &mut merged);
        merged.sort_by(f32::total_cmp);
        for (k, (lo, hi)) in intervals(&merged, near, far).enumerate() {
            out.t.push(merged[k]);
            out.lo.push(lo);
            out.delta.push(hi - lo);
        }
    }
    out
}

/// Compositing weights `[R * S]` of `samples` by the field's density, without gradients.
fn probe_weights(field: &AvatarField, pose: &PoseTensors, origins: &Tensor<2>, directions: &Tensor<2>, samples: &Samples, r: usize) -> Vec<f32> {
    let plain = origins.device().without_autodiff();
    let s = samples.t.len() / r.max(1);
    let t = Tensor::<2>::from_data(TensorData::new(samples.t.clone(), [r, s]), &plain);
    let delta = Tensor::<2>::from_data(TensorData::new(samples.delta.clone(), [r, s]), &plain);
    let points = sample_points(&origins.clone().without_autodiff(), &directions.clone().without_autodiff(), &t);
    let still = field.valid();
    let density = still.density(still.sdf(points, pose)).reshape([r, s]);
    compositing_weights(density, delta).into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_else(|_| vec![0.0; r * s])
}

/// Per-sample compositing weights `T alpha` from densities and interval lengths `[R, S]`.
fn compositing_weights(density: Tensor<2>, delta: Tensor<2>) -> Tensor<2> {
    let optical = density * delta; // sigma delta
    let alpha = optical.clone().neg().exp().neg() + 1.0;
    // Transmittance before each sample: exp(-exclusive cumulative optical depth).
    let before = (optical.clone().cumsum(1) - optical).neg().exp();
    before * alpha
}

/// Points `o + t d` of every sample, `[R * S, 3]`.
fn sample_points(origins: &Tensor<2>, directions: &Tensor<2>, t: &Tensor<2>) -> Tensor<2> {
    let [r, s] = t.dims();
    (origins.clone().unsqueeze_dim::<3>(1) + directions.clone().unsqueeze_dim::<3>(1) * t.clone().unsqueeze_dim::<3>(2)).reshape([r * s, 3])
}

/// Volume-renders `rays` through the field in `pose`, sampled as `sampling` says, with
/// `jitter` in [0, 1) per sample (`[R * coarse]` values for the coarse strata, then
/// `[R * fine]` for the fine draws; 0.5 everywhere for a deterministic render).
/// Normals cost a gradient of the SDF per ray, so they are computed only when `normals` says
/// by which method.
pub fn render(
    field: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    sampling: Sampling,
    jitter: &[f32],
    normals: Option<GradientMethod>,
    device: &Device,
) -> Deferred {
    let r = rays.len();
    let origins: Tensor<2> = Tensor::from_data(TensorData::new(rays.origins.clone(), [r, 3]), device);
    let directions: Tensor<2> = Tensor::from_data(TensorData::new(rays.directions.clone(), [r, 3]), device);
    let (sc, sp, sf) = (sampling.coarse, sampling.probe, sampling.fine);
    let coarse = stratified(rays, sc, &jitter[..r * sc]);
    let samples = if sf == 0 {
        coarse
    } else {
        // Without gradients: the coarse pass, then, if asked, probes where it found density,
        // so the fine samples are drawn from a finer picture of where the surface is.
        let mut located = coarse.clone();
        let mut weights = probe_weights(field, pose, &origins, &directions, &located, r);
        if sp > 0 {
            located = refine(rays, &located, &weights, sp, &jitter[r * sc..r * (sc + sp)], &coarse);
            weights = probe_weights(field, pose, &origins, &directions, &located, r);
        }
        refine(rays, &located, &weights, sf, &jitter[r * (sc + sp)..r * (sc + sp + sf)], &coarse)
    };
    let s = sampling.total();
    let t = Tensor::<2>::from_data(TensorData::new(samples.t, [r, s]), device);
    let delta = Tensor::<2>::from_data(TensorData::new(samples.delta, [r, s]), device);
    let points = sample_points(&origins, &directions, &t);
    let out = field.forward(points.clone(), pose);
    let density = field.density(out.sdf);
    let weights = compositing_weights(density.clone().reshape([r, s]), delta); // [R, S]
    let accumulation = weights.clone().sum_dim(1).reshape([r]);
    let albedo = (weights.clone().unsqueeze_dim::<3>(2) * out.albedo.reshape([r, s, 3])).sum_dim(1).reshape([r, 3]);
    let depth = (weights * t).sum_dim(1).reshape([r]) / (accumulation.clone() + 1e-6);
    let surface = origins + directions * depth.clone().reshape([r, 1]);
    let normal = normals.map(|method| {
        let gradient = field.sdf_gradient(surface.clone(), pose, method);
        gradient.clone() / (gradient.clone() * gradient).sum_dim(1).sqrt().clamp_min(1e-6)
    });
    Deferred { accumulation, albedo, depth, surface, normal, sample_points: points, sample_density: density }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one_ray(near: f32, far: f32) -> RaySet {
        RaySet { origins: vec![0.0; 3], directions: vec![0.0, 0.0, 1.0], near: vec![near], far: vec![far] }
    }

    #[test]
    fn importance_draws_follow_the_weights() {
        // All the mass in the third of four bins: every draw but the floor's lands there.
        let bins = [(0.0, 1.0), (1.0, 2.0), (2.0, 2.5), (2.5, 4.0)];
        let mut out = Vec::new();
        let jitter = vec![0.5; 32];
        importance(&bins, &[0.0, 0.0, 1.0, 0.0], 32, &jitter, &mut out);
        assert_eq!(out.len(), 32);
        let inside = out.iter().filter(|&&t| (2.0..=2.5).contains(&t)).count();
        assert!(inside >= 30, "{inside} of 32 draws in the weighted bin");
        assert!(out.windows(2).all(|w| w[0] <= w[1]), "stratified draws come out in order");
    }

    #[test]
    fn refined_intervals_tile_the_bound_and_probes_sharpen_the_draws() {
        let rays = one_ray(1.0, 3.0);
        let coarse = stratified(&rays, 8, &[0.5; 8]);
        // A surface in the fifth stratum, at t = 2.05.
        let weights: Vec<f32> = coarse.lo.iter().zip(&coarse.delta).map(|(lo, d)| if (*lo..lo + d).contains(&2.05) { 1.0 } else { 0.0 }).collect();
        let probed = refine(&rays, &coarse, &weights, 16, &[0.5; 16], &coarse);
        assert_eq!(probed.t.len(), 24);
        assert!(probed.t.windows(2).all(|w| w[0] <= w[1]));
        let covered: f32 = probed.delta.iter().sum();
        assert!((covered - 2.0).abs() < 1e-5, "intervals cover the bound: {covered}");
        for k in 1..probed.t.len() {
            assert!((probed.lo[k] - (probed.lo[k - 1] + probed.delta[k - 1])).abs() < 1e-6, "intervals are contiguous");
        }
        // A probe round that puts all its weight on the sample nearest the surface narrows the
        // fine draws to that sample's interval, much finer than a coarse stratum.
        let nearest = (0..probed.t.len()).min_by(|&a, &b| (probed.t[a] - 2.05).abs().total_cmp(&(probed.t[b] - 2.05).abs())).unwrap_or(0);
        let sharp: Vec<f32> = (0..probed.t.len()).map(|k| if k == nearest { 1.0 } else { 0.0 }).collect();
        let fine = refine(&rays, &probed, &sharp, 16, &[0.5; 16], &coarse);
        assert_eq!(fine.t.len(), 24, "the merged set holds the coarse samples and the draws only");
        let near_surface = fine.t.iter().filter(|&&t| (t - 2.05).abs() < 0.02).count();
        assert!(near_surface >= 15, "{near_surface} fine samples within 2 cm of the surface");
    }
}
