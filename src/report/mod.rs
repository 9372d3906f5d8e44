//! A run's report for a person to judge the fit by: `RUN/report.html`, self-contained (every
//! image embedded, a few lines of plain JavaScript, nothing fetched), and `RUN/report.md`
//! beside it. Both give the recovered light against the scene's, the stage times, the losses'
//! plot, the metrics per group, and the renders beside the truth with their differences; the
//! HTML adds a relighting panel built on one view's visibility basis (`basis`): drag the sun
//! or pick one of the scene's environments and the avatar is relit at once in the browser,
//! by the same sums as `TransferBasis::relight` (the page checks itself against the image
//! Rust made for the training light and says whether they agree).

use crate::backend::Backend;
use crate::basis::TransferBasis;
use crate::fit_error::{io, FitError};
use crate::fit_report::FitReport;
use crate::light::Light;
use burn::module::Module;
use glam::DVec3;
use serde_json::Value;
use std::path::{Path, PathBuf};

mod panel;
use panel::{panel_json, PANEL_SCRIPT};

/// What `umbra report` writes about.
pub struct ReportOptions {
    pub run: PathBuf,
    pub scene: Option<PathBuf>,
    /// The view of the relighting panel.
    pub camera: usize,
    pub frame: usize,
    /// Directions of the panel's visibility basis: with 256 (cells 12.7 degrees across) the
    /// human-sun report, its panel 256 x 256 with the ground, is 8.4 MB.
    pub directions: usize,
    pub backend: Backend,
}

/// Default directions of the report's relighting panel.
pub const PANEL_DIRECTIONS: usize = 256;

/// Writes `report.html` and `report.md` into the run folder; returns their paths.
pub fn write_report(options: &ReportOptions) -> Result<(PathBuf, PathBuf), FitError> {
    let run = &options.run;
    let fit_json = run.join("fit.json");
    if !fit_json.is_file() {
        return Err(io(&fit_json, "missing (a report needs a finished fit)"));
    }
    let fit = FitReport::read(&fit_json)?;
    let restored = crate::run::restore(run, options.scene.as_deref(), options.backend)?;
    let scene = &restored.scene;
    if options.camera >= scene.cameras.len() {
        return Err(FitError::Input(format!("--camera {}: out of range, the scene has {}", options.camera, scene.cameras.len())));
    }
    if options.frame >= scene.frames.len() {
        return Err(FitError::Input(format!("--frame {}: out of range, the scene has {}", options.frame, scene.frames.len())));
    }
    if options.directions == 0 {
        return Err(FitError::Input("--directions must be at least 1".into()));
    }
    let _lock = crate::run_lock::RunLock::acquire(run, "report")?;
    let model = restored.fitted.model.valid();
    let device = restored.fitted.device.clone().without_autodiff();

    // The panel: one view's basis at PANEL_SIDE or more, the scene's training sun first.
    let panel_scene = panel_view(scene, options.camera);
    let scene = &panel_scene;
    let basis = TransferBasis::of_view(&model, scene, options.camera, options.frame, options.directions, &device);
    let camera = &scene.cameras[options.camera];
    let up = crate::relight::world_up(&scene.cameras);
    let training = scene.training_lights().first().and_then(|name| scene.lights.get(*name)).cloned();
    let (sun, irradiance, ambient) = match &training {
        Some(Light::Directional { direction, irradiance, ambient }) => (*direction, *irradiance, *ambient),
        // A capture's unstated sun: the panel starts from the fitted one.
        Some(Light::Unknown { kind: crate::light::UnknownLight::Sun, strength, ambient }) => match model.light.location() {
            Some(d) => (DVec3::from_array(d).normalize(), strength.unwrap_or(DVec3::ONE), *ambient),
            None => ((up + camera.camera_to_world.z_axis.truncate() * -0.5).normalize(), DVec3::ONE, DVec3::splat(0.25)),
        },
        _ => ((up + camera.camera_to_world.z_axis.truncate() * -0.5).normalize(), DVec3::ONE, DVec3::splat(0.25)),
    };
    let first = basis.relight(&Light::Directional { direction: sun, irradiance, ambient });
    let pose = &scene.frames[options.frame].pose;
    let (lo, hi) = pose.bounds(&scene.skeleton);
    let centre = (lo + hi) * 0.5;
    let turns = |light: &Light| -> Option<Vec<Vec<DVec3>>> {
        (0..360 / panel::SKY_TURN).map(|k| basis.sky_light(&crate::relight::adjusted(light, (k * panel::SKY_TURN) as f64, 1.0, centre))).collect()
    };
    let skies: Vec<(String, Vec<Vec<DVec3>>)> = scene.lights.iter().filter_map(|(name, light)| turns(light).map(|cells| (name.clone(), cells))).collect();
    let casters = model.light.shadow_casters_posed(&model.gaussians.to_set().pose(pose));
    let height = crate::relight::ground::lowest_point(&casters);
    let ground = panel::ground_basis(&basis.directions, camera, &casters, height, centre, scene.body_extent());
    let forward = camera.camera_to_world.z_axis.truncate();
    let panel = panel_json(&panel::Panel { basis: &basis, up, forward, sun, irradiance, ambient, skies, ground, first: &first });

    let relit_png = crate::imageio::encode_png_rgb(&first).map_err(|e| io(&run.join("report.html"), e))?;
    let relit_path = run.join("report-relit.png");
    crate::imageio::write_atomic(&relit_path, &relit_png).map_err(|e| io(&relit_path, e))?;
    let embed = |path: &Path| std::fs::read(path).ok().map(|bytes| format!("data:image/png;base64,{}", base64(&bytes)));
    let images = [
        ("Losses", embed(&run.join("losses.png")), "losses.png"),
        ("Renders beside the truth (truth, render, difference; albedo, its truth, difference)", embed(&run.join("renders/compare.png")), "renders/compare.png"),
    ];
    let summary = summary_rows(&fit, training.as_ref());
    let html = html_page(&scene.display_name(), &summary, &fit, &images, &panel);
    let md = markdown_page(&scene.display_name(), &summary, &fit, &images);
    let (html_path, md_path) = (run.join("report.html"), run.join("report.md"));
    crate::imageio::write_atomic(&html_path, html.as_bytes()).map_err(|e| io(&html_path, e))?;
    crate::imageio::write_atomic(&md_path, md.as_bytes()).map_err(|e| io(&md_path, e))?;
    Ok((html_path, md_path))
}

