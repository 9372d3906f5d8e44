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

use crate::field::{AvatarField, Decoded, GradientMethod, PoseTensors};
use crate::shadow::PosedGaussian;
use burn::module::Module;
use burn::tensor::{Device, IndexingUpdateOp, Int, Tensor, TensorData};
use glam::DVec3;

mod locate;
mod parts;
mod samples;
mod search_tensors;
mod still;

use locate::*;
pub use parts::{render_in_parts, sum_gradients, Parts};
pub use still::render_still;

pub use samples::{CULL_OPTICAL_DEPTH, CULL_TRANSMITTANCE};

/// Radius of a Gaussian's bounding sphere in units of its largest scale, and the least radius
/// (m, on the reference human; `ray_bounds` takes a body's own): outside it the body cannot
/// be, so no samples are spent there.
pub const BOUND_SIGMAS: f64 = 3.0;
pub const MIN_BOUND_RADIUS: f64 = 0.08;

/// The length of each row of `v`, `[N, 1]`, with a finite gradient everywhere: the square
/// root of the squared length plus 1e-12, so a zero row (an SDF flat at a point: no prior's
/// slope and every decoder unit off) has length 1e-6 and gradient zero, where `sqrt` of 0 would
/// send infinity times zero, NaN, into every parameter (it did: a fit diverged at its first
/// RGB step). For a row of length 1e-3 or more the added term is below f32's resolution.
pub fn row_lengths(v: Tensor<2>) -> Tensor<2> {
    ((v.clone() * v).sum_dim(1) + 1e-12).sqrt()
}

/// Each row of `v` scaled to unit length (`row_lengths`): surface normals from SDF gradients.
pub fn unit_rows(v: Tensor<2>) -> Tensor<2> {
    v.clone() / row_lengths(v)
}

/// Step (m) of the central differences that give surface normals.
pub const NORMAL_STEP: f32 = 0.004;

