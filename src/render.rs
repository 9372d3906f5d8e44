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
/// (`[R * S]`) over their intervals: `[R * count]`, ascending along each ray.
fn draw(rays: &RaySet, samples: &Samples, weights: &[f32], count: usize, jitter: &[f32]) -> Vec<f32> {
    let r = rays.len();
    let s = samples.t.len() / r.max(1);
    let mut out = Vec::with_capacity(r * count);
    let mut bins = Vec::with_capacity(s);
    for i in 0..r {
        bins.clear();
        bins.extend((i * s..(i + 1) * s).map(|k| (samples.lo[k], samples.lo[k] + samples.delta[k])));
        importance(&bins, &weights[i * s..(i + 1) * s], count, &jitter[i * count..(i + 1) * count], &mut out);
    }
    out
}

/// Merges two sets of ascending distances per ray (`[R * na]` and `[R * nb]`), carrying a value
/// per distance (the density) when given; each merged sample stands for the interval between
/// the midpoints to its neighbours.
fn merge<V: Copy + Default>(rays: &RaySet, a: &[f32], na: usize, b: &[f32], nb: usize, values: Option<(&[V], &[V])>) -> (Samples, Vec<V>) {
    let r = rays.len();
    let n = r * (na + nb);
    let mut out = Samples { t: Vec::with_capacity(n), lo: Vec::with_capacity(n), delta: Vec::with_capacity(n) };
    let mut merged_values = Vec::with_capacity(if values.is_some() { n } else { 0 });
    let mut merged: Vec<(f32, V)> = Vec::with_capacity(na + nb);
    let mut t: Vec<f32> = Vec::with_capacity(na + nb);
    let value = |v: Option<&[V]>, k: usize| v.map_or(V::default(), |v| v[k]);
    for i in 0..r {
        merged.clear();
        merged.extend((i * na..(i + 1) * na).map(|k| (a[k], value(values.map(|v| v.0), k))));
        merged.extend((i * nb..(i + 1) * nb).map(|k| (b[k], value(values.map(|v| v.1), k))));
        merged.sort_by(|x, y| x.0.total_cmp(&y.0));
        t.clear();
        t.extend(merged.iter().map(|m| m.0));
        for (k, (lo, hi)) in intervals(&t, rays.near[i], rays.far[i]).enumerate() {
            out.t.push(t[k]);
            out.lo.push(lo);
            out.delta.push(hi - lo);
        }
        if values.is_some() {
            merged_values.extend(merged.iter().map(|m| m.1));
        }
    }
    (out, merged_values)
}

/// The field's density at every sample of every ray (`[R * S]`), without gradients, and the
/// field's decoding of those points (row `k` is sample `k`), from which their albedo is read
/// without looking them up again.
fn densities(still: &AvatarField, pose: &PoseTensors, origins: &Tensor<2>, directions: &Tensor<2>, t: &[f32], r: usize) -> (Vec<f32>, Decoded) {
    let s = t.len() / r.max(1);
    let t = Tensor::<2>::from_data(TensorData::new(t.to_vec(), [r, s]), &origins.device());
    let points = sample_points(origins, directions, &t);
    let decoded = still.decode(points, pose);
    let density = crate::backend::host_values(still.density(decoded.sdf.clone()));
    (density, decoded)
}

/// `densities` of the rays `rays` (indices) only, their distances `t` (`[R * S]`); the other
/// rays' samples get density 0. The decoding holds the evaluated samples only, ray by ray in
/// the order of `rays` (none when `rays` is empty).
fn densities_of(still: &AvatarField, pose: &PoseTensors, all: &RaySet, t: &[f32], r: usize, rays: &[usize], device: &Device) -> (Vec<f32>, Option<Decoded>) {
    let s = t.len() / r.max(1);
    let mut out = vec![0.0f32; r * s];
    if rays.is_empty() {
        return (out, None);
    }
    let samples: Vec<usize> = rays.iter().flat_map(|&i| i * s..(i + 1) * s).collect();
    let decoded = still.decode(points_at(all, t, s, &samples, device), pose);
    let values = crate::backend::host_values(still.density(decoded.sdf.clone()));
    for (j, &i) in rays.iter().enumerate() {
        out[i * s..(i + 1) * s].copy_from_slice(&values[j * s..(j + 1) * s]);
    }
    (out, Some(decoded))
}

/// The optical depth `sigma delta` a view's ray must find at one of its coarse samples for its
/// probe and fine samples to be evaluated (`locate`): below it the ray's coarse samples change
/// its coverage by less than 1e-7 (as `CULL_OPTICAL_DEPTH` reasons), far below an 8-bit step.
const EMPTY_OPTICAL_DEPTH: f32 = 1e-7;