/// The scene with camera `camera` enlarged by a whole factor until its short side is at least
/// `panel::PANEL_SIDE` pixels.
fn panel_view(scene: &crate::scene::Scene, camera: usize) -> crate::scene::Scene {
    let _ = scene.footprint();
    let mut enlarged = scene.clone();
    let c = &scene.cameras[camera];
    let factor = panel::PANEL_SIDE.div_ceil(c.width.min(c.height).max(1)).max(1);
    enlarged.cameras[camera] = c.resized(c.width * factor, c.height * factor);
    enlarged
}

/// The fit's headline rows: (what, value), the recovered light beside the scene's `truth`.
fn summary_rows(fit: &FitReport, truth: Option<&Light>) -> Vec<(String, String)> {
    let vector = |v: &Value| -> String {
        let numbers: Vec<String> = v.as_array().into_iter().flatten().filter_map(|x| x.as_f64()).map(|x| format!("{x:.3}")).collect();
        format!("({})", numbers.join(", "))
    };
    let light = &fit.light;
    let recovered = ["direction", "position", "ambient"]
        .iter()
        .filter(|key| light.get(**key).is_some())
        .map(|key| format!("{key} {}", vector(&light[*key])))
        .collect::<Vec<_>>()
        .join(", ");
    let dvec = |v: &DVec3| format!("({:.3}, {:.3}, {:.3})", v.x, v.y, v.z);
    let truth = match truth {
        Some(Light::Directional { direction, ambient, .. }) => format!("sun: direction {}, ambient {}", dvec(direction), dvec(ambient)),
        Some(Light::Point { position, ambient, .. }) => format!("point light: position {}, ambient {}", dvec(position), dvec(ambient)),
        Some(other) => other.type_name().to_string(),
        None => "unknown".into(),
    };
    let mut rows = vec![
        ("scene".to_string(), fit.scene.clone()),
        ("iterations".into(), fit.iterations.to_string()),
        ("wall time".into(), format!("{:.1} s", fit.wall_seconds)),
    ];
    if let Some(bytes) = fit.peak_device_memory_bytes {
        rows.push(("device memory, at most".into(), format!("{:.0} MiB", bytes as f64 / (1u64 << 20) as f64)));
    }
    rows.extend([("recovered light".into(), format!("{}: {recovered}", light["type"].as_str().unwrap_or("?"))), ("the scene's training light".into(), truth)]);
    if let Some(error) = fit.direction_error() {
        rows.push(("light direction error against the scene's".into(), format!("{error:.2} degrees")));
    }
    if let Some(error) = fit.position_error() {
        rows.push(("light position error against the scene's".into(), format!("{error:.3} m")));
    }
    if let Some(line) = crate::fit_report::camera_colours_line(&fit.capture) {
        rows.push(("cameras' colours".into(), line.trim_start_matches("camera colours: ").to_string()));
    }
    if let Some(line) = crate::fit_report::cameras_line(&fit.capture) {
        rows.push(("training cameras".into(), line.trim_start_matches("cameras refined: ").to_string()));
    }
    if let Some(line) = crate::fit_report::motion_line(&fit.capture) {
        rows.push(("training motion".into(), line.trim_start_matches("motion refined: ").to_string()));
    }
    for stage in &fit.stages {
        let seconds = stage.seconds.map_or("-".to_string(), |s| format!("{s:.1} s"));
        let ran = if stage.ran { seconds } else { "skipped".into() };
        rows.push((format!("stage: {}", stage.name), ran));
    }
    rows
}

