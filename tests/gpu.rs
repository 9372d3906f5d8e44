//! The wgpu backend against the CPU (`cargo test --features gpu --test gpu`; a Vulkan driver
//! must be present: lavapipe, Debian's `mesa-vulkan-drivers`, where there is no GPU).
//!
//! f32 on other hardware sums in another order, so nothing is compared bit for bit. The field's
//! values and gradients must agree to 1e-4 of their largest magnitude: an f32 sum of a few
//! hundred terms differs by about 1e-6 relative between orders, while a wrong row, corner or
//! coefficient in a kernel is an error of order one. A fit's losses are compared with the spread
//! between the two CPU backends (flex and ndarray, which also sum in different orders): the
//! device must stay within ten times it.
#![cfg(feature = "gpu")]

mod common;

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};
use common::TempDir;
use glam::DVec3;
use std::path::Path;
use umbra::backend::Backend;
use umbra::field::{AvatarField, FieldConfig, PoseTensors};
use umbra::random::Stream;
use umbra::schedule::Schedule;
use umbra::skeleton::MotionIncrement;
use umbra::synth::character::{Character, Kind};
use umbra::synth::{TestKind, TrainingLight};
use umbra::train::Trainer;

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
}

/// The largest difference between `a` and `b` against the largest magnitude in `b`.
fn relative_gap(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
    let worst = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(scale > 0.0, "nothing to compare: all zeros");
    worst / scale
}

/// A grid field with busy features on the walking human, made on the CPU.
fn busy_field(character: &Character, pose: &umbra::skeleton::Pose) -> AvatarField {
    let (lo, hi) = pose.bounds(&character.skeleton);
    let config = FieldConfig::with_grid(character.skeleton.bones.iter().map(|b| b.length as f32).collect(), (hi - lo).length() as f32);
    let device = Backend::Flex.device();
    let mut field = config.init(&device, 7);
    let mut stream = Stream::new(3, 1, 0);
    let grid = field.grid.as_mut().unwrap();
    let [rows, features] = grid.table.val().dims();
    let table: Vec<f32> = (0..rows * features).map(|_| (stream.uniform() * 2.0 - 1.0) as f32 * 0.5).collect();
    grid.table = Param::from_tensor(Tensor::from_data(TensorData::new(table, [rows, features]), &device));
    field
}

/// On one device: the SDF of `points` carrying a motion increment, weighted and summed; the
/// SDF, the table's and the increment's gradients, the SDF's spatial gradient (the planned
/// tangents) and the SDF looked up without gradients (the fused host lookup).
fn field_outputs(field: &AvatarField, character: &Character, pose: &umbra::skeleton::Pose, points: &[DVec3], device: &Device) -> Vec<(&'static str, Vec<f32>)> {
    let field = field.clone().fork(device);
    let mut tensors = PoseTensors::new(pose, &character.skeleton, device);
    tensors.motion = Some(MotionIncrement::new(&character.skeleton, pose, device));
    let flat: Vec<f32> = points.iter().flat_map(|p| p.as_vec3().to_array()).collect();
    let input = || Tensor::<2>::from_data(TensorData::new(flat.clone(), [points.len(), 3]), device);
    let mut stream = Stream::new(4, 4, 0);
    let w: Vec<f32> = (0..points.len()).map(|_| (stream.uniform() * 2.0 - 1.0) as f32).collect();
    let weights = Tensor::<1>::from_data(TensorData::new(w, [points.len()]), device);
    let sdf = field.decode(input(), &tensors).sdf;
    let grads = (sdf.clone() * weights).sum().backward();
    let table = field.grid.as_ref().unwrap().table.grad(&grads).expect("the table is in the graph");
    let increment = tensors.motion.as_ref().unwrap().leaf.grad(&grads).expect("the increment is in the graph");
    let plain = PoseTensors::new(pose, &character.skeleton, device);
    let normal = field.sdf_gradient(input(), &plain, umbra::field::GRADIENT);
    let still = field.valid().decode(input().inner(), &plain).sdf;
    vec![
        ("sdf", values(sdf.inner())),
        ("table gradient", values(table)),
        ("motion gradient", values(increment)),
        ("sdf gradient", values(normal.inner())),
        ("sdf without gradients", values(still)),
    ]
}

