//! What a hostile user tried on import, clips and the outputs of a run, each numbered as the
//! defect it found: a folder import did not make is never removed; render and relight replace
//! only the files they listed; the PLY header, not its text, marks an earlier export; orbits are
//! bounded; units, up axes, lenses and clips that cannot be right are refused; COLMAP models
//! read by their fields and in a folder per camera; messages name the user's files.

mod common;

use common::{fails, short_run, succeeds, umbra, TempDir};
use glam::DMat4;
use std::path::{Path, PathBuf};
use umbra::capture::{bvh, import, ImportOptions, Units, Up};
use umbra::scene::Scene;
use umbra::synth::Export;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn cwd() -> PathBuf {
    std::env::current_dir().unwrap()
}

/// A tiny synthetic scene exported as a nerfstudio capture (centimetre BVH), in `dir/capture`.
fn capture(dir: &Path) -> PathBuf {
    let options = common::small_capture_options(Some(Export::Nerfstudio));
    let out = dir.join("capture");
    umbra::synth::generate(&options, &out, false, |_, _| {}).unwrap();
    out
}

fn options(capture: &Path, out: PathBuf) -> ImportOptions {
    common::import_options(capture, out)
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            copy_tree(&path, &to.join(path.file_name().unwrap()));
        } else {
            std::fs::copy(&path, to.join(path.file_name().unwrap())).unwrap();
        }
    }
}

/// `capture` copied to `to` with `file` (relative) replaced by `text`.
fn altered(capture: &Path, to: &Path, file: &str, text: &str) -> PathBuf {
    copy_tree(capture, to);
    std::fs::write(to.join(file), text).unwrap();
    to.to_path_buf()
}

fn import_error(options: &ImportOptions) -> String {
    let err = import(options, &|_, _| {}).unwrap_err().to_string();
    assert!(!options.out.exists(), "a refused import wrote {}", options.out.display());
    err
}

#[test]
fn defect_01_import_never_removes_a_folder_it_did_not_make() {
    let dir = TempDir::new("hostile-import-temp");
    let capture = capture(dir.path());
    // Folders of the names import used and would use, holding a user's file.
    let theirs = [".scene.importing".to_string(), format!(".scene.importing-{}-0", std::process::id())];
    for name in &theirs {
        std::fs::create_dir_all(dir.path().join(name)).unwrap();
        std::fs::write(dir.path().join(name).join("keep.txt"), "keep").unwrap();
    }
    // Refused after the images were written (the cameras' up is +Y, not +Z), then accepted.
    let out = dir.path().join("scene");
    let err = import_error(&ImportOptions { up: Up::PlusZ, ..options(&capture, out.clone()) });
    assert!(err.contains("--up"), "{err}");
    import(&options(&capture, out.clone()), &|_, _| {}).unwrap();
    for name in &theirs {
        assert_eq!(std::fs::read_to_string(dir.path().join(name).join("keep.txt")).unwrap(), "keep", "{name}");
    }
    let left: Vec<String> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert_eq!(left.iter().filter(|n| n.starts_with(".scene.")).count(), 2, "import left a folder of its own: {left:?}");
    // `--out .` in an empty folder imports there, the folder kept (defect 13).
    let here = dir.path().join("here");
    std::fs::create_dir_all(&here).unwrap();
    succeeds(&here, &["import", s(&capture), "--out", ".", "--light", "sun"]);
    assert!(Scene::load(&here).is_ok());
}

