//! `umbra bench scenes`: every shipped scene fitted with the default schedule, one after
//! another, and one table of what each fit recovers (light error, foreground PSNR and SSIM of
//! its novel poses and views, albedo) and what it costs (wall time), written as `scenes.md` and
//! `scenes.csv`: the README's results table made by one command. Fitted at several seeds, each
//! scene also gets its mean and standard deviation over them (`scenes-summary.csv`, and a
//! second table in `scenes.md`): one seed's figures vary by about half a dB, so two scenes are
//! compared by their means.

use crate::backend::Backend;
use crate::fit::FitOptions;
use crate::fit_error::FitError;
use std::path::{Path, PathBuf};

/// What to fit.
pub struct ScenesBenchOptions {
    /// Scene folders; empty: every folder of `datasets-synthetic/` holding a `scene.json`, then
    /// `../shared/examples/quadruped-tiny` when it is there.
    pub scenes: Vec<PathBuf>,
    pub schedule: PathBuf,
    pub iterations: Option<usize>,
    /// One fit of every scene per seed, in this order (at least one, none twice).
    pub seeds: Vec<u64>,
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

/// Fits every scene at every seed and returns the Markdown table(s) (also written with the CSV).
pub fn scenes(options: &ScenesBenchOptions, mut on: impl FnMut(String)) -> Result<String, FitError> {
    let scenes = if options.scenes.is_empty() { shipped_scenes() } else { options.scenes.clone() };
    if scenes.is_empty() {
        return Err(FitError::Input("bench scenes: no scene to fit (none named, and no datasets-synthetic/*/scene.json here)".into()));
    }
    if options.seeds.is_empty() {
        return Err(FitError::Input("bench scenes: no seed to fit with".into()));
    }
    if let Some(seed) = options.seeds.iter().enumerate().find_map(|(k, s)| options.seeds[..k].contains(s).then_some(s)) {
        return Err(FitError::Input(format!("bench scenes: seed {seed} is named twice: each seed is one fit of every scene")));
    }
    std::fs::create_dir_all(&options.out).map_err(|e| crate::fit_error::io(&options.out, e))?;
    let several = options.seeds.len() > 1;
    let mut md = table_head(["scene", "seed"]);
    let mut csv_rows: Vec<Vec<String>> = Vec::new();
    let mut names: Vec<String> = Vec::new();
    let mut rows: Vec<Row> = Vec::new();
    let fits = scenes.len() * options.seeds.len();
    for (k, scene) in scenes.iter().enumerate() {
        // Two scenes in folders of the same name get their own run folders.
        let mut name = scene_name(scene);
        if names.contains(&name) {
            name = format!("{name}-{}", k + 1);
        }
        names.push(name.clone());
        for (j, &seed) in options.seeds.iter().enumerate() {
            // One seed: the run is `OUT/NAME`, as before seeds; several: `OUT/NAME-seedS`.
            let run = if several { format!("{name}-seed{seed}") } else { name.clone() };
            on(format!("bench scenes: {}/{fits}: fitting {run}", k * options.seeds.len() + j + 1));
            let fit = FitOptions {
                scene: scene.clone(),
                out: options.out.join(&run),
                schedule: options.schedule.clone(),
                iterations: options.iterations,
                seed,
                resume: false,
                force: true,
                force_schedule: false,
                backend: Backend::Flex,
                evaluate: true,
            };
            let report = crate::fit::fit(&fit, |_| {})?;
            let row = Row::of(&name, seed, &report);
            on(format!("bench scenes: {run}: {}", row.cells().join(", ")));
            md += &format!("| {} |\n", row.cells().join(" | "));
            csv_rows.push(row.csv());
            rows.push(row);
        }
    }
    let write = |file: &str, text: &str| {
        crate::imageio::write_atomic(&options.out.join(file), text.as_bytes()).map_err(|e| crate::fit_error::io(&options.out.join(file), e))
    };
    if several {
        let (summary_md, summary_csv) = summary(&names, &rows);
        md = format!(
            "{md}\nMean +- standard deviation over seeds {}:\n\n{summary_md}",
            options.seeds.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", ")
        );
        write("scenes-summary.csv", &summary_csv)?;
    } else if options.out.join("scenes-summary.csv").is_file() {
        // A summary of an earlier run at several seeds would contradict this run's table.
        std::fs::remove_file(options.out.join("scenes-summary.csv")).map_err(|e| crate::fit_error::io(&options.out.join("scenes-summary.csv"), e))?;
    }
    let header = [
        "scene",
        "wall_seconds",
        "light_error",
        "light_error_unit",
        "novel_pose_foreground_psnr",
        "novel_pose_ssim",
        "novel_view_foreground_psnr",
        "albedo_foreground_psnr",
        "seed",
    ];
    write("scenes.md", &md)?;
    write("scenes.csv", &crate::table::to_csv(&header, csv_rows))?;
    Ok(md)
}

