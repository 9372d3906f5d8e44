//! Run folders that cannot hurt the user: a fit started from any folder (the default schedule
//! is compiled in, the scene path is stored absolute), a user's folder is never written into
//! without --force, a failing --resume writes nothing, and a checkpoint swap interrupted between
//! its two renames still leaves a checkpoint that resumes and renders.

mod common;

use common::{fails, short_run, snapshot, succeeds, umbra, TempDir};
use std::path::{Path, PathBuf};
use umbra::synth::{TestKind, TrainingLight};

fn tiny_scene(dir: &Path) -> PathBuf {
    common::tiny_synth(dir, TrainingLight::Sun, 24, 3, vec![TestKind::Poses], 9)
}

#[test]
fn a_fit_started_elsewhere_uses_the_built_in_schedule_and_its_run_renders_from_anywhere() {
    let dir = TempDir::new("relocatable");
    let scene = tiny_scene(dir.path());
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir_all(&elsewhere).unwrap();
    let run = dir.path().join("run");
    // No schedules/ folder in `elsewhere`: the default schedule is the compiled-in copy.
    succeeds(&elsewhere, &["fit", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "3"]);
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("fit.json")).unwrap()).unwrap();
    assert!(Path::new(report["scene"].as_str().unwrap()).is_absolute(), "{}", report["scene"]);
    // Three iterations end long before the light stage's start: it did not run.
    let stages = report["stages"].as_array().unwrap();
    let light = stages.iter().find(|s| s["name"] == "light and RGB fitting").unwrap();
    assert_eq!(light["ran"], false, "{light}");
    assert_eq!(std::fs::read_to_string(run.join("schedule.toml")).unwrap(), umbra::schedule::DEFAULT_TEXT);
    // `umbra fit` ends with the run's report.
    assert!(run.join("report.html").exists() && run.join("report.md").exists());
    // A run moved to another folder renders from a third one.
    let moved = dir.path().join("moved-run");
    std::fs::rename(&run, &moved).unwrap();
    succeeds(&elsewhere, &["render", moved.to_str().unwrap()]);
    // A run fitted on a GPU build renders in any build: its backend is only a name there.
    let report = std::fs::read_to_string(moved.join("fit.json")).unwrap();
    assert!(report.contains("\"backend\": \"flex\""), "fit.json names its backend");
    std::fs::write(moved.join("fit.json"), report.replace("\"backend\": \"flex\"", "\"backend\": \"wgpu\"")).unwrap();
    succeeds(&elsewhere, &["render", moved.to_str().unwrap()]);
}

