//! The report's relighting panel: one view's visibility basis (`basis`) at 256 pixels or more on
//! its short side, the ground's visibility beside it, the scene's skies binned per direction at
//! every `SKY_TURN` degrees of turn, and the page's script that relights from them: a sun by
//! azimuth and elevation (shown as numbers), a sky turned about the up axis, both scaled by an
//! intensity, over a ground that receives the shadow or not.

use super::base64;
use crate::basis::TransferBasis;
use crate::imageio::{linear_to_srgb8, RgbImage};
use crate::scene::Camera;
use crate::shadow::{PosedGaussian, ShadowCaster, ShadowRay};
use glam::DVec3;
use rayon::prelude::*;
use serde_json::{json, Value};

/// The least side of the panel's view (pixels): a capture's view is enlarged by a whole factor
/// until its short side reaches it.
pub const PANEL_SIDE: usize = 256;

/// Degrees between the turns of a sky the page holds (its rotation slider's step).
pub const SKY_TURN: usize = 15;

/// The side (pixels) of the square blocks the ground's visibility is taken in: one shadow ray
/// set per block, which keeps the page's ground a quarter of its pixels.
const GROUND_BLOCK: usize = 2;

/// How far from the body's centre (in body extents) the ground receives a shadow in the panel.
const GROUND_REACH: f64 = 1.5;

/// The ground's visibility in the panel's view: per block of `GROUND_BLOCK` pixels whose
/// centre ray meets the ground near the body, the transmittance toward each basis direction
/// above the horizon (8 bits).
pub struct GroundBasis {
    pub blocks: Vec<u32>,
    /// The indices of the directions above the horizon.
    pub upper: Vec<u32>,
    pub visibility: Vec<u8>,
}

/// The ground's visibility under `casters`, at `height`, in the view `camera` shows.
pub fn ground_basis(directions: &[DVec3], camera: &Camera, casters: &[PosedGaussian], height: f64, centre: DVec3, extent: f64) -> GroundBasis {
    let (bw, bh) = (camera.width.div_ceil(GROUND_BLOCK), camera.height.div_ceil(GROUND_BLOCK));
    let upper: Vec<u32> = (0..directions.len()).filter(|&k| directions[k].y > 0.0).map(|k| k as u32).collect();
    let meets = |b: usize| {
        let at = glam::DVec2::new(((b % bw) * GROUND_BLOCK) as f64 + 0.5 * GROUND_BLOCK as f64, ((b / bw) * GROUND_BLOCK) as f64 + 0.5 * GROUND_BLOCK as f64);
        let ray = camera.ray_through(at);
        let t = (height - ray.origin.y) / ray.direction.y;
        let x = ray.at(t);
        (ray.direction.y.abs() > 1e-9 && t > 0.0 && glam::DVec2::new(x.x - centre.x, x.z - centre.z).length() < GROUND_REACH * extent).then_some(x)
    };
    let points: Vec<(u32, DVec3)> = (0..bw * bh).filter_map(|b| meets(b).map(|x| (b as u32, x))).collect();
    let caster = ShadowCaster::new(casters, 1e-4);
    let visibility = points
        .par_iter()
        .flat_map_iter(|(_, x)| {
            let origin = (*x + DVec3::Y * crate::shading::SHADOW_START as f64).as_vec3().to_array();
            let caster = &caster;
            upper.iter().map(move |&k| {
                let ray = ShadowRay { origin, direction: directions[k as usize].as_vec3().to_array(), t0: 0.0, t1: f32::INFINITY };
                (caster.transmittance(&ray, true).clamp(0.0, 1.0) * 255.0).round() as u8
            })
        })
        .collect();
    GroundBasis { blocks: points.iter().map(|(b, _)| *b).collect(), upper, visibility }
}

/// What the panel shows and starts from.
pub struct Panel<'a> {
    pub basis: &'a TransferBasis,
    pub up: DVec3,
    pub forward: DVec3,
    pub sun: DVec3,
    pub irradiance: DVec3,
    pub ambient: DVec3,
    /// Per sky, its cells at every `SKY_TURN` degrees of turn from 0.
    pub skies: Vec<(String, Vec<Vec<DVec3>>)>,
    pub ground: GroundBasis,
    /// The first sun's image as Rust relit it, for the page to check itself.
    pub first: &'a RgbImage,
}

