//! The differentiable deferred renderer: samples along camera rays only inside the posed
//! Gaussians' bounding spheres (rays that miss every one cost nothing and stay background),
//! volume-renders the field's VolSDF density into accumulation, depth and albedo, and finds the
//! surface point and its normal for deferred shading. Also renders whole views for evaluation.

use crate::field::{AvatarField, GradientMethod, PoseTensors};
use crate::gaussians::PosedGaussian;
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
        RaySet { origins: self.origins[..3 * n].to_vec(), directions: self.directions[..3 * n].to_vec(), near: self.near[..n].to_vec(), far: self.far[..n].to_vec() }
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

/// Volume-renders `rays` through the field in `pose` with `samples` stratified samples per ray,
/// `jitter` in [0, 1) per sample (`[R * S]` values; 0.5 for a deterministic render).
/// Normals cost a gradient of the SDF per ray, so they are computed only when `normals` says
/// by which method.
pub fn render(
    field: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    samples: usize,
    jitter: &[f32],
    normals: Option<GradientMethod>,
    device: &Device,
) -> Deferred {
    let r = rays.len();
    let s = samples;
    let t1 = |v: &Vec<f32>| Tensor::<1>::from_data(TensorData::new(v.clone(), [r]), device);
    let origins: Tensor<2> = Tensor::from_data(TensorData::new(rays.origins.clone(), [r, 3]), device);
    let directions: Tensor<2> = Tensor::from_data(TensorData::new(rays.directions.clone(), [r, 3]), device);
    let near = t1(&rays.near).reshape([r, 1]);
    let far = t1(&rays.far).reshape([r, 1]);
    let step = (far - near.clone()) / s as f32; // [R, 1]
    let index: Vec<f32> = (0..r * s).map(|k| (k % s) as f32 + jitter[k]).collect();
    let t: Tensor<2> = near + step.clone() * Tensor::<2>::from_data(TensorData::new(index, [r, s]), device); // [R, S]
    let points = (origins.clone().unsqueeze_dim::<3>(1) + directions.clone().unsqueeze_dim::<3>(1) * t.clone().unsqueeze_dim::<3>(2)).reshape([r * s, 3]);
    let out = field.forward(points.clone(), pose);
    let density = field.density(out.sdf);
    let optical = density.clone().reshape([r, s]) * step; // sigma delta
    let alpha = optical.clone().neg().exp().neg() + 1.0;
    // Transmittance before each sample: exp(-exclusive cumulative optical depth).
    let before = (optical.clone().cumsum(1) - optical).neg().exp();
    let weights = before * alpha; // [R, S]
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
