//! Ablations: one scene fitted with several schedules, each run in its own folder, compared in
//! one table (light error, PSNR per test group, time, final loss) and one plot of PSNR
//! against time. Every schedule is read and checked against the scene before the first run.
//!
//! Resumable and shareable: a run that finished with the same schedule, iteration count and
//! seed is reused, an interrupted one resumed, and one that another process is fitting (its
//! folder is locked, `run_lock`) left to it, so several invocations pointed at one folder
//! (on one machine, or on several sharing a disk) split the work; each writes the table of
//! every run finished so far.

use crate::backend::Backend;
use crate::fit::FitOptions;
use crate::fit_error::{io, FitError};
use crate::fit_report::FitReport;
use crate::messages::TrainMessage;
use crate::plot::{Chart, Series};
use crate::schedule::Schedule;
use std::path::{Path, PathBuf};

pub struct AblateOptions {
    pub scene: PathBuf,
    pub schedules: Vec<PathBuf>,
    pub out: PathBuf,
    pub iterations: Option<usize>,
    pub seed: u64,
    pub force: bool,
    pub backend: Backend,
}

/// One run's line in the comparison.
#[derive(Clone, Debug, serde::Serialize)]
pub struct AblationRow {
    pub schedule: String,
    pub iterations: u64,
    pub wall_seconds: f64,
    pub light_error_degrees: Option<f64>,
    pub light_error_metres: Option<f64>,
    pub novel_pose_psnr: Option<f64>,
    pub novel_pose_foreground_psnr: Option<f64>,
    pub novel_pose_ssim: Option<f64>,
    pub novel_view_psnr: Option<f64>,
    pub relit_psnr: Option<f64>,
    pub albedo_psnr: Option<f64>,
    pub albedo_foreground_psnr: Option<f64>,
    pub final_total: Option<f64>,
}

impl AblationRow {
    fn from_report(schedule: String, report: &FitReport) -> Self {
        let evaluation = &report.evaluation;
        Self {
            schedule,
            iterations: report.iterations as u64,
            wall_seconds: report.wall_seconds,
            light_error_degrees: report.direction_error(),
            light_error_metres: report.position_error(),
            novel_pose_psnr: evaluation["novel_pose_psnr"].as_f64(),
            novel_pose_foreground_psnr: evaluation["novel_pose_foreground_psnr"].as_f64(),
            novel_pose_ssim: evaluation["novel_pose_ssim"].as_f64(),
            novel_view_psnr: evaluation["novel_view_psnr"].as_f64(),
            relit_psnr: evaluation["relit_psnr"].as_f64(),
            albedo_psnr: evaluation["albedo_psnr"].as_f64(),
            albedo_foreground_psnr: evaluation["albedo_foreground_psnr"].as_f64(),
            final_total: Some(report.final_total),
        }
    }

    /// The cells after the schedule's name, `missing` where a run has no such figure.
    fn cells(&self, missing: &str) -> Vec<String> {
        let f = |v: Option<f64>, digits: usize| v.map(|v| format!("{v:.digits$}")).unwrap_or_else(|| missing.to_string());
        vec![
            self.iterations.to_string(),
            format!("{:.1}", self.wall_seconds),
            f(self.light_error_degrees, 2),
            f(self.light_error_metres, 3),
            f(self.novel_pose_psnr, 2),
            f(self.novel_pose_foreground_psnr, 2),
            f(self.novel_pose_ssim, 4),
            f(self.novel_view_psnr, 2),
            f(self.relit_psnr, 2),
            f(self.albedo_psnr, 2),
            f(self.albedo_foreground_psnr, 2),
            f(self.final_total, 5),
        ]
    }
}

const COLUMNS: [&str; 13] = [
    "schedule",
    "iterations",
    "wall time (s)",
    "light error (deg)",
    "light error (m)",
    "novel pose PSNR",
    "novel pose foreground PSNR",
    "novel pose SSIM",
    "novel view PSNR",
    "relit PSNR",
    "albedo PSNR",
    "albedo foreground PSNR",
    "final loss",
];

/// The name a schedule's run folder and table row get: its file stem.
fn run_name(schedule: &Path) -> String {
    schedule.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "schedule".into())
}

/// What an ablation found in a run's folder.
enum RunState {
    /// Nothing of a run yet (or `--force`): fit from the start.
    Fresh,
    /// A checkpoint of this schedule but no report: resume it.
    Interrupted,
    /// Finished with this schedule, iteration count and seed: its report.
    Finished(Box<FitReport>),
}