/// A sun as a light file, in `dir`.
fn sun_file(dir: &Path) -> PathBuf {
    let sun = dir.join("sun.json");
    std::fs::write(&sun, r#"{"type": "directional", "direction": [1, 0.6, 0.3], "irradiance": [2, 2, 2], "ambient": [0.1, 0.1, 0.1]}"#).unwrap();
    sun
}

/// The scene's frames as a centimetre BVH, with `edit` applied to its text.
fn clip(scene: &Scene, edit: impl Fn(String) -> String) -> String {
    let frames: Vec<Vec<DMat4>> = scene.frames.iter().map(|f| f.pose.bone_to_world.clone()).collect();
    edit(bvh::write(&scene.skeleton, &frames, 1.0 / 30.0, 100.0).unwrap())
}

#[test]
fn defects_02_to_05_outputs_replace_only_what_they_wrote_and_stay_bounded() {
    let (dir, scene_dir, run) = short_run("hostile-outputs");
    let scene = Scene::load(&scene_dir).unwrap();
    let sun = sun_file(dir.path());
    let sun = s(&sun);
    let clip_file = dir.path().join("clip.bvh");
    std::fs::write(&clip_file, clip(&scene, |t| t)).unwrap();
    // 2: a folder holding files named as a render's but no manifest is refused untouched.
    for (args, marker) in [(vec!["relight", s(&run), "--light", sun], "sheet.png"), (vec!["render", s(&run), "--motion", s(&clip_file)], "animation.png")] {
        let users = dir.path().join(format!("users-{marker}"));
        std::fs::create_dir_all(&users).unwrap();
        for name in [marker, "f0000.png", "c00_f0000.png"] {
            std::fs::write(users.join(name), "mine").unwrap();
        }
        let err = fails(&cwd(), &[args.as_slice(), &["--out", s(&users)]].concat());
        assert!(err.contains(".umbra-written.json"), "{err}");
        for name in [marker, "f0000.png", "c00_f0000.png"] {
            assert_eq!(std::fs::read_to_string(users.join(name)).unwrap(), "mine");
        }
    }
    // A folder a render wrote is written again; a user's file put in the way of a new name is not.
    let animated = dir.path().join("animated");
    succeeds(&cwd(), &["render", s(&run), "--motion", s(&clip_file), "--out", s(&animated)]);
    let frames = scene.frames.len();
    assert!((0..frames).all(|k| animated.join(format!("f{k:04}.png")).is_file()));
    succeeds(&cwd(), &["render", s(&run), "--motion", s(&clip_file), "--out", s(&animated)]);
    std::fs::write(animated.join("notes.txt"), "mine").unwrap();
    let longer = dir.path().join("longer.bvh");
    let doubled: Vec<Vec<DMat4>> = scene.frames.iter().chain(&scene.frames).map(|f| f.pose.bone_to_world.clone()).collect();
    std::fs::write(&longer, bvh::write(&scene.skeleton, &doubled, 1.0 / 30.0, 100.0).unwrap()).unwrap();
    std::fs::write(animated.join(format!("f{frames:04}.png")), "mine").unwrap();
    let err = fails(&cwd(), &["render", s(&run), "--motion", s(&longer), "--out", s(&animated)]);
    assert!(err.contains(&format!("f{frames:04}.png")) && err.contains("in the way"), "{err}");
    assert_eq!(std::fs::read_to_string(animated.join(format!("f{frames:04}.png"))).unwrap(), "mine");
    assert_eq!(std::fs::read_to_string(animated.join("notes.txt")).unwrap(), "mine");
    // 5: the streamed animation holds every frame, each the frame's PNG.
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(animated.join("animation.png")).unwrap()));
    let reader = decoder.read_info().unwrap();
    assert_eq!(reader.info().animation_control().map(|a| a.num_frames), Some(frames as u32));
    // 3: a file holding the PLY mark's text is not a PLY of export-gaussians.
    let notes = dir.path().join("notes.txt");
    std::fs::write(&notes, "my notes\ncomment umbra export-gaussians\n").unwrap();
    let err = fails(&cwd(), &["export-gaussians", s(&run), "--frame", "0", "--out", s(&notes)]);
    assert!(err.contains("not a PLY"), "{err}");
    assert_eq!(std::fs::read_to_string(&notes).unwrap(), "my notes\ncomment umbra export-gaussians\n");
    let ply = dir.path().join("g.ply");
    succeeds(&cwd(), &["export-gaussians", s(&run), "--frame", "0", "--out", s(&ply)]);
    succeeds(&cwd(), &["export-gaussians", s(&run), "--frame", "1", "--out", s(&ply)]);
    // 4: orbits are bounded; a motion render makes one camera per clip frame at most.
    for n in ["18446744073709551615", "1000000000", "0"] {
        let out = umbra(&cwd(), &["relight", s(&run), "--light", sun, "--orbit", n, "--out", s(&dir.path().join("orbit"))]);
        assert_eq!(out.status.code(), Some(2), "--orbit {n}: {}", String::from_utf8_lossy(&out.stderr));
        assert!(String::from_utf8_lossy(&out.stderr).contains("3600"));
    }
    let orbit = umbra::relight::orbit_cameras(&scene, 0, 1_000_000_000).take(3).count();
    assert_eq!(orbit, 3);
    let too_many = umbra::relight::RelightOptions {
        run: run.clone(),
        scene: None,
        light: Some(sun.into()),
        cameras: None,
        frames: Some(vec![0; 3]),
        samples: 1,
        out: Some(dir.path().join("too-many")),
        backend: umbra::backend::Backend::Flex,
        basis: None,
        orbit: Some(3600),
        size: None,
        rotate: 0.0,
        intensity: 1.0,
        ground: None,
    };
    let err = umbra::relight::relight_run(&too_many, |_| {}).unwrap_err().to_string();
    assert!(err.contains("10800 views"), "{err}");
    assert!(!dir.path().join("too-many").exists());
}