/// The `[near, far]` interval where a ray meets any Gaussian's bounding sphere (at least
/// `min_radius` m); `None` misses.
pub fn ray_bounds(origin: DVec3, direction: DVec3, gaussians: &[PosedGaussian], min_radius: f64) -> Option<(f64, f64)> {
    let mut near = f64::INFINITY;
    let mut far = f64::NEG_INFINITY;
    for g in gaussians {
        let radius = (g.scales.max_element() * BOUND_SIGMAS).max(min_radius);
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
    /// Per ray, its camera's row in the pose's view increment (`PoseTensors::view`), when the
    /// render is to carry one (else empty).
    pub cameras: Vec<u32>,
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
        self.range(0, n)
    }

    /// Rays `lo..hi` (clamped to the set).
    pub fn range(&self, lo: usize, hi: usize) -> RaySet {
        let hi = hi.min(self.len());
        let lo = lo.min(hi);
        RaySet {
            origins: self.origins[3 * lo..3 * hi].to_vec(),
            directions: self.directions[3 * lo..3 * hi].to_vec(),
            near: self.near[lo..hi].to_vec(),
            far: self.far[lo..hi].to_vec(),
            cameras: self.cameras.get(lo..hi).map(<[u32]>::to_vec).unwrap_or_default(),
        }
    }

    /// `pose` for a lookup of the points `rows` (indices into `[R * S]`, `s` samples a ray):
    /// its view increment following them when it has one and the rays carry their cameras.
    fn pose_along(&self, pose: &PoseTensors, s: usize, rows: impl Iterator<Item = usize>) -> PoseTensors {
        match &pose.view {
            Some(view) if self.cameras.len() == self.len() => {
                let rays: Vec<usize> = rows.map(|k| k / s).collect();
                let cameras: Vec<u32> = rays.iter().map(|&i| self.cameras[i]).collect();
                let mut origins = Vec::with_capacity(3 * rays.len());
                rays.iter().for_each(|&i| origins.extend_from_slice(&self.origins[3 * i..3 * i + 3]));
                PoseTensors { view: Some(view.along(&cameras, origins)), ..pose.clone() }
            }
            _ => pose.clone(),
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
    /// Wall seconds of the three parts (`RENDER_PARTS`), for the cost breakdown.
    pub seconds: [f64; 3],
    /// Samples the field was evaluated at with gradients (`R * S`, fewer when culled; none for
    /// a still render).
    pub evaluated: usize,
    /// The motion increments the render's lookups carried (`PoseTensors::motion`), one per
    /// part rendered on its own thread: their gradients sum to the increment's.
    pub motion_leaves: Vec<Tensor<2>>,
    /// The same for the view increment of the cameras (`PoseTensors::view`).
    pub view_leaves: Vec<Tensor<2>>,
}

/// The parts of `render` whose time `Deferred::seconds` holds.
pub const RENDER_PARTS: [&str; 3] =
    ["surface search (coarse + probe samples, no gradients)", "field forward (differentiable samples)", "normals (SDF gradient at the surface)"];

/// Samples per ray: `coarse` stratified over the ray's bound; `probe` more, without gradients,
/// where the coarse pass found density, only to locate the surface more finely; `fine` more
/// where coarse and probe samples together found density (none: the coarse samples alone,
/// rendered with gradients). The differentiable pass renders `coarse + fine`, and decodes the
/// albedo only at its samples of compositing weight `albedo_floor` or more (0: at all of them).
/// With `cull`, it evaluates the field only at the samples that can change a ray's colour or
/// coverage, or pass a gradient (`culled`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sampling {
    pub coarse: usize,
    pub probe: usize,
    pub fine: usize,
    pub albedo_floor: f32,
    pub cull: bool,
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

    /// The jitter of rays `lo..hi` out of `jitter` for `r` rays, laid out as `render` takes
    /// it: pass by pass (coarse, probe, fine), each pass ray by ray.
    fn jitter_of(&self, jitter: &[f32], r: usize, lo: usize, hi: usize) -> Vec<f32> {
        let passes = if self.fine == 0 { vec![self.coarse] } else { vec![self.coarse, self.probe, self.fine] };
        let mut start = 0;
        let mut out = Vec::with_capacity((hi - lo) * self.draws());
        for n in passes {
            out.extend_from_slice(&jitter[start + lo * n..start + hi * n]);
            start += r * n;
        }
        out
    }
}

/// Per-sample compositing weights `T alpha` from densities and interval lengths `[R, S]`.
fn compositing_weights(density: Tensor<2>, delta: Tensor<2>) -> Tensor<2> {
    let optical = density * delta; // sigma delta
    let alpha = optical.clone().neg().exp().neg() + 1.0;
    // Transmittance before each sample: exp(-exclusive cumulative optical depth).
    let before = (optical.clone().cumsum(1) - optical).neg().exp();
    before * alpha
}

/// Samples whose compositing weight is below this contribute nothing to a rendered view's
/// albedo (`Sampling::albedo_floor` of `eval::VIEW_SAMPLING`): with 40 samples per ray (coarse and fine),
/// what they hold together is under 1e-2 of the albedo's range in the worst case and, with the
/// surface as sharp as a fitted beta makes it, nearly all of a ray's weight sits on a handful of
/// samples. Training keeps every sample (floor 0): the gradient of a ray's colour to a sample's
/// weight is that sample's albedo, which tells the geometry whether density there would match
/// the image; without it human-sun-128 lost 0.8 dB foreground (seed 0, 23.88 against 24.66).
pub const ALBEDO_WEIGHT_FLOOR: f32 = 1e-4;

/// A ray's albedo, the compositing weights' sum of its samples' albedos (`[R, 3]`), with the
/// albedo decoded only at samples of weight `floor` or more (`ALBEDO_WEIGHT_FLOOR`): most
/// samples of a fitted body lie in front of the surface or hidden behind it. Those samples
/// then pass no gradient to their weights, which training needs (`ALBEDO_WEIGHT_FLOOR`), so
/// it asks for floor 0: the albedo decoded at every sample.
pub fn composite_albedo(field: &AvatarField, decoded: &Decoded, weights: &Tensor<2>, floor: f32) -> Tensor<2> {
    let [r, s] = weights.dims();
    if floor <= 0.0 {
        let albedo = field.albedo_at(decoded, None).reshape([r, s, 3]);
        return (weights.clone().unsqueeze_dim::<3>(2) * albedo).sum_dim(1).reshape([r, 3]);
    }
    let device = weights.device();
    let host = crate::backend::host_values(weights.clone());
    let rows: Vec<usize> = (0..r * s).filter(|&k| host.get(k).is_none_or(|&w| w >= floor)).collect();
    if rows.is_empty() {
        return Tensor::zeros([r, 3], &device);
    }
    let picked = row_index(rows.iter().copied(), &device);
    weighted_per_ray(field.albedo_at(decoded, Some(picked)), weights, &rows)
}

/// Rows `rows` as an index tensor, for `select` and `select_assign`.
pub fn row_index(rows: impl ExactSizeIterator<Item = usize>, device: &Device) -> Tensor<1, Int> {
    let n = rows.len();
    Tensor::<1, Int>::from_data(TensorData::new(rows.map(|k| k as i64).collect::<Vec<i64>>(), [n]), device)
}

/// Volume-renders `rays` through the field in `pose`, sampled as `sampling` says, with
/// `jitter` in [0, 1) per sample, pass by pass (`[R * coarse]` values for the coarse strata,
/// then `[R * probe]` and `[R * fine]` for the probe and fine draws; 0.5 everywhere for a
/// deterministic render).
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
    render_searching(field, pose, rays, sampling, jitter, normals, device, !crate::backend::on_host(device))
}

