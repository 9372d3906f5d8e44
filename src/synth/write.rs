//! Writing a planned scene: every image rendered and saved, scene.json, the meshes, all into a
//! temporary folder renamed into place; an existing scene replaced only when `synth` wrote it.

use super::*;

fn matrix_rows(m: &DMat4) -> Value {
    json!((0..4).map(|r| m.row(r).to_array().to_vec()).collect::<Vec<_>>())
}

fn light_json(light: &Light) -> Value {
    let v = |d: &DVec3| json!(d.to_array());
    match light {
        Light::Directional { direction, irradiance, ambient } => {
            json!({"type": "directional", "direction": v(direction), "irradiance": v(irradiance), "ambient": v(ambient)})
        }
        Light::Uniform { radiance } => json!({"type": "uniform", "radiance": v(radiance)}),
        Light::Environment { path, scale, .. } => {
            json!({"type": "environment", "path": path.to_string_lossy(), "scale": scale})
        }
        Light::Point { position, intensity, ambient } => {
            json!({"type": "point", "position": v(position), "intensity": v(intensity), "ambient": v(ambient)})
        }
        Light::Unknown { kind, strength, ambient } => {
            let (kind, key) = match kind {
                crate::light::UnknownLight::Sun => ("directional", "irradiance"),
                crate::light::UnknownLight::Point => ("point", "intensity"),
            };
            let mut light = json!({"type": kind, "ambient": v(ambient)});
            if let Some(s) = strength {
                light[key] = v(s);
            }
            light
        }
    }
}

/// What `generate` made.
pub struct Report {
    pub images: usize,
    pub bytes: u64,
}

/// Writes the whole scene into `out`, atomically: everything goes to a temp folder beside it
/// that is renamed into place at the end. An existing `out` is replaced only with `force`, and
/// only when it is a scene `umbra synth` wrote holding nothing but the files it lists
/// (`check_replaceable`): the generator never removes what it did not write.
pub fn generate(options: &SynthOptions, out: &Path, force: bool, mut progress: impl FnMut(usize, usize)) -> Result<Report, SynthError> {
    let plan = options.plan()?;
    let out = &check_replaceable(out, force)?;
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).map_err(|e| io_error(parent, e))?;
    // A folder of its own beside `out` (never one that was there), removed only by this run.
    let temp = crate::files::create_folder_beside(out, "synth").map_err(|e| io_error(out, e))?;
    // The scene is named after its folder (`datasets-synthetic/human-mono` is "human-mono").
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned());
    let result = write_scene(options, &plan, &temp, name, &mut progress);
    let result = match (result, options.export) {
        (Ok(report), Some(Export::Nerfstudio)) => export_capture(&temp, report, options),
        (result, _) => result,
    };
    match result {
        Ok(report) => {
            if out.exists() {
                // Checked again: the folder may have changed while the scene was rendered.
                check_replaceable(out, force)?;
                std::fs::remove_dir_all(out).map_err(|e| io_error(out, e))?;
            }
            std::fs::rename(&temp, out).map_err(|e| io_error(out, e))?;
            Ok(report)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&temp);
            Err(e)
        }
    }
}

/// The scene just written in `dir` replaced by its capture (`capture::export`), with the errors
/// `options` asks for.
fn export_capture(dir: &Path, report: Report, options: &SynthOptions) -> Result<Report, SynthError> {
    let scene = crate::scene::Scene::load(dir).map_err(|e| SynthError::Options(e.to_string()))?;
    let capture = crate::files::create_folder_beside(dir, "capture").map_err(|e| io_error(dir, e))?;
    let errors = options.errors.clone().unwrap_or_default();
    let written = crate::capture::export::write_capture(&scene, &capture, EXPORT_UNITS, &errors, options.seed).map_err(|e| SynthError::Options(e.to_string()));
    let images = match written {
        Ok(images) => images,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&capture);
            return Err(e);
        }
    };
    std::fs::remove_dir_all(dir).map_err(|e| io_error(dir, e))?;
    std::fs::rename(&capture, dir).map_err(|e| io_error(dir, e))?;
    Ok(Report { images, ..report })
}

/// The folders a scene of `umbra synth` holds its files in.
const SCENE_FOLDERS: [&str; 5] = ["images", "masks", "albedo", "lights", "meshes"];

