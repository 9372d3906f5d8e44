//! Importing captures as people have them: a synth scene exported as nerfstudio + a centimetre
//! BVH + plates comes back as the same scene; BVH channel orders, units and up axes; lens
//! distortion removed against an independent implementation of OpenCV's model; malformed input
//! refused with the file and the line or JSON path, and nothing written.

mod common;

use common::TempDir;
use glam::{DMat3, DMat4, DQuat, DVec3};
use std::path::{Path, PathBuf};
use umbra::capture::{bvh, import, ImportOptions, Intrinsics, Units, Up};
use umbra::scene::Scene;
use umbra::synth::{Export, SynthOptions};

fn synth_options(export: Option<Export>) -> SynthOptions {
    common::small_capture_options(export)
}

fn options(capture: &Path, out: PathBuf) -> ImportOptions {
    common::import_options(capture, out)
}

/// A scene and the same scene exported as a capture, in `dir`.
fn scene_and_capture(dir: &Path) -> (PathBuf, PathBuf) {
    let (scene, capture) = (dir.join("scene"), dir.join("capture"));
    umbra::synth::generate(&synth_options(None), &scene, false, |_, _| {}).unwrap();
    umbra::synth::generate(&synth_options(Some(Export::Nerfstudio)), &capture, false, |_, _| {}).unwrap();
    (scene, capture)
}

fn stem(path: &Path) -> String {
    path.file_stem().unwrap().to_string_lossy().into_owned()
}

fn max_difference(a: &DMat4, b: &DMat4) -> f64 {
    (*a - *b).to_cols_array().iter().fold(0.0f64, |m, d| m.max(d.abs()))
}

#[test]
fn a_scene_exported_as_nerfstudio_and_a_centimetre_bvh_imports_as_the_same_scene() {
    let dir = TempDir::new("capture-round-trip");
    let (scene_dir, capture) = scene_and_capture(dir.path());
    let out = dir.path().join("imported");
    let report = import(&options(&capture, out.clone()), &|_, _| {}).unwrap();
    assert!(report.assumed.iter().any(|a| a.starts_with("units: cm (inferred")), "{:?}", report.assumed);
    let (original, imported) = (Scene::load(&scene_dir).unwrap(), Scene::load(&out).unwrap());
    assert_eq!(imported.views.len(), original.views.len(), "every image is under the training light");
    assert_eq!(imported.cameras.len(), original.cameras.len(), "images of one pose and intrinsics share a camera");
    for view in &imported.views {
        let twin = original.views.iter().find(|v| stem(&v.path) == stem(&view.path)).expect("each image keeps its name");
        let (a, b) = (&imported.cameras[view.camera], &original.cameras[twin.camera]);
        assert!(max_difference(&a.camera_to_world, &b.camera_to_world) < 1e-6, "{}: camera pose", stem(&view.path));
        assert!((a.fx - b.fx).abs() + (a.fy - b.fy).abs() + (a.cx - b.cx).abs() + (a.cy - b.cy).abs() < 1e-9 && a.width == b.width);
        assert_eq!(view.split, twin.split);
        // Its frame: the same poses (the joints' places, below).
        assert_eq!(imported.frames[view.frame].index as usize, twin.frame);
        assert_eq!(view.mask, twin.mask, "{}: mask", stem(&view.path));
        let mask = twin.mask.as_ref().unwrap();
        // Outside the mask, what the camera saw is kept near the mask's edge where the
        // camera's plate is known (a training image of a static camera), blacked elsewhere.
        let near = umbra::silhouette::near_body(mask, umbra::silhouette::EDGE_BAND);
        let (photo, _) = umbra::photo::read_photo(&capture.join("images").join(view.path.file_name().unwrap())).unwrap();
        for (p, &near) in near.iter().enumerate() {
            let kept = view.plate.as_ref().is_some_and(|plate| near && plate.known.foreground[p]);
            if mask.foreground[p] {
                assert_eq!(view.colour.pixel(p), twin.colour.pixel(p), "{}: pixel {p} inside the mask", stem(&view.path));
            } else if kept {
                let byte = |v: [f32; 3]| v.map(umbra::imageio::linear_to_srgb8);
                assert_eq!(byte(view.colour.pixel(p)), byte(photo.pixels[p]), "{}: pixel {p} by the mask's edge", stem(&view.path));
            } else {
                assert_eq!(view.colour.pixel(p), [0.0; 3], "the plate's background is blacked");
            }
        }
    }
    // Bones: the same names, parents and heads in every frame; each bone's frame the original's
    // turned by one fixed rotation (the bone rule), the identity where the bone's child sits at
    // its tail (pelvis -> spine, spine -> chest).
    assert_eq!(
        imported.skeleton.bones.iter().map(|b| (&b.name, b.parent)).collect::<Vec<_>>(),
        original.skeleton.bones.iter().map(|b| (&b.name, b.parent)).collect::<Vec<_>>()
    );
    for b in 0..original.skeleton.len() {
        let turn = |f: usize| original.frames[f].pose.bone_to_world[b].inverse() * imported.frames[f].pose.bone_to_world[b];
        for f in 0..original.frames.len() {
            let (a, o) = (imported.frames[f].pose.bone_to_world[b], original.frames[f].pose.bone_to_world[b]);
            assert!(a.w_axis.truncate().distance(o.w_axis.truncate()) < 1e-5, "bone {b} frame {f}: head");
            assert!(max_difference(&turn(f), &turn(0)) < 1e-5, "bone {b} frame {f}: a fixed turn from the original");
        }
        // Every bone but the shins has its bone child at its tail (the foot hangs off the shin's
        // axis): the same frame and length. A shin points at its foot's head.
        let name = original.skeleton.bones[b].name.as_str();
        if name.starts_with("shin") {
            let foot = original.skeleton.bones.iter().position(|f| f.parent == Some(b)).unwrap();
            let pose = &imported.frames[0].pose;
            let tip = pose.to_world(b, DVec3::new(0.0, imported.skeleton.bones[b].length, 0.0));
            assert!(tip.distance(pose.bone_to_world[foot].w_axis.truncate()) < 1e-5, "{name} points at its foot's head");
        } else {
            assert!(max_difference(&turn(0), &DMat4::IDENTITY) < 1e-5, "{name}: its child at its tail, its frame unturned");
            assert!((imported.skeleton.bones[b].length - original.skeleton.bones[b].length).abs() < 1e-6, "{name}: length");
        }
    }
}

