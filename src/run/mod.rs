//! The run folder: where a fit's checkpoint lives and how it is written (atomically, swapped
//! in whole) and read back (verified against the scene and schedule it came from), the model
//! restored from it for rendering, the losses it records, and the images written into it.
//! Below every command that reads a run (fit, eval, relight, report, export).

use crate::fit_error::{io, FitError};
use crate::messages::StepStats;
use std::path::Path;

mod checkpoint;
mod restore;

pub use checkpoint::*;
pub use restore::*;

pub const CHECKPOINT: &str = "checkpoint";

/// Where the previous checkpoint waits while a new one is swapped in.
pub(crate) const OLD_CHECKPOINT: &str = ".checkpoint.old";

/// The schedule a run was fitted with, copied into the run (rendering rebuilds the model
/// from it; the original file may have moved).
pub const SCHEDULE_COPY: &str = "schedule.toml";

/// What a run's report writes into the run folder.
pub const REPORT_FILES: [&str; 3] = ["report.html", "report.md", "report-relit.png"];

/// What a fit writes beside its checkpoint (besides the evaluation's folders and the report).
pub const FIT_FILES: [&str; 6] = ["fit.json", "gaussians.json", "losses.csv", "losses.png", REFINED_MOTION, REFINED_CAMERAS];

/// The training motion as a fit refined it (a BVH; a fit that refines no motion writes none).
pub const REFINED_MOTION: &str = "motion.bvh";

/// The training cameras as a fit refined them (nerfstudio's `transforms.json` format; a fit
/// that refines no cameras writes none).
pub const REFINED_CAMERAS: &str = "cameras.json";

/// The folders an evaluation renders into.
pub const RENDER_FOLDERS: [&str; 2] = ["renders", "renders-train"];

/// Removes from `dir` what an earlier evaluation wrote there (the images its `metrics.csv`
/// lists with their albedos, `compare.png`, `metrics.*`), and `dir` itself when that leaves it
/// empty: another scene's or an earlier fit's renders must not stand beside a new table. Any
/// other file, a user's, stays.
pub fn clear_renders(dir: &Path) -> Result<(), FitError> {
    let listed = crate::files::read_text(&dir.join("metrics.csv"), crate::files::STATE_BYTES)
        .ok()
        .and_then(|text| crate::table::read_csv(&text).ok())
        .map(|(_, rows)| rows.into_iter().filter_map(|row| row.into_iter().next()).collect::<Vec<String>>())
        .unwrap_or_default();
    // A render's name is one plain file name (`render_name`); anything else is not ours.
    let plain = |name: &String| !name.is_empty() && !name.starts_with('.') && !name.contains(['/', '\\']) && name.ends_with(".png");
    let renders = listed.iter().filter(|n| plain(n)).flat_map(|n| [n.clone(), n.replace(".png", "-albedo.png")]);
    let own = ["compare.png", "metrics.csv", "metrics.md", "metrics.json"].map(String::from);
    for name in renders.chain(own) {
        let path = dir.join(&name);
        if std::fs::symlink_metadata(&path).is_ok_and(|m| m.is_file()) {
            std::fs::remove_file(&path).map_err(|e| io(&path, e))?;
        }
    }
    let _ = std::fs::remove_dir(dir);
    Ok(())
}

/// Removes what an earlier fit's evaluation and report left in `run` (its renders, report,
/// and with `fit_outputs` also fit.json, gaussians.json and the losses), so that a fit that
/// replaces it or ends without evaluating leaves nothing that describes another fit.
pub fn clear_run_outputs(run: &Path, fit_outputs: bool) -> Result<(), FitError> {
    for folder in RENDER_FOLDERS {
        clear_renders(&run.join(folder))?;
    }
    let files = REPORT_FILES.iter().chain(if fit_outputs { FIT_FILES.iter() } else { [].iter() });
    for name in files {
        let path = run.join(name);
        if path.is_file() {
            std::fs::remove_file(&path).map_err(|e| io(&path, e))?;
        }
    }
    Ok(())
}

