//! The training motion's refinement: the gradient a motion increment carries through the grid
//! field's lookups against finite differences of the field in the corrected pose, and the
//! corrected pose itself (a tracker's error undone by its inverse).

mod common;

use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};
use glam::{DMat3, DVec3};
use umbra::field::{AvatarField, FieldConfig, PoseTensors};
use umbra::random::Stream;
use umbra::skeleton::{MotionIncrement, Pose};
use umbra::synth::character::{Character, Kind};
use umbra::train::motion::MotionCorrections;

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
}

/// A grid field with busy features (so the SDF varies within a cell) on the walking human.
fn field(character: &Character, pose: &Pose, device: &Device) -> AvatarField {
    let (lo, hi) = pose.bounds(&character.skeleton);
    let config = FieldConfig::with_grid(character.skeleton.bones.iter().map(|b| b.length as f32).collect(), (hi - lo).length() as f32);
    let mut field = config.init(device, 7);
    let mut stream = Stream::new(3, 1, 0);
    let grid = field.grid.as_mut().unwrap();
    let [rows, features] = grid.table.val().dims();
    let table: Vec<f32> = (0..rows * features).map(|_| (stream.uniform() * 2.0 - 1.0) as f32 * 0.5).collect();
    grid.table = Param::from_tensor(Tensor::from_data(TensorData::new(table, [rows, features]), device));
    field
}

/// The walking human mid-stride and a busy field on it.
fn walking(device: &Device) -> (Character, Pose, AvatarField) {
    let character = Character::new(Kind::Human);
    let pose = character.pose(0.3, 0.2, DVec3::new(0.05, 0.0, -0.1));
    let field = field(&character, &pose, device);
    (character, pose, field)
}

/// Points along the middle of every bone, a few centimetres off its axis: carried by one bone
/// (given beside each).
fn points(character: &Character, pose: &Pose) -> (Vec<DVec3>, Vec<usize>) {
    let mut stream = Stream::new(9, 2, 0);
    let (mut out, mut carriers) = (Vec::new(), Vec::new());
    for (b, bone) in character.skeleton.bones.iter().enumerate() {
        for _ in 0..12 {
            let along = bone.length * (0.3 + 0.4 * stream.uniform());
            let local = DVec3::new((stream.uniform() - 0.5) * 0.06, along, (stream.uniform() - 0.5) * 0.06);
            out.push(pose.to_world(b, local));
            carriers.push(b);
        }
    }
    (out, carriers)
}

/// `sum_i w_i sdf(x_i)` in `pose`, carrying `motion` when given.
fn loss(
    field: &AvatarField,
    character: &Character,
    pose: &Pose,
    pts: &[DVec3],
    weights: &Tensor<1>,
    motion: bool,
    device: &Device,
) -> (Tensor<1>, PoseTensors) {
    let mut tensors = PoseTensors::new(pose, &character.skeleton, device);
    if motion {
        tensors.motion = Some(MotionIncrement::new(&character.skeleton, pose, device));
    }
    let flat: Vec<f32> = pts.iter().flat_map(|p| p.as_vec3().to_array()).collect();
    let input = Tensor::<2>::from_data(TensorData::new(flat, [pts.len(), 3]), device);
    let sdf = field.decode(input, &tensors).sdf;
    ((sdf * weights.clone()).sum(), tensors)
}

/// The increment's gradient (`[B + 1, 3]`, flattened) of `sum_i w_i sdf(x_i)` in `pose`, and
/// that loss in any pose, summed in f64 on the host so that a small step's difference is not
/// rounding.
fn gradient_and_loss<'a>(
    field: &'a AvatarField,
    character: &'a Character,
    pose: &Pose,
    pts: &'a [DVec3],
    w: &'a [f32],
    device: &'a Device,
) -> (Vec<f32>, impl Fn(&Pose) -> f64 + 'a) {
    let weights = Tensor::<1>::from_data(TensorData::new(w.to_vec(), [pts.len()]), device);
    let (l, tensors) = loss(field, character, pose, pts, &weights, true, device);
    let grads = l.backward();
    let gradient = values(tensors.motion.as_ref().unwrap().leaf.clone().grad(&grads).expect("the increment is in the graph"));
    let value = move |p: &Pose| {
        let tensors = PoseTensors::new(p, &character.skeleton, device);
        let flat: Vec<f32> = pts.iter().flat_map(|p| p.as_vec3().to_array()).collect();
        let sdf = values(field.decode(Tensor::<2>::from_data(TensorData::new(flat, [pts.len(), 3]), device), &tensors).sdf.inner());
        sdf.iter().zip(w).map(|(s, w)| *s as f64 * *w as f64).sum::<f64>()
    };
    (gradient, value)
}