/// The figures both tables give after their first two columns.
const FIGURES: [&str; 6] =
    ["wall time (s)", "light error", "novel pose foreground PSNR (dB)", "novel pose SSIM", "novel view foreground PSNR (dB)", "albedo foreground PSNR (dB)"];

/// A Markdown table's head: the `first` two columns, then `FIGURES`.
fn table_head(first: [&str; 2]) -> String {
    let header: Vec<&str> = first.into_iter().chain(FIGURES).collect();
    format!("| {} |\n|{}\n", header.join(" | "), "---|".repeat(header.len()))
}

/// Each scene's mean and sample standard deviation over its fits, as a Markdown table and a CSV.
fn summary(names: &[String], rows: &[Row]) -> (String, String) {
    let mut md = table_head(["scene", "fits"]);
    let mut csv_rows: Vec<Vec<String>> = Vec::new();
    for name in names {
        let fits: Vec<&Row> = rows.iter().filter(|r| &r.name == name).collect();
        let stats = |value: &dyn Fn(&Row) -> Option<f64>| MeanSd::of(fits.iter().filter_map(|r| value(r)));
        let wall = stats(&|r| Some(r.wall));
        let light = stats(&|r| r.light.map(|(v, _)| v));
        let unit = fits.iter().find_map(|r| r.light.map(|(_, u)| u)).unwrap_or("");
        let columns = [stats(&|r| r.pose), stats(&|r| r.pose_ssim), stats(&|r| r.view), stats(&|r| r.albedo)];
        let light_cell = match light {
            None => "(no light to fit)".to_string(),
            Some(l) => {
                let ((mean, shown, digits), (sd, _, _)) = (in_shown_unit(l.mean, unit), in_shown_unit(l.sd, unit));
                format!("{mean:.digits$} +- {sd:.digits$} {shown}")
            }
        };
        let cell = |s: Option<MeanSd>, digits: usize| s.map(|s| format!("{:.digits$} +- {:.digits$}", s.mean, s.sd)).unwrap_or_else(|| "-".into());
        let digits = [2, 3, 2, 2];
        let mut cells = vec![name.clone(), fits.len().to_string(), cell(wall, 0), light_cell];
        cells.extend(columns.iter().zip(digits).map(|(s, d)| cell(*s, d)));
        md += &format!("| {} |\n", cells.join(" | "));
        let pair = |s: Option<MeanSd>| s.map(|s| [format!("{:.4}", s.mean), format!("{:.4}", s.sd)]).unwrap_or_default();
        let mut row = vec![name.clone(), fits.len().to_string()];
        row.extend(pair(wall));
        row.extend(pair(light));
        row.push(unit.to_string());
        columns.iter().for_each(|s| row.extend(pair(*s)));
        csv_rows.push(row);
    }
    let header = [
        "scene",
        "fits",
        "wall_seconds_mean",
        "wall_seconds_sd",
        "light_error_mean",
        "light_error_sd",
        "light_error_unit",
        "novel_pose_foreground_psnr_mean",
        "novel_pose_foreground_psnr_sd",
        "novel_pose_ssim_mean",
        "novel_pose_ssim_sd",
        "novel_view_foreground_psnr_mean",
        "novel_view_foreground_psnr_sd",
        "albedo_foreground_psnr_mean",
        "albedo_foreground_psnr_sd",
    ];
    (md, crate::table::to_csv(&header, csv_rows))
}