/// The grid lookup's ops on the device (forward, table backward, the carried shift's
/// backward, the tangents, the lookup without gradients) give the CPU's values and gradients.
#[test]
fn the_field_on_the_device_is_the_field_on_the_cpu() {
    let character = Character::new(Kind::Human);
    let pose = character.pose(0.3, 0.2, DVec3::new(0.05, 0.0, -0.1));
    let field = busy_field(&character, &pose);
    let mut stream = Stream::new(9, 2, 0);
    let points: Vec<DVec3> = (0..character.skeleton.len() * 16)
        .map(|k| {
            let b = k % character.skeleton.len();
            let along = character.skeleton.bones[b].length * stream.uniform();
            let off = DVec3::new(stream.uniform() - 0.5, 0.0, stream.uniform() - 0.5) * 0.12;
            pose.to_world(b, DVec3::new(off.x, along, off.z))
        })
        .collect();
    let cpu = field_outputs(&field, &character, &pose, &points, &Backend::Flex.device());
    let gpu = field_outputs(&field, &character, &pose, &points, &Backend::Wgpu.device());
    for ((what, a), (_, b)) in gpu.iter().zip(&cpu) {
        let gap = relative_gap(a, b);
        eprintln!("{what}: the device within {gap:.1e} of the largest value");
        assert!(gap < 1e-4, "{what}: the device differs from the CPU by {gap} of the largest value");
    }
}

/// Each step's total loss over a short fit of a tiny sunlit scene on `backend`.
#[allow(deprecated)] // burn-ndarray stays our --backend ndarray
fn losses(scene: &Path, backend: Backend) -> Vec<f64> {
    let schedule = Schedule::parse(&common::QUICK.replace("iterations = 60", "iterations = 8"), Path::new("quick.toml")).unwrap();
    let scene = umbra::scene::Scene::load(scene).unwrap();
    let mut trainer = Trainer::new(scene, schedule, backend, 1).unwrap();
    (0..8).map(|_| trainer.iterate().unwrap().total).collect()
}

/// A short fit on the device follows the CPU's: each step's loss within ten times the gap
/// between the two CPU backends (or 1e-5 of the loss where they agree closer than that).
#[test]
#[allow(deprecated)] // burn-ndarray stays our --backend ndarray
fn a_short_fit_on_the_device_follows_the_cpu() {
    let dir = TempDir::new("gpu-fit");
    let scene = common::tiny_synth(dir.path(), TrainingLight::Sun, 32, 4, vec![TestKind::Poses], 5);
    let flex = losses(&scene, Backend::Flex);
    let ndarray = losses(&scene, Backend::Ndarray);
    let wgpu = losses(&scene, Backend::Wgpu);
    assert!(flex.last() < flex.first(), "the loss falls: {flex:?}");
    eprintln!("flex {flex:?}\nndarray {ndarray:?}\nwgpu {wgpu:?}");
    for (step, ((f, n), w)) in flex.iter().zip(&ndarray).zip(&wgpu).enumerate() {
        let bound = (10.0 * (f - n).abs()).max(1e-5 * f.abs());
        assert!((w - f).abs() <= bound, "step {step}: wgpu {w}, flex {f}, ndarray {n} (bound {bound})\nflex {flex:?}\nndarray {ndarray:?}\nwgpu {wgpu:?}");
    }
}