#[test]
fn a_users_folder_is_not_written_into_and_a_failing_resume_writes_nothing() {
    let dir = TempDir::new("foreign");
    let scene = tiny_scene(dir.path());
    let cwd = std::env::current_dir().unwrap();
    let mine = dir.path().join("my-files");
    std::fs::create_dir_all(&mine).unwrap();
    std::fs::write(mine.join("gaussians.json"), "my own file").unwrap();
    let before = snapshot(&mine);
    let stderr = fails(&cwd, &["fit", scene.to_str().unwrap(), "--out", mine.to_str().unwrap(), "--iterations", "2"]);
    assert!(stderr.contains("not an umbra run") && stderr.contains("--force"), "{stderr}");
    assert_eq!(before, snapshot(&mine), "nothing written into the user's folder");
    // --resume on a folder that does not exist: an error, and the folder is not created.
    let missing = dir.path().join("no-such-run");
    fails(&cwd, &["fit", scene.to_str().unwrap(), "--out", missing.to_str().unwrap(), "--resume"]);
    assert!(!missing.exists(), "a failed --resume created the folder");
    // A run whose checkpoint is corrupt: --resume fails and its schedule copy is unchanged.
    let run = dir.path().join("run");
    succeeds(&cwd, &["fit", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "2"]);
    std::fs::write(run.join("checkpoint/state.json"), "{ not json").unwrap();
    let other = dir.path().join("other.toml");
    let changed = umbra::schedule::DEFAULT_TEXT.replace("iterations = 2900", "iterations = 1700");
    assert_ne!(changed, umbra::schedule::DEFAULT_TEXT, "the other schedule must differ from the default");
    std::fs::write(&other, changed).unwrap();
    let before = snapshot(&run);
    fails(&cwd, &["fit", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--resume", "--schedule", other.to_str().unwrap()]);
    assert_eq!(before, snapshot(&run), "a failing --resume changed the run");
}

#[test]
fn a_checkpoint_swap_interrupted_between_its_renames_still_resumes_and_renders() {
    let (_dir, scene, run) = short_run("swap");
    let cwd = std::env::current_dir().unwrap();
    // The state a kill between `checkpoint -> .checkpoint.old` and `.checkpoint.tmp ->
    // checkpoint` leaves: no checkpoint/, the previous one aside, the new one complete in tmp.
    std::fs::rename(run.join("checkpoint"), run.join(".checkpoint.old")).unwrap();
    let tmp = run.join(".checkpoint.tmp");
    std::fs::create_dir_all(&tmp).unwrap();
    for entry in std::fs::read_dir(run.join(".checkpoint.old")).unwrap().flatten() {
        std::fs::copy(entry.path(), tmp.join(entry.file_name())).unwrap();
    }
    succeeds(&cwd, &["render", run.to_str().unwrap()]);
    // Without --resume the set-aside checkpoint still counts as an earlier fit.
    assert!(fails(&cwd, &["fit", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "4"]).contains("--resume"));
    succeeds(&cwd, &["fit", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "4", "--resume", "--force-schedule"]);
    let state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("checkpoint/state.json")).unwrap()).unwrap();
    assert_eq!(state["iteration"], 4);
    assert!(!run.join(".checkpoint.old").exists(), "the set-aside checkpoint is removed once a new one is in place");
}

#[test]
fn resume_refuses_another_schedule_or_iteration_count_unless_forced() {
    let dir = TempDir::new("continuation");
    let scene = tiny_scene(dir.path());
    let cwd = std::env::current_dir().unwrap();
    let run = dir.path().join("run");
    let run_arg = run.to_str().unwrap();
    let scene_arg = scene.to_str().unwrap();
    succeeds(&cwd, &["fit", scene_arg, "--out", run_arg, "--iterations", "3"]);
    let before = snapshot(&run);
    // Another iteration count: refused, saying what changed, nothing written.
    let stderr = fails(&cwd, &["fit", scene_arg, "--out", run_arg, "--iterations", "5", "--resume"]);
    assert!(stderr.contains("iteration count (3 -> 5)") && stderr.contains("--force-schedule"), "{stderr}");
    // Another schedule: refused, naming a changed line.
    let other = dir.path().join("other.toml");
    std::fs::write(&other, umbra::schedule::DEFAULT_TEXT.replace("rays_per_batch = 512", "rays_per_batch = 256")).unwrap();
    let stderr = fails(&cwd, &["fit", scene_arg, "--out", run_arg, "--iterations", "3", "--resume", "--schedule", other.to_str().unwrap()]);
    assert!(stderr.contains("rays_per_batch: 512 -> 256"), "{stderr}");
    // Fewer iterations than are done: refused even when forced.
    let stderr = fails(&cwd, &["fit", scene_arg, "--out", run_arg, "--iterations", "2", "--resume", "--force-schedule"]);
    assert!(stderr.contains("would run nothing"), "{stderr}");
    assert_eq!(before, snapshot(&run), "refused resumes wrote nothing");
    // A forced resume to more iterations runs.
    succeeds(&cwd, &["fit", scene_arg, "--out", run_arg, "--iterations", "5", "--resume", "--force-schedule", "--no-eval"]);
}

