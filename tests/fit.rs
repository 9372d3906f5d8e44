//! A few seconds of fitting on a tiny synthetic scene: the loss goes down, the light moves
//! toward the truth, a resumed fit continues exactly, and bad schedules are refused.

mod common;

use common::TempDir;
use std::path::Path;
use umbra::backend::Backend;
use umbra::fit::FitOptions;
use umbra::schedule::Schedule;
use umbra::synth::{TestKind, TrainingLight};
use umbra::train::Trainer;

fn tiny_scene(dir: &Path, light: TrainingLight) -> std::path::PathBuf {
    tiny_scene_with_tests(dir, light, vec![TestKind::Poses])
}

fn tiny_scene_with_tests(dir: &Path, light: TrainingLight, test: Vec<TestKind>) -> std::path::PathBuf {
    common::tiny_synth(dir, light, 32, 4, test, 5)
}

/// Options for a fit of `scene` into `out` with the given schedule file, no evaluation.
fn fit_options(scene: &Path, out: std::path::PathBuf, schedule: &Path, iterations: Option<usize>, seed: u64, resume: bool) -> FitOptions {
    FitOptions {
        scene: scene.to_path_buf(),
        out,
        schedule: schedule.to_path_buf(),
        iterations,
        seed,
        resume,
        force: false,
        // The resume test stops a fit early by asking for fewer iterations, then continues it.
        force_schedule: resume,
        backend: Backend::Flex,
        evaluate: false,
    }
}

use common::QUICK;

/// A temp folder holding a tiny scene lit by `light` and `quick.toml`, the quick schedule cut
/// to `iterations`.
fn quick_setup(tag: &str, light: TrainingLight, iterations: usize) -> (TempDir, std::path::PathBuf, std::path::PathBuf) {
    let dir = TempDir::new(tag);
    let scene_path = tiny_scene(dir.path(), light);
    let schedule_path = dir.path().join("quick.toml");
    std::fs::write(&schedule_path, QUICK.replace("iterations = 60", &format!("iterations = {iterations}"))).unwrap();
    (dir, scene_path, schedule_path)
}

fn angle_to(direction: &serde_json::Value, truth: glam::DVec3) -> f64 {
    let d = glam::DVec3::new(direction[0].as_f64().unwrap(), direction[1].as_f64().unwrap(), direction[2].as_f64().unwrap()).normalize();
    d.dot(truth.normalize()).clamp(-1.0, 1.0).acos().to_degrees()
}