#[test]
fn units_and_up_axes_give_the_same_scene() {
    let dir = TempDir::new("capture-units");
    let (_, capture) = scene_and_capture(dir.path());
    let reference = dir.path().join("reference");
    import(&options(&capture, reference.clone()), &|_, _| {}).unwrap();
    let reference = Scene::load(&reference).unwrap();
    // The same capture in metres, +Z up: every position divided by 100, turned so +Y becomes +Z.
    let turned = dir.path().join("metres-z-up");
    std::fs::create_dir_all(&turned).unwrap();
    for sub in ["images", "masks"] {
        copy_dir(&capture.join(sub), &turned.join(sub));
    }
    let to_z_up = DMat4::from_rotation_x(std::f64::consts::FRAC_PI_2);
    let mut transforms: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(capture.join("transforms.json")).unwrap()).unwrap();
    for frame in transforms["frames"].as_array_mut().unwrap() {
        let m = matrix(&frame["transform_matrix"]);
        let mut moved = to_z_up * m;
        moved.w_axis = (moved.w_axis.truncate() / 100.0).extend(1.0);
        frame["transform_matrix"] = rows(&moved);
    }
    std::fs::write(turned.join("transforms.json"), serde_json::to_string(&transforms).unwrap()).unwrap();
    let motion = bvh::read(&capture.join("motion.bvh")).unwrap();
    std::fs::write(turned.join("motion.bvh"), rewritten_clip(&motion, |m| to_z_up * m, 1.0)).unwrap();
    let out = dir.path().join("from-metres-z-up");
    let report = import(&ImportOptions { up: Up::PlusZ, ..options(&turned, out.clone()) }, &|_, _| {}).unwrap();
    assert!(report.assumed.iter().any(|a| a.starts_with("units: m (inferred")), "{:?}", report.assumed);
    let scene = Scene::load(&out).unwrap();
    for (a, b) in scene.cameras.iter().zip(&reference.cameras) {
        assert!(max_difference(&a.camera_to_world, &b.camera_to_world) < 1e-6);
    }
    for (f, g) in scene.frames.iter().zip(&reference.frames) {
        for (a, b) in f.pose.bone_to_world.iter().zip(&g.pose.bone_to_world) {
            assert!(max_difference(a, b) < 1e-5);
        }
    }
    // Stated units that make the body no size a body has are refused, saying what its size
    // suggests: the metre capture read as centimetres would be 100 times smaller.
    let small = dir.path().join("stated-cm");
    let err = import(&ImportOptions { up: Up::PlusZ, units: Some(Units::Cm), ..options(&turned, small.clone()) }, &|_, _| {}).unwrap_err().to_string();
    assert!(err.contains("in cm (--units)") && err.contains("in m (what its size suggests)"), "{err}");
    assert!(!small.exists());
}

/// `motion` (a centimetre clip) written again: each joint's frame changed by `change`, in metres
/// times `units` per metre, leaves as long as their End Sites.
fn rewritten_clip(motion: &bvh::Motion, change: impl Fn(DMat4) -> DMat4, units: f64) -> String {
    let bones = motion.joints.iter().map(|j| umbra::skeleton::Bone {
        name: j.name.clone(),
        parent: j.parent,
        length: j.end_site.map(|e| e.length() / 100.0).unwrap_or(0.1),
    });
    let skeleton = umbra::skeleton::Skeleton { bones: bones.collect() };
    let frames: Vec<Vec<DMat4>> = (0..motion.frames.len())
        .map(|k| {
            motion
                .joint_to_world(k)
                .into_iter()
                .map(|m| {
                    let mut moved = change(m);
                    moved.w_axis = (moved.w_axis.truncate() / 100.0).extend(1.0);
                    moved
                })
                .collect()
        })
        .collect();
    bvh::write(&skeleton, &frames, motion.frame_time, units).unwrap()
}

fn matrix(value: &serde_json::Value) -> DMat4 {
    let r = |i: usize| -> [f64; 4] { std::array::from_fn(|j| value[i][j].as_f64().unwrap()) };
    DMat4::from_cols_array_2d(&[r(0), r(1), r(2), r(3)]).transpose()
}

fn rows(m: &DMat4) -> serde_json::Value {
    serde_json::json!((0..4).map(|r| m.row(r).to_array().to_vec()).collect::<Vec<_>>())
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        std::fs::copy(&path, to.join(path.file_name().unwrap())).unwrap();
    }
}

/// A joint's frame composed independently: quaternions about the axes in the file's order.
fn expected(offset: DVec3, order: &[(char, f64)]) -> DMat4 {
    let q = order.iter().fold(DQuat::IDENTITY, |q, &(axis, degrees)| {
        let a = match axis {
            'X' => DVec3::X,
            'Y' => DVec3::Y,
            _ => DVec3::Z,
        };
        q * DQuat::from_axis_angle(a, degrees.to_radians())
    });
    DMat4::from_rotation_translation(q, offset)
}

#[test]
fn bvh_channels_in_any_order_with_root_translation_and_end_sites() {
    let text = "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Yrotation Xrotation Zrotation\n\
                JOINT Knee\n {\n  OFFSET 0 -40 5\n  CHANNELS 3 Xrotation Zrotation Yrotation\n  End Site\n  {\n   OFFSET 0 -45 0\n  }\n }\n}\n\
                MOTION\nFrames: 2\nFrame Time: 0.04\n1 90 2 10 20 30 40 -50 60\n0 0 0 0 0 0 0 0 0\n";
    let motion = bvh::parse(text, Path::new("clip.bvh")).unwrap();
    assert_eq!(motion.joints.len(), 2);
    assert_eq!(motion.joints[1].end_site, Some(DVec3::new(0.0, -45.0, 0.0)));
    assert!((motion.time(1) - 0.04).abs() < 1e-12);
    let world = motion.joint_to_world(0);
    let hips = expected(DVec3::new(1.0, 90.0, 2.0), &[('Y', 10.0), ('X', 20.0), ('Z', 30.0)]);
    let knee = hips * expected(DVec3::new(0.0, -40.0, 5.0), &[('X', 40.0), ('Z', -50.0), ('Y', 60.0)]);
    assert!(max_difference(&world[0], &hips) < 1e-12 && max_difference(&world[1], &knee) < 1e-12);
    // Rotation only, as written: a fixed rotation matrix.
    assert!((DMat3::from_mat4(world[1]).determinant() - 1.0).abs() < 1e-12);
}