/// `render`, its surface search run by tensor ops on the device (`search_tensors`) when
/// `on_device`, and then its differentiable pass over every sample (a culled pass would read
/// the search's densities back to choose its samples).
#[allow(clippy::too_many_arguments)]
pub(crate) fn render_searching(
    field: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    sampling: Sampling,
    jitter: &[f32],
    normals: Option<GradientMethod>,
    device: &Device,
    on_device: bool,
) -> Deferred {
    let start = std::time::Instant::now();
    let r = rays.len();
    let (origins, directions) = ray_tensors(rays, device);
    let s = sampling.total();
    // The samples, and for a culled pass those it keeps, their distances and the search's densities.
    let (t, delta, culled) = if on_device {
        let found = search_tensors::search_by_tensors(field, pose, rays, &origins, &directions, sampling, jitter);
        (found.t, found.delta, None)
    } else {
        let want = if sampling.cull { Want::Culled } else { Want::Samples };
        let Located { samples, density: searched, kept, .. } = locate(field, pose, rays, &origins, &directions, sampling, jitter, want);
        let t = Tensor::<2>::from_data(TensorData::new(samples.t.clone(), [r, s]), device);
        let delta = Tensor::<2>::from_data(TensorData::new(samples.delta, [r, s]), device);
        (t, delta, kept.map(|kept| (kept, samples.t, searched)))
    };
    let located = start.elapsed().as_secs_f64();
    let points = sample_points(&origins, &directions, &t);
    let (weights, albedo, density, evaluated) = match culled {
        Some((kept, host_t, searched)) => {
            let along = rays.pose_along(pose, s, kept.iter().copied());
            let (weights, albedo, density) = culled_pass(field, &along, rays, &host_t, &kept, delta, device);
            // The density-fit and regulariser points are drawn from every sample: a culled
            // one's density (detached there) is the search's.
            let mut left_out: Vec<f32> = searched.iter().map(|&d| if d.is_finite() { d } else { 0.0 }).collect();
            for &k in &kept {
                left_out[k] = 0.0;
            }
            let density = density.detach() + Tensor::<1>::from_data(TensorData::new(left_out, [r * s]), device);
            (weights, albedo, density, kept.len())
        }
        None => {
            let decoded = field.decode(points.clone(), &rays.pose_along(pose, s, 0..r * s));
            let density = field.density(decoded.sdf.clone());
            let weights = compositing_weights(density.clone().reshape([r, s]), delta); // [R, S]
            let albedo = composite_albedo(field, &decoded, &weights, sampling.albedo_floor);
            (weights, albedo, density, r * s)
        }
    };
    let accumulation = weights.clone().sum_dim(1).reshape([r]);
    let depth = (weights * t).sum_dim(1).reshape([r]) / (accumulation.clone() + 1e-6);
    let surface = origins + directions * depth.clone().reshape([r, 1]);
    let forward = start.elapsed().as_secs_f64();
    // With the cameras refined, the surface point follows its ray's camera too, and so do the
    // shading's normal and shadows at it.
    let seen = rays.pose_along(pose, 1, 0..r).view.map(|view| (view.seen_shift(surface.clone()), view.stencil));
    let normal = normals.map(|method| {
        let gradient = field.sdf_gradient(surface.clone(), pose, method);
        match &seen {
            Some((shift, stencil)) => unit_rows(gradient.clone() + slope_along(field, pose, &surface, &gradient, shift, *stencil, method)),
            None => unit_rows(gradient),
        }
    });
    let surface = match seen {
        Some((shift, _)) => surface + shift,
        None => surface,
    };
    let seconds = [located, forward - located, start.elapsed().as_secs_f64() - forward];
    let motion_leaves = pose.motion.iter().map(|m| m.leaf.clone()).collect();
    let view_leaves = pose.view.iter().map(|v| v.leaf.clone()).collect();
    Deferred { accumulation, albedo, depth, surface, normal, sample_points: points, sample_density: density, seconds, evaluated, motion_leaves, view_leaves }
}

