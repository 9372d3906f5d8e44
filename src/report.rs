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
use crate::imageio::{linear_to_srgb8, RgbImage};
use crate::light::Light;
use burn::module::Module;
use glam::DVec3;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// What `umbra report` writes about.
pub struct ReportOptions {
    pub run: PathBuf,
    pub scene: Option<PathBuf>,
    /// The view of the relighting panel.
    pub camera: usize,
    pub frame: usize,
    /// Directions of the panel's visibility basis: 256 (cells 12.7 degrees across) keeps the
    /// page near 1 MB at 128 x 128.
    pub directions: usize,
    pub backend: Backend,
}

/// Default directions of the report's relighting panel.
pub const PANEL_DIRECTIONS: usize = 256;

/// Writes `report.html` and `report.md` into the run folder; returns their paths.
pub fn write_report(options: &ReportOptions) -> Result<(PathBuf, PathBuf), FitError> {
    let run = &options.run;
    let fit_json = run.join("fit.json");
    let text = std::fs::read_to_string(&fit_json).map_err(|e| io(&fit_json, format!("{e} (a report needs a finished fit)")))?;
    let fit: Value = serde_json::from_str(&text).map_err(|e| io(&fit_json, e))?;
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

    // The panel: one view's basis, the scene's training sun as the first light.
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
    let skies: Vec<(String, Vec<DVec3>)> = scene.lights.iter().filter_map(|(name, light)| basis.sky_light(light).map(|cells| (name.clone(), cells))).collect();
    let panel = panel_json(&basis, up, camera.camera_to_world.z_axis.truncate(), sun, irradiance, ambient, &skies, &first);

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

/// The fit's headline rows: (what, value), the recovered light beside the scene's `truth`.
fn summary_rows(fit: &Value, truth: Option<&Light>) -> Vec<(String, String)> {
    let vector = |v: &Value| -> String {
        let numbers: Vec<String> = v.as_array().into_iter().flatten().filter_map(|x| x.as_f64()).map(|x| format!("{x:.3}")).collect();
        format!("({})", numbers.join(", "))
    };
    let light = &fit["light"];
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
        ("scene".to_string(), fit["scene"].as_str().unwrap_or("?").to_string()),
        ("iterations".into(), fit["iterations"].to_string()),
        ("wall time".into(), format!("{:.1} s", fit["wall_seconds"].as_f64().unwrap_or(f64::NAN))),
        ("recovered light".into(), format!("{}: {recovered}", light["type"].as_str().unwrap_or("?"))),
        ("the scene's training light".into(), truth),
    ];
    if let Some(error) = fit["light_error_against_scene"]["direction_degrees"].as_f64() {
        rows.push(("light direction error against the scene's".into(), format!("{error:.2} degrees")));
    }
    if let Some(error) = fit["light_error_against_scene"]["position_metres"].as_f64() {
        rows.push(("light position error against the scene's".into(), format!("{error:.3} m")));
    }
    for stage in fit["stages"].as_array().into_iter().flatten() {
        let seconds = stage["seconds"].as_f64().map_or("-".to_string(), |s| format!("{s:.1} s"));
        let ran = if stage["ran"].as_bool().unwrap_or(false) { seconds } else { "skipped".into() };
        rows.push((format!("stage: {}", stage["name"].as_str().unwrap_or("?")), ran));
    }
    rows
}