/// The pose with bone `bone` (and every bone below it) turned by `angle` about world `axis`
/// through its head, or the whole skeleton shifted by `shift`.
fn moved(character: &Character, pose: &Pose, bone: Option<usize>, axis: DVec3, angle: f64, shift: DVec3) -> Pose {
    let turn = glam::DMat4::from_axis_angle(axis, angle);
    let bone_to_world = pose
        .bone_to_world
        .iter()
        .enumerate()
        .map(|(b, m)| match bone {
            Some(j) if below(character, b, j) => {
                let head = pose.bone_to_world[j].w_axis.truncate();
                glam::DMat4::from_translation(head) * turn * glam::DMat4::from_translation(-head) * *m
            }
            Some(_) => *m,
            None => glam::DMat4::from_translation(shift) * *m,
        })
        .collect();
    Pose { bone_to_world }
}

/// The increment's gradient (each bone's world turn about its head, then the world shift)
/// against central differences of the loss with the bones moved: the skeleton shifted and the
/// root turned (every bone moves alike, where the blended warp is exact), and a limb turned
/// with its children (points carried by one bone).
#[test]
fn the_motion_increment_carries_the_gradient_of_the_corrected_pose() {
    let device = Device::flex().autodiff();
    let (character, pose, field) = walking(&device);
    let (pts, carriers) = points(&character, &pose);
    let b = character.skeleton.len();
    let limb = character.skeleton.bones.iter().position(|bone| bone.name.contains("forearm") || bone.name.contains("shin")).unwrap_or(b - 1);
    let mut checked = 0;
    for (bone, row) in [(None, b), (Some(0), 0), (Some(limb), limb)] {
        // The loss weighs the points the move carries rigidly (every one for the skeleton's
        // shift and the root's turn; the limb's and those below it for the limb's turn).
        let mut stream = Stream::new(4, 4, row as u64);
        let w: Vec<f32> =
            carriers.iter().map(|&c| if bone.is_none_or(|j| below(&character, c, j)) { (stream.uniform() * 2.0 - 1.0) as f32 } else { 0.0 }).collect();
        let (gradient, value) = gradient_and_loss(&field, &character, &pose, &pts, &w, &device);
        for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
            // Small beside the finest cell (1/160 of the body), so few points cross a cell's
            // face, where the trilinear slope jumps.
            let h = 2e-4;
            let (plus, minus) = match bone {
                None => (moved(&character, &pose, None, axis, 0.0, axis * h), moved(&character, &pose, None, axis, 0.0, -axis * h)),
                Some(j) => (moved(&character, &pose, Some(j), axis, h, DVec3::ZERO), moved(&character, &pose, Some(j), axis, -h, DVec3::ZERO)),
            };
            let fd = (value(&plus) - value(&minus)) / (2.0 * h);
            let analytic = gradient[3 * row..3 * row + 3].iter().zip(axis.to_array()).map(|(g, a)| *g as f64 * a).sum::<f64>();
            let scale = fd.abs().max(analytic.abs()).max(0.02);
            assert!((fd - analytic).abs() < 0.03 * scale, "bone {bone:?} axis {axis}: finite difference {fd} vs gradient {analytic}");
            checked += (fd.abs() > 0.02) as usize;
        }
    }
    assert!(checked >= 6, "too few of the differences were large enough to test ({checked})");
}

/// Whether bone `b` is bone `j` or below it.
fn below(character: &Character, b: usize, j: usize) -> bool {
    let mut k = Some(b);
    while let Some(c) = k {
        if c == j {
            return true;
        }
        k = character.skeleton.bones[c].parent;
    }
    false
}