#[test]
fn a_run_refuses_another_scene_and_a_damaged_checkpoint() {
    let (dir, scene, run) = short_run("identity");
    let cwd = std::env::current_dir().unwrap();
    let run_arg = run.to_str().unwrap();
    let before = snapshot(&run);
    // The same capture but one bone 10% longer: another skeleton, same bone count.
    let longer = dir.path().join("longer");
    std::fs::create_dir_all(&longer).unwrap();
    for entry in walk_files(&scene) {
        let target = longer.join(entry.strip_prefix(&scene).unwrap());
        std::fs::create_dir_all(target.parent().unwrap()).unwrap();
        std::fs::copy(&entry, &target).unwrap();
    }
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(longer.join("scene.json")).unwrap()).unwrap();
    let length = json["skeleton"]["bones"][1]["length"].as_f64().unwrap();
    json["skeleton"]["bones"][1]["length"] = serde_json::json!(length * 1.1);
    std::fs::write(longer.join("scene.json"), serde_json::to_string(&json).unwrap()).unwrap();
    let stderr = fails(&cwd, &["render", dir.path().join("no-run").to_str().unwrap()]);
    assert!(stderr.contains("does not exist") && stderr.contains("umbra fit"), "{stderr}");
    let stderr = fails(&cwd, &["render", scene.to_str().unwrap()]);
    assert!(stderr.contains("is not an umbra run"), "{stderr}");
    let stderr = fails(&cwd, &["render", run_arg, "--scene", longer.to_str().unwrap()]);
    assert!(stderr.contains("state.json") && stderr.contains("skeleton"), "{stderr}");
    // Another capture of the same skeleton: renders, but the fit does not resume on it.
    let other = common::tiny_synth(&dir.path().join("other"), TrainingLight::Sun, 24, 3, vec![TestKind::Poses], 10);
    let stderr = fails(&cwd, &["fit", other.to_str().unwrap(), "--out", run_arg, "--iterations", "2", "--resume"]);
    assert!(stderr.contains("training_data"), "{stderr}");
    assert_eq!(before, snapshot(&run), "refused commands wrote nothing");
    // One flipped byte in the model: refused by its checksum.
    let model = run.join("checkpoint/model.bpk");
    let mut bytes = std::fs::read(&model).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x40;
    std::fs::write(&model, bytes).unwrap();
    let stderr = fails(&cwd, &["render", run_arg]);
    assert!(stderr.contains("model.bpk") && stderr.contains("checksum"), "{stderr}");
    assert!(!run.join("renders").exists(), "nothing rendered from a damaged checkpoint");
}

/// Every file under `dir`.
fn walk_files(dir: &Path) -> Vec<PathBuf> {
    snapshot(dir).into_iter().map(|(p, _)| p).collect()
}

#[test]
fn a_run_folder_in_use_is_refused_and_a_stale_lock_taken_over() {
    let (_dir, scene, run) = short_run("lock");
    let cwd = std::env::current_dir().unwrap();
    let run_arg = run.to_str().unwrap();
    assert!(!run.join(".lock").exists(), "the lock is released when the fit ends");
    // A lock held by a running process (this test's): fit and render refuse, nothing written.
    std::fs::write(run.join(".lock"), format!("{} fit", std::process::id())).unwrap();
    let before = snapshot(&run);
    let stderr = fails(&cwd, &["fit", scene.to_str().unwrap(), "--out", run_arg, "--iterations", "3", "--resume", "--force-schedule"]);
    assert!(stderr.contains("another umbra fit") && stderr.contains(&std::process::id().to_string()), "{stderr}");
    assert!(fails(&cwd, &["render", run_arg]).contains("another umbra"));
    assert_eq!(before, snapshot(&run), "refused commands wrote nothing");
    // A lock left by a process that is gone (above Linux's largest pid): taken over.
    std::fs::write(run.join(".lock"), "4194305 fit").unwrap();
    succeeds(&cwd, &["render", run_arg]);
    assert!(!run.join(".lock").exists());
}

