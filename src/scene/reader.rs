//! The scene reader: `scene.json`'s every field checked with its JSON path, each image named
//! checked for its file and size, and the images decoded in parallel.

use super::*;
use crate::imageio::{self, ImageError, Mask, RgbImage};
use crate::light::{EnvironmentMap, Light, UnknownLight};
use crate::silhouette::Plate;
use crate::skeleton::{Bone, Pose, Skeleton};
use json::At;
use rayon::prelude::*;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub(super) struct Reader<'a> {
    pub(super) root: &'a Path,
    pub(super) file: &'a Path,
    /// Told `(done, total)` as each image is decoded.
    pub(super) on_image: Option<&'a (dyn Fn(usize, usize) + Sync)>,
}

/// An image path to decode later, with the JSON path that named it.
pub(super) struct Pending {
    pub(super) scene_file: PathBuf,
    pub(super) json_path: String,
    pub(super) file: PathBuf,
    pub(super) relative: String,
}

impl Reader<'_> {
    pub(super) fn scene(&self, doc: &At) -> Result<Scene, SceneError> {
        let format = doc.field("format")?;
        let found = format.str()?;
        if found != FORMAT {
            return Err(format.error(format!("unsupported format {found:?}, expected {FORMAT:?}")));
        }
        let name = doc.opt_field("name")?.map(|n| n.str().map(str::to_string)).transpose()?;
        let capture = doc.opt_field("capture")?.map(|c| capture_world(&c)).transpose()?;
        let skeleton = self.skeleton(&doc.field("skeleton")?)?;
        let cameras = doc.field("cameras")?.non_empty_array()?.iter().map(|c| self.camera(c)).collect::<Result<Vec<_>, _>>()?;
        let frames = self.frames(&doc.field("frames")?, &skeleton)?;
        let lights = self.lights(&doc.field("lights")?)?;
        let views = self.views(&doc.field("images")?, &cameras, frames.len(), &lights)?;
        Ok(Scene { root: self.root.to_path_buf(), name, capture, skeleton, cameras, frames, lights, views, footprint: std::sync::OnceLock::new() })
    }

    pub(super) fn skeleton(&self, node: &At) -> Result<Skeleton, SceneError> {
        let items = node.field("bones")?.non_empty_array()?;
        let mut bones = Vec::with_capacity(items.len());
        let mut names = HashSet::new();
        for (i, item) in items.iter().enumerate() {
            let name_node = item.field("name")?;
            let name = name_node.str()?.to_string();
            if !names.insert(name.clone()) {
                return Err(name_node.error(format!("bone name {name:?} is used twice")));
            }
            // Required, null for a root: a bone that lost its parent would silently become a
            // second root.
            let has_parent_key = item.value.as_object().is_some_and(|o| o.contains_key("parent"));
            if !has_parent_key {
                return Err(SceneError {
                    file: self.file.to_path_buf(),
                    path: format!("{}.parent", item.path),
                    message: "missing required field (null for a root)".into(),
                });
            }
            let parent = match item.opt_field("parent")? {
                None => None,
                Some(p) => {
                    let v = p.i64()?;
                    if v < 0 || v as u64 >= i as u64 {
                        return Err(p.error(format!("parent must be null or the index of an earlier bone (< {i}), found {v}")));
                    }
                    Some(v as usize)
                }
            };
            let length = item.field("length")?.positive_f64()?;
            bones.push(Bone { name, parent, length });
        }
        Ok(Skeleton { bones })
    }

    pub(super) fn camera(&self, node: &At) -> Result<Camera, SceneError> {
        let name = node.opt_field("name")?.map(|n| n.str().map(str::to_string)).transpose()?.unwrap_or_default();
        let transform_node = node.field("camera_to_world")?;
        let camera_to_world = transform_node.mat4()?;
        let det = glam::DMat3::from_mat4(camera_to_world).determinant();
        if det.abs() < 1e-9 {
            return Err(transform_node.error("the rotation part is singular"));
        }
        Ok(Camera {
            name,
            width: node.field("width")?.positive_usize()?,
            height: node.field("height")?.positive_usize()?,
            fx: node.field("fx")?.positive_f64()?,
            fy: node.field("fy")?.positive_f64()?,
            cx: node.field("cx")?.f64()?,
            cy: node.field("cy")?.f64()?,
            camera_to_world,
        })
    }

    pub(super) fn frames(&self, node: &At, skeleton: &Skeleton) -> Result<Vec<Frame>, SceneError> {
        let mut seen = HashMap::new();
        let mut frames = Vec::new();
        for (position, item) in node.non_empty_array()?.iter().enumerate() {
            let index_node = item.field("index")?;
            let index = index_node.i64()?;
            if let Some(first) = seen.insert(index, position) {
                return Err(index_node.error(format!("frame index {index} is used twice (also frames[{first}])")));
            }
            let time = item.opt_field("time")?.map(|t| t.f64()).transpose()?;
            let transforms_node = item.field("bone_to_world")?;
            let transforms = transforms_node.array()?;
            if transforms.len() != skeleton.len() {
                return Err(transforms_node.error(format!("expected one matrix per bone ({}), found {}", skeleton.len(), transforms.len())));
            }
            let bone_to_world = transforms.iter().map(|m| m.rigid_mat4()).collect::<Result<Vec<_>, _>>()?;
            let mesh = match item.opt_field("mesh")? {
                None => None,
                Some(m) => {
                    let file = self.existing_file(&m)?;
                    crate::geometry::load_obj(&file).map_err(|e| m.error(format!("{}: {e}", m.str().unwrap_or_default())))?;
                    Some(file)
                }
            };
            frames.push(Frame { index, time, pose: Pose { bone_to_world }, mesh });
        }
        Ok(frames)
    }

    /// The file a path of the scene names: relative to the scene's folder and inside it (the
    /// format says so; `/etc/...` or `../..` would read a user's other files), and a readable
    /// regular file (a directory or a symlink loop is said to be one, not "not found").
    pub(super) fn existing_file(&self, node: &At) -> Result<PathBuf, SceneError> {
        let relative = node.str()?;
        let path = Path::new(relative);
        if path.is_absolute() || path.components().any(|c| !matches!(c, std::path::Component::Normal(_) | std::path::Component::CurDir)) {
            return Err(node.error(format!("{relative}: paths must be relative to the scene's folder and stay inside it")));
        }
        let file = self.root.join(relative);
        match std::fs::metadata(&file) {
            Ok(meta) if meta.is_file() => {
                // The text stays inside; a link must too, once resolved.
                let inside =
                    match (std::fs::canonicalize(&file), std::fs::canonicalize(if self.root.as_os_str().is_empty() { Path::new(".") } else { self.root })) {
                        (Ok(resolved), Ok(root)) => resolved.starts_with(root),
                        _ => false,
                    };
                if !inside {
                    return Err(node.error(format!("{relative} is a link that leads outside the scene's folder: copy the file into the scene instead")));
                }
                Ok(file)
            }
            Ok(meta) if meta.is_dir() => Err(node.error(format!("{relative} is a directory, not a file"))),
            Ok(_) => Err(node.error(format!("{relative} is not a regular file (a device, FIFO or socket)"))),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(node.error(format!("file not found: {relative}"))),
            Err(e) => Err(node.error(format!("{relative} cannot be read: {e}"))),
        }
    }

    pub(super) fn lights(&self, node: &At) -> Result<BTreeMap<String, Light>, SceneError> {
        let entries = node.entries()?;
        if entries.is_empty() {
            return Err(node.error("must hold at least one light"));
        }
        let mut lights = BTreeMap::new();
        for (name, item) in entries {
            lights.insert(name, self.light(&item)?);
        }
        Ok(lights)
    }

    /// A light whose direction or position the capture leaves out (or gives as null); its
    /// strength (`strength_key`) is then optional too.
    pub(super) fn unknown_light(&self, node: &At, kind: UnknownLight, strength_key: &str) -> Result<Light, SceneError> {
        let strength = node.opt_field(strength_key)?.map(|s| s.rgb()).transpose()?;
        let ambient = node.opt_field("ambient")?.map(|a| a.rgb()).transpose()?.unwrap_or(glam::DVec3::ZERO);
        Ok(Light::Unknown { kind, strength, ambient })
    }

    pub(super) fn light(&self, node: &At) -> Result<Light, SceneError> {
        let type_node = node.field("type")?;
        let ambient = |n: &At| -> Result<glam::DVec3, SceneError> { Ok(n.opt_field("ambient")?.map(|a| a.rgb()).transpose()?.unwrap_or(glam::DVec3::ZERO)) };
        match type_node.str()? {
            "directional" => {
                let Some(direction_node) = node.opt_field("direction")? else {
                    return self.unknown_light(node, UnknownLight::Sun, "irradiance");
                };
                let direction = direction_node.vec3()?;
                if direction.length() < 1e-12 {
                    return Err(direction_node.error("direction has zero length"));
                }
                Ok(Light::Directional { direction: direction.normalize(), irradiance: node.field("irradiance")?.rgb()?, ambient: ambient(node)? })
            }
            "uniform" => Ok(Light::Uniform { radiance: node.field("radiance")?.rgb()? }),
            "point" => match node.opt_field("position")? {
                Some(position) => Ok(Light::Point { position: position.vec3()?, intensity: node.field("intensity")?.rgb()?, ambient: ambient(node)? }),
                None => self.unknown_light(node, UnknownLight::Point, "intensity"),
            },
            "environment" => {
                let path_node = node.field("path")?;
                let file = self.existing_file(&path_node)?;
                let scale_node = node.opt_field("scale")?;
                let scale = match scale_node {
                    Some(s) => {
                        let v = s.f64()?;
                        if v < 0.0 {
                            return Err(s.error(format!("scale must be >= 0, found {v}")));
                        }
                        v
                    }
                    None => 1.0,
                };
                if !file.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr")) {
                    return Err(
                        path_node.error(format!("{}: an environment map is a linear EXR (.exr), not an 8-bit image", path_node.str().unwrap_or_default()))
                    );
                }
                let image = imageio::read_rgb(&file).map_err(|e| path_node.error(image_message(e, path_node.str().unwrap_or_default())))?;
                if let Some(message) = environment_problem(&image) {
                    return Err(path_node.error(message));
                }
                Ok(Light::Environment { path: file, scale, map: EnvironmentMap { image } })
            }
            other => Err(type_node.error(format!("unknown light type {other:?} (expected directional, uniform, environment or point)"))),
        }
    }

    pub(super) fn views(&self, node: &At, cameras: &[Camera], frame_count: usize, lights: &BTreeMap<String, Light>) -> Result<Vec<View>, SceneError> {
        struct Record {
            camera: usize,
            frame: usize,
            light: String,
            split: Split,
            colour: Pending,
            mask: Option<Pending>,
            albedo: Option<Pending>,
            plate: Option<Pending>,
        }
        let mut records = Vec::new();
        for item in node.non_empty_array()?.iter() {
            let camera = item.field("camera")?.index(cameras.len(), "cameras")?;
            let frame = item.field("frame")?.index(frame_count, "frames")?;
            let light_node = item.field("light")?;
            let light = light_node.str()?.to_string();
            if !lights.contains_key(&light) {
                let known: Vec<&str> = lights.keys().map(String::as_str).collect();
                return Err(light_node.error(format!("unknown light {light:?} (lights are {known:?})")));
            }
            let split_node = item.field("split")?;
            let split = match split_node.str()? {
                "train" => Split::Train,
                "val" => Split::Val,
                "test" => Split::Test,
                other => return Err(split_node.error(format!("unknown split {other:?} (expected train, val or test)"))),
            };
            let colour = self.pending(&item.field("path")?)?;
            let mask = match item.opt_field("mask")? {
                Some(m) => Some(self.pending(&m)?),
                None if split == Split::Train => {
                    return Err(SceneError {
                        file: self.file.to_path_buf(),
                        path: format!("{}.mask", item.path),
                        message: "missing: a mask is required for a training image".into(),
                    })
                }
                None => None,
            };
            let albedo = item.opt_field("albedo")?.map(|a| self.pending(&a)).transpose()?;
            let plate = item.opt_field("plate")?.map(|a| self.pending(&a)).transpose()?;
            if let (Some(plate), None) = (&plate, &mask) {
                return Err(pending_error(plate, "a plate needs the image's mask: it is used only near the mask's edge".into()));
            }
            records.push(Record { camera, frame, light, split, colour, mask, albedo, plate });
        }
        // An unknown light is recovered from its training images: one that lights none cannot
        // be rendered, so no image of another split may name it.
        let trains = |name: &str| records.iter().any(|r| r.split == Split::Train && r.light == name);
        if let Some((k, r)) = records.iter().enumerate().find(|(_, r)| !lights[&r.light].is_known() && !trains(&r.light)) {
            return Err(SceneError {
                file: self.file.to_path_buf(),
                path: format!("{}[{k}].light", node.path),
                message: format!(
                    "{:?} is an unknown light (no direction or position) that lights no training image: an unknown light is recovered by a fit, so it may light test images only of a capture whose training images it lights",
                    r.light
                ),
            });
        }
        let plates = self.plates(records.iter().filter_map(|r| r.plate.as_ref().map(|p| (p, &cameras[r.camera]))))?;
        // Decoding is the slow part of loading: do it in parallel, report the first failure in order.
        let (total, done) = (records.len(), std::sync::atomic::AtomicUsize::new(0));
        records
            .into_par_iter()
            .map(|r| {
                let plate = r.plate.as_ref().map(|p| plates[&p.file].clone());
                let (w, h) = (cameras[r.camera].width, cameras[r.camera].height);
                let colour = decode_photo(&r.colour, w, h)?;
                let mask = r.mask.as_ref().map(|m| decode_mask(m, w, h)).transpose()?;
                let albedo = r.albedo.as_ref().map(|a| decode_rgb(a, w, h)).transpose()?;
                if let Some(on) = self.on_image {
                    on(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1, total);
                }
                Ok(View { camera: r.camera, frame: r.frame, light: r.light, split: r.split, path: r.colour.file, colour, mask, albedo, plate })
            })
            .collect()
    }

    /// Each plate the images name, read once (images of one camera share it), in parallel.
    fn plates<'a>(&self, named: impl Iterator<Item = (&'a Pending, &'a Camera)>) -> Result<BTreeMap<PathBuf, Arc<Plate>>, SceneError> {
        let mut first: BTreeMap<PathBuf, (&Pending, &Camera)> = BTreeMap::new();
        for (p, camera) in named {
            let (w, h) = (camera.width, camera.height);
            match first.get(&p.file) {
                Some((_, c)) if (c.width, c.height) != (w, h) => {
                    return Err(pending_error(p, format!("{} is named by images of cameras of different sizes", p.relative)));
                }
                Some(_) => {}
                None => {
                    first.insert(p.file.clone(), (p, camera));
                }
            }
        }
        first.into_par_iter().map(|(file, (p, camera))| Ok((file, Arc::new(decode_plate(p, camera.width, camera.height)?)))).collect()
    }

    pub(super) fn pending(&self, node: &At) -> Result<Pending, SceneError> {
        let relative = node.str()?.to_string();
        let file = self.existing_file(node)?;
        Ok(Pending { scene_file: self.file.to_path_buf(), json_path: node.path.clone(), file, relative })
    }
}

