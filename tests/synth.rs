//! The scene generator: same options give the same bytes, its scenes load, and its images
//! match an independent per-pixel evaluation of the scene format's formula.

mod common;

use common::TempDir;
use glam::DVec3;
use umbra::light::Light;
use umbra::scene::{Ray, Scene, Split};
use umbra::synth::{render_view, Character, Kind, SynthOptions, TestKind, TrainingLight};

fn tiny(character: Kind, light: TrainingLight) -> SynthOptions {
    SynthOptions {
        character,
        light,
        size: 24,
        cameras: 2,
        frames: 2,
        test_frames: 1,
        test: vec![TestKind::Poses, TestKind::Views, TestKind::Relight],
        samples: 4,
        seed: 3,
        meshes: true,
        mesh_cell: 0.04,
        ..SynthOptions::default()
    }
}

fn files(dir: &std::path::Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for sub in ["", "images", "masks", "albedo", "lights", "meshes"] {
        let Ok(entries) = std::fs::read_dir(dir.join(sub)) else {
            continue;
        };
        for e in entries {
            let p = e.unwrap().path();
            if p.is_file() {
                out.push((p.strip_prefix(dir).unwrap().display().to_string(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn same_seed_same_bytes_and_the_scene_loads() {
    let a = TempDir::new("synth-a");
    let b = TempDir::new("synth-b");
    let options = tiny(Kind::Quadruped, TrainingLight::Sun);
    umbra::synth::generate(&options, &a.path().join("s"), false, |_, _| {}).unwrap();
    umbra::synth::generate(&options, &b.path().join("s"), false, |_, _| {}).unwrap();
    let (fa, fb) = (files(&a.path().join("s")), files(&b.path().join("s")));
    assert!(fa.len() > 10);
    assert_eq!(fa.iter().map(|f| &f.0).collect::<Vec<_>>(), fb.iter().map(|f| &f.0).collect::<Vec<_>>());
    for (x, y) in fa.iter().zip(&fb) {
        assert!(x.1 == y.1, "{} differs between two runs", x.0);
    }
    let scene = Scene::load(&a.path().join("s")).unwrap();
    assert_eq!(scene.skeleton.len(), 12);
    let kinds: Vec<&str> = scene.lights.values().map(Light::type_name).collect();
    for k in ["directional", "point", "environment"] {
        assert!(kinds.contains(&k), "{kinds:?}");
    }
    let train_frames: Vec<usize> = scene.views_in(Split::Train).map(|v| v.frame).collect();
    let novel_pose = scene.views_in(Split::Test).any(|v| !train_frames.contains(&v.frame));
    assert!(novel_pose);
    assert!(scene.views.iter().all(|v| v.mask.as_ref().unwrap().foreground.iter().any(|&f| f)), "the character is in every image");
    // An existing output is not replaced without --force, and nothing else is touched.
    let err = umbra::synth::generate(&options, &a.path().join("s"), false, |_, _| {}).err().unwrap();
    assert!(err.to_string().contains("already exists"));
}

#[test]
fn human_has_at_least_15_bones_with_the_named_parts() {
    let human = Character::new(Kind::Human);
    assert!(human.skeleton.len() >= 15);
    for part in ["pelvis", "spine", "chest", "neck", "head", "upper_arm_l", "forearm_r", "hand_l", "thigh_r", "shin_l", "foot_r"] {
        assert!(human.skeleton.bones.iter().any(|b| b.name == part), "{part}");
    }
}

/// Dense marching with bisection: an intersection routine independent of sphere tracing.
fn march(character: &Character, pose: &umbra::skeleton::Pose, ray: &Ray, t_max: f64) -> (Option<f64>, f64) {
    let (centre, radius) = character.bounding_sphere(pose);
    let oc = ray.origin - centre;
    let b = oc.dot(ray.direction);
    let disc = b * b - (oc.length_squared() - radius * radius);
    if disc <= 0.0 {
        return (None, f64::INFINITY);
    }
    let (start, end) = ((-b - disc.sqrt()).max(0.0), (-b + disc.sqrt()).min(t_max));
    let step = 0.001;
    let mut t = start;
    let mut closest = f64::INFINITY;
    let mut previous = character.sdf(pose, ray.at(t)).0;
    while t < end {
        let next = (t + step).min(end);
        let d = character.sdf(pose, ray.at(next)).0;
        // How close the ray passes to the surface, away from where it starts.
        if next > 0.02 {
            closest = closest.min(d.abs());
        }
        if d < 0.0 && previous >= 0.0 {
            let (mut lo, mut hi) = (t, next);
            for _ in 0..60 {
                let mid = 0.5 * (lo + hi);
                if character.sdf(pose, ray.at(mid)).0 < 0.0 {
                    hi = mid;
                } else {
                    lo = mid;
                }
            }
            return (Some(hi), closest);
        }
        previous = d;
        t = next;
    }
    (None, closest)
}

fn check_against_independent_formula(light: &Light, kind: Kind) {
    let character = Character::new(kind);
    let pose = character.pose(0.3, 0.2, DVec3::ZERO);
    let target = if kind == Kind::Human { DVec3::new(0.0, 0.9, 0.0) } else { DVec3::new(0.0, 0.45, 0.0) };
    const SIZE: usize = 48;
    let camera = umbra::scene::Camera::look_at("c", target + DVec3::new(2.0, 0.6, 2.2), target, DVec3::Y, SIZE, SIZE, 100.0);
    let rendered = render_view(&character, &pose, &camera, light, 4, 1, 0, 0);
    let (mut compared, mut ambiguous, mut worst) = (0, 0, 0.0f64);
    for j in 1..SIZE - 1 {
        for i in 1..SIZE - 1 {
            let interior = [(0, 0), (1, 0), (0, 1), (-1, 0), (0, -1)]
                .iter()
                .all(|(dx, dy)| rendered.mask.foreground[((j as i64 + dy) * SIZE as i64 + i as i64 + dx) as usize]);
            if !interior {
                continue;
            }
            let ray = camera.pixel_ray(i, j);
            let Some(t) = march(&character, &pose, &ray, 100.0).0 else { panic!("pixel ({i},{j}) is foreground but the march misses") };
            let x = ray.at(t);
            let n = character.normal(&pose, x);
            let a = character.albedo(&pose, x);
            let (l, irradiance, ambient, t_max) = match light {
                Light::Directional { direction, irradiance, ambient } => (*direction, *irradiance, *ambient, 100.0),
                Light::Point { position, intensity, ambient } => {
                    let r = (*position - x).length();
                    ((*position - x) / r, *intensity / (r * r), *ambient, r)
                }
                _ => unreachable!(),
            };
            let cosine = n.dot(l).max(0.0);
            let (blocked, closest) = march(&character, &pose, &Ray { origin: x + n * umbra::synth::trace::SHADOW_OFFSET, direction: l }, t_max);
            if cosine > 0.0 && closest < 0.003 && blocked.is_none() {
                ambiguous += 1; // the shadow ray grazes the surface: a shadow edge
                continue;
            }
            let visibility = if blocked.is_some() { 0.0 } else { 1.0 };
            let expected = a * (ambient + irradiance * cosine * visibility);
            let got = rendered.colour.get(i, j);
            for c in 0..3 {
                worst = worst.max((got[c] as f64 - expected[c]).abs());
            }
            compared += 1;
        }
    }
    assert!(compared > 200, "compared {compared}");
    assert!(ambiguous * 10 < compared, "{ambiguous} shadow-edge pixels of {compared}");
    assert!(worst < 1e-3, "max error {worst:e} over {compared} pixels");
}

#[test]
fn sunlit_images_match_an_independent_evaluation() {
    let sun = Light::Directional {
        direction: DVec3::new(0.45, 0.8, 0.4).normalize(),
        irradiance: DVec3::new(0.85, 0.82, 0.78),
        ambient: DVec3::new(0.2, 0.21, 0.24),
    };
    check_against_independent_formula(&sun, Kind::Human);
    check_against_independent_formula(&sun, Kind::Quadruped);
    check_against_independent_formula(&sun, Kind::Dressed);
}

#[test]
fn point_lit_images_match_an_independent_evaluation() {
    let lamp = Light::Point { position: DVec3::new(1.1, 2.3, 1.4), intensity: DVec3::new(4.6, 4.4, 4.1), ambient: DVec3::new(0.15, 0.15, 0.17) };
    check_against_independent_formula(&lamp, Kind::Human);
}

#[test]
fn uniform_light_without_occlusion_is_albedo_times_radiance() {
    // Monte Carlo with visibility: on open, convex parts the estimate is exact up to occlusion.
    let character = Character::new(Kind::Human);
    let pose = character.pose(0.0, 0.0, DVec3::ZERO);
    let camera = umbra::scene::Camera::look_at("c", DVec3::new(0.0, 1.6, 3.0), DVec3::new(0.0, 1.6, 0.0), DVec3::Y, 16, 16, 60.0);
    let light = Light::Uniform { radiance: DVec3::new(0.9, 0.9, 0.9) };
    let r = render_view(&character, &pose, &camera, &light, 64, 1, 1, 0);
    let mut n = 0;
    for k in 0..256 {
        if r.mask.foreground[k] {
            let (c, a) = (r.colour.pixels[k], r.albedo.pixels[k]);
            for ch in 0..3 {
                assert!(c[ch] <= a[ch] * 0.9 + 1e-6, "never brighter than unoccluded");
            }
            n += 1;
        }
    }
    assert!(n > 10);
}

#[test]
fn shipped_scenes_reproduce_byte_for_byte_from_their_options() {
    for name in ["human-sun", "dog-sun", "human-mono", "human-sun-128", "human-sun-128-aa", "human-dressed", "human-lamp", "human-suns"] {
        let shipped = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("datasets-synthetic").join(name);
        let text = std::fs::read_to_string(shipped.join("scene.json")).unwrap();
        let json: serde_json::Value = serde_json::from_str(&text).unwrap();
        let options: SynthOptions = serde_json::from_value(json["generator"]["options"].clone()).unwrap();
        let out = TempDir::new("reproduce");
        umbra::synth::generate(&options, &out.path().join(name), false, |_, _| {}).unwrap();
        let (a, b) = (files(&shipped), files(&out.path().join(name)));
        assert_eq!(a.len(), b.len(), "{name}");
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(x.0, y.0);
            assert!(x.1 == y.1, "{name}/{} differs from a fresh generation", x.0);
        }
    }
}

#[test]
fn clothing_pattern_has_fine_high_contrast_detail_where_plain_has_none() {
    use umbra::synth::Pattern;
    let plain = Character::new(Kind::Human);
    let clothed = Character::new(Kind::Human).with_pattern(Pattern::Clothing);
    let pose = plain.pose(0.0, 0.0, glam::DVec3::ZERO);
    // Walk up the front of the chest and down the front of the left thigh, 5 mm at a time,
    // on the surface (march in from the front along -Z until the SDF changes sign).
    let surface = |x: f64, y: f64| {
        let mut z = 0.4;
        while plain.sdf(&pose, glam::DVec3::new(x, y, z)).0 > 0.0 && z > -0.4 {
            z -= 0.001;
        }
        glam::DVec3::new(x, y, z)
    };
    let luminance = |c: glam::DVec3| 0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z;
    for (x, ys) in [(0.02, (1.06..1.42)), (0.10, (0.55..0.9))] {
        let samples: Vec<glam::DVec3> = (0..).map(|k| ys.start + 0.005 * k as f64).take_while(|y| *y < ys.end).map(|y| surface(x, y)).collect();
        let edges = |c: &Character| samples.windows(2).filter(|w| (luminance(c.albedo(&pose, w[0])) - luminance(c.albedo(&pose, w[1]))).abs() > 0.2).count();
        // 4-6 cm cells over 35 cm: several strong edges; the plain clothes have none.
        assert!(edges(&clothed) >= 5, "x = {x}: {} edges", edges(&clothed));
        assert_eq!(edges(&plain), 0, "x = {x}");
    }
}

#[test]
fn a_scaled_capture_is_the_same_images_of_a_larger_world() {
    // Body, motion, cameras and lamps scaled together (lamps brighter by the square): the
    // images are the same but for the few pixels where the tracer's fixed epsilons decide.
    for kind in [Kind::Human, Kind::Dressed] {
        let base = SynthOptions { light: TrainingLight::Point, test: vec![TestKind::Poses], meshes: false, ..tiny(kind, TrainingLight::Point) };
        let (one, three) = (base.plan().unwrap(), SynthOptions { scale: 3.0, ..base.clone() }.plan().unwrap());
        for (a, b) in one.character.skeleton.bones.iter().zip(&three.character.skeleton.bones) {
            assert!((b.length - 3.0 * a.length).abs() < 1e-12, "{}", a.name);
        }
        let (l1, l3) = (&one.lights[0].1, &three.lights[0].1);
        match (l1, l3) {
            (Light::Point { position: p1, intensity: i1, .. }, Light::Point { position: p3, intensity: i3, .. }) => {
                assert!((*p3 - *p1 * 3.0).length() < 1e-12 && (*i3 - *i1 * 9.0).length() < 1e-9);
            }
            _ => panic!("the training light is a lamp"),
        }
        let mut differing = 0;
        let mut total = 0;
        for (k, view) in one.views.iter().enumerate() {
            let (f1, f3) = (&one.frames[view.frame].2, &three.frames[view.frame].2);
            let r1 = render_view(&one.character, f1, &one.cameras[view.camera], l1, 4, 1, 3, k as u64);
            let r3 = render_view(&three.character, f3, &three.cameras[view.camera], l3, 4, 1, 3, k as u64);
            for (p, q) in r1.colour.pixels.iter().zip(&r3.colour.pixels) {
                total += 1;
                if (0..3).any(|c| (p[c] - q[c]).abs() > 1e-3) {
                    differing += 1;
                }
            }
            assert_eq!(r1.mask.foreground, r3.mask.foreground, "{kind:?} view {k}: the silhouettes differ");
        }
        assert!(differing * 100 <= total, "{kind:?}: {differing} of {total} pixels differ");
    }
}

#[test]
fn a_near_lamp_sits_at_its_distance_and_lights_the_body_as_brightly() {
    let base = SynthOptions { test: vec![TestKind::Poses], meshes: false, ..tiny(Kind::Human, TrainingLight::Point) };
    let near = SynthOptions { lamp_distance: Some(1.0), ..base.clone() };
    let (far, near) = (base.plan().unwrap(), near.plan().unwrap());
    let centre = DVec3::new(0.0, 0.9, 0.0);
    match (&far.lights[0].1, &near.lights[0].1) {
        (Light::Point { position: pf, intensity: i_far, .. }, Light::Point { position: pn, intensity: i_near, .. }) => {
            assert!(((*pn - centre).length() - 1.0).abs() < 1e-12, "{pn:?}");
            assert!((*pn - centre).normalize().dot((*pf - centre).normalize()) > 1.0 - 1e-12, "same direction");
            let ratio = (*pn - centre).length() / (*pf - centre).length();
            assert!((*i_near - *i_far * (ratio * ratio)).length() < 1e-12);
        }
        _ => panic!("the training light is a lamp"),
    }
    // Only a point-lit capture has a lamp to place, and not inside the body.
    assert!(SynthOptions { lamp_distance: Some(1.0), ..tiny(Kind::Human, TrainingLight::Sun) }.plan().is_err());
    assert!(SynthOptions { lamp_distance: Some(0.1), ..base }.plan().is_err());
}

#[test]
fn the_training_sun_can_come_from_any_direction() {
    let base = SynthOptions { test: vec![TestKind::Poses], meshes: false, ..tiny(Kind::Human, TrainingLight::Sun) };
    let low = SynthOptions { sun_direction: Some(vec![0.9, 0.3, -0.3]), ..base.clone() };
    match (&base.plan().unwrap().lights[0].1, &low.plan().unwrap().lights[0].1) {
        (Light::Directional { direction: usual, .. }, Light::Directional { direction, .. }) => {
            assert!((*usual - DVec3::new(0.45, 0.8, 0.4).normalize()).length() < 1e-12, "the default sun is unchanged");
            assert!((*direction - DVec3::new(0.9, 0.3, -0.3).normalize()).length() < 1e-12, "{direction:?}");
        }
        _ => panic!("the training light is a sun"),
    }
    // Three numbers, not all zero, and only for a sun.
    for bad in [vec![0.0, 0.0, 0.0], vec![1.0, 2.0], vec![f64::NAN, 1.0, 0.0]] {
        assert!(SynthOptions { sun_direction: Some(bad.clone()), ..base.clone() }.plan().is_err(), "{bad:?}");
    }
    assert!(SynthOptions { sun_direction: Some(vec![0.0, 1.0, 0.0]), ..tiny(Kind::Human, TrainingLight::Point) }.plan().is_err());
}

#[test]
fn a_light_stage_capture_lights_each_image_by_one_of_its_suns() {
    let options = SynthOptions { suns: 3, test: vec![TestKind::Poses, TestKind::Relight], meshes: false, ..tiny(Kind::Human, TrainingLight::Sun) };
    let plan = options.plan().unwrap();
    let names: Vec<&str> = plan.lights.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(&names[..3], &["sun", "sun-b", "sun-c"], "{names:?}");
    assert!(plan.lights[..3].iter().all(|(_, l)| matches!(l, Light::Directional { .. })));
    for view in plan.views.iter().filter(|v| v.split == Split::Train) {
        assert_eq!(view.light, names[(view.camera + view.frame) % 3], "{}", view.name);
    }
    // The relighting lights stay test-only.
    assert!(plan.views.iter().any(|v| v.split == Split::Test && v.light == "sun2"));
    assert!(plan.views.iter().filter(|v| v.split == Split::Train).all(|v| v.light.starts_with("sun") && v.light != "sun2"));
    assert!(SynthOptions { suns: 5, ..options.clone() }.plan().is_err());
    assert!(SynthOptions { suns: 2, light: TrainingLight::Point, ..options }.plan().is_err());
}

/// `--pixel-samples 4` averages 4 x 4 stratified rays per pixel: the same images as one ray
/// where a pixel lies wholly on or off the body, partly covered pixels between, the mask
/// where more than half is covered; and the scene's footprint is read off its training images
/// (area for the anti-aliased capture, centre for the other, and for the shared example from
/// an independent renderer, area).
#[test]
fn anti_aliased_captures_average_each_pixel_and_are_recognised() {
    let dir = TempDir::new("aa");
    let options = |pixel_samples: usize| SynthOptions {
        size: 48,
        cameras: 3,
        frames: 3,
        test: vec![TestKind::Poses],
        pixel_samples,
        ..tiny(Kind::Human, TrainingLight::Sun)
    };
    umbra::synth::generate(&options(1), &dir.path().join("centre"), false, |_, _| {}).unwrap();
    umbra::synth::generate(&options(4), &dir.path().join("area"), false, |_, _| {}).unwrap();
    let centre = Scene::load(&dir.path().join("centre")).unwrap();
    let area = Scene::load(&dir.path().join("area")).unwrap();
    // Inside the silhouette a pixel's mean stays near its centre (the shading varies a little
    // across it); along it, where the pixel is partly covered, it moves much more.
    let (mut inside, mut edge) = ((0.0, 0usize), (0.0, 0usize));
    for (a, b) in centre.views.iter().zip(&area.views) {
        let (ma, mb) = (a.mask.as_ref().unwrap(), b.mask.as_ref().unwrap());
        let w = mb.width;
        for p in 0..ma.foreground.len() {
            let (ca, cb) = (a.colour.pixel(p), b.colour.pixel(p));
            if !mb.foreground[p] {
                assert_eq!(cb, [0.0; 3], "pixels outside the mask are black");
                continue;
            }
            if !ma.foreground[p] {
                continue;
            }
            let (x, y) = (p % w, p / w);
            let interior =
                x > 0 && y > 0 && x + 1 < w && y + 1 < mb.height && [p - 1, p + 1, p - w, p + w].iter().all(|&q| mb.foreground[q] && ma.foreground[q]);
            let difference = (0..3).map(|c| (ca[c] - cb[c]).abs() as f64).sum::<f64>();
            let tally = if interior { &mut inside } else { &mut edge };
            tally.0 += difference;
            tally.1 += 1;
        }
        let differing = ma.foreground.iter().zip(&mb.foreground).filter(|(x, y)| x != y).count();
        assert!(differing * 10 < ma.foreground.iter().filter(|&&f| f).count(), "masks agree but at the silhouette: {differing}");
    }
    let (inside, edge) = (inside.0 / inside.1.max(1) as f64, edge.0 / edge.1.max(1) as f64);
    assert!(edge > 2.0 * inside, "mean difference inside {inside}, along the silhouette {edge}");
    let (ec, ea) = (centre.footprint(), area.footprint());
    assert_eq!(ec.footprint, umbra::scene::Footprint::Centre, "{ec:?}");
    assert_eq!(ea.footprint, umbra::scene::Footprint::Area, "{ea:?}");
    let example = Scene::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/examples/quadruped-tiny")).unwrap();
    assert_eq!(example.footprint().footprint, umbra::scene::Footprint::Area, "{:?}", example.footprint());
}

#[test]
fn each_relighting_light_can_see_the_novel_pose_views() {
    // Three test frames seen by two cameras each: six novel-pose views.
    let base = SynthOptions { cameras: 4, test_frames: 3, meshes: false, ..tiny(Kind::Human, TrainingLight::Sun) };
    let pose_views = |plan: &umbra::synth::Plan| -> Vec<(usize, usize)> {
        plan.views.iter().filter(|v| v.split == umbra::scene::Split::Test && v.light == "sun" && v.frame >= 2).map(|v| (v.camera, v.frame)).collect()
    };
    let relit = |plan: &umbra::synth::Plan, light: &str| -> Vec<(usize, usize)> {
        plan.views.iter().filter(|v| v.light == light).map(|v| (v.camera, v.frame)).collect()
    };
    let one = base.plan().unwrap();
    assert_eq!(pose_views(&one).len(), 6);
    for light in ["sun2", "lamp", "sky"] {
        assert_eq!(relit(&one, light).len(), 1, "{light}: one view by default");
    }
    for asked in [4, 6, 50] {
        let plan = SynthOptions { relit_views: asked, ..base.clone() }.plan().unwrap();
        assert_eq!(pose_views(&plan), pose_views(&one), "the novel-pose views do not change");
        for light in ["sun2", "lamp", "sky"] {
            let views = relit(&plan, light);
            assert_eq!(views[0], relit(&one, light)[0], "{light}: the first view is the default's");
            assert_eq!(views.len(), asked.min(6), "{light}: {views:?}");
            let mut distinct = views.clone();
            distinct.sort();
            distinct.dedup();
            assert_eq!(distinct.len(), views.len(), "{light}: no view twice");
            assert!(views.iter().all(|v| pose_views(&plan).contains(v)), "{light}: {views:?} are novel-pose views");
        }
        let mut names: Vec<&str> = plan.views.iter().map(|v| v.name.as_str()).collect();
        names.sort();
        assert!(names.windows(2).all(|w| w[0] != w[1]), "every image has a name of its own");
    }
    assert!(SynthOptions { relit_views: 0, ..base }.plan().is_err());
}
