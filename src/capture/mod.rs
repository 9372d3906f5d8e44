//! Captures as people have them, into `scene/1`: cameras from nerfstudio's `transforms.json`
//! (`nerfstudio`) or COLMAP's text model (`colmap`), motion from a BVH (`bvh`) or per-frame joint
//! transforms (`joints`), its bones by one rule (`bones`), masks from files or
//! the images' alpha, lens distortion removed (`distortion`), images downscaled and their
//! background blacked (`photos`), and the bones checked against the masks (`check`). `import` checks everything before it writes, writes into a
//! temporary folder and moves it into place, and says what it assumed.

pub mod bones;
pub mod bvh;
pub mod check;
pub mod colmap;
pub mod distortion;
pub mod export;
pub mod flaws;
pub mod joints;
pub mod nerfstudio;
mod options;
mod photos;
pub mod retarget;
mod scene_json;

pub use distortion::Distortion;

use crate::scene::Split;
use glam::{DMat4, DVec3};
pub use options::{parse_max_size, CaptureLight, ImportOptions, Units, Up, SMALLEST_MAX_SIZE};
use scene_json::{cameras, frame_json, light_json, World};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// A pinhole camera's intrinsics (pixels; the top-left pixel's centre at (0.5, 0.5)).
#[derive(Clone, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: usize,
    pub height: usize,
}

/// One image of a capture as its camera file lists it.
#[derive(Clone, Debug)]
pub struct CaptureImage {
    pub path: PathBuf,
    /// The image's name in the capture, without its extension: its path below the images'
    /// folder (`cam02/000000` in a rig's folder per camera). Unique; the scene's image and its
    /// mask take it.
    pub key: String,
    /// Where the camera file names it (`frames[12].file_path`).
    pub json_path: String,
    pub mask: Option<PathBuf>,
    pub intrinsics: Intrinsics,
    pub distortion: Distortion,
    /// OpenCV camera axes to the capture's world (its units, its up).
    pub camera_to_world: DMat4,
    pub time: Option<f64>,
    pub split: Split,
}

/// `name` (a camera file's image or mask path) as a relative path that stays inside the
/// folder it is relative to; an absolute path or one through `..` is refused.
pub(crate) fn inside(name: &str) -> Result<PathBuf, String> {
    let path = Path::new(name);
    let plain = path.components().all(|c| matches!(c, std::path::Component::Normal(_) | std::path::Component::CurDir));
    match !name.is_empty() && !path.is_absolute() && plain {
        true => Ok(path.components().filter(|c| matches!(c, std::path::Component::Normal(_))).collect()),
        false => Err(format!("{name:?} leads outside the capture (absolute, or through '..'): name files inside it")),
    }
}

/// An image's key (`CaptureImage::key`) from its path below the images' folder: `/`-separated,
/// without the extension.
pub(crate) fn image_key(relative: &Path) -> String {
    let parts: Vec<String> = relative.with_extension("").components().map(|c| c.as_os_str().to_string_lossy().into_owned()).collect();
    parts.join("/")
}