pub(super) fn image_message(e: ImageError, relative: &str) -> String {
    match e {
        ImageError::NotFound(_) => format!("file not found: {relative}"),
        other => other.to_string(),
    }
}

pub(super) fn pending_error(p: &Pending, message: String) -> SceneError {
    SceneError { file: p.scene_file.clone(), path: p.json_path.clone(), message }
}

pub(super) fn check_size(p: &Pending, (w, h): (usize, usize), expected: (usize, usize)) -> Result<(), SceneError> {
    if (w, h) != expected {
        return Err(pending_error(p, format!("{} is {w}x{h}, but its camera is {}x{}", p.relative, expected.0, expected.1)));
    }
    Ok(())
}

/// The image's size from its header must be its camera's before anything is decoded.
pub(super) fn check_header(p: &Pending, expected: (usize, usize)) -> Result<(), SceneError> {
    let size = imageio::dimensions(&p.file).map_err(|e| pending_error(p, image_message(e, &p.relative)))?;
    check_size(p, size, expected)
}

pub(super) fn decode_rgb(p: &Pending, w: usize, h: usize) -> Result<RgbImage, SceneError> {
    check_header(p, (w, h))?;
    let image = imageio::read_rgb(&p.file).map_err(|e| pending_error(p, image_message(e, &p.relative)))?;
    check_size(p, (image.width, image.height), (w, h))?;
    if image.pixels.iter().any(|px| px.iter().any(|c| !c.is_finite())) {
        return Err(pending_error(p, format!("{} holds a non-finite value", p.relative)));
    }
    Ok(image)
}

