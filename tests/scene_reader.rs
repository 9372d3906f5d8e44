//! The scene reader: valid scenes load with every field; each validation rule of the format
//! has a broken scene whose error names the file and the JSON path.

mod common;

use common::*;
use serde_json::{json, Value};
use umbra::light::Light;
use umbra::scene::{Scene, Split};

#[test]
fn valid_scene_with_all_light_types_and_mixed_camera_sizes_loads() {
    let dir = TempDir::new("valid");
    valid_scene(dir.path());
    let scene = Scene::load(dir.path()).unwrap();
    assert_eq!(scene.skeleton.len(), 2);
    assert_eq!((scene.cameras[0].width, scene.cameras[1].width, scene.cameras[1].height), (8, 6, 4));
    assert_eq!(scene.frames[0].index, 5);
    assert_eq!(scene.frames[1].index, 2);
    let types: Vec<&str> = scene.lights.values().map(Light::type_name).collect();
    for t in ["directional", "uniform", "environment", "point"] {
        assert!(types.contains(&t), "{t} missing from {types:?}");
    }
    match &scene.lights["sun"] {
        Light::Directional { direction, .. } => assert!((direction.length() - 1.0).abs() < 1e-12, "direction normalised on load"),
        _ => panic!("sun is directional"),
    }
    match &scene.lights["sky"] {
        Light::Environment { map, scale, .. } => {
            assert_eq!(*scale, 0.5);
            assert_eq!(map.image.get(3, 2), [2.0, 1.5, 1.0], "EXR read as linear");
        }
        _ => panic!("sky is an environment"),
    }
    let train = &scene.views[0];
    assert_eq!(train.split, Split::Train);
    assert_eq!(train.frame, 1, "images[].frame is a position in frames");
    let mask = train.mask.as_ref().unwrap();
    assert_eq!(mask.foreground.iter().filter(|&&f| f).count(), (0..64).filter(|k| k % 3 == 0).count());
    // sRGB PNG decoded to linear: code 128 is 0.2158605, code 36 is 0.0176420.
    assert!((train.colour.get(0, 0)[1] - 0.215_860_5).abs() < 1e-6, "{:?}", train.colour.get(0, 0));
    assert!((train.colour.get(1, 0)[0] - 0.017_642_0).abs() < 1e-6, "{:?}", train.colour.get(1, 0));
    assert!(scene.views[1].albedo.is_some());
    assert!(scene.views[2].mask.is_none(), "masks are optional outside train");
}

/// Applies `edit` to the valid scene, loads it and returns the error.
fn broken(edit: impl FnOnce(&mut Value, &std::path::Path)) -> umbra::scene::SceneError {
    let dir = TempDir::new("broken");
    let mut scene = valid_scene(dir.path());
    edit(&mut scene, dir.path());
    write_scene_json(dir.path(), &scene);
    let err = Scene::load(dir.path()).expect_err("a broken scene must not load");
    assert!(err.to_string().contains("scene.json"), "message names the file: {err}");
    err
}

fn expect_path(err: umbra::scene::SceneError, path: &str, words: &str) {
    assert_eq!(err.path, path, "{err}");
    let text = err.to_string();
    assert!(text.contains(path), "{text}");
    assert!(text.to_lowercase().contains(words), "{text} should mention {words:?}");
}

#[test]
fn format_must_be_scene_1() {
    expect_path(broken(|s, _| s["format"] = json!("scene/2")), "format", "scene/2");
}

#[test]
fn required_top_level_fields() {
    for key in ["skeleton", "cameras", "frames", "lights", "images"] {
        expect_path(broken(|s, _| drop(s.as_object_mut().unwrap().remove(key))), key, "missing");
    }
}