#[test]
fn an_environment_lit_capture_is_refused_saying_why_not_fitted_as_uniform() {
    let dir = TempDir::new("environment");
    let scene = common::tiny_synth(dir.path(), TrainingLight::Sun, 24, 2, vec![TestKind::Relight], 4);
    let file = scene.join("scene.json");
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    for image in json["images"].as_array_mut().unwrap() {
        if image["split"] == "train" {
            image["light"] = serde_json::json!("sky");
        }
    }
    std::fs::write(&file, serde_json::to_string(&json).unwrap()).unwrap();
    let run = dir.path().join("run");
    let stderr = fails(&std::env::current_dir().unwrap(), &["fit", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "2"]);
    assert!(stderr.contains("environment map \"sky\"") && stderr.contains("scene.json"), "{stderr}");
    assert!(!run.exists(), "nothing written");
}

#[test]
fn bench_fit_scores_both_fields_and_refits_the_grid_for_the_mlps_time() {
    let dir = TempDir::new("bench-fit");
    let scene = tiny_scene(dir.path());
    let out = dir.path().join("bench");
    let root = std::env::current_dir().unwrap();
    let args = ["bench", "fit", "--scene", scene.to_str().unwrap(), "--out", out.to_str().unwrap(), "--iterations", "4", "--evaluations", "2", "--equal-time"];
    succeeds(&root, &args);
    let csv = std::fs::read_to_string(out.join("fit-curves.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    let runs: Vec<&str> = rows.iter().map(|r| r[0]).collect();
    assert_eq!(&runs[..4], &["mlp", "mlp", "grid", "grid"], "{csv}");
    // The third fit is the grid again, for at least as many iterations as the first grid fit
    // (the MLP's step costs more), scored twice, its last point at its last iteration; it takes
    // turns with the MLP's fit run again, scored once at its end, as the first run scored.
    assert_eq!(rows.len(), 7, "{csv}");
    let equal_time = &rows[4..6];
    assert!(equal_time.iter().all(|r| r[0].starts_with("grid at the MLP's time (")), "{csv}");
    let last: usize = equal_time[1][1].parse().unwrap();
    assert!(last >= 4 && equal_time[1][0].ends_with(&format!("({last} iterations)")), "{csv}");
    let again = &rows[6];
    assert!(again[0].starts_with("mlp again"), "{csv}");
    assert_eq!((again[1], &again[3..9]), (rows[1][1], &rows[1][3..9]), "the MLP's second run scores as its first: {csv}");
    for file in ["fit-curves.md", "fit-foreground-psnr.png", "fit-albedo-psnr.png"] {
        assert!(out.join(file).is_file(), "{file}");
    }
}

/// `bench scenes` fits each named scene into `OUT/NAME` and writes one row per scene, with a
/// sun's error in degrees and a lamp's in centimetres; a missing scene fails naming it.
#[test]
fn bench_scenes_fits_every_scene_into_one_table() {
    let dir = TempDir::new("bench-scenes");
    let sun = common::tiny_synth(&dir.path().join("sunlit"), TrainingLight::Sun, 24, 2, vec![TestKind::Poses], 3);
    let lamp = common::tiny_synth(&dir.path().join("lamplit"), TrainingLight::Point, 24, 2, vec![TestKind::Poses], 3);
    let out = dir.path().join("bench");
    let root = std::env::current_dir().unwrap();
    let scenes = format!("{},{}", sun.display(), lamp.display());
    succeeds(&root, &["bench", "scenes", "--scenes", &scenes, "--out", out.to_str().unwrap(), "--iterations", "4"]);
    let csv = std::fs::read_to_string(out.join("scenes.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 2, "{csv}");
    assert_eq!((rows[0][3], rows[1][3]), ("degrees", "m"), "{csv}");
    assert!(rows.iter().all(|r| r[1].parse::<f64>().unwrap() > 0.0 && r[4].parse::<f64>().unwrap().is_finite()), "{csv}");
    let md = std::fs::read_to_string(out.join("scenes.md")).unwrap();
    assert!(md.contains(" cm |") && md.contains(" degrees |"), "{md}");
    // Both fits are where the table says: both scenes' folders are named `scene`, so the second
    // run gets its own.
    assert!(out.join("scene/fit.json").is_file() && out.join("scene-2/fit.json").is_file());
    assert_eq!((rows[0][0], rows[1][0]), ("scene", "scene-2"), "{csv}");
    let missing =
        umbra(&root, &["bench", "scenes", "--scenes", dir.path().join("nowhere").to_str().unwrap(), "--out", out.to_str().unwrap(), "--iterations", "4"]);
    assert!(!missing.status.success() && String::from_utf8_lossy(&missing.stderr).contains("nowhere"));
}

/// `bench memory` fits a scene's training images at two sizes, each in its own process, and
/// reads each fit's peak memory from its fit.json into one table. 200 images, so that the
/// larger size's pixels (about 25 MB more) stand well above the run-to-run spread of a
/// process's peak (about 3 MB; with 6 images the two sizes' peaks crossed).
#[test]
fn bench_memory_measures_two_sizes_in_one_table() {
    let dir = TempDir::new("bench-memory");
    let scene = common::tiny_synth(dir.path(), TrainingLight::Sun, 24, 2, vec![TestKind::Poses], 3);
    let out = dir.path().join("bench");
    let root = std::env::current_dir().unwrap();
    succeeds(
        &root,
        &["bench", "memory", "--scene", scene.to_str().unwrap(), "--out", out.to_str().unwrap(), "--iterations", "2", "--images", "200", "--quick"],
    );
    let (header, rows) = umbra::table::read_csv(&std::fs::read_to_string(out.join("memory.csv")).unwrap()).unwrap();
    assert_eq!(rows.len(), 2, "{rows:?}");
    let column = |name: &str| header.iter().position(|h| h == name).unwrap();
    let peak = |r: usize| rows[r][column("peak_bytes")].parse::<f64>().unwrap();
    assert!(peak(0) > 1e6 && peak(1) > peak(0), "{rows:?}");
    assert_eq!((rows[0][column("size")].as_str(), rows[1][column("size")].as_str()), ("120", "504"), "{rows:?}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("run-504px-200-images/fit.json")).unwrap()).unwrap();
    assert_eq!(report["peak_memory_bytes"].as_f64(), Some(peak(1)));
    // On the CPU there is no device memory to report: the column stays empty, as fit.json's.
    assert!(rows.iter().all(|r| r[column("device_bytes")].is_empty()) && report["peak_device_memory_bytes"].is_null(), "{rows:?}");
    // A backend is for this benchmark alone: another refuses it rather than run on flex unasked.
    let other = out.join("steps");
    let refused = fails(&root, &["bench", "steps", "--backend", "flex", "--out", other.to_str().unwrap(), "--quick"]);
    assert!(refused.contains("--backend flex is for `bench memory`"), "{refused}");
    assert!(!other.exists(), "nothing written");
    // Run again, it replaces its own scenes and runs; a folder of the user's in the way of one
    // is refused before anything is written, and kept.
    let again = ["bench", "memory", "--scene", scene.to_str().unwrap(), "--out", out.to_str().unwrap(), "--iterations", "2", "--images", "200", "--quick"];
    succeeds(&root, &again);
    let user = dir.path().join("user");
    std::fs::create_dir_all(user.join("504px-200-images")).unwrap();
    std::fs::write(user.join("504px-200-images/mine.txt"), "mine").unwrap();
    let refused = fails(
        &root,
        &["bench", "memory", "--scene", scene.to_str().unwrap(), "--out", user.to_str().unwrap(), "--iterations", "2", "--images", "200", "--quick"],
    );
    assert!(refused.contains("504px-200-images") && refused.contains("nothing was written"), "{refused}");
    assert_eq!(std::fs::read_to_string(user.join("504px-200-images/mine.txt")).unwrap(), "mine");
    assert_eq!(std::fs::read_dir(&user).unwrap().count(), 1, "nothing else written");
}

/// `bench scenes --seeds` fits every scene once per seed into `OUT/NAME-seedS`, one row each,
/// and a summary of each scene's mean and standard deviation over them that the rows give back;
/// a seed named twice is refused before anything is fitted.
#[test]
fn bench_scenes_at_several_seeds_adds_each_scenes_mean_and_spread() {
    let dir = TempDir::new("bench-seeds");
    let sun = common::tiny_synth(&dir.path().join("sunlit"), TrainingLight::Sun, 24, 2, vec![TestKind::Poses], 3);
    let out = dir.path().join("bench");
    let root = std::env::current_dir().unwrap();
    let args = |seeds: &str| {
        vec![
            "bench".to_string(),
            "scenes".into(),
            "--scenes".into(),
            sun.display().to_string(),
            "--out".into(),
            out.display().to_string(),
            "--iterations".into(),
            "4".into(),
            "--seeds".into(),
            seeds.into(),
        ]
    };
    let twice = umbra(&root, &args("1,1").iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!twice.status.success() && String::from_utf8_lossy(&twice.stderr).contains("seed 1 is named twice"));
    assert!(!out.join("scene-seed1").exists());
    succeeds(&root, &args("0,1").iter().map(String::as_str).collect::<Vec<_>>());
    let csv = std::fs::read_to_string(out.join("scenes.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.iter().map(|r| (r[0], r[8])).collect::<Vec<_>>(), vec![("scene", "0"), ("scene", "1")], "{csv}");
    assert!(out.join("scene-seed0/fit.json").is_file() && out.join("scene-seed1/fit.json").is_file());
    // The two seeds fit differently, and the summary is their mean and sample spread.
    let pose: Vec<f64> = rows.iter().map(|r| r[4].parse().unwrap()).collect();
    assert_ne!(pose[0], pose[1], "{csv}");
    let summary = std::fs::read_to_string(out.join("scenes-summary.csv")).unwrap();
    let header: Vec<&str> = summary.lines().next().unwrap().split(',').collect();
    let line: Vec<&str> = summary.lines().nth(1).unwrap().split(',').collect();
    let column = |name: &str| line[header.iter().position(|h| *h == name).unwrap()].parse::<f64>().unwrap();
    assert_eq!(column("fits"), 2.0, "{summary}");
    let (mean, sd) = ((pose[0] + pose[1]) / 2.0, (pose[0] - pose[1]).abs() / 2f64.sqrt());
    assert!((column("novel_pose_foreground_psnr_mean") - mean).abs() < 1e-3 && (column("novel_pose_foreground_psnr_sd") - sd).abs() < 1e-3, "{summary}");
    assert!(std::fs::read_to_string(out.join("scenes.md")).unwrap().contains("Mean +- standard deviation over seeds 0, 1"));
    // One seed into the same folder: no summary of the earlier seeds is left beside its table.
    succeeds(&root, &args("2").iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!out.join("scenes-summary.csv").exists() && out.join("scene/fit.json").is_file());
}

/// Whether a triangle mesh is closed and consistently oriented: every directed
/// edge appears once and its reverse once.
fn closed_and_oriented(indices: &[u32]) -> bool {
    let mut edges = std::collections::HashMap::new();
    for t in indices.chunks(3) {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            *edges.entry((a, b)).or_insert(0) += 1;
        }
    }
    edges.iter().all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1))
}

#[test]
fn export_mesh_writes_a_closed_coloured_mesh_that_tobj_loads_and_refuses_bad_frames() {
    let (dir, _scene, run) = short_run("export-mesh");
    let root = std::env::current_dir().unwrap();
    let file = dir.path().join("frame0.obj");
    succeeds(&root, &["export-mesh", run.to_str().unwrap(), "--frame", "0", "--out", file.to_str().unwrap()]);
    let options = tobj::LoadOptions { single_index: true, triangulate: true, ..Default::default() };
    let (models, _) = tobj::load_obj(&file, &options).unwrap();
    assert_eq!(models.len(), 1);
    let mesh = &models[0].mesh;
    let vertices = mesh.positions.len() / 3;
    assert!(vertices > 1000 && mesh.indices.len() > 1000, "{vertices} vertices");
    assert_eq!(mesh.vertex_color.len(), mesh.positions.len(), "a colour per vertex");
    assert!(mesh.vertex_color.iter().all(|c| (0.0..=1.0).contains(c)));
    assert_eq!(mesh.normals.len(), mesh.positions.len(), "a normal per vertex");
    for n in mesh.normals.chunks(3) {
        assert!(((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt() - 1.0).abs() < 1e-3);
    }
    assert!(closed_and_oriented(&mesh.indices), "the exported surface is not closed");
    // Every frame into a folder; a frame out of range and a missing target are refused, and
    // write nothing.
    let all = dir.path().join("all");
    succeeds(&root, &["export-mesh", run.to_str().unwrap(), "--all-frames", all.to_str().unwrap()]);
    let written = std::fs::read_dir(&all).unwrap().count();
    assert!(written >= 2 && all.join("frame_0000.obj").is_file(), "{written} meshes");
    let bad = dir.path().join("bad.obj");
    let message = fails(&root, &["export-mesh", run.to_str().unwrap(), "--frame", "999", "--out", bad.to_str().unwrap()]);
    assert!(message.contains("--frame 999: out of range"), "{message}");
    assert!(!bad.exists());
    let message = fails(&root, &["export-mesh", run.to_str().unwrap()]);
    assert!(message.contains("--frame F --out FILE.obj or --all-frames DIR"), "{message}");
}

#[test]
fn eval_scores_test_and_training_images_and_the_surface_against_the_scenes_meshes() {
    // The independent example scene carries a ground-truth mesh per frame.
    let dir = TempDir::new("eval");
    let run = dir.path().join("run");
    let root = std::env::current_dir().unwrap();
    let scene = common::example_scene();
    succeeds(&root, &["fit", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "2", "--no-eval"]);
    succeeds(&root, &["eval", run.to_str().unwrap()]);
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("renders/metrics.json")).unwrap()).unwrap();
    let frames = metrics["geometry"].as_array().unwrap();
    // A geometry entry per frame with a mesh, up to six evenly spread.
    let meshed = umbra::scene::Scene::load(&scene).unwrap().frames.iter().filter(|f| f.mesh.is_some()).count();
    assert_eq!(frames.len(), meshed.min(6), "{frames:?}");
    assert!(frames.windows(2).all(|w| w[0]["frame"].as_u64() < w[1]["frame"].as_u64()), "in order, each once");
    for f in frames {
        let (accuracy, completeness, chamfer) = (f["accuracy"].as_f64().unwrap(), f["completeness"].as_f64().unwrap(), f["chamfer"].as_f64().unwrap());
        // Two iterations leave the prior's capsules: centimetres off, not metres, not zero.
        assert!(accuracy > 1e-4 && accuracy < 0.2 && completeness > 1e-4 && completeness < 0.2, "{f}");
        assert!((chamfer - 0.5 * (accuracy + completeness)).abs() < 1e-12);
        assert!((0.0..=180.0).contains(&f["normal_angle"].as_f64().unwrap()));
        // The training cameras see part of the surface (a ring of cameras: not its underside).
        let (seen, seen_close) = (f["seen"].as_f64().unwrap(), f["seen_within_2cm"].as_f64().unwrap());
        assert!(seen > 0.3 && seen < 1.0 && (0.0..=1.0).contains(&seen_close), "{f}");
    }
    assert!(metrics["light_error"]["direction_degrees"].is_number() || metrics["light_error"].is_null());
    // Relit images and albedos are scored again after a per-channel least-squares scale, which
    // brings them closer in linear values (scored in 8-bit sRGB, within rounding of that).
    for (plain, scaled) in [("relit", "relit_scaled"), ("albedo", "albedo_scaled")] {
        let (a, b) = (metrics[format!("{plain}_foreground_psnr")].as_f64().unwrap(), metrics[format!("{scaled}_foreground_psnr")].as_f64().unwrap());
        assert!(b >= a - 0.5, "{scaled}: {b} against {a}");
    }
    assert!(std::fs::read_to_string(run.join("renders/metrics.md")).unwrap().contains("## Geometry against the scene's meshes"));
    // The training images, into their own folder, as one group.
    succeeds(&root, &["eval", run.to_str().unwrap(), "--split", "train"]);
    let train: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("renders-train/metrics.json")).unwrap()).unwrap();
    let groups: Vec<&str> = train["groups"].as_array().unwrap().iter().filter_map(|g| g["group"].as_str()).collect();
    assert!(groups.contains(&"training pose and view"), "{groups:?}");
    assert_eq!(train["images"].as_array().unwrap().len(), 9);
}

#[test]
fn a_checkpoint_swap_interrupted_at_every_step_leaves_a_complete_checkpoint() {
    let (dir, _scene, run) = short_run("swap-every-step");
    let pristine = dir.path().join("pristine");
    copy_tree(&run, &pristine);
    let iteration_on_disk = |run: &Path| -> u64 {
        let found = umbra::fit::existing_checkpoint(run).expect("some complete checkpoint is on disk");
        let state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(found.join("state.json")).unwrap()).unwrap();
        state["iteration"].as_u64().unwrap()
    };
    let mut steps = 1;
    loop {
        let _ = std::fs::remove_dir_all(&run);
        copy_tree(&pristine, &run);
        let mut trainer = umbra::run::restore_trainer(&run, umbra::backend::Backend::Flex).unwrap();
        trainer.set_iteration(7).unwrap();
        let finished = umbra::fit::save_checkpoint_until(&trainer, &run, &[], steps).unwrap();
        // Killed after `steps` steps: the run still loads, from the old checkpoint or the new.
        let on_disk = iteration_on_disk(&run);
        assert!(on_disk == 2 || on_disk == 7, "step {steps}: iteration {on_disk} on disk");
        umbra::fit::restore(&run, None, umbra::backend::Backend::Flex).unwrap_or_else(|e| panic!("step {steps}: the run does not load: {e}"));
        if finished {
            assert_eq!(on_disk, 7);
            break;
        }
        // The next save after the kill completes and leaves nothing aside.
        assert!(umbra::fit::save_checkpoint_until(&trainer, &run, &[], usize::MAX).unwrap());
        assert_eq!(iteration_on_disk(&run), 7, "step {steps}");
        assert!(!run.join(".checkpoint.old").exists() && !run.join(".checkpoint.tmp").exists(), "step {steps}");
        steps += 1;
    }
    assert!(steps >= 10, "the swap has its writes and both renames: {steps} steps");
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap().flatten() {
        let target = to.join(entry.file_name());
        if entry.path().is_dir() {
            copy_tree(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target).unwrap();
        }
    }
}

#[test]
fn a_truncated_model_without_checksums_is_refused_in_words_not_a_debug_dump() {
    let (_dir, _scene, run) = short_run("truncated-model");
    let state_path = run.join("checkpoint/state.json");
    let mut state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state_path).unwrap()).unwrap();
    common::without_checksums(&state_path, &mut state);
    let model = run.join("checkpoint/model.bpk");
    let bytes = std::fs::read(&model).unwrap();
    std::fs::write(&model, &bytes[..bytes.len() / 2]).unwrap();
    let stderr = fails(&std::env::current_dir().unwrap(), &["render", run.to_str().unwrap()]);
    assert!(stderr.contains("model.bpk") && stderr.contains("truncated") && !stderr.contains("Io(\""), "{stderr}");
}