/// A tracker's error (each bone turned in its parent's frame, the root shifted) is undone by the
/// corrections that invert it, to rounding.
#[test]
fn a_corrected_pose_undoes_the_error_it_inverts() {
    let character = Character::new(Kind::Human);
    let truth = character.pose(0.6, -0.3, DVec3::new(0.0, 0.0, 0.2));
    let mut stream = Stream::new(1, 2, 3);
    let turns: Vec<[f64; 3]> = (0..character.skeleton.len()).map(|_| [(); 3].map(|_| (stream.uniform() - 0.5) * 0.1)).collect();
    let shift = [0.01, -0.02, 0.005];
    let tracked = truth.corrected(&character.skeleton, &turns, shift);
    // Undo: the inverse turn in each bone's frame, the shift back (the root's turn is about
    // its head, which the shift moved).
    let undo: Vec<[f64; 3]> = turns.iter().map(|t| (-DVec3::from_array(*t)).to_array()).collect();
    let back = tracked.corrected(&character.skeleton, &undo, shift.map(|v| -v));
    for (a, b) in back.bone_to_world.iter().zip(&truth.bone_to_world) {
        let rotation = (DMat3::from_mat4(*a).transpose() * DMat3::from_mat4(*b) - DMat3::IDENTITY).abs_diff_eq(DMat3::ZERO, 1e-9);
        assert!(rotation && (a.w_axis - b.w_axis).length() < 1e-9, "{a} vs {b}");
    }
    // And it moved the bones: the tracked pose is not the truth.
    assert!((tracked.bone_to_world[5].w_axis - truth.bone_to_world[5].w_axis).length() > 1e-3);
}

/// The corrections start at the given motion, an Adam step moves a frame's against its
/// gradient by the learning rate (and no other frame), and a checkpoint's copy restores them
/// exactly but is refused for another scene's frames.
#[test]
fn corrections_step_against_their_gradient_and_survive_a_checkpoint() {
    let dir = common::TempDir::new("motion-corrections");
    let path = common::tiny_synth(dir.path(), umbra::synth::TrainingLight::Sun, 16, 2, vec![umbra::synth::TestKind::Poses], 3);
    let scene = umbra::scene::Scene::load(&path).unwrap();
    let mut motion = MotionCorrections::new(&scene).unwrap();
    let lever = motion.lever();
    assert!((lever - umbra::skeleton::body_length(umbra::train::motion::LEVER_ON_HUMAN, scene.body_extent())).abs() < 1e-12);
    let frames = motion.frames().to_vec();
    assert_eq!(frames.len(), 2, "two training frames");
    let (f, other) = (frames[0], frames[1]);
    assert_eq!(motion.pose(&scene.skeleton, f, &scene.frames[f].pose), scene.frames[f].pose);
    let rows = scene.skeleton.len() + 1;
    // A gradient on bone 2's x turn through the leaf, and on the shift through the render.
    let mut leaf = vec![0.0f32; 3 * rows];
    leaf[3 * 2] = 0.5;
    let mut increment = vec![0.0f32; 3 * rows];
    increment[3 * (rows - 1) + 1] = -2.0;
    motion.step(0, &leaf, &increment, &scene.frames[f].pose, 0.01);
    let moved = motion.pose(&scene.skeleton, f, &scene.frames[f].pose);
    let turn = |p: &Pose| DMat3::from_mat4(p.bone_to_world[2]);
    let before = turn(&scene.frames[f].pose);
    let angle = glam::DQuat::from_mat3(&(before.transpose() * turn(&moved))).to_scaled_axis();
    assert!((angle.x + 0.01).abs() < 1e-6 && angle.y.abs() < 1e-6, "bone 2 turned by {angle} in its own frame");
    let shift = moved.bone_to_world[0].w_axis - scene.frames[f].pose.bone_to_world[0].w_axis;
    assert!((shift.y - 0.01 * lever).abs() < 1e-6 && shift.x.abs() < 1e-9, "the root moved by {shift}");
    assert_eq!(motion.pose(&scene.skeleton, other, &scene.frames[other].pose), scene.frames[other].pose);
    let moved_report = motion.moved(&scene.skeleton);
    assert!((moved_report.largest_degrees - 0.01f64.to_degrees()).abs() < 1e-6 && (moved_report.largest_shift_cm - lever).abs() < 1e-6);
    // The checkpoint's copy.
    let mut restored = MotionCorrections::new(&scene).unwrap();
    restored.restore(&motion.to_json()).unwrap();
    assert_eq!(restored, motion);
    let mut other_frames = motion.to_json();
    other_frames["frames"] = serde_json::json!([0, 7]);
    assert!(restored.restore(&other_frames).unwrap_err().contains("frames"));
}