/// The state of the run in `folder` for `schedule_text`; an error when the folder holds a run
/// of another schedule, iteration count or seed (unless `force`, which starts afresh).
fn run_state(folder: &Path, schedule_text: &str, scene: &SceneIdentity<'_>, options: &AblateOptions, force: bool) -> Result<RunState, FitError> {
    let Some(checkpoint) = crate::run::existing_checkpoint(folder) else { return Ok(RunState::Fresh) };
    if force {
        return Ok(RunState::Fresh);
    }
    let read = |file: &Path| crate::files::read_text(file, crate::files::STATE_BYTES).ok().and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok());
    let state = read(&checkpoint.join("state.json")).unwrap_or_default();
    if !state["training_data"].as_str().is_some_and(|recorded| scene.is_recorded(recorded)) {
        return Err(io(folder, "holds a run fitted on other training data than this scene's: pass --force to replace it, or choose another --out"));
    }
    let copy = crate::files::read_text(&folder.join(crate::run::SCHEDULE_COPY), crate::files::SMALL_TEXT_BYTES).unwrap_or_default();
    if copy != schedule_text {
        return Err(io(folder, "holds a run of another schedule: pass --force to replace it, or choose another --out"));
    }
    let Ok(report) = FitReport::read(&folder.join("fit.json")) else {
        return Ok(RunState::Interrupted);
    };
    // Its evaluation was of the test images of the scene it names.
    if report.scene != scene.path {
        return Err(io(folder, format!("holds a run of the scene {:?}: pass --force to replace it, or choose another --out", report.scene)));
    }
    let same_seed = report.seed == options.seed;
    let same_length = options.iterations.is_none_or(|n| report.iterations == n);
    if !same_seed || !same_length {
        return Err(io(folder, "holds a run with another seed or iteration count: pass --force to replace it, or choose another --out"));
    }
    Ok(RunState::Finished(Box::new(report)))
}

/// What a run must have been fitted on to be reused: the scene's training data and its
/// folder (fit.json records it absolute).
struct SceneIdentity<'a> {
    training: String,
    /// For runs that recorded the first (unversioned) training identity.
    scene: &'a crate::scene::Scene,
    path: String,
}

impl SceneIdentity<'_> {
    /// Whether a run's recorded training identity is this scene's, in either version.
    fn is_recorded(&self, recorded: &str) -> bool {
        self.scene.is_training_identity(recorded, &self.training)
    }
}

/// Whether `out` holds anything but what ablations write: their tables and run folders.
fn foreign_entry(out: &Path) -> Option<std::path::PathBuf> {
    let entries = std::fs::read_dir(out).ok()?;
    entries.flatten().map(|e| e.path()).find(|path| {
        let table = path.file_name().is_some_and(|n| ["ablation.csv", "ablation.md", "ablation.png"].iter().any(|t| n == *t));
        let run = path.is_dir() && (crate::run::existing_checkpoint(path).is_some() || path.join("fit.json").is_file());
        let empty = path.is_dir() && std::fs::read_dir(path).is_ok_and(|mut e| e.next().is_none());
        !(table || run || empty)
    })
}

/// What one invocation of `ablate` did.
#[derive(Debug)]
pub struct AblationSummary {
    /// Every finished run's row, in the order of the schedules.
    pub rows: Vec<AblationRow>,
    /// Runs this invocation fitted (or resumed).
    pub fitted: usize,
    /// Runs left to the processes that hold their folders.
    pub elsewhere: Vec<String>,
}