#[test]
fn a_short_fit_lowers_the_loss_and_turns_the_light_toward_the_truth() {
    let dir = TempDir::new("fit");
    let scene_path = tiny_scene(dir.path(), TrainingLight::Sun);
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let schedule = Schedule::parse(QUICK, Path::new("quick.toml")).unwrap();
    let mut trainer = Trainer::new(scene, schedule, Backend::Flex, 1).unwrap();
    let truth = glam::DVec3::new(0.45, 0.8, 0.4);
    let before = angle_to(&trainer.model().unwrap().light.report()["direction"], truth);
    let mut first = Vec::new();
    let mut last = Vec::new();
    for i in 0..60 {
        let stats = trainer.iterate().unwrap();
        if i < 10 {
            first.push(stats.total);
        } else if i >= 50 {
            last.push(stats.total);
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(mean(&last) < 0.8 * mean(&first), "loss {} -> {}", mean(&first), mean(&last));
    let after = angle_to(&trainer.model().unwrap().light.report()["direction"], truth);
    eprintln!("loss {:.4} -> {:.4}, light error {before:.1} -> {after:.1} degrees", mean(&first), mean(&last));
    assert!(after < 0.5 * before, "light direction error {before:.1} -> {after:.1} degrees");
}

/// When the light starts to be fitted, the sun search scores directions on surface samples and
/// the light starts from the best; however hard the light's steps push afterwards (a learning
/// rate 50x the default, which does reach the cone's edge), the direction stays within the
/// cone around that start.
#[test]
fn the_sun_search_seeds_the_light_and_its_cone_holds_it() {
    let dir = TempDir::new("sun-search");
    let scene_path = tiny_scene(dir.path(), TrainingLight::Sun);
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let text = QUICK.replace("light_from = 0", "light_from = 40\nsun_search = 64").replace("light = 5e-2", "light = 1.0");
    let schedule = Schedule::parse(&text, Path::new("search.toml")).unwrap();
    let mut trainer = Trainer::new(scene, schedule, Backend::Flex, 1).unwrap();
    for _ in 0..40 {
        trainer.iterate().unwrap();
    }
    assert!(trainer.searches[0].is_none(), "the search waits for light_from");
    trainer.iterate().unwrap();
    let report = trainer.searches[0].clone().expect("the search ran at light_from");
    assert!(report.samples > 50 && report.candidates == 64 + 64, "{report:?}");
    let start = glam::DVec3::from_array(report.best.direction);
    let cone = (4.0f64 / 64.0).sqrt().to_degrees() * umbra::train::SUN_CONE_SPACINGS;
    let mut widest: f64 = 0.0;
    for _ in 0..15 {
        trainer.iterate().unwrap();
        let now = angle_to(&trainer.model().unwrap().light.report()["direction"], start);
        assert!(now <= cone + 1e-3, "the direction left the cone: {now:.2} > {cone:.2} degrees");
        widest = widest.max(now);
    }
    assert!(widest > 0.5 * cone, "the steps pressed the direction toward the cone's edge ({widest:.2} of {cone:.2} degrees)");
}

#[test]
fn resume_continues_where_the_fit_stopped_bit_for_bit_with_either_field() {
    for kind in ["mlp", "grid"] {
        let (dir, scene_path, schedule_path) = quick_setup(&format!("resume-{kind}"), TrainingLight::Sun, 40);
        // Hierarchical sampling too, so the coarse pass and its draws are part of what resumes;
        // the Gaussians' rebinding at 5 and 10, so their bones are part of it too;
        // and the sun search at iteration 10 with a light rate that presses the direction
        // against the search's cone, so the checkpoint at 20 must carry the cone; and the
        // field's average from 12, so the checkpoint at 20 holds the average and the last
        // step's parameters apart; and a third of the rays drawn by the error maps, so the
        // checkpoint must carry them.
        let text = std::fs::read_to_string(&schedule_path)
            .unwrap()
            .replace("samples_per_ray = 16", "samples_per_ray = 8\nfine_samples_per_ray = 8\nerror_rays = 1.0")
            .replace("light_from = 0", "light_from = 10\nsun_search = 512\nrebind_every = 5\nfield_lr_decay_from = 12\nfield_average_half_life = 4")
            .replace("light = 5e-2", "light = 2.0");
        std::fs::write(&schedule_path, format!("{text}\n[field]\nkind = \"{kind}\"\n")).unwrap();
        let options = |out: &str, iterations: usize, resume: bool| fit_options(&scene_path, dir.path().join(out), &schedule_path, Some(iterations), 3, resume);
        let straight = serde_json::to_value(umbra::fit::fit(&options("straight", 40, false), |_| {}).unwrap()).unwrap();
        umbra::fit::fit(&options("resumed", 20, false), |_| {}).unwrap();
        // A second fit into the same folder without --resume is refused.
        let err = umbra::fit::fit(&options("resumed", 40, false), |_| {}).unwrap_err();
        assert!(err.to_string().contains("--resume"), "{err}");
        let resumed = serde_json::to_value(umbra::fit::fit(&options("resumed", 40, true), |_| {}).unwrap()).unwrap();
        let a = std::fs::read_to_string(dir.path().join("straight/losses.csv")).unwrap();
        let b = std::fs::read_to_string(dir.path().join("resumed/losses.csv")).unwrap();
        let column = |text: &str| text.lines().skip(1).map(|l| l.split(',').nth(1).unwrap().parse::<f64>().unwrap()).collect::<Vec<_>>();
        let (ta, tb) = (column(&a), column(&b));
        assert_eq!(ta.len(), 40);
        assert_eq!(tb.len(), 40);
        // Bit for bit: every loss to the digits written, and the final Gaussians (serde_json
        // writes each f64 so that it reads back exactly).
        for i in 0..40 {
            assert!(ta[i] == tb[i], "{kind}, iteration {i}: {} vs {}", ta[i], tb[i]);
        }
        let gaussians = |run: &str| std::fs::read(dir.path().join(run).join("gaussians.json")).unwrap();
        assert!(gaussians("straight") == gaussians("resumed"), "{kind}: the resumed fit's Gaussians differ");
        assert_eq!(straight["light"]["direction"], resumed["light"]["direction"], "{kind}");
        // The light's path: a point after every step of a 40-step fit, the resumed run's first
        // half read back from its losses.csv (7 decimals), ending where the light ended.
        let path = |report: &serde_json::Value| report["light_path"].as_array().cloned().unwrap_or_default();
        let (pa, pb) = (path(&straight), path(&resumed));
        assert_eq!(pa.len(), 40, "{kind}");
        assert_eq!(pb.len(), 40, "{kind}");
        for (p, q) in pa.iter().zip(&pb) {
            assert_eq!(p["after_iteration"], q["after_iteration"], "{kind}");
            for k in 0..3 {
                let (x, y) = (p["direction"][k].as_f64().unwrap(), q["direction"][k].as_f64().unwrap());
                assert!((x - y).abs() < 1e-6, "{kind}: {p} vs {q}");
            }
            assert!(p["error_against_scene"]["direction_degrees"].as_f64().is_some_and(|d| (0.0..=180.0).contains(&d)), "{kind}: {p}");
        }
        assert_eq!(pa[39]["direction"], straight["light"]["direction"], "{kind}: the path ends at the fitted light");
        assert_ne!(pa[9]["direction"], pa[10]["direction"], "{kind}: the search moved the light after step 10");
        // The checkpoint holds the field's average as the model and the last step's beside it.
        let checkpoint = dir.path().join("resumed/checkpoint");
        assert!(checkpoint.join("training-model.bpk").is_file(), "{kind}: no training model beside the average");
        // The run renders from its checkpoint and schedule copy, whatever the field, and the
        // resumed fit's average renders as the straight fit's does.
        let evaluation = umbra::scoring::render_run(&dir.path().join("resumed"), None, Backend::Flex, |_| {}).unwrap();
        let psnr = evaluation["novel_pose_foreground_psnr"].as_f64().unwrap_or(f64::NAN);
        assert!(psnr.is_finite() && psnr > 5.0, "{kind}: {psnr}");
        let straight_evaluation = umbra::scoring::render_run(&dir.path().join("straight"), None, Backend::Flex, |_| {}).unwrap();
        assert_eq!(straight_evaluation["novel_pose_foreground_psnr"], evaluation["novel_pose_foreground_psnr"], "{kind}");
        assert_eq!(straight_evaluation["novel_pose_ssim"], evaluation["novel_pose_ssim"], "{kind}");
    }
}

#[test]
fn uniform_scenes_skip_the_light_and_refuse_a_light_fitting_schedule() {
    let (dir, scene_path, schedule_path) = quick_setup("uniform", TrainingLight::Uniform, 3);
    let options = fit_options(&scene_path, dir.path().join("run"), &schedule_path, None, 0, false);
    let report = serde_json::to_value(umbra::fit::fit(&options, |_| {}).unwrap()).unwrap();
    assert_eq!(report["light"]["type"], "uniform");
    // fit.json is written and read by one type: what reads back is what the fit returned.
    let read = umbra::fit_report::FitReport::read(&dir.path().join("run/fit.json")).unwrap();
    assert_eq!(serde_json::to_value(read).unwrap(), report);
    let stages = report["stages"].as_array().unwrap();
    let light_stage = stages.iter().find(|s| s["name"].as_str().unwrap().starts_with("light")).unwrap();
    assert_eq!(light_stage["ran"], false);
    assert!(light_stage["skipped_because"].as_str().unwrap().contains("uniformly lit"));
    // The colour is still fitted: every second of training is in a stage.
    let rgb = stages.iter().find(|s| s["name"] == "RGB fitting").expect("the RGB stage");
    assert_eq!(rgb["ran"], true);
    let staged: f64 = stages.iter().filter_map(|s| s["seconds"].as_f64()).sum();
    let (header, rows) = umbra::table::read_csv(&std::fs::read_to_string(dir.path().join("run/losses.csv")).unwrap()).unwrap();
    let column = header.iter().position(|h| h == "seconds").unwrap();
    let stepped: f64 = rows.iter().map(|r| r[column].parse::<f64>().unwrap()).sum();
    // losses.csv keeps each step's seconds to 4 decimals.
    assert!((staged - stepped).abs() <= 1e-4 * rows.len() as f64, "{staged} s in stages, {stepped} s of steps");

    std::fs::write(&schedule_path, format!("light = \"fit\"\n{QUICK}")).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_umbra"))
        .args(["fit", scene_path.to_str().unwrap(), "--out", dir.path().join("run2").to_str().unwrap(), "--schedule", schedule_path.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("quick.toml: light:") && stderr.contains("uniformly lit"), "{stderr}");
    assert!(!dir.path().join("run2/fit.json").exists(), "nothing written");
}

#[test]
fn point_lit_scenes_fit_a_light_position_and_ndarray_runs_the_same_step() {
    let dir = TempDir::new("point");
    let scene_path = tiny_scene(dir.path(), TrainingLight::Point);
    let schedule = Schedule::parse(&QUICK.replace("iterations = 60", "iterations = 4"), Path::new("quick.toml")).unwrap();
    for backend in [Backend::Flex, Backend::Ndarray] {
        let scene = umbra::scene::Scene::load(&scene_path).unwrap();
        let mut trainer = Trainer::new(scene, schedule.clone(), backend, 1).unwrap();
        let before = trainer.model().unwrap().light.report();
        assert_eq!(before["type"], "point");
        for _ in 0..4 {
            let stats = trainer.iterate().unwrap();
            assert!(stats.total.is_finite() && stats.terms.contains_key("rgb"), "{backend:?}: {stats:?}");
        }
        let after = trainer.model().unwrap().light.report();
        assert_ne!(before["position"], after["position"], "{backend:?}: the light position learns");
    }
}

/// A copy of `param` with its first value replaced by NaN.
fn poisoned<const D: usize>(param: &burn::module::Param<burn::tensor::Tensor<D>>) -> burn::module::Param<burn::tensor::Tensor<D>> {
    let value = param.val();
    let shape = value.shape();
    let mut data = value.into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
    data[0] = f32::NAN;
    burn::module::Param::from_tensor(burn::tensor::Tensor::from_data(burn::tensor::TensorData::new(data, shape), &trainer_device()))
}

fn trainer_device() -> burn::tensor::Device {
    Backend::Flex.device()
}

#[test]
fn a_non_finite_parameter_or_loss_stops_the_fit_and_keeps_the_last_good_checkpoint() {
    use burn::module::Module;
    let dir = TempDir::new("nonfinite");
    let scene_path = tiny_scene(dir.path(), TrainingLight::Sun);
    let schedule =
        Schedule::parse(&QUICK.replace("iterations = 60", "iterations = 8").replace("checkpoint_every = 20", "checkpoint_every = 2"), Path::new("quick.toml"))
            .unwrap();

    // A parameter this step's losses do not read (a sun has no intensity) is still checked.
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let mut trainer = Trainer::new(scene, schedule.clone(), Backend::Flex, 1).unwrap();
    trainer.iterate().unwrap();
    let model = trainer.model_mut().unwrap();
    model.light.log_intensity = poisoned(&model.light.log_intensity);
    let err = trainer.iterate().unwrap_err().to_string();
    assert!(err.contains("iteration 1") && err.contains("light.log_intensity"), "{err}");

    // A fit whose loss turns NaN stops with an error that points at the checkpoint it kept.
    let schedule_path = dir.path().join("quick.toml");
    std::fs::write(&schedule_path, QUICK.replace("iterations = 60", "iterations = 8").replace("checkpoint_every = 20", "checkpoint_every = 2")).unwrap();
    let out = dir.path().join("run");
    umbra::fit::fit(&fit_options(&scene_path, out.clone(), &schedule_path, Some(4), 2, false), |_| {}).unwrap();
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let mut model = Trainer::new(scene, schedule, Backend::Flex, 2).unwrap().model().unwrap().clone();
    model.light.vector = poisoned(&model.light.vector);
    let bpk = out.join("checkpoint/model.bpk");
    model.save_file(&bpk).unwrap();
    let before = std::fs::read(&bpk).unwrap();
    // The poisoned model replaces the saved one on purpose: its state must not list the old
    // checksum (a checkpoint from before checksums were recorded is loaded unchecked).
    let state_path = out.join("checkpoint/state.json");
    let mut state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state_path).unwrap()).unwrap();
    common::without_checksums(&state_path, &mut state);
    std::fs::remove_file(out.join("fit.json")).unwrap();
    let err = umbra::fit::fit(&fit_options(&scene_path, out.clone(), &schedule_path, Some(8), 2, true), |_| {}).unwrap_err().to_string();
    assert!(err.contains("diverged at iteration 4") && err.contains("loss is not finite"), "{err}");
    assert!(err.contains("checkpoint (iteration 4) is kept in") && err.contains("checkpoint"), "{err}");
    assert_eq!(std::fs::read(&bpk).unwrap(), before, "the checkpoint is not overwritten");
    assert!(!out.join("fit.json").exists(), "no report for a diverged fit");
}

#[test]
fn evaluation_renders_and_scores_every_test_image_and_umbra_render_repeats_it() {
    let dir = TempDir::new("evaluate");
    let scene_path = tiny_scene_with_tests(dir.path(), TrainingLight::Sun, vec![TestKind::Poses, TestKind::Views, TestKind::Relight]);
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let tests: Vec<_> = scene.views_in(umbra::scene::Split::Test).collect();
    let schedule_path = dir.path().join("quick.toml");
    std::fs::write(&schedule_path, QUICK.replace("iterations = 60", "iterations = 10")).unwrap();
    let out = dir.path().join("run");
    let mut options = fit_options(&scene_path, out.clone(), &schedule_path, None, 1, false);
    options.evaluate = true;
    let report = serde_json::to_value(umbra::fit::fit(&options, |_| {}).unwrap()).unwrap();
    // The prior is capped exactly where the root's grids reach loose clothing.
    let field = &report["field"];
    assert!(field.as_object().is_some_and(|f| f.contains_key("prior_capped_at") && f.contains_key("root_grids_reach_loose_body")), "{field}");
    assert_eq!(field["prior_capped_at"].is_null(), field["root_grids_reach_loose_body"].is_null(), "{field}");
    let evaluation = &report["evaluation"];
    for group in ["novel_pose", "novel_view", "relit", "albedo"] {
        let psnr = evaluation[format!("{group}_psnr")].as_f64().unwrap_or(f64::NAN);
        assert!(psnr.is_finite() && psnr > 5.0, "{group}: {psnr}");
        // The foreground is a fraction of the image and the background is right almost
        // everywhere, so the foreground scores lower.
        let foreground = evaluation[format!("{group}_foreground_psnr")].as_f64().unwrap_or(f64::NAN);
        assert!(foreground.is_finite() && foreground < psnr, "{group}: foreground {foreground} vs {psnr}");
        let ssim = evaluation[format!("{group}_ssim")].as_f64().unwrap_or(f64::NAN);
        assert!(ssim > 0.0 && ssim < 1.0, "{group}: SSIM {ssim}");
    }
    let rows = evaluation["images"].as_array().unwrap();
    assert_eq!(rows.len(), tests.len());
    let lights: std::collections::BTreeSet<&str> = rows.iter().filter(|r| r["relit"] == true).map(|r| r["light"].as_str().unwrap()).collect();
    assert_eq!(lights.into_iter().collect::<Vec<_>>(), ["lamp", "sky", "sun2"], "every kind of relighting light is rendered");
    for row in rows {
        let png = out.join("renders").join(row["image"].as_str().unwrap());
        assert!(png.exists(), "{}", png.display());
    }
    let csv = std::fs::read_to_string(out.join("renders/metrics.csv")).unwrap();
    assert_eq!(csv.lines().count(), tests.len() + 1);
    assert!(std::fs::read_to_string(out.join("renders/metrics.md")).unwrap().contains("| relit |"));

    // `umbra render` rebuilds the model from the run's checkpoint and gets the same scores.
    std::fs::remove_dir_all(out.join("renders")).unwrap();
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_umbra")).args(["render", out.to_str().unwrap()]).output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let again = std::fs::read_to_string(out.join("renders/metrics.csv")).unwrap();
    assert_eq!(again, csv);

    // `umbra relight` by a light of the scene and by a light file: one PNG per view and a sheet.
    let cli = |args: &[&str]| std::process::Command::new(env!("CARGO_BIN_EXE_umbra")).args(args).output().unwrap();
    let run = cli(&["relight", out.to_str().unwrap(), "--light", "sky", "--camera", "0,1", "--frame", "0,2", "--samples", "32"]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let sky = out.join("relit/sky");
    for name in ["c00_f0000.png", "c01_f0002.png", "sheet.png"] {
        assert!(sky.join(name).exists(), "{name}");
    }
    // The four views, the sheet and the manifest of what relight wrote.
    assert_eq!(std::fs::read_dir(&sky).unwrap().count(), 6);
    assert!(sky.join(umbra::written::MANIFEST).is_file());
    let lamp = dir.path().join("lamp.json");
    std::fs::write(&lamp, r#"{"type": "point", "position": [1.0, 2.0, 1.5], "intensity": [5, 5, 5]}"#).unwrap();
    let run = cli(&["relight", out.to_str().unwrap(), "--light", lamp.to_str().unwrap(), "--camera", "0", "--frame", "1"]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    // The scene has a light named lamp too: the file's renders get a folder of their own.
    assert!(out.join("relit/file-lamp/c00_f0001.png").exists());
    // Through a visibility basis: the same views, and basis.md with its times and the first
    // view's scores against the direct estimator (the basis is a quadrature of the same
    // integral, so they agree closely; `basis` tests the maths against dense quadrature).
    let run = cli(&[
        "relight",
        out.to_str().unwrap(),
        "--light",
        "sky",
        "--camera",
        "0,1",
        "--frame",
        "0",
        "--basis",
        "256",
        "--out",
        dir.path().join("basis").to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let table = std::fs::read_to_string(dir.path().join("basis/basis.md")).unwrap();
    assert!(table.contains("256 directions") && table.contains("| c00 f0000 |") && table.contains("| c01 f0000 |"), "{table}");
    let against: Vec<f64> =
        table.lines().find(|l| l.starts_with("| c00 f0000 |")).unwrap().split('|').nth(5).unwrap().split(['/', ' ']).filter_map(|v| v.parse().ok()).collect();
    assert!(against.len() == 3 && against[0] > 30.0 && against[2] > 0.98, "{table}");
    for directions in ["0", "100000000"] {
        // No direction, or more than a basis may hold in memory: refused before any work.
        let run = cli(&["relight", out.to_str().unwrap(), "--light", "sky", "--basis", directions, "--out", dir.path().join("refused").to_str().unwrap()]);
        assert!(!run.status.success() && String::from_utf8_lossy(&run.stderr).contains("--basis"), "{}", String::from_utf8_lossy(&run.stderr));
        assert!(!dir.path().join("refused").exists(), "nothing written");
    }
    // A turntable: N views around the body in the chosen frame, and an animated PNG of them.
    let run = cli(&[
        "relight",
        out.to_str().unwrap(),
        "--light",
        "sun2",
        "--orbit",
        "4",
        "--frame",
        "1",
        "--basis",
        "64",
        "--out",
        dir.path().join("orbit").to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    for k in 0..4 {
        assert!(dir.path().join(format!("orbit/orbit{k:03}_f0001.png")).exists());
    }
    let apng = std::fs::read(dir.path().join("orbit/orbit_f0001.png")).unwrap();
    let actl = apng.windows(4).position(|w| w == b"acTL").expect("an animation control chunk");
    assert_eq!(u32::from_be_bytes(apng[actl + 4..actl + 8].try_into().unwrap()), 4, "four frames");
    assert_eq!(apng.windows(4).filter(|w| *w == b"fcTL").count(), 4);
    let run = cli(&["relight", out.to_str().unwrap(), "--light", "sun2", "--orbit", "4", "--camera", "0"]);
    assert!(!run.status.success(), "--orbit renders its own cameras: --camera is refused");
    // `umbra bench render`: a view's seconds under four lights, all threads and one.
    let run = cli(&["bench", "render", "--run", out.to_str().unwrap(), "--quick", "--out", dir.path().join("bench").to_str().unwrap()]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let table = std::fs::read_to_string(dir.path().join("bench/render.md")).unwrap();
    for light in ["fitted light", "a sun", "a point light", "an environment"] {
        assert!(table.lines().any(|l| l.starts_with(&format!("| {light}")) && l.ends_with("x |")), "{table}");
    }
    assert!(dir.path().join("bench/render.png").exists() && table.contains("at once"));
    assert!(table.contains("The view in those 4 lights from one trace"), "{table}");
    // `umbra report`: a self-contained page (images and data inline, nothing fetched) with the
    // relighting panel, and its Markdown twin; a bad camera is refused and changes nothing.
    let run = cli(&["report", out.to_str().unwrap(), "--directions", "64"]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(html.contains("<canvas") && html.contains("id=\"basis\"") && html.contains("expected_mean_srgb8"));
    assert!(!html.contains("http://") && !html.contains("https://") && !html.contains("<script src"), "self-contained");
    assert!(html.matches("data:image/png;base64,").count() >= 2, "the losses and the renders beside the truth are embedded");
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(md.contains("| novel pose |") && md.contains("light direction error") && md.contains("report-relit.png"), "{md}");
    let run = cli(&["report", out.to_str().unwrap(), "--camera", "99"]);
    assert!(!run.status.success() && String::from_utf8_lossy(&run.stderr).contains("--camera 99"));
    assert_eq!(std::fs::read_to_string(out.join("report.html")).unwrap(), html, "a refused report leaves the old one");
    // In a real browser (where Chromium is installed: `apt-get install chromium`), the page's
    // own relighting of the training sun must agree with umbra's (it prints whether it does).
    if Path::new("/usr/bin/chromium").exists() {
        let profile = dir.path().join("chromium-profile");
        let page = format!("file://{}", out.join("report.html").canonicalize().unwrap().display());
        let flags = [
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            // The page inflates its arrays asynchronously: let its work finish before the dump.
            "--virtual-time-budget=20000",
        ];
        let dom = std::process::Command::new("/usr/bin/chromium")
            .args(flags)
            .arg(format!("--user-data-dir={}", profile.display()))
            .args(["--dump-dom", &page])
            .output()
            .unwrap();
        let dom = String::from_utf8_lossy(&dom.stdout);
        assert!(dom.contains("; agree</pre>"), "{}", dom.lines().find(|l| l.contains("id=\"check\"")).unwrap_or("no check line: the script did not run"));
    } else {
        eprintln!("chromium not installed: the report's in-browser check was not run");
    }
    // Bad input is named: a light file with a bad value, a camera that does not exist.
    std::fs::write(&lamp, r#"{"type": "point", "position": [1.0, 2.0], "intensity": [5, 5, 5]}"#).unwrap();
    let run = cli(&["relight", out.to_str().unwrap(), "--light", lamp.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && stderr.contains("lamp.json") && stderr.contains("position"), "{stderr}");
    let run = cli(&["relight", out.to_str().unwrap(), "--light", "sun2", "--camera", "99"]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && stderr.contains("--camera 99"), "{stderr}");

    // A run folder without a fit is refused with the file named.
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_umbra")).args(["render", dir.path().to_str().unwrap()]).output().unwrap();
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("schedule.toml"), "{}", String::from_utf8_lossy(&run.stderr));
}

#[test]
fn ablate_compares_schedules_in_one_table_and_checks_them_all_first() {
    let dir = TempDir::new("ablate");
    let scene_path = tiny_scene(dir.path(), TrainingLight::Sun);
    let base = dir.path().join("base.toml");
    let no_eikonal = dir.path().join("no-eikonal.toml");
    std::fs::write(&base, QUICK.replace("iterations = 60", "iterations = 4")).unwrap();
    std::fs::write(&no_eikonal, QUICK.replace("iterations = 60", "iterations = 4").replace("eikonal = 0.05", "eikonal = 0.0")).unwrap();
    let out = dir.path().join("ablation");
    let options = |schedules: Vec<std::path::PathBuf>, out: std::path::PathBuf| umbra::ablate::AblateOptions {
        scene: scene_path.clone(),
        schedules,
        out,
        iterations: None,
        seed: 1,
        force: false,
        backend: Backend::Flex,
    };
    let summary = umbra::ablate::ablate(&options(vec![base.clone(), no_eikonal.clone()], out.clone()), |_, _, _| {}).unwrap();
    let rows = summary.rows;
    assert_eq!(summary.fitted, 2);
    assert_eq!(rows.iter().map(|r| r.schedule.as_str()).collect::<Vec<_>>(), ["base", "no-eikonal"]);
    assert!(rows.iter().all(|r| r.iterations == 4 && r.light_error_degrees.is_some() && r.novel_pose_psnr.is_some()), "{rows:?}");
    let csv = std::fs::read_to_string(out.join("ablation.csv")).unwrap();
    assert_eq!(csv.lines().count(), 3, "{csv}");
    assert!(csv.lines().nth(2).unwrap().starts_with("no-eikonal,4,"), "{csv}");
    for file in ["ablation.md", "ablation.png", "base/fit.json", "no-eikonal/fit.json", "base/renders/metrics.csv"] {
        assert!(out.join(file).exists(), "{file}");
    }
    // Resumable: run again, finished runs are reused (their reports untouched), an interrupted
    // one (a checkpoint, no report) is resumed, one locked by another live process is left to it.
    let report = std::fs::read(out.join("base/fit.json")).unwrap();
    let again = umbra::ablate::ablate(&options(vec![base.clone(), no_eikonal.clone()], out.clone()), |_, _, _| {}).unwrap();
    assert_eq!((again.fitted, again.rows.len()), (0, 2));
    assert_eq!(report, std::fs::read(out.join("base/fit.json")).unwrap(), "a finished run is not refitted");
    std::fs::remove_file(out.join("no-eikonal/fit.json")).unwrap();
    let resumed = umbra::ablate::ablate(&options(vec![base.clone(), no_eikonal.clone()], out.clone()), |_, _, _| {}).unwrap();
    assert_eq!((resumed.fitted, resumed.rows.len()), (1, 2));
    std::fs::remove_file(out.join("no-eikonal/fit.json")).unwrap();
    let mut holder = std::process::Command::new("sleep").arg("30").spawn().unwrap();
    std::fs::write(out.join("no-eikonal/.lock"), format!("{} fit", holder.id())).unwrap();
    let shared = umbra::ablate::ablate(&options(vec![base.clone(), no_eikonal.clone()], out.clone()), |_, _, _| {});
    let _ = holder.kill();
    let _ = holder.wait();
    let shared = shared.unwrap();
    assert_eq!((shared.fitted, shared.rows.len(), shared.elsewhere.clone()), (0, 1, vec!["no-eikonal".to_string()]));
    // A folder holding a run of another schedule needs --force.
    std::fs::write(&no_eikonal, QUICK.replace("iterations = 60", "iterations = 4").replace("eikonal = 0.05", "eikonal = 0.01")).unwrap();
    std::fs::remove_file(out.join("no-eikonal/.lock")).unwrap();
    let err = umbra::ablate::ablate(&options(vec![base.clone(), no_eikonal.clone()], out.clone()), |_, _, _| {}).unwrap_err().to_string();
    assert!(err.contains("another schedule") && err.contains("--force"), "{err}");
    // An impossible schedule (a light stage on a uniformly lit scene) is refused before any run.
    std::fs::create_dir_all(dir.path().join("uniform")).unwrap();
    let uniform = tiny_scene_with_tests(&dir.path().join("uniform"), TrainingLight::Uniform, vec![TestKind::Poses]);
    let light = dir.path().join("light.toml");
    std::fs::write(&light, format!("light = \"fit\"\n{}", QUICK.replace("iterations = 60", "iterations = 4"))).unwrap();
    let mut refused = options(vec![base.clone(), light], dir.path().join("refused"));
    refused.scene = uniform;
    let err = umbra::ablate::ablate(&refused, |_, _, _| {}).unwrap_err().to_string();
    assert!(err.contains("light.toml") && err.contains("uniformly lit"), "{err}");
    assert!(!dir.path().join("refused").exists(), "nothing written");
}

/// A 32-pixel synthetic walker seen by `cameras` cameras in `frames` frames, one test frame.
fn small_capture(cameras: usize, frames: usize) -> umbra::synth::SynthOptions {
    umbra::synth::SynthOptions { size: 32, cameras, frames, test_frames: 1, test: vec![TestKind::Poses], samples: 4, seed: 5, ..Default::default() }
}

/// Every length of a fit follows the body: the same capture at a third and at three times
/// the size (`synth --scale`: the same images up to the tracer's epsilons) takes the same
/// steps, every loss term equal to a small tolerance, with the default schedule's terms all
/// on (field, Gaussians, light and their regularisers).
#[test]
fn a_fit_of_the_same_capture_at_another_size_takes_the_same_steps() {
    let dir = TempDir::new("scale");
    let scene_at = |scale: f64| {
        let options = umbra::synth::SynthOptions { scale, ..small_capture(4, 2) };
        let out = dir.path().join(format!("scale-{scale}"));
        umbra::synth::generate(&options, &out, false, |_, _| {}).unwrap();
        umbra::scene::Scene::load(&out).unwrap()
    };
    let text = r#"
iterations = 6
rays_per_batch = 256
samples_per_ray = 16
fine_samples_per_ray = 8
probe_samples_per_ray = 8
density_points = 64
regulariser_points = 32
light_from = 0
[field]
kind = "grid"
[losses]
mask = 1.0
rgb = 1.0
grey = 0.1
density = 0.5
sigma = 0.25
mean = 0.5
ambient = 0.2
eikonal = 0.1
curvature = 0.05
"#;
    let schedule = Schedule::parse(text, Path::new("scale.toml")).unwrap();
    let steps = |scene| {
        let mut trainer = Trainer::new(scene, schedule.clone(), Backend::Flex, 2).unwrap();
        (0..6).map(|_| trainer.iterate().unwrap().terms).collect::<Vec<_>>()
    };
    let one = steps(scene_at(1.0));
    for scale in [1.0 / 3.0, 3.0] {
        let other = steps(scene_at(scale));
        for (k, (a, b)) in one.iter().zip(&other).enumerate() {
            for (term, x) in a {
                let y = b[term];
                assert!((x - y).abs() <= 0.03 * x.abs().max(1e-3), "scale {scale}, step {k}, {term}: {x} at scale 1, {y}");
            }
        }
    }
}

/// A light-stage-like capture (three suns, each image under one) is fitted jointly: every sun
/// is searched and turns toward its truth, the first keeps irradiance 1 and the others learn
/// theirs, a checkpoint resumes with every light's search and cone, and fit.json names each
/// light's error. A capture mixing a sun and a point light is refused, naming both.
#[test]
fn several_training_suns_are_fitted_jointly_and_mixed_kinds_are_refused() {
    let dir = TempDir::new("suns");
    let options = umbra::synth::SynthOptions { suns: 3, ..small_capture(3, 3) };
    let scene_path = dir.path().join("suns");
    umbra::synth::generate(&options, &scene_path, false, |_, _| {}).unwrap();
    let text = QUICK.replace("light_from = 0", "light_from = 10\nsun_search = 64").replace("checkpoint_every = 20", "checkpoint_every = 15");
    let schedule_path = dir.path().join("suns.toml");
    std::fs::write(&schedule_path, &text).unwrap();
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let truths: Vec<glam::DVec3> = scene
        .training_lights()
        .iter()
        .map(|n| match &scene.lights[*n] {
            umbra::light::Light::Directional { direction, .. } => *direction,
            other => panic!("{other:?}"),
        })
        .collect();
    assert_eq!(truths.len(), 3);
    let schedule = Schedule::parse(&text, Path::new("suns.toml")).unwrap();
    let mut trainer = Trainer::new(scene, schedule, Backend::Flex, 1).unwrap();
    assert_eq!(trainer.model().unwrap().light_count(), 3);
    for _ in 0..11 {
        trainer.iterate().unwrap();
    }
    let model = trainer.model().unwrap();
    for (k, truth) in truths.iter().enumerate() {
        let search = trainer.searches[k].as_ref().unwrap_or_else(|| panic!("light {k} was searched"));
        let found = glam::DVec3::from_array(search.best.direction);
        assert!(found.angle_between(*truth).to_degrees() < 40.0, "light {k}: search {found:?} against {truth:?}");
        assert!(trainer.cones[k].is_some(), "light {k} has its cone");
        let irradiance = &model.light_at(k).report()["irradiance"];
        let learned = model.light_at(k).strength_learned;
        assert_eq!(learned, k > 0, "light {k}: {irradiance}");
        if k == 0 {
            assert_eq!(irradiance[0].as_f64(), Some(1.0));
        }
    }

    // A fit of the same capture writes every light and resumes with every light's state.
    let out = dir.path().join("run");
    let report = serde_json::to_value(umbra::fit::fit(&fit_options(&scene_path, out.clone(), &schedule_path, Some(20), 1, false), |_| {}).unwrap()).unwrap();
    assert_eq!(report["lights"].as_object().map(|m| m.len()), Some(3), "{}", report["lights"]);
    assert_eq!(report["light_errors_against_scene"].as_object().map(|m| m.len()), Some(3));
    let state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("checkpoint/state.json")).unwrap()).unwrap();
    assert_eq!(state["light_cones"].as_array().map(|c| c.len()), Some(2), "{state}");
    umbra::fit::fit(&fit_options(&scene_path, out.clone(), &schedule_path, Some(30), 1, true), |_| {}).unwrap();

    // One image under a point light among the suns: refused, naming the kinds.
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(scene_path.join("scene.json")).unwrap()).unwrap();
    json["lights"]["lamp"] = serde_json::json!({"type": "point", "position": [1.0, 2.0, 1.0], "intensity": [4.0, 4.0, 4.0]});
    let first_train = json["images"].as_array().unwrap().iter().position(|i| i["split"] == "train").unwrap();
    json["images"][first_train]["light"] = serde_json::json!("lamp");
    std::fs::write(scene_path.join("scene.json"), serde_json::to_string(&json).unwrap()).unwrap();
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let err = Trainer::new(scene, Schedule::parse(&text, Path::new("suns.toml")).unwrap(), Backend::Flex, 1).err().unwrap().to_string();
    assert!(err.contains("point") && err.contains("directional") && err.contains("scene.json"), "{err}");
}

/// A run fitted before the albedo had a decoder of its own (its `state.json` does not say, its
/// schedule does not either, its model has one decoder with four outputs) still renders and
/// resumes, rebuilt as it was fitted rather than with today's default.
#[test]
fn a_run_from_before_the_albedo_decoder_renders_and_resumes_as_it_was_fitted() {
    let (dir, scene_path, schedule_path) = quick_setup("old-decoder", TrainingLight::Sun, 10);
    let text = std::fs::read_to_string(&schedule_path).unwrap();
    let old = dir.path().join("old.toml");
    // (Nor the root's skinning, which came after.)
    std::fs::write(&old, format!("{text}\n[field]\nkind = \"grid\"\nalbedo_layers = 0\nroot_skinning = false\n")).unwrap();
    let today = dir.path().join("today.toml");
    std::fs::write(&today, format!("{text}\n[field]\nkind = \"grid\"\n")).unwrap();
    let run = dir.path().join("run");
    umbra::fit::fit(&fit_options(&scene_path, run.clone(), &old, Some(10), 2, false), |_| {}).unwrap();
    // What such a run looked like: no record of the decoder anywhere.
    let state_path = run.join("checkpoint/state.json");
    let mut state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state_path).unwrap()).unwrap();
    assert_eq!(state["albedo_layers"], 0, "a checkpoint records its albedo decoder");
    for key in ["albedo_layers", "field", "gaussian_bones"] {
        state.as_object_mut().unwrap().remove(key);
    }
    common::without_checksums(&state_path, &mut state);
    std::fs::copy(&today, run.join("schedule.toml")).unwrap();
    let evaluation = umbra::scoring::render_run(&run, None, Backend::Flex, |_| {}).unwrap();
    assert!(evaluation["novel_pose_psnr"].as_f64().is_some_and(|p| p.is_finite()), "{evaluation}");
    let resumed = serde_json::to_value(umbra::fit::fit(&fit_options(&scene_path, run.clone(), &today, Some(14), 2, true), |_| {}).unwrap()).unwrap();
    assert_eq!(resumed["iterations"], 14, "{resumed}");
    let state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state_path).unwrap()).unwrap();
    assert_eq!(state["albedo_layers"], 0, "the resumed run kept its shared decoder");
    assert!(state["field"]["grid"]["root"].is_null(), "and its skinning by distance alone: {}", state["field"]);
    // A run of today's default records its own decoder and restores with it.
    let fresh = dir.path().join("fresh");
    umbra::fit::fit(&fit_options(&scene_path, fresh.clone(), &today, Some(4), 2, false), |_| {}).unwrap();
    let state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(fresh.join("checkpoint/state.json")).unwrap()).unwrap();
    assert_eq!(state["albedo_layers"], 2);
    assert_eq!(state["field"]["grid"]["root"]["bone"], 0, "today's grid lets far points follow the root: {}", state["field"]);
    assert!(umbra::scoring::render_run(&fresh, None, Backend::Flex, |_| {}).is_ok());
}

/// The first test view of a trainer's scene in its fitted light and its albedo, rendered from
/// one trace (`render_view_layers`) and each on its own (`render_view`).
fn view_and_albedo(trainer: &Trainer) -> (umbra::imageio::RgbImage, umbra::imageio::RgbImage, umbra::imageio::RgbImage, umbra::imageio::RgbImage) {
    use umbra::eval::{render_view, render_view_layers, Lighting, Strata, VIEW_SAMPLING};
    let (model, scene, device) = (trainer.model().unwrap(), &trainer.scene, &trainer.device);
    let view = scene.views.iter().find(|v| v.split == umbra::scene::Split::Test).unwrap();
    let scale = glam::DVec3::new(1.0, 0.9, 1.1);
    let layers = render_view_layers(model, scene, view.camera, view.frame, VIEW_SAMPLING, device, &Lighting::Fitted(0), Some(scale), Strata::Shortcuts);
    let (image, albedo) = (layers.image, layers.albedo);
    let alone = render_view(model, scene, view.camera, view.frame, VIEW_SAMPLING, device, &Lighting::Fitted(0));
    let albedo_alone = render_view(model, scene, view.camera, view.frame, VIEW_SAMPLING, device, &Lighting::Albedo { albedo_scale: scale });
    (image, albedo.unwrap(), alone, albedo_alone)
}

/// The first test view of a trainer's scene in five lights (the fitted light, the albedo, a
/// sun, a lamp and a uniform sky: more than one trace shades) rendered together
/// (`render_view_lights`), and each on its own.
fn view_in_lights(trainer: &Trainer) -> (Vec<umbra::imageio::RgbImage>, Vec<umbra::imageio::RgbImage>) {
    use umbra::eval::{render_view, render_view_lights, Lighting, Strata, LIGHTS_PER_TRACE, VIEW_SAMPLING};
    use umbra::light::Light;
    let (model, scene, device) = (trainer.model().unwrap(), &trainer.scene, &trainer.device);
    let view = scene.views.iter().find(|v| v.split == umbra::scene::Split::Test).unwrap();
    let albedo_scale = glam::DVec3::new(1.0, 0.9, 1.1);
    let sun = Light::Directional { direction: glam::DVec3::new(-0.6, 0.55, -0.35).normalize(), irradiance: glam::DVec3::ONE, ambient: glam::DVec3::splat(0.1) };
    let lamp = Light::Point { position: glam::DVec3::new(-1.3, 2.0, 1.2), intensity: glam::DVec3::splat(4.0), ambient: glam::DVec3::splat(0.1) };
    let sky = Light::Uniform { radiance: glam::DVec3::new(0.9, 0.8, 1.0) };
    let lightings = [
        Lighting::Fitted(0),
        Lighting::Albedo { albedo_scale },
        Lighting::Known { light: &sun, albedo_scale, samples: 8 },
        Lighting::Known { light: &lamp, albedo_scale, samples: 8 },
        Lighting::Known { light: &sky, albedo_scale, samples: 8 },
    ];
    assert!(lightings.len() > LIGHTS_PER_TRACE, "the view is traced twice");
    let together = render_view_lights(model, scene, view.camera, view.frame, VIEW_SAMPLING, device, &lightings, None, Strata::Shortcuts);
    let alone = lightings.iter().map(|l| render_view(model, scene, view.camera, view.frame, VIEW_SAMPLING, device, l)).collect();
    assert!(together.albedo.is_none());
    (together.images, alone)
}

/// A capture whose pixels average their area (anti-aliased, `synth --pixel-samples`) is read as
/// such, fitted (the fit runs and lowers its loss) and its views rendered over each pixel's
/// area; a centre-sampled one at pixel centres, unless the schedule says otherwise.
#[test]
fn an_anti_aliased_capture_is_read_as_one_and_rendered_over_each_pixels_area() {
    let dir = TempDir::new("footprint");
    // 64 pixels square: at 32 the limbs are a pixel or two wide, with no inside to compare
    // their silhouette's pixels with.
    let options = |pixel_samples| umbra::synth::SynthOptions {
        size: 64,
        cameras: 4,
        frames: 2,
        test_frames: 1,
        test: vec![TestKind::Poses],
        samples: 8,
        seed: 5,
        pixel_samples,
        ..umbra::synth::SynthOptions::default()
    };
    umbra::synth::generate(&options(4), &dir.path().join("area"), false, |_, _| {}).unwrap();
    let schedule = Schedule::parse(QUICK, Path::new("quick.toml")).unwrap();
    let scene = umbra::scene::Scene::load(&dir.path().join("area")).unwrap();
    let mut trainer = Trainer::new(scene, schedule.clone(), Backend::Flex, 1).unwrap();
    assert_eq!(trainer.footprint, umbra::scene::Footprint::Area, "{:?}", trainer.footprint_estimate);
    let losses: Vec<f64> = (0..60).map(|_| trainer.iterate().unwrap().total).collect();
    assert!(losses.iter().all(|l| l.is_finite()));
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(mean(&losses[50..]) < 0.8 * mean(&losses[..10]), "{losses:?}");
    // A test view and its albedo from one trace, against two renders: over an area capture's
    // pixels the two share the pixels rendered over their area, so a pixel may be its area's
    // mean in one and its centre in the other, where the image is smooth.
    let (image, albedo, alone, albedo_alone) = view_and_albedo(&trainer);
    let srgb = |v: f32| umbra::imageio::linear_to_srgb(v.max(0.0));
    for (a, b) in [(&image, &alone), (&albedo, &albedo_alone)] {
        let gaps: Vec<f32> = a.pixels.iter().zip(&b.pixels).flat_map(|(p, q)| (0..3).map(move |c| (srgb(p[c]) - srgb(q[c])).abs())).collect();
        let worst = gaps.iter().cloned().fold(0.0, f32::max);
        let average = gaps.iter().sum::<f32>() / gaps.len() as f32;
        assert!(worst < 8.0 / 255.0 && average < 0.5 / 255.0, "worst {worst}, mean {average}");
    }
    use umbra::eval::LIGHTS_PER_TRACE;
    // The view in five lights from one geometry, against each light's own render: a pixel any
    // light needs over its area is rendered over it in all, so a few pixels another light found
    // an edge in differ from their centres; everywhere else the two are the same.
    let (together, alone) = view_in_lights(&trainer);
    assert_eq!(together.len(), alone.len());
    for (k, (a, b)) in together.iter().zip(&alone).enumerate() {
        let gaps: Vec<f32> = a.pixels.iter().zip(&b.pixels).map(|(p, q)| (0..3).map(|c| (srgb(p[c]) - srgb(q[c])).abs()).fold(0.0, f32::max)).collect();
        let differing = gaps.iter().filter(|&&g| g > 1.0 / 255.0).count();
        let average = gaps.iter().sum::<f32>() / gaps.len() as f32;
        let covered = a.pixels.iter().filter(|p| p.iter().any(|&v| v > 0.0)).count();
        // Measured: 10-23 of 456 pixels, mean 0.01-0.02 of a step; the fifth light, traced on
        // its own, 0.
        assert!(differing * 100 <= 6 * covered && average < 0.05 / 255.0, "light {k}: {differing} of {covered} pixels differ, mean {average}");
        assert!(k < LIGHTS_PER_TRACE || differing == 0, "light {k} is traced alone");
        assert!(covered > 100, "light {k}: the view sees the body");
    }
    // The strata of its refined pixels interpolated inside the body and searched near their
    // neighbours' depths along silhouettes, against every one traced: the same picture to
    // within a quarter of an 8-bit step on average, and the silhouette within 1% of its pixels.
    {
        use umbra::eval::{render_view_layers, Lighting, Strata, VIEW_SAMPLING};
        let (model, scene, device) = (trainer.model().unwrap(), &trainer.scene, &trainer.device);
        let view = scene.views.iter().find(|v| v.split == umbra::scene::Split::Test).unwrap();
        let scale = Some(glam::DVec3::new(1.0, 0.9, 1.1));
        let render = |strata| {
            let layers = render_view_layers(model, scene, view.camera, view.frame, VIEW_SAMPLING, device, &Lighting::Fitted(0), scale, strata);
            (layers.image, layers.albedo)
        };
        let ((fast, fast_albedo), (traced, traced_albedo)) = (render(Strata::Shortcuts), render(Strata::Traced));
        for (a, b) in [(&fast, &traced), (&fast_albedo.unwrap(), &traced_albedo.unwrap())] {
            let drawn = |p: &[f32; 3]| p.iter().any(|&v| v > 0.0);
            let gaps: Vec<f32> = a.pixels.iter().zip(&b.pixels).flat_map(|(p, q)| (0..3).map(move |c| (srgb(p[c]) - srgb(q[c])).abs())).collect();
            let worst = gaps.iter().cloned().fold(0.0, f32::max);
            let average = gaps.iter().sum::<f32>() / gaps.len() as f32;
            let flipped = a.pixels.iter().zip(&b.pixels).filter(|(p, q)| drawn(p) != drawn(q)).count();
            let covered = a.pixels.iter().filter(|p| drawn(p)).count();
            // Measured: mean 0.07 and 0.04 of an 8-bit step, no pixel flipped of 462.
            assert!(average < 0.25 / 255.0 && flipped * 100 <= covered, "worst {worst}, mean {average}, {flipped} of {covered} flipped");
        }
    }
    // The same capture sampled at pixel centres: read as such, or as the schedule says.
    let centre = tiny_scene(dir.path(), TrainingLight::Sun);
    let mut trainer = Trainer::new(umbra::scene::Scene::load(&centre).unwrap(), schedule.clone(), Backend::Flex, 1).unwrap();
    assert_eq!(trainer.footprint, umbra::scene::Footprint::Centre);
    // At pixel centres one trace gives exactly the two renders.
    for _ in 0..20 {
        trainer.iterate().unwrap();
    }
    let (image, albedo, alone, albedo_alone) = view_and_albedo(&trainer);
    assert!(image.pixels == alone.pixels && albedo.pixels == albedo_alone.pixels);
    assert!(albedo.pixels.iter().any(|p| p[0] > 0.0), "the view sees the body");
    // And one trace in five lights gives exactly each light's own render, the sky's samples
    // included.
    let (together, alone) = view_in_lights(&trainer);
    for (k, (a, b)) in together.iter().zip(&alone).enumerate() {
        assert!(a.pixels == b.pixels, "light {k}");
    }
    assert!(together[4].pixels != together[2].pixels, "the lights differ");
    let forced = Schedule::parse(&format!("footprint = \"area\"\n{QUICK}"), Path::new("quick.toml")).unwrap();
    let trainer = Trainer::new(umbra::scene::Scene::load(&centre).unwrap(), forced, Backend::Flex, 1).unwrap();
    assert_eq!(trainer.footprint, umbra::scene::Footprint::Area);
}

/// Gaussians fit the field's density wherever it is; a fit moves each to the bone whose
/// skinning carries it, and a run keeps the bones its Gaussians ended on.
#[test]
fn gaussians_move_to_the_bones_that_carry_them_and_a_run_keeps_their_bones() {
    let (dir, scene_path, schedule_path) = quick_setup("rebind", TrainingLight::Sun, 4);
    let text = std::fs::read_to_string(&schedule_path).unwrap();
    std::fs::write(&schedule_path, format!("{text}\n[field]\nkind = \"grid\"\n")).unwrap();
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let pose = scene.frames[0].pose.clone();
    let mut trainer = Trainer::new(scene, Schedule::load(&schedule_path).unwrap(), Backend::Flex, 1).unwrap();
    let started: Vec<usize> = trainer.model().unwrap().gaussians.bones.clone();
    // Every Gaussian handed to the last bone (a foot), where it is not carried: the rebinding
    // gives each limb its own back, and nothing moves where nothing is wrong.
    let last = started.iter().max().copied().unwrap();
    trainer.model_mut().unwrap().gaussians.rebind(&vec![last; started.len()], &pose);
    let moved = trainer.rebind_gaussians().unwrap();
    let bones = trainer.model().unwrap().gaussians.bones.clone();
    let back = bones.iter().zip(&started).filter(|(a, b)| a == b).count();
    assert!(moved > started.len() / 2 && back * 10 >= started.len() * 9, "moved {moved}, back on their bones {back} of {}", started.len());
    assert_eq!(trainer.rebind_gaussians().unwrap(), 0, "a second rebinding moves nothing");
    // The moved Gaussians still train.
    let means = |t: &Trainer| t.model().unwrap().gaussians.means.val().into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
    let before = means(&trainer);
    trainer.iterate().unwrap();
    assert!(means(&trainer) != before, "a step moves the rebound Gaussians' means");
    // A run records its Gaussians' bones and restores them with its checkpoint.
    let run = dir.path().join("run");
    umbra::fit::fit(&fit_options(&scene_path, run.clone(), &schedule_path, Some(4), 2, false), |_| {}).unwrap();
    let state_path = run.join("checkpoint/state.json");
    let mut state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state_path).unwrap()).unwrap();
    let recorded: Vec<usize> = serde_json::from_value(state["gaussian_bones"].clone()).unwrap();
    assert_eq!(recorded.len(), started.len());
    let mut edited = recorded.clone();
    edited[0] = last;
    state["gaussian_bones"] = serde_json::json!(edited);
    common::rewrite_state(&state_path, &state);
    let restored = umbra::fit::restore(&run, None, Backend::Flex).unwrap();
    assert_eq!(restored.fitted.model.gaussians.bones, edited);
    state["gaussian_bones"] = serde_json::json!([0, 1]);
    common::rewrite_state(&state_path, &state);
    let err = umbra::fit::restore(&run, None, Backend::Flex).err().expect("a wrong count is refused");
    assert!(err.to_string().contains("gaussian_bones"), "{err}");
}

/// A turntable's cameras circle the body at the scene's cameras' mean height and distance, each
/// looking at the centre of the bones' box.
#[test]
fn orbit_cameras_circle_the_body_at_the_scenes_height_and_distance() {
    let dir = TempDir::new("orbit");
    let scene = umbra::scene::Scene::load(&tiny_scene(dir.path(), TrainingLight::Sun)).unwrap();
    let (lo, hi) = scene.frames[0].pose.bounds(&scene.skeleton);
    let centre = (lo + hi) * 0.5;
    let mean = |f: &dyn Fn(&umbra::scene::Camera) -> f64, cameras: &[umbra::scene::Camera]| cameras.iter().map(f).sum::<f64>() / cameras.len() as f64;
    let height = |c: &umbra::scene::Camera| (c.centre() - centre).y;
    let distance = |c: &umbra::scene::Camera| {
        let o = c.centre() - centre;
        (o.x * o.x + o.z * o.z).sqrt()
    };
    let orbit = umbra::relight::orbit_cameras(&scene, 0, 8).collect::<Vec<_>>();
    assert_eq!(orbit.len(), 8);
    for c in &orbit {
        let at = c.project(centre).unwrap();
        assert!((at.x - c.cx).abs() < 1e-6 && (at.y - c.cy).abs() < 1e-6, "{at}");
        assert!((height(c) - mean(&height, &scene.cameras)).abs() < 1e-6 && (distance(c) - mean(&distance, &scene.cameras)).abs() < 1e-6);
    }
    // Evenly around: neighbours 45 degrees apart.
    for pair in orbit.windows(2) {
        let (a, b) = (pair[0].centre() - centre, pair[1].centre() - centre);
        let cosine = (a.x * b.x + a.z * b.z) / ((a.x * a.x + a.z * a.z) * (b.x * b.x + b.z * b.z)).sqrt();
        assert!((cosine.acos().to_degrees() - 45.0).abs() < 1e-6, "{cosine}");
    }
}

/// One camera's training images a quarter brighter and redder than the others' (its exposure
/// and white balance): a short fit learns that camera the largest gain in every channel, the
/// red most, while the gains' mean over the cameras stays 1.
#[test]
fn a_brighter_camera_is_learned_a_larger_gain_and_the_gains_mean_is_one() {
    let dir = TempDir::new("camera-colours");
    let scene_path = tiny_scene(dir.path(), TrainingLight::Sun);
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let bright = [1.35f32, 1.2, 1.2];
    for view in scene.views.iter().filter(|v| v.camera == 1 && v.split == umbra::scene::Split::Train) {
        let mut image = umbra::imageio::read_rgb(&view.path).unwrap();
        image.pixels.iter_mut().for_each(|p| *p = [0, 1, 2].map(|c| (p[c] * bright[c]).min(1.0)));
        std::fs::write(&view.path, umbra::imageio::encode_png_rgb(&image).unwrap()).unwrap();
    }
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let schedule = Schedule::parse(QUICK, Path::new("quick.toml")).unwrap();
    let mut trainer = Trainer::new(scene, schedule, Backend::Flex, 1).unwrap();
    for _ in 0..60 {
        trainer.iterate().unwrap();
    }
    let gains = trainer.camera_gains();
    eprintln!("{gains:?}");
    assert_eq!(gains.len(), 4, "every training camera has a gain");
    let (_, brighter) = gains.iter().find(|(c, _)| *c == 1).unwrap();
    for (camera, gain) in gains.iter().filter(|(c, _)| *c != 1) {
        assert!((0..3).all(|c| brighter[c] > gain[c] + 0.05), "camera 1 {brighter:?} against camera {camera} {gain:?}");
    }
    assert!(brighter[0] > brighter[1] && brighter[0] > brighter[2], "{brighter:?}");
    assert!((0..3).all(|c| (gains.iter().map(|(_, g)| g[c]).sum::<f64>() / 4.0 - 1.0).abs() < 1e-9));
}

/// A step reads the Gaussians with its check after the update, for the next batch's ray
/// bounds: they are the model's, and whoever may change them (a rebinding, anyone taking the
/// state mutably) drops them, so the next batch reads them afresh.
#[test]
fn the_gaussians_a_step_read_for_the_next_batch_are_the_models_until_someone_may_change_them() {
    let (_dir, scene_path, schedule_path) = quick_setup("gaussians-read", TrainingLight::Sun, 4);
    let scene = umbra::scene::Scene::load(&scene_path).unwrap();
    let mut trainer = Trainer::new(scene, Schedule::load(&schedule_path).unwrap(), Backend::Flex, 1).unwrap();
    let read = |trainer: &Trainer| trainer.state().unwrap().gaussians_read.clone();
    assert_eq!(read(&trainer), None, "nothing read before the first step");
    trainer.iterate().unwrap();
    assert_eq!(read(&trainer), Some(trainer.model().unwrap().gaussians.to_set()), "the step's read is the model's Gaussians");
    trainer.rebind_gaussians().unwrap();
    assert_eq!(read(&trainer), None, "a rebinding drops them");
    trainer.iterate().unwrap();
    assert!(read(&trainer).is_some());
    let _ = trainer.model_mut().unwrap();
    assert_eq!(read(&trainer), None, "taking the model mutably drops them");
}
