//! What leaves umbra: `umbra export-mesh`, a fitted avatar's surface (`eval::surface_mesh`)
//! in one of its scene's poses as an OBJ mesh with vertex colours (the fitted albedo, scaled to
//! reflectance as the renders are) and normals (the SDF's exact gradient); `umbra
//! export-gaussians`, its shadow Gaussians posed in a frame as a splatting PLY (`ply`).

pub mod gltf;
pub mod ply;

use crate::eval::{coloured_frame_surface, frame_surface};
use crate::fit_error::{io, FitError};
use crate::messages::TrainMessage;
use crate::skeleton::PoseTensors;
use burn::module::Module;
use std::path::{Path, PathBuf};

pub struct ExportOptions {
    pub run: PathBuf,
    pub scene: Option<PathBuf>,
    pub targets: Targets,
    pub backend: crate::backend::Backend,
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

/// The first line of every OBJ `export-mesh` writes: what lets a later export replace it.
pub const EXPORT_HEADER: &str = "# umbra export-mesh";

/// Whether `path` is a file an earlier `export-mesh` wrote (its first line is `EXPORT_HEADER`).
fn written_by_export(path: &Path) -> bool {
    use std::io::Read;
    let line = format!("{EXPORT_HEADER}\n");
    let mut head = vec![0u8; line.len()];
    let is_file = std::fs::symlink_metadata(path).is_ok_and(|m| m.is_file());
    is_file && std::fs::File::open(path).and_then(|mut f| f.read_exact(&mut head)).is_ok() && head == line.as_bytes()
}

/// Exports the meshes; every file is written atomically, and nothing before the run, its scene
/// and the frames are known good.
pub fn export_meshes(options: &ExportOptions, mut on: impl FnMut(TrainMessage)) -> Result<Vec<Exported>, FitError> {
    let restored = crate::run::restore(&options.run, options.scene.as_deref(), options.backend)?;
    let scene = &restored.scene;
    let targets = options.targets.resolve(scene.frames.len())?;
    // A file in the way is replaced only when an earlier export wrote it.
    if let Some((_, path)) = targets.iter().find(|(_, path)| path.exists() && !written_by_export(path)) {
        return Err(io(path, "exists and is not a mesh umbra export-mesh wrote: choose another --out, or move it away (nothing was written)"));
    }
    let written = match &options.targets {
        Targets::One { out, .. } => out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")).to_path_buf(),
        Targets::All { dir } => dir.clone(),
    };
    let _lock = crate::run_lock::RunLock::for_output(&options.run, &written, "export-mesh")?;
    let model = restored.fitted.model.valid();
    let device = restored.fitted.device.clone().without_autodiff();
    let scale = crate::run::albedo_scale(scene, &model);
    on(TrainMessage::Evaluating { images: targets.len() });
    let mut done = Vec::new();
    for (k, (frame, path)) in targets.iter().enumerate() {
        let (mesh, colours, normals, _) = coloured_frame_surface(&model, scene, *frame, scale, &device)?;
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|e| io(parent, e))?;
        }
        let text = format!("{EXPORT_HEADER}\n{}", mesh.to_obj(Some(&colours), Some(&normals)));
        crate::imageio::write_atomic(path, text.as_bytes()).map_err(|e| io(path, e))?;
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

/// Whether `path` is a file an earlier `export-gaussians` wrote: a regular file that opens with
/// the header `ply::ply_bytes` writes (`ply::HEADER_START`), not merely one that holds its text.
fn written_by_ply_export(path: &Path) -> bool {
    use std::io::Read;
    let start = ply::HEADER_START.as_bytes();
    let mut head = vec![0u8; start.len()];
    let is_file = std::fs::symlink_metadata(path).is_ok_and(|m| m.is_file());
    is_file && std::fs::File::open(path).and_then(|mut f| f.read_exact(&mut head)).is_ok() && head == start
}

/// `umbra export-gaussians`: the fitted shadow Gaussians posed in `frame` (a position in the
/// scene's frames) into `out` as a splatting PLY, written atomically; an existing file is
/// replaced only when an earlier export wrote it. Returns how many Gaussians.
pub fn export_gaussians(run: &Path, scene: Option<&Path>, frame: usize, out: &Path, backend: crate::backend::Backend) -> Result<usize, FitError> {
    let restored = crate::run::restore(run, scene, backend)?;
    let scene = &restored.scene;
    if frame >= scene.frames.len() {
        return Err(FitError::Input(format!("--frame {frame}: out of range, the scene has {} frames", scene.frames.len())));
    }
    if out.exists() && !written_by_ply_export(out) {
        return Err(io(out, "exists and is not a PLY umbra export-gaussians wrote: choose another --out, or move it away (nothing was written)"));
    }
    let model = restored.fitted.model.valid();
    let posed = model.gaussians.to_set().pose(&scene.frames[frame].pose);
    let casters = model.light.shadow_casters_posed(&posed);
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| io(parent, e))?;
    }
    crate::imageio::write_atomic(out, &ply::ply_bytes(&casters, frame)).map_err(|e| io(out, e))?;
    Ok(casters.len())
}