#[test]
fn malformed_captures_are_refused_naming_the_file_and_the_place_and_nothing_is_written() {
    let dir = TempDir::new("capture-malformed");
    let (_, capture) = scene_and_capture(dir.path());
    let bvh_text = std::fs::read_to_string(capture.join("motion.bvh")).unwrap();
    let transforms = std::fs::read_to_string(capture.join("transforms.json")).unwrap();
    let cases: Vec<(&str, String, String, &str)> = vec![
        ("motion.bvh", bvh_text.replacen("CHANNELS 3 Zrotation", "CHANNELS 3 Wrotation", 1), "transforms.json".into(), "line 9: unknown channel"),
        ("motion.bvh", bvh_text.trim_end().rsplit_once(' ').unwrap().0.to_string(), "transforms.json".into(), "MOTION section holds"),
        ("motion.bvh", bvh_text.replacen("Frame Time: ", "Frame Time: -", 1), "transforms.json".into(), "Frame Time"),
        ("transforms.json", transforms.replacen("\"fl_x\": ", "\"fl_x\": -", 1), "motion.bvh".into(), "frames[0]: fl_x, fl_y, w and h must be positive"),
        (
            "transforms.json",
            transforms.replacen("\"transform_matrix\": [", "\"transform_matrix\": [[1,0,0,0],", 1),
            "motion.bvh".into(),
            "frames[0].transform_matrix",
        ),
        ("transforms.json", transforms.replacen("\"time\": 0.0", "\"time\": 99.0", 1), "motion.bvh".into(), "frames[0].file_path: time 99"),
        (
            "transforms.json",
            transforms.replacen("\"camera_model\": \"PINHOLE\"", "\"camera_model\": \"OPENCV_FISHEYE\"", 1),
            "motion.bvh".into(),
            "camera_model \"OPENCV_FISHEYE\"",
        ),
        // A training image also listed for testing would score the fit on what it saw.
        (
            "transforms.json",
            transforms.replacen("\"test_filenames\": [", "\"test_filenames\": [\n    \"images/c00_f0000_sun.png\",", 1),
            "motion.bvh".into(),
            "frames[0].file_path: listed in train_filenames and test_filenames",
        ),
        (
            "transforms.json",
            transforms.replacen("\"test_filenames\": [", "\"test_filenames\": [\n    \"images/c09_f0000_sun.png\",", 1),
            "motion.bvh".into(),
            "test_filenames[0]: \"images/c09_f0000_sun.png\" names none of the frames' file_path",
        ),
    ];
    for (k, (file, text, _, expected)) in cases.iter().enumerate() {
        let broken = dir.path().join(format!("broken-{k}"));
        copy_dir(&capture.join("images"), &broken.join("images"));
        copy_dir(&capture.join("masks"), &broken.join("masks"));
        std::fs::write(broken.join("motion.bvh"), &bvh_text).unwrap();
        std::fs::write(broken.join("transforms.json"), &transforms).unwrap();
        std::fs::write(broken.join(file), text).unwrap();
        let out = dir.path().join(format!("out-{k}"));
        let err = import(&options(&broken, out.clone()), &|_, _| {}).unwrap_err().to_string();
        assert!(err.contains(file) && err.contains(expected), "case {k}: {err}");
        assert!(!out.exists(), "case {k}: nothing written");
    }
    // An image whose size differs from its camera's, and a missing mask.
    let broken = dir.path().join("broken-image");
    copy_dir(&capture.join("images"), &broken.join("images"));
    copy_dir(&capture.join("masks"), &broken.join("masks"));
    std::fs::copy(capture.join("motion.bvh"), broken.join("motion.bvh")).unwrap();
    std::fs::write(broken.join("transforms.json"), transforms.replacen("\"w\": 32", "\"w\": 33", 1)).unwrap();
    let out = dir.path().join("out-image");
    let err = import(&options(&broken, out.clone()), &|_, _| {}).unwrap_err().to_string();
    assert!(err.contains("is 32x32, its camera (frames[0].file_path) says 33x32"), "{err}");
    assert!(!out.exists() && !dir.path().join(".out-image.importing").exists());
    // An existing folder with anything in it is never written into.
    let occupied = dir.path().join("occupied");
    std::fs::create_dir_all(&occupied).unwrap();
    std::fs::write(occupied.join("notes.txt"), "mine").unwrap();
    let err = import(&options(&capture, occupied.clone()), &|_, _| {}).unwrap_err().to_string();
    assert!(err.contains("not an empty folder"), "{err}");
    assert_eq!(std::fs::read_to_string(occupied.join("notes.txt")).unwrap(), "mine");
}

/// OpenCV's `undistortPoints`, written from its documentation: the pinhole point whose
/// distortion lands on the distorted one, by fixed-point iteration.
fn opencv_undistort_point(xd: f64, yd: f64, k: [f64; 5]) -> (f64, f64) {
    let [k1, k2, p1, p2, k3] = k;
    let (mut x, mut y) = (xd, yd);
    for _ in 0..50 {
        let r2 = x * x + y * y;
        let icdist = 1.0 / (1.0 + ((k3 * r2 + k2) * r2 + k1) * r2);
        let delta_x = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let delta_y = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        x = (xd - delta_x) * icdist;
        y = (yd - delta_y) * icdist;
    }
    (x, y)
}

#[test]
fn lens_distortion_is_removed_as_opencv_models_it() {
    // A smooth pattern in the pinhole image's normalised coordinates, photographed through a
    // lens: each distorted pixel shows the pattern where OpenCV's inverse sends it.
    let pattern = |x: f64, y: f64| [(0.5 + 0.4 * (6.0 * x).sin()) as f32, (0.5 + 0.4 * (5.0 * y).cos()) as f32, (0.3 + 0.2 * (x + y)) as f32];
    let k = [-0.21, 0.05, 0.0012, -0.0008, -0.004];
    let camera = Intrinsics { fx: 180.0, fy: 175.0, cx: 96.3, cy: 71.8, width: 192, height: 144 };
    let mut photo = umbra::imageio::RgbImage::new(camera.width, camera.height);
    for j in 0..camera.height {
        for i in 0..camera.width {
            let (xd, yd) = ((i as f64 + 0.5 - camera.cx) / camera.fx, (j as f64 + 0.5 - camera.cy) / camera.fy);
            let (x, y) = opencv_undistort_point(xd, yd, k);
            photo.set(i, j, pattern(x, y));
        }
    }
    let distortion = umbra::capture::Distortion { model: "OPENCV".into(), k1: k[0], k2: k[1], p1: k[2], p2: k[3], k3: k[4] };
    let pinhole = umbra::capture::distortion::undistort_colour(&photo, &camera, &distortion);
    // Away from the border (where the lens leaves no source), each pinhole pixel shows the
    // pattern at its own normalised coordinates, to the bilinear resampling's error.
    let mut worst = 0.0f32;
    for j in 12..camera.height - 12 {
        for i in 12..camera.width - 12 {
            let (x, y) = ((i as f64 + 0.5 - camera.cx) / camera.fx, (j as f64 + 0.5 - camera.cy) / camera.fy);
            let truth = pattern(x, y);
            let got = pinhole.get(i, j);
            worst = worst.max((0..3).map(|c| (got[c] - truth[c]).abs()).fold(0.0, f32::max));
        }
    }
    assert!(worst < 2e-3, "worst difference {worst}");
    // And the forward model against OpenCV's inverse: distort(undistort(p)) = p.
    for (xd, yd) in [(0.3, -0.2), (-0.5, 0.4), (0.05, 0.6)] {
        let (x, y) = opencv_undistort_point(xd, yd, k);
        let (u, v) = distortion.distort(x, y);
        assert!((u - xd).abs() < 1e-9 && (v - yd).abs() < 1e-9, "({xd}, {yd})");
    }
}