/// The view increment's gradient (each camera's world turn about its centre) against central
/// differences of the loss with the camera turned: every point of a ray seen where the turned
/// camera's ray of the same pixel meets it (`CameraPoses::corrected_ray`'s rule,
/// `o + R (x - o)`). Two cameras; the points of each are weighed apart, so each camera's row
/// must carry its own points' gradient and none of the other's.
#[test]
fn the_view_increment_carries_the_gradient_of_the_turned_cameras() {
    use umbra::skeleton::ViewIncrement;
    let device = Device::flex().autodiff();
    let (character, pose, field) = walking(&device);
    let (pts, _) = points(&character, &pose);
    let centres = [DVec3::new(0.4, 1.1, 3.0), DVec3::new(-2.6, 0.9, 0.8)];
    let rows: Vec<u32> = (0..pts.len()).map(|i| (i % 2) as u32).collect();
    let origins: Vec<f32> = rows.iter().flat_map(|&r| centres[r as usize].as_vec3().to_array()).collect();
    let mut stream = Stream::new(5, 6, 7);
    let w: Vec<f32> = pts.iter().map(|_| (stream.uniform() * 2.0 - 1.0) as f32).collect();
    let weights = Tensor::<1>::from_data(TensorData::new(w.clone(), [pts.len()]), &device);
    let mut tensors = PoseTensors::new(&pose, &character.skeleton, &device);
    let view = ViewIncrement::new(2, 0.01, &device);
    tensors.view = Some(view.along(&rows, origins));
    let flat: Vec<f32> = pts.iter().flat_map(|p| p.as_vec3().to_array()).collect();
    let sdf = field.decode(Tensor::<2>::from_data(TensorData::new(flat, [pts.len(), 3]), &device), &tensors).sdf;
    let grads = (sdf * weights).sum().backward();
    let gradient = values(view.leaf.grad(&grads).expect("the view increment is in the graph"));
    let plain = PoseTensors::new(&pose, &character.skeleton, &device);
    // Camera `camera` turned by `turn` about its centre: the loss in f64.
    let value = |camera: usize, turn: DVec3| {
        let rotation = DMat3::from_quat(glam::DQuat::from_scaled_axis(turn));
        let moved: Vec<f32> = pts
            .iter()
            .zip(&rows)
            .flat_map(|(p, &r)| {
                let o = centres[r as usize];
                let seen = if r as usize == camera { o + rotation * (*p - o) } else { *p };
                seen.as_vec3().to_array()
            })
            .collect();
        let sdf = values(field.decode(Tensor::<2>::from_data(TensorData::new(moved, [pts.len(), 3]), &device), &plain).sdf.inner());
        sdf.iter().zip(&w).map(|(s, w)| *s as f64 * *w as f64).sum::<f64>()
    };
    let mut checked = 0;
    for camera in 0..2 {
        for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
            // Points 1-3 m away move by 0.1-0.3 mm, small beside the finest cell.
            let h = 1e-4;
            let fd = (value(camera, axis * h) - value(camera, -axis * h)) / (2.0 * h);
            let analytic = gradient[3 * camera..3 * camera + 3].iter().zip(axis.to_array()).map(|(g, a)| *g as f64 * a).sum::<f64>();
            let scale = fd.abs().max(analytic.abs()).max(0.05);
            assert!((fd - analytic).abs() < 0.03 * scale, "camera {camera} axis {axis}: finite difference {fd} vs gradient {analytic}");
            checked += (fd.abs() > 0.05) as usize;
        }
    }
    assert!(checked >= 4, "too few of the differences were large enough to test ({checked})");
}