/// Compositing weights `T alpha` of every ray's samples from their densities, on the CPU (the
/// same sums as `compositing_weights`).
fn host_weights(samples: &Samples, density: &[f32], r: usize) -> Vec<f32> {
    let before = transmittance_before(samples, density, r);
    (0..before.len()).map(|k| before[k] * (1.0 - (-density[k] * samples.delta[k]).exp())).collect()
}

/// What a culled differentiable pass (`Sampling::cull`) leaves out: a coarse sample whose
/// optical depth `sigma delta` is below `CULL_OPTICAL_DEPTH`, or which lies behind at most
/// `CULL_TRANSMITTANCE` (an upper bound: the optical depth of the coarse samples before it
/// alone). Every fine sample is kept: they are drawn where the search found weight.
///
/// Why the pass is then the full pass to within these figures: a sample reaches the colour and
/// coverage through its weight `T (1 - exp(-sigma delta))` and the parameters through `d sigma /
/// d sdf`, which outside the surface is `sigma / beta` (VolSDF): a sample of optical depth below
/// 1e-7 changes the colour by less than 1e-7 and passes a gradient below 1e-7 / beta per unit
/// of SDF gradient, against about 1 / beta at the surface; a sample behind 1e-8 of transmittance
/// changes the colour, and the earlier samples' gradients, by less than 1e-8. What goes: most
/// coarse samples of a ray that hits the body (the empty space before the surface and the
/// inside behind it) and every coarse sample of a ray that passes far from it. A test pins the
/// culled pass to the full one, outputs and gradients. (A first bound, the transmittance of the
/// search's coarse and probe samples, is an estimate, not a bound: where a grazing ray's probe
/// overstated the optical depth it culled what lay behind, and `dog-sun` lost 1.5 dB of novel
/// view and 0.9 degrees of sun over three seeds.)
pub const CULL_OPTICAL_DEPTH: f32 = 1e-7;
pub const CULL_TRANSMITTANCE: f32 = 1e-8;