#[test]
fn defects_09_and_10_clips_lights_and_grounds_that_cannot_render_are_refused() {
    let (dir, scene_dir, run) = short_run("hostile-clips");
    let scene = Scene::load(&scene_dir).unwrap();
    let sun = sun_file(dir.path());
    let sun = s(&sun);
    let zero_offsets = clip(&scene, |t| {
        t.lines()
            .map(|l| match l.trim_start().strip_prefix("OFFSET") {
                Some(_) => format!("{}OFFSET 0 0 0", &l[..l.len() - l.trim_start().len()]),
                None => l.to_string(),
            })
            .collect::<Vec<_>>()
            .join("\n")
    });
    // The root's position in the last frame at 1e30 (the first three values of the last line).
    let far = clip(&scene, |t| {
        let (head, last) = t.trim_end().rsplit_once('\n').unwrap();
        let mut values: Vec<String> = last.split_whitespace().map(String::from).collect();
        values[0] = "1e30".into();
        format!("{head}\n{}\n", values.join(" "))
    });
    let mut equal = serde_json::json!({"frame_time": 0.1, "joints": [], "frames": []});
    equal["joints"] = serde_json::json!(scene.skeleton.bones.iter().map(|b| serde_json::json!({"name": b.name, "parent": b.parent})).collect::<Vec<_>>());
    let still: Vec<Vec<Vec<f64>>> =
        scene.skeleton.bones.iter().map(|_| DMat4::IDENTITY.transpose().to_cols_array_2d().iter().map(|r| r.to_vec()).collect()).collect();
    equal["frames"] = serde_json::json!([still.clone(), still]);
    for (name, text, expected) in [("zero.bvh", zero_offsets, "no size"), ("far.bvh", far, "a joint lies 1e30"), ("equal.json", equal.to_string(), "no size")] {
        let file = dir.path().join(name);
        std::fs::write(&file, text).unwrap();
        let read = umbra::capture::read_clip(&file);
        if name == "equal.json" && read.is_ok() {
            panic!("joints.json with every position equal was read");
        }
        let out = dir.path().join(format!("render-{name}"));
        let err = fails(&cwd(), &["render", s(&run), "--motion", s(&file), "--out", s(&out)]);
        assert!(err.contains(name) && (err.contains(expected) || name == "equal.json"), "{name}: {err}");
        assert!(!out.exists(), "{name}");
        let glb = dir.path().join(format!("{name}.glb"));
        let err = fails(&cwd(), &["export-avatar", s(&run), "--motion", s(&file), "--out", s(&glb)]);
        assert!(err.contains(name), "{name}: {err}");
        assert!(!glb.exists(), "{name}");
    }
    // 10: a light scaled past what f32 renders, and grounds no render can show.
    let err = fails(&cwd(), &["relight", s(&run), "--light", sun, "--intensity", "1e39", "--out", s(&dir.path().join("bright"))]);
    assert!(err.contains("--intensity") && err.contains("beyond"), "{err}");
    for height in ["NaN", "inf", "1e30", "1000"] {
        let out = dir.path().join("ground");
        let err = fails(&cwd(), &["relight", s(&run), "--light", sun, "--ground-height", height, "--out", s(&out)]);
        assert!(err.contains("--ground-height"), "{height}: {err}");
        assert!(!out.exists());
    }
}