/// The panel's data: the basis as gzipped little-endian arrays in base64 (pixel indices u32,
/// reflectance and normals f32, visibility quantised to u8), the directions, the sun's frame
/// (up, and azimuth 0 facing the camera), the first sun, the skies per direction and turn, the
/// ground's blocks and visibility, and the mean 8-bit sRGB of the first sun's image.
pub fn panel_json(panel: &Panel) -> Value {
    let basis = panel.basis;
    let (pixels, reflectance, normals, visibility, coverage) = basis.parts();
    let u32s = |v: &mut dyn Iterator<Item = u32>| -> Vec<u8> { v.flat_map(|p| p.to_le_bytes()).collect() };
    let f32s = |v: &[DVec3]| -> Vec<u8> { v.iter().flat_map(|x| x.as_vec3().to_array()).flat_map(|x| x.to_le_bytes()).collect() };
    let quantised: Vec<u8> = visibility.iter().map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    let up = panel.up;
    // Azimuth 0 is the side the camera looks from (against its forward axis, made level).
    let toward_camera = (-panel.forward - up * (-panel.forward).dot(up)).try_normalize().unwrap_or_else(|| up.any_orthonormal_vector());
    let side = up.cross(toward_camera);
    let sun = panel.sun;
    let elevation = sun.dot(up).clamp(-1.0, 1.0).asin().to_degrees();
    let azimuth = sun.dot(side).atan2(sun.dot(toward_camera)).to_degrees();
    let mut sum = [0.0f64; 3];
    for &p in pixels {
        for (c, s) in sum.iter_mut().enumerate() {
            *s += linear_to_srgb8(panel.first.pixels[p][c]) as f64;
        }
    }
    let mean = sum.map(|s| s / pixels.len().max(1) as f64);
    let flat = |v: &[DVec3]| -> Vec<f64> { v.iter().flat_map(|x| x.to_array()).collect() };
    // A sky's turns one after another, each its cells' RGB per direction (f32).
    let skies: Vec<Value> =
        panel.skies.iter().map(|(name, turns)| json!({"name": name, "turns": turns.len(), "cells": packed(&f32s(&turns.concat()))})).collect();
    json!({
        "width": basis.width,
        "height": basis.height,
        "pixels": packed(&u32s(&mut pixels.iter().map(|&p| p as u32))),
        "reflectance": packed(&f32s(reflectance)),
        "normals": packed(&f32s(normals)),
        "visibility": packed(&quantised),
        "coverage": packed(&coverage.iter().flat_map(|c| c.to_le_bytes()).collect::<Vec<u8>>()),
        "directions": flat(&basis.directions),
        "up": up.to_array(),
        "toward_camera": toward_camera.to_array(),
        "side": side.to_array(),
        "azimuth": azimuth,
        "elevation": elevation,
        "irradiance": panel.irradiance.to_array(),
        "ambient": panel.ambient.to_array(),
        "skies": skies,
        "sky_turn": SKY_TURN,
        "ground": {
            "block": GROUND_BLOCK,
            "blocks": packed(&u32s(&mut panel.ground.blocks.iter().copied())),
            "upper": panel.ground.upper,
            "visibility": packed(&panel.ground.visibility),
        },
        "expected_mean_srgb8": mean,
    })
}

/// Gzipped and in base64: the page inflates it with the browser's `DecompressionStream`.
fn packed(bytes: &[u8]) -> String {
    use std::io::Write;
    let mut encoder = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    // Writing to a Vec cannot fail.
    let zipped = encoder.write_all(bytes).and_then(|_| encoder.finish()).unwrap_or_default();
    base64(&zipped)
}