/// The evaluation's groups: (group, images, PSNR, foreground PSNR, SSIM, where the error lies:
/// its shares outside the mask / along the silhouette / inside, `metrics::ErrorRegions`).
fn group_rows(fit: &FitReport) -> Vec<[String; 6]> {
    let number = |v: &Value, digits: usize| v.as_f64().map_or("-".to_string(), |x| format!("{x:.digits$}"));
    fit.evaluation["groups"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|g| {
            [
                g["group"].as_str().unwrap_or("?").to_string(),
                g["images"].to_string(),
                number(&g["psnr"], 2),
                number(&g["foreground_psnr"], 2),
                number(&g["ssim"], 4),
                crate::metrics::ErrorRegions::from_json(&g["error_share"]).map_or("-".to_string(), |e| e.percentages().join(" / ")),
            ]
        })
        .collect()
}

const GROUP_HEADER: [&str; 6] = ["group", "images", "PSNR (dB)", "foreground PSNR (dB)", "SSIM", "error outside the mask / along the silhouette / inside"];

fn markdown_page(name: &str, summary: &[(String, String)], fit: &FitReport, images: &[(&str, Option<String>, &str)]) -> String {
    let mut md = format!("# Fit report: {name}\n\n| | |\n|---|---|\n");
    for (what, value) in summary {
        md += &format!("| {what} | {} |\n", value.replace('|', "\\|"));
    }
    let groups = group_rows(fit);
    if !groups.is_empty() {
        md += &format!("\n## Test images\n\n| {} |\n|---|---|---|---|---|---|\n", GROUP_HEADER.join(" | "));
        for row in groups {
            md += &format!("| {} |\n", row.join(" | "));
        }
    }
    for (title, data, file) in images {
        if data.is_some() {
            md += &format!("\n## {title}\n\n![{title}]({file})\n");
        }
    }
    md += "\n## Relit by the training light through the visibility basis\n\n![relit](report-relit.png)\n\nOpen report.html to relight it interactively.\n";
    md
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

fn html_page(name: &str, summary: &[(String, String)], fit: &FitReport, images: &[(&str, Option<String>, &str)], panel: &Value) -> String {
    let mut body = format!("<h1>Fit report: {}</h1>\n<table>\n", escape(name));
    for (what, value) in summary {
        body += &format!("<tr><th>{}</th><td>{}</td></tr>\n", escape(what), escape(value));
    }
    body += "</table>\n";
    let groups = group_rows(fit);
    if !groups.is_empty() {
        body += "<h2>Test images</h2>\n<table>\n<tr>";
        body += &GROUP_HEADER.iter().map(|h| format!("<th>{h}</th>")).collect::<String>();
        body += "</tr>\n";
        for row in groups {
            body += &format!("<tr>{}</tr>\n", row.iter().map(|c| format!("<td>{}</td>", escape(c))).collect::<String>());
        }
        body += "</table>\n";
    }
    for (title, data, _) in images {
        if let Some(data) = data {
            body += &format!("<h2>{}</h2>\n<img class=\"px\" src=\"{data}\" alt=\"{}\">\n", escape(title), escape(title));
        }
    }
    body += r#"<h2>Relight</h2>
<p>Drag on the image to move the sun (left-right: around, up-down: height), or pick a light; turn it about the up axis, scale it, and show the ground that receives the shadow.</p>
<div><select id="light"><option value="sun">sun</option></select>
azimuth <input id="azimuth" type="range" min="-180" max="180" step="1"> <output id="azimuth-value"></output>
elevation <input id="elevation" type="range" min="-10" max="90" step="1"> <output id="elevation-value"></output></div>
<div>turn <input id="turn" type="range" min="-180" max="180" value="0"> <output id="turn-value"></output>
intensity <input id="intensity" type="range" min="0" max="4" step="0.05" value="1"> <output id="intensity-value"></output>
<label><input id="ground" type="checkbox"> ground</label></div>
<canvas id="view" class="px"></canvas>
<pre id="check"></pre>
"#;
    format!(
        "<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>umbra: {}</title>\n<style>body{{font-family:sans-serif;max-width:70em;margin:2em auto}}table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:.2em .6em;text-align:left}}.px{{image-rendering:pixelated;width:min(100%,40em)}}canvas.px{{width:24em;cursor:crosshair}}</style>\n</head><body>\n{body}<script type=\"application/json\" id=\"basis\">{}</script>\n<script>\n{PANEL_SCRIPT}\n</script>\n</body></html>\n",
        escape(name),
        panel.to_string().replace("</", "<\\/")
    )
}

/// Standard base64 with padding (RFC 4648), for images and arrays embedded in the page.
pub fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [chunk[0], chunk.get(1).copied().unwrap_or(0), chunk.get(2).copied().unwrap_or(0)];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc_4648_test_vectors() {
        for (raw, encoded) in [("", ""), ("f", "Zg=="), ("fo", "Zm8="), ("foo", "Zm9v"), ("foob", "Zm9vYg=="), ("fooba", "Zm9vYmE="), ("foobar", "Zm9vYmFy")] {
            assert_eq!(base64(raw.as_bytes()), encoded);
        }
    }
}