#[test]
fn defect_06_units_and_up_that_cannot_be_right_are_refused_saying_what_was_inferred() {
    let dir = TempDir::new("hostile-units");
    let capture = capture(dir.path());
    for (units, expected) in [(Units::M, "in cm (what its size suggests)"), (Units::Mm, "in cm (what its size suggests)")] {
        let err = import_error(&ImportOptions { units: Some(units), ..options(&capture, dir.path().join("wrong-units")) });
        assert!(err.contains("motion.bvh") && err.contains(expected) && err.contains("umbra fits bodies"), "{err}");
    }
    // A Y-up capture said to be Z-up, and the same capture turned Z-up but read as Y-up.
    let err = import_error(&ImportOptions { up: Up::PlusZ, ..options(&capture, dir.path().join("wrong-up")) });
    assert!(err.contains("--up") && err.contains("level about an up"), "{err}");
    let turned = dir.path().join("z-up");
    copy_tree(&capture, &turned);
    let to_z_up = DMat4::from_rotation_x(std::f64::consts::FRAC_PI_2);
    let mut transforms: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(capture.join("transforms.json")).unwrap()).unwrap();
    for frame in transforms["frames"].as_array_mut().unwrap() {
        let r = |i: usize| -> [f64; 4] { std::array::from_fn(|j| frame["transform_matrix"][i][j].as_f64().unwrap()) };
        let m = to_z_up * DMat4::from_cols_array_2d(&[r(0), r(1), r(2), r(3)]).transpose();
        frame["transform_matrix"] = serde_json::json!((0..4).map(|i| m.row(i).to_array().to_vec()).collect::<Vec<_>>());
    }
    std::fs::write(turned.join("transforms.json"), transforms.to_string()).unwrap();
    let motion = bvh::read(&capture.join("motion.bvh")).unwrap();
    let frames: Vec<Vec<DMat4>> = (0..motion.frames.len())
        .map(|k| motion.joint_to_world(k).into_iter().map(|m| DMat4::from_scale(glam::DVec3::splat(0.01)) * to_z_up * m).collect())
        .collect();
    let bones =
        motion.joints.iter().map(|j| umbra::skeleton::Bone { name: j.name.clone(), parent: j.parent, length: j.end_site.map_or(0.1, |e| e.length() / 100.0) });
    let skeleton = umbra::skeleton::Skeleton { bones: bones.collect() };
    let unscaled: Vec<Vec<DMat4>> =
        frames.iter().map(|f| f.iter().map(|m| DMat4::from_cols(m.x_axis * 100.0, m.y_axis * 100.0, m.z_axis * 100.0, m.w_axis)).collect()).collect();
    std::fs::write(turned.join("motion.bvh"), bvh::write(&skeleton, &unscaled, motion.frame_time, 100.0).unwrap()).unwrap();
    let err = import_error(&options(&turned, dir.path().join("z-read-as-y")));
    assert!(err.contains("--up +z"), "{err}");
    import(&ImportOptions { up: Up::PlusZ, ..options(&turned, dir.path().join("z-read-as-z")) }, &|_, _| {}).unwrap();
}