pub(crate) fn write_text(path: &Path, text: &str) -> Result<(), FitError> {
    crate::imageio::write_atomic(path, text.as_bytes()).map_err(|e| io(path, e))
}

/// The columns of `losses.csv` after the loss terms: the first training light's direction or
/// position (`StepStats::light`), empty when none is fitted.
const LIGHT_COLUMNS: [&str; 3] = ["light_x", "light_y", "light_z"];

pub(crate) fn losses_csv(history: &[(usize, StepStats)]) -> String {
    let header: Vec<&str> = ["iteration", "total", "seconds"].into_iter().chain(crate::losses::names()).chain(LIGHT_COLUMNS).collect();
    let rows = history.iter().map(|(it, s)| {
        let mut row = vec![it.to_string(), format!("{:.6e}", s.total), format!("{:.4}", s.seconds)];
        row.extend(crate::losses::names().map(|t| s.terms.get(t).map(|v| format!("{v:.6e}")).unwrap_or_default()));
        row.extend((0..3).map(|k| s.light.map(|v| format!("{:.7}", v[k])).unwrap_or_default()));
        row
    });
    crate::table::to_csv(&header, rows)
}

fn parse_losses_csv(text: &str) -> Vec<(usize, StepStats)> {
    let mut rows = Vec::new();
    let (header, table) = crate::table::read_csv(text).unwrap_or_default();
    // Columns by name: a run from before a term or the light's columns existed reads back
    // without them.
    let column = |name: &str| header.iter().position(|h| h == name);
    for line in &table {
        let cell = |k: Option<usize>| k.and_then(|k| line.get(k)).and_then(|c| c.parse::<f64>().ok());
        let (Some(it), Some(total), Some(seconds)) = (line.first().and_then(|c| c.parse().ok()), cell(Some(1)), cell(Some(2))) else {
            continue;
        };
        let terms = crate::losses::names().filter_map(|t| cell(column(t)).map(|v| (t.to_string(), v))).collect();
        let light_cell = |k: usize| cell(column(LIGHT_COLUMNS[k]));
        let light = match (light_cell(0), light_cell(1), light_cell(2)) {
            (Some(x), Some(y), Some(z)) => Some([x, y, z]),
            _ => None,
        };
        rows.push((it, StepStats { total, terms, seconds, phases: Vec::new(), phase_cpu: Vec::new(), cpu_seconds: None, light, device_memory_bytes: None }));
    }
    rows
}

pub fn save_png(path: &Path, image: &crate::imageio::RgbImage) -> Result<(), FitError> {
    let png = crate::imageio::encode_png_rgb(image).map_err(|e| io(path, e))?;
    crate::imageio::write_atomic(path, &png).map_err(|e| io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `losses.csv` reads back what it wrote, and reads its columns by name: a run from before
    /// the light's columns, or with its columns in another order, loses nothing it holds.
    #[test]
    fn losses_csv_reads_back_by_column_name() {
        let stats = |light| StepStats {
            total: 0.5,
            terms: [("rgb".to_string(), 0.25), ("eikonal".to_string(), 0.125)].into(),
            seconds: 0.75,
            phases: Vec::new(),
            phase_cpu: Vec::new(),
            cpu_seconds: None,
            light,
            device_memory_bytes: None,
        };
        let history = vec![(0, stats(None)), (10, stats(Some([0.0, 0.6, 0.8])))];
        let back = parse_losses_csv(&losses_csv(&history));
        assert_eq!(back.len(), 2);
        for ((it, s), (it_back, b)) in history.iter().zip(&back) {
            assert_eq!((it, s.total, &s.terms, s.seconds, s.light), (it_back, b.total, &b.terms, b.seconds, b.light));
        }
        let old = "iteration,total,seconds,eikonal,rgb\n7,1.5,0.25,0.5,0.125\n";
        let back = parse_losses_csv(old);
        assert_eq!(back[0].0, 7);
        assert_eq!(back[0].1.terms, [("eikonal".to_string(), 0.5), ("rgb".to_string(), 0.125)].into());
        assert_eq!(back[0].1.light, None);
    }
}