#[test]
fn a_capture_whose_cameras_and_motion_disagree_is_refused_with_the_figure() {
    let dir = TempDir::new("capture-check");
    let (_, capture) = scene_and_capture(dir.path());
    let agreeing = import(&options(&capture, dir.path().join("agreeing")), &|_, _| {}).unwrap();
    assert!(agreeing.score > 0.95, "{}", agreeing.score);
    assert!(dir.path().join("agreeing/check.png").is_file(), "the contact sheet");
    let transforms: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(capture.join("transforms.json")).unwrap()).unwrap();
    let motion = bvh::read(&capture.join("motion.bvh")).unwrap();
    let flip = DMat4::from_diagonal(glam::DVec4::new(1.0, -1.0, -1.0, 1.0));
    let mut opencv = transforms.clone();
    for frame in opencv["frames"].as_array_mut().unwrap() {
        frame["transform_matrix"] = rows(&(matrix(&frame["transform_matrix"]) * flip));
    }
    let z_up = DMat4::from_rotation_x(std::f64::consts::FRAC_PI_2);
    // Cameras in OpenCV axes are upside down (their image rows are level about -Y) and a metre
    // clip read as centimetres is a body 1.6 cm across: both are named before the bones are
    // projected.
    let disagree = "the cameras and the motion disagree";
    let cases: Vec<(&str, serde_json::Value, String, &str)> = vec![
        ("cameras in OpenCV axes", opencv, std::fs::read_to_string(capture.join("motion.bvh")).unwrap(), "180 degrees from its +Y"),
        ("motion in metres, cameras in centimetres", transforms.clone(), rewritten_clip(&motion, |m| m, 1.0), "in m (what its size suggests)"),
        ("motion +Z up, cameras +Y up", transforms.clone(), rewritten_clip(&motion, |m| z_up * m, 100.0), disagree),
    ];
    for (what, cameras, clip, expected) in cases {
        let broken = dir.path().join(what.replace(' ', "-").replace(',', ""));
        copy_dir(&capture.join("images"), &broken.join("images"));
        copy_dir(&capture.join("masks"), &broken.join("masks"));
        std::fs::write(broken.join("transforms.json"), serde_json::to_string(&cameras).unwrap()).unwrap();
        std::fs::write(broken.join("motion.bvh"), clip).unwrap();
        let out = dir.path().join(format!("{}-out", broken.file_name().unwrap().to_string_lossy()));
        let err = import(&ImportOptions { units: Some(Units::Cm), ..options(&broken, out.clone()) }, &|_, _| {}).unwrap_err().to_string();
        assert!(err.contains(expected) && (expected != disagree || err.contains("% of the bones' points")), "{what}: {err}");
        assert!(!out.exists(), "{what}: nothing written");
    }
}

/// A COLMAP text model written from the scene (world-to-camera quaternions, one camera per
/// intrinsics) imports with the same cameras; frames come from the numbers in the images' names.
/// An imported scene remembers the capture's units and world (and has its motion refined by the
/// default schedule, where a scene that states its poses keeps them), so a motion the fit gives back
/// (`fit::motion_bvh`, the refined training motion's `motion.bvh`) is in the capture's terms:
/// the given motion written back has the capture's joints, their distances (centimetres) and
/// the root's positions, frame by frame.
#[test]
fn a_motion_goes_back_in_the_captures_units() {
    let dir = TempDir::new("capture-motion-back");
    let (original, capture) = scene_and_capture(dir.path());
    let out = dir.path().join("imported");
    import(&options(&capture, out.clone()), &|_, _| {}).unwrap();
    let scene = Scene::load(&out).unwrap();
    let world = scene.capture.clone().expect("an imported scene names its capture");
    // The default schedule refines an imported capture's motion, and keeps a scene's poses.
    let schedule = umbra::schedule::Schedule::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("schedules/default.toml")).unwrap();
    let refines = |scene: Scene| umbra::train::Trainer::new(scene, schedule.clone(), umbra::backend::Backend::Flex, 0).unwrap().motion_moved().is_some();
    assert!(refines(scene.clone()), "an imported capture's motion is refined");
    assert!(!refines(Scene::load(&original).unwrap()), "a scene's stated poses are kept");
    assert!((world.metres_per_unit - 0.01).abs() < 1e-12, "centimetres: {}", world.metres_per_unit);
    let poses: Vec<(usize, umbra::skeleton::Pose)> = (0..scene.frames.len()).map(|f| (f, scene.frames[f].pose.clone())).collect();
    let text = umbra::fit::motion_bvh(&scene, &poses).unwrap();
    let back = bvh::parse(&text, Path::new("motion.bvh")).unwrap();
    let original = bvh::read(&capture.join("motion.bvh")).unwrap();
    assert_eq!(back.joints.iter().map(|j| &j.name).collect::<Vec<_>>(), original.joints.iter().map(|j| &j.name).collect::<Vec<_>>());
    // Each joint as far from its parent (the joints' own axes are the scene's bones', which
    // run along +Y to the next joint, not necessarily the capture's).
    for (a, b) in back.joints.iter().zip(&original.joints) {
        assert!((a.offset.length() - b.offset.length()).abs() < 1e-6, "{}: offset {} against {}", a.name, a.offset, b.offset);
    }
    for (f, frame) in back.frames.iter().enumerate() {
        let original_frame = &original.frames[scene.frames[f].index as usize];
        for c in 0..3 {
            assert!((frame[c] - original_frame[c]).abs() < 1e-6, "frame {f}: root position {:?} against {:?}", &frame[..3], &original_frame[..3]);
        }
    }
}

