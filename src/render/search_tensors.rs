//! The surface search by tensor ops on the rays' device, for a device that keeps its tensors (a
//! GPU): the coarse samples' densities, the probes and the fine samples drawn by inverse
//! transform of the compositing weights, and the merges in order along each ray, as `locate`
//! does on the host for a differentiable pass, with nothing read back. Only the stratified
//! samples, which depend on the rays and the jitter alone, are made on the host. A test pins
//! the samples to `locate`'s.

use super::samples::stratified;
use super::{compositing_weights, sample_points, RaySet, Sampling};
use crate::field::{AvatarField, PoseTensors};
use burn::module::Module;
use burn::tensor::{Device, IndexingUpdateOp, Int, Tensor, TensorData};

/// Each ray's samples (`[R, S]`, ascending along the ray): distances `t` and the intervals they
/// stand for, by their start `lo` and length `delta`.
#[derive(Clone, Debug)]
pub(super) struct SampleTensors {
    pub(super) t: Tensor<2>,
    pub(super) lo: Tensor<2>,
    pub(super) delta: Tensor<2>,
}

/// `[R, count]` of host values, ray-major.
fn upload(values: &[f32], r: usize, count: usize, device: &Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(values.to_vec(), [r, count]), device)
}

/// Where a differentiable pass samples `rays` (`locate` with `Want::Samples`): the coarse
/// strata, then, with fine samples, probes drawn where the coarse samples found weight and
/// fine samples where coarse and probes together did, merged with the coarse ones.
pub(super) fn search_by_tensors(
    field: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    origins: &Tensor<2>,
    directions: &Tensor<2>,
    sampling: Sampling,
    jitter: &[f32],
) -> SampleTensors {
    let device = origins.device();
    let r = rays.len();
    let (sc, sp, sf) = (sampling.coarse, sampling.probe, sampling.fine);
    let host = stratified(rays, sc, &jitter[..r * sc]);
    let coarse = SampleTensors { t: upload(&host.t, r, sc, &device), lo: upload(&host.lo, r, sc, &device), delta: upload(&host.delta, r, sc, &device) };
    if sf == 0 || r == 0 {
        return coarse;
    }
    let still = field.valid();
    let (o, d) = (origins.clone().without_autodiff(), directions.clone().without_autodiff());
    let density = |t: &Tensor<2>| {
        let [r, s] = t.dims();
        still.density(still.decode(sample_points(&o, &d, &t.clone().without_autodiff()), pose).sdf).reshape([r, s])
    };
    let bounds = (upload(&rays.near, r, 1, &device), upload(&rays.far, r, 1, &device));
    let coarse_density = density(&coarse.t);
    let (located, located_density) = if sp > 0 {
        let weights = compositing_weights(coarse_density.clone(), coarse.delta.clone());
        let probes = draw(&coarse, weights, sp, upload(&jitter[r * sc..r * (sc + sp)], r, sp, &device));
        let probe_density = density(&probes);
        let (merged, values) = merge(&coarse.t, &probes, &bounds, Some((coarse_density, probe_density)));
        (merged, values.unwrap_or_else(|| Tensor::zeros([r, sc + sp], &device)))
    } else {
        (coarse.clone(), coarse_density)
    };
    let weights = compositing_weights(located_density, located.delta.clone());
    let fine = draw(&located, weights, sf, upload(&jitter[r * (sc + sp)..r * (sc + sp + sf)], r, sf, &device));
    merge(&coarse.t, &fine, &bounds, None).0
}

/// `count` distances per ray drawn by stratified inverse transform (`samples::importance`) from
/// the piecewise-constant density whose mass over each sample's interval is its weight
/// (`[R, S]`) plus a small uniform floor: `[R, count]`, ascending along each ray.
pub(super) fn draw(samples: &SampleTensors, weights: Tensor<2>, count: usize, jitter: Tensor<2>) -> Tensor<2> {
    let device = weights.device();
    let [r, n] = weights.dims();
    let floor = weights.clone().sum_dim(1).clamp_min(1e-3) * 1e-2 / n as f32; // [R, 1]
    let cdf = Tensor::cat(vec![Tensor::zeros([r, 1], &device), (weights.clamp_min(0.0) + floor).cumsum(1)], 1); // [R, n + 1]
    let total = cdf.clone().slice([0..r, n..n + 1]);
    let strata = Tensor::<1, Int>::arange(0..count as i64, &device).float().reshape([1, count]);
    let target = (strata + jitter) / count as f32 * total.clone(); // [R, count]
    if n < 2 {
        return samples.lo.clone() + samples.delta.clone() * ((target / total.clamp_min(1e-12)).clamp(0.0, 1.0));
    }
    // Each target's bin: how many of the inner edges lie below it.
    let inner = cdf.clone().slice([0..r, 1..n]).reshape([r, 1, n - 1]).expand([r, count, n - 1]);
    let bin: Tensor<2, Int> = inner.lower(target.clone().reshape([r, count, 1]).expand([r, count, n - 1])).int().sum_dim(2).reshape([r, count]);
    let (low, high) = (cdf.clone().gather(1, bin.clone()), cdf.gather(1, bin.clone().add_scalar(1)));
    let inside = ((target - low.clone()) / (high - low).clamp_min(1e-12)).clamp(0.0, 1.0);
    let lo = samples.lo.clone().gather(1, bin.clone());
    let hi = lo.clone() + samples.delta.clone().gather(1, bin);
    lo.clone() + (hi - lo) * inside
}

/// Two sets of ascending distances per ray (`[R, A]`, `[R, B]`) merged in order, with the
/// intervals between the midpoints to each sample's neighbours (`bounds`: each ray's near and
/// far, `[R, 1]`), and the values they carry (the densities) when given. As a stable sort of
/// `a` then `b`: where distances tie, `a`'s come first.
pub(super) fn merge(
    a: &Tensor<2>,
    b: &Tensor<2>,
    bounds: &(Tensor<2>, Tensor<2>),
    values: Option<(Tensor<2>, Tensor<2>)>,
) -> (SampleTensors, Option<Tensor<2>>) {
    let device = a.device();
    let ([r, na], [_, nb]) = (a.dims(), b.dims());
    let n = na + nb;
    let index = |count: usize| Tensor::<1, Int>::arange(0..count as i64, &device).reshape([1, count]).expand([r, count]);
    // Each sample's place: its own index plus how many of the other set come before it.
    let a_wide = a.clone().reshape([r, na, 1]).expand([r, na, nb]);
    let b_wide = b.clone().reshape([r, 1, nb]).expand([r, na, nb]);
    let place_a = index(na) + b_wide.clone().lower(a_wide.clone()).int().sum_dim(2).reshape([r, na]);
    let place_b = index(nb) + a_wide.lower_equal(b_wide).int().sum_dim(1).reshape([r, nb]);
    let placed = |x: Tensor<2>, y: Tensor<2>| {
        Tensor::<2>::zeros([r, n], &device).scatter(1, place_a.clone(), x, IndexingUpdateOp::Add).scatter(1, place_b.clone(), y, IndexingUpdateOp::Add)
    };
    let t = placed(a.clone(), b.clone());
    let (near, far) = bounds.clone();
    let middles = (t.clone().slice([0..r, 0..n - 1]) + t.clone().slice([0..r, 1..n])) * 0.5;
    let lo = Tensor::cat(vec![near, middles.clone()], 1);
    let hi = Tensor::cat(vec![middles, far], 1).max_pair(lo.clone());
    let delta = hi - lo.clone();
    (SampleTensors { t, lo, delta }, values.map(|(x, y)| placed(x, y)))
}
