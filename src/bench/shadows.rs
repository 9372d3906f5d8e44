//! The shadow benchmark: closed-form transmittance on the CPU (scalar and eight-lane) and
//! through burn, culling on and off, and against ray marching at the same precision and with
//! the same culling.

use super::{machine_peak_flops, time};
use crate::plot::{Chart, Series};
use crate::random::Stream;
use crate::shadow::tensor::{transmittance, GaussianTensors, RaySegments};
use crate::shadow::PosedGaussian;
use crate::shadow::{transmittance_f64, ShadowCaster, ShadowRay};
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

/// Transmittance by the midpoint rule over `steps` samples, in f32 like the closed form, over
/// the same Gaussians the closed form integrates with culling on (`caster.touching`), from the
/// ray's start to where it leaves the last of their 4-sigma spheres: the approximation the
/// closed form replaces, at its precision and with its culling.
fn marched_transmittance(caster: &ShadowCaster, ray: &ShadowRay, steps: usize) -> f32 {
    let touching = caster.touching(ray);
    let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let far = touching
        .iter()
        .map(|g| {
            let widest = 1.0 / g.inverse_scales.iter().fold(f32::INFINITY, |m, &v| m.min(v));
            let to_mean = [g.mean[0] - ray.origin[0], g.mean[1] - ray.origin[1], g.mean[2] - ray.origin[2]];
            dot(to_mean, ray.direction) + 4.0 * widest
        })
        .fold(ray.t0, f32::max)
        .min(ray.t1);
    let dt = (far - ray.t0) / steps as f32;
    let mut tau = 0.0f32;
    for k in 0..steps {
        let t = ray.t0 + (k as f32 + 0.5) * dt;
        let p = [0, 1, 2].map(|j| ray.origin[j] + t * ray.direction[j]);
        tau += touching.iter().map(|g| g.density(p)).sum::<f32>() * dt;
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
    /// Share of integrated pairs the lanes handed to the scalar integral.
    pub scalar_share: Option<f64>,
}

/// The shadow benchmark: the scalar closed form, the eight-lane kernel (as dispatched, and
/// built for the baseline instruction set) and the burn path, culling on and off, 24 to 10,000
/// Gaussians; then the closed form against f32 ray marching over the same culled Gaussians.
/// Writes `shadows.md`, `shadows.csv` and `shadows.png`.
pub fn shadows(out: &Path, quick: bool) -> Result<String, String> {
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let budget = if quick { 0.05 } else { 0.3 };
    let sizes: &[usize] = if quick { &[24, 96] } else { &[24, 96, 1000, 10000] };
    let rows: Vec<Row> = sizes.iter().flat_map(|&n| throughput(n, quick, budget)).collect();
    let trade = accuracy(quick, budget);
    write_tables(out, &rows, &trade)
}

/// Every method's throughput on a body of `n` Gaussians.
fn throughput(n: usize, quick: bool, budget: f64) -> Vec<Row> {
    let device = Device::flex();
    let kernel = crate::shadow::lanes::kernel_build().name();
    let mut rows = Vec::new();
    let gaussians = body_cloud(n, 1);
    let rays = sun_rays(if quick { 256 } else { 2048 }, 2);
    let caster = ShadowCaster::new(&gaussians, 1e-5);
    let mut push = |method: String, rays_timed: usize, seconds: f64, scalar_share: Option<f64>| {
        rows.push(Row { method, gaussians: n, rays: rays_timed, seconds, pairs_per_second: (rays_timed * n) as f64 / seconds, max_error: None, scalar_share });
    };
    for cull in [false, true] {
        let on = if cull { "on" } else { "off" };
        let seconds = time(budget, || {
            std::hint::black_box(caster.transmittance_all_scalar(&rays, cull));
        });
        push(format!("closed form, scalar, culling {on}"), rays.len(), seconds, None);
        let seconds = time(budget, || {
            std::hint::black_box(caster.transmittance_all(&rays, cull));
        });
        let (integrated, scalar) = rays.iter().map(|r| caster.collect(r, cull)).fold((0, 0), |(i, s), c| (i + c.integrated, s + c.scalar));
        push(format!("closed form, {kernel}, culling {on}"), rays.len(), seconds, Some(scalar as f64 / integrated.max(1) as f64));
    }
    // The blocks' spheres each tested on their own, without the groups above them.
    let flat = ShadowCaster::new(&gaussians, 1e-5).with_group_size(1);
    let seconds = time(budget, || {
        std::hint::black_box(flat.transmittance_all(&rays, true));
    });
    push(format!("closed form, {kernel}, culling on, no groups of blocks"), rays.len(), seconds, None);
    // The slower builds the CPU also runs, for the ratio each instruction set buys.
    for build in crate::shadow::lanes::Build::ALL.into_iter().filter(|&b| b.available() && b != crate::shadow::lanes::kernel_build()) {
        let seconds = time(budget, || {
            use rayon::prelude::*;
            std::hint::black_box(rays.par_iter().map(|r| caster.collect_built(build, r, false).map_or(0.0, |c| c.depth)).collect::<Vec<f32>>());
        });
        push(format!("closed form, {} build, culling off", build.name()), rays.len(), seconds, None);
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
    push("burn tensor (flex), forward, no culling".into(), tensor_rays.len(), seconds, None);
    rows
}

/// The closed form and ray marching against the f64 closed form (every Gaussian, no culling)
/// on the 96-Gaussian body: both in f32, both over the Gaussians culling keeps.
fn accuracy(quick: bool, budget: f64) -> Vec<Row> {
    let kernel = crate::shadow::lanes::kernel_build().name();
    use rayon::prelude::*;
    let gaussians = body_cloud(96, 1);
    let rays = sun_rays(if quick { 128 } else { 512 }, 3);
    let reference: Vec<f64> = rays.iter().map(|r| transmittance_f64(&gaussians, r)).collect();
    let caster = ShadowCaster::new(&gaussians, 1e-6);
    let max_error = |got: &[f32]| got.iter().zip(&reference).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
    let mut trade = Vec::new();
    let mut measure = |method: String, run: &dyn Fn() -> Vec<f32>| {
        let error = max_error(&run());
        let seconds = time(budget, || {
            std::hint::black_box(run());
        });
        trade.push(Row {
            method,
            gaussians: 96,
            rays: rays.len(),
            seconds,
            pairs_per_second: (rays.len() * 96) as f64 / seconds,
            max_error: Some(error),
            scalar_share: None,
        });
    };
    measure(format!("closed form, {kernel}, culled"), &|| caster.transmittance_all(&rays, true));
    measure("closed form, scalar, culled".into(), &|| caster.transmittance_all_scalar(&rays, true));
    for steps in [16, 64, 256] {
        measure(format!("ray marching f32, {steps} steps, culled"), &|| rays.par_iter().map(|r| marched_transmittance(&caster, r, steps)).collect());
    }
    trade
}

/// shadows.md, shadows.csv and shadows.png of the throughput and accuracy rows; the Markdown.
fn write_tables(out: &Path, rows: &[Row], trade: &[Row]) -> Result<String, String> {
    let (peak, peak_text) = machine_peak_flops();
    let mut md = String::from(
        "## Shadow casting throughput\n\n(ray, Gaussian) pairs per second counted over every pair, culled or not; the ratio is \
         against the scalar closed form without culling, measured in the same run.\n\n\
         | method | Gaussians | rays | time (ms) | pairs/s | vs scalar, culling off | pairs sent to the scalar integral | % of FLOP peak |\n|---|---|---|---|---|---|---|---|\n",
    );
    let mut csv_rows = Vec::new();
    let csv_row = |section: &str, r: &Row, max_error: String, scalar_share: String| {
        [
            section.to_string(),
            r.method.to_string(),
            r.gaussians.to_string(),
            r.rays.to_string(),
            r.seconds.to_string(),
            r.pairs_per_second.to_string(),
            max_error,
            scalar_share,
        ]
    };
    for r in rows {
        let baseline = rows
            .iter()
            .find(|b| b.gaussians == r.gaussians && b.method == "closed form, scalar, culling off")
            .map(|b| b.pairs_per_second)
            .unwrap_or(r.pairs_per_second);
        let share = r.scalar_share.map(|f| format!("{:.3}%", 100.0 * f)).unwrap_or_else(|| "-".into());
        md += &format!(
            "| {} | {} | {} | {:.3} | {:.3e} | {:.2}x | {share} | {:.2}% |\n",
            r.method,
            r.gaussians,
            r.rays,
            r.seconds * 1e3,
            r.pairs_per_second,
            r.pairs_per_second / baseline,
            100.0 * r.pairs_per_second * FLOPS_PER_PAIR / peak
        );
        csv_rows.push(csv_row("throughput", r, String::new(), r.scalar_share.unwrap_or(f64::NAN).to_string()));
    }
    md += "\n## Closed form against ray marching (96 Gaussians, culling tolerance 1e-6, max error against the unculled f64 closed form)\n\n| method | time (ms) | speed vs closed form | max abs transmittance error |\n|---|---|---|---|\n";
    let closed_seconds = trade[0].seconds;
    for r in trade {
        md += &format!("| {} | {:.3} | {:.2}x | {:.2e} |\n", r.method, r.seconds * 1e3, closed_seconds / r.seconds, r.max_error.unwrap_or(f64::NAN));
        csv_rows.push(csv_row("accuracy", r, r.max_error.unwrap_or(f64::NAN).to_string(), String::new()));
    }
    md += &format!("\nFLOP peak: {:.1} GFLOP/s ({peak_text}); the closed form is counted at {FLOPS_PER_PAIR} flop per pair.\n", peak / 1e9);
    crate::imageio::write_atomic(&out.join("shadows.md"), md.as_bytes()).map_err(|e| e.to_string())?;
    let csv = crate::table::to_csv(&["section", "method", "gaussians", "rays", "seconds", "pairs_per_second", "max_error", "scalar_share"], csv_rows);
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
        marks: Vec::new(),
    };
    chart.render(720, 480).save_png(&out.join("shadows.png"))?;
    Ok(md)
}
