//! `umbra export-mesh`: a fitted avatar's surface in one of its scene's poses as an OBJ mesh.
//! The fitted SDF is sampled on a grid whose cell follows the body's size (the grid field's
//! finest cell, 1/160 of the body's extent) over the posed bones' box widened by the grid's
//! reach; marching tetrahedra (`isosurface`) extracts its zero level set, each crossing is
//! bisected on the field itself, vertex colours are the fitted albedo (scaled to reflectance as
//! the renders are) and normals the SDF's exact gradient.

use crate::field::PoseTensors;
use crate::isosurface::{bisect, extract, Grid, Mesh};
use crate::train::{io, Avatar, FitError, TrainMessage};
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;
use std::path::PathBuf;

/// Mesh cells per body extent (the grid field's finest level: 11 mm for a human).
const CELLS_PER_EXTENT: f64 = 160.0;
/// How far beyond the posed bones' box the grid reaches, per body extent (the grid field's
/// boxes reach as far, so no surface the field can hold is cut).
const REACH_PER_EXTENT: f64 = 0.125;
/// Bisection rounds per crossing: the cell / 2^10, about 10 micrometres for a human.
const BISECTIONS: usize = 10;
/// Points per field evaluation.
const CHUNK: usize = 1 << 15;

pub struct ExportOptions {
    pub run: PathBuf,
    pub scene: Option<PathBuf>,
    pub targets: Targets,
    pub backend: crate::train::Backend,
}

/// Which poses go to which files.
pub enum Targets {
    /// One frame (by position in the scene's frames) to one file.
    One { frame: usize, out: PathBuf },
    /// Every frame into a folder, as `frame_PPPP.obj`.
    All { dir: PathBuf },
}

/// What one exported mesh holds.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Exported {
    pub frame: usize,
    pub path: PathBuf,
    pub vertices: usize,
    pub triangles: usize,
    pub closed: bool,
}

impl Targets {
    /// The frames and their files, for a scene of `frames` frames.
    fn resolve(&self, frames: usize) -> Result<Vec<(usize, PathBuf)>, FitError> {
        match self {
            Targets::One { frame, .. } if *frame >= frames => Err(FitError::Input(format!("--frame {frame}: out of range, the scene has {frames} frames"))),
            Targets::One { frame, out } => Ok(vec![(*frame, out.clone())]),
            Targets::All { dir } => Ok((0..frames).map(|f| (f, dir.join(format!("frame_{f:04}.obj")))).collect()),
        }
    }
}

/// Exports the meshes; every file is written atomically, and nothing before the run, its scene
/// and the frames are known good.
pub fn export_meshes(options: &ExportOptions, mut on: impl FnMut(TrainMessage)) -> Result<Vec<Exported>, FitError> {
    let trainer = crate::fit::restore(&options.run, options.scene.as_deref(), options.backend)?;
    let scene = &trainer.scene;
    let targets = options.targets.resolve(scene.frames.len())?;
    let _lock = crate::run_lock::RunLock::acquire(&options.run, "export-mesh")?;
    let model = trainer.model()?.valid();
    let device = trainer.device.clone().without_autodiff();
    let scale = crate::fit::albedo_scale(scene, &model);
    let extent = scene.frames.iter().map(|f| f.pose.bounds(&scene.skeleton)).map(|(a, b)| (b - a).length()).fold(0.0, f64::max);
    on(TrainMessage::Evaluating { images: targets.len() });
    let mut done = Vec::new();
    for (k, (frame, path)) in targets.iter().enumerate() {
        let pose = &scene.frames[*frame].pose;
        let (mesh, colours, normals) =
            surface(&model, &PoseTensors::new(pose, &scene.skeleton, &device), pose.bounds(&scene.skeleton), extent, scale, &device)?;
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|e| io(parent, e))?;
        }
        crate::imageio::write_atomic(path, mesh.to_obj(Some(&colours), Some(&normals)).as_bytes()).map_err(|e| io(path, e))?;
        done.push(Exported {
            frame: *frame,
            path: path.clone(),
            vertices: mesh.vertices.len(),
            triangles: mesh.triangles.len(),
            closed: mesh.is_closed_manifold(),
        });
        on(TrainMessage::Rendered { done: k + 1, total: targets.len(), name: path.display().to_string(), psnr: None });
    }
    Ok(done)
}

/// The fitted surface in one pose, with per-vertex albedo (times `scale`) and unit normals.
#[allow(clippy::type_complexity)]
fn surface(
    model: &Avatar,
    pose: &PoseTensors,
    bones: (DVec3, DVec3),
    extent: f64,
    scale: DVec3,
    device: &Device,
) -> Result<(Mesh, Vec<DVec3>, Vec<DVec3>), FitError> {
    let reach = DVec3::splat(extent * REACH_PER_EXTENT);
    let grid = Grid::covering(bones.0 - reach, bones.1 + reach, extent / CELLS_PER_EXTENT);
    let values: Vec<f64> = sdf(model, pose, &grid.points(), device)?.into_iter().map(f64::from).collect();
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
    if let Some(e) = failed {
        return Err(e);
    }
    let mut colours = Vec::with_capacity(mesh.vertices.len());
    let mut normals = Vec::with_capacity(mesh.vertices.len());
    for chunk in mesh.vertices.chunks(CHUNK) {
        let points = tensor(chunk, device);
        let albedo = read(model.field.forward(points.clone(), pose).albedo, 3 * chunk.len())?;
        let (_, gradient) = model.field.sdf_and_gradient(points, pose);
        let gradient = read(gradient, 3 * chunk.len())?;
        for (a, g) in albedo.chunks(3).zip(gradient.chunks(3)) {
            colours.push(DVec3::new(a[0] as f64, a[1] as f64, a[2] as f64) * scale);
            normals.push(DVec3::new(g[0] as f64, g[1] as f64, g[2] as f64).normalize_or(DVec3::Y));
        }
    }
    Ok((mesh, colours, normals))
}

/// A tensor's values, which must number `expected`.
fn read<const D: usize>(values: Tensor<D>, expected: usize) -> Result<Vec<f32>, FitError> {
    let values = values.into_data().convert::<f32>().try_to_vec::<f32>().map_err(|e| FitError::Input(format!("reading the field's output: {e:?}")))?;
    if values.len() != expected {
        return Err(FitError::Input(format!("the field returned {} values for {expected}", values.len())));
    }
    Ok(values)
}

fn tensor(points: &[DVec3], device: &Device) -> Tensor<2> {
    let flat: Vec<f32> = points.iter().flat_map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect();
    Tensor::from_data(TensorData::new(flat, [points.len(), 3]), device)
}

/// The fitted SDF at world points, in chunks.
fn sdf(model: &Avatar, pose: &PoseTensors, points: &[DVec3], device: &Device) -> Result<Vec<f32>, FitError> {
    let mut out = Vec::with_capacity(points.len());
    for chunk in points.chunks(CHUNK) {
        out.extend(read(model.field.sdf(tensor(chunk, device), pose), chunk.len())?);
    }
    Ok(out)
}
