//! Time against error (`umbra bench fit`): one scene fitted once per field kind with the same
//! schedule otherwise, the training paused at evenly spaced iterations to score the novel-pose
//! test images (foreground PSNR, SSIM), their albedo and the light direction; the curves of
//! training wall time against each, both kinds on the same axes. Scoring time is not counted.

use crate::backend::Backend;
use crate::eval::Lighting;
use crate::fit_error::FitError;
use crate::plot::{Chart, Series};
use crate::run::albedo_scale;
use crate::scene::{Scene, Split};
use crate::schedule::{FieldKind, Schedule};
use crate::scoring::{light_error, score_views, TestKinds};
use crate::train::Trainer;
use burn::module::Module;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A chart of the fit curves: its file, its y label and what it plots of each point.
type CurveChart = (&'static str, &'static str, fn(&CurvePoint) -> Option<f64>);

#[derive(Clone, Debug)]
pub struct FitBenchOptions {
    pub scene: PathBuf,
    pub schedule: PathBuf,
    pub out: PathBuf,
    pub kinds: Vec<FieldKind>,
    /// Scoring points per fit (the last at the final iteration).
    pub evaluations: usize,
    pub iterations: Option<usize>,
    pub seed: u64,
    /// After the fits, fit the grid again for as many iterations as fill the MLP's training
    /// time (its schedule stretched: `Schedule::stretched`): the two fields at equal cost.
    pub equal_time: bool,
}

/// One scoring point of one fit.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CurvePoint {
    /// Which fit: the field kind, and for the equal-time grid fit its iteration count.
    pub run: String,
    pub kind: FieldKind,
    pub iteration: usize,
    pub train_seconds: f64,
    pub novel_pose_psnr: f64,
    pub novel_pose_foreground_psnr: f64,
    pub novel_pose_ssim: f64,
    pub albedo_psnr: Option<f64>,
    pub albedo_foreground_psnr: Option<f64>,
    pub light_error_degrees: Option<f64>,
    pub peak_rss_mib: Option<f64>,
}

/// The process's peak resident memory so far (Linux), MiB.
pub(crate) fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse::<f64>().ok().map(|kb| kb / 1024.0)
}

fn kind_name(kind: FieldKind) -> &'static str {
    match kind {
        FieldKind::Mlp => "mlp",
        FieldKind::Grid => "grid",
    }
}

