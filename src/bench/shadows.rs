//! The shadow benchmark: closed-form transmittance on the CPU and through burn, culling on and
//! off, against ray marching.

use super::{machine_peak_flops, time};
use crate::gaussians::PosedGaussian;
use crate::plot::{Chart, Series};
use crate::shadow::tensor::{transmittance, GaussianTensors, RaySegments};
use crate::shadow::{transmittance_f64, ShadowCaster, ShadowRay};
use crate::synth::trace::Stream;
use burn::tensor::{Device, Tensor, TensorData};
use glam::{DMat3, DQuat, DVec3};
use std::path::Path;

/// Estimated floating-point work of one closed-form (ray, Gaussian) pair: about 80 arithmetic
/// operations plus two erfc and one exp, each worth roughly 25 (the ratios below use 150).
pub const FLOPS_PER_PAIR: f64 = 150.0;

/// A body-sized cloud of `n` Gaussians whose total volume stays about constant as n grows.
pub fn body_cloud(n: usize, seed: u64) -> Vec<PosedGaussian> {
    let mut s = Stream::new(seed, 17, 19);
    let shrink = (24.0 / n as f64).cbrt();
    (0..n)
        .map(|_| {
            let axis = DVec3::new(s.uniform() - 0.5, s.uniform() - 0.5, s.uniform() - 0.5).normalize_or(DVec3::Y);
            PosedGaussian {
                mean: DVec3::new((s.uniform() - 0.5) * 0.6, s.uniform() * 1.7, (s.uniform() - 0.5) * 0.4),
                axes: DMat3::from_quat(DQuat::from_axis_angle(axis, s.uniform() * std::f64::consts::TAU)),
                scales: DVec3::new(0.03 + 0.08 * s.uniform(), 0.03 + 0.1 * s.uniform(), 0.03 + 0.08 * s.uniform()) * shrink,
                amplitude: 8.0 + 8.0 * s.uniform(),
            }
        })
        .collect()
}

/// Shadow rays from points in and around the body toward a sun.
pub fn sun_rays(n: usize, seed: u64) -> Vec<ShadowRay> {
    let mut s = Stream::new(seed, 23, 29);
    let sun = DVec3::new(0.45, 0.8, 0.4).normalize().as_vec3().to_array();
    (0..n)
        .map(|_| ShadowRay {
            origin: [((s.uniform() - 0.5) * 0.8) as f32, (s.uniform() * 1.7) as f32, ((s.uniform() - 0.5) * 0.6) as f32],
            direction: sun,
            t0: 0.0,
            t1: f32::INFINITY,
        })
        .collect()
}

/// Transmittance by the midpoint rule over `steps` samples up to where the ray leaves the
/// cloud's bounding box: the approximation closed-form integration replaces.
fn marched_transmittance(gaussians: &[PosedGaussian], ray: &ShadowRay, steps: usize, far: f32) -> f32 {
    let t1 = ray.t1.min(far);
    let dt = (t1 - ray.t0) / steps as f32;
    let mut tau = 0.0f32;
    for k in 0..steps {
        let t = ray.t0 + (k as f32 + 0.5) * dt;
        let p = DVec3::new(
            (ray.origin[0] + t * ray.direction[0]) as f64,
            (ray.origin[1] + t * ray.direction[1]) as f64,
            (ray.origin[2] + t * ray.direction[2]) as f64,
        );
        tau += gaussians.iter().map(|g| g.density(p) as f32).sum::<f32>() * dt;
    }
    (-tau).exp()
}

pub struct Row {
    pub method: String,
    pub gaussians: usize,
    pub rays: usize,
    pub seconds: f64,
    pub pairs_per_second: f64,
    pub max_error: Option<f64>,
}