#[test]
fn defects_08_11_13_degenerate_cameras_clips_photos_and_unclear_messages() {
    let dir = TempDir::new("hostile-degenerate");
    let capture = capture(dir.path());
    let transforms = std::fs::read_to_string(capture.join("transforms.json")).unwrap();
    let bvh_text = std::fs::read_to_string(capture.join("motion.bvh")).unwrap();
    let frame_time = bvh_text.lines().find(|l| l.starts_with("Frame Time:")).unwrap().to_string();
    let first_path = {
        let v: serde_json::Value = serde_json::from_str(&transforms).unwrap();
        v["frames"][0]["file_path"].as_str().unwrap().to_string()
    };
    let cases: Vec<(&str, String, &str)> = vec![
        ("transforms.json", transforms.replacen("\"fl_x\": ", "\"fl_x\": 1e-12, \"old_fl_x\": ", 1), "field of view"),
        ("transforms.json", transforms.replacen("\"PINHOLE\"", "\"OPENCV\"", 1).replacen("\"fl_x\": ", "\"k1\": -3.0, \"fl_x\": ", 1), "folds back"),
        ("transforms.json", transforms.replacen("\"w\": 32", "\"w\": 32.5", 1), "whole number of pixels"),
        ("transforms.json", format!("\u{feff}{transforms}"), ""),
        ("transforms.json", transforms.replacen(&format!("\"{first_path}\""), "\"../outside.png\"", 1), "leads outside the capture"),
        ("transforms.json", transforms.replacen(&format!("\"{first_path}\""), "\"/etc/hostname\"", 1), "leads outside the capture"),
        ("motion.bvh", bvh_text.replacen(&frame_time, "Frame Time: 1e300", 1), "Frame Time 1.0000e300"),
    ];
    for (k, (file, text, expected)) in cases.iter().enumerate() {
        assert!(text != &transforms && text != &bvh_text, "case {k} changed nothing");
        let broken = altered(&capture, &dir.path().join(format!("case-{k}")), file, text);
        let out = dir.path().join(format!("out-{k}"));
        if expected.is_empty() {
            import(&options(&broken, out), &|_, _| {}).unwrap();
            continue;
        }
        let err = import_error(&options(&broken, out));
        assert!(err.contains(file) && err.contains(expected), "case {k}: {err}");
    }
    // 8: a truncated JPEG plate.
    let jpeg = dir.path().join("jpeg");
    copy_tree(&capture, &jpeg);
    let plate = image::open(capture.join(&first_path)).unwrap().to_rgb8();
    let jpg = first_path.replace(".png", ".jpg");
    plate.save(jpeg.join(&jpg)).unwrap();
    let bytes = std::fs::read(jpeg.join(&jpg)).unwrap();
    std::fs::write(jpeg.join(&jpg), &bytes[..bytes.len() * 2 / 3]).unwrap();
    std::fs::write(jpeg.join("transforms.json"), transforms.replace(&first_path, &jpg)).unwrap();
    let err = import_error(&options(&jpeg, dir.path().join("from-cut-jpeg")));
    assert!(err.contains(&jpg) && err.contains("truncated"), "{err}");
    // 13: --max-size below an image's worth, a --masks folder that does not exist.
    for size in ["0", "1"] {
        let out = umbra(&cwd(), &["import", s(&capture), "--out", s(&dir.path().join("tiny")), "--light", "sun", "--max-size", size]);
        assert_eq!(out.status.code(), Some(2), "--max-size {size}");
    }
    let err = import_error(&ImportOptions { masks: Some(dir.path().join("no-such-masks")), ..options(&capture, dir.path().join("no-masks")) });
    assert!(err.contains("no-such-masks") && err.contains("--masks"), "{err}");
}

/// A COLMAP text model of `capture`'s training images in `dir`: `name(k)` names image k (its
/// mask the same below `masks/`); `points` writes each image's line of 2D points.
fn colmap(capture: &Path, dir: &Path, name: impl Fn(usize, usize) -> String, points: impl Fn(usize) -> Option<String>) -> (PathBuf, String) {
    let transforms: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(capture.join("transforms.json")).unwrap()).unwrap();
    std::fs::create_dir_all(dir.join("sparse/0")).unwrap();
    std::fs::copy(capture.join("motion.bvh"), dir.join("motion.bvh")).unwrap();
    let mut cameras = String::new();
    let mut images = String::new();
    let train: Vec<&serde_json::Value> = transforms["frames"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| {
            let path = f["file_path"].as_str().unwrap();
            transforms["train_filenames"].as_array().unwrap().iter().any(|n| n.as_str() == Some(path))
        })
        .collect();
    for (k, frame) in train.iter().enumerate() {
        let (fx, fy, cx, cy) = (frame["fl_x"].as_f64().unwrap(), frame["fl_y"].as_f64().unwrap(), frame["cx"].as_f64().unwrap(), frame["cy"].as_f64().unwrap());
        cameras += &format!("{} PINHOLE 32 32 {fx} {fy} {cx} {cy}\n", k + 1);
        let r = |i: usize| -> [f64; 4] { std::array::from_fn(|j| frame["transform_matrix"][i][j].as_f64().unwrap()) };
        let opengl = DMat4::from_cols_array_2d(&[r(0), r(1), r(2), r(3)]).transpose();
        let world_to_camera = (opengl * DMat4::from_diagonal(glam::DVec4::new(1.0, -1.0, -1.0, 1.0))).inverse();
        let (_, q, t) = world_to_camera.to_scale_rotation_translation();
        let time = frame["time"].as_f64().unwrap();
        let frame_index = (time * 30.0).round() as usize;
        let image_name = name(k, frame_index);
        images += &format!("{} {} {} {} {} {} {} {} {} {image_name}\n", k + 1, q.w, q.x, q.y, q.z, t.x, t.y, t.z, k + 1);
        if let Some(line) = points(k) {
            images += &format!("{line}\n");
        }
        for (sub, key) in [("images", "file_path"), ("masks", "mask_path")] {
            let target = dir.join(sub).join(&image_name);
            std::fs::create_dir_all(target.parent().unwrap()).unwrap();
            std::fs::copy(capture.join(frame[key].as_str().unwrap()), target).unwrap();
        }
    }
    std::fs::write(dir.join("sparse/0/cameras.txt"), cameras).unwrap();
    std::fs::write(dir.join("sparse/0/images.txt"), &images).unwrap();
    (dir.to_path_buf(), images)
}