/// Scores the novel-pose test images (training light, training cameras, unseen frames).
fn score(trainer: &Trainer, run: &str, kind: FieldKind, iteration: usize, train_seconds: f64) -> Result<CurvePoint, FitError> {
    let scene = &trainer.scene;
    let kinds = TestKinds::new(scene);
    let views: Vec<&crate::scene::View> = scene.views_in(Split::Test).filter(|v| kinds.of(v).group == "novel pose").collect();
    if views.is_empty() {
        return Err(FitError::Input(format!("{}: no novel-pose test images to score", scene.root.join("scene.json").display())));
    }
    let model = trainer.fitted_model()?.valid();
    let device = trainer.device.clone().without_autodiff();
    let scale = albedo_scale(scene, &model);
    let scored: Vec<_> = views.iter().flat_map(|v| score_views(&model, scene, &[v], &[Lighting::Fitted(0)], scale, &device)).collect();
    let mean = |f: &dyn Fn(&crate::scoring::ScoredView) -> Option<f64>| {
        let values: Vec<f64> = scored.iter().filter_map(f).collect();
        (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
    };
    let light = trainer.model()?.light.report();
    Ok(CurvePoint {
        run: run.to_string(),
        kind,
        iteration,
        train_seconds,
        novel_pose_psnr: mean(&|s| Some(s.scores.psnr)).unwrap_or(f64::NAN),
        novel_pose_foreground_psnr: mean(&|s| Some(s.scores.foreground_psnr)).unwrap_or(f64::NAN),
        novel_pose_ssim: mean(&|s| Some(s.scores.ssim)).unwrap_or(f64::NAN),
        albedo_psnr: mean(&|s| s.albedo.as_ref().map(|a| a.1.psnr)),
        albedo_foreground_psnr: mean(&|s| s.albedo.as_ref().map(|a| a.1.foreground_psnr)),
        light_error_degrees: light_error(&trainer.scene, trainer.fit_light, 0, &light)["direction_degrees"].as_f64(),
        peak_rss_mib: peak_rss_mib(),
    })
}

/// Fits the scene once per kind, scoring along the way; writes `fit-curves.{csv,md}` and one
/// PNG per measure into `out`; returns the Markdown table.
pub fn fit_curves(options: &FitBenchOptions, mut on: impl FnMut(String)) -> Result<String, FitError> {
    let scene = Scene::load(&options.scene)?;
    let base = Schedule::load(&options.schedule)?;
    if options.kinds.is_empty() || options.evaluations == 0 {
        return Err(FitError::Input("bench fit needs at least one field kind and one evaluation".into()));
    }
    // Everything is checked before the output folder is made.
    let mut trainers = Vec::new();
    for &kind in &options.kinds {
        let mut schedule = base.clone();
        schedule.field.kind = kind;
        let trainer = Trainer::new(scene.clone(), schedule.clone(), Backend::Flex, options.seed)?;
        let iterations = options.iterations.unwrap_or_else(|| schedule.iterations_for(trainer.fit_light));
        trainers.push((kind, trainer, iterations));
    }
    std::fs::create_dir_all(&options.out).map_err(|e| crate::fit_error::io(&options.out, e))?;
    let mut points = Vec::new();
    let fits =
        trainers.into_iter().map(|(kind, trainer, iterations)| Curve::new(trainer, kind_name(kind).to_string(), iterations, options.evaluations)).collect();
    let seconds: Vec<(FieldKind, usize, f64)> = run_curves(fits, options, &mut points, &mut on)?;
    let time_of = |kind| seconds.iter().find(|(k, _, _)| *k == kind).map(|&(_, n, t)| (n, t));
    if let (true, Some((grid_iterations, grid_seconds)), Some((_, mlp_seconds))) = (options.equal_time, time_of(FieldKind::Grid), time_of(FieldKind::Mlp)) {
        let iterations = equal_time_iterations(&points, grid_iterations, grid_seconds, mlp_seconds);
        // The default schedule stretched to that length (as `schedules/detail.toml` is): the
        // field's rates fall over the same last share of the fit.
        let mut schedule = base.stretched(iterations);
        schedule.field.kind = FieldKind::Grid;
        let trainer = Trainer::new(scene.clone(), schedule, Backend::Flex, options.seed)?;
        let label = format!("grid at the MLP's time ({iterations} iterations)");
        on(format!("{label}: {grid_iterations} grid iterations took {grid_seconds:.1} s, the MLP {mlp_seconds:.1} s (stepped in turn)"));
        // It takes turns with the MLP's fit run again (the same seed, the same scores), so that
        // its time compares with an MLP time measured beside it, not minutes earlier.
        let mut mlp_schedule = base.clone();
        mlp_schedule.field.kind = FieldKind::Mlp;
        let mlp = Trainer::new(scene.clone(), mlp_schedule, Backend::Flex, options.seed)?;
        let mlp_iterations = options.iterations.unwrap_or_else(|| mlp.schedule.iterations_for(mlp.fit_light));
        let fits = vec![Curve::new(trainer, label, iterations, options.evaluations), Curve::new(mlp, MLP_AGAIN.to_string(), mlp_iterations, 1)];
        run_curves(fits, options, &mut points, &mut on)?;
    }
    write_outputs(&options.out, &options.scene, &points)
}

/// The MLP's fit run a second time, in turn with the equal-time grid fit, for its time.
const MLP_AGAIN: &str = "mlp again (in turn with the equal-time grid)";

/// How many iterations of the grid fill the MLP's training time. The stretched schedule adds
/// its iterations to the fit's last segment (light, RGB and the rates' decay), whose steps cost
/// more than the silhouette stage's: the extra iterations are costed at the rate between the
/// grid's last two scoring marks (the whole fit's mean rate, which overran the MLP's time by 1%,
/// without them).
fn equal_time_iterations(points: &[CurvePoint], grid_iterations: usize, grid_seconds: f64, mlp_seconds: f64) -> usize {
    let mut marks: Vec<(usize, f64)> = points.iter().filter(|p| p.run == kind_name(FieldKind::Grid)).map(|p| (p.iteration, p.train_seconds)).collect();
    marks.sort_by_key(|m| m.0);
    let late = match marks.as_slice() {
        [.., (i0, t0), (i1, t1)] if i1 > i0 && t1 > t0 => (t1 - t0) / (i1 - i0) as f64,
        _ => grid_seconds / grid_iterations.max(1) as f64,
    };
    let extra = ((mlp_seconds - grid_seconds) / late.max(1e-9)).floor().max(0.0) as usize;
    grid_iterations + extra
}

/// One fit of a benchmark: its trainer, name, length, scoring marks and training time so far.
struct Curve {
    trainer: Trainer,
    run: String,
    iterations: usize,
    marks: Vec<usize>,
    train_seconds: f64,
}

impl Curve {
    fn new(mut trainer: Trainer, run: String, iterations: usize, evaluations: usize) -> Self {
        trainer.schedule.iterations = iterations;
        let marks = (1..=evaluations).map(|k| (k * iterations).div_ceil(evaluations)).collect();
        Self { trainer, run, iterations, marks, train_seconds: 0.0 }
    }

    fn finished(&self) -> bool {
        self.trainer.iteration() >= self.iterations
    }

    /// One training step (timed); the scores if it ends at a mark.
    fn step(&mut self) -> Result<Option<CurvePoint>, FitError> {
        let step = Instant::now();
        self.trainer.iterate()?;
        self.train_seconds += step.elapsed().as_secs_f64();
        let iteration = self.trainer.iteration();
        if !self.marks.contains(&iteration) {
            return Ok(None);
        }
        score(&self.trainer, &self.run, self.trainer.schedule.field.kind, iteration, self.train_seconds).map(Some)
    }
}

/// How long a fit steps before the next one takes its turn: long enough that a turn's first
/// steps, whose memory the other fit's turn pushed out of the caches, do not weigh (a step of
/// each in turn slowed the grid's lookups, cache-bound, more than the MLP's matrix products:
/// 0.74x the MLP's time against 0.57x with the fits one after the other), short against the
/// machine's slow spells (tens of seconds).
const TURN_SECONDS: f64 = 2.0;

/// Trains the fits to their lengths in turns of about `TURN_SECONDS` each, scoring each at its
/// evenly spaced marks; returns each one's kind, length and training time. Taking turns, every
/// fit sees the machine as it is at that moment: a slow spell (this machine's timings vary 2x
/// from run to run) slows all of them alike, so their times compare as ratios, which fits run
/// one after the other did not (the MLP's 2,900 iterations once took 290 s in one run
/// and 344 s in the next, the grid's 240 s and 195 s).
fn run_curves(
    mut fits: Vec<Curve>,
    options: &FitBenchOptions,
    points: &mut Vec<CurvePoint>,
    on: &mut impl FnMut(String),
) -> Result<Vec<(FieldKind, usize, f64)>, FitError> {
    let started = Instant::now();
    let total: usize = fits.iter().map(|f| f.iterations).sum();
    let mut done = 0usize;
    while fits.iter().any(|f| !f.finished()) {
        for fit in fits.iter_mut().filter(|f| !f.finished()) {
            let turn = Instant::now();
            while !fit.finished() && turn.elapsed().as_secs_f64() < TURN_SECONDS {
                let scored = fit.step()?;
                done += 1;
                if let Some(point) = scored {
                    on(format!(
                        "{} iteration {}/{}: {:.1} s of training, novel pose foreground {:.2} dB, SSIM {:.4}, albedo {}, light {} (eta {:.0} s)",
                        fit.run,
                        point.iteration,
                        fit.iterations,
                        fit.train_seconds,
                        point.novel_pose_foreground_psnr,
                        point.novel_pose_ssim,
                        point.albedo_psnr.map(|v| format!("{v:.2} dB")).unwrap_or("-".into()),
                        point.light_error_degrees.map(|v| format!("{v:.2} deg")).unwrap_or("-".into()),
                        started.elapsed().as_secs_f64() / done.max(1) as f64 * total.saturating_sub(done) as f64,
                    ));
                    points.push(point);
                    write_outputs(&options.out, &options.scene, points)?;
                }
            }
        }
    }
    Ok(fits.iter().map(|f| (f.trainer.schedule.field.kind, f.iterations, f.train_seconds)).collect())
}

/// The grid against the MLP as issue 9 asks, from the curves: when (training time, linear
/// between scoring points) the grid first reaches the MLP's final foreground PSNR, as a
/// fraction of the MLP's time; and where each grid fit that ends within the MLP's time (its
/// own, and the equal-time one if there is one) ends against the MLP. `None` without both
/// fields.
pub fn grid_against_mlp(points: &[CurvePoint]) -> Option<String> {
    let last = |run: &dyn Fn(&str) -> bool, limit: f64| {
        points.iter().filter(|p| run(&p.run) && p.train_seconds <= limit).max_by(|a, b| a.train_seconds.total_cmp(&b.train_seconds))
    };
    let mlp = last(&|r| r == "mlp", f64::INFINITY)?;
    let grid: Vec<&CurvePoint> = points.iter().filter(|p| p.run == "grid").collect();
    grid.first()?;
    let target = mlp.novel_pose_foreground_psnr;
    let mut reached = None;
    let mut previous = (0.0, f64::NEG_INFINITY);
    for p in &grid {
        let (t, v) = (p.train_seconds, p.novel_pose_foreground_psnr);
        if v >= target {
            let along = if previous.1.is_finite() && v > previous.1 { (target - previous.1) / (v - previous.1) } else { 1.0 };
            reached = Some(previous.0 + (t - previous.0) * along.clamp(0.0, 1.0));
            break;
        }
        previous = (t, v);
    }
    let mut out = format!(
        "The MLP ends at {:.2} dB foreground PSNR{} after {:.1} s of training. ",
        target,
        mlp.albedo_psnr.map(|a| format!(" (albedo {a:.2} dB)")).unwrap_or_default(),
        mlp.train_seconds
    );
    out += &match reached {
        Some(t) => format!("The grid reaches it after {t:.1} s, {:.2}x the MLP's time. ", t / mlp.train_seconds.max(1e-9)),
        None => "The grid never reaches it. ".to_string(),
    };
    // The default grid fit if it ends within the MLP's time, and the one whose length fills it
    // (set by the two fits' times stepped in turn). That one is timed against the MLP's second
    // run, with which it took turns, when there is one: the first run's time, minutes earlier,
    // carries another spell of the machine.
    let within = mlp.train_seconds * 1.02;
    let mlp_again = last(&|r| r == MLP_AGAIN, f64::INFINITY);
    let ends: Vec<&CurvePoint> = [last(&|r| r == "grid", within), last(&|r| r.starts_with("grid at"), f64::INFINITY)].into_iter().flatten().collect();
    if ends.is_empty() {
        out += "No grid fit ends within the MLP's time.";
    }
    for (k, end) in ends.into_iter().enumerate() {
        let (beside, against) = match mlp_again {
            Some(again) if end.run != "grid" => (again.train_seconds, format!(" the MLP's time beside it ({:.1} s)", again.train_seconds)),
            _ => (mlp.train_seconds, " the MLP's time".to_string()),
        };
        out += &format!(
            "{}{} (iteration {}, {:.1} s, {:.2}x{against}) ends {:+.2} dB foreground PSNR{} against the MLP.",
            if k > 0 { " " } else { "" },
            if end.run == "grid" { "The grid's own fit".to_string() } else { format!("The {}", end.run) },
            end.iteration,
            end.train_seconds,
            end.train_seconds / beside.max(1e-9),
            end.novel_pose_foreground_psnr - target,
            match (end.albedo_psnr, mlp.albedo_psnr) {
                (Some(g), Some(m)) => format!(" and {:+.2} dB albedo PSNR", g - m),
                _ => String::new(),
            }
        );
    }
    Some(out)
}

fn write_outputs(out: &Path, scene: &Path, points: &[CurvePoint]) -> Result<String, FitError> {
    // Fits stepped in turn score in turn: the tables list each fit's points together, fits in
    // the order they first scored.
    let mut order: Vec<&str> = Vec::new();
    for p in points {
        if !order.contains(&p.run.as_str()) {
            order.push(&p.run);
        }
    }
    let mut sorted: Vec<CurvePoint> = points.to_vec();
    sorted.sort_by_key(|p| (order.iter().position(|r| *r == p.run), p.iteration));
    let points = &sorted[..];
    let f = |v: Option<f64>, digits: usize| v.map(|v| format!("{v:.digits$}")).unwrap_or_else(|| "-".into());
    let mut csv_rows = Vec::new();
    let mut md = format!(
        "## Time against error: {}\n\nTraining wall time (scoring excluded), novel-pose test images (sRGB 8-bit; foreground = mask or any rendered pixel).\n\n| fit | iteration | training time (s) | novel pose PSNR | foreground PSNR | SSIM | albedo PSNR | albedo foreground PSNR | light error (deg) | peak RSS (MiB) |\n|---|---|---|---|---|---|---|---|---|---|\n",
        scene.display()
    );
    for p in points {
        let cells = [
            p.run.clone(),
            p.iteration.to_string(),
            format!("{:.1}", p.train_seconds),
            format!("{:.2}", p.novel_pose_psnr),
            format!("{:.2}", p.novel_pose_foreground_psnr),
            format!("{:.4}", p.novel_pose_ssim),
            f(p.albedo_psnr, 2),
            f(p.albedo_foreground_psnr, 2),
            f(p.light_error_degrees, 2),
            f(p.peak_rss_mib, 0),
        ];
        md += &format!("| {} |\n", cells.join(" | "));
        csv_rows.push(cells.map(|c| if c == "-" { String::new() } else { c }));
    }
    let csv = crate::table::to_csv(
        &[
            "run",
            "iteration",
            "train_seconds",
            "novel_pose_psnr",
            "novel_pose_foreground_psnr",
            "novel_pose_ssim",
            "albedo_psnr",
            "albedo_foreground_psnr",
            "light_error_degrees",
            "peak_rss_mib",
        ],
        csv_rows,
    );
    let write = |name: &str, text: &str| crate::imageio::write_atomic(&out.join(name), text.as_bytes()).map_err(|e| crate::fit_error::io(&out.join(name), e));
    if let Some(summary) = grid_against_mlp(points) {
        md += &format!("\n{summary}\n");
    }
    write("fit-curves.csv", &csv)?;
    write("fit-curves.md", &md)?;
    let charts: [CurveChart; 3] = [
        ("fit-foreground-psnr.png", "novel pose foreground PSNR (dB)", |p| Some(p.novel_pose_foreground_psnr)),
        ("fit-albedo-psnr.png", "albedo PSNR (dB)", |p| p.albedo_psnr),
        ("fit-light-error.png", "light direction error (degrees)", |p| p.light_error_degrees),
    ];
    for (file, label, pick) in charts {
        let series: Vec<Series> = order
            .iter()
            .filter_map(|run| {
                let pts: Vec<(f64, f64)> =
                    points.iter().filter(|p| p.run == *run).filter_map(|p| pick(p).filter(|v| v.is_finite()).map(|v| (p.train_seconds, v))).collect();
                (!pts.is_empty()).then(|| Series { name: run.to_string(), points: pts, lines: true })
            })
            .collect();
        if series.is_empty() {
            continue;
        }
        let chart = Chart {
            title: format!("{label} against training time"),
            x_label: "training wall time (s)".into(),
            y_label: label.into(),
            log_x: false,
            log_y: false,
            series,
            marks: Vec::new(),
        };
        chart.render(800, 500).save_png(&out.join(file)).map_err(|e| crate::fit_error::io(&out.join(file), e))?;
    }
    Ok(md)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(run: &str, kind: FieldKind, iteration: usize, seconds: f64, foreground: f64, albedo: f64) -> CurvePoint {
        CurvePoint {
            run: run.into(),
            kind,
            iteration,
            train_seconds: seconds,
            novel_pose_psnr: foreground + 10.0,
            novel_pose_foreground_psnr: foreground,
            novel_pose_ssim: 0.9,
            albedo_psnr: Some(albedo),
            albedo_foreground_psnr: None,
            light_error_degrees: None,
            peak_rss_mib: None,
        }
    }

    #[test]
    fn the_equal_time_fit_costs_its_extra_iterations_at_the_last_segments_rate() {
        let points = vec![
            point("mlp", FieldKind::Mlp, 300, 300.0, 20.0, 27.0),
            point("grid", FieldKind::Grid, 100, 20.0, 18.0, 26.0),
            point("grid", FieldKind::Grid, 300, 80.0, 24.0, 30.0),
            point("grid", FieldKind::Grid, 200, 40.0, 22.0, 29.0),
        ];
        // The last marks cost 0.4 s an iteration (the mean 0.27): 220 s more is 550 iterations.
        assert_eq!(equal_time_iterations(&points, 300, 80.0, 300.0), 850);
        // With one mark, the whole fit's mean rate; never fewer than the grid's own.
        assert_eq!(equal_time_iterations(&points[..2], 100, 20.0, 300.0), 1500);
        assert_eq!(equal_time_iterations(&points, 300, 80.0, 50.0), 300);
    }

    #[test]
    fn the_summary_interpolates_where_the_grid_passes_the_mlp_and_compares_at_equal_time() {
        let mut points = vec![
            point("mlp", FieldKind::Mlp, 100, 100.0, 20.0, 27.0),
            point("mlp", FieldKind::Mlp, 200, 200.0, 22.0, 28.0),
            point("grid", FieldKind::Grid, 100, 30.0, 18.0, 26.0),
            point("grid", FieldKind::Grid, 200, 60.0, 24.0, 30.0),
        ];
        let text = grid_against_mlp(&points).unwrap();
        // 22 dB lies two thirds of the way from (30 s, 18 dB) to (60 s, 24 dB): 50 s.
        assert!(text.contains("after 50.0 s, 0.25x the MLP's time"), "{text}");
        assert!(text.contains("own fit (iteration 200, 60.0 s, 0.30x the MLP's time) ends +2.00 dB foreground PSNR and +2.00 dB albedo"), "{text}");
        points.push(point("grid at the MLP's time (600 iterations)", FieldKind::Grid, 600, 195.0, 26.0, 31.0));
        points.push(point("grid at the MLP's time (600 iterations)", FieldKind::Grid, 300, 97.0, 25.0, 30.5));
        let text = grid_against_mlp(&points).unwrap();
        assert!(text.contains("own fit (iteration 200, 60.0 s, 0.30x"), "{text}");
        assert!(text.contains("(600 iterations) (iteration 600, 195.0 s, 0.97x the MLP's time) ends +4.00 dB foreground PSNR and +3.00 dB albedo"), "{text}");
        // Timed against the MLP's second run beside it, when there is one.
        points.push(point(MLP_AGAIN, FieldKind::Mlp, 200, 250.0, 22.0, 28.0));
        let text = grid_against_mlp(&points).unwrap();
        assert!(text.contains("(iteration 600, 195.0 s, 0.78x the MLP's time beside it (250.0 s)) ends +4.00 dB"), "{text}");
        assert!(text.contains("The MLP ends at 22.00 dB foreground PSNR (albedo 28.00 dB) after 200.0 s"), "{text}");
        points.retain(|p| p.run != "grid");
        assert!(grid_against_mlp(&points).is_none(), "no grid curve, no summary");
    }
}
