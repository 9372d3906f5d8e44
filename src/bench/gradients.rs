//! The SDF-gradient benchmark: forward-mode tangents against central differences, for the
//! Eikonal term (forward and backward over a batch of points, against a plain SDF step over the
//! same points), for normals (forward only), and inside whole training steps on a real scene.

use super::time;
use crate::field::{AvatarField, FieldConfig, GradientMethod, PoseTensors};
use crate::plot::{Chart, Series};
use crate::random::Stream;
use crate::render::NORMAL_STEP;
use crate::synth::character::{Character, Kind};
use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;
use std::path::Path;

const CENTRAL: GradientMethod = GradientMethod::CentralDifferences(NORMAL_STEP);

struct Row {
    task: String,
    method: String,
    points: usize,
    seconds: f64,
    baseline_seconds: f64,
    error: Option<(f64, f64)>,
}

fn name(method: GradientMethod) -> String {
    match method {
        GradientMethod::Tangents => "forward-mode tangents".into(),
        GradientMethod::CentralDifferences(h) => format!("central differences (h = {} mm)", h * 1e3),
    }
}

/// A human field whose MLP residual bends the SDF (an initial field is the capsule prior),
/// so that the methods' disagreement says something.
fn field_with_residual(device: &Device) -> (AvatarField, PoseTensors, Vec<f32>, usize) {
    let character = Character::new(Kind::Human);
    let pose = character.pose(0.3, 0.4, DVec3::ZERO);
    let mut field = FieldConfig::for_bones(character.skeleton.len()).init(device, 11);
    let scaled = (field.output.weight.val() * 60.0).into_data();
    field.output.weight = Param::from_tensor(Tensor::from_data(scaled, device));
    let tensors = PoseTensors::new(&pose, &character.skeleton, device);
    let mut s = Stream::new(8, 8, 8);
    let bones = character.skeleton.len();
    let points: Vec<f32> = (0..8192)
        .flat_map(|_| {
            let b = s.below(bones);
            let (head, tail) = pose.segment(&character.skeleton, b);
            let p = head + (tail - head) * s.uniform() + DVec3::new(s.uniform() - 0.5, s.uniform() - 0.5, s.uniform() - 0.5) * 0.2;
            p.as_vec3().to_array()
        })
        .collect();
    (field, tensors, points, bones)
}

fn gradient_values(field: &AvatarField, pose: &PoseTensors, points: Tensor<2>, method: GradientMethod) -> Vec<f32> {
    crate::backend::host_values(field.sdf_gradient(points, pose, method))
}

/// Max and median of |g - reference| / max(|reference|, 0.1) over points.
fn disagreement(values: &[f32], reference: &[f32]) -> (f64, f64) {
    let mut errors: Vec<f64> = values
        .chunks(3)
        .zip(reference.chunks(3))
        .map(|(a, b)| {
            let d = (0..3).map(|k| ((a[k] - b[k]) as f64).powi(2)).sum::<f64>().sqrt();
            d / (0..3).map(|k| (b[k] as f64).powi(2)).sum::<f64>().sqrt().max(0.1)
        })
        .collect();
    errors.sort_by(f64::total_cmp);
    (errors.last().copied().unwrap_or(0.0), errors.get(errors.len() / 2).copied().unwrap_or(0.0))
}

