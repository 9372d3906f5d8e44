//! `umbra bench scenes`: every shipped scene fitted once with the default schedule, one after
//! another, and one table of what each fit recovers (light error, foreground PSNR and SSIM of
//! its novel poses and views, albedo) and what it costs (wall time), written as `scenes.md` and
//! `scenes.csv`: the README's measured table made by one command.

use crate::train::{Backend, FitError, FitOptions};
use std::path::{Path, PathBuf};

/// What to fit.
pub struct ScenesBenchOptions {
    /// Scene folders; empty: every folder of `datasets-synthetic/` holding a `scene.json`, then
    /// `../shared/examples/quadruped-tiny` when it is there.
    pub scenes: Vec<PathBuf>,
    pub schedule: PathBuf,
    pub iterations: Option<usize>,
    pub seed: u64,
    /// Each fit goes to `out/NAME`; the tables to `out`.
    pub out: PathBuf,
}

/// The shipped scenes, in name order, and the independent example.
pub fn shipped_scenes() -> Vec<PathBuf> {
    let mut scenes: Vec<PathBuf> = std::fs::read_dir("datasets-synthetic")
        .map(|dir| dir.filter_map(|e| e.ok()).map(|e| e.path()).filter(|p| p.join("scene.json").is_file()).collect())
        .unwrap_or_default();
    scenes.sort();
    let example = PathBuf::from("../shared/examples/quadruped-tiny");
    if example.join("scene.json").is_file() {
        scenes.push(example);
    }
    scenes
}

/// Fits every scene and returns the Markdown table (also written with its CSV).
pub fn scenes(options: &ScenesBenchOptions, mut on: impl FnMut(String)) -> Result<String, FitError> {
    let scenes = if options.scenes.is_empty() { shipped_scenes() } else { options.scenes.clone() };
    if scenes.is_empty() {
        return Err(FitError::Input("bench scenes: no scene to fit (none named, and no datasets-synthetic/*/scene.json here)".into()));
    }
    std::fs::create_dir_all(&options.out).map_err(|e| crate::train::io(&options.out, e))?;
    let header = [
        "scene",
        "wall time (s)",
        "light error",
        "novel pose foreground PSNR (dB)",
        "novel pose SSIM",
        "novel view foreground PSNR (dB)",
        "albedo foreground PSNR (dB)",
    ];
    let mut md = format!("| {} |\n|{}\n", header.join(" | "), "---|".repeat(header.len()));
    let mut csv =
        "scene,wall_seconds,light_error,light_error_unit,novel_pose_foreground_psnr,novel_pose_ssim,novel_view_foreground_psnr,albedo_foreground_psnr\n"
            .to_string();
    let mut names: Vec<String> = Vec::new();
    for (k, scene) in scenes.iter().enumerate() {
        // Two scenes in folders of the same name get their own run folders.
        let mut name = scene_name(scene);
        if names.contains(&name) {
            name = format!("{name}-{}", k + 1);
        }
        names.push(name.clone());
        on(format!("bench scenes: {}/{}: fitting {name}", k + 1, scenes.len()));
        let fit = FitOptions {
            scene: scene.clone(),
            out: options.out.join(&name),
            schedule: options.schedule.clone(),
            iterations: options.iterations,
            seed: options.seed,
            resume: false,
            force: true,
            force_schedule: false,
            backend: Backend::Flex,
            evaluate: true,
        };
        let report = crate::fit::fit(&fit, |_| {})?;
        let row = Row::of(&name, &report);
        on(format!("bench scenes: {name}: {}", row.cells().join(", ")));
        md += &format!("| {} |\n", row.cells().join(" | "));
        csv += &row.csv();
    }
    let write = |file: &str, text: &str| {
        crate::imageio::write_atomic(&options.out.join(file), text.as_bytes()).map_err(|e| crate::train::io(&options.out.join(file), e))
    };
    write("scenes.md", &md)?;
    write("scenes.csv", &csv)?;
    Ok(md)
}

fn scene_name(scene: &Path) -> String {
    let folder = if scene.file_name().is_some_and(|n| n == "scene.json") { scene.parent().unwrap_or(scene) } else { scene };
    folder.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".into())
}

/// One fit's figures, read back from its `fit.json` report.
struct Row {
    name: String,
    wall: f64,
    /// The value and its unit ("degrees" for a sun, "m" for a point light's position).
    light: Option<(f64, &'static str)>,
    pose: Option<f64>,
    pose_ssim: Option<f64>,
    view: Option<f64>,
    albedo: Option<f64>,
}

impl Row {
    fn of(name: &str, report: &serde_json::Value) -> Self {
        let error = &report["light_error_against_scene"];
        let light = error["direction_degrees"].as_f64().map(|v| (v, "degrees")).or_else(|| error["position_metres"].as_f64().map(|v| (v, "m")));
        let e = &report["evaluation"];
        Self {
            name: name.to_string(),
            wall: report["wall_seconds"].as_f64().unwrap_or(f64::NAN),
            light,
            pose: e["novel_pose_foreground_psnr"].as_f64(),
            pose_ssim: e["novel_pose_ssim"].as_f64(),
            view: e["novel_view_foreground_psnr"].as_f64(),
            albedo: e["albedo_foreground_psnr"].as_f64(),
        }
    }

    fn cells(&self) -> Vec<String> {
        let f = |v: Option<f64>, digits: usize| v.map(|v| format!("{v:.digits$}")).unwrap_or_else(|| "-".into());
        let light = match self.light {
            Some((v, "m")) => format!("{:.1} cm", v * 100.0),
            Some((v, unit)) => format!("{v:.2} {unit}"),
            None => "(no light to fit)".into(),
        };
        vec![self.name.clone(), format!("{:.0}", self.wall), light, f(self.pose, 2), f(self.pose_ssim, 3), f(self.view, 2), f(self.albedo, 2)]
    }

    fn csv(&self) -> String {
        let f = |v: Option<f64>| v.map(|v| format!("{v:.4}")).unwrap_or_default();
        let (light, unit) = self.light.map(|(v, u)| (format!("{v:.4}"), u)).unwrap_or_default();
        format!("{},{:.1},{light},{unit},{},{},{},{}\n", self.name, self.wall, f(self.pose), f(self.pose_ssim), f(self.view), f(self.albedo))
    }
}
