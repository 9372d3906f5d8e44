//! Finding the body along the rays: the coarse pass's densities (every other sample first,
//! the rest where the body may be), the probe and fine samples drawn where it was found, and the
//! field's decodings kept for the samples a picture needs.

use super::samples::*;
use super::{RaySet, Sampling};
use crate::field::{AvatarField, Decoded, PoseTensors};
use burn::module::Module;
use burn::tensor::{Device, IndexingUpdateOp, Int, Tensor, TensorData};

/// The field's density at every sample of every ray (`[R * S]`), without gradients, and the
/// field's decoding of those points (row `k` is sample `k`), from which their albedo is read
/// without looking them up again.
pub(super) fn densities(still: &AvatarField, pose: &PoseTensors, origins: &Tensor<2>, directions: &Tensor<2>, t: &[f32], r: usize) -> (Vec<f32>, Decoded) {
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
pub(super) fn densities_of(
    still: &AvatarField,
    pose: &PoseTensors,
    all: &RaySet,
    t: &[f32],
    r: usize,
    rays: &[usize],
    device: &Device,
) -> (Vec<f32>, Option<Decoded>) {
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

/// The points `o + t d` of the samples `rows` (indices into `[R * S]`, `s` per ray) as an
/// `[K, 3]` tensor.
pub(super) fn points_at(rays: &RaySet, t: &[f32], s: usize, rows: &[usize], device: &Device) -> Tensor<2> {
    let point = |k: usize, c: usize| rays.origins[3 * (k / s) + c] + rays.directions[3 * (k / s) + c] * t[k];
    let points: Vec<f32> = rows.iter().flat_map(|&k| [point(k, 0), point(k, 1), point(k, 2)]).collect();
    Tensor::<2>::from_data(TensorData::new(points, [rows.len(), 3]), device)
}

/// Each ray's sum of `albedo` (`[K, 3]`, one row per sample of `rows`, indices into `[R * S]`)
/// weighted by those samples' `weights` (`[R, S]`): `[R, 3]`.
pub(super) fn weighted_per_ray(albedo: Tensor<2>, weights: &Tensor<2>, rows: &[usize]) -> Tensor<2> {
    let [r, s] = weights.dims();
    let device = weights.device();
    let k = rows.len();
    let index = |v: Vec<i64>| Tensor::<1, Int>::from_data(TensorData::new(v, [k]), &device);
    let weighted = albedo * weights.clone().reshape([r * s]).select(0, index(rows.iter().map(|&j| j as i64).collect())).reshape([k, 1]);
    Tensor::zeros([r, 3], &device).select_assign(0, index(rows.iter().map(|&j| (j / s) as i64).collect()), weighted, IndexingUpdateOp::Add)
}

/// The rays' origins and directions as `[R, 3]` tensors.
pub(super) fn ray_tensors(rays: &RaySet, device: &Device) -> (Tensor<2>, Tensor<2>) {
    let r = rays.len();
    let tensor = |values: &Vec<f32>| Tensor::<2>::from_data(TensorData::new(values.clone(), [r, 3]), device);
    (tensor(&rays.origins), tensor(&rays.directions))
}

/// Points `o + t d` of every sample, `[R * S, 3]`.
pub(super) fn sample_points(origins: &Tensor<2>, directions: &Tensor<2>, t: &Tensor<2>) -> Tensor<2> {
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
pub(super) fn locate(
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
pub(super) const SDF_SLOPE_BOUND: f32 = 2.0;

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
pub(super) fn coarse_densities(
    still: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    coarse: &Samples,
    s: usize,
    device: &Device,
) -> (Vec<f32>, Decoded, Vec<u32>) {
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

/// The row of a sample whose point was not decoded (a fine sample of a ray found empty).
pub(super) const NOT_DECODED: u32 = u32::MAX;

/// The field's decoding of a still pass's samples: `rows[k]` is merged sample `k`'s row in
/// `decoded` (`NOT_DECODED` for none).
pub(super) struct SampleDecoding {
    pub(super) decoded: Decoded,
    pub(super) rows: Vec<u32>,
}

/// What `locate` returns besides the samples.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Want {
    Samples,
    Densities,
    Culled,
}

pub(super) struct Located {
    pub(super) samples: Samples,
    /// Per merged sample: its density (`Want::Densities`), or for `Want::Culled` the coarse
    /// samples' densities and +infinity for the fine ones.
    pub(super) density: Vec<f32>,
    /// `Want::Culled`: the merged samples the differentiable pass evaluates, ascending.
    pub(super) kept: Option<Vec<usize>>,
    /// `Want::Densities` with fine samples: the decoded points, for their albedo.
    pub(super) decoding: Option<SampleDecoding>,
}