/// How the SDF's gradient at `surface` (`gradient`, `[R, 3]`) changes as the points move by
/// `shift` (`[R, 3]`, carrying an increment): its slope along each axis differenced over
/// `stencil` (m) without gradients, times the shift's component along it. The field's
/// second derivatives are not followed; this carries an increment into a shading normal. By
/// tensor ops on the surface's device: nothing is read back.
fn slope_along(
    field: &AvatarField,
    pose: &PoseTensors,
    surface: &Tensor<2>,
    gradient: &Tensor<2>,
    shift: &Tensor<2>,
    stencil: f32,
    method: GradientMethod,
) -> Tensor<2> {
    let [r, _] = surface.dims();
    let device = surface.device();
    let here = surface.clone().without_autodiff();
    let step = |axis: usize| Tensor::<2>::from_data(TensorData::new([0, 1, 2].map(|c| if c == axis { stencil } else { 0.0 }).to_vec(), [1, 3]), &here.device());
    let offsets = Tensor::cat((0..3).map(|axis| here.clone() + step(axis)).collect(), 0); // [3R, 3], axis-major
    let there = field.valid().sdf_gradient(offsets, pose, method);
    let g = gradient.clone().without_autodiff();
    let mut total = Tensor::<2>::zeros([r, 3], &device);
    for axis in 0..3 {
        let slope = (there.clone().slice([axis * r..(axis + 1) * r, 0..3]) - g.clone()) / stencil;
        total = total + shift.clone().narrow(1, axis, 1) * slope;
    }
    total
}

/// The differentiable pass over the `kept` samples only (`contributing`): the field decoded at
/// them, every other sample given density zero, composited over every ray's `S` samples as the
/// full pass would (`[R, S]` weights), each ray's albedo the weighted sum over its kept samples
/// (`[R, 3]`), and every sample's density (`[R * S]`, zero where left out).
fn culled_pass(
    field: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    t: &[f32],
    kept: &[usize],
    delta: Tensor<2>,
    device: &Device,
) -> (Tensor<2>, Tensor<2>, Tensor<1>) {
    let [r, s] = delta.dims();
    if kept.is_empty() {
        return (Tensor::zeros([r, s], device), Tensor::zeros([r, 3], device), Tensor::zeros([r * s], device));
    }
    let decoded = field.decode(points_at(rays, t, s, kept, device), pose);
    let rows = row_index(kept.iter().copied(), device);
    let density = Tensor::<1>::zeros([r * s], device).select_assign(0, rows, field.density(decoded.sdf.clone()), IndexingUpdateOp::Add);
    let weights = compositing_weights(density.clone().reshape([r, s]), delta);
    let albedo = weighted_per_ray(field.albedo_at(&decoded, None), &weights, kept);
    (weights, albedo, density)
}

impl Deferred {
    /// Renders of consecutive runs of rays joined into one, in order; each part's time is the
    /// slowest run's (they ran at once).
    fn cat(parts: Vec<Deferred>) -> Deferred {
        let mut seconds = [0.0f64; 3];
        for part in &parts {
            for (s, p) in seconds.iter_mut().zip(part.seconds) {
                *s = s.max(p);
            }
        }
        let normal =
            if parts.iter().all(|p| p.normal.is_some()) { Some(Tensor::cat(parts.iter().filter_map(|p| p.normal.clone()).collect(), 0)) } else { None };
        let join1 = |f: fn(&Deferred) -> Tensor<1>| Tensor::cat(parts.iter().map(f).collect(), 0);
        let join2 = |f: fn(&Deferred) -> Tensor<2>| Tensor::cat(parts.iter().map(f).collect(), 0);
        Deferred {
            accumulation: join1(|p| p.accumulation.clone()),
            albedo: join2(|p| p.albedo.clone()),
            depth: join1(|p| p.depth.clone()),
            surface: join2(|p| p.surface.clone()),
            normal,
            sample_points: join2(|p| p.sample_points.clone()),
            sample_density: join1(|p| p.sample_density.clone()),
            seconds,
            evaluated: parts.iter().map(|p| p.evaluated).sum(),
            motion_leaves: parts.iter().flat_map(|p| p.motion_leaves.iter().cloned()).collect(),
            view_leaves: parts.iter().flat_map(|p| p.view_leaves.iter().cloned()).collect(),
        }
    }
}

#[cfg(test)]
mod tests;