/// Transmittance before each of a ray's samples, from their densities (`[R * S]`).
fn transmittance_before(samples: &Samples, density: &[f32], r: usize) -> Vec<f32> {
    let s = samples.t.len() / r.max(1);
    let mut out = Vec::with_capacity(r * s);
    for i in 0..r {
        let mut transmittance = 1.0f32;
        for k in i * s..(i + 1) * s {
            out.push(transmittance);
            let alpha = 1.0 - (-density[k] * samples.delta[k]).exp();
            transmittance *= 1.0 - alpha;
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

/// The points `o + t d` of the samples `rows` (indices into `[R * S]`, `s` per ray) as an
/// `[K, 3]` tensor.
fn points_at(rays: &RaySet, t: &[f32], s: usize, rows: &[usize], device: &Device) -> Tensor<2> {
    let point = |k: usize, c: usize| rays.origins[3 * (k / s) + c] + rays.directions[3 * (k / s) + c] * t[k];
    let points: Vec<f32> = rows.iter().flat_map(|&k| [point(k, 0), point(k, 1), point(k, 2)]).collect();
    Tensor::<2>::from_data(TensorData::new(points, [rows.len(), 3]), device)
}

/// Each ray's sum of `albedo` (`[K, 3]`, one row per sample of `rows`, indices into `[R * S]`)
/// weighted by those samples' `weights` (`[R, S]`): `[R, 3]`.
fn weighted_per_ray(albedo: Tensor<2>, weights: &Tensor<2>, rows: &[usize]) -> Tensor<2> {
    let [r, s] = weights.dims();
    let device = weights.device();
    let k = rows.len();
    let index = |v: Vec<i64>| Tensor::<1, Int>::from_data(TensorData::new(v, [k]), &device);
    let weighted = albedo * weights.clone().reshape([r * s]).select(0, index(rows.iter().map(|&j| j as i64).collect())).reshape([k, 1]);
    Tensor::zeros([r, 3], &device).select_assign(0, index(rows.iter().map(|&j| (j / s) as i64).collect()), weighted, IndexingUpdateOp::Add)
}

/// The rays' origins and directions as `[R, 3]` tensors.
fn ray_tensors(rays: &RaySet, device: &Device) -> (Tensor<2>, Tensor<2>) {
    let r = rays.len();
    let tensor = |values: &Vec<f32>| Tensor::<2>::from_data(TensorData::new(values.clone(), [r, 3]), device);
    (tensor(&rays.origins), tensor(&rays.directions))
}

/// Points `o + t d` of every sample, `[R * S, 3]`.
fn sample_points(origins: &Tensor<2>, directions: &Tensor<2>, t: &Tensor<2>) -> Tensor<2> {
    let [r, s] = t.dims();
    (origins.clone().unsqueeze_dim::<3>(1) + directions.clone().unsqueeze_dim::<3>(1) * t.clone().unsqueeze_dim::<3>(2)).reshape([r * s, 3])
}

/// Where `render` and `render_still` sample each ray: stratified coarse samples; then, if
/// `sampling.fine`, probes where the coarse pass found density (only the probes evaluated: the
/// coarse densities are kept), and fine samples drawn from that finer picture of where the
/// surface is, merged with the coarse ones. All without gradients. `want` says what else to
/// return: the merged samples' densities (the fine ones evaluated here), or which of them a
/// culled differentiable pass evaluates.
#[allow(clippy::too_many_arguments)]
fn locate(
    field: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    origins: &Tensor<2>,
    directions: &Tensor<2>,
    sampling: Sampling,
    jitter: &[f32],
    want: Want,
) -> Located {
    let r = rays.len();
    let (sc, sp, sf) = (sampling.coarse, sampling.probe, sampling.fine);
    let coarse = stratified(rays, sc, &jitter[..r * sc]);
    if sf == 0 && want == Want::Samples {
        return Located { samples: coarse, density: Vec::new(), kept: None, decoding: None };
    }
    let still = field.valid();
    let (o, d) = (origins.clone().without_autodiff(), directions.clone().without_autodiff());
    // A view's coarse pass (nothing differentiated, probes and fine samples to follow) skips
    // what the SDF shows to be empty (`coarse_densities`); training's evaluates every sample.
    let (coarse_density, coarse_decoded, coarse_row) = if want == Want::Densities && sf > 0 {
        coarse_densities(&still, pose, rays, &coarse, sc, &o.device())
    } else {
        let (density, decoded) = densities(&still, pose, &o, &d, &coarse.t, r);
        (density, decoded, (0..(r * sc) as u32).collect())
    };
    if sf == 0 {
        let kept = (want == Want::Culled).then(|| culled(&coarse, &coarse_density, &transmittance_before(&coarse, &coarse_density, r)));
        return Located { samples: coarse, density: coarse_density, kept, decoding: None };
    }
    // A view's rays (nothing is differentiated) whose coarse samples found no optical depth
    // have no surface to refine: their probe and fine samples are not evaluated (density 0).
    let found: Option<Vec<usize>> = (want == Want::Densities)
        .then(|| (0..r).filter(|&i| (i * sc..(i + 1) * sc).any(|k| coarse_density[k] * coarse.delta[k] >= EMPTY_OPTICAL_DEPTH)).collect());
    let evaluate = |t: &[f32]| match &found {
        Some(found) => densities_of(&still, pose, rays, t, r, found, &o.device()),
        None => {
            let (density, decoded) = densities(&still, pose, &o, &d, t, r);
            (density, Some(decoded))
        }
    };
    let (located, density) = if sp > 0 {
        let weights = host_weights(&coarse, &coarse_density, r);
        let probes = draw(rays, &coarse, &weights, sp, &jitter[r * sc..r * (sc + sp)]);
        let (probe_density, _) = evaluate(&probes);
        merge(rays, &coarse.t, sc, &probes, sp, Some((&coarse_density, &probe_density)))
    } else {
        (coarse.clone(), coarse_density.clone())
    };
    let weights = host_weights(&located, &density, r);
    let fine = draw(rays, &located, &weights, sf, &jitter[r * (sc + sp)..r * (sc + sp + sf)]);
    match want {
        Want::Densities => {
            let (fine_density, fine_decoded) = evaluate(&fine);
            // Each sample carries its density and its row among the decoded points: the
            // coarse samples' rows first, then the fine samples' of the evaluated rays.
            let mut evaluated = vec![None; r];
            match &found {
                Some(found) => found.iter().enumerate().for_each(|(j, &i)| evaluated[i] = Some(j)),
                None => evaluated.iter_mut().enumerate().for_each(|(i, e)| *e = Some(i)),
            }
            let decoded_coarse = coarse_decoded.sdf.dims()[0];
            let coarse_rows: Vec<(f32, u32)> = coarse_density.iter().zip(&coarse_row).map(|(&v, &row)| (v, row)).collect();
            let fine_rows: Vec<(f32, u32)> =
                (0..r * sf).map(|k| (fine_density[k], evaluated[k / sf].map_or(NOT_DECODED, |j| (decoded_coarse + j * sf + k % sf) as u32))).collect();
            let (samples, merged) = merge(rays, &coarse.t, sc, &fine, sf, Some((&coarse_rows, &fine_rows)));
            let decoded = match fine_decoded {
                Some(fine) => Decoded::cat(vec![coarse_decoded, fine]),
                None => coarse_decoded,
            };
            let decoding = SampleDecoding { decoded, rows: merged.iter().map(|m| m.1).collect() };
            Located { samples, density: merged.iter().map(|m| m.0).collect(), kept: None, decoding: Some(decoding) }
        }
        Want::Samples => Located { samples: merge::<f32>(rays, &coarse.t, sc, &fine, sf, None).0, density: Vec::new(), kept: None, decoding: None },
        Want::Culled => {
            // Fine samples carry density +infinity: never culled, and left out of the optical
            // depth below, which is then the coarse samples' alone over their intervals among
            // the merged samples: a lower bound on the pass's (fine samples only add to it), so
            // the transmittance it gives is an upper bound and a sample culled by it is hidden
            // at least that well.
            let (samples, density) = merge(rays, &coarse.t, sc, &fine, sf, Some((&coarse_density, &vec![f32::INFINITY; r * sf])));
            let coarse_only: Vec<f32> = density.iter().map(|&d| if d.is_finite() { d } else { 0.0 }).collect();
            let before = transmittance_before(&samples, &coarse_only, r);
            let kept = culled(&samples, &density, &before);
            Located { samples, density, kept: Some(kept), decoding: None }
        }
    }
}

/// How steep the fitted SDF may be between two coarse samples for `coarse_densities` to take
/// its value at one as a bound at the next (an exact SDF's gradient has length 1; the Eikonal
/// loss holds the fitted one near it).
const SDF_SLOPE_BOUND: f32 = 2.0;

/// The coarse pass of a view's rays in rounds. First every other sample (every fourth, then
/// the other even ones but those hidden, below): a ray whose samples there show no optical
/// depth, and whose SDF there keeps every sample between them outside the body (its value
/// minus `SDF_SLOPE_BOUND` times the distance to the skipped sample) with an optical depth
/// under a thousandth of `EMPTY_OPTICAL_DEPTH`, is empty: its other samples are not evaluated
/// (density 0), and it is left alone as a ray found empty is. Every other ray's remaining
/// samples are evaluated in the last round, but those the samples before them show hidden
/// behind the surface, so its densities are those of one pass wherever they can change the ray
/// (`CULL_TRANSMITTANCE`). Returns the densities (`[R * S]`), the decoded points and each
/// sample's row among them (`NOT_DECODED` for a skipped one).
fn coarse_densities(still: &AvatarField, pose: &PoseTensors, rays: &RaySet, coarse: &Samples, s: usize, device: &Device) -> (Vec<f32>, Decoded, Vec<u32>) {
    let r = rays.len();
    let t = &coarse.t;
    let mut density = vec![0.0f32; r * s];
    let mut value = vec![f32::NAN; r * s];
    let mut row = vec![NOT_DECODED; r * s];
    let mut parts: Vec<Decoded> = Vec::new();
    let mut decoded_rows = 0u32;
    // Decodes `samples`, records their densities, SDF values and rows.
    let mut evaluate = |samples: &[usize], density: &mut [f32], value: &mut [f32], row: &mut [u32]| {
        // (The first round is decoded even when empty, so there is always a decoding to return.)
        if samples.is_empty() && !parts.is_empty() {
            return;
        }
        let decoded = still.decode(points_at(rays, t, s, samples, device), pose);
        let host = |v: Tensor<1>| crate::backend::host_values(v);
        let (sdf, sigma) = (host(decoded.sdf.clone()), host(still.density(decoded.sdf.clone())));
        for (j, &k) in samples.iter().enumerate() {
            (density[k], value[k], row[k]) = (sigma[j], sdf[j], decoded_rows + j as u32);
        }
        decoded_rows += samples.len() as u32;
        parts.push(decoded);
    };
    // Where ray `i`'s samples not yet evaluated start to be hidden: the evaluated samples'
    // optical depth before one, each over its own interval, is a lower bound on the ray's (the
    // rest only add to it), so its transmittance is an upper bound, and from the first sample
    // it puts under `CULL_TRANSMITTANCE` on, the ray is hidden at least that well (as a culled
    // pass reasons). Such samples are not evaluated (density 0: their weights, and every later
    // one's, move by at most that much). A fitted body is opaque within one sample of its
    // surface, so this leaves out most samples behind it.
    let hidden_from = |i: usize, density: &[f32], row: &[u32]| {
        let mut depth = 0.0f32;
        (i * s..(i + 1) * s)
            .find(|&k| {
                if row[k] != NOT_DECODED {
                    depth += density[k] * coarse.delta[k];
                    false
                } else {
                    (-depth).exp() < CULL_TRANSMITTANCE
                }
            })
            .unwrap_or((i + 1) * s)
    };
    // Every fourth sample, then the other even ones in front of what those show hidden.
    let first: Vec<usize> = (0..r * s).filter(|k| (k % s) % 4 == 0).collect();
    evaluate(&first, &mut density, &mut value, &mut row);
    let even: Vec<usize> = (0..r).flat_map(|i| (i * s..hidden_from(i, &density, &row)).filter(|k| (k % s) % 4 == 2)).collect();
    evaluate(&even, &mut density, &mut value, &mut row);
    let beta = crate::backend::host_scalar(still.beta());
    // The most a skipped sample's optical depth can be, from a neighbour's SDF value `v` at
    // distance `gap` (VolSDF: density exp(-sdf / beta) / (2 beta) outside the body).
    let bound = |v: f32, gap: f32, delta: f32| {
        let outside = v - SDF_SLOPE_BOUND * gap;
        if outside > 0.0 {
            delta * (-outside / beta).exp() * 0.5 / beta
        } else {
            f32::INFINITY
        }
    };
    // A ray with a hidden even sample has optical depth and is not empty (a hidden sample's
    // SDF value is NaN, which bounds nothing).
    let empty = |i: usize| {
        (i * s..(i + 1) * s).all(|k| match (k % s) % 2 {
            0 => row[k] != NOT_DECODED && density[k] * coarse.delta[k] < EMPTY_OPTICAL_DEPTH,
            _ => {
                [k - 1, k + 1].iter().filter(|&&n| n < (i + 1) * s).all(|&n| bound(value[n], (t[k] - t[n]).abs(), coarse.delta[k]) < EMPTY_OPTICAL_DEPTH * 1e-3)
            }
        })
    };
    let odd: Vec<usize> = (0..r).filter(|&i| !empty(i)).flat_map(|i| (i * s..hidden_from(i, &density, &row)).filter(|k| (k % s) % 2 == 1)).collect();
    evaluate(&odd, &mut density, &mut value, &mut row);
    (density, Decoded::cat(parts), row)
}

/// Rows `rows` as an index tensor, for `select` and `select_assign`.
pub fn row_index(rows: impl ExactSizeIterator<Item = usize>, device: &Device) -> Tensor<1, Int> {
    let n = rows.len();
    Tensor::<1, Int>::from_data(TensorData::new(rows.map(|k| k as i64).collect::<Vec<i64>>(), [n]), device)
}

/// The row of a sample whose point was not decoded (a fine sample of a ray found empty).
const NOT_DECODED: u32 = u32::MAX;

/// The field's decoding of a still pass's samples: `rows[k]` is merged sample `k`'s row in
/// `decoded` (`NOT_DECODED` for none).
struct SampleDecoding {
    decoded: Decoded,
    rows: Vec<u32>,
}

/// What `locate` returns besides the samples.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Want {
    Samples,
    Densities,
    Culled,
}

struct Located {
    samples: Samples,
    /// Per merged sample: its density (`Want::Densities`), or for `Want::Culled` the coarse
    /// samples' densities and +infinity for the fine ones.
    density: Vec<f32>,
    /// `Want::Culled`: the merged samples the differentiable pass evaluates, ascending.
    kept: Option<Vec<usize>>,
    /// `Want::Densities` with fine samples: the decoded points, for their albedo.
    decoding: Option<SampleDecoding>,
}

/// The samples a culled pass keeps (`CULL_OPTICAL_DEPTH`, `CULL_TRANSMITTANCE`), from their
/// densities and the transmittance before them.
fn culled(samples: &Samples, density: &[f32], before: &[f32]) -> Vec<usize> {
    (0..samples.t.len()).filter(|&k| before[k] >= CULL_TRANSMITTANCE && density[k] * samples.delta[k] >= CULL_OPTICAL_DEPTH).collect()
}

/// Renders `rays` for a picture, with no gradients to keep: the same samples and compositing
/// as `render` (a test pins the two together), but the samples' densities are the ones
/// `locate` evaluated, composited on the CPU, and the field is asked for the albedo only at
/// the samples of weight `sampling.albedo_floor` or more; the differentiable pass, which
/// evaluates every sample again, is skipped.
pub fn render_still(
    field: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    sampling: Sampling,
    jitter: &[f32],
    normals: Option<GradientMethod>,
    device: &Device,
) -> Deferred {
    let start = std::time::Instant::now();
    let r = rays.len();
    let (origins, directions) = ray_tensors(rays, device);
    let Located { samples, density, decoding, .. } = locate(field, pose, rays, &origins, &directions, sampling, jitter, Want::Densities);
    let located = start.elapsed().as_secs_f64();
    let s = sampling.total();
    let weights = host_weights(&samples, &density, r);
    let mut accumulation = vec![0.0f32; r];
    let mut depth = vec![0.0f32; r];
    let mut surface = vec![0.0f32; 3 * r];
    for i in 0..r {
        let w = &weights[i * s..(i + 1) * s];
        accumulation[i] = w.iter().sum();
        depth[i] = w.iter().zip(&samples.t[i * s..(i + 1) * s]).map(|(w, t)| w * t).sum::<f32>() / (accumulation[i] + 1e-6);
        for c in 0..3 {
            surface[3 * i + c] = rays.origins[3 * i + c] + rays.directions[3 * i + c] * depth[i];
        }
    }
    // The albedo where the weights matter: those samples' points decoded, weighted, summed.
    let rows: Vec<usize> = (0..r * s).filter(|&k| weights[k] >= sampling.albedo_floor).collect();
    let mut albedo = vec![0.0f32; 3 * r];
    if !rows.is_empty() {
        // Read off the points the search decoded; looked up again only if one of them was not.
        let albedo_rows = match &decoding {
            Some(d) if rows.iter().all(|&k| d.rows[k] != NOT_DECODED) => {
                field.valid().albedo_at(&d.decoded, Some(row_index(rows.iter().map(|&k| d.rows[k] as usize), device)))
            }
            _ => field.albedo_at(&field.decode(points_at(rays, &samples.t, s, &rows, device), pose), None),
        };
        let values = crate::backend::host_values(albedo_rows);
        for (j, &k) in rows.iter().enumerate() {
            for c in 0..3 {
                albedo[3 * (k / s) + c] += weights[k] * values.get(3 * j + c).copied().unwrap_or(0.0);
            }
        }
    }
    let forward = start.elapsed().as_secs_f64();
    let tensor1 = |v: Vec<f32>| Tensor::<1>::from_data(TensorData::new(v, [r]), device);
    let tensor2 = |v: Vec<f32>, width: usize| Tensor::<2>::from_data(TensorData::new(v, [r, width]), device);
    // A normal where the ray carries albedo: elsewhere (no sample of weight `albedo_floor` or
    // more) the albedo is zero, so is its shaded colour whatever the normal, and the ray's
    // reverse direction stands in for it.
    let mut has_albedo = vec![false; r];
    rows.iter().for_each(|&k| has_albedo[k / s] = true);
    let carried: Vec<usize> = (0..r).filter(|&i| has_albedo[i]).collect();
    let normal = normals.map(|method| {
        if carried.len() == r {
            return unit_rows(field.sdf_gradient(tensor2(surface.clone(), 3), pose, method));
        }
        let mut normal: Vec<f32> = rays.directions.iter().map(|d| -d).collect();
        if !carried.is_empty() {
            let points: Vec<f32> = carried.iter().flat_map(|&i| surface[3 * i..3 * i + 3].to_vec()).collect();
            let points = Tensor::<2>::from_data(TensorData::new(points, [carried.len(), 3]), device);
            let unit = crate::backend::host_values(unit_rows(field.sdf_gradient(points, pose, method)));
            for (j, &i) in carried.iter().enumerate() {
                normal[3 * i..3 * i + 3].copy_from_slice(unit.get(3 * j..3 * j + 3).unwrap_or(&[f32::NAN; 3]));
            }
        }
        tensor2(normal, 3)
    });
    let surface = tensor2(surface, 3);
    let t = Tensor::<2>::from_data(TensorData::new(samples.t, [r, s]), device);
    let seconds = [located, forward - located, start.elapsed().as_secs_f64() - forward];
    Deferred {
        accumulation: tensor1(accumulation),
        albedo: tensor2(albedo, 3),
        depth: tensor1(depth),
        surface,
        normal,
        sample_points: sample_points(&origins, &directions, &t),
        sample_density: Tensor::<1>::from_data(TensorData::new(density, [r * s]), device),
        seconds,
        evaluated: 0,
    }
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
    let start = std::time::Instant::now();
    let r = rays.len();
    let (origins, directions) = ray_tensors(rays, device);
    let want = if sampling.cull { Want::Culled } else { Want::Samples };
    let Located { samples, density: searched, kept, .. } = locate(field, pose, rays, &origins, &directions, sampling, jitter, want);
    let located = start.elapsed().as_secs_f64();
    let s = sampling.total();
    let t = Tensor::<2>::from_data(TensorData::new(samples.t.clone(), [r, s]), device);
    let delta = Tensor::<2>::from_data(TensorData::new(samples.delta.clone(), [r, s]), device);
    let points = sample_points(&origins, &directions, &t);
    let (weights, albedo, density, evaluated) = match kept {
        Some(kept) => {
            let (weights, albedo, density) = culled_pass(field, pose, rays, &samples.t, &kept, delta, device);
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
            let decoded = field.decode(points.clone(), pose);
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
    let normal = normals.map(|method| {
        let gradient = field.sdf_gradient(surface.clone(), pose, method);
        unit_rows(gradient)
    });
    let seconds = [located, forward - located, start.elapsed().as_secs_f64() - forward];
    Deferred { accumulation, albedo, depth, surface, normal, sample_points: points, sample_density: density, seconds, evaluated }
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

/// Fewest rays a part of a split render holds: below this a second thread costs more than it saves.
const MIN_RAYS_PER_PART: usize = 64;

/// `render`, the rays cut into up to `parts` runs rendered at once on as many threads, their
/// outputs joined in ray order. Why: most of a step's tensor operations run on one thread
/// (flex parallelises matrix products, not the element-wise work between them), so a second
/// core sat idle. Every ray's samples and arithmetic are its own, so the result is the unsplit
/// render's (a test pins them). Each part renders through its own fork of `field` (the same
/// parameters, same ids, as leaves of a graph of its own: burn's autodiff graph client is not
/// safe for several threads registering nodes of one shared graph), so after the backward pass
/// the parameters' gradients are the sum of the field's and of every returned fork's
/// (`sum_gradients`). One part: `field` itself, no forks.
#[allow(clippy::too_many_arguments)]
pub fn render_in_parts(
    field: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    sampling: Sampling,
    jitter: &[f32],
    normals: Option<GradientMethod>,
    device: &Device,
    parts: usize,
) -> (Deferred, Vec<AvatarField>) {
    let r = rays.len();
    let parts = parts.min(r / MIN_RAYS_PER_PART).max(1);
    if parts == 1 {
        return (render(field, pose, rays, sampling, jitter, normals, device), Vec::new());
    }
    use rayon::prelude::*;
    let per_part = r.div_ceil(parts);
    let forks: Vec<AvatarField> = (0..parts).map(|_| field.clone().fork(device)).collect();
    let rendered: Vec<Deferred> = forks
        .par_iter()
        .enumerate()
        .map(|(k, fork)| {
            let (lo, hi) = (k * per_part, ((k + 1) * per_part).min(r));
            render(fork, pose, &rays.range(lo, hi), sampling, &sampling.jitter_of(jitter, r, lo, hi), normals, device)
        })
        .collect();
    (Deferred::cat(rendered), forks)
}

/// The gradients of `module`'s parameters, summed over it and its `forks` (the same
/// parameters as leaves of other graphs: `render::render_in_parts`).
pub fn sum_gradients<M: Module>(grads: &mut burn::tensor::Gradients, module: &M, forks: &[M]) -> burn::optim::GradientsParams {
    use burn::optim::GradientsParams;
    struct Adder {
        into: GradientsParams,
        from: GradientsParams,
    }
    impl burn::module::ModuleVisitor for Adder {
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            if let Some(g) = self.from.remove::<D>(param.id) {
                let sum = match self.into.remove::<D>(param.id) {
                    Some(sum) => sum + g,
                    None => g,
                };
                self.into.register(param.id, sum);
            }
        }
    }
    let mut adder = Adder { into: GradientsParams::from_module(grads, module), from: GradientsParams::new() };
    for fork in forks {
        adder.from = GradientsParams::from_module(grads, fork);
        module.visit(&mut adder);
    }
    adder.into
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
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_views_coarse_pass_skips_only_samples_the_sdf_shows_empty_or_the_rounds_before_show_hidden() {
        use crate::skeleton::{Bone, Pose, Skeleton};
        use glam::{DMat4, DQuat};
        let skeleton =
            Skeleton { bones: vec![Bone { name: "spine".into(), parent: None, length: 0.5 }, Bone { name: "arm".into(), parent: Some(0), length: 0.3 }] };
        let pose = Pose { bone_to_world: vec![DMat4::IDENTITY, DMat4::from_rotation_translation(DQuat::from_rotation_z(1.2), DVec3::new(0.0, 0.4, 0.0))] };
        let device = Device::flex();
        let mut field = crate::field::FieldConfig::with_grid(vec![0.5, 0.3], 1.0).init(&device, 3);
        // A fitted field's sharp surface (beta at its floor), not a fresh field's haze.
        field.beta_raw = burn::module::Param::from_tensor(Tensor::from_data(TensorData::new(vec![-1e3f32], [1]), &device));
        let tensors = PoseTensors::new(&pose, &skeleton, &device);
        // Rays from 2 m away toward a lattice around the bones: through the body and beside it.
        let eye = DVec3::new(0.1, 0.3, 2.0);
        let mut rays = RaySet::default();
        // Each ray four times, its bounds shifted by a quarter of a sample's spacing each time, so
        // that some rays cross the body between two samples of the first round.
        for k in 0..256 {
            let target = DVec3::new(-0.5 + (k % 8) as f64 / 7.0, -0.2 + (k / 8 % 8) as f64 / 7.0, 0.0);
            let shift = (k / 64) as f64 * 0.02;
            rays.push(eye, (target - eye).normalize(), Some((1.0 + shift, 3.0 + shift)));
        }
        let (r, s) = (rays.len(), 24);
        let coarse = stratified(&rays, s, &vec![0.5; r * s]);
        let (density, decoded, row) = coarse_densities(&field, &tensors, &rays, &coarse, s, &device);
        let (origins, directions) = ray_tensors(&rays, &device);
        let (full, _) = densities(&field, &tensors, &origins, &directions, &coarse.t, r);
        let before = transmittance_before(&coarse, &full, r);
        let (mut skipped, mut kept, mut hidden, mut hidden_even) = (0, 0, 0, 0);
        for i in 0..r {
            let samples = i * s..(i + 1) * s;
            let empty = full[samples.clone()].iter().zip(&coarse.delta[samples.clone()]).all(|(d, delta)| d * delta < EMPTY_OPTICAL_DEPTH);
            if empty && samples.clone().any(|k| row[k] == NOT_DECODED) {
                // Skipped: every other sample (the whole ray is empty in one full pass).
                skipped += 1;
                assert!(samples.clone().all(|k| ((k % s) % 2 == 1) == (row[k] == NOT_DECODED)), "ray {i}");
                continue;
            }
            kept += 1;
            for k in samples {
                if row[k] == NOT_DECODED {
                    // Hidden: a later round's sample the full pass puts behind the surface.
                    hidden += 1;
                    hidden_even += usize::from((k % s) % 2 == 0);
                    assert!((k % s) % 4 != 0 && density[k] == 0.0, "sample {k}");
                    assert!(before[k] < CULL_TRANSMITTANCE, "sample {k} left out, {} of the ray passes it", before[k]);
                } else {
                    assert!((density[k] - full[k]).abs() <= 1e-5 * full[k].abs().max(1e-3), "sample {k}: {} against {}", density[k], full[k]);
                }
            }
        }
        assert!(
            skipped > 0 && kept > 0 && hidden_even > 0 && hidden > hidden_even,
            "{skipped} rays skipped, {kept} kept, {hidden} samples hidden ({hidden_even} even)"
        );
        assert_eq!(decoded.sdf.dims()[0], row.iter().filter(|&&k| k != NOT_DECODED).count());
    }

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
    fn merged_intervals_tile_the_bound_and_probes_sharpen_the_draws() {
        let rays = one_ray(1.0, 3.0);
        let coarse = stratified(&rays, 8, &[0.5; 8]);
        // A surface in the fifth stratum, at t = 2.05: density 0 before it, 1e4 behind.
        let body = |t: f32| if t < 2.05 { 0.0 } else { 1e4 };
        let density: Vec<f32> = coarse.t.iter().map(|&t| body(t)).collect();
        let weights = host_weights(&coarse, &density, 1);
        assert!((weights.iter().sum::<f32>() - 1.0).abs() < 1e-5, "an opaque body takes all the weight");
        let probes = draw(&rays, &coarse, &weights, 16, &[0.5; 16]);
        let probe_density: Vec<f32> = probes.iter().map(|&t| body(t)).collect();
        let (probed, merged_density) = merge(&rays, &coarse.t, 8, &probes, 16, Some((&density, &probe_density)));
        assert_eq!(probed.t.len(), 24);
        assert!(probed.t.windows(2).all(|w| w[0] <= w[1]));
        for (t, d) in probed.t.iter().zip(&merged_density) {
            assert_eq!(*d, body(*t), "densities travel with their samples");
        }
        let covered: f32 = probed.delta.iter().sum();
        assert!((covered - 2.0).abs() < 1e-5, "intervals cover the bound: {covered}");
        for k in 1..probed.t.len() {
            assert!((probed.lo[k] - (probed.lo[k - 1] + probed.delta[k - 1])).abs() < 1e-6, "intervals are contiguous");
        }
        // The coarse pass locates the surface within a stratum (25 cm), the probes within their
        // spacing: the fine draws from the probed weights crowd the surface.
        let fine_coarse = draw(&rays, &coarse, &weights, 16, &[0.5; 16]);
        let fine_probed = draw(&rays, &probed, &host_weights(&probed, &merged_density, 1), 16, &[0.5; 16]);
        let near = |draws: &[f32]| draws.iter().filter(|&&t| (t - 2.05).abs() < 0.02).count();
        assert!(near(&fine_probed) >= 12 && near(&fine_probed) > 3 * near(&fine_coarse), "{} vs {}", near(&fine_probed), near(&fine_coarse));
        let (fine, _) = merge::<f32>(&rays, &coarse.t, 8, &fine_probed, 16, None);
        assert_eq!(fine.t.len(), 24, "the rendered set holds the coarse samples and the fine draws");
    }

    #[test]
    fn host_weights_match_the_differentiable_compositing() {
        let (r, n) = (3, 7);
        let samples =
            stratified(&RaySet { origins: vec![0.0; 3 * r], directions: vec![0.0; 3 * r], near: vec![0.5, 1.0, 0.0], far: vec![2.0, 1.5, 4.0] }, n, &[0.3; 21]);
        let density: Vec<f32> = (0..r * n).map(|k| [0.0, 3.0, 40.0, 0.5, 900.0, 0.0, 12.0][k % n] * (1.0 + k as f32 * 0.1)).collect();
        let device = Device::flex();
        let tensor = compositing_weights(
            Tensor::from_data(TensorData::new(density.clone(), [r, n]), &device),
            Tensor::from_data(TensorData::new(samples.delta.clone(), [r, n]), &device),
        );
        let expected = tensor.into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
        for (a, b) in host_weights(&samples, &density, r).iter().zip(&expected) {
            assert!((a - b).abs() < 1e-6, "{a} vs {b}");
        }
    }
}