/// The shadow benchmark: both paths, culling on and off, 24 to 10,000 Gaussians, and the
/// closed form against ray marching. Writes `shadows.md`, `shadows.csv` and `shadows.png`.
pub fn shadows(out: &Path, quick: bool) -> Result<String, String> {
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let budget = if quick { 0.05 } else { 0.3 };
    let sizes: &[usize] = if quick { &[24, 96] } else { &[24, 96, 1000, 10000] };
    let device = Device::flex();
    let mut rows = Vec::new();
    for &n in sizes {
        let gaussians = body_cloud(n, 1);
        let rays = sun_rays(if quick { 256 } else { 2048 }, 2);
        let caster = ShadowCaster::new(&gaussians, 1e-5);
        for cull in [false, true] {
            let seconds = time(budget, || {
                std::hint::black_box(caster.transmittance_all(&rays, cull));
            });
            rows.push(Row {
                method: format!("cpu f32, culling {}", if cull { "on" } else { "off" }),
                gaussians: n,
                rays: rays.len(),
                seconds,
                pairs_per_second: (rays.len() * n) as f64 / seconds,
                max_error: None,
            });
        }
        let tensor_rays = &rays[..rays.len().min((4_000_000 / n).max(16))];
        let g = GaussianTensors::from_posed(&gaussians, &device);
        let segments = RaySegments {
            origins: Tensor::from_data(TensorData::new(tensor_rays.iter().flat_map(|r| r.origin).collect::<Vec<f32>>(), [tensor_rays.len(), 3]), &device),
            directions: Tensor::from_data(TensorData::new(tensor_rays.iter().flat_map(|r| r.direction).collect::<Vec<f32>>(), [tensor_rays.len(), 3]), &device),
            t0: Tensor::zeros([tensor_rays.len()], &device),
            t1: None,
        };
        let seconds = time(budget, || {
            std::hint::black_box(transmittance(&g, &segments).into_data());
        });
        rows.push(Row {
            method: "burn tensor (flex), forward".into(),
            gaussians: n,
            rays: tensor_rays.len(),
            seconds,
            pairs_per_second: (tensor_rays.len() * n) as f64 / seconds,
            max_error: None,
        });
    }
    // Accuracy against the f64 closed form on the 96-Gaussian body.
    let gaussians = body_cloud(96, 1);
    let rays = sun_rays(if quick { 128 } else { 512 }, 3);
    let reference: Vec<f64> = rays.iter().map(|r| transmittance_f64(&gaussians, r)).collect();
    let caster = ShadowCaster::new(&gaussians, 1e-6);
    let mut trade = Vec::new();
    let closed = caster.transmittance_all(&rays, true);
    let seconds = time(budget, || {
        std::hint::black_box(caster.transmittance_all(&rays, true));
    });
    let error = closed.iter().zip(&reference).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
    trade.push(Row {
        method: "closed form (cpu f32, culled)".into(),
        gaussians: 96,
        rays: rays.len(),
        seconds,
        pairs_per_second: (rays.len() * 96) as f64 / seconds,
        max_error: Some(error),
    });
    for steps in [16, 64, 256] {
        use rayon::prelude::*;
        let run = || rays.par_iter().map(|r| marched_transmittance(&gaussians, r, steps, 4.0)).collect::<Vec<f32>>();
        let marched = run();
        let seconds = time(budget, || {
            std::hint::black_box(run());
        });
        let error = marched.iter().zip(&reference).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
        trade.push(Row {
            method: format!("ray marching, {steps} steps"),
            gaussians: 96,
            rays: rays.len(),
            seconds,
            pairs_per_second: (rays.len() * 96) as f64 / seconds,
            max_error: Some(error),
        });
    }
    let (peak, peak_text) = machine_peak_flops();
    let mut md = String::from("## Shadow casting throughput\n\n| method | Gaussians | rays | time (ms) | pairs/s | vs culling off | % of FLOP peak |\n|---|---|---|---|---|---|---|\n");
    let mut csv = String::from("section,method,gaussians,rays,seconds,pairs_per_second,max_error\n");
    for r in &rows {
        let baseline =
            rows.iter().find(|b| b.gaussians == r.gaussians && b.method == "cpu f32, culling off").map(|b| b.pairs_per_second).unwrap_or(r.pairs_per_second);
        md += &format!(
            "| {} | {} | {} | {:.3} | {:.3e} | {:.2}x | {:.2}% |\n",
            r.method,
            r.gaussians,
            r.rays,
            r.seconds * 1e3,
            r.pairs_per_second,
            r.pairs_per_second / baseline,
            100.0 * r.pairs_per_second * FLOPS_PER_PAIR / peak
        );
        csv += &format!("throughput,{},{},{},{},{},\n", r.method, r.gaussians, r.rays, r.seconds, r.pairs_per_second);
    }
    md += "\n## Closed form against ray marching (96 Gaussians, error against the f64 closed form)\n\n| method | time (ms) | speed vs closed form | max abs transmittance error |\n|---|---|---|---|\n";
    let closed_seconds = trade[0].seconds;
    for r in &trade {
        md += &format!("| {} | {:.3} | {:.2}x | {:.2e} |\n", r.method, r.seconds * 1e3, closed_seconds / r.seconds, r.max_error.unwrap_or(f64::NAN));
        csv += &format!("accuracy,{},{},{},{},{},{}\n", r.method, r.gaussians, r.rays, r.seconds, r.pairs_per_second, r.max_error.unwrap_or(f64::NAN));
    }
    md += &format!("\nFLOP peak: {:.1} GFLOP/s ({peak_text}); the closed form is counted at {FLOPS_PER_PAIR} flop per pair.\n", peak / 1e9);
    crate::imageio::write_atomic(&out.join("shadows.md"), md.as_bytes()).map_err(|e| e.to_string())?;
    crate::imageio::write_atomic(&out.join("shadows.csv"), csv.as_bytes()).map_err(|e| e.to_string())?;
    let chart = Chart {
        title: "shadow transmittance: time vs error".into(),
        x_label: "time ms".into(),
        y_label: "max error".into(),
        log_x: true,
        log_y: true,
        series: trade
            .iter()
            .map(|r| Series { name: r.method.clone(), points: vec![(r.seconds * 1e3, r.max_error.unwrap_or(f64::NAN).max(1e-9))], lines: false })
            .collect(),
    };
    chart.render(720, 480).save_png(&out.join("shadows.png"))?;
    Ok(md)
}
