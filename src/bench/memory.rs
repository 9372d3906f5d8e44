//! Memory and time at real capture sizes: a scene's training images upscaled (nearest, the
//! intrinsics with them) to a small and a large size and repeated to a count of images, each
//! fitted for a few iterations in a process of its own; its peak resident memory (`fit.json`),
//! on a GPU backend the most its device's allocator held, and its wall time, the large size's
//! against the small one's, in one table.

use serde_json::{json, Value};
use std::path::{Path, PathBuf};

pub struct MemoryBenchOptions {
    pub scene: PathBuf,
    pub out: PathBuf,
    /// The training images each variant holds (the scene's, repeated).
    pub images: usize,
    /// The two image sizes (longest side, pixels): the baseline and the large one.
    pub sizes: (usize, usize),
    pub iterations: usize,
    /// The backend the fits run on.
    pub backend: crate::backend::Backend,
}

/// The command its folders' manifests name (`written`).
const COMMAND: &str = "bench memory";

/// One variant's measurement.
struct Measured {
    size: usize,
    images: usize,
    peak_bytes: u64,
    /// The device allocator's most (a GPU backend's).
    device_bytes: Option<u64>,
    seconds: f64,
}

/// `scene`'s training images at `factor` times their size, repeated to `images`, written as a
/// scene in `dir` (no test images: the fit is timed alone).
fn upscaled(scene_dir: &Path, dir: &Path, factor: usize, images: usize) -> Result<(), String> {
    let file = crate::scene::scene_file(scene_dir);
    let text = crate::files::read_text(&file, crate::files::SCENE_BYTES).map_err(|e| format!("{}: {e}", file.display()))?;
    let mut scene: Value = serde_json::from_str(&text).map_err(|e| format!("{}: {e}", file.display()))?;
    let root = file.parent().unwrap_or(Path::new("."));
    for camera in scene["cameras"].as_array_mut().ok_or("no cameras")? {
        for key in ["width", "height"] {
            camera[key] = json!(camera[key].as_u64().unwrap_or(0) as usize * factor);
        }
        for key in ["fx", "fy", "cx", "cy"] {
            camera[key] = json!(camera[key].as_f64().unwrap_or(0.0) * factor as f64);
        }
    }
    let training: Vec<Value> = scene["images"].as_array().ok_or("no images")?.iter().filter(|i| i["split"] == "train").cloned().collect();
    if training.is_empty() {
        return Err("the scene has no training images".into());
    }
    std::fs::create_dir_all(dir.join("images")).map_err(|e| e.to_string())?;
    std::fs::create_dir_all(dir.join("masks")).map_err(|e| e.to_string())?;
    let mut entries = Vec::new();
    for (k, image) in training.iter().enumerate() {
        let colour = crate::imageio::read_rgb(&root.join(image["path"].as_str().unwrap_or_default())).map_err(|e| e.to_string())?;
        let mask = crate::imageio::read_mask(&root.join(image["mask"].as_str().unwrap_or_default())).map_err(|e| e.to_string())?;
        let (w, h) = (colour.width * factor, colour.height * factor);
        let big = crate::imageio::RgbImage { width: w, height: h, pixels: (0..w * h).map(|p| colour.get(p % w / factor, p / w / factor)).collect() };
        let big_mask = crate::imageio::Mask {
            width: w,
            height: h,
            foreground: (0..w * h).map(|p| mask.foreground[(p / w / factor) * mask.width + p % w / factor]).collect(),
        };
        let (path, mask_path) = (format!("images/{k:04}.png"), format!("masks/{k:04}.png"));
        crate::imageio::write_atomic(&dir.join(&path), &crate::imageio::encode_png_rgb(&big).map_err(|e| e.to_string())?).map_err(|e| e.to_string())?;
        crate::imageio::write_atomic(&dir.join(&mask_path), &crate::imageio::encode_png_mask(&big_mask).map_err(|e| e.to_string())?)
            .map_err(|e| e.to_string())?;
        entries.push((image.clone(), path, mask_path));
    }
    // Repeated to the count asked: the same files named again (memory holds each image once per
    // entry, as it would distinct frames).
    let listed: Vec<Value> = (0..images)
        .map(|k| {
            let (image, path, mask) = &entries[k % entries.len()];
            let mut image = image.clone();
            image["path"] = json!(path);
            image["mask"] = json!(mask);
            image.as_object_mut().map(|o| o.remove("albedo"));
            image
        })
        .collect();
    // Only the training lights: the others (a sky's map) are not copied.
    let used: std::collections::BTreeSet<String> = listed.iter().filter_map(|i| i["light"].as_str().map(String::from)).collect();
    if let Some(lights) = scene["lights"].as_object_mut() {
        lights.retain(|name, _| used.contains(name));
    }
    scene["images"] = json!(listed);
    scene["name"] = json!(dir.file_name().map(|n| n.to_string_lossy().into_owned()));
    for frame in scene["frames"].as_array_mut().into_iter().flatten() {
        frame.as_object_mut().map(|o| o.remove("mesh"));
    }
    let text = serde_json::to_string(&scene).map_err(|e| e.to_string())?;
    crate::imageio::write_atomic(&dir.join("scene.json"), text.as_bytes()).map_err(|e| e.to_string())
}

