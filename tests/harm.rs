//! Nothing a user types can do harm: each hostile input a probe found is refused with a clear
//! message (file and JSON/TOML path), writes nothing, and removes or overwrites nothing the
//! command did not create; and what a command writes never leaves a stale neighbour behind.

mod common;

use common::{fails, short_run, snapshot, succeeds, umbra, TempDir};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use umbra::synth::{Kind, SynthOptions, TestKind, TrainingLight};

fn cwd() -> PathBuf {
    std::env::current_dir().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn read_json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn write_json(path: &Path, value: &Value) {
    std::fs::write(path, serde_json::to_string_pretty(value).unwrap()).unwrap();
}

/// A copy of the tree at `from` in `to`.
fn copy_tree(from: &Path, to: &Path) {
    for (file, bytes) in snapshot(from) {
        let target = to.join(file.strip_prefix(from).unwrap());
        std::fs::create_dir_all(target.parent().unwrap()).unwrap();
        std::fs::write(target, bytes).unwrap();
    }
}

const TINY_SYNTH: [&str; 8] = ["--size", "8", "--cameras", "1", "--frames", "1", "--test-frames", "1"];

fn synth_args(out: &str, force: bool) -> Vec<&str> {
    let mut args = vec!["synth", "--out", out];
    if force {
        args.push("--force");
    }
    args.extend(TINY_SYNTH);
    args
}

#[test]
fn synth_refuses_a_relit_views_count_it_cannot_make() {
    let dir = TempDir::new("synth-relit-views");
    for (value, test) in [("0", None), ("-1", None), ("NaN", None), ("1e39", None), ("18446744073709551616", None), ("201", None), ("2", Some("poses"))] {
        let option = format!("--relit-views={value}");
        let mut args = synth_args("scene", false);
        args.push(&option);
        if let Some(test) = test {
            args.extend(["--test", test]);
        }
        let stderr = fails(dir.path(), &args);
        assert!(stderr.contains("relit-views"), "{value}: {stderr}");
        assert!(!dir.path().join("scene").exists(), "{value}: nothing is written");
    }
    // A negative count after a space reads as an option of its own: refused as such.
    let mut args = synth_args("scene", false);
    args.extend(["--relit-views", "-1"]);
    fails(dir.path(), &args);
    assert!(!dir.path().join("scene").exists());
    let mut args = synth_args("scene", false);
    args.extend(["--relit-views", "2"]);
    succeeds(dir.path(), &args);
}

#[test]
fn synth_force_never_removes_what_it_did_not_write() {
    let dir = TempDir::new("synth-force");
    let work = dir.path().join("x");
    std::fs::create_dir_all(&work).unwrap();
    std::fs::write(work.join("a.txt"), "keep").unwrap();
    // The working folder and its parent: refused, everything kept.
    let stderr = fails(&work, &synth_args(".", true));
    assert!(stderr.contains("working folder"), "{stderr}");
    let stderr = fails(&work, &synth_args("..", true));
    assert!(stderr.contains("working folder"), "{stderr}");
    assert_eq!(std::fs::read_to_string(work.join("a.txt")).unwrap(), "keep");
    // A user's folder (not a scene synth wrote): refused even with --force.
    let users = dir.path().join("users");
    std::fs::create_dir_all(&users).unwrap();
    std::fs::write(users.join("notes.txt"), "mine").unwrap();
    let stderr = fails(dir.path(), &synth_args("users", true));
    assert!(stderr.contains("not a scene umbra synth wrote"), "{stderr}");
    assert_eq!(std::fs::read_to_string(users.join("notes.txt")).unwrap(), "mine");
    // A file: refused.
    std::fs::write(dir.path().join("file"), "mine").unwrap();
    let stderr = fails(dir.path(), &synth_args("file", true));
    assert!(stderr.contains("not a folder"), "{stderr}");
    // A scene synth wrote is replaced with --force; with a user's file added, refused.
    succeeds(dir.path(), &synth_args("scene", false));
    succeeds(dir.path(), &synth_args("scene", true));
    std::fs::write(dir.path().join("scene/images/mine.png"), "mine").unwrap();
    let stderr = fails(dir.path(), &synth_args("scene", true));
    assert!(stderr.contains("mine.png") && stderr.contains("not a file of the scene"), "{stderr}");
    assert!(dir.path().join("scene/images/mine.png").exists() && dir.path().join("scene/scene.json").exists());
    // An empty folder is used as it is.
    std::fs::create_dir_all(dir.path().join("empty")).unwrap();
    succeeds(dir.path(), &synth_args("empty", false));
    assert!(dir.path().join("empty/scene.json").is_file());
}

#[test]
fn a_light_name_never_becomes_a_path_outside_the_run() {
    for (name, label) in [("../../../../escaped", "escaped"), ("/abs/path", "abs_path"), ("..", "light"), ("sun", "sun"), ("a b", "a_b")] {
        let got = umbra::relight::folder_label(name);
        assert!(!got.contains('/') && !got.contains('\\') && !got.starts_with('.'), "{name:?} -> {got:?}");
        assert!(got.ends_with(label), "{name:?} -> {got:?}");
    }
    // End to end: a scene light named to escape renders inside RUN/relit, and a light file of
    // the same stem as a scene light gets a folder of its own.
    let (dir, scene, run) = short_run("light-name");
    let mut json = read_json(&scene.join("scene.json"));
    let sun = json["lights"]["sun"].clone();
    json["lights"]["../../../../escaped"] = sun.clone();
    write_json(&scene.join("scene.json"), &json);
    let light_file = dir.path().join("sun.json");
    write_json(&light_file, &sun);
    let render = |light: &str| succeeds(&cwd(), &["relight", s(&run), "--scene", s(&scene), "--light", light, "--camera", "0", "--frame", "0"]);
    render("../../../../escaped");
    render("sun");
    render(s(&light_file));
    let relit: Vec<String> = std::fs::read_dir(run.join("relit")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert!(relit.iter().any(|n| n.ends_with("escaped")), "{relit:?}");
    assert!(relit.contains(&"sun".to_string()) && relit.contains(&"file-sun".to_string()), "{relit:?}");
    let escaped: Vec<_> =
        snapshot(dir.path()).into_iter().filter(|(p, _)| p.to_string_lossy().contains("escaped") && !p.starts_with(run.join("relit"))).collect();
    assert!(escaped.is_empty(), "written outside relit/: {:?}", escaped.iter().map(|(p, _)| p).collect::<Vec<_>>());
}

/// Rewrites a run's checkpoint state (and, with `checksum`, the checksum beside it, as a
/// deliberate editor would).
fn edit_state(run: &Path, edit: impl Fn(&mut Value), checksum: bool) {
    let path = run.join("checkpoint/state.json");
    let mut state = read_json(&path);
    edit(&mut state);
    std::fs::write(&path, state.to_string()).unwrap();
    if checksum {
        std::fs::write(run.join("checkpoint/state.checksum"), umbra::scene::identity::file_checksum(&path).unwrap()).unwrap();
    }
}

#[test]
fn a_checkpoint_state_is_checksummed_and_its_sizes_validated() {
    let (dir, _scene, run) = short_run("state");
    let pristine = dir.path().join("pristine");
    copy_tree(&run, &pristine);
    let reset = || {
        std::fs::remove_dir_all(&run).unwrap();
        copy_tree(&pristine, &run);
    };
    // An edit without its checksum: refused as damaged.
    edit_state(&run, |s| s["field"]["skinning_width"] = json!(s["field"]["skinning_width"].as_f64().unwrap() / 5.0), false);
    let stderr = fails(&cwd(), &["render", s(&run)]);
    assert!(stderr.contains("state.json") && stderr.contains("checksum"), "{stderr}");
    // Edits with their checksum recomputed: each refused by validation, naming the key.
    type Edit = Box<dyn Fn(&mut Value)>;
    let cases: Vec<(&str, Edit)> = vec![
        ("coarsest_cell", Box::new(|s: &mut Value| s["field"]["grid"]["coarsest_cell"] = json!(0.0))),
        ("bone_lengths[1]", Box::new(|s: &mut Value| s["field"]["grid"]["bone_lengths"][1] = json!(-0.2))),
        ("table_log2", Box::new(|s: &mut Value| s["field"]["grid"]["table_log2"] = json!(40))),
        ("root.reach", Box::new(|s: &mut Value| s["field"]["grid"]["root"]["reach"] = json!(40.0))),
        ("skeleton", Box::new(|s: &mut Value| s["skeleton"] = json!(true))),
    ];
    for (key, edit) in cases {
        reset();
        edit_state(&run, edit, true);
        let stderr = fails(&cwd(), &["render", s(&run)]);
        assert!(stderr.contains("state.json") && stderr.contains(key), "{key}: {stderr}");
        let stderr = fails(&cwd(), &["fit", s(&dir.path().join("scene")), "--out", s(&run), "--resume", "--iterations", "3"]);
        assert!(stderr.contains(key), "{key}: {stderr}");
    }
    // The checksum file itself removed: the checkpoint is incomplete.
    reset();
    std::fs::remove_file(run.join("checkpoint/state.checksum")).unwrap();
    let stderr = fails(&cwd(), &["render", s(&run)]);
    assert!(stderr.contains("state.checksum"), "{stderr}");
}

#[test]
fn ablate_reuses_only_runs_of_its_own_scene_and_keeps_out_of_a_users_folder() {
    let dir = TempDir::new("ablate-scene");
    let first = common::tiny_synth(&dir.path().join("a"), TrainingLight::Sun, 24, 3, vec![TestKind::Poses], 9);
    let second = common::tiny_synth(&dir.path().join("b"), TrainingLight::Sun, 24, 3, vec![TestKind::Poses], 10);
    let schedules = dir.path().join("schedules");
    std::fs::create_dir_all(&schedules).unwrap();
    for name in ["one", "two"] {
        std::fs::write(schedules.join(format!("{name}.toml")), umbra::schedule::DEFAULT_TEXT).unwrap();
    }
    let out = dir.path().join("ablation");
    let args = |scene: &Path| {
        vec![
            "ablate".to_string(),
            s(scene).to_string(),
            "--schedule".into(),
            s(&schedules.join("one.toml")).into(),
            "--schedule".into(),
            s(&schedules.join("two.toml")).into(),
            "--out".into(),
            s(&out).into(),
            "--iterations".into(),
            "2".into(),
        ]
    };
    let run = |scene: &Path| umbra(&cwd(), &args(scene).iter().map(String::as_str).collect::<Vec<_>>());
    assert!(run(&first).status.success());
    let (header, rows) = umbra::table::read_csv(&std::fs::read_to_string(out.join("ablation.csv")).unwrap()).unwrap();
    assert!(rows.len() == 2 && rows.iter().all(|r| r.len() == header.len()), "{header:?} {rows:?}");
    let before = snapshot(&out);
    let refused = run(&second);
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && stderr.contains("other training data"), "{stderr}");
    assert_eq!(before, snapshot(&out), "a refused ablation wrote nothing");
    // A user's folder: not written into without --force.
    let users = dir.path().join("users");
    std::fs::create_dir_all(&users).unwrap();
    std::fs::write(users.join("notes.txt"), "mine").unwrap();
    let mut user_args = args(&first);
    user_args[7] = s(&users).into();
    let refused = umbra(&cwd(), &user_args.iter().map(String::as_str).collect::<Vec<_>>());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && stderr.contains("notes.txt"), "{stderr}");
    assert_eq!(snapshot(&users).len(), 1);
}

