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

/// Samples per ray: `coarse` stratified over the ray's bound; `fine` more where the coarse
/// pass found density (none: the coarse samples alone, rendered with gradients).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sampling {
    pub coarse: usize,
    pub fine: usize,
}

impl Sampling {
    /// Samples per ray in the differentiable pass.
    pub fn total(&self) -> usize {
        self.coarse + self.fine
    }
}

/// Where each ray is sampled: distances `t` and the lengths `delta` of the intervals they
/// stand for (`[R * S]` each, ray-major, ascending along each ray).
struct Samples {
    t: Vec<f32>,
    delta: Vec<f32>,
}

/// Stratified samples over `[near, far]`: sample `k` at `near + (k + jitter) step`.
fn stratified(rays: &RaySet, samples: usize, jitter: &[f32]) -> Samples {
    let mut out = Samples { t: Vec::with_capacity(rays.len() * samples), delta: Vec::with_capacity(rays.len() * samples) };
    for i in 0..rays.len() {
        let step = (rays.far[i] - rays.near[i]) / samples as f32;
        for k in 0..samples {
            out.t.push(rays.near[i] + step * (k as f32 + jitter[i * samples + k]));
            out.delta.push(step);
        }
    }
    out
}

/// Adds `fine` samples per ray drawn by inverse transform from the coarse samples' weights
/// (`[R * Sc]`) over their strata (a small uniform floor keeps empty rays sampled), merges
/// them with the coarse ones in order and gives each sample the interval between the
/// midpoints to its neighbours.
fn refine(rays: &RaySet, coarse: &Samples, weights: &[f32], sampling: Sampling, jitter: &[f32]) -> Samples {
    let (sc, sf) = (sampling.coarse, sampling.fine);
    let s = sc + sf;
    let mut out = Samples { t: Vec::with_capacity(rays.len() * s), delta: Vec::with_capacity(rays.len() * s) };
    let mut merged = Vec::with_capacity(s);
    for i in 0..rays.len() {
        let (near, far) = (rays.near[i], rays.far[i]);
        let step = (far - near) / sc as f32;
        let w = &weights[i * sc..(i + 1) * sc];
        let floor = 1e-2 * w.iter().sum::<f32>().max(1e-3) / sc as f32;
        let mut cdf = Vec::with_capacity(sc + 1);
        cdf.push(0.0f32);
        for &wk in w {
            cdf.push(cdf.last().copied().unwrap_or(0.0) + wk.max(0.0) + floor);
        }
        let total = cdf[sc];
        merged.clear();
        merged.extend_from_slice(&coarse.t[i * sc..(i + 1) * sc]);
        let mut bin = 0;
        for j in 0..sf {
            let u = (j as f32 + jitter[i * sf + j]) / sf as f32 * total;
            while bin + 1 < sc && cdf[bin + 1] < u {
                bin += 1;
            }
            let inside = ((u - cdf[bin]) / (cdf[bin + 1] - cdf[bin]).max(1e-12)).clamp(0.0, 1.0);
            merged.push(near + step * (bin as f32 + inside));
        }
        merged.sort_by(f32::total_cmp);
        for k in 0..s {
            let lo = if k == 0 { near } else { 0.5 * (merged[k - 1] + merged[k]) };
            let hi = if k + 1 == s { far } else { 0.5 * (merged[k] + merged[k + 1]) };
            out.t.push(merged[k]);
            out.delta.push((hi - lo).max(0.0));
        }
    }
    out
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
    let coarse = stratified(rays, sampling.coarse, &jitter[..r * sampling.coarse]);
    let samples = if sampling.fine == 0 {
        coarse
    } else {
        // The coarse pass: no gradients, no graph.
        let plain = device.clone().without_autodiff();
        let sc = sampling.coarse;
        let t = Tensor::<2>::from_data(TensorData::new(coarse.t.clone(), [r, sc]), &plain);
        let delta = Tensor::<2>::from_data(TensorData::new(coarse.delta.clone(), [r, sc]), &plain);
        let points = sample_points(&origins.clone().without_autodiff(), &directions.clone().without_autodiff(), &t);
        let still = field.valid();
        let density = still.density(still.sdf(points, pose)).reshape([r, sc]);
        let weights = compositing_weights(density, delta).into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_else(|_| vec![0.0; r * sc]);
        refine(rays, &coarse, &weights, sampling, &jitter[r * sc..])
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