/// What `umbra export-avatar` writes.
pub struct AvatarOptions {
    pub run: PathBuf,
    pub scene: Option<PathBuf>,
    /// A clip (BVH or joints.json) to animate with instead of the scene's frames.
    pub motion: Option<PathBuf>,
    pub units: Option<crate::capture::Units>,
    pub out: PathBuf,
    pub backend: crate::backend::Backend,
}

/// What an exported avatar holds.
pub struct AvatarExported {
    pub vertices: usize,
    pub triangles: usize,
    pub bones: usize,
    pub frames: usize,
    /// The skinning checked: the frame, and the skinned mesh posed in it against the surface
    /// meshed in it (`geometry::compare`: accuracy is the skinned mesh's mean distance to it).
    pub skin_check: Option<(usize, crate::geometry::GeometryScores)>,
}

/// How many points `skin_check` samples on each surface.
const SKIN_CHECK_SAMPLES: usize = 20_000;

/// The skinned mesh posed by its weights in `frame` (as a viewer poses the file) against the
/// surface meshed directly in that frame.
fn skin_check(
    model: &crate::avatar::Avatar,
    scene: &crate::scene::Scene,
    skinned: &gltf::SkinnedMesh,
    frame: usize,
    device: &burn::tensor::Device,
) -> Result<Option<crate::geometry::GeometryScores>, FitError> {
    let pose = &scene.frames[frame].pose;
    let (meshed, _) = frame_surface(model, scene, frame, device)?;
    let vertices = gltf::skin_vertices(skinned, &scene.frames[0].pose, pose);
    let posed = crate::isosurface::Mesh { vertices, triangles: skinned.mesh.triangles.clone() };
    Ok(crate::geometry::compare(&posed, &meshed, SKIN_CHECK_SAMPLES, 0, None))
}

/// Whether `path` is a GLB an earlier `export-avatar` wrote (its JSON chunk's generator).
fn written_by_avatar_export(path: &Path) -> bool {
    use std::io::Read;
    let Ok(mut file) = std::fs::File::open(path) else { return false };
    let mut head = [0u8; 20];
    if file.read_exact(&mut head).is_err() || &head[..4] != b"glTF" || &head[16..20] != b"JSON" {
        return false;
    }
    let length = u32::from_le_bytes([head[12], head[13], head[14], head[15]]) as u64;
    let mut json = Vec::new();
    let read = file.take(length.min(GLB_JSON_BYTES)).read_to_end(&mut json);
    let document: Option<serde_json::Value> = read.ok().and_then(|_| serde_json::from_slice(&json).ok());
    document.is_some_and(|d| d["asset"]["generator"] == gltf::GENERATOR)
}

/// The most of a GLB's JSON chunk read to tell whether umbra wrote it.
const GLB_JSON_BYTES: u64 = 256 << 20;

