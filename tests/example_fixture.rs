//! Conventions checked on a scene from an independent renderer (`../shared/examples`): camera
//! axes, row-major matrices, bone frames, frame positions vs indices, colour decoding.

mod common;

use glam::DVec3;
use umbra::light::Light;
use umbra::scene::{Scene, Split, View};

fn near_foreground(view: &View, x: f64, y: f64, radius: i64) -> bool {
    let mask = view.mask.as_ref().unwrap();
    let (xi, yi) = (x.floor() as i64, y.floor() as i64);
    for dy in -radius..=radius {
        for dx in -radius..=radius {
            let (px, py) = (xi + dx, yi + dy);
            if px >= 0 && py >= 0 && (px as usize) < mask.width && (py as usize) < mask.height && mask.foreground[py as usize * mask.width + px as usize] {
                return true;
            }
        }
    }
    false
}

#[test]
fn fixture_loads_and_frames_are_positions() {
    let scene = Scene::load(&common::example_scene()).unwrap();
    assert_eq!(scene.skeleton.len(), 14);
    assert_eq!(scene.cameras.len(), 4);
    let indices: Vec<i64> = scene.frames.iter().map(|f| f.index).collect();
    assert_eq!(indices, vec![0, 10, 20, 15]);
    assert_eq!(scene.views.iter().filter(|v| v.split == Split::Train).count(), 9);
    assert!(matches!(scene.lights["dusk"], Light::Environment { .. }));
}

#[test]
fn ground_truth_mesh_projects_into_the_masks() {
    let scene = Scene::load(&common::example_scene()).unwrap();
    let mut checked = 0;
    for view in &scene.views {
        let frame = &scene.frames[view.frame];
        let mesh = frame.mesh.as_ref().expect("fixture frames have meshes");
        let (models, _) = tobj::load_obj(mesh, &tobj::LoadOptions::default()).unwrap();
        let camera = &scene.cameras[view.camera];
        let mut outside = 0;
        let mut total = 0;
        for model in &models {
            for v in model.mesh.positions.chunks(3) {
                let p = DVec3::new(v[0] as f64, v[1] as f64, v[2] as f64);
                let pixel = camera.project(p).expect("mesh in front of the camera");
                total += 1;
                if !near_foreground(view, pixel.x, pixel.y, 1) {
                    outside += 1;
                }
            }
        }
        assert!(total > 100);
        assert_eq!(outside, 0, "{}: {outside} of {total} vertices project outside the mask", view.path.display());
        checked += 1;
    }
    assert_eq!(checked, scene.views.len());
}

#[test]
fn posed_bone_centres_land_in_the_masks() {
    let scene = Scene::load(&common::example_scene()).unwrap();
    for view in &scene.views {
        let pose = &scene.frames[view.frame].pose;
        for (b, bone) in scene.skeleton.bones.iter().enumerate() {
            let centre = pose.to_world(b, bone.centre_local());
            let pixel = scene.cameras[view.camera].project(centre).unwrap();
            assert!(
                near_foreground(view, pixel.x, pixel.y, 0) || near_foreground(view, pixel.x, pixel.y, 1),
                "{} bone {} at {pixel}",
                view.path.display(),
                bone.name
            );
        }
    }
}

#[test]
fn sunlit_pixels_are_bounded_by_the_formula() {
    // a (ambient + E max(0, n.l) V) lies between a * ambient and a * (ambient + E): decoded to
    // linear, every foreground pixel of a sun-lit test image with albedo obeys it.
    let scene = Scene::load(&common::example_scene()).unwrap();
    let Light::Directional { irradiance, ambient, .. } = scene.lights["sun"] else { panic!("sun") };
    let mut interior = 0;
    for view in scene.views.iter().filter(|v| v.light == "sun" && v.albedo.is_some()) {
        let mask = view.mask.as_ref().unwrap();
        let albedo = view.albedo.as_ref().unwrap();
        for y in 1..mask.height - 1 {
            for x in 1..mask.width - 1 {
                let all = (0..9).all(|k| mask.foreground[(y + k / 3 - 1) * mask.width + x + k % 3 - 1]);
                if !all {
                    continue; // silhouettes are anti-aliased
                }
                interior += 1;
                let c = view.colour.get(x, y);
                let a = albedo.get(x, y);
                for ch in 0..3 {
                    let lo = a[ch] as f64 * ambient[ch];
                    let hi = a[ch] as f64 * (ambient[ch] + irradiance[ch]);
                    assert!(
                        c[ch] as f64 >= lo - 0.02 && (c[ch] as f64) <= hi + 0.02,
                        "{} ({x},{y}) ch{ch}: {} not in [{lo}, {hi}]",
                        view.path.display(),
                        c[ch]
                    );
                }
            }
        }
    }
    assert!(interior > 50);
}