/// A training step's camera gradient points down its loss: each camera value's first Adam step
/// (against its gradient's sign) agrees with central differences of the step's loss on the same
/// batch, its rays cast again from the cameras turned (their sampling intervals kept, as a
/// step's gradient keeps its samples' distances along the rays). Under uniform light, where
/// a ray's colour is its albedo's: the whole path from the batch's camera rows through the
/// render's parts to the Adam step, exact. (A sun's shading carries the increment into its
/// normals by a difference over a stencil, and a grid's normals jump at its cells' faces, so
/// there the step's loss is too rough for a difference to judge.)
#[test]
fn a_steps_camera_gradient_points_down_its_loss() {
    use umbra::train::{TrainState, Trainer};
    let dir = common::TempDir::new("camera-gradient");
    let path = common::tiny_synth(dir.path(), umbra::synth::TrainingLight::Uniform, 32, 3, vec![umbra::synth::TestKind::Poses], 4);
    let scene = umbra::scene::Scene::load(&path).unwrap();
    let default = std::fs::read_to_string(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("schedules/default.toml")).unwrap();
    // The samples stratified over each ray's bound alone (no search for the surface), so the
    // loss is smooth in the cameras: a search's fine samples move by jumps.
    let settings = [
        ("refine_cameras", "true"),
        ("rays_per_batch", "384"),
        ("samples_per_ray", "48"),
        ("fine_samples_per_ray", "0"),
        ("early_fine_samples_per_ray", "0"),
        ("probe_samples_per_ray", "0"),
        ("early_probe_samples_per_ray", "0"),
        ("cull_samples", "false"),
    ];
    // Each key's line set whole, so no key is changed through another's name.
    let text: String = default
        .lines()
        .map(|line| match settings.iter().find(|(key, _)| line.split('=').next().map(str::trim) == Some(*key)) {
            Some((key, value)) => format!("{key} = {value}\n"),
            None => format!("{line}\n"),
        })
        .collect();
    assert_eq!(settings.iter().filter(|(key, _)| text.contains(&format!("\n{key} = "))).count(), settings.len(), "every setting is in the default schedule");
    let schedule_path = dir.path().join("schedule.toml");
    std::fs::write(&schedule_path, text).unwrap();
    let schedule = umbra::schedule::Schedule::load(&schedule_path).unwrap();
    let mut trainer = Trainer::new(scene, schedule, umbra::backend::Backend::Flex, 0).unwrap();
    for _ in 0..60 {
        trainer.iterate().unwrap();
    }
    // Past the silhouette stage: the colour, the mask and the cameras' prior all weigh.
    trainer.set_iteration(800).unwrap();
    let batch = trainer.draw_batch().unwrap();
    assert_eq!(batch.rays.cameras.len(), batch.rays.len(), "the batch's rays carry their cameras");
    let state = trainer.state().unwrap().clone();
    let given = state.cameras.as_ref().unwrap().to_json();
    // The step's loss with camera value `k` (row-major over the `[C, 3]` turns) moved
    // by `h`, the batch's rays cast from the moved cameras.
    let loss_with = |k: usize, h: f64| -> f64 {
        let mut moved = given.clone();
        let value = &mut moved["turns"][k / 3][k % 3];
        *value = serde_json::json!(value.as_f64().unwrap() + h);
        let mut state: TrainState = state.clone();
        let cameras = state.cameras.as_mut().unwrap();
        cameras.restore(&moved).unwrap();
        let mut recast = batch.clone();
        for (i, &(view, pixel, _)) in batch.sources.iter().enumerate() {
            let c = trainer.scene.views[view].camera;
            let camera = &trainer.scene.cameras[c];
            let ray = cameras.corrected_ray(c, camera.pixel_ray(pixel % camera.width, pixel / camera.width));
            recast.rays.origins[3 * i..3 * i + 3].copy_from_slice(&ray.origin.as_vec3().to_array());
            recast.rays.directions[3 * i..3 * i + 3].copy_from_slice(&ray.direction.as_vec3().to_array());
        }
        let stats = trainer.step(recast, state).1.unwrap();
        // The terms a ray's colour and coverage make: the others (the Gaussians' fit, the
        // regularisers) are evaluated at the rays' samples but say nothing of the cameras.
        let it = trainer.state().unwrap().iteration;
        stats
            .terms
            .iter()
            .filter(|(name, _)| ["mask", "rgb", "grey", "camera_prior"].contains(&name.as_str()))
            .map(|(name, v)| v * trainer.schedule.weight(name, it))
            .sum::<f64>()
    };
    let (after, stats) = trainer.step(batch.clone(), state.clone());
    stats.unwrap();
    let moved = after.cameras.as_ref().unwrap().to_json();
    let rows = given["turns"].as_array().unwrap().len();
    let (mut agreed, mut tested) = (0, 0);
    for k in 0..3 * rows {
        let step = moved["turns"][k / 3][k % 3].as_f64().unwrap() - given["turns"][k / 3][k % 3].as_f64().unwrap();
        let h: f64 = std::env::var("H").ok().and_then(|v| v.parse().ok()).unwrap_or(2e-4);
        let slope = (loss_with(k, h) - loss_with(k, -h)) / (2.0 * h);
        if slope.abs() > 1e-3 {
            tested += 1;
            agreed += (step * slope < 0.0) as usize;
        }
    }
    assert!(tested >= 6, "too few of the slopes were large enough to test ({tested})");
    assert_eq!(agreed, tested, "each camera value steps down its loss's slope");
}