/// `out` as the scene will be written to it (absolute, so `.` and `..` name real folders), once
/// it is known that writing there removes nothing the generator did not write: `out` does not
/// exist, is an empty folder, or (with `force`) is a scene `umbra synth` wrote that holds no file
/// its `scene.json` does not list. The working folder and its ancestors are never replaced.
fn check_replaceable(out: &Path, force: bool) -> Result<PathBuf, SynthError> {
    if out.as_os_str().is_empty() {
        return Err(SynthError::Options("--out: an empty path".into()));
    }
    let absolute = std::path::absolute(out).map_err(|e| io_error(out, e))?;
    let Ok(meta) = std::fs::symlink_metadata(&absolute) else { return Ok(absolute) };
    if meta.file_type().is_symlink() {
        return Err(io_error(out, "is a link: name the folder itself, or choose another --out (nothing was written)"));
    }
    if !meta.is_dir() {
        return Err(io_error(out, "exists and is not a folder: choose another --out (nothing was written)"));
    }
    let resolved = std::fs::canonicalize(&absolute).map_err(|e| io_error(out, e))?;
    if std::env::current_dir().is_ok_and(|cwd| cwd.starts_with(&resolved)) {
        return Err(io_error(out, "is the working folder or holds it: choose a new folder for --out (nothing was written)"));
    }
    let mut entries = std::fs::read_dir(&resolved).map_err(|e| io_error(out, e))?;
    if entries.next().is_none() {
        return Ok(resolved);
    }
    if !force {
        return Err(io_error(out, "already exists (pass --force to replace a scene umbra synth wrote; nothing was written)"));
    }
    let listed = synth_scene_files(&resolved).map_err(|why| {
        io_error(out, format!("{why}: --force replaces only a scene umbra synth wrote; remove it yourself or choose another --out (nothing was written)"))
    })?;
    if let Some(foreign) = unlisted_file(&resolved, Path::new(""), &listed) {
        return Err(io_error(
            &resolved.join(&foreign),
            "is not a file of the scene umbra synth wrote here: --force replaces only what it wrote; move it away or choose another --out (nothing was written)",
        ));
    }
    Ok(resolved)
}

/// The files (relative, `/`-separated) a scene written by `umbra synth` lists, or why `dir`
/// holds no such scene.
fn synth_scene_files(dir: &Path) -> Result<std::collections::BTreeSet<String>, String> {
    let path = dir.join("scene.json");
    if !path.exists() {
        return Err("is not a scene umbra synth wrote (it holds no scene.json)".into());
    }
    let text = crate::scene::read_capped(&path).map_err(|e| format!("is not a scene umbra synth wrote ({e})"))?;
    let scene: Value = serde_json::from_str(&text).map_err(|e| format!("is not a scene umbra synth wrote (its scene.json is not JSON: {e})"))?;
    if scene["generator"]["program"].as_str() != Some("umbra synth") {
        return Err("is not a scene umbra synth wrote (its scene.json names no generator \"umbra synth\")".into());
    }
    let mut files: std::collections::BTreeSet<String> = ["scene.json".to_string()].into();
    let strings = |values: Vec<&Value>| values.into_iter().filter_map(|v| v.as_str().map(String::from)).collect::<Vec<_>>();
    let images = scene["images"].as_array().map(|a| a.iter().flat_map(|i| [&i["path"], &i["mask"], &i["albedo"]]).collect()).unwrap_or_default();
    let meshes = scene["frames"].as_array().map(|a| a.iter().map(|f| &f["mesh"]).collect()).unwrap_or_default();
    let maps = scene["lights"].as_object().map(|m| m.values().map(|l| &l["path"]).collect()).unwrap_or_default();
    files.extend(strings(images));
    files.extend(strings(meshes));
    files.extend(strings(maps));
    Ok(files)
}

/// The first file or folder below `dir` (walked from `relative`) that is neither in `listed` nor
/// one of the scene's folders.
fn unlisted_file(dir: &Path, relative: &Path, listed: &std::collections::BTreeSet<String>) -> Option<PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir.join(relative)) else { return Some(relative.to_path_buf()) };
    for entry in entries {
        let Ok(entry) = entry else { return Some(relative.to_path_buf()) };
        let name = relative.join(entry.file_name());
        let key = name.to_string_lossy().replace('\\', "/");
        let is_folder = entry.file_type().is_ok_and(|t| t.is_dir());
        if is_folder && relative.as_os_str().is_empty() && SCENE_FOLDERS.contains(&key.as_str()) {
            if let Some(found) = unlisted_file(dir, &name, listed) {
                return Some(found);
            }
        } else if is_folder || !listed.contains(&key) {
            return Some(name);
        }
    }
    None
}