/// Fits `scene` for `iterations` on `backend` in a child process; its peak memory, its device's
/// (a GPU backend's) and wall seconds.
fn measure(scene: &Path, run: &Path, iterations: usize, backend: crate::backend::Backend) -> Result<(u64, Option<u64>, f64), String> {
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    let start = std::time::Instant::now();
    let status = std::process::Command::new(exe)
        .args([
            "fit",
            &scene.display().to_string(),
            "--out",
            &run.display().to_string(),
            "--iterations",
            &iterations.to_string(),
            "--no-eval",
            "--force",
            "--backend",
            &backend.to_string(),
        ])
        .stdout(std::process::Stdio::null())
        .status()
        .map_err(|e| e.to_string())?;
    let seconds = start.elapsed().as_secs_f64();
    if !status.success() {
        return Err(format!("the fit of {} failed", scene.display()));
    }
    let report = crate::fit_report::FitReport::read(&run.join("fit.json")).map_err(|e| e.to_string())?;
    let peak = report.peak_memory_bytes.ok_or("fit.json: no peak_memory_bytes (this system does not report it)")?;
    Ok((peak, report.peak_device_memory_bytes, seconds))
}

/// Runs the benchmark; writes `memory.md` and `memory.csv` into `out`, returns the Markdown.
pub fn memory(options: &MemoryBenchOptions, mut on: impl FnMut(&str)) -> Result<String, String> {
    let scene = crate::scene::Scene::load(&options.scene).map_err(|e| e.to_string())?;
    let side = scene.cameras.iter().map(|c| c.width.max(c.height)).max().unwrap_or(1);
    let sizes: Vec<(usize, String)> = [options.sizes.0, options.sizes.1]
        .into_iter()
        .map(|size| {
            let factor = (size / side).max(1);
            (factor, format!("{}px-{}-images", side * factor, options.images))
        })
        .collect();
    // Each scene and run folder is this benchmark's own (new, or marked by an earlier run of it)
    // before anything is written: a folder of the user's under --out is neither removed nor
    // fitted over.
    let claim = |dir: PathBuf| crate::written::OutputFolder::claim(&dir, COMMAND, &[]);
    let mut folders = Vec::new();
    for (_, name) in &sizes {
        folders.push((claim(options.out.join(name))?, claim(options.out.join(format!("run-{name}")))?));
    }
    let mut measured = Vec::new();
    for ((factor, name), (scene_folder, run_folder)) in sizes.iter().zip(&folders) {
        on(&format!("writing {name}"));
        if scene_folder.dir().exists() {
            std::fs::remove_dir_all(scene_folder.dir()).map_err(|e| format!("{}: {e}", scene_folder.dir().display()))?;
        }
        upscaled(&options.scene, scene_folder.dir(), *factor, options.images)?;
        scene_folder.begin(&[]).map_err(|e| format!("{}: {e}", scene_folder.dir().display()))?;
        on(&format!("fitting {name} for {} iterations", options.iterations));
        let (peak_bytes, device_bytes, seconds) = measure(scene_folder.dir(), run_folder.dir(), options.iterations, options.backend)?;
        run_folder.begin(&[]).map_err(|e| format!("{}: {e}", run_folder.dir().display()))?;
        measured.push(Measured { size: side * factor, images: options.images, peak_bytes, device_bytes, seconds });
    }
    let base = &measured[0];
    let mib = |bytes: u64| bytes as f64 / (1 << 20) as f64;
    let device = measured.iter().any(|m| m.device_bytes.is_some());
    let mut md = format!(
        "# Memory at capture sizes\n\n{} training images of `{}` upscaled, {} iterations each on the {} backend, one process per size.\n\n| size | images | peak memory (MiB) | per training image (KiB) | wall (s) | memory / smallest | wall / smallest |{}\n|---|---|---|---|---|---|---|{}\n",
        options.images,
        options.scene.display(),
        options.iterations,
        options.backend,
        if device { " device memory (MiB) |" } else { "" },
        if device { "---|" } else { "" },
    );
    let mut rows = Vec::new();
    for m in &measured {
        let per_image = m.peak_bytes as f64 / m.images as f64;
        let (memory_ratio, time_ratio) = (m.peak_bytes as f64 / base.peak_bytes as f64, m.seconds / base.seconds);
        md += &format!(
            "| {0}x{0} | {1} | {2:.0} | {3:.0} | {4:.1} | {5:.2} | {6:.2} |{7}\n",
            m.size,
            m.images,
            mib(m.peak_bytes),
            per_image / 1024.0,
            m.seconds,
            memory_ratio,
            time_ratio,
            if device { format!(" {} |", m.device_bytes.map_or("-".to_string(), |b| format!("{:.0}", mib(b)))) } else { String::new() },
        );
        rows.push(vec![
            m.size.to_string(),
            m.images.to_string(),
            m.peak_bytes.to_string(),
            format!("{per_image:.0}"),
            format!("{:.3}", m.seconds),
            format!("{memory_ratio:.3}"),
            format!("{time_ratio:.3}"),
            m.device_bytes.map_or(String::new(), |b| b.to_string()),
        ]);
    }
    if let [small, large] = measured.as_slice() {
        let marginal = (large.peak_bytes as f64 - small.peak_bytes as f64) / large.images as f64;
        let pixels = (large.size * large.size) as f64 - (small.size * small.size) as f64;
        md += &format!(
            "\nMarginal memory per training image: {:.2} bytes per pixel ({:.2} MB per 1080p image).\n",
            marginal / pixels,
            marginal / pixels * 1920.0 * 1080.0 / 1e6
        );
    }
    std::fs::create_dir_all(&options.out).map_err(|e| e.to_string())?;
    crate::imageio::write_atomic(&options.out.join("memory.md"), md.as_bytes()).map_err(|e| e.to_string())?;
    let csv = crate::table::to_csv(&["size", "images", "peak_bytes", "bytes_per_image", "seconds", "memory_ratio", "time_ratio", "device_bytes"], &rows);
    crate::imageio::write_atomic(&options.out.join("memory.csv"), csv.as_bytes()).map_err(|e| e.to_string())?;
    Ok(md)
}