/// The default schedule refines an imported capture's cameras and keeps a scene's; the refined
/// cameras go back as nerfstudio's `transforms.json` in the capture's units and world: the
/// cameras as given read back as the capture's own, and a camera turned and moved reads back
/// turned and moved.
#[test]
fn the_cameras_go_back_in_the_captures_units() {
    let dir = TempDir::new("capture-cameras-back");
    let (original, capture) = scene_and_capture(dir.path());
    let out = dir.path().join("imported");
    import(&options(&capture, out.clone()), &|_, _| {}).unwrap();
    let scene = Scene::load(&out).unwrap();
    let schedule = umbra::schedule::Schedule::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("schedules/default.toml")).unwrap();
    let trainer = |scene: Scene| umbra::train::Trainer::new(scene, schedule.clone(), umbra::backend::Backend::Flex, 0).unwrap();
    let imported = trainer(scene.clone());
    assert_eq!(imported.cameras_moved().map(|m| m.cameras.len()), Some(3), "an imported capture's three cameras are refined");
    assert!(trainer(Scene::load(&original).unwrap()).cameras_moved().is_none(), "a scene's stated cameras are kept");
    // Read a transforms.json back: each image's camera-to-world in the scene's world (metres).
    let world = scene.capture.clone().unwrap();
    let read_back = |transforms: &serde_json::Value, name: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, serde_json::to_string(transforms).unwrap()).unwrap();
        let images = umbra::capture::nerfstudio::read(&path).unwrap();
        images
            .into_iter()
            .map(|i| {
                let mut m = world.to_scene * i.camera_to_world;
                m.w_axis = (m.w_axis.truncate() * world.metres_per_unit).extend(1.0);
                (stem(&i.path), i.time, m)
            })
            .collect::<Vec<_>>()
    };
    let given = read_back(&umbra::fit::cameras_transforms(&scene, &scene.cameras), "given.json");
    let train: Vec<_> = scene.views.iter().filter(|v| v.split == umbra::scene::Split::Train).collect();
    assert_eq!(given.len(), train.len(), "one frame per training image");
    let captured: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(capture.join("transforms.json")).unwrap()).unwrap();
    for ((name, time, m), view) in given.iter().zip(&train) {
        assert_eq!(*name, stem(&view.path));
        assert!(max_difference(m, &scene.cameras[view.camera].camera_to_world) < 1e-9, "{name}");
        assert_eq!(*time, scene.frames[view.frame].time, "{name}: the scene's time");
        let own = captured["frames"].as_array().unwrap().iter().find(|f| f["file_path"].as_str().is_some_and(|p| p.contains(name.as_str()))).unwrap();
        let transform = matrix(&own["transform_matrix"]);
        let written = given.iter().find(|g| g.0 == *name).unwrap();
        let mut back = world.to_scene.inverse() * written.2;
        back.w_axis = (back.w_axis.truncate() / world.metres_per_unit).extend(1.0);
        assert!(max_difference(&(back * umbra::capture::nerfstudio::flip_yz()), &transform) < 1e-6, "{name}: the capture's own transform");
    }
    // A camera turned 0.2 degrees about its centre and moved 4 mm reads back so.
    let mut moved = scene.cameras.clone();
    let centre = moved[0].centre();
    let turn = DMat4::from_axis_angle(DVec3::new(0.3, 1.0, -0.2).normalize(), 0.2f64.to_radians());
    moved[0].camera_to_world =
        DMat4::from_translation(centre + DVec3::new(0.004, 0.0, 0.0)) * turn * DMat4::from_translation(-centre) * moved[0].camera_to_world;
    let back = read_back(&umbra::fit::cameras_transforms(&scene, &moved), "moved.json");
    for ((name, _, m), view) in back.iter().zip(&train) {
        assert!(max_difference(m, &moved[view.camera].camera_to_world) < 1e-9, "{name}");
    }
    assert!(back.iter().zip(&given).any(|(a, b)| max_difference(&a.2, &b.2) > 1e-3), "the moved camera moved");
}

#[test]
fn a_colmap_text_model_imports_with_the_scenes_cameras() {
    let dir = TempDir::new("capture-colmap");
    let (scene_dir, capture) = scene_and_capture(dir.path());
    let original = Scene::load(&scene_dir).unwrap();
    let colmap = dir.path().join("colmap");
    std::fs::create_dir_all(colmap.join("sparse/0")).unwrap();
    std::fs::create_dir_all(colmap.join("images")).unwrap();
    std::fs::create_dir_all(colmap.join("masks")).unwrap();
    std::fs::copy(capture.join("motion.bvh"), colmap.join("motion.bvh")).unwrap();
    let mut cameras = String::from("# Camera list with one line of data per camera:\n");
    for (c, camera) in original.cameras.iter().enumerate() {
        cameras += &format!("{} PINHOLE {} {} {} {} {} {}\n", c + 1, camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy);
    }
    std::fs::write(colmap.join("sparse/0/cameras.txt"), cameras).unwrap();
    let mut images = String::from("# Image list with two lines of data per image:\n");
    let training: Vec<&umbra::scene::View> = original.views.iter().filter(|v| v.split == umbra::scene::Split::Train).collect();
    for (k, view) in training.iter().enumerate() {
        let world_to_camera = original.cameras[view.camera].camera_to_world.inverse();
        // In centimetres, as the clip: one world.
        let (_, q, t) = world_to_camera.to_scale_rotation_translation();
        let t = t * 100.0;
        let name = format!("c{}_frame_{:04}.png", view.camera, view.frame);
        images += &format!("{} {} {} {} {} {} {} {} {} {name}\n\n", k + 1, q.w, q.x, q.y, q.z, t.x, t.y, t.z, view.camera + 1);
        let source = stem(&view.path);
        std::fs::copy(capture.join(format!("images/{source}.png")), colmap.join("images").join(&name)).unwrap();
        std::fs::copy(capture.join(format!("masks/{source}.png")), colmap.join("masks").join(&name)).unwrap();
    }
    std::fs::write(colmap.join("sparse/0/images.txt"), &images).unwrap();
    let out = dir.path().join("imported");
    let report = import(&options(&colmap, out.clone()), &|_, _| {}).unwrap();
    assert!(report.score > 0.95, "{:?}", report.assumed);
    let imported = Scene::load(&out).unwrap();
    assert_eq!(imported.views.len(), training.len());
    for (view, twin) in imported.views.iter().zip(&training) {
        let (a, b) = (&imported.cameras[view.camera], &original.cameras[twin.camera]);
        assert!(max_difference(&a.camera_to_world, &b.camera_to_world) < 1e-6, "{}", view.path.display());
        assert_eq!(imported.frames[view.frame].index as usize, twin.frame);
        assert_eq!(view.mask, twin.mask);
    }
    // A malformed line is refused with the file and the line.
    let broken: Vec<String> = images
        .lines()
        .enumerate()
        .map(|(n, l)| if n == 1 { l.split(' ').enumerate().map(|(k, w)| if k == 1 { "zero" } else { w }).collect::<Vec<_>>().join(" ") } else { l.to_string() })
        .collect();
    std::fs::write(colmap.join("sparse/0/images.txt"), broken.join("\n")).unwrap();
    let err = import(&options(&colmap, dir.path().join("broken")), &|_, _| {}).unwrap_err().to_string();
    assert!(err.contains("images.txt: line 2: expected a finite number"), "{err}");
}