#[test]
fn a_scene_without_test_images_is_fitted_and_says_there_was_nothing_to_evaluate() {
    let dir = TempDir::new("no-tests");
    let scene = common::tiny_synth(dir.path(), TrainingLight::Sun, 24, 3, vec![TestKind::Poses], 9);
    let mut json = read_json(&scene.join("scene.json"));
    let images: Vec<Value> = json["images"].as_array().unwrap().iter().filter(|i| i["split"] == "train").cloned().collect();
    json["images"] = json!(images);
    write_json(&scene.join("scene.json"), &json);
    let run = dir.path().join("run");
    let out = umbra(&cwd(), &["fit", s(&scene), "--out", s(&run), "--iterations", "2"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("no test images"), "{stdout}");
    let report = read_json(&run.join("fit.json"));
    assert!(report["evaluation_skipped"].as_str().unwrap().contains("no test images"), "{report}");
    assert!(report["evaluation"].is_null());
}

#[test]
fn ground_truth_meshes_are_validated_with_the_scene() {
    let dir = TempDir::new("meshes");
    common::valid_scene(dir.path());
    assert!(umbra::scene::Scene::load(dir.path()).is_ok());
    for (text, says) in [
        ("", "no triangles"),
        ("this is not an obj\x00\x01", "no triangles"),
        ("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "not finite"),
        ("v 0 0 0\nv 1 0 0\nv 0 1e30 0\nf 1 2 3\n", "beyond"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", ""),
    ] {
        std::fs::write(dir.path().join("meshes/f0.obj"), text).unwrap();
        let err = umbra::scene::Scene::load(dir.path()).err().unwrap_or_else(|| panic!("{text:?} accepted"));
        assert_eq!(err.path, "frames[0].mesh", "{text:?}: {err}");
        assert!(err.to_string().contains("meshes/f0.obj") && err.to_string().contains(says), "{text:?}: {err}");
    }
}

#[test]
fn iteration_counts_beyond_the_schedules_limit_are_refused_saying_the_limit() {
    let dir = TempDir::new("iterations");
    for args in [
        vec!["fit", "nowhere", "--out", "run", "--iterations", "99999999999"],
        vec!["ablate", "nowhere", "--schedule", "a", "--schedule", "b", "--out", "x", "--iterations", "1000000001"],
    ] {
        let stderr = fails(dir.path(), &args);
        assert!(stderr.contains("1000000000"), "{stderr}");
    }
    assert!(snapshot(dir.path()).is_empty());
    let err = umbra::schedule::Schedule::parse("iterations = 2e9\n[losses]\nmask = 1", Path::new("s.toml")).unwrap_err();
    assert!(err.to_string().contains("1000000000"), "{err}");
}

#[test]
fn outputs_of_an_earlier_fit_or_scene_are_not_left_beside_new_ones() {
    let (dir, scene, run) = short_run("stale");
    // A finished, evaluated run.
    succeeds(&cwd(), &["fit", s(&scene), "--out", s(&run), "--iterations", "3", "--resume", "--force-schedule"]);
    let evaluation = read_json(&run.join("fit.json"))["evaluation"].clone();
    assert!(!evaluation.is_null() && run.join("report.html").exists() && run.join("renders/compare.png").exists());
    // Its tables read back with a CSV reader, every row as wide as its header.
    for table in ["renders/metrics.csv", "losses.csv"] {
        let (header, rows) = umbra::table::read_csv(&std::fs::read_to_string(run.join(table)).unwrap()).unwrap();
        assert!(!rows.is_empty() && rows.iter().all(|r| r.len() == header.len()), "{table}: {header:?}");
    }
    // Resumed with nothing to do and --no-eval: its evaluation stays.
    succeeds(&cwd(), &["fit", s(&scene), "--out", s(&run), "--iterations", "3", "--resume", "--no-eval"]);
    assert_eq!(read_json(&run.join("fit.json"))["evaluation"], evaluation);
    // Rendered on a scene with fewer test images: no render of the first stays.
    let smaller = dir.path().join("smaller");
    copy_tree(&scene, &smaller);
    let mut json = read_json(&smaller.join("scene.json"));
    let mut kept_one = false;
    let images: Vec<Value> =
        json["images"].as_array().unwrap().iter().filter(|i| i["split"] == "train" || !std::mem::replace(&mut kept_one, true)).cloned().collect();
    json["images"] = json!(images);
    write_json(&smaller.join("scene.json"), &json);
    let pngs = |dir: &Path| std::fs::read_dir(dir).unwrap().filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "png")).count();
    let before = pngs(&run.join("renders"));
    std::fs::write(run.join("renders/notes.txt"), "mine").unwrap();
    std::fs::write(run.join("renders/my-picture.png"), "mine").unwrap();
    succeeds(&cwd(), &["render", s(&run), "--scene", s(&smaller)]);
    let after = pngs(&run.join("renders"));
    assert!(after < before, "{before} -> {after} PNGs");
    assert_eq!(std::fs::read_to_string(run.join("renders/notes.txt")).unwrap(), "mine", "a user's file stays");
    assert_eq!(std::fs::read_to_string(run.join("renders/my-picture.png")).unwrap(), "mine", "a user's picture stays");
    // Refitted with --force --no-eval: no report or renders of the old fit remain.
    succeeds(&cwd(), &["fit", s(&scene), "--out", s(&run), "--iterations", "2", "--force", "--no-eval"]);
    for stale in ["report.html", "report.md", "report-relit.png", "renders/compare.png", "renders/metrics.csv"] {
        assert!(!run.join(stale).exists(), "{stale} left from the earlier fit");
    }
    assert!(read_json(&run.join("fit.json"))["evaluation"].is_null());
}

#[test]
fn a_resume_keeps_its_seed_and_accepts_a_schedule_the_same_but_for_its_text() {
    let (dir, scene, run) = short_run("seed");
    let stderr = fails(&cwd(), &["fit", s(&scene), "--out", s(&run), "--iterations", "3", "--resume", "--seed", "5", "--no-eval"]);
    assert!(stderr.contains("--seed 0"), "{stderr}");
    // The same schedule with a comment and 0.10 for 0.1 (or 0.1 for 0.10): the same fit.
    let text = umbra::schedule::DEFAULT_TEXT;
    let (a, b) = if text.contains("= 0.1\n") { ("= 0.1\n", "= 0.10\n") } else { ("= 0.10\n", "= 0.1\n") };
    assert!(text.contains(a));
    let same = dir.path().join("same.toml");
    std::fs::write(&same, format!("# my copy\n{}", text.replacen(a, b, 1))).unwrap();
    // The copy in the run is the default's text; resumed with --seed 0 and the rewritten copy.
    succeeds(&cwd(), &["fit", s(&scene), "--out", s(&run), "--iterations", "2", "--resume", "--schedule", s(&same), "--seed", "0", "--no-eval"]);
    // A real change is still named, with its values.
    let other = dir.path().join("other.toml");
    std::fs::write(&other, text.replace("rays_per_batch = 512", "rays_per_batch = 256")).unwrap();
    let stderr = fails(&cwd(), &["fit", s(&scene), "--out", s(&run), "--iterations", "2", "--resume", "--schedule", s(&other)]);
    assert!(stderr.contains("rays_per_batch: 512 -> 256") && !stderr.contains("``"), "{stderr}");
}

#[cfg(unix)]
#[test]
fn unbounded_and_non_regular_files_are_refused() {
    let dir = TempDir::new("unbounded");
    common::valid_scene(dir.path());
    let zero = dir.path().join("zero");
    std::fs::create_dir_all(&zero).unwrap();
    std::os::unix::fs::symlink("/dev/zero", zero.join("scene.json")).unwrap();
    let err = umbra::scene::Scene::load(&zero).err().unwrap();
    assert!(err.to_string().contains("not a regular file"), "{err}");
    std::os::unix::fs::symlink("/dev/zero", dir.path().join("schedule.toml")).unwrap();
    let err = umbra::schedule::Schedule::load(&dir.path().join("schedule.toml")).unwrap_err();
    assert!(err.to_string().contains("not a regular file"), "{err}");
    // A scene.json past the size limit: refused before it is parsed.
    let big = dir.path().join("big");
    std::fs::create_dir_all(&big).unwrap();
    let file = std::fs::File::create(big.join("scene.json")).unwrap();
    file.set_len(umbra::files::SCENE_BYTES + 1).unwrap();
    let err = umbra::scene::Scene::load(&big).err().unwrap();
    assert!(err.to_string().contains("more than"), "{err}");
}

#[test]
fn training_masks_that_hold_no_body_are_refused() {
    let dir = TempDir::new("empty-masks");
    let scene = common::tiny_synth(dir.path(), TrainingLight::Sun, 24, 2, vec![TestKind::Poses], 9);
    let json = read_json(&scene.join("scene.json"));
    let empty = umbra::imageio::Mask { width: 24, height: 24, foreground: vec![false; 24 * 24].into() };
    for image in json["images"].as_array().unwrap().iter().filter(|i| i["split"] == "train") {
        std::fs::write(scene.join(image["mask"].as_str().unwrap()), umbra::imageio::encode_png_mask(&empty).unwrap()).unwrap();
    }
    let run = dir.path().join("run");
    let stderr = fails(&cwd(), &["fit", s(&scene), "--out", s(&run), "--iterations", "2"]);
    assert!(stderr.contains("mask") && stderr.contains("body"), "{stderr}");
    assert!(!run.exists(), "a refused fit wrote nothing");
}

#[cfg(unix)]
#[test]
fn a_link_that_leads_outside_the_scene_is_refused() {
    let dir = TempDir::new("links");
    let scene = dir.path().join("scene");
    std::fs::create_dir_all(&scene).unwrap();
    common::valid_scene(&scene);
    let outside = dir.path().join("outside.png");
    std::fs::rename(scene.join("images/a.png"), &outside).unwrap();
    std::os::unix::fs::symlink(&outside, scene.join("images/a.png")).unwrap();
    let err = umbra::scene::Scene::load(&scene).err().unwrap();
    assert_eq!(err.path, "images[0].path", "{err}");
    assert!(err.to_string().contains("outside the scene"), "{err}");
    // A folder linked from outside: the same.
    std::fs::remove_file(scene.join("images/a.png")).unwrap();
    std::fs::rename(&outside, scene.join("images/a.png")).unwrap();
    let masks = dir.path().join("masks-elsewhere");
    std::fs::rename(scene.join("masks"), &masks).unwrap();
    std::os::unix::fs::symlink(&masks, scene.join("masks")).unwrap();
    let err = umbra::scene::Scene::load(&scene).err().unwrap();
    assert!(err.to_string().contains("outside the scene"), "{err}");
    // A link inside the scene is followed.
    std::fs::remove_file(scene.join("masks")).unwrap();
    std::fs::rename(&masks, scene.join("masks")).unwrap();
    std::fs::rename(scene.join("images/a.png"), scene.join("images/a-real.png")).unwrap();
    std::os::unix::fs::symlink("a-real.png", scene.join("images/a.png")).unwrap();
    assert!(umbra::scene::Scene::load(&scene).is_ok());
}

#[test]
fn environment_maps_are_linear_exrs_of_non_negative_radiance() {
    let dir = TempDir::new("environment");
    let json = common::valid_scene(dir.path());
    let mut map = umbra::imageio::RgbImage::new(8, 4);
    map.pixels.iter_mut().for_each(|p| *p = [1.0, 1.0, 1.0]);
    map.pixels[5] = [1.0, -0.5, 1.0];
    umbra::imageio::write_exr_atomic(&dir.path().join("lights/sky.exr"), &map).unwrap();
    let err = umbra::scene::Scene::load(dir.path()).err().unwrap();
    assert_eq!(err.path, "lights.sky.path");
    assert!(err.to_string().contains("negative"), "{err}");
    let mut png = json.clone();
    png["lights"]["sky"]["path"] = json!("images/c.png");
    common::write_scene_json(dir.path(), &png);
    let err = umbra::scene::Scene::load(dir.path()).err().unwrap();
    assert!(err.to_string().contains("EXR"), "{err}");
}

#[cfg(unix)]
#[test]
fn a_read_only_run_relights_and_exports_into_a_folder_elsewhere() {
    use std::os::unix::fs::PermissionsExt;
    let (dir, scene, run) = short_run("read-only");
    // Root ignores permission bits; a folder where the lock file would go stands in for the
    // lock that cannot be created in a read-only run, for root as for anyone.
    std::fs::create_dir_all(run.join(".lock")).unwrap();
    let read_only = |mode: u32| std::fs::set_permissions(&run, std::fs::Permissions::from_mode(mode)).unwrap();
    read_only(0o555);
    let out = dir.path().join("relit");
    let relit = umbra(&cwd(), &["relight", s(&run), "--light", "sun", "--camera", "0", "--frame", "0", "--out", s(&out)]);
    let mesh = dir.path().join("mesh.obj");
    let exported = umbra(&cwd(), &["export-mesh", s(&run), "--frame", "0", "--out", s(&mesh)]);
    read_only(0o755);
    assert!(relit.status.success(), "{}", String::from_utf8_lossy(&relit.stderr));
    assert!(exported.status.success(), "{}", String::from_utf8_lossy(&exported.stderr));
    assert!(out.join("c00_f0000.png").is_file() && mesh.is_file());
    assert!(run.join(".lock").is_dir(), "the run was left as it was");
    // Into the run itself, the lock is needed: refused.
    let stderr = fails(&cwd(), &["relight", s(&run), "--scene", s(&scene), "--light", "sun", "--camera", "0", "--frame", "0"]);
    assert!(stderr.contains(".lock"), "{stderr}");
}

#[test]
fn unclear_messages_say_what_is_wrong() {
    let (dir, scene, run) = short_run("messages");
    // --out naming a file.
    let file = dir.path().join("file");
    std::fs::write(&file, "mine").unwrap();
    let stderr = fails(&cwd(), &["fit", s(&scene), "--out", s(&file), "--iterations", "2"]);
    assert!(stderr.contains("not a folder"), "{stderr}");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "mine");
    // A schedule's shorthand weight: the error names the key as written.
    let schedule = dir.path().join("bad.toml");
    std::fs::write(&schedule, "[losses]\nmask = 1\neikonal = -1\n").unwrap();
    let stderr = fails(&cwd(), &["fit", s(&scene), "--out", s(&dir.path().join("r2")), "--schedule", s(&schedule)]);
    assert!(stderr.contains("losses.eikonal:") && !stderr.contains("losses.eikonal.weight"), "{stderr}");
    // Render while a fit holds the run and has no fit.json yet.
    std::fs::remove_file(run.join("fit.json")).unwrap();
    let mut holder = std::process::Command::new("sleep").arg("30").spawn().unwrap();
    std::fs::write(run.join(".lock"), format!("{} fit\n", holder.id())).unwrap();
    let stderr = fails(&cwd(), &["render", s(&run)]);
    let _ = holder.kill();
    let _ = holder.wait();
    assert!(stderr.contains("fit is in progress"), "{stderr}");
}