/// Runs the benchmark; `scene` (a training scene) adds whole training steps to the table.
pub fn gradients(out: &Path, quick: bool, scene: Option<&Path>) -> Result<String, String> {
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let budget = if quick { 0.1 } else { 1.0 };
    let sizes: &[usize] = if quick { &[128] } else { &[128, 1024, 8192] };
    let mut rows = Vec::new();
    let train = Device::flex().autodiff();
    let infer = Device::flex();
    for &n in sizes {
        let (field, pose, points, _) = field_with_residual(&train);
        let batch = || Tensor::<2>::from_data(TensorData::new(points[..n * 3].to_vec(), [n, 3]), &train);
        let plain = time(budget, || {
            let _ = field.sdf(batch(), &pose).mean().backward();
        });
        let reference = gradient_values(&field, &pose, batch(), GradientMethod::Tangents);
        for method in [GradientMethod::Tangents, CENTRAL] {
            let seconds = time(budget, || {
                let _ = crate::losses::eikonal(field.sdf_gradient(batch(), &pose, method)).backward();
            });
            let error = disagreement(&gradient_values(&field, &pose, batch(), method), &reference);
            rows.push(Row {
                task: "Eikonal loss, forward + backward".into(),
                method: name(method),
                points: n,
                seconds,
                baseline_seconds: plain,
                error: Some(error),
            });
        }
        let (field, pose, points, _) = field_with_residual(&infer);
        let batch = || Tensor::<2>::from_data(TensorData::new(points[..n * 3].to_vec(), [n, 3]), &infer);
        let plain = time(budget, || {
            std::hint::black_box(field.sdf(batch(), &pose).into_data());
        });
        for method in [GradientMethod::Tangents, CENTRAL] {
            let seconds = time(budget, || {
                std::hint::black_box(field.sdf_gradient(batch(), &pose, method).into_data());
            });
            rows.push(Row { task: "normals, forward only".into(), method: name(method), points: n, seconds, baseline_seconds: plain, error: None });
        }
    }
    if let Some(scene) = scene {
        rows.extend(training_steps(scene, if quick { 3 } else { 12 })?);
    }
    let mut md = String::from(
        "## SDF gradients: forward-mode tangents vs central differences\n\n\
         | task | method | points | time (ms) | vs baseline | max / median disagreement with tangents |\n|---|---|---|---|---|---|\n",
    );
    let mut csv_rows = Vec::new();
    for r in &rows {
        let error = r.error.map(|(max, median)| format!("{max:.2e} / {median:.2e}")).unwrap_or_else(|| "-".into());
        md += &format!("| {} | {} | {} | {:.2} | {:.2}x | {} |\n", r.task, r.method, r.points, r.seconds * 1e3, r.seconds / r.baseline_seconds, error);
        let (max, median) = r.error.map(|(a, b)| (a.to_string(), b.to_string())).unwrap_or_default();
        csv_rows.push([r.task.to_string(), r.method.to_string(), r.points.to_string(), r.seconds.to_string(), r.baseline_seconds.to_string(), max, median]);
    }
    let csv = crate::table::to_csv(&["task", "method", "points", "seconds", "baseline_seconds", "max_disagreement", "median_disagreement"], csv_rows);
    md += "\nBaselines, measured in the same run: a plain SDF step (forward + backward of the mean SDF) over the same points \
           for the Eikonal rows; a plain SDF forward pass for normals; for training steps, a step with tangents. \
           Disagreement: |g - g_tangents| / max(|g_tangents|, 0.1) on a human field with an MLP residual.\n";
    crate::imageio::write_atomic(&out.join("gradients.md"), md.as_bytes()).map_err(|e| e.to_string())?;
    crate::imageio::write_atomic(&out.join("gradients.csv"), csv.as_bytes()).map_err(|e| e.to_string())?;
    let eikonal: Vec<&Row> = rows.iter().filter(|r| r.task.starts_with("Eikonal")).collect();
    let series = [GradientMethod::Tangents, CENTRAL]
        .iter()
        .map(|m| Series {
            name: name(*m),
            points: eikonal.iter().filter(|r| r.method == name(*m)).map(|r| (r.points as f64, r.seconds * 1e3)).collect(),
            lines: true,
        })
        .collect();
    let chart = Chart {
        title: "Eikonal term: time vs points".into(),
        x_label: "points".into(),
        y_label: "time ms".into(),
        log_x: true,
        log_y: true,
        series,
        marks: Vec::new(),
    };
    chart.render(720, 480).save_png(&out.join("gradients.png"))?;
    Ok(md)
}

/// Mean time of whole training steps (default schedule, in the light stage, where shading
/// needs normals and the Eikonal and curvature terms are on) with each method, interleaved so
/// that both see the same model and machine state.
fn training_steps(scene_path: &Path, steps: usize) -> Result<Vec<Row>, String> {
    let scene = crate::scene::Scene::load(scene_path).map_err(|e| e.to_string())?;
    let schedule = crate::schedule::Schedule::load(Path::new("schedules/default.toml")).map_err(|e| e.to_string())?;
    let mut trainer = crate::train::Trainer::new(scene, schedule, crate::backend::Backend::Flex, 1).map_err(|e| e.to_string())?;
    trainer.set_iteration(trainer.schedule.light_from + 300).map_err(|e| e.to_string())?;
    let methods = [GradientMethod::Tangents, CENTRAL];
    let mut seconds = [0.0f64; 2];
    for round in 0..steps + 1 {
        for (k, method) in methods.iter().enumerate() {
            trainer.gradient = *method;
            let stats = trainer.iterate().map_err(|e| e.to_string())?;
            if round > 0 {
                seconds[k] += stats.seconds; // the first round warms caches and allocators
            }
        }
    }
    let points = trainer.schedule.rays_per_batch;
    let task = format!("training step ({}, {} rays)", scene_path.display(), points);
    Ok(methods
        .iter()
        .enumerate()
        .map(|(k, m)| Row {
            task: task.clone(),
            method: name(*m),
            points,
            seconds: seconds[k] / steps as f64,
            baseline_seconds: seconds[0] / steps as f64,
            error: None,
        })
        .collect())
}