/// The page's relighting, the sums of `TransferBasis::relight` over the embedded arrays: a sun
/// blends the visibility of the directions within one lattice spacing (a tent), a sky sums its
/// cells' light with exact cosines over pi; the ground's shadow is one less the same blend (a
/// sun) or the sky's light it receives over what an open ground would (a sky), drawn over grey.
pub const PANEL_SCRIPT: &str = r#"
const D = JSON.parse(document.getElementById('basis').textContent);
const bytes = b => { const s = atob(b); const a = new Uint8Array(s.length); for (let i = 0; i < s.length; i++) a[i] = s.charCodeAt(i); return a; };
const unzip = async b => new Uint8Array(await new Response(new Blob([bytes(b)]).stream().pipeThrough(new DecompressionStream('gzip'))).arrayBuffer());
(async () => {
const G = D.ground;
const [pixB, reflB, nrmB, vis, covB, gblocksB, gvis] = await Promise.all([D.pixels, D.reflectance, D.normals, D.visibility, D.coverage, G.blocks, G.visibility].map(unzip));
const pix = new Uint32Array(pixB.buffer), refl = new Float32Array(reflB.buffer), nrm = new Float32Array(nrmB.buffer), dirs = D.directions;
const K = dirs.length / 3, P = pix.length, spacing = Math.sqrt(4 * Math.PI / K);
const gblocks = new Uint32Array(gblocksB.buffer), U = G.upper.length;
const canvas = document.getElementById('view'); canvas.width = D.width; canvas.height = D.height;
const cov = new Float32Array(covB.buffer);
const skies = await Promise.all(D.skies.map(async s => { const all = new Float32Array((await unzip(s.cells)).buffer);
  return { name: s.name, turns: Array.from({ length: s.turns }, (_, t) => all.subarray(t * 3 * K, (t + 1) * 3 * K)) }; }));
const srgb = v => { v = Math.min(1, Math.max(0, v)); return v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1 / 2.4) - 0.055; };
// A pixel is composited as its image stores it (umbra's imageio::composite_centre_sample).
const srgb8 = (v, a) => Math.round(255 * (a >= 1 ? srgb(v) : a > 0 ? a * srgb(v / a) : 0));
const GREY = 0.5;
function draw(values, shadow) {
  const W = D.width, BW = Math.ceil(W / G.block), ctx = canvas.getContext('2d'), img = ctx.createImageData(W, D.height);
  const covered = new Float32Array(W * D.height), body = new Float32Array(W * D.height * 3), mean = [0, 0, 0];
  for (let p = 0; p < P; p++) { covered[pix[p]] = cov[p];
    for (let c = 0; c < 3; c++) { body[pix[p] * 3 + c] = values[p * 3 + c]; mean[c] += srgb8(values[p * 3 + c], cov[p]) / Math.max(P, 1); } }
  for (let q = 0; q < W * D.height; q++) {
    img.data[q * 4 + 3] = 255;
    // The body's colour is premultiplied by its coverage; the ground shows through the rest.
    const s = shadow ? (shadow.get(Math.floor(Math.floor(q / W) / G.block) * BW + Math.floor((q % W) / G.block)) || 0) : 0;
    for (let c = 0; c < 3; c++) img.data[q * 4 + c] = shadow ? Math.round(255 * srgb(body[q * 3 + c] + (1 - covered[q]) * GREY * (1 - s))) : srgb8(body[q * 3 + c], covered[q]);
  }
  ctx.putImageData(img, 0, 0);
  return mean;
}
function sunDirection(az, el) {
  const a = az * Math.PI / 180, e = el * Math.PI / 180, t = D.toward_camera, s = D.side, u = D.up;
  return [0, 1, 2].map(c => Math.cos(e) * (Math.cos(a) * t[c] + Math.sin(a) * s[c]) + Math.sin(e) * u[c]);
}
function tent(l) {
  const blend = []; let total = 0;
  for (let k = 0; k < K; k++) { const c = dirs[3 * k] * l[0] + dirs[3 * k + 1] * l[1] + dirs[3 * k + 2] * l[2];
    if (c > Math.cos(spacing)) { const w = 1 - Math.acos(Math.min(1, c)) / spacing; blend.push([k, w]); total += w; } }
  return blend.map(([k, w]) => [k, w / total]);
}
function sun(l, scale) {
  const blend = tent(l), out = new Float32Array(P * 3);
  for (let p = 0; p < P; p++) {
    let v = 0; for (const [k, w] of blend) v += w * vis[p * K + k] / 255;
    const cos = Math.max(0, nrm[3 * p] * l[0] + nrm[3 * p + 1] * l[1] + nrm[3 * p + 2] * l[2]);
    for (let c = 0; c < 3; c++) out[p * 3 + c] = scale * refl[p * 3 + c] * (D.ambient[c] + D.irradiance[c] * cos * v);
  }
  return out;
}
function sunShadow(l) {
  const slot = new Map(G.upper.map((k, i) => [k, i])), blend = tent(l).filter(([k]) => slot.has(k)), out = new Map();
  if (l[1] <= 0) return out;
  for (let b = 0; b < gblocks.length; b++) { let v = 0; for (const [k, w] of blend) v += w * gvis[b * U + slot.get(k)] / 255; out.set(gblocks[b], 1 - v); }
  return out;
}
function sky(cells, scale) {
  const out = new Float32Array(P * 3);
  for (let p = 0; p < P; p++) {
    const n = [nrm[3 * p], nrm[3 * p + 1], nrm[3 * p + 2]]; const sum = [0, 0, 0];
    for (let k = 0; k < K; k++) { const v = vis[p * K + k]; if (!v) continue;
      const w = Math.max(0, n[0] * dirs[3 * k] + n[1] * dirs[3 * k + 1] + n[2] * dirs[3 * k + 2]) * v / 255;
      for (let c = 0; c < 3; c++) sum[c] += cells[3 * k + c] * w; }
    for (let c = 0; c < 3; c++) out[p * 3 + c] = scale * refl[p * 3 + c] * sum[c] / Math.PI;
  }
  return out;
}
function skyShadow(cells) {
  const out = new Map(); let open = 0; const weight = G.upper.map(k => { const w = dirs[3 * k + 1] * (cells[3 * k] + cells[3 * k + 1] + cells[3 * k + 2]); open += w; return w; });
  for (let b = 0; b < gblocks.length; b++) { let seen = 0; for (let i = 0; i < U; i++) seen += weight[i] * gvis[b * U + i] / 255; out.set(gblocks[b], open > 0 ? 1 - seen / open : 0); }
  return out;
}
const $ = id => document.getElementById(id);
const pick = $('light'), az = $('azimuth'), el = $('elevation'), turn = $('turn'), gain = $('intensity'), ground = $('ground');
for (const s of skies) { const o = document.createElement('option'); o.value = o.textContent = s.name; pick.appendChild(o); }
az.value = D.azimuth; el.value = D.elevation; turn.step = D.sky_turn;
function update() {
  const rotation = +turn.value, scale = +gain.value;
  $('azimuth-value').textContent = (+az.value).toFixed(0) + '\u00b0'; $('elevation-value').textContent = (+el.value).toFixed(0) + '\u00b0';
  $('turn-value').textContent = rotation.toFixed(0) + '\u00b0'; $('intensity-value').textContent = scale.toFixed(2) + 'x';
  if (pick.value === 'sun') { const l = sunDirection(+az.value + rotation, +el.value); return draw(sun(l, scale), ground.checked ? sunShadow(l) : null); }
  const turns = skies.find(s => s.name === pick.value).turns;
  const cells = turns[((Math.round(rotation / D.sky_turn) % turns.length) + turns.length) % turns.length];
  return draw(sky(cells, scale), ground.checked ? skyShadow(cells) : null);
}
let dragging = false;
canvas.addEventListener('pointerdown', e => { dragging = true; pick.value = 'sun'; });
window.addEventListener('pointerup', () => dragging = false);
canvas.addEventListener('pointermove', e => { if (!dragging) return; const r = canvas.getBoundingClientRect();
  az.value = 360 * (e.clientX - r.left) / r.width - 180; el.value = 90 - 100 * (e.clientY - r.top) / r.height; update(); });
for (const x of [pick, az, el, turn, gain, ground]) x.addEventListener('input', update);
const first = draw(sun(sunDirection(D.azimuth, D.elevation), 1), null);
update();
const off = Math.max(...first.map((m, c) => Math.abs(m - D.expected_mean_srgb8[c])));
$('check').textContent = 'relit in this browser: mean sRGB ' + first.map(m => m.toFixed(2)).join(' ') + '; as umbra relit it: ' + D.expected_mean_srgb8.map(m => m.toFixed(2)).join(' ') + (off < 0.5 ? '; agree' : '; DISAGREE');
})();
"#;