/// A lookup that carries a zero motion increment is the plain lookup: the same SDF and the same
/// gradient of the feature table, so refining the motion changes what the field learns only by
/// the corrections themselves.
#[test]
fn carrying_the_motion_leaves_the_fields_values_and_table_gradient_alone() {
    let device = Device::flex().autodiff();
    let (character, pose, field) = walking(&device);
    let (pts, _) = points(&character, &pose);
    let mut stream = Stream::new(4, 5, 0);
    let w: Vec<f32> = pts.iter().map(|_| (stream.uniform() * 2.0 - 1.0) as f32).collect();
    let weights = Tensor::<1>::from_data(TensorData::new(w, [pts.len()]), &device);
    let table = |motion: bool| {
        let (l, _) = loss(&field, &character, &pose, &pts, &weights, motion, &device);
        let value = values(l.clone().inner())[0];
        let grads = l.backward();
        let grid = field.grid.as_ref().unwrap();
        (value, values(grid.table.val().grad(&grads).expect("the table is in the graph")))
    };
    let (plain, plain_gradient) = table(false);
    let (carried, carried_gradient) = table(true);
    assert!((plain - carried).abs() <= 1e-5 * plain.abs().max(1.0), "the loss {plain} plain, {carried} carrying the motion");
    let largest = plain_gradient.iter().fold(0.0f32, |a, g| a.max(g.abs()));
    let apart = plain_gradient.iter().zip(&carried_gradient).fold(0.0f32, |a, (p, c)| a.max((p - c).abs()));
    assert!(largest > 0.0 && apart <= 1e-5 * largest, "the table's gradient {apart} apart (largest {largest})");
}

/// Points within a few centimetres of bone `joint`'s head, where it and its parent blend.
fn near_joint(pose: &Pose, joint: usize) -> Vec<DVec3> {
    let mut stream = Stream::new(9, 3, joint as u64);
    (0..48)
        .map(|_| {
            let local = DVec3::new(stream.uniform() - 0.5, stream.uniform() - 0.5, stream.uniform() - 0.5) * 0.08;
            pose.to_world(joint, local)
        })
        .collect()
}

/// Where two bones blend (about a joint), the increment's gradient still follows the field in
/// the corrected pose: each bone's content moves with its own bone, not with their blend, so a
/// turn of the bone below the joint moves only its share of a point's lookup.
#[test]
fn the_motion_increment_carries_the_gradient_where_bones_blend() {
    let device = Device::flex().autodiff();
    let (character, pose, field) = walking(&device);
    let bone = |name: &str| character.skeleton.bones.iter().position(|b| b.name == name).expect("the human has the bone");
    let mut worst = 0.0f64;
    for name in ["upper_arm_l", "forearm_r", "shin_l", "thigh_r"] {
        let j = bone(name);
        let pts = near_joint(&pose, j);
        let mut stream = Stream::new(4, 6, j as u64);
        let w: Vec<f32> = pts.iter().map(|_| (stream.uniform() * 2.0 - 1.0) as f32).collect();
        let (gradient, value) = gradient_and_loss(&field, &character, &pose, &pts, &w, &device);
        for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
            let h = 2e-4;
            let fd = (value(&moved(&character, &pose, Some(j), axis, h, DVec3::ZERO)) - value(&moved(&character, &pose, Some(j), axis, -h, DVec3::ZERO)))
                / (2.0 * h);
            let analytic = gradient[3 * j..3 * j + 3].iter().zip(axis.to_array()).map(|(g, a)| *g as f64 * a).sum::<f64>();
            let scale = fd.abs().max(analytic.abs()).max(0.02);
            worst = worst.max((fd - analytic).abs() / scale);
        }
    }
    assert!(worst < 0.03, "the increment's gradient is {worst} of the finite difference's scale off");
}