/// The evaluation's groups: (group, images, PSNR, foreground PSNR, SSIM, where the error lies:
/// its shares outside the mask / along the silhouette / inside, `metrics::ErrorRegions`).
fn group_rows(fit: &Value) -> Vec<[String; 6]> {
    let number = |v: &Value, digits: usize| v.as_f64().map_or("-".to_string(), |x| format!("{x:.digits$}"));
    fit["evaluation"]["groups"]
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

fn markdown_page(name: &str, summary: &[(String, String)], fit: &Value, images: &[(&str, Option<String>, &str)]) -> String {
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

fn html_page(name: &str, summary: &[(String, String)], fit: &Value, images: &[(&str, Option<String>, &str)], panel: &Value) -> String {
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
<p>Drag on the image to move the sun (left-right: around, up-down: height), or pick a light.</p>
<div><select id="light"><option value="sun">sun</option></select>
azimuth <input id="azimuth" type="range" min="-180" max="180" step="1">
elevation <input id="elevation" type="range" min="-10" max="90" step="1"></div>
<canvas id="view" class="px"></canvas>
<pre id="check"></pre>
"#;
    format!(
        "<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>umbra: {}</title>\n<style>body{{font-family:sans-serif;max-width:70em;margin:2em auto}}table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:.2em .6em;text-align:left}}.px{{image-rendering:pixelated;width:min(100%,40em)}}canvas.px{{width:24em;cursor:crosshair}}</style>\n</head><body>\n{body}<script type=\"application/json\" id=\"basis\">{}</script>\n<script>\n{PANEL_SCRIPT}\n</script>\n</body></html>\n",
        escape(name),
        panel.to_string().replace("</", "<\\/")
    )
}

/// The panel's data: the basis as little-endian arrays in base64 (pixel indices u32,
/// reflectance and normals f32, visibility quantised to u8), the directions, the sun's frame
/// (up, and azimuth 0 facing the camera), the first sun, the scene's skies per direction, and
/// the mean 8-bit sRGB of the first sun's image as Rust relit it, for the page to check itself.
#[allow(clippy::too_many_arguments)]
fn panel_json(
    basis: &TransferBasis,
    up: DVec3,
    forward: DVec3,
    sun: DVec3,
    irradiance: DVec3,
    ambient: DVec3,
    skies: &[(String, Vec<DVec3>)],
    first: &RgbImage,
) -> Value {
    let (pixels, reflectance, normals, visibility, coverage) = basis.parts();
    let u32s: Vec<u8> = pixels.iter().flat_map(|&p| (p as u32).to_le_bytes()).collect();
    let f32s = |v: &[DVec3]| -> Vec<u8> { v.iter().flat_map(|x| x.as_vec3().to_array()).flat_map(|x| x.to_le_bytes()).collect() };
    let quantised: Vec<u8> = visibility.iter().map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    // Azimuth 0 is the side the camera looks from (against its forward axis, made level).
    let toward_camera = (-forward - up * (-forward).dot(up)).try_normalize().unwrap_or_else(|| up.any_orthonormal_vector());
    let side = up.cross(toward_camera);
    let elevation = sun.dot(up).clamp(-1.0, 1.0).asin().to_degrees();
    let azimuth = sun.dot(side).atan2(sun.dot(toward_camera)).to_degrees();
    let mut sum = [0.0f64; 3];
    for &p in pixels {
        for (c, s) in sum.iter_mut().enumerate() {
            *s += linear_to_srgb8(first.pixels[p][c]) as f64;
        }
    }
    let mean = sum.map(|s| s / pixels.len().max(1) as f64);
    let flat = |v: &[DVec3]| -> Vec<f64> { v.iter().flat_map(|x| x.to_array()).collect() };
    json!({
        "width": basis.width,
        "height": basis.height,
        "pixels": base64(&u32s),
        "reflectance": base64(&f32s(reflectance)),
        "normals": base64(&f32s(normals)),
        "visibility": base64(&quantised),
        "coverage": base64(&coverage.iter().flat_map(|c| c.to_le_bytes()).collect::<Vec<u8>>()),
        "directions": flat(&basis.directions),
        "up": up.to_array(),
        "toward_camera": toward_camera.to_array(),
        "side": side.to_array(),
        "azimuth": azimuth,
        "elevation": elevation,
        "irradiance": irradiance.to_array(),
        "ambient": ambient.to_array(),
        "skies": skies.iter().map(|(name, cells)| json!({"name": name, "cells": flat(cells)})).collect::<Vec<_>>(),
        "expected_mean_srgb8": mean,
    })
}

/// The page's relighting, the sums of `TransferBasis::relight` over the embedded arrays: a sun
/// blends the visibility of the directions within one lattice spacing (a tent), a sky sums its
/// cells' light with exact cosines over pi.
const PANEL_SCRIPT: &str = r#"
const D = JSON.parse(document.getElementById('basis').textContent);
const bytes = b => { const s = atob(b); const a = new Uint8Array(s.length); for (let i = 0; i < s.length; i++) a[i] = s.charCodeAt(i); return a; };
const pix = new Uint32Array(bytes(D.pixels).buffer), refl = new Float32Array(bytes(D.reflectance).buffer);
const nrm = new Float32Array(bytes(D.normals).buffer), vis = bytes(D.visibility), dirs = D.directions;
const K = dirs.length / 3, P = pix.length, spacing = Math.sqrt(4 * Math.PI / K);
const canvas = document.getElementById('view'); canvas.width = D.width; canvas.height = D.height;
const cov = new Float32Array(bytes(D.coverage).buffer);
const srgb = v => { v = Math.min(1, Math.max(0, v)); return v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1 / 2.4) - 0.055; };
// A pixel is composited as its image stores it (umbra's imageio::composite_centre_sample).
const srgb8 = (v, a) => Math.round(255 * (a >= 1 ? srgb(v) : a > 0 ? a * srgb(v / a) : 0));
function draw(values) {
  const ctx = canvas.getContext('2d'), img = ctx.createImageData(D.width, D.height);
  for (let i = 3; i < img.data.length; i += 4) img.data[i] = 255;
  const mean = [0, 0, 0];
  for (let p = 0; p < P; p++) for (let c = 0; c < 3; c++) { const v = srgb8(values[p * 3 + c], cov[p]); img.data[pix[p] * 4 + c] = v; mean[c] += v / Math.max(P, 1); }
  ctx.putImageData(img, 0, 0);
  return mean;
}
function sunDirection(az, el) {
  const a = az * Math.PI / 180, e = el * Math.PI / 180, t = D.toward_camera, s = D.side, u = D.up;
  return [0, 1, 2].map(c => Math.cos(e) * (Math.cos(a) * t[c] + Math.sin(a) * s[c]) + Math.sin(e) * u[c]);
}
function sun(l) {
  const blend = []; let total = 0;
  for (let k = 0; k < K; k++) { const c = dirs[3 * k] * l[0] + dirs[3 * k + 1] * l[1] + dirs[3 * k + 2] * l[2];
    if (c > Math.cos(spacing)) { const w = 1 - Math.acos(Math.min(1, c)) / spacing; blend.push([k, w]); total += w; } }
  const out = new Float32Array(P * 3);
  for (let p = 0; p < P; p++) {
    let v = 0; for (const [k, w] of blend) v += w / total * vis[p * K + k] / 255;
    const cos = Math.max(0, nrm[3 * p] * l[0] + nrm[3 * p + 1] * l[1] + nrm[3 * p + 2] * l[2]);
    for (let c = 0; c < 3; c++) out[p * 3 + c] = refl[p * 3 + c] * (D.ambient[c] + D.irradiance[c] * cos * v);
  }
  return out;
}
function sky(cells) {
  const out = new Float32Array(P * 3);
  for (let p = 0; p < P; p++) {
    const n = [nrm[3 * p], nrm[3 * p + 1], nrm[3 * p + 2]]; const sum = [0, 0, 0];
    for (let k = 0; k < K; k++) { const v = vis[p * K + k]; if (!v) continue;
      const w = Math.max(0, n[0] * dirs[3 * k] + n[1] * dirs[3 * k + 1] + n[2] * dirs[3 * k + 2]) * v / 255;
      for (let c = 0; c < 3; c++) sum[c] += cells[3 * k + c] * w; }
    for (let c = 0; c < 3; c++) out[p * 3 + c] = refl[p * 3 + c] * sum[c] / Math.PI;
  }
  return out;
}
const pick = document.getElementById('light'), az = document.getElementById('azimuth'), el = document.getElementById('elevation');
for (const s of D.skies) { const o = document.createElement('option'); o.value = o.textContent = s.name; pick.appendChild(o); }
az.value = D.azimuth; el.value = D.elevation;
function update() {
  if (pick.value === 'sun') return draw(sun(sunDirection(+az.value, +el.value)));
  return draw(sky(D.skies.find(s => s.name === pick.value).cells));
}
let dragging = false;
canvas.addEventListener('pointerdown', e => { dragging = true; pick.value = 'sun'; });
window.addEventListener('pointerup', () => dragging = false);
canvas.addEventListener('pointermove', e => { if (!dragging) return; const r = canvas.getBoundingClientRect();
  az.value = 360 * (e.clientX - r.left) / r.width - 180; el.value = 90 - 100 * (e.clientY - r.top) / r.height; update(); });
for (const x of [pick, az, el]) x.addEventListener('input', update);
const first = draw(sun(sunDirection(D.azimuth, D.elevation)));
const off = Math.max(...first.map((m, c) => Math.abs(m - D.expected_mean_srgb8[c])));
document.getElementById('check').textContent = 'relit in this browser: mean sRGB ' + first.map(m => m.toFixed(2)).join(' ') + '; as umbra relit it: ' + D.expected_mean_srgb8.map(m => m.toFixed(2)).join(' ') + (off < 0.5 ? '; agree' : '; DISAGREE');
"#;

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
