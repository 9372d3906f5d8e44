//! A render for a picture, with no gradients to keep (`render_still`): the search's own
//! densities composited on the host, the albedo decoded only where the weights matter, the
//! normals only where a ray carries albedo.

use super::locate::*;
use super::samples::*;
use super::{row_index, unit_rows, Deferred, RaySet, Sampling};
use crate::field::{AvatarField, GradientMethod, PoseTensors};
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};

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
        motion_leaves: Vec::new(),
        view_leaves: Vec::new(),
    }
}