/// Per-frame joint transforms as JSON (what an SMPL-family tracker gives after forward
/// kinematics), written from the scene's own frames in centimetres, import as the BVH does.
#[test]
fn per_frame_joint_transforms_import_as_the_bvh_does() {
    let dir = TempDir::new("capture-joints");
    let (scene_dir, capture) = scene_and_capture(dir.path());
    let original = Scene::load(&scene_dir).unwrap();
    let from_bvh = dir.path().join("from-bvh");
    import(&options(&capture, from_bvh.clone()), &|_, _| {}).unwrap();
    let from_bvh = Scene::load(&from_bvh).unwrap();
    let skeleton = &original.skeleton;
    let leaves: serde_json::Map<String, serde_json::Value> = (0..skeleton.len())
        .filter(|&b| !skeleton.bones.iter().any(|c| c.parent == Some(b)))
        .map(|b| (skeleton.bones[b].name.clone(), serde_json::json!([0.0, skeleton.bones[b].length * 100.0, 0.0])))
        .collect();
    let frames: Vec<serde_json::Value> = original
        .frames
        .iter()
        .map(|f| {
            let rotations: Vec<Vec<Vec<f64>>> = f.pose.bone_to_world.iter().map(|m| (0..3).map(|r| (0..3).map(|c| m.row(r)[c]).collect()).collect()).collect();
            let positions: Vec<[f64; 3]> = f.pose.bone_to_world.iter().map(|m| (m.w_axis.truncate() * 100.0).to_array()).collect();
            serde_json::json!({"rotations": rotations, "positions": positions})
        })
        .collect();
    let joints = serde_json::json!({
        "frame_time": umbra::capture::export::FRAME_TIME,
        "joints": skeleton.bones.iter().map(|b| serde_json::json!({"name": b.name, "parent": b.parent})).collect::<Vec<_>>(),
        "tips": leaves,
        "frames": frames,
    });
    std::fs::write(capture.join("joints.json"), serde_json::to_string(&joints).unwrap()).unwrap();
    let out = dir.path().join("from-joints");
    import(&ImportOptions { motion: Some(capture.join("joints.json")), ..options(&capture, out.clone()) }, &|_, _| {}).unwrap();
    let from_joints = Scene::load(&out).unwrap();
    for (a, b) in from_joints.skeleton.bones.iter().zip(&from_bvh.skeleton.bones) {
        assert!(a.name == b.name && a.parent == b.parent && (a.length - b.length).abs() < 1e-9, "{a:?} against {b:?}");
    }
    for (f, g) in from_joints.frames.iter().zip(&from_bvh.frames) {
        for (a, b) in f.pose.bone_to_world.iter().zip(&g.pose.bone_to_world) {
            assert!(max_difference(a, b) < 1e-5);
        }
    }
    // A rotation that is not one is refused by its JSON path.
    let mut bad = joints.clone();
    bad["frames"][1]["rotations"][2][0][0] = serde_json::json!(2.0);
    std::fs::write(capture.join("joints.json"), serde_json::to_string(&bad).unwrap()).unwrap();
    let err =
        import(&ImportOptions { motion: Some(capture.join("joints.json")), ..options(&capture, dir.path().join("bad")) }, &|_, _| {}).unwrap_err().to_string();
    assert!(err.contains("joints.json: frames[1].rotations[2]: not a rotation"), "{err}");
}

/// `--max-size` downscales by a whole factor (the intrinsics with it, masks by majority); a
/// JPEG photo with the mask in a PNG and a PNG whose alpha is the mask both read.
#[test]
fn max_size_downscales_and_jpeg_or_alpha_photos_read() {
    let dir = TempDir::new("capture-size");
    let (scene_dir, capture) = scene_and_capture(dir.path());
    let original = Scene::load(&scene_dir).unwrap();
    let out = dir.path().join("half");
    let report = import(&ImportOptions { max_size: Some(16), ..options(&capture, out.clone()) }, &|_, _| {}).unwrap();
    assert!(report.assumed.iter().any(|a| a.contains("downscaled up to 2x")), "{:?}", report.assumed);
    let half = Scene::load(&out).unwrap();
    for view in &half.views {
        let twin = original.views.iter().find(|v| stem(&v.path) == stem(&view.path)).unwrap();
        let (a, b) = (&half.cameras[view.camera], &original.cameras[twin.camera]);
        assert_eq!((a.width, a.height), (b.width / 2, b.height / 2));
        assert!((a.fx - b.fx / 2.0).abs() < 1e-12 && (a.cx - b.cx / 2.0).abs() < 1e-12);
        // Each pixel the mean of its 2x2 block inside the body: of the photo as the camera saw
        // it when the image has a plate (the fit composites its edge over the plate), else of
        // the photo blacked outside the body.
        let mask = view.mask.as_ref().unwrap();
        let (photo, _) = umbra::photo::read_photo(&capture.join("images").join(view.path.file_name().unwrap())).unwrap();
        let source = |x: usize, y: usize| if view.plate.is_some() { photo.pixels[y * photo.width + x] } else { twin.colour.get(x, y) };
        for y in 0..a.height {
            for x in 0..a.width {
                if !mask.foreground[y * a.width + x] {
                    continue;
                }
                let block: Vec<[f32; 3]> = (0..4).map(|q| source(2 * x + q % 2, 2 * y + q / 2)).collect();
                let mean: [f32; 3] = std::array::from_fn(|c| block.iter().map(|p| p[c]).sum::<f32>() / 4.0);
                let got = view.colour.get(x, y);
                // Written as 8-bit sRGB: within a step of 8-bit rounding.
                assert!((0..3).all(|c| (got[c] - mean[c]).abs() < 0.01), "({x}, {y}): {got:?} against {mean:?}");
            }
        }
    }
    // The plates as JPEG (their masks still PNG), and as PNGs carrying the mask as alpha.
    let jpeg = dir.path().join("jpeg");
    let alpha = dir.path().join("alpha");
    for folder in [&jpeg, &alpha] {
        std::fs::create_dir_all(folder.join("images")).unwrap();
        std::fs::copy(capture.join("motion.bvh"), folder.join("motion.bvh")).unwrap();
    }
    copy_dir(&capture.join("masks"), &jpeg.join("masks"));
    let mut transforms: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(capture.join("transforms.json")).unwrap()).unwrap();
    let mut without_masks = transforms.clone();
    for (frame, bare) in transforms["frames"].as_array_mut().unwrap().iter_mut().zip(without_masks["frames"].as_array_mut().unwrap()) {
        let path = frame["file_path"].as_str().unwrap().to_string();
        let plate = image::open(capture.join(&path)).unwrap().to_rgb8();
        let jpg = path.replace(".png", ".jpg");
        plate.save(jpeg.join(&jpg)).unwrap();
        frame["file_path"] = serde_json::json!(jpg);
        let mask = image::open(capture.join(frame["mask_path"].as_str().unwrap())).unwrap().to_luma8();
        let rgba = image::RgbaImage::from_fn(plate.width(), plate.height(), |x, y| {
            let p = plate.get_pixel(x, y);
            image::Rgba([p[0], p[1], p[2], mask.get_pixel(x, y)[0]])
        });
        rgba.save(alpha.join(&path)).unwrap();
        bare.as_object_mut().unwrap().remove("mask_path");
    }
    for list in ["train_filenames", "val_filenames", "test_filenames"] {
        let renamed: Vec<String> = transforms[list].as_array().unwrap().iter().map(|n| n.as_str().unwrap().replace(".png", ".jpg")).collect();
        transforms[list] = serde_json::json!(renamed);
    }
    std::fs::write(jpeg.join("transforms.json"), serde_json::to_string(&transforms).unwrap()).unwrap();
    std::fs::write(alpha.join("transforms.json"), serde_json::to_string(&without_masks).unwrap()).unwrap();
    let from_jpeg = import(&options(&jpeg, dir.path().join("from-jpeg")), &|_, _| {}).unwrap();
    assert!(from_jpeg.score > 0.95, "{:?}", from_jpeg.assumed);
    let from_alpha = import(&options(&alpha, dir.path().join("from-alpha")), &|_, _| {}).unwrap();
    assert!(from_alpha.assumed.iter().any(|a| a.contains("0 from files") && a.contains("from the images' alpha")), "{:?}", from_alpha.assumed);
    let from_alpha = Scene::load(&dir.path().join("from-alpha")).unwrap();
    for view in &from_alpha.views {
        let twin = original.views.iter().find(|v| stem(&v.path) == stem(&view.path)).unwrap();
        assert_eq!(view.mask, twin.mask, "{}: the alpha is the mask", view.path.display());
    }
}