#[test]
fn defects_07_12_13_colmap_models_read_by_their_fields_in_a_folder_per_camera() {
    let dir = TempDir::new("hostile-colmap");
    let capture = capture(dir.path());
    let frame_time = bvh::read(&capture.join("motion.bvh")).unwrap().frame_time;
    assert!((frame_time - 1.0 / 30.0).abs() < 1e-6, "the test names frames at 30 per second: {frame_time}");
    let flat = |k: usize, f: usize| format!("c{k}_frame_{f:04}.png");
    // 12: a folder per camera, the images of one name in each.
    let (rig, _) = colmap(&capture, &dir.path().join("rig"), |k, f| format!("cam{k:02}/{f:06}.png"), |_| Some(String::new()));
    let out = dir.path().join("from-rig");
    import(&options(&rig, out.clone()), &|_, _| {}).unwrap();
    let imported = Scene::load(&out).unwrap();
    let train = imported.views.iter().filter(|v| v.split == umbra::scene::Split::Train).count();
    assert!(train >= 6 && imported.views.iter().all(|v| v.mask.is_some()), "{train}");
    // 7: without any line of 2D points, with one missing, and with lines of points: all images.
    for (tag, points) in [("none", 0usize), ("one-missing", 1), ("all", 2)] {
        let (model, _) = colmap(&capture, &dir.path().join(tag), flat, |k| match points {
            0 => None,
            1 if k == 1 => None,
            _ => Some(format!("{}.5 17.25 -1 3.0 4.0 {k}", 10 + k)),
        });
        let out = dir.path().join(format!("from-{tag}"));
        import(&options(&model, out.clone()), &|_, _| {}).unwrap();
        assert_eq!(Scene::load(&out).unwrap().views.len(), train, "{tag}");
    }
    let (model, images) = colmap(&capture, &dir.path().join("edited"), flat, |_| Some(String::new()));
    let images_txt = model.join("sparse/0/images.txt");
    let cameras_txt = model.join("sparse/0/cameras.txt");
    let cameras = std::fs::read_to_string(&cameras_txt).unwrap();
    let first = images.lines().next().unwrap().to_string();
    let cases: Vec<(&Path, String, &str)> = vec![
        (&images_txt, images.replacen(&first, &first.replacen("1 ", "abc ", 1), 1), "line 1: image id \"abc\""),
        (&images_txt, format!("{images}{first}\n"), "a second image 1"),
        (&cameras_txt, format!("{cameras}{}", cameras.lines().next().unwrap()), "a second camera 1"),
        (
            &cameras_txt,
            cameras.replacen(cameras.lines().next().unwrap(), "1 PINHOLE 32 32 1e30 1e30 16 16", 1),
            "line 1: camera 1: a focal length of 1000000000000000000000000000000",
        ),
        (&images_txt, images.replacen(&flat(0, 0), "../../outside.png", 1), "leads outside the capture"),
    ];
    for (k, (file, text, expected)) in cases.iter().enumerate() {
        let original = std::fs::read_to_string(file).unwrap();
        std::fs::write(file, text).unwrap();
        let err = import_error(&options(&model, dir.path().join(format!("colmap-out-{k}"))));
        assert!(err.contains(s(file)) && err.contains(expected), "case {k}: {err}");
        std::fs::write(file, original).unwrap();
    }
}