/// A step on the device says what the device's allocator holds: at least the parameters it
/// trains, with their Adam moments once a step has taken them (three copies); a step on the CPU
/// says nothing, its memory being the process's (`fit.json` keeps both).
#[test]
fn a_step_on_the_device_reports_the_device_memory() {
    let dir = TempDir::new("gpu-memory");
    let scene = common::tiny_synth(dir.path(), TrainingLight::Sun, 32, 4, vec![TestKind::Poses], 5);
    let schedule = Schedule::parse(&common::QUICK.replace("iterations = 60", "iterations = 2"), Path::new("quick.toml")).unwrap();
    let scene = umbra::scene::Scene::load(&scene).unwrap();
    let mut device = Trainer::new(scene.clone(), schedule.clone(), Backend::Wgpu, 1).unwrap();
    let parameters = device.model().unwrap().num_params() as u64;
    let held: Vec<u64> = (0..2).map(|_| device.iterate().unwrap().device_memory_bytes.expect("the device reports its memory")).collect();
    eprintln!("{parameters} parameters; the device held {held:?} bytes after each step");
    assert!(held.iter().all(|&bytes| bytes >= 3 * 4 * parameters), "{held:?} bytes hold fewer than three f32 copies of {parameters} parameters");
    let mut cpu = Trainer::new(scene, schedule, Backend::Flex, 1).unwrap();
    assert_eq!(cpu.iterate().unwrap().device_memory_bytes, None);
}

/// The check after each update, that no parameter went NaN or infinite, sums the parameters on
/// the device and reads one number back; it finds them there as on the CPU.
#[test]
fn a_parameter_gone_nan_is_found_on_the_device() {
    use burn::nn::{Linear, LinearConfig};
    use umbra::avatar::first_non_finite;
    let device = Backend::Wgpu.device();
    let layer: Linear = LinearConfig::new(2, 2).init(&device);
    assert_eq!(first_non_finite(&layer), None);
    for bad in [f32::NAN, f32::INFINITY] {
        let mut broken = layer.clone();
        broken.weight = Param::from_tensor(Tensor::from_data(TensorData::new(vec![0.5, bad, 1e30, -2.0], [2, 2]), &device));
        assert_eq!(first_non_finite(&broken).as_deref(), Some("weight"), "{bad}");
    }
}

/// The peak signal-to-noise ratio (dB) of one PNG against another.
fn psnr(a: &Path, b: &Path) -> f64 {
    let (a, b) = (image::open(a).unwrap().to_rgb8(), image::open(b).unwrap().to_rgb8());
    assert_eq!(a.dimensions(), b.dimensions());
    let sum: f64 = a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| (*x as f64 - *y as f64).powi(2)).sum();
    let mse = sum / a.as_raw().len() as f64 / 255.0 / 255.0;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

/// `umbra fit`, `eval` and `relight` with `--backend wgpu` end to end; the device's evaluation
/// of the run renders what the CPU's does.
#[test]
fn a_fit_an_evaluation_and_a_relight_run_on_the_device() {
    let dir = TempDir::new("gpu-cli");
    let scene = common::tiny_synth(dir.path(), TrainingLight::Sun, 24, 3, vec![TestKind::Poses], 9);
    let cwd = std::env::current_dir().unwrap();
    let run = dir.path().join("run");
    let (scene, run_str) = (scene.to_str().unwrap(), run.to_str().unwrap());
    common::succeeds(&cwd, &["fit", scene, "--out", run_str, "--iterations", "4", "--no-eval", "--backend", "wgpu"]);
    assert!(run.join("checkpoint/state.json").is_file() || run.join("fit.json").is_file(), "the fit wrote its run");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("fit.json")).unwrap()).unwrap();
    assert!(
        report["peak_device_memory_bytes"].as_u64().is_some_and(|bytes| bytes > 0),
        "fit.json says what the device held: {}",
        report["peak_device_memory_bytes"]
    );
    common::succeeds(&cwd, &["eval", run_str, "--backend", "wgpu"]);
    let device =
        std::fs::read_dir(run.join("renders")).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "png")).collect::<Vec<_>>();
    assert!(!device.is_empty(), "the evaluation wrote renders");
    let copies = dir.path().join("device-renders");
    std::fs::create_dir_all(&copies).unwrap();
    for p in &device {
        std::fs::copy(p, copies.join(p.file_name().unwrap())).unwrap();
    }
    common::succeeds(&cwd, &["eval", run_str, "--backend", "flex"]);
    for p in &device {
        let db = psnr(&copies.join(p.file_name().unwrap()), p);
        eprintln!("{}: the device's render {db:.1} dB from the CPU's", p.display());
        assert!(db > 40.0, "{}: the device's render is {db:.1} dB from the CPU's", p.display());
    }
    let relit = dir.path().join("relit");
    common::succeeds(&cwd, &["relight", run_str, "--light", "sun", "--out", relit.to_str().unwrap(), "--backend", "wgpu"]);
    assert!(std::fs::read_dir(&relit).unwrap().any(|e| e.unwrap().path().extension().is_some_and(|e| e == "png")), "the relight wrote images");
}

