//! What leaves umbra: `umbra export-mesh`, a fitted avatar's surface (`eval::surface_mesh`)
//! in one of its scene's poses as an OBJ mesh with vertex colours (the fitted albedo, scaled to
//! reflectance as the renders are) and normals (the SDF's exact gradient); `umbra
//! export-gaussians`, its shadow Gaussians posed in a frame as a splatting PLY (`ply`).

pub mod ply;

use crate::eval::surface_mesh;
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
    let mut head = [0u8; EXPORT_HEADER.len()];
    path.is_file() && std::fs::File::open(path).and_then(|mut f| f.read_exact(&mut head)).is_ok() && head == EXPORT_HEADER.as_bytes()
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
    let extent = scene.body_extent();
    on(TrainMessage::Evaluating { images: targets.len() });
    let mut done = Vec::new();
    for (k, (frame, path)) in targets.iter().enumerate() {
        let pose = &scene.frames[*frame].pose;
        let (mesh, colours, normals) =
            surface_mesh(&model, &PoseTensors::new(pose, &scene.skeleton, &device), pose.bounds(&scene.skeleton), extent, scale, &device)?;
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

/// Whether `path` is a file an earlier `export-gaussians` wrote (`ply::PLY_MARK` in its header).
fn written_by_ply_export(path: &Path) -> bool {
    use std::io::Read;
    let mut head = [0u8; 256];
    let read = std::fs::File::open(path).and_then(|mut f| f.read(&mut head)).unwrap_or(0);
    path.is_file() && String::from_utf8_lossy(&head[..read]).contains(ply::PLY_MARK)
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
