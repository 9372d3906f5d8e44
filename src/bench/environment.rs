//! The environment-lighting benchmark: three estimators of a Lambertian point's sky light with
//! Gaussian visibility, at equal samples, against a 4096-sample reference of the unbiased one:
//! the per-pixel MIS estimator (`environment`), the shared-direction luminance sampler it
//! replaced (`relight::EnvironmentSampler`: one set of directions for every pixel), and the
//! research code's (one ray to the brightest texel plus cosine rays on a 32x64 blurred map).
//! Two skies: a clear one with a small bright sun, and a soft overcast one.

use super::shadows::body_cloud;
use super::time;
use crate::environment::{cosine_sample, MisEstimator};
use crate::imageio::RgbImage;
use crate::light::{uv_to_direction, EnvironmentMap};
use crate::plot::{Chart, Series};
use crate::random::Stream;
use crate::relight::EnvironmentSampler;
use crate::shading::SHADOW_START;
use crate::shadow::PosedGaussian;
use crate::shadow::{ShadowCaster, ShadowRay};
use glam::DVec3;
use rayon::prelude::*;
use std::f64::consts::PI;
use std::path::Path;

/// Points on a sphere inside the body cloud, normals outward: partly occluded in every way.
fn probes(n: usize) -> (Vec<DVec3>, Vec<DVec3>) {
    let centre = DVec3::new(0.0, 0.85, 0.0);
    let normals = crate::light::fibonacci_sphere(n, 0.0);
    (normals.iter().map(|n| centre + *n * 0.35).collect(), normals)
}

fn overcast(width: usize, height: usize) -> EnvironmentMap {
    let mut image = RgbImage::new(width, height);
    for y in 0..height {
        for x in 0..width {
            let d = uv_to_direction((x as f64 + 0.5) / width as f64, (y as f64 + 0.5) / height as f64);
            let v = (0.35 + 0.65 * d.y.max(0.0) + 0.1 * (3.0 * d.x).sin() * d.y.max(0.0)) as f32;
            image.set(x, y, [v * 0.9, v * 0.92, v]);
        }
    }
    EnvironmentMap { image }
}

/// The research code's estimator: the brightest texel as a point light with its visibility,
/// plus cosine-sampled rays on a 32x64 box-filtered map from which that texel's light is taken
/// out (so it is not counted twice).
struct Research {
    sun: DVec3,
    /// Radiance times solid angle of the brightest texel.
    sun_irradiance: DVec3,
    blurred: EnvironmentMap,
}

impl Research {
    fn new(map: &EnvironmentMap) -> Self {
        let (w, h) = (map.image.width, map.image.height);
        let lum = |p: [f32; 3]| 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2];
        let brightest = (0..w * h).max_by(|&a, &b| lum(map.image.pixels[a]).total_cmp(&lum(map.image.pixels[b]))).unwrap_or(0);
        let (bx, by) = (brightest % w, brightest / w);
        let p = map.image.pixels[brightest];
        let sun_irradiance = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) * map.texel_solid_angle(by);
        let (bw, bh) = (64usize, 32usize);
        let mut sums = vec![DVec3::ZERO; bw * bh];
        let mut areas = vec![0.0; bw * bh];
        for y in 0..h {
            for x in 0..w {
                let k = (y * bh / h) * bw + x * bw / w;
                let omega = map.texel_solid_angle(y);
                let p = if (x, y) == (bx, by) { [0.0; 3] } else { map.image.pixels[y * w + x] };
                sums[k] += DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) * omega;
                areas[k] += omega;
            }
        }
        let mut blurred = RgbImage::new(bw, bh);
        for k in 0..bw * bh {
            blurred.pixels[k] = (sums[k] / areas[k].max(1e-12)).as_vec3().to_array();
        }
        Self { sun: map.texel_direction(bx, by), sun_irradiance, blurred: EnvironmentMap { image: blurred } }
    }

    fn shade(&self, points: &[DVec3], normals: &[DVec3], samples: usize, seed: u64, casters: &[PosedGaussian]) -> Vec<DVec3> {
        let caster = ShadowCaster::new(casters, 1e-4);
        points
            .par_iter()
            .zip(normals)
            .enumerate()
            .map(|(k, (&x, &n))| {
                let origin = (x + n * SHADOW_START as f64).as_vec3().to_array();
                // The same visibility as umbra's estimator (the point's own Gaussians left out):
                // only the sampling differs.
                let shares = caster.shares_at(x.as_vec3().to_array());
                let visible = |d: DVec3| {
                    caster.transmittance_from(&shares, &ShadowRay { origin, direction: d.as_vec3().to_array(), t0: SHADOW_START, t1: f32::INFINITY }, true)
                        as f64
                };
                let mut sum = self.sun_irradiance * n.dot(self.sun).max(0.0) / PI * visible(self.sun);
                let rays = samples.saturating_sub(1).max(1);
                let mut stream = Stream::new(seed, k as u64, 0x7E5);
                let mut sky = DVec3::ZERO;
                for j in 0..rays {
                    let d = cosine_sample(n, [(j as f64 + stream.uniform()) / rays as f64, stream.uniform()]);
                    sky += self.blurred.lookup(d) * visible(d);
                }
                sum += sky / rays as f64;
                sum
            })
            .collect()
    }
}