/// Asked for a device the machine does not have, a fit is refused before it writes anything,
/// with a reason and a hint, not a crash.
#[test]
fn a_missing_device_is_refused_before_anything_is_written() {
    let dir = TempDir::new("gpu-missing");
    let scene = common::tiny_synth(dir.path(), TrainingLight::Sun, 24, 3, vec![TestKind::Poses], 9);
    let run = dir.path().join("run");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_umbra"))
        .args(["fit", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "2", "--no-eval", "--backend", "wgpu"])
        .env("CUBECL_WGPU_DEFAULT_DEVICE", "DiscreteGpu(99)")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("error: the wgpu backend found no usable device") && stderr.contains("mesa-vulkan-drivers"), "{stderr}");
    assert!(!run.exists(), "nothing written");
}

/// A lookup on the device is planned and summed there: with tangents, carrying a motion
/// increment and without gradients, no values come down to the host. The composite of the
/// host's plan, for contrast, reads each lookup's points.
#[test]
fn a_lookup_on_the_device_reads_nothing_back() {
    use umbra::field::grid::Route;
    let character = Character::new(Kind::Human);
    let pose = character.pose(0.3, 0.2, DVec3::new(0.05, 0.0, -0.1));
    let device = Backend::Wgpu.device();
    let field = busy_field(&character, &pose).fork(&device);
    let skinning = field.config.skinning();
    let mut tensors = PoseTensors::new(&pose, &character.skeleton, &device);
    tensors.motion = Some(MotionIncrement::new(&character.skeleton, &pose, &device));
    let points = Tensor::<2>::from_data(TensorData::new((0..90).map(|k| ((k * 37) % 100) as f32 * 0.01 - 0.5).collect::<Vec<_>>(), [30, 3]), &device);
    let reads = |grid: &umbra::field::grid::FeatureGrid| {
        let before = umbra::backend::reads_to_host();
        let _ = grid.encode(points.clone(), &tensors.frames, skinning, true, None);
        let _ = grid.encode(points.clone(), &tensors.frames, skinning, false, tensors.motion.as_ref());
        let _ = grid.clone().valid().encode(points.clone().inner(), &tensors.frames, skinning, false, None);
        umbra::backend::reads_to_host() - before
    };
    let mut grid = field.grid.clone().unwrap();
    assert_eq!(reads(&grid), 0, "the device's lookups read nothing back");
    grid.route = Route::Composite;
    assert!(reads(&grid) >= 3, "the host's plan reads each lookup's points");
}

/// A default fit's step on the device waits on the host once, after the update: for the step's
/// losses, the parameters' check, the light and the Gaussians that bound the next batch's rays. The first step reads the Gaussians
/// once more, as nothing has read them before it. The lookups, the surface search and the
/// differentiable pass read nothing back.
#[test]
fn a_step_on_the_device_reads_once() {
    let dir = TempDir::new("gpu-reads");
    let scene = common::tiny_synth(dir.path(), TrainingLight::Sun, 32, 4, vec![TestKind::Poses], 5);
    let schedule = Schedule::load(Path::new("schedules/default.toml")).unwrap();
    let scene = umbra::scene::Scene::load(&scene).unwrap();
    let mut trainer = Trainer::new(scene, schedule, Backend::Wgpu, 1).unwrap();
    for step in 0..4 {
        let before = umbra::backend::reads_to_host();
        trainer.iterate().unwrap();
        assert_eq!(umbra::backend::reads_to_host() - before, if step == 0 { 2 } else { 1 }, "step {step}");
    }
}