/// Runs every schedule on the scene (`on` hears each run's messages with its index) and
/// writes `ablation.csv`, `ablation.md` and `ablation.png` into `options.out`.
pub fn ablate(options: &AblateOptions, mut on: impl FnMut(usize, &str, TrainMessage)) -> Result<AblationSummary, FitError> {
    if options.schedules.len() < 2 {
        return Err(FitError::Input("an ablation compares at least two schedules (--schedule A.toml --schedule B.toml)".into()));
    }
    if options.out.exists() && !options.out.is_dir() {
        return Err(io(&options.out, "exists and is not a folder: --out names the ablation's folder (nothing was written)"));
    }
    let scene = crate::scene::Scene::load(&options.scene)?;
    if !options.force {
        if let Some(foreign) = foreign_entry(&options.out) {
            return Err(io(
                &options.out,
                format!("holds {}, which is neither an ablation's table nor a run: pass --force to write into it anyway, or choose another --out (nothing was written)", foreign.display()),
            ));
        }
    }
    let identity = SceneIdentity {
        training: scene.training_identity(),
        scene: &scene,
        path: std::fs::canonicalize(&options.scene).unwrap_or_else(|_| options.scene.clone()).display().to_string(),
    };
    let light = scene.training_lights().first().map(|name| scene.lights[*name].casts_shadows()).unwrap_or(false);
    let mut names: Vec<String> = Vec::new();
    let mut texts: Vec<String> = Vec::new();
    for path in &options.schedules {
        let (schedule, text) = Schedule::read(path)?;
        schedule.check_against(light)?;
        let name = run_name(path);
        if names.contains(&name) {
            return Err(FitError::Input(format!("{}: another schedule is also named {name:?}; runs are kept by file name", path.display())));
        }
        run_state(&options.out.join(&name), &text, &identity, options, options.force)?;
        names.push(name);
        texts.push(text);
    }
    std::fs::create_dir_all(&options.out).map_err(|e| io(&options.out, e))?;
    let mut summary = AblationSummary { rows: Vec::new(), fitted: 0, elsewhere: Vec::new() };
    for (k, (path, name)) in options.schedules.iter().zip(&names).enumerate() {
        let folder = options.out.join(name);
        let resume = match run_state(&folder, &texts[k], &identity, options, options.force)? {
            RunState::Finished(_) => continue,
            RunState::Interrupted => true,
            RunState::Fresh => false,
        };
        let fit = FitOptions {
            scene: options.scene.clone(),
            out: folder.clone(),
            schedule: path.clone(),
            iterations: options.iterations,
            seed: options.seed,
            resume,
            force: !resume,
            force_schedule: false,
            backend: options.backend,
            evaluate: true,
        };
        match crate::fit::fit(&fit, |message| on(k, name, message)) {
            Ok(_) => summary.fitted += 1,
            // Another invocation holds this run: it will finish it.
            Err(_) if crate::run_lock::held_elsewhere(&folder) => {
                summary.elsewhere.push(name.clone());
                continue;
            }
            Err(e) => return Err(e),
        }
        // After every run, so a stopped ablation keeps its rows.
        summary.rows = finished_rows(options, &identity, &names, &texts);
        write_tables(&options.out, &summary.rows)?;
    }
    summary.rows = finished_rows(options, &identity, &names, &texts);
    write_tables(&options.out, &summary.rows)?;
    Ok(summary)
}

/// The rows of every run in `options.out` that has finished with its schedule.
fn finished_rows(options: &AblateOptions, scene: &SceneIdentity<'_>, names: &[String], texts: &[String]) -> Vec<AblationRow> {
    names
        .iter()
        .zip(texts)
        .filter_map(|(name, text)| match run_state(&options.out.join(name), text, scene, options, false) {
            Ok(RunState::Finished(report)) => Some(AblationRow::from_report(name.clone(), &report)),
            _ => None,
        })
        .collect()
}

fn write_tables(out: &Path, rows: &[AblationRow]) -> Result<(), FitError> {
    let csv = crate::table::to_csv(&COLUMNS, rows.iter().map(|row| std::iter::once(row.schedule.clone()).chain(row.cells("")).collect::<Vec<_>>()));
    let mut md = format!("## Ablation\n\n| {} |\n|{}\n", COLUMNS.join(" | "), "---|".repeat(COLUMNS.len()));
    for row in rows {
        md += &format!("| {} | {} |\n", row.schedule, row.cells("-").join(" | "));
    }
    md += "\nPSNR in dB over whole test images, sRGB 8-bit; light error against the light the scene states.\n";
    for (name, text) in [("ablation.csv", &csv), ("ablation.md", &md)] {
        crate::imageio::write_atomic(&out.join(name), text.as_bytes()).map_err(|e| io(&out.join(name), e))?;
    }
    let series =
        rows.iter().filter_map(|r| r.novel_pose_psnr.map(|p| Series { name: r.schedule.clone(), points: vec![(r.wall_seconds, p)], lines: false })).collect();
    let chart = Chart {
        title: "ablation: novel-pose PSNR vs wall time".into(),
        x_label: "wall time s".into(),
        y_label: "PSNR dB".into(),
        log_x: false,
        log_y: false,
        series,
        marks: Vec::new(),
    };
    chart.render(720, 480).save_png(&out.join("ablation.png")).map_err(|e| io(&out.join("ablation.png"), e))
}