/// What every training frame's correction shares is the avatar's: every pose, a test pose's
/// and a training frame's alike, is shown turned by each bone's mean correction where the frames
/// agree on it, and by nothing of the shift; a checkpoint's copy gives the same turns.
#[test]
fn the_turns_every_training_frame_shares_are_shown_in_every_other_pose() {
    let dir = common::TempDir::new("motion-shared");
    let path = common::tiny_synth(dir.path(), umbra::synth::TrainingLight::Sun, 16, 2, vec![umbra::synth::TestKind::Poses], 3);
    let mut scene = umbra::scene::Scene::load(&path).unwrap();
    let mut motion = MotionCorrections::new(&scene).unwrap();
    let frames = motion.frames().to_vec();
    let test = (0..scene.frames.len()).find(|f| !frames.contains(f)).expect("a test frame");
    let rows = scene.skeleton.len() + 1;
    // Frame 0 turns bone 3 by 0.02 rad about x and moves the root; frame 1 turns it by 0.04
    // about x and bone 5 by -0.01 about z.
    let mut values = vec![vec![[0.0f64; 3]; rows]; 2];
    values[0][3] = [0.02, 0.0, 0.0];
    values[0][rows - 1] = [0.0, 0.05, 0.0];
    values[1][3] = [0.04, 0.0, 0.0];
    values[1][5] = [0.0, 0.0, -0.01];
    let mut state = motion.to_json();
    state["values"] = serde_json::json!(values);
    motion.restore(&state).unwrap();
    let shared = motion.shared_turns();
    assert_eq!(shared.len(), scene.skeleton.len());
    // The mean's squared standard error: the frames' squared scatter about it over their count
    // squared. Bone 3's mean, 0.03, stands sqrt(18) standard errors (each 0.01 / sqrt(2)) out:
    // it is kept but for 2 / 18 of it. Bone 5's, -0.005, sqrt(2) of them: nothing shows.
    let error = (2.0 * 0.01f64.powi(2)) / 4.0;
    let keep = 1.0 - umbra::train::motion::SHARED_TURN_EVIDENCE * error / 0.03f64.powi(2);
    assert!((keep - 8.0 / 9.0).abs() < 1e-12);
    assert!((shared[3][0] - 0.03 * keep).abs() < 1e-12 && shared[3][1] == 0.0, "bone 3 shows {:?}", shared[3]);
    assert!(shared[5] == [0.0; 3] && shared[0] == [0.0; 3], "bone 5 shows {:?}", shared[5]);
    assert_eq!(MotionCorrections::shared_turns_in(&state).unwrap(), shared);
    let given = scene.frames[test].pose.clone();
    let shown = umbra::train::motion::shown_pose(&scene.skeleton, &given, &shared);
    assert_eq!(shown, given.corrected(&scene.skeleton, &shared, [0.0; 3]));
    // Bone 3 turned in its parent's frame, the root not moved.
    let local = |p: &Pose, b: usize| DMat3::from_mat4(p.bone_to_world[scene.skeleton.bones[b].parent.unwrap()].inverse() * p.bone_to_world[b]);
    let turn = glam::DQuat::from_mat3(&(local(&given, 3).transpose() * local(&shown, 3))).to_scaled_axis();
    assert!((turn - DVec3::new(0.03 * keep, 0.0, 0.0)).length() < 1e-9, "bone 3 turned by {turn}");
    assert_eq!(shown.bone_to_world[0], given.bone_to_world[0]);
    let report = motion.moved(&scene.skeleton);
    assert!((report.shared_largest_degrees - (0.03 * keep).to_degrees()).abs() < 1e-9);
    // A scene shown so: every frame, a training frame too, turned alike.
    let before = scene.clone();
    umbra::train::motion::show_in(&mut scene, &shared);
    for f in [test, frames[0]] {
        assert_eq!(scene.frames[f].pose, before.frames[f].pose.corrected(&before.skeleton, &shared, [0.0; 3]));
    }
    // No shared turn: every pose as given, to the bit.
    let zeros = vec![[0.0; 3]; shared.len()];
    assert_eq!(umbra::train::motion::shown_pose(&scene.skeleton, &given, &zeros), given);
    // Corrections that are not finite are refused.
    state["values"][0][3][0] = serde_json::json!(null);
    assert!(MotionCorrections::shared_turns_in(&state).is_err());
}

