//! What leaves umbra: the posed shadow Gaussians as a splatting PLY, read back by a reader
//! written here from the format's description.

mod common;

use common::{short_run, succeeds};
use glam::{DMat3, DQuat, DVec3};
use std::path::Path;

/// A binary little-endian PLY of float vertex properties: the property names and the rows.
fn read_ply(path: &Path) -> (Vec<String>, Vec<Vec<f32>>, String) {
    let bytes = std::fs::read(path).unwrap();
    let end = b"end_header\n";
    let at = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = String::from_utf8(bytes[..at].to_vec()).unwrap();
    let mut lines = header.lines();
    assert_eq!(lines.next(), Some("ply"));
    assert_eq!(lines.next(), Some("format binary_little_endian 1.0"));
    let mut count = 0;
    let mut names = Vec::new();
    for line in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["element", "vertex", n] => count = n.parse().unwrap(),
            ["property", "float", name] => names.push(name.to_string()),
            ["property", ..] => panic!("not a float property: {line}"),
            _ => {}
        }
    }
    let body = &bytes[at..];
    assert_eq!(body.len(), count * names.len() * 4, "the body holds exactly the vertices");
    let rows = body.chunks(names.len() * 4).map(|row| row.chunks(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()).collect();
    (names, rows, header)
}

#[test]
fn posed_gaussians_export_as_a_splatting_ply_that_reads_back() {
    let (dir, scene_dir, run) = short_run("export-gaussians");
    let cwd = std::env::current_dir().unwrap();
    let out = dir.path().join("g.ply");
    succeeds(&cwd, &["export-gaussians", run.to_str().unwrap(), "--frame", "1", "--out", out.to_str().unwrap()]);
    let (names, rows, header) = read_ply(&out);
    for name in ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"] {
        assert!(names.iter().any(|n| n == name), "{name} missing from {names:?}");
    }
    let col = |name: &str| names.iter().position(|n| n == name).unwrap();
    // The same Gaussians from the library: posed in frame 1, amplitudes as shadows use them.
    let restored = umbra::run::restore(&run, None, umbra::backend::Backend::Flex).unwrap();
    let scene = umbra::scene::Scene::load(&scene_dir).unwrap();
    let model = &restored.fitted.model;
    let posed = model.light.shadow_casters_posed(&model.gaussians.to_set().pose(&scene.frames[1].pose));
    assert_eq!(rows.len(), posed.len());
    for (row, g) in rows.iter().zip(&posed) {
        let v = |name: &str| row[col(name)] as f64;
        assert!(DVec3::new(v("x"), v("y"), v("z")).distance(g.mean) < 1e-5);
        let scales = DVec3::new(v("scale_0").exp(), v("scale_1").exp(), v("scale_2").exp());
        assert!((scales - g.scales).abs().max_element() < 1e-5 * g.scales.max_element());
        // The quaternion's rotation spans the same covariance: R diag(s^2) R^T.
        let r = DMat3::from_quat(DQuat::from_xyzw(v("rot_1"), v("rot_2"), v("rot_3"), v("rot_0")).normalize());
        let covariance = |axes: DMat3| axes * DMat3::from_diagonal(g.scales * g.scales) * axes.transpose();
        let (ours, theirs) = (covariance(r), covariance(g.axes));
        let gap = (0..3).map(|c| (ours.col(c) - theirs.col(c)).abs().max_element()).fold(0.0, f64::max);
        assert!(gap < 1e-5 * g.scales.max_element().powi(2), "covariance off by {gap}");
        // Opacity: the sigmoid of the logit is 1 - exp(-tau), tau through the centre along
        // the geometric mean of the axes.
        let tau = g.amplitude * (2.0 * std::f64::consts::PI).sqrt() * (g.scales.x * g.scales.y * g.scales.z).cbrt();
        let opacity = 1.0 / (1.0 + (-v("opacity")).exp());
        assert!((opacity - (1.0 - (-tau).exp()).clamp(1e-6, 1.0 - 1e-6)).abs() < 1e-4, "opacity {opacity} for tau {tau}");
    }
    assert!(header.contains("comment umbra export-gaussians"));
    // A second export replaces the first; a file of someone else's is refused and kept.
    succeeds(&cwd, &["export-gaussians", run.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    let theirs = dir.path().join("theirs.ply");
    std::fs::write(&theirs, "ply\nmine\n").unwrap();
    let error = common::fails(&cwd, &["export-gaussians", run.to_str().unwrap(), "--out", theirs.to_str().unwrap()]);
    assert!(error.contains("theirs.ply"), "{error}");
    assert_eq!(std::fs::read_to_string(&theirs).unwrap(), "ply\nmine\n");
    common::fails(&cwd, &["export-gaussians", run.to_str().unwrap(), "--frame", "99", "--out", dir.path().join("x.ply").to_str().unwrap()]);
}

/// A GLB's JSON chunk and binary chunk.
fn read_glb(path: &Path) -> (serde_json::Value, Vec<u8>) {
    let bytes = std::fs::read(path).unwrap();
    let word = |at: usize| u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]) as usize;
    assert_eq!(&bytes[..4], b"glTF");
    assert_eq!(word(4), 2, "version 2");
    assert_eq!(word(8), bytes.len(), "the header's length is the file's");
    let json_length = word(12);
    assert_eq!(&bytes[16..20], b"JSON");
    assert_eq!(json_length % 4, 0);
    let document = serde_json::from_slice(&bytes[20..20 + json_length]).unwrap();
    let at = 20 + json_length;
    assert_eq!(&bytes[at + 4..at + 8], b"BIN\0");
    let bin = bytes[at + 8..at + 8 + word(at)].to_vec();
    assert_eq!(at + 8 + bin.len(), bytes.len());
    (document, bin)
}