/// A shading method under comparison: its label and a run of it over the probes.
type ShadingMethod<'a> = (&'static str, Box<dyn Fn() -> Vec<DVec3> + 'a>);

struct Row {
    sky: &'static str,
    method: &'static str,
    samples: usize,
    error: f64,
    seconds: f64,
}

/// Runs the benchmark and writes `environment.md`, `environment.csv` and `environment.png`.
pub fn environment(out: &Path, quick: bool) -> Result<String, String> {
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let casters = body_cloud(96, 1);
    let (points, normals) = probes(if quick { 64 } else { 256 });
    let ids: Vec<u64> = (0..points.len() as u64).collect();
    let reference_samples = if quick { 1024 } else { 4096 };
    let budget = if quick { 0.02 } else { 0.2 };
    let mut rows = Vec::new();
    for (sky, map) in [("clear sky, small sun", crate::synth::synthetic_sky(128, 64)), ("overcast", overcast(128, 64))] {
        let reference = MisEstimator::new(&map, 1.0, reference_samples, 99).shade(&points, &normals, &ids, &casters);
        let scale = reference.iter().map(|v| v.length()).sum::<f64>() / reference.len() as f64;
        let error =
            |values: &[DVec3]| (values.iter().zip(&reference).map(|(a, b)| (*a - *b).length_squared()).sum::<f64>() / values.len() as f64).sqrt() / scale;
        let research = Research::new(&map);
        for samples in [16, 64, 256] {
            let mis = MisEstimator::new(&map, 1.0, samples, 5);
            let shared = EnvironmentSampler::new(&map, 1.0, samples, 5);
            let methods: [ShadingMethod<'_>; 3] = [
                ("per-pixel MIS (map + cosine, balance heuristic)", Box::new(|| mis.shade(&points, &normals, &ids, &casters))),
                ("shared luminance directions (previous)", Box::new(|| shared.shade(&points, &normals, &casters))),
                ("brightest texel + cosine rays on a 32x64 blur (research code)", Box::new(|| research.shade(&points, &normals, samples, 5, &casters))),
            ];
            for (method, run) in methods {
                let values = run();
                let seconds = time(budget, || {
                    std::hint::black_box(run());
                });
                rows.push(Row { sky, method, samples, error: error(&values), seconds });
            }
        }
    }
    let mut md = format!(
        "## Environment light: error against a {reference_samples}-sample reference at equal samples\n\n{} points inside a 96-Gaussian body, normals all around; error = RMS over points of the difference, over the reference's mean.\n\n| sky | estimator | samples | relative RMS error | time (ms) |\n|---|---|---|---|---|\n",
        points.len()
    );
    for r in &rows {
        md += &format!("| {} | {} | {} | {:.4} | {:.1} |\n", r.sky, r.method, r.samples, r.error, r.seconds * 1e3);
    }
    let csv = crate::table::to_csv(
        &["sky", "estimator", "samples", "relative_rms_error", "seconds"],
        rows.iter().map(|r| [r.sky.to_string(), r.method.to_string(), r.samples.to_string(), r.error.to_string(), r.seconds.to_string()]),
    );
    crate::imageio::write_atomic(&out.join("environment.md"), md.as_bytes()).map_err(|e| e.to_string())?;
    crate::imageio::write_atomic(&out.join("environment.csv"), csv.as_bytes()).map_err(|e| e.to_string())?;
    let mut series = Vec::new();
    for sky in ["clear sky, small sun", "overcast"] {
        for method in rows.iter().filter(|r| r.sky == sky).map(|r| r.method).collect::<std::collections::BTreeSet<_>>() {
            let points = rows.iter().filter(|r| r.sky == sky && r.method == method).map(|r| (r.samples as f64, r.error.max(1e-6))).collect();
            series.push(Series { name: format!("{sky}: {}", method.split(" (").next().unwrap_or(method)), points, lines: true });
        }
    }
    let chart = Chart {
        title: "sky light: error against samples".into(),
        x_label: "samples per pixel".into(),
        y_label: "relative RMS error".into(),
        log_x: true,
        log_y: true,
        series,
        marks: Vec::new(),
    };
    chart.render(800, 500).save_png(&out.join("environment.png"))?;
    Ok(md)
}