/// The poses an exported avatar is animated with and their times (s): the clip's, driving the
/// fitted bones (`capture::retarget`), or the scene's frames in order (at their times when
/// every frame has one and they increase, else 30 a second: a scene's test frames may carry
/// times among its training ones').
fn avatar_motion(options: &AvatarOptions, restored: &crate::run::FittedRun) -> Result<Vec<(f64, crate::skeleton::Pose)>, FitError> {
    let scene = &restored.scene;
    let Some(file) = &options.motion else {
        let times: Option<Vec<f64>> = scene.frames.iter().map(|f| f.time).collect();
        let times = times.filter(|t| t.windows(2).all(|w| w[1] > w[0])).unwrap_or_else(|| (0..scene.frames.len()).map(|k| k as f64 / 30.0).collect());
        return Ok(times.into_iter().zip(&scene.frames).map(|(t, f)| (t, f.pose.clone())).collect());
    };
    let clip = crate::capture::read_clip(file).map_err(|e| FitError::Input(e.to_string()))?;
    let units = options.units.unwrap_or_else(|| crate::capture::Units::for_extent(crate::capture::joint_extent(&clip)));
    let driven = crate::capture::retarget::drive(&scene.skeleton, &scene.frames[0].pose, &clip, units.metres()).map_err(|e| io(file, e))?;
    Ok(driven.poses.into_iter().enumerate().map(|(k, pose)| (k as f64 * driven.frame_time, restored.shown_motion(pose))).collect())
}

/// The fitted surface in the scene's first frame with its skinning (`gltf::SkinnedMesh`).
pub fn skinned_mesh(model: &crate::avatar::Avatar, scene: &crate::scene::Scene, device: &burn::tensor::Device) -> Result<gltf::SkinnedMesh, FitError> {
    let bind = &scene.frames[0].pose;
    let tensors = PoseTensors::new(bind, &scene.skeleton, device);
    let scale = crate::run::albedo_scale(scene, model);
    let (mesh, colours, normals, _) = coloured_frame_surface(model, scene, 0, scale, device)?;
    let weights = mesh.vertices.iter().map(|v| gltf::four_largest(model.field.skinning_weights(&tensors.frames, v.as_vec3().to_array()))).collect();
    Ok(gltf::SkinnedMesh { mesh, normals, colours, weights })
}

/// `umbra export-avatar`: the fitted surface as a skinned glTF binary animated by the scene's
/// frames or a clip, written atomically; an existing file is replaced only when an earlier
/// export wrote it.
pub fn export_avatar(options: &AvatarOptions) -> Result<AvatarExported, FitError> {
    let restored = crate::run::restore(&options.run, options.scene.as_deref(), options.backend)?;
    let scene = &restored.scene;
    let out = &options.out;
    if out.exists() && !written_by_avatar_export(out) {
        return Err(io(out, "exists and is not a GLB umbra export-avatar wrote: choose another --out, or move it away (nothing was written)"));
    }
    let motion = avatar_motion(options, &restored)?;
    let model = restored.fitted.model.valid();
    let device = restored.fitted.device.clone().without_autodiff();
    let skinned = skinned_mesh(&model, scene, &device)?;
    let name = scene.display_name();
    let bytes = gltf::glb_bytes(&scene.skeleton, &skinned, &scene.frames[0].pose, &motion, &name);
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| io(parent, e))?;
    }
    crate::imageio::write_atomic(out, &bytes).map_err(|e| io(out, e))?;
    // A frame in the middle of the scene's, away from the bind pose.
    let frame = scene.frames.len() / 2;
    let skin_check = skin_check(&model, scene, &skinned, frame, &device)?.map(|scores| (frame, scores));
    Ok(AvatarExported {
        vertices: skinned.mesh.vertices.len(),
        triangles: skinned.mesh.triangles.len(),
        bones: scene.skeleton.len(),
        frames: motion.len(),
        skin_check,
    })
}