/// `x` as a person reads it: plain when it is an everyday size, in exponent form when it is
/// not (`1e300`, not three hundred digits).
pub(crate) fn readable(x: f64) -> String {
    match (1e-3..1e6).contains(&x.abs()) || x == 0.0 {
        true => format!("{}", (x * 1e4).round() / 1e4),
        false => format!("{x:.4e}"),
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{0}")]
    Scene(#[from] crate::scene::SceneError),
    #[error("{0}")]
    Motion(#[from] bvh::BvhError),
    #[error("{0}")]
    Image(#[from] crate::imageio::ImageError),
    #[error("{path}: {message}")]
    Input { path: PathBuf, message: String },
}

fn input(path: &Path, message: impl Into<String>) -> ImportError {
    ImportError::Input { path: path.to_path_buf(), message: message.into() }
}

/// What an import did and assumed, in sentences for the user.
#[derive(Clone, Debug, Default)]
pub struct ImportReport {
    /// The capture check's share of the bones' points inside the masks.
    pub score: f64,
    pub images: usize,
    pub cameras: usize,
    pub frames: usize,
    pub assumed: Vec<String>,
}

/// The only file of the capture folder ending in `extension` (what `--{what}` would name).
fn only_file(capture: &Path, extension: &str, what: &str) -> Result<PathBuf, ImportError> {
    let entries = std::fs::read_dir(capture).map_err(|e| input(capture, format!("cannot list the capture folder: {e}")))?;
    let matching: Vec<PathBuf> =
        entries.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.extension().is_some_and(|x| x.eq_ignore_ascii_case(extension))).collect();
    match matching.as_slice() {
        [one] => Ok(one.clone()),
        [] => Err(input(capture, format!("holds no .{extension} file: name the {what} with --{what}"))),
        many => Err(input(capture, format!("holds {} .{extension} files: name the {what} with --{what}", many.len()))),
    }
}

/// The capture's images with their cameras, and the camera file (for messages): `--cameras` (a
/// nerfstudio `transforms.json`, or a COLMAP text model's folder or one of its files), else the
/// capture's `transforms.json`, else a COLMAP model in the capture, `sparse/0` or `sparse`, its
/// images in `images/` (else the capture) and masks of their names in `masks/` when present.
fn read_cameras(options: &ImportOptions) -> Result<(Vec<CaptureImage>, PathBuf), ImportError> {
    let capture = &options.capture;
    let colmap_dir = |p: &Path| -> Option<PathBuf> {
        if p.is_dir() && p.join("cameras.txt").is_file() {
            return Some(p.to_path_buf());
        }
        let named = p.file_name().is_some_and(|n| n == "cameras.txt" || n == "images.txt");
        named.then(|| p.parent().unwrap_or(Path::new(".")).to_path_buf())
    };
    let dir = match &options.cameras {
        Some(file) => match colmap_dir(file) {
            Some(dir) => dir,
            None => return Ok((nerfstudio::read(file)?, file.clone())),
        },
        None if capture.join("transforms.json").is_file() => return Ok((nerfstudio::read(&capture.join("transforms.json"))?, capture.join("transforms.json"))),
        None => [capture.clone(), capture.join("sparse/0"), capture.join("sparse")].into_iter().find_map(|d| colmap_dir(&d)).ok_or_else(|| {
            input(
                capture,
                "holds no cameras: no transforms.json, and no COLMAP text model (cameras.txt, images.txt) in it, sparse/0 or sparse; name one with --cameras",
            )
        })?,
    };
    let images_dir = if capture.join("images").is_dir() { capture.join("images") } else { capture.clone() };
    let mut images = colmap::read(&dir, &images_dir)?;
    for image in &mut images {
        let mask = capture.join("masks").join(format!("{}.png", image.key));
        if options.masks.is_none() && mask.is_file() {
            image.mask = Some(mask);
        }
    }
    Ok((images, dir.join("images.txt")))
}

/// Imports the capture `options` describe into a new scene folder; `on(done, total)` follows
/// the images.
pub fn import(options: &ImportOptions, on: &(dyn Fn(usize, usize) + Sync)) -> Result<ImportReport, ImportError> {
    let out = &options.out;
    if out.exists() && std::fs::read_dir(out).map(|mut d| d.next().is_some()).unwrap_or(true) {
        return Err(input(out, "exists and is not an empty folder: import writes a new scene (nothing was written)"));
    }
    // `--out .` or `--out ..` names a folder by where it is: the scene is named after it.
    let out = &crate::files::absolute_target(out).map_err(|e| input(out, format!("{e} (nothing was written)")))?;
    let (images, camera_file) = read_cameras(options)?;
    let (motion, motion_file) = read_motion(options)?;
    let rig = bones::rig(&motion).map_err(|e| input(&motion_file, e))?;
    let mut report = ImportReport { images: images.len(), ..ImportReport::default() };
    let units = units_of(options, &motion, &motion_file, &mut report)?;
    let up = match options.up {
        Up::PlusY => DMat4::IDENTITY,
        // +Z up to +Y up: a quarter turn about X.
        Up::PlusZ => DMat4::from_rotation_x(-std::f64::consts::FRAC_PI_2),
    };
    report.assumed.push(format!("up: {} (--up; +y unless given)", if options.up == Up::PlusY { "+y" } else { "+z" }));
    let world = World { up, metres: units.metres() };
    let frame_of = frames_of_images(&images, &motion, &camera_file)?;
    let used: std::collections::BTreeSet<usize> = frame_of.iter().copied().collect();
    report.frames = used.len();
    report.assumed.push(format!("motion: {} of the clip's {} frames ({:.4} s apart) are seen by an image", used.len(), motion.frames.len(), motion.frame_time));
    let photos = photos::prepare(&images, options, &camera_file)?;
    report.assumed.extend(photos.assumed.iter().cloned());
    let (cameras, camera_of) = cameras(&images, &photos.intrinsics, &world);
    report.cameras = cameras.len();
    let frames: Vec<Value> = used.iter().map(|&k| frame_json(&motion, &rig, k, &world)).collect();
    let position = |k: usize| used.iter().position(|&u| u == k).unwrap_or(0);
    let (light_name, light) = light_json(options.light);
    report.assumed.push(format!("light: {light_name} ({}; the fit recovers it)", light["type"].as_str().unwrap_or("?")));
    // A folder of import's own beside `out` (never one that was there): the only one it removes.
    let temp = crate::files::create_folder_beside(out, "importing").map_err(|e| input(out, format!("{e} (nothing was written)")))?;
    let written = photos::write(&images, &photos, &camera_of, &temp, on);
    let result = written.and_then(|entries| {
        let plates: std::collections::BTreeSet<&String> = entries.iter().filter_map(|e| e.2.as_ref()).collect();
        report.assumed.push(format!(
            "plates: {} of {} cameras (from their frames' backgrounds): near the masks' edges there the fit decides the silhouette",
            plates.len(),
            report.cameras
        ));
        let image_entries: Vec<Value> = entries
            .into_iter()
            .enumerate()
            .map(|(i, (path, mask, plate))| {
                let mut entry =
                    json!({"camera": camera_of[i], "frame": position(frame_of[i]), "light": light_name, "split": images[i].split.name(), "path": path});
                if let Some(mask) = mask {
                    entry["mask"] = json!(mask);
                }
                if let Some(plate) = plate {
                    entry["plate"] = json!(plate);
                }
                entry
            })
            .collect();
        let bones: Vec<Value> = motion
            .joints
            .iter()
            .enumerate()
            .map(|(j, joint)| json!({"name": joint.name, "parent": joint.parent, "length": rig.lengths[j] * world.metres}))
            .collect();
        let name = out.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_else(|| "capture".into());
        let scene = json!({
            "format": "scene/1", "name": name, "generator": "umbra import", "capture": world.json(), "skeleton": {"bones": bones},
            "cameras": cameras, "frames": frames, "lights": {light_name: light}, "images": image_entries,
        });
        let text = serde_json::to_string_pretty(&scene).map_err(|e| input(out, e.to_string()))?;
        crate::imageio::write_atomic(&temp.join("scene.json"), text.as_bytes()).map_err(|e| input(&temp, e.to_string()))?;
        // What the scene reader refuses lies in the capture's values: named by the capture's
        // files, not by the temporary folder the user never saw.
        let scene = crate::scene::Scene::load(&temp).map_err(|e| {
            let said = e.to_string().replace(&temp.display().to_string(), "the converted scene");
            input(&camera_file, format!("with {}: {said} (nothing was written)", motion_file.display()))
        })?;
        agreement(&scene, &temp, &options.capture, &mut report)?;
        move_into_place(&temp, out)
    });
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&temp);
    }
    result.map(|_| report)
}

/// The finished scene in `temp` moved to `out`: renamed when `out` does not exist; moved entry
/// by entry into an existing empty `out` (the user's folder, perhaps their working folder, is
/// kept), `scene.json` last so that the folder is a scene only once it is whole.
fn move_into_place(temp: &Path, out: &Path) -> Result<(), ImportError> {
    let fail = |e: std::io::Error| input(out, format!("cannot move the imported scene into place: {e}"));
    if !out.exists() {
        return std::fs::rename(temp, out).map_err(fail);
    }
    let mut names: Vec<std::ffi::OsString> = std::fs::read_dir(temp).map_err(fail)?.filter_map(|e| e.ok().map(|e| e.file_name())).collect();
    names.sort_by_key(|n| n == "scene.json");
    for name in names {
        let target = out.join(&name);
        if std::fs::symlink_metadata(&target).is_ok() {
            return Err(input(&target, "appeared while the scene was imported: nothing more was moved"));
        }
        std::fs::rename(temp.join(&name), &target).map_err(fail)?;
    }
    std::fs::remove_dir(temp).map_err(fail)
}

/// The capture's motion: `--motion`, else its only .bvh, else its `joints.json`; a BVH, or
/// per-frame joint transforms as JSON (`joints`).
fn read_motion(options: &ImportOptions) -> Result<(bvh::Motion, PathBuf), ImportError> {
    let capture = &options.capture;
    let file = match &options.motion {
        Some(file) => file.clone(),
        None if capture.join("joints.json").is_file() && only_file(capture, "bvh", "motion").is_err() => capture.join("joints.json"),
        None => only_file(capture, "bvh", "motion")?,
    };
    Ok((read_clip(&file)?, file))
}

/// Reads a clip: a BVH, or per-frame joint transforms as JSON (`joints`) when its name ends
/// in `.json`.
pub fn read_clip(file: &Path) -> Result<bvh::Motion, ImportError> {
    let motion = match file.extension().is_some_and(|e| e.eq_ignore_ascii_case("json")) {
        true => joints::read(file)?,
        false => bvh::read(file)?,
    };
    match motion.problem() {
        Some(problem) => Err(input(file, format!("{problem} (nothing was written)"))),
        None => Ok(motion),
    }
}

/// The capture's units: `--units`, else inferred from the joints' span; said in `report`.
/// Refused when they make the body a size umbra does not fit (`check::size_problem`), saying
/// what the inference would take.
fn units_of(options: &ImportOptions, motion: &bvh::Motion, motion_file: &Path, report: &mut ImportReport) -> Result<Units, ImportError> {
    let extent = joint_extent(motion);
    let inferred = Units::for_extent(extent);
    let units = options.units.unwrap_or(inferred);
    if let Some(problem) = check::size_problem(extent * units.metres()) {
        let how = if options.units.is_some() { "--units" } else { "inferred" };
        let other = match options.units.filter(|&u| u != inferred) {
            Some(_) => format!("; in {} (what its size suggests) it is {:.2} m", inferred.name(), extent * inferred.metres()),
            None => String::new(),
        };
        return Err(input(
            motion_file,
            format!("the skeleton's joints span {} file units: in {} ({how}) {problem}{other} (nothing was written)", readable(extent), units.name()),
        ));
    }
    report.assumed.push(match options.units {
        Some(u) => format!("units: {} (--units)", u.name()),
        None => format!("units: {0} (inferred: the skeleton's joints span {extent:.3} file units, {1:.2} m in {0})", units.name(), extent * units.metres()),
    });
    Ok(units)
}

/// The capture check (`check`) of the scene written in `dir`: its contact sheet beside it
/// (`check.png`), its figure in the report; refused when the cameras and the motion disagree.
fn agreement(scene: &crate::scene::Scene, dir: &Path, capture: &Path, report: &mut ImportReport) -> Result<(), ImportError> {
    if let Some(problem) = check::orientation_problem(scene) {
        return Err(input(capture, format!("{problem}: check --up (+y unless given; a Z-up capture takes --up +z) (nothing was written)")));
    }
    let found = check::check(scene);
    check::contact_sheet(scene, &found).save_png(&dir.join("check.png")).map_err(|e| input(dir, e))?;
    let figure = format!("{:.0}% of the bones' points project inside the training masks", 100.0 * found.score);
    if found.score < check::REFUSE {
        return Err(input(
            capture,
            format!(
                "the cameras and the motion disagree: only {figure} (worst: {}); check --up, --units, the cameras' axes (nerfstudio's are OpenGL's) and the images' times (nothing was written)",
                found.worst_bones(3)
            ),
        ));
    }
    report.assumed.push(match found.score < check::WARN {
        true => format!("WARNING: capture check: only {figure} (worst: {}): look at check.png before fitting", found.worst_bones(3)),
        false => format!("capture check: {figure} (check.png)"),
    });
    report.score = found.score;
    Ok(())
}

/// The diagonal of the box of the clip's joints in its first frame (file units).
pub fn joint_extent(motion: &bvh::Motion) -> f64 {
    let joints = motion.joint_to_world(0);
    let points = joints.iter().map(|m| m.w_axis.truncate());
    let (lo, hi) = points.fold((DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)), |(lo, hi), p| (lo.min(p), hi.max(p)));
    (hi - lo).length()
}

