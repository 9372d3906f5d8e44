//! A fitted avatar driven by a new motion and rendered at any size: a clip written from the
//! scene's own frames drives the bones exactly and renders what the scene's poses render; a
//! clip of another body is retargeted; joints are matched by name; `--size` scales the cameras.

mod common;

use common::{short_run, succeeds, TempDir};
use glam::DMat4;
use std::path::Path;
use umbra::capture::{bvh, retarget};
use umbra::scene::Scene;

fn max_difference(a: &DMat4, b: &DMat4) -> f64 {
    (*a - *b).to_cols_array().iter().fold(0.0f64, |m, d| m.max(d.abs()))
}

/// The scene's frames `chosen` as a centimetre BVH.
fn clip_of(scene: &Scene, chosen: &[usize]) -> String {
    let frames: Vec<Vec<DMat4>> = chosen.iter().map(|&f| scene.frames[f].pose.bone_to_world.clone()).collect();
    bvh::write(&scene.skeleton, &frames, 1.0 / 30.0, 100.0).unwrap()
}

#[test]
fn a_clip_written_from_the_scenes_frames_drives_the_bones_exactly() {
    let scene = Scene::load(&umbra_scene()).unwrap();
    let all: Vec<usize> = (0..scene.frames.len()).collect();
    let motion = bvh::parse(&clip_of(&scene, &all), Path::new("clip.bvh")).unwrap();
    let driven = retarget::drive(&scene.skeleton, &scene.frames[0].pose, &motion, 0.01).unwrap();
    assert!(driven.direct && driven.unmatched.is_empty());
    for (pose, frame) in driven.poses.iter().zip(&scene.frames) {
        for (a, b) in pose.bone_to_world.iter().zip(&frame.pose.bone_to_world) {
            assert!(max_difference(a, b) < 1e-6, "{a} {b}");
        }
    }
}

/// A shipped scene (the walking human), for its skeleton and poses.
fn umbra_scene() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("datasets-synthetic/human-sun-128")
}

#[test]
fn a_clip_of_another_body_is_retargeted_and_joints_match_by_plain_name() {
    let scene = Scene::load(&umbra_scene()).unwrap();
    let all: Vec<usize> = (0..scene.frames.len()).collect();
    // The same motion on a body 1.25 times larger, its joints named as a Mixamo export names
    // them, and one joint no bone is named after.
    let mut motion = bvh::parse(&clip_of(&scene, &all), Path::new("clip.bvh")).unwrap();
    for joint in &mut motion.joints {
        joint.offset *= 1.25;
        joint.end_site = joint.end_site.map(|e| e * 1.25);
        joint.name = format!("mixamorig:{}", joint.name.to_uppercase());
    }
    for values in &mut motion.frames {
        values[..3].iter_mut().for_each(|v| *v *= 1.25);
    }
    let mut extra = motion.joints[0].clone();
    extra.name = "prop".into();
    extra.parent = Some(0);
    extra.channels.clear();
    extra.end_site = Some(glam::DVec3::new(0.0, 10.0, 0.0));
    motion.joints.push(extra);
    let driven = retarget::drive(&scene.skeleton, &scene.frames[0].pose, &motion, 0.01).unwrap();
    assert!(!driven.direct);
    assert_eq!(driven.unmatched, vec!["prop".to_string()]);
    assert!((driven.scale - 0.8).abs() < 1e-6, "scale {}", driven.scale);
    // Each bone's head lies where the scene's does (the travel of the larger body scaled
    // back), and its +Y runs along its bone in the clip: toward its bone child's head (import's
    // bone rule), a leaf's along the scene's bone (its End Site).
    for (pose, frame) in driven.poses.iter().zip(&scene.frames) {
        let heads: Vec<glam::DVec3> = frame.pose.bone_to_world.iter().map(|m| m.w_axis.truncate()).collect();
        for (b, a) in pose.bone_to_world.iter().enumerate() {
            assert!(a.w_axis.truncate().distance(heads[b]) < 1e-6, "bone {b}: head");
            let along = match umbra::capture::bones::bone_child(&motion.joints, b) {
                Some(c) => (heads[c] - heads[b]).normalize(),
                None => frame.pose.bone_to_world[b].y_axis.truncate(),
            };
            assert!(a.y_axis.truncate().distance(along) < 1e-6, "bone {b}: {} against {along}", a.y_axis);
        }
    }
    // A bone without a joint is refused, naming it.
    motion.joints[3].name = "elsewhere".into();
    let error = retarget::drive(&scene.skeleton, &scene.frames[0].pose, &motion, 0.01).err().unwrap();
    assert!(error.contains(&scene.skeleton.bones[3].name), "{error}");
}