/// Each bone's rotation in its parent's frame, per frame of a clip.
fn local_rotations(motion: &bvh::Motion) -> Vec<Vec<DMat3>> {
    (0..motion.frames.len())
        .map(|k| {
            let world = motion.joint_to_world(k);
            motion.joints.iter().enumerate().map(|(j, joint)| DMat3::from_mat4(joint.parent.map_or(world[j], |p| world[p].inverse() * world[j]))).collect()
        })
        .collect()
}

#[test]
fn a_capture_with_a_real_pipelines_errors_errs_by_the_stated_sizes_and_keeps_its_truth() {
    let dir = TempDir::new("capture-flaws");
    let synth = SynthOptions { size: 48, frames: 8, ..synth_options(Some(Export::Nerfstudio)) };
    let (clean, flawed) = (dir.path().join("clean"), dir.path().join("flawed"));
    umbra::synth::generate(&synth, &clean, false, |_, _| {}).unwrap();
    umbra::synth::generate(&SynthOptions { errors: Some(umbra::capture::flaws::REAL), ..synth }, &flawed, false, |_, _| {}).unwrap();
    // The truth beside it is the clean capture's motion and cameras.
    assert_eq!(std::fs::read(flawed.join("truth/motion.bvh")).unwrap(), std::fs::read(clean.join("motion.bvh")).unwrap());
    let json = |p: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap() };
    let (truth, clean_cameras, given) =
        (json(&flawed.join("truth/transforms.json")), json(&clean.join("transforms.json")), json(&flawed.join("transforms.json")));
    let test_names: Vec<String> = given["test_filenames"].as_array().unwrap().iter().map(|n| n.as_str().unwrap().to_string()).collect();
    let mut turned = Vec::new();
    // Each training image's camera turned by a tenth of a degree or so (the trace of R^T R' is
    // 3 at no turn).
    for ((t, c), g) in truth["frames"].as_array().unwrap().iter().zip(clean_cameras["frames"].as_array().unwrap()).zip(given["frames"].as_array().unwrap()) {
        assert_eq!(t["transform_matrix"], c["transform_matrix"]);
        let path = g["file_path"].as_str().unwrap();
        let (a, b) = (matrix(&t["transform_matrix"]), matrix(&g["transform_matrix"]));
        if test_names.iter().any(|n| n == path) {
            assert!(path.ends_with(".png") && max_difference(&a, &b) == 0.0, "{path}: a test image is exact");
        } else {
            assert!(path.ends_with(".jpg"), "{path}: a training plate as JPEG");
            turned.push((DMat3::from_mat4(a).transpose() * DMat3::from_mat4(b)).to_cols_array().iter().sum::<f64>());
            // Moved by millimetres (the capture is in centimetres).
            assert!((a.w_axis - b.w_axis).length() < 2.0, "{path}");
        }
    }
    assert!(!turned.is_empty() && turned.iter().all(|&t| t < 3.0 && t > 3.0 - 1e-4), "{turned:?}");
    // The motion: training frames' bones turned by about the stated spread per channel (the
    // angle of three normal turns of 2.5 degrees has a mean of 2.5 sqrt(8 / pi) = 3.99), test
    // frames exact.
    let (exact, tracked) = (bvh::read(&clean.join("motion.bvh")).unwrap(), bvh::read(&flawed.join("motion.bvh")).unwrap());
    let times: Vec<usize> = given["frames"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| test_names.iter().any(|n| Some(n.as_str()) == f["file_path"].as_str()))
        .map(|f| (f["time"].as_f64().unwrap() * 30.0).round() as usize)
        .collect();
    let (a, b) = (local_rotations(&exact), local_rotations(&tracked));
    let mut angles = Vec::new();
    for (k, (fa, fb)) in a.iter().zip(&b).enumerate() {
        for (ra, rb) in fa.iter().zip(fb) {
            let angle = DQuat::from_mat3(&(ra.transpose() * *rb)).to_axis_angle().1.to_degrees();
            if times.contains(&k) {
                assert!(angle < 1e-4, "frame {k} is a test frame: exact");
            } else {
                angles.push(angle);
            }
        }
    }
    let mean = angles.iter().sum::<f64>() / angles.len() as f64;
    assert!((3.3..4.7).contains(&mean), "mean joint error {mean:.2} degrees over {} bones and frames", angles.len());
    // The masks: changed only near their edges (a pixel, and blobs of 2), every training one.
    let training: Vec<&serde_json::Value> =
        given["frames"].as_array().unwrap().iter().filter(|f| !test_names.iter().any(|n| Some(n.as_str()) == f["file_path"].as_str())).collect();
    for frame in training {
        let path = frame["mask_path"].as_str().unwrap();
        let (m0, m1) = (umbra::imageio::read_mask(&clean.join(path)).unwrap(), umbra::imageio::read_mask(&flawed.join(path)).unwrap());
        let changed: Vec<usize> = (0..m0.foreground.len()).filter(|&p| m0.foreground[p] != m1.foreground[p]).collect();
        assert!(!changed.is_empty(), "{path}");
        let near_edge = |p: usize| {
            let (x, y) = ((p % m0.width) as i64, (p / m0.width) as i64);
            (-4i64..=4).any(|dy| {
                (-4i64..=4).any(|dx| {
                    let (u, v) = (x + dx, y + dy);
                    (0..m0.width as i64).contains(&u)
                        && (0..m0.height as i64).contains(&v)
                        && m0.foreground[(v * m0.width as i64 + u) as usize] != m0.foreground[p]
                })
            })
        };
        assert!(changed.iter().all(|&p| near_edge(p)), "{path}: a change away from the edge");
    }
    // It still imports, its capture check said.
    let report = import(&options(&flawed, dir.path().join("imported")), &|_, _| {}).unwrap();
    assert!(report.score > 0.5, "{:?}", report.assumed);
}