/// A light error as the tables show it: a position's metres in centimetres to 1 digit, a
/// direction's degrees to 2. Returns the value, its unit and its digits.
fn in_shown_unit(value: f64, unit: &'static str) -> (f64, &'static str, usize) {
    match unit {
        "m" => (value * 100.0, "cm", 1),
        _ => (value, unit, 2),
    }
}

/// The mean and sample standard deviation (n - 1; 0 for one value) of some values.
#[derive(Clone, Copy, Debug, PartialEq)]
struct MeanSd {
    mean: f64,
    sd: f64,
}

impl MeanSd {
    /// `None` when there is no value.
    fn of(values: impl Iterator<Item = f64>) -> Option<Self> {
        let values: Vec<f64> = values.collect();
        let n = values.len();
        if n == 0 {
            return None;
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let sd = if n > 1 { (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt() } else { 0.0 };
        Some(Self { mean, sd })
    }
}

fn scene_name(scene: &Path) -> String {
    let folder = if scene.file_name().is_some_and(|n| n == "scene.json") { scene.parent().unwrap_or(scene) } else { scene };
    folder.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".into())
}

/// One fit's figures, read back from its `fit.json` report.
struct Row {
    name: String,
    seed: u64,
    wall: f64,
    /// The value and its unit ("degrees" for a sun, "m" for a point light's position).
    light: Option<(f64, &'static str)>,
    pose: Option<f64>,
    pose_ssim: Option<f64>,
    view: Option<f64>,
    albedo: Option<f64>,
}

impl Row {
    fn of(name: &str, seed: u64, report: &crate::fit_report::FitReport) -> Self {
        let light = report.direction_error().map(|v| (v, "degrees")).or_else(|| report.position_error().map(|v| (v, "m")));
        let e = &report.evaluation;
        Self {
            name: name.to_string(),
            seed,
            wall: report.wall_seconds,
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
            Some((v, unit)) => {
                let (v, shown, digits) = in_shown_unit(v, unit);
                format!("{v:.digits$} {shown}")
            }
            None => "(no light to fit)".into(),
        };
        vec![
            self.name.clone(),
            self.seed.to_string(),
            format!("{:.0}", self.wall),
            light,
            f(self.pose, 2),
            f(self.pose_ssim, 3),
            f(self.view, 2),
            f(self.albedo, 2),
        ]
    }

    fn csv(&self) -> Vec<String> {
        let f = |v: Option<f64>| v.map(|v| format!("{v:.4}")).unwrap_or_default();
        let (light, unit) = self.light.map(|(v, u)| (format!("{v:.4}"), u)).unwrap_or_default();
        vec![
            self.name.clone(),
            format!("{:.1}", self.wall),
            light,
            unit.to_string(),
            f(self.pose),
            f(self.pose_ssim),
            f(self.view),
            f(self.albedo),
            self.seed.to_string(),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::MeanSd;

    #[test]
    fn mean_and_sample_standard_deviation() {
        let s = MeanSd::of([26.0, 27.0, 28.0].into_iter()).unwrap();
        assert!((s.mean - 27.0).abs() < 1e-12 && (s.sd - 1.0).abs() < 1e-12, "{s:?}");
        assert_eq!(MeanSd::of([5.0].into_iter()), Some(MeanSd { mean: 5.0, sd: 0.0 }));
        assert_eq!(MeanSd::of(std::iter::empty()), None);
    }
}