/// Each image's frame of the clip: the frame nearest its `time`, within half a frame time; an
/// image without a time, the last number in its file name.
fn frames_of_images(images: &[CaptureImage], motion: &bvh::Motion, file: &Path) -> Result<Vec<usize>, ImportError> {
    images
        .iter()
        .map(|image| {
            let refuse = |message: String| input(file, format!("{}: {message}", image.json_path));
            let k = match image.time {
                Some(t) => {
                    let k = (t / motion.frame_time).round();
                    if k < 0.0 || (t - k * motion.frame_time).abs() > 0.5 * motion.frame_time + 1e-9 || k as usize >= motion.frames.len() {
                        return Err(refuse(format!(
                            "time {t} s has no frame of the clip within half a frame time (the clip spans 0 to {:.4} s)",
                            motion.time(motion.frames.len() - 1)
                        )));
                    }
                    k as usize
                }
                None => number_in_name(&image.path).ok_or_else(|| refuse("no time and no frame number in the file name".into()))?,
            };
            if k >= motion.frames.len() {
                return Err(refuse(format!("frame {k} is beyond the clip's {} frames", motion.frames.len())));
            }
            Ok(k)
        })
        .collect()
}

/// The last run of digits in a file's stem (`frame_00012.png`: 12).
pub fn number_in_name(path: &Path) -> Option<usize> {
    let stem = path.file_stem()?.to_string_lossy().into_owned();
    let digits: String = stem.chars().rev().skip_while(|c| !c.is_ascii_digit()).take_while(|c| c.is_ascii_digit()).collect();
    digits.chars().rev().collect::<String>().parse().ok()
}
