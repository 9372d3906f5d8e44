//! The fitted surface in a pose as a mesh: the SDF sampled on a grid whose cell follows the
//! body's size, its zero level set by marching tetrahedra (`isosurface`), each crossing bisected
//! on the field, and that mesh in a scene's frame cut to the frame's visual hull (`carve`).

use crate::avatar::Avatar;
use crate::fit_error::FitError;
use crate::isosurface::{bisect, extract, narrow_band_values, Grid, Mesh};
use crate::scene::Scene;
use crate::skeleton::PoseTensors;
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;

/// Bisection rounds per crossing: the cell / 2^10, about 10 micrometres for a human.
const BISECTIONS: usize = 10;
/// Points per field evaluation.
const CHUNK: usize = 1 << 15;

/// The fitted surface in one pose (`bones`: the posed bones' box; `extent`: the body's, from
/// `Scene::body_extent`).
pub fn surface_mesh(model: &Avatar, pose: &PoseTensors, bones: (DVec3, DVec3), extent: f64, device: &Device) -> Result<Mesh, FitError> {
    // As far as the field's grids reach (a loose body's root farther), so no surface the field
    // can hold is cut, at their finest cell.
    let (reach, cell) = model.field.surface_reach_and_cell(extent);
    let reach = DVec3::splat(reach);
    let grid = Grid::covering(bones.0 - reach, bones.1 + reach, cell);
    // Sampled whole only near the surface (the SDF on a human's grid, about a million points,
    // took longer than the rest of the mesh).
    let values = narrow_band_values(&grid, |points| Ok::<_, FitError>(sdf(model, pose, points, device)?.into_iter().map(f64::from).collect()))?;
    let mut failed = None;
    let mesh = extract(&grid, &values, |crossings| {
        bisect(crossings, BISECTIONS, |points| match sdf(model, pose, points, device) {
            Ok(values) => values.into_iter().map(|v| v < 0.0).collect(),
            Err(e) => {
                failed = Some(e);
                vec![false; points.len()]
            }
        })
    });
    match failed {
        Some(e) => Err(e),
        None => Ok(mesh),
    }
}

/// The fitted albedo (times `scale`) and the unit normal at each of a posed surface's vertices.
pub fn vertex_albedo_and_normals(
    model: &Avatar,
    pose: &PoseTensors,
    vertices: &[DVec3],
    scale: DVec3,
    device: &Device,
) -> Result<(Vec<DVec3>, Vec<DVec3>), FitError> {
    let mut colours = Vec::with_capacity(vertices.len());
    let mut normals = Vec::with_capacity(vertices.len());
    for chunk in vertices.chunks(CHUNK) {
        let points = tensor(chunk, device);
        let albedo = read(model.field.forward(points.clone(), pose).albedo, 3 * chunk.len())?;
        let (_, gradient) = model.field.sdf_and_gradient(points, pose);
        let gradient = read(gradient, 3 * chunk.len())?;
        for (a, g) in albedo.chunks(3).zip(gradient.chunks(3)) {
            colours.push(DVec3::new(a[0] as f64, a[1] as f64, a[2] as f64) * scale);
            normals.push(DVec3::new(g[0] as f64, g[1] as f64, g[2] as f64).normalize_or(DVec3::Y));
        }
    }
    Ok((colours, normals))
}

/// The fitted surface in `scene`'s frame `frame` (`surface_mesh`) cut to the frame's visual
/// hull (`carve`): the mesh and what the cut removed.
pub fn frame_surface(model: &Avatar, scene: &Scene, frame: usize, device: &Device) -> Result<(Mesh, crate::carve::Carved), FitError> {
    let pose = &scene.frames[frame].pose;
    let tensors = PoseTensors::new(pose, &scene.skeleton, device);
    let mesh = surface_mesh(model, &tensors, pose.bounds(&scene.skeleton), scene.body_extent(), device)?;
    // A pose without training images is judged in the training frames too, by its skinning.
    let skinning: Option<Vec<Vec<(usize, f32)>>> = crate::carve::needs_skinning(scene, frame)
        .then(|| mesh.vertices.iter().map(|v| model.field.skinning_weights(&tensors.frames, v.as_vec3().to_array())).collect());
    let carved = crate::carve::carve(&mesh, scene, frame, skinning.as_deref());
    Ok((carved.mesh.clone(), carved))
}

/// `frame_surface` with each kept vertex's albedo (times `scale`) and unit normal
/// (`vertex_albedo_and_normals`): the mesh, its colours and normals, and what the cut removed.
pub fn coloured_frame_surface(
    model: &Avatar,
    scene: &Scene,
    frame: usize,
    scale: DVec3,
    device: &Device,
) -> Result<(Mesh, Vec<DVec3>, Vec<DVec3>, crate::carve::Carved), FitError> {
    let (mesh, carved) = frame_surface(model, scene, frame, device)?;
    let tensors = PoseTensors::new(&scene.frames[frame].pose, &scene.skeleton, device);
    let (colours, normals) = vertex_albedo_and_normals(model, &tensors, &mesh.vertices, scale, device)?;
    Ok((mesh, colours, normals, carved))
}

/// A tensor's values, which must number `expected`.
fn read<const D: usize>(values: Tensor<D>, expected: usize) -> Result<Vec<f32>, FitError> {
    let values = crate::backend::to_host(values).map_err(|e| FitError::Input(format!("reading the field's output: {e}")))?;
    if values.len() != expected {
        return Err(FitError::Input(format!("the field returned {} values for {expected}", values.len())));
    }
    Ok(values)
}

fn tensor(points: &[DVec3], device: &Device) -> Tensor<2> {
    let flat: Vec<f32> = points.iter().flat_map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect();
    Tensor::from_data(TensorData::new(flat, [points.len(), 3]), device)
}

/// The fitted SDF at world points, in chunks on every thread.
fn sdf(model: &Avatar, pose: &PoseTensors, points: &[DVec3], device: &Device) -> Result<Vec<f32>, FitError> {
    use rayon::prelude::*;
    let chunks: Vec<Vec<f32>> =
        points.par_chunks(CHUNK).map(|chunk| read(model.field.sdf(tensor(chunk, device), pose), chunk.len())).collect::<Result<_, _>>()?;
    Ok(chunks.concat())
}