#[cfg(unix)]
#[test]
fn a_fifo_is_reported_as_what_it_is() {
    let dir = TempDir::new("fifo");
    common::valid_scene(dir.path());
    std::fs::remove_file(dir.path().join("images/a.png")).unwrap();
    let made = std::process::Command::new("mkfifo").arg(dir.path().join("images/a.png")).status();
    if !made.is_ok_and(|s| s.success()) {
        return;
    }
    let err = umbra::scene::Scene::load(dir.path()).err().unwrap();
    assert!(err.to_string().contains("not a regular file") && !err.to_string().contains("directory"), "{err}");
}

#[test]
fn synth_writes_the_same_scene_into_an_empty_folder_as_into_a_new_one() {
    let dir = TempDir::new("synth-empty");
    let options = SynthOptions { character: Kind::Human, size: 8, cameras: 1, frames: 1, test_frames: 1, samples: 1, ..SynthOptions::default() };
    // Both folders are named `scene` (a scene is named after its folder).
    let (new, empty) = (dir.path().join("new/scene"), dir.path().join("empty/scene"));
    umbra::synth::generate(&options, &new, false, |_, _| {}).unwrap();
    std::fs::create_dir_all(&empty).unwrap();
    umbra::synth::generate(&options, &empty, false, |_, _| {}).unwrap();
    let strip = |root: &Path| snapshot(root).into_iter().map(|(p, b)| (p.strip_prefix(root).unwrap().to_path_buf(), b)).collect::<Vec<_>>();
    assert_eq!(strip(&new), strip(&empty));
    assert_eq!(read_json(&new.join("scene.json"))["name"], "scene");
}