/// A clean capture of static cameras: each camera's plate, where known, is what its photos show
/// where no body is near; a training image keeps the body, and what the camera saw within
/// `EDGE_BAND` of its mask where the plate is known, and is black elsewhere; test images keep
/// only their body and have no plate.
#[test]
fn a_static_cameras_plate_comes_from_its_frames_and_training_images_keep_what_it_saw_near_the_masks_edge() {
    use umbra::silhouette::{near_body, EDGE_BAND, PLATE_CLEARANCE};
    let dir = TempDir::new("plates");
    let capture = dir.path().join("capture");
    umbra::synth::generate(&SynthOptions { frames: 6, ..synth_options(Some(Export::Nerfstudio)) }, &capture, false, |_, _| {}).unwrap();
    let out = dir.path().join("scene");
    let report = import(&options(&capture, out.clone()), &|_, _| {}).unwrap();
    assert!(report.assumed.iter().any(|a| a.starts_with("plates: 3 of 3 cameras")), "{:?}", report.assumed);
    let scene = Scene::load(&out).unwrap();
    let byte = umbra::imageio::linear_to_srgb8;
    let same = |a: [f32; 3], b: [f32; 3]| a.iter().zip(&b).all(|(&x, &y)| (byte(x) as i32 - byte(y) as i32).abs() <= 1);
    let mut kept_beyond_mask = 0;
    for view in &scene.views {
        let mask = view.mask.as_ref().unwrap();
        let (photo, _) = umbra::photo::read_photo(&capture.join("images").join(view.path.file_name().unwrap())).unwrap();
        let Some(plate) = view.plate.as_ref() else {
            assert_ne!(view.split, umbra::scene::Split::Train, "{}: a training image of a static camera has a plate", view.path.display());
            assert!((0..photo.pixels.len()).all(|p| mask.foreground[p] || view.colour.pixel(p) == [0.0; 3]), "{}", view.path.display());
            continue;
        };
        assert_eq!(view.split, umbra::scene::Split::Train);
        let (near, clear) = (near_body(mask, EDGE_BAND), near_body(mask, PLATE_CLEARANCE));
        for p in 0..photo.pixels.len() {
            let stored = view.colour.pixel(p);
            let keep = mask.foreground[p] || (near[p] && plate.known.foreground[p]);
            assert!(if keep { same(stored, photo.pixels[p]) } else { stored == [0.0; 3] }, "{}: pixel {p}", view.path.display());
            kept_beyond_mask += (keep && !mask.foreground[p]) as usize;
            if plate.known.foreground[p] && !clear[p] {
                assert!(same(plate.colour.pixels[p], photo.pixels[p]), "{}: the plate at pixel {p}", view.path.display());
            }
        }
    }
    assert!(kept_beyond_mask > 0);

    // A training batch composites over the plate, and trusts the mask less, exactly at the
    // pixels near a mask's edge where the plate is known.
    let schedule = umbra::schedule::Schedule::load(Path::new("schedules/default.toml")).unwrap();
    let mut trainer = umbra::train::Trainer::new(scene.clone(), schedule, umbra::backend::Backend::Flex, 0).unwrap();
    let (mut near_edge, mut elsewhere) = (0, 0);
    for _ in 0..4 {
        let batch = trainer.draw_batch().unwrap();
        assert_eq!(batch.backgrounds.len(), 3 * batch.masks.len());
        for (k, &(v, p, _)) in batch.sources.iter().enumerate() {
            let view = &scene.views[v];
            let (mask, plate) = (view.mask.as_ref().unwrap(), view.plate.as_ref().unwrap());
            let edge = umbra::silhouette::edge_pixels(mask, EDGE_BAND).contains(&(p as u32)) && plate.known.foreground[p];
            let behind = [0, 1, 2].map(|c| batch.backgrounds[3 * k + c]);
            match edge {
                true => assert!(behind == plate.colour.pixels[p] && batch.mask_weights[k] < 1.0, "{k}"),
                false => assert!(behind == [0.0; 3] && batch.mask_weights[k] == 1.0, "{k}"),
            }
            near_edge += edge as usize;
            elsewhere += !edge as usize;
        }
    }
    assert!(near_edge > 0 && elsewhere > 0, "{near_edge} near the edge, {elsewhere} elsewhere");

    // The plates are training data: another plate is another identity (a fit does not resume
    // on it).
    let mut other = scene.clone();
    let view = other.views.iter_mut().find(|v| v.plate.is_some()).unwrap();
    let plate = std::sync::Arc::make_mut(view.plate.as_mut().unwrap());
    let known = plate.known.foreground.iter().position(|&k| k).unwrap();
    plate.colour.pixels[known][0] += 0.25;
    assert_ne!(other.training_identity(), scene.training_identity());
}

/// The motion's smoothness and prior weigh by what of the given motion is noise: a synthetic
/// walk sampled 30 times a cycle, exported and imported as a user would, is movement, held to the
/// given motion many times the schedule's weight, and the same walk with a tracker's errors (2.5
/// degrees a joint channel) is almost all noise between frames, of about that size, smoothed
/// several times the schedule's weight and held at it.
#[test]
fn a_trackers_errors_are_told_from_the_walk_smoothed_harder_and_held_less() {
    use umbra::train::motion::MotionCorrections;
    let dir = TempDir::new("capture-motion-noise");
    let synth = SynthOptions { size: 16, cameras: 1, frames: 30, samples: 1, ..synth_options(Some(Export::Nerfstudio)) };
    let errors = umbra::capture::flaws::CaptureErrors::parse("joints=2.5,root=1").unwrap();
    let mut shares = Vec::new();
    for (name, errors) in [("clean", None), ("tracked", Some(errors))] {
        let capture = dir.path().join(name);
        umbra::synth::generate(&SynthOptions { errors, ..synth.clone() }, &capture, false, |_, _| {}).unwrap();
        let scene = dir.path().join(format!("{name}-scene"));
        import(&options(&capture, scene.clone()), &|_, _| {}).unwrap();
        let motion = MotionCorrections::new(&Scene::load(&scene).unwrap()).unwrap();
        assert_eq!(motion.frames().len(), 30);
        shares.push((motion.noise_share(), motion.smoothness_scale(), motion.noise().to_degrees(), motion.prior_scale()));
    }
    let ((clean, clean_scale, clean_noise, clean_prior), (tracked, tracked_scale, tracked_noise, tracked_prior)) = (shares[0], shares[1]);
    assert!(clean < 0.5 && clean_scale == 1.0, "the exact walk: {clean:.3}, smoothed {clean_scale}x");
    assert!(clean_noise < 0.5 && clean_prior > 25.0, "the exact walk's noise {clean_noise:.3} degrees, held {clean_prior}x");
    assert!(tracked > 0.9 && tracked_scale > 3.0, "the tracker's: {tracked:.3}, smoothed {tracked_scale}x");
    assert!((2.0..3.0).contains(&tracked_noise) && tracked_prior < 1.6, "the tracker's noise {tracked_noise:.3} degrees, held {tracked_prior}x");
}