fn read_png(path: &Path) -> umbra::imageio::RgbImage {
    umbra::imageio::read_rgb(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn a_clip_of_the_test_pose_renders_what_the_fit_renders_in_that_pose_at_any_size() {
    let (dir, scene_dir, run) = short_run("animate");
    let scene = Scene::load(&scene_dir).unwrap();
    let test_frame = scene.views.iter().find(|v| v.split == umbra::scene::Split::Test).unwrap().frame;
    let clip = dir.path().join("clip.bvh");
    std::fs::write(&clip, clip_of(&scene, &[test_frame, 0])).unwrap();
    let cwd = std::env::current_dir().unwrap();
    let (motion_dir, views_dir) = (dir.path().join("motion"), dir.path().join("views"));
    let path = |p: &Path| p.to_str().unwrap().to_string();
    let frame = test_frame.to_string();
    succeeds(&cwd, &["render", &path(&run), "--motion", &path(&clip), "--camera", "1", "--size", "40x32", "--out", &path(&motion_dir)]);
    succeeds(&cwd, &["render", &path(&run), "--camera", "1", "--frame", &frame, "--size", "40x32", "--out", &path(&views_dir)]);
    let driven = read_png(&motion_dir.join("f0000.png"));
    let posed = read_png(&views_dir.join(format!("c01_f{test_frame:04}.png")));
    assert_eq!((driven.width, driven.height), (40, 32));
    assert!(motion_dir.join("f0001.png").is_file() && motion_dir.join("animation.png").is_file());
    let psnr = umbra::metrics::score(&driven, &posed, None).psnr;
    assert!(psnr >= 35.0, "the clip's render of the test pose against the fit's: {psnr:.2} dB");
    // A second motion render replaces the first; a folder of someone else's is refused.
    succeeds(&cwd, &["render", &path(&run), "--motion", &path(&clip), "--size", "16x16", "--out", &path(&motion_dir)]);
    let theirs = TempDir::new("animate-theirs");
    std::fs::write(theirs.path().join("notes.txt"), "mine").unwrap();
    common::fails(&cwd, &["render", &path(&run), "--motion", &path(&clip), "--out", &path(theirs.path())]);
    assert_eq!(std::fs::read_dir(theirs.path()).unwrap().count(), 1);
}

#[test]
fn a_ground_receives_the_shadow_as_rgba_to_composite() {
    let (dir, _scene, run) = short_run("ground");
    let cwd = std::env::current_dir().unwrap();
    let out = dir.path().join("ground");
    let path = |p: &Path| p.to_str().unwrap().to_string();
    let sun = dir.path().join("sun.json");
    // A low sun, so the shadow falls beside the body where the ground shows.
    std::fs::write(&sun, r#"{"type": "directional", "direction": [1, 0.6, 0.3], "irradiance": [2, 2, 2], "ambient": [0.1, 0.1, 0.1]}"#).unwrap();
    succeeds(&cwd, &["relight", &path(&run), "--light", &path(&sun), "--camera", "0", "--frame", "0", "--size", "48x48", "--ground", "--out", &path(&out)]);
    let image = image::open(out.join("c00_f0000.png")).unwrap();
    assert_eq!(image.color(), image::ColorType::Rgba8, "an RGBA picture to composite");
    let pixels: Vec<[u8; 4]> = image.to_rgba8().pixels().map(|p| p.0).collect();
    // Clear ground, body, and shadow: black, partly or wholly opaque, where no body is.
    assert!(pixels.iter().any(|p| p[3] == 0), "some ground is clear");
    assert!(pixels.iter().any(|p| p[3] > 0 && p[0..3] == [0, 0, 0]), "some ground is in shadow");
    assert!(pixels.iter().any(|p| p[3] == 255 && p[0..3] != [0, 0, 0]), "the body is opaque");
    // Without --ground the picture has no alpha.
    let plain = dir.path().join("plain");
    succeeds(&cwd, &["relight", &path(&run), "--light", &path(&sun), "--camera", "0", "--frame", "0", "--out", &path(&plain)]);
    assert_eq!(image::open(plain.join("c00_f0000.png")).unwrap().color(), image::ColorType::Rgb8);
    // A visibility basis renders the avatar alone: --ground is refused with it.
    common::fails(&cwd, &["relight", &path(&run), "--light", &path(&sun), "--basis", "8", "--ground", "--out", &path(&dir.path().join("b"))]);
}

#[test]
fn per_frame_joint_transforms_drive_the_bones_as_the_bvh_does() {
    let scene = Scene::load(&umbra_scene()).unwrap();
    let skeleton = &scene.skeleton;
    let tips: serde_json::Map<String, serde_json::Value> = (0..skeleton.len())
        .filter(|&b| !skeleton.bones.iter().any(|c| c.parent == Some(b)))
        .map(|b| (skeleton.bones[b].name.clone(), serde_json::json!([0.0, skeleton.bones[b].length, 0.0])))
        .collect();
    let frames: Vec<serde_json::Value> = scene
        .frames
        .iter()
        .map(|f| {
            let rotations: Vec<Vec<Vec<f64>>> = f.pose.bone_to_world.iter().map(|m| (0..3).map(|r| (0..3).map(|c| m.row(r)[c]).collect()).collect()).collect();
            let positions: Vec<[f64; 3]> = f.pose.bone_to_world.iter().map(|m| m.w_axis.truncate().to_array()).collect();
            serde_json::json!({"rotations": rotations, "positions": positions})
        })
        .collect();
    let joints = serde_json::json!({
        "frame_time": 1.0 / 30.0,
        "joints": skeleton.bones.iter().map(|b| serde_json::json!({"name": b.name, "parent": b.parent})).collect::<Vec<_>>(),
        "tips": tips,
        "frames": frames,
    });
    let dir = TempDir::new("animate-joints");
    let file = dir.path().join("joints.json");
    std::fs::write(&file, serde_json::to_string(&joints).unwrap()).unwrap();
    let motion = umbra::capture::read_clip(&file).unwrap();
    let driven = retarget::drive(skeleton, &scene.frames[0].pose, &motion, 1.0).unwrap();
    assert!(driven.direct, "joint transforms in metres at the bones' own offsets drive them directly");
    for (pose, frame) in driven.poses.iter().zip(&scene.frames) {
        for (a, b) in pose.bone_to_world.iter().zip(&frame.pose.bone_to_world) {
            assert!(max_difference(a, b) < 1e-6, "{a} {b}");
        }
    }
}