/// A view's colour image, kept compact (`crate::photo::Photo`).
pub(super) fn decode_photo(p: &Pending, w: usize, h: usize) -> Result<crate::photo::Photo, SceneError> {
    check_header(p, (w, h))?;
    let photo = crate::photo::read_photo_compact(&p.file).map_err(|e| pending_error(p, image_message(e, &p.relative)))?;
    check_size(p, (photo.width(), photo.height()), (w, h))?;
    if let crate::photo::Photo::Linear(image) = &photo {
        if image.pixels.iter().any(|px| px.iter().any(|c| !c.is_finite())) {
            return Err(pending_error(p, format!("{} holds a non-finite value", p.relative)));
        }
    }
    Ok(photo)
}

/// A plate: an sRGB PNG whose alpha says where it is known (opaque), or an EXR known everywhere.
fn decode_plate(p: &Pending, w: usize, h: usize) -> Result<Plate, SceneError> {
    check_header(p, (w, h))?;
    let (colour, alpha) = crate::photo::read_photo(&p.file).map_err(|e| pending_error(p, image_message(e, &p.relative)))?;
    check_size(p, (colour.width, colour.height), (w, h))?;
    if colour.pixels.iter().any(|px| px.iter().any(|c| !c.is_finite())) {
        return Err(pending_error(p, format!("{} holds a non-finite value", p.relative)));
    }
    let known = alpha.unwrap_or_else(|| Mask { width: w, height: h, foreground: vec![true; w * h].into() });
    Ok(Plate { colour, known })
}

pub(super) fn decode_mask(p: &Pending, w: usize, h: usize) -> Result<Mask, SceneError> {
    check_header(p, (w, h))?;
    let mask = imageio::read_mask(&p.file).map_err(|e| pending_error(p, image_message(e, &p.relative)))?;
    check_size(p, (mask.width, mask.height), (w, h))?;
    Ok(mask)
}

/// `capture`: the capture's metres per unit and its world's rotation into scene/1's.
fn capture_world(node: &At) -> Result<super::CaptureWorld, SceneError> {
    let metres_per_unit = node.field("metres_per_unit")?.positive_f64()?;
    let turn = node.field("to_scene")?;
    let to_scene = turn.mat4()?;
    crate::skeleton::check_rigid(&to_scene, 1e-6).map_err(|e| turn.error(e))?;
    if to_scene.w_axis.truncate().length() > 1e-9 {
        return Err(turn.error("must be a rotation: its last column [0, 0, 0, 1]"));
    }
    Ok(super::CaptureWorld { metres_per_unit, to_scene })
}