/// Accessor `k`'s floats.
fn floats(document: &serde_json::Value, bin: &[u8], k: usize) -> Vec<f32> {
    let accessor = &document["accessors"][k];
    assert_eq!(accessor["componentType"], 5126);
    let view = &document["bufferViews"][accessor["bufferView"].as_u64().unwrap() as usize];
    let (offset, length) = (view["byteOffset"].as_u64().unwrap() as usize, view["byteLength"].as_u64().unwrap() as usize);
    bin[offset..offset + length].chunks(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

#[test]
fn the_avatar_exports_as_a_skinned_animated_gltf_binary() {
    let (dir, scene_dir, run) = short_run("export-avatar");
    let cwd = std::env::current_dir().unwrap();
    let out = dir.path().join("avatar.glb");
    succeeds(&cwd, &["export-avatar", run.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    let (document, bin) = read_glb(&out);
    let scene = umbra::scene::Scene::load(&scene_dir).unwrap();
    let bones = scene.skeleton.len();
    assert_eq!(document["asset"]["version"], "2.0");
    assert_eq!(document["skins"].as_array().unwrap().len(), 1);
    assert_eq!(document["skins"][0]["joints"].as_array().unwrap().len(), bones);
    assert_eq!(document["animations"].as_array().unwrap().len(), 1);
    // Every joint's translation and rotation animated over every frame of the scene.
    let channels = document["animations"][0]["channels"].as_array().unwrap();
    assert_eq!(channels.len(), 2 * bones);
    let sampler = &document["animations"][0]["samplers"][0];
    let times = floats(&document, &bin, sampler["input"].as_u64().unwrap() as usize);
    assert_eq!(times.len(), scene.frames.len());
    assert!(times.windows(2).all(|w| w[1] > w[0]), "times increase: {times:?}");
    // The inverse bind matrices undo the first frame's bones.
    let ibm = floats(&document, &bin, document["skins"][0]["inverseBindMatrices"].as_u64().unwrap() as usize);
    for (b, m) in scene.frames[0].pose.bone_to_world.iter().enumerate() {
        let product = *m * glam::DMat4::from_cols_array(&std::array::from_fn(|i| ibm[16 * b + i] as f64));
        assert!(product.abs_diff_eq(glam::DMat4::IDENTITY, 1e-4), "bone {b}: {product}");
    }
    // Per vertex four weights summing to 1, and a unit normal.
    let attributes = &document["meshes"][0]["primitives"][0]["attributes"];
    let weights = floats(&document, &bin, attributes["WEIGHTS_0"].as_u64().unwrap() as usize);
    let normals = floats(&document, &bin, attributes["NORMAL"].as_u64().unwrap() as usize);
    assert!(!weights.is_empty() && weights.len() % 4 == 0);
    assert!(weights.chunks(4).all(|w| (w.iter().sum::<f32>() - 1.0).abs() < 1e-5 && w.iter().all(|&v| v >= 0.0)));
    assert!(normals.chunks(3).all(|n| ((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt() - 1.0).abs() < 1e-4));
    // Its own earlier export is replaced; someone else's file is refused and kept.
    succeeds(&cwd, &["export-avatar", run.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    let theirs = dir.path().join("theirs.glb");
    std::fs::write(&theirs, "glTF mine").unwrap();
    common::fails(&cwd, &["export-avatar", run.to_str().unwrap(), "--out", theirs.to_str().unwrap()]);
    assert_eq!(std::fs::read_to_string(&theirs).unwrap(), "glTF mine");
}

/// A sphere meshed on a grid of `cell`.
fn sphere(centre: DVec3, radius: f64, cell: f64) -> umbra::isosurface::Mesh {
    use umbra::isosurface::{bisect, extract, Grid};
    let grid = Grid::covering(centre - DVec3::splat(radius + 2.0 * cell), centre + DVec3::splat(radius + 2.0 * cell), cell);
    let f = |p: DVec3| (p - centre).length() - radius;
    let values: Vec<f64> = grid.points().into_iter().map(f).collect();
    extract(&grid, &values, |c| bisect(c, 30, |points| points.iter().map(|&p| f(p) < 0.0).collect()))
}

#[test]
fn carving_keeps_what_lies_inside_every_mask_and_cuts_a_sheet_beside_the_body() {
    let dir = common::TempDir::new("carve");
    let scene_dir = common::tiny_synth(dir.path(), umbra::synth::TrainingLight::Sun, 32, 6, vec![umbra::synth::TestKind::Poses], 4);
    let scene = umbra::scene::Scene::load(&scene_dir).unwrap();
    let pose = &scene.frames[0].pose;
    // A small ball at the pelvis (inside every mask), and one a metre beside the body, which
    // at least two cameras see outside their masks (six cameras around it: one may see it
    // over the body).
    let pelvis = pose.bone_to_world[0].w_axis.truncate();
    let (body, beside) = (sphere(pelvis, 0.04, 0.01), sphere(pelvis + DVec3::new(1.0, 0.3, 0.0), 0.1, 0.02));
    let offset = body.vertices.len();
    let both = umbra::isosurface::Mesh {
        vertices: body.vertices.iter().chain(&beside.vertices).copied().collect(),
        triangles: body.triangles.iter().copied().chain(beside.triangles.iter().map(|t| t.map(|v| v + offset))).collect(),
    };
    let carved = umbra::carve::carve(&both, &scene, 0, None);
    assert!(carved.views >= 3, "every camera's image of frame 0 judged: {}", carved.views);
    assert_eq!(carved.triangles_cut, beside.triangles.len());
    assert_eq!(carved.mesh.triangles.len(), body.triangles.len());
    assert!(carved.kept.iter().all(|&v| v < offset), "only the ball at the pelvis is kept");
    assert!(carved.mesh.is_closed_manifold());
    // One image's mask cut away at the pelvis (a segmenter's stray bite) cuts nothing the other
    // images see inside theirs; two such masks do.
    let mut bitten = scene.clone();
    let of_frame: Vec<usize> = (0..bitten.views.len()).filter(|&v| bitten.views[v].frame == 0 && bitten.views[v].mask.is_some()).collect();
    let bite = |scene: &mut umbra::scene::Scene, v: usize| {
        let mask = scene.views[v].mask.as_mut().unwrap();
        mask.foreground = vec![false; mask.width * mask.height].into();
    };
    bite(&mut bitten, of_frame[0]);
    assert_eq!(umbra::carve::carve(&both, &bitten, 0, None).mesh.triangles.len(), body.triangles.len());
    bite(&mut bitten, of_frame[1]);
    assert_eq!(umbra::carve::carve(&both, &bitten, 0, None).mesh.triangles.len(), 0);

    // A test pose with no image of its own: its own hull says nothing, and the training frames'
    // hulls, the vertices moved there with the pelvis, cut the same ball and keep the other.
    let mut training = scene.clone();
    training.views.retain(|v| v.split == umbra::scene::Split::Train);
    let test = (0..training.frames.len()).find(|&f| umbra::carve::needs_skinning(&training, f)).expect("a test pose");
    let pose = &training.frames[test].pose;
    let pelvis = pose.bone_to_world[0].w_axis.truncate();
    let side = pose.bone_to_world[0].transform_vector3(DVec3::new(1.0, 0.3, 0.0));
    let (body, beside) = (sphere(pelvis, 0.04, 0.01), sphere(pelvis + side, 0.1, 0.02));
    let both = umbra::isosurface::Mesh {
        vertices: body.vertices.iter().chain(&beside.vertices).copied().collect(),
        triangles: body.triangles.iter().copied().chain(beside.triangles.iter().map(|t| t.map(|v| v + offset))).collect(),
    };
    assert_eq!(umbra::carve::carve(&both, &training, test, None).triangles_cut, 0, "no image of the test pose judges it");
    let skinning: Vec<Vec<(usize, f32)>> = both.vertices.iter().map(|_| vec![(0, 1.0)]).collect();
    let carved = umbra::carve::carve(&both, &training, test, Some(&skinning));
    let training_images = training.views.iter().filter(|v| v.mask.is_some()).count();
    assert_eq!((carved.views, carved.training_views), (0, training_images));
    assert_eq!(carved.triangles_cut, beside.triangles.len());
    assert!(carved.kept.iter().all(|&v| v < offset) && carved.mesh.is_closed_manifold());
}