/// A run whose checkpoint holds refined motion is shown in its shared turns by every command
/// that renders from it: `run::restore` poses the scene's frames so, and a clip's poses too.
#[test]
fn a_restored_run_shows_its_scene_and_new_motion_in_the_shared_turns() {
    let (_dir, scene_path, run) = common::short_run("motion-shown");
    let state_path = run.join(umbra::run::CHECKPOINT).join("state.json");
    let mut state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state_path).unwrap()).unwrap();
    let given = umbra::scene::Scene::load(&scene_path).unwrap();
    let motion = MotionCorrections::new(&given).unwrap();
    let rows = given.skeleton.len() + 1;
    // Every training frame turns bone 4 alike (but for a hair), so all of it is shared.
    let values: Vec<Vec<[f64; 3]>> = (0..motion.frames().len())
        .map(|k| {
            let mut frame = vec![[0.0f64; 3]; rows];
            frame[4] = [0.0, 0.05 + 1e-4 * k as f64, 0.0];
            frame
        })
        .collect();
    let mut corrections = motion.to_json();
    corrections["values"] = serde_json::json!(values);
    state["motion"] = corrections.clone();
    common::rewrite_state(&state_path, &state);
    let shared = MotionCorrections::shared_turns_in(&corrections).unwrap();
    assert!(shared[4][1] > 0.049, "bone 4's turn is shared: {:?}", shared[4]);
    let restored = umbra::run::restore(&run, None, umbra::backend::Backend::Flex).unwrap();
    for (shown, frame) in restored.scene.frames.iter().zip(&given.frames) {
        assert_eq!(shown.pose, frame.pose.corrected(&given.skeleton, &shared, [0.0; 3]));
    }
    assert_ne!(restored.scene.frames[0].pose, given.frames[0].pose);
    assert_eq!(restored.shown_motion(given.frames[1].pose.clone()), restored.scene.frames[1].pose);
    // A checkpoint without refined motion: the scene as given.
    state["motion"] = serde_json::Value::Null;
    common::rewrite_state(&state_path, &state);
    let restored = umbra::run::restore(&run, None, umbra::backend::Backend::Flex).unwrap();
    assert!(restored.scene.frames.iter().zip(&given.frames).all(|(a, b)| a.pose == b.pose) && restored.shared_turns.is_empty());
}

#[test]
fn a_motions_error_splits_into_what_every_frame_shares_and_each_frames_own() {
    let character = Character::new(Kind::Human);
    let bones = character.skeleton.len();
    let mut stream = Stream::new(21, 1, 0);
    let mut angle = || (stream.uniform() - 0.5) * 0.08;
    // Each bone's shared error and each of 7 frames' own, the own ones summing to zero.
    let shared: Vec<DVec3> = (0..bones).map(|_| DVec3::new(angle(), angle(), angle())).collect();
    let mut own: Vec<Vec<DVec3>> = (0..7).map(|_| (0..bones).map(|_| DVec3::new(angle(), angle(), angle())).collect()).collect();
    for b in 0..bones {
        let mean = own.iter().map(|o| o[b]).sum::<DVec3>() / own.len() as f64;
        own.iter_mut().for_each(|o| o[b] -= mean);
    }
    let truths: Vec<Pose> = (0..own.len()).map(|k| character.pose(0.1 * k as f64, 0.2, DVec3::new(0.02 * k as f64, 0.0, 0.0))).collect();
    let errs: Vec<Pose> = truths
        .iter()
        .zip(&own)
        .map(|(truth, own)| {
            let turns: Vec<[f64; 3]> = (0..bones).map(|b| (shared[b] + own[b]).to_array()).collect();
            truth.corrected(&character.skeleton, &turns, [0.0; 3])
        })
        .collect();
    let pairs: Vec<(&Pose, &Pose)> = truths.iter().zip(&errs).collect();
    let (mean, rest) = umbra::train::motion::turns_between(&character.skeleton, &pairs);
    // A mean of rotation vectors is the mean rotation to second order: within 1e-3 radians of
    // 0.04-radian turns.
    for b in 0..bones {
        assert!((mean[b] - shared[b]).length() < 1e-3, "bone {b}: shared {:?}, found {:?}", shared[b], mean[b]);
        for k in 0..own.len() {
            assert!((rest[k][b] - own[k][b]).length() < 1e-3, "bone {b}, frame {k}: own {:?}, found {:?}", own[k][b], rest[k][b]);
        }
    }
    // A pose against itself has no error at all.
    let same: Vec<(&Pose, &Pose)> = truths.iter().map(|t| (t, t)).collect();
    let (mean, rest) = umbra::train::motion::turns_between(&character.skeleton, &same);
    assert!(mean.iter().chain(rest.iter().flatten()).all(|t| t.length() < 1e-9));
}