fn write_scene(options: &SynthOptions, plan: &Plan, dir: &Path, name: Option<String>, progress: &mut impl FnMut(usize, usize)) -> Result<Report, SynthError> {
    for sub in SCENE_FOLDERS {
        if sub == "meshes" && !options.meshes {
            continue;
        }
        let p = dir.join(sub);
        std::fs::create_dir_all(&p).map_err(|e| io_error(&p, e))?;
    }
    let mut bytes = 0u64;
    let mut write = |relative: &str, data: &[u8]| -> Result<(), SynthError> {
        let path = dir.join(relative);
        bytes += data.len() as u64;
        std::fs::write(&path, data).map_err(|e| io_error(&path, e))
    };
    let lights: std::collections::BTreeMap<&str, &Light> = plan.lights.iter().map(|(n, l)| (n.as_str(), l)).collect();
    for (_, light) in &plan.lights {
        if let Light::Environment { path, map, .. } = light {
            imageio::write_exr_atomic(&dir.join(path), &map.image).map_err(|e| io_error(path, e))?;
        }
    }
    let mut images = Vec::new();
    for (k, view) in plan.views.iter().enumerate() {
        progress(k, plan.views.len());
        let (_, _, pose) = &plan.frames[view.frame];
        let light = lights[view.light.as_str()];
        let r = render_view(&plan.character, pose, &plan.cameras[view.camera], light, options.samples, options.pixel_samples, options.seed, k as u64);
        let png = |e: imageio::ImageError| io_error(Path::new(&view.name), e);
        let path = format!("images/{}.png", view.name);
        let mask = format!("masks/{}.png", view.name);
        write(&path, &imageio::encode_png_rgb(&r.colour).map_err(png)?)?;
        write(&mask, &imageio::encode_png_mask(&r.mask).map_err(png)?)?;
        let mut entry = json!({"camera": view.camera, "frame": view.frame, "light": view.light, "split": view.split.name(), "path": path, "mask": mask});
        if view.split != Split::Train {
            let albedo = format!("albedo/{}.png", view.name);
            write(&albedo, &imageio::encode_png_rgb(&r.albedo).map_err(png)?)?;
            entry["albedo"] = json!(albedo);
        }
        images.push(entry);
    }
    progress(plan.views.len(), plan.views.len());
    let skeleton: Vec<Value> = plan.character.skeleton.bones.iter().map(|b| json!({"name": b.name, "parent": b.parent, "length": b.length})).collect();
    let cameras: Vec<Value> = plan
        .cameras
        .iter()
        .map(|c| json!({"name": c.name, "width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "camera_to_world": matrix_rows(&c.camera_to_world)}))
        .collect();
    let mut frames: Vec<Value> = Vec::new();
    for (index, time, pose) in &plan.frames {
        let mut frame = json!({"index": index, "time": time, "bone_to_world": pose.bone_to_world.iter().map(matrix_rows).collect::<Vec<_>>()});
        if options.meshes {
            let (vertices, triangles) = mesh::extract(&plan.character, pose, options.mesh_cell);
            let relative = format!("meshes/f{index:04}.obj");
            write(&relative, mesh::to_obj(&vertices, &triangles).as_bytes())?;
            frame["mesh"] = json!(relative);
        }
        frames.push(frame);
    }
    let lights_json: serde_json::Map<String, Value> = plan.lights.iter().map(|(n, l)| (n.clone(), light_json(l))).collect();
    let name = name.unwrap_or_else(|| {
        format!(
            "{}-{}",
            serde_json::to_value(options.character).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default(),
            serde_json::to_value(options.light).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default()
        )
    });
    let scene = json!({
        "format": crate::scene::FORMAT,
        "name": name,
        "generator": {"program": "umbra synth", "version": env!("CARGO_PKG_VERSION"), "options": options},
        "skeleton": {"bones": skeleton},
        "cameras": cameras,
        "frames": frames,
        "lights": lights_json,
        "images": images,
    });
    let text = serde_json::to_string_pretty(&scene).map_err(|e| io_error(Path::new("scene.json"), e))?;
    write("scene.json", text.as_bytes())?;
    Ok(Report { images: plan.views.len(), bytes })
}