/// umbra's own `capture` key (what `umbra import` converted the scene from): its units and a
/// rotation into scene/1's world, refused by path when it is anything else.
#[test]
fn capture_world_rules() {
    let z_up = json!([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]);
    let dir = TempDir::new("capture-key");
    let mut scene = valid_scene(dir.path());
    scene["capture"] = json!({"metres_per_unit": 0.01, "to_scene": z_up});
    write_scene_json(dir.path(), &scene);
    let loaded = Scene::load(dir.path()).unwrap().capture.unwrap();
    assert_eq!(loaded.metres_per_unit, 0.01);
    assert!((loaded.to_scene.transform_vector3(glam::DVec3::Z) - glam::DVec3::Y).length() < 1e-12, "the capture's +Z is scene/1's up");
    expect_path(broken(|s, _| s["capture"] = json!({"metres_per_unit": 0.0, "to_scene": z_up})), "capture.metres_per_unit", "> 0");
    expect_path(broken(|s, _| s["capture"] = json!({"metres_per_unit": 1.0})), "capture.to_scene", "missing");
    let scaled = json!([[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
    expect_path(broken(|s, _| s["capture"] = json!({"metres_per_unit": 1.0, "to_scene": scaled})), "capture.to_scene", "");
    let moved = json!([[1, 0, 0, 3], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
    expect_path(broken(|s, _| s["capture"] = json!({"metres_per_unit": 1.0, "to_scene": moved})), "capture.to_scene", "rotation");
}

#[test]
fn skeleton_rules() {
    expect_path(broken(|s, _| s["skeleton"]["bones"] = json!([])), "skeleton.bones", "at least one");
    expect_path(broken(|s, _| s["skeleton"]["bones"][1]["parent"] = json!(1)), "skeleton.bones[1].parent", "earlier");
    // A bone without its parent key would become a second root: refused.
    expect_path(broken(|s, _| drop(s["skeleton"]["bones"][1].as_object_mut().unwrap().remove("parent"))), "skeleton.bones[1].parent", "missing");
    expect_path(broken(|s, _| s["skeleton"]["bones"][0]["parent"] = json!(0)), "skeleton.bones[0].parent", "earlier");
    expect_path(broken(|s, _| s["skeleton"]["bones"][0]["length"] = json!(0.0)), "skeleton.bones[0].length", "> 0");
    expect_path(broken(|s, _| s["skeleton"]["bones"][1]["name"] = json!("root")), "skeleton.bones[1].name", "twice");
    expect_path(broken(|s, _| s["skeleton"]["bones"][1]["length"] = json!("long")), "skeleton.bones[1].length", "number");
}

#[test]
fn camera_rules() {
    expect_path(broken(|s, _| s["cameras"] = json!([])), "cameras", "at least one");
    expect_path(broken(|s, _| s["cameras"][0]["width"] = json!(0)), "cameras[0].width", "positive");
    expect_path(broken(|s, _| s["cameras"][1]["height"] = json!(2.5)), "cameras[1].height", "integer");
    expect_path(broken(|s, _| s["cameras"][1]["fx"] = json!(-1.0)), "cameras[1].fx", "> 0");
    expect_path(broken(|s, _| s["cameras"][0]["fy"] = json!(0)), "cameras[0].fy", "> 0");
    expect_path(broken(|s, _| s["cameras"][0]["camera_to_world"] = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])), "cameras[0].camera_to_world", "4 rows");
    expect_path(broken(|s, _| s["cameras"][0]["camera_to_world"][3] = json!([0, 0, 1, 1])), "cameras[0].camera_to_world[3]", "last row");
    expect_path(broken(|s, _| s["cameras"][0]["camera_to_world"][1] = json!([0, 1, 0])), "cameras[0].camera_to_world[1]", "4 numbers");
}

#[test]
fn frame_rules() {
    expect_path(broken(|s, _| s["frames"] = json!([])), "frames", "at least one");
    expect_path(broken(|s, _| s["frames"][1]["index"] = json!(5)), "frames[1].index", "twice");
    expect_path(broken(|s, _| s["frames"][0]["bone_to_world"] = json!([identity_rows(0.0)])), "frames[0].bone_to_world", "one matrix per bone");
    expect_path(
        broken(|s, _| s["frames"][1]["bone_to_world"][0] = json!([[1.1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),
        "frames[1].bone_to_world[0]",
        "rigid",
    );
    expect_path(
        broken(|s, _| s["frames"][1]["bone_to_world"][1] = json!([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),
        "frames[1].bone_to_world[1]",
        "determinant",
    );
    expect_path(broken(|s, _| s["frames"][0]["mesh"] = json!("meshes/none.obj")), "frames[0].mesh", "not found");
    expect_path(broken(|s, _| s["frames"][0]["time"] = json!("soon")), "frames[0].time", "number");
}

#[test]
fn light_rules() {
    expect_path(broken(|s, _| s["lights"] = json!({})), "lights", "at least one");
    expect_path(broken(|s, _| s["lights"]["sun"]["type"] = json!("laser")), "lights.sun.type", "unknown light type");
    expect_path(broken(|s, _| s["lights"]["sun"]["direction"] = json!([0, 0, 0])), "lights.sun.direction", "zero length");
    expect_path(broken(|s, _| s["lights"]["sun"]["irradiance"] = json!([1, -1, 1])), "lights.sun.irradiance", ">= 0");
    expect_path(broken(|s, _| drop(s["lights"]["studio"].as_object_mut().unwrap().remove("radiance"))), "lights.studio.radiance", "missing");
    expect_path(broken(|s, _| s["lights"]["sky"]["path"] = json!("lights/none.exr")), "lights.sky.path", "not found");
    expect_path(broken(|s, _| s["lights"]["lamp"]["position"] = json!([1, 2])), "lights.lamp.position", "3 numbers");
}

#[test]
fn image_rules() {
    expect_path(broken(|s, _| s["images"] = json!([])), "images", "at least one");
    expect_path(broken(|s, _| s["images"][0]["camera"] = json!(2)), "images[0].camera", "out of range");
    expect_path(broken(|s, _| s["images"][0]["frame"] = json!(5)), "images[0].frame", "out of range");
    expect_path(broken(|s, _| s["images"][2]["frame"] = json!(-1)), "images[2].frame", "out of range");
    expect_path(broken(|s, _| s["images"][0]["light"] = json!("moon")), "images[0].light", "unknown light");
    expect_path(broken(|s, _| s["images"][0]["split"] = json!("training")), "images[0].split", "unknown split");
    expect_path(broken(|s, _| s["images"][1]["path"] = json!("images/none.png")), "images[1].path", "not found");
    expect_path(broken(|s, _| drop(s["images"][0].as_object_mut().unwrap().remove("mask"))), "images[0].mask", "mask is required");
    expect_path(broken(|s, _| s["images"][0]["path"] = json!("images/b.png")), "images[0].path", "6x4");
    expect_path(broken(|s, _| s["images"][1]["albedo"] = json!("images/a.png")), "images[1].albedo", "8x8");
    expect_path(broken(|s, _| s["images"][0]["mask"] = json!("masks/none.png")), "images[0].mask", "not found");
    expect_path(broken(|s, _| s["images"][0]["plate"] = json!("plates/none.png")), "images[0].plate", "not found");
    expect_path(broken(|s, _| s["images"][0]["plate"] = json!("images/b.png")), "images[0].plate", "6x4");
    expect_path(broken(|s, _| s["images"][2]["plate"] = json!("images/a.png")), "images[2].plate", "needs the image's mask");
}

#[test]
fn paths_stay_inside_the_scene_folder_and_name_files() {
    // The image exists outside the scene's folder: still refused, before it is read.
    let outside = |path: &'static str| {
        move |s: &mut Value, dir: &std::path::Path| {
            std::fs::copy(dir.join("images/a.png"), dir.parent().unwrap().join("a-outside.png")).unwrap();
            s["images"][0]["path"] = json!(path);
        }
    };
    expect_path(broken(outside("../a-outside.png")), "images[0].path", "inside");
    expect_path(broken(|s, dir| s["images"][0]["path"] = json!(dir.join("images/a.png").to_str().unwrap())), "images[0].path", "relative");
    expect_path(broken(|s, _| s["images"][0]["mask"] = json!("masks")), "images[0].mask", "directory");
    #[cfg(unix)]
    expect_path(
        broken(|s, dir| {
            std::os::unix::fs::symlink(dir.join("loop.png"), dir.join("loop.png")).unwrap();
            s["images"][0]["path"] = json!("loop.png");
        }),
        "images[0].path",
        "cannot be read",
    );
}

#[test]
fn corrupt_files_are_errors_not_panics() {
    expect_path(broken(|_, dir| std::fs::write(dir.join("images/a.png"), b"\x89PNG\r\n\x1a\n not really").unwrap()), "images[0].path", "decode");
    expect_path(broken(|_, dir| std::fs::write(dir.join("masks/a.png"), b"").unwrap()), "images[0].mask", "decode");
    expect_path(broken(|_, dir| std::fs::write(dir.join("lights/sky.exr"), b"v/1\x01garbage").unwrap()), "lights.sky.path", "decode");
    expect_path(broken(|s, _| s["images"][0]["path"] = json!("scene.json")), "images[0].path", "unsupported");
}

/// A PNG that is nothing but a valid signature and header declaring `w x h` RGB pixels and a
/// few bytes of broken image data: decoding it would fail, so an error that names its size proves the size was
/// read from the header and checked first.
fn png_header_only(w: u32, h: u32) -> Vec<u8> {
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = 0xFFFF_FFFFu32;
        for &b in bytes {
            crc ^= b as u32;
            for _ in 0..8 {
                crc = if crc & 1 == 1 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
            }
        }
        !crc
    }
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]);
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    png.extend(13u32.to_be_bytes());
    png.extend(&ihdr);
    png.extend(crc32(&ihdr).to_be_bytes());
    // An image-data chunk whose bytes are not a valid stream: headers end at its start.
    let idat = [b"IDAT".as_slice(), &[0x78, 0x9c, 0, 0, 0, 0]].concat();
    png.extend(6u32.to_be_bytes());
    png.extend(&idat);
    png.extend(crc32(&idat).to_be_bytes());
    png.extend(0u32.to_be_bytes());
    png.extend(b"IEND");
    png.extend(crc32(b"IEND").to_be_bytes());
    png
}

#[test]
fn an_image_size_is_checked_from_its_header_before_decoding() {
    let huge = png_header_only(20_000, 20_000);
    expect_path(broken(|_, dir| std::fs::write(dir.join("images/a.png"), &huge).unwrap()), "images[0].path", "20000x20000, but its camera is");
    expect_path(broken(|_, dir| std::fs::write(dir.join("masks/a.png"), &huge).unwrap()), "images[0].mask", "20000x20000, but its camera is");
    let dir = TempDir::new("header");
    let small = dir.path().join("small.png");
    std::fs::write(&small, png_header_only(7, 3)).unwrap();
    assert_eq!(umbra::imageio::dimensions(&small).unwrap(), (7, 3));
    // Where no camera fixes the size (an environment map), a header above the cap is refused.
    let path = dir.path().join("huge.png");
    std::fs::write(&path, png_header_only(20_000, 20_000)).unwrap();
    let err = umbra::imageio::read_rgb(&path).unwrap_err().to_string();
    assert!(err.contains("20000x20000") && err.contains("allowed"), "{err}");
}

fn broken_text(edit: impl FnOnce(String) -> String) -> umbra::scene::SceneError {
    let dir = TempDir::new("text");
    let scene = valid_scene(dir.path());
    let text = edit(serde_json::to_string_pretty(&scene).unwrap());
    std::fs::write(dir.path().join("scene.json"), text).unwrap();
    Scene::load(dir.path()).expect_err("must not load")
}

#[test]
fn nan_infinity_and_truncation_are_reported() {
    // NaN, Infinity and 1e999 are not JSON, but exporters write them: named by their JSON path.
    let err = broken_text(|t| t.replace("\"length\": 0.5", "\"length\": NaN"));
    assert!(err.path.starts_with("skeleton.bones[") && err.path.ends_with("].length") && err.to_string().contains("NaN is not a finite number"), "{err}");
    let err = broken_text(|t| t.replace("\"fx\": 10.0", "\"fx\": Infinity"));
    assert!(err.path.ends_with(".fx") && err.to_string().contains("Infinity is not a finite number"), "{err}");
    let err = broken_text(|t| t.replace("\"fx\": 10.0", "\"fx\": -1e999"));
    assert!(err.path.ends_with(".fx") && err.to_string().contains("-1e999"), "{err}");
    // Inside a string the same letters are text, not a number: a name may be "NaN".
    let err = broken_text(|t| t.replace("\"fx\": 10.0", "\"fx\": \"NaN\""));
    assert!(err.to_string().contains("expected a number, found the string \"NaN\""), "{err}");
    // A syntax error is still reported by line and column.
    let err = broken_text(|t| t.replacen("{", "{]", 2));
    assert!(err.to_string().contains("invalid JSON at line"), "{err}");
    let err = broken_text(|t| t[..t.len() / 2].to_string());
    assert!(err.to_string().contains("EOF") || err.to_string().contains("invalid JSON"), "{err}");
    let dir = TempDir::new("none");
    let err = Scene::load(dir.path()).unwrap_err();
    assert!(err.to_string().contains("scene.json") && err.to_string().contains("not found"), "{err}");
}

#[test]
fn numbers_beyond_f32_are_refused_by_their_json_path() {
    expect_path(broken(|s, _| s["cameras"][0]["fx"] = json!(1e39)), "cameras[0].fx", "f32");
    expect_path(broken(|s, _| s["skeleton"]["bones"][0]["length"] = json!(1e30)), "skeleton.bones[0].length", "f32");
    expect_path(broken(|s, _| s["frames"][0]["bone_to_world"][0][0][3] = json!(-1e20)), "frames[0].bone_to_world[0][0][3]", "f32");
    expect_path(broken(|s, _| s["lights"]["sun"]["direction"] = json!([1e200, 1e200, 0])), "lights.sun.direction[0]", "f32");
    expect_path(broken(|s, _| s["lights"]["lamp"]["intensity"] = json!([1e39, 1, 1])), "lights.lamp.intensity[0]", "f32");
}

#[test]
fn inspect_exits_non_zero_with_the_json_path_and_writes_nothing() {
    let dir = TempDir::new("cli");
    let mut scene = valid_scene(dir.path());
    scene["images"][2]["camera"] = json!(7);
    write_scene_json(dir.path(), &scene);
    let before: Vec<_> = walk(dir.path());
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_umbra")).arg("inspect").arg(dir.path()).output().unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("scene.json: images[2].camera: index 7 out of range"), "{stderr}");
    assert_eq!(before, walk(dir.path()), "inspect wrote nothing");

    scene["images"][2]["camera"] = json!(1);
    scene["images"][2]["path"] = json!("images/b.png");
    write_scene_json(dir.path(), &scene);
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_umbra")).arg("inspect").arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("cameras: 2"), "{stdout}");
}

fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let p = entry.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out.sort();
    out
}

#[test]
fn loading_tells_how_many_images_are_decoded() {
    let seen = std::sync::Mutex::new(Vec::new());
    let scene = umbra::scene::Scene::load_reporting(&common::example_scene(), &|done, total| seen.lock().unwrap().push((done, total))).unwrap();
    let mut seen = seen.into_inner().unwrap();
    seen.sort();
    let n = scene.views.len();
    assert_eq!(seen, (1..=n).map(|k| (k, n)).collect::<Vec<_>>(), "one report per image, each of the total");
}

/// The first training identity, computed here from its description: FNV-1a 64 over the
/// skeleton (name, parent or -1, length per bone) and then, image after image, its camera
/// (name, fx, fy, cx, cy, camera-to-world by columns), its frame's bone transforms, its light
/// and every pixel's linear RGB as f32 bits.
fn first_training_identity(scene: &Scene) -> String {
    use umbra::scene::identity::Fingerprint;
    let mut f = Fingerprint::default();
    for bone in &scene.skeleton.bones {
        f = f.text(&bone.name).number(bone.parent.map_or(-1.0, |p| p as f64)).number(bone.length);
    }
    for view in scene.views.iter().filter(|v| v.split == Split::Train) {
        let c = &scene.cameras[view.camera];
        f = f.text(&c.name).number(c.fx).number(c.fy).number(c.cx).number(c.cy);
        for v in c.camera_to_world.to_cols_array().into_iter().chain(scene.frames[view.frame].pose.bone_to_world.iter().flat_map(|m| m.to_cols_array())) {
            f = f.number(v);
        }
        f = f.text(&view.light);
        for p in view.colour.pixels() {
            for c in p {
                f = f.bytes(&c.to_bits().to_le_bytes());
            }
        }
    }
    f.hex()
}

#[test]
fn a_checkpoint_of_the_first_training_identity_still_matches_its_scene() {
    let scene = Scene::load(&example_scene()).unwrap();
    let current = scene.training_identity();
    assert!(current.starts_with("v2:"), "{current}");
    assert!(scene.is_training_identity(&current, &current));
    let first = first_training_identity(&scene);
    assert!(scene.is_training_identity(&first, &current), "an unversioned identity is checked as the first one");
    let mut other = first.clone();
    other.replace_range(0..1, if first.starts_with('0') { "1" } else { "0" });
    assert!(!scene.is_training_identity(&other, &current));
    assert!(!scene.is_training_identity("v2:0000000000000000", &current));
}

/// A plate (umbra's own `images[*].plate`) is read once for the images that share it, known
/// where its alpha is opaque, everywhere when it has none.
#[test]
fn a_plate_is_read_once_and_known_where_it_is_opaque() {
    let dir = TempDir::new("plate");
    let mut scene = valid_scene(dir.path());
    let rgba: Vec<u8> = (0..64).flat_map(|k| [200, 100, 50, if k % 2 == 0 { 255 } else { 0 }]).collect();
    let bytes = umbra::imageio::encode_png_raw(&rgba, 8, 8, image::ExtendedColorType::Rgba8).unwrap();
    std::fs::write(dir.path().join("plate.png"), bytes).unwrap();
    scene["images"][0]["plate"] = json!("plate.png");
    write_scene_json(dir.path(), &scene);
    let loaded = Scene::load(dir.path()).unwrap();
    let plate = loaded.views[0].plate.as_ref().expect("a plate");
    assert!((0..64).all(|k| plate.known.foreground[k] == (k % 2 == 0)));
    assert!((plate.colour.pixels[0][0] - umbra::imageio::srgb_to_linear(200.0 / 255.0)).abs() < 1e-6);
    assert!(loaded.views[1].plate.is_none());
    scene["images"][0]["plate"] = json!("images/a.png");
    write_scene_json(dir.path(), &scene);
    let opaque = Scene::load(dir.path()).unwrap();
    assert!(opaque.views[0].plate.as_ref().unwrap().known.foreground.iter().all(|&k| k));
}
