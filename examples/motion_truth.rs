//! How far a fit's refined training motion and cameras, and the ones it was given, lie from the
//! true ones (`cargo run --release --example motion_truth -- SCENE TRUE_SCENE RUN`): SCENE is the scene
//! the fit ran on (a capture imported with a tracker's errors: `umbra synth --export nerfstudio
//! --errors joints=2.5,root=1`), TRUE_SCENE the same capture imported without errors (the same
//! seed), RUN the fit's run folder (its checkpoint's corrections). Prints each bone's rotation
//! error (degrees, mean over bones and training frames) and the root's (cm), given and refined;
//! and, when the fit refined the cameras (`--errors camera_turn=..,camera_move=..`), each training
//! camera's turn (degrees) and centre (mm) from the true camera's, given and refined. The
//! joints' error is also split into what every training frame shares (each bone's mean error
//! over them) and each frame's own.

use std::path::Path;
use umbra::scene::Scene;
use umbra::train::camera_pose::CameraPoses;
use umbra::train::motion::{joint_error, turns_between, MotionCorrections};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(given), Some(truth), Some(run)) = (args.get(1), args.get(2), args.get(3)) else {
        return Err("usage: motion_truth SCENE TRUE_SCENE RUN".into());
    };
    let given = Scene::load(Path::new(given))?;
    let truth = Scene::load(Path::new(truth))?;
    let state_path = Path::new(run).join(umbra::run::CHECKPOINT).join("state.json");
    let state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state_path)?)?;
    let mut motion = MotionCorrections::new(&given).ok_or("the scene has no training frames")?;
    motion.restore(&state["motion"]).map_err(|e| format!("{}: motion: {e}", state_path.display()))?;
    let (mut before, mut after) = ((0.0, 0.0), (0.0, 0.0));
    let refined = motion.refined(&given);
    for (f, pose) in &refined {
        let exact = &truth.frames.get(*f).ok_or("the true scene has fewer frames")?.pose;
        let b = joint_error(&given.skeleton, &given.frames[*f].pose, exact);
        let a = joint_error(&given.skeleton, pose, exact);
        before = (before.0 + b.0, before.1 + b.1);
        after = (after.0 + a.0, after.1 + a.1);
    }
    let n = refined.len().max(1) as f64;
    // Each bone's error alone (degrees, mean over frames), given -> refined.
    for (b, bone) in given.skeleton.bones.iter().enumerate() {
        let one = |pose: &umbra::skeleton::Pose, exact: &umbra::skeleton::Pose| {
            let local = |p: &umbra::skeleton::Pose| match bone.parent {
                Some(q) => p.bone_to_world[q].inverse() * p.bone_to_world[b],
                None => p.bone_to_world[b],
            };
            let (a, e) = (glam::DMat3::from_mat4(local(pose)), glam::DMat3::from_mat4(local(exact)));
            glam::DQuat::from_mat3(&(a.transpose() * e)).normalize().to_scaled_axis().length().to_degrees()
        };
        let (mut g, mut r) = (0.0, 0.0);
        for (f, pose) in &refined {
            let exact = &truth.frames[*f].pose;
            g += one(&given.frames[*f].pose, exact);
            r += one(pose, exact);
        }
        println!("  {:<14} {:6.2} -> {:6.2}", bone.name, g / n, r / n);
    }
    println!("training frames: {}", refined.len());
    println!("given:   joints {:.3} degrees, root {:.3} cm", before.0 / n, before.1 / n);
    println!("refined: joints {:.3} degrees, root {:.3} cm", after.0 / n, after.1 / n);
    // The same error split into each bone's direction (swing) and its turn about its own
    // length (twist, which a limb's outline hardly shows).
    let split = |pose: &dyn Fn(usize) -> umbra::skeleton::Pose| {
        let (mut swing, mut twist) = (0.0, 0.0);
        for (f, _) in &refined {
            let (p, e) = (pose(*f), &truth.frames[*f].pose);
            for b in 0..given.skeleton.len() {
                let (a, t) = (glam::DMat3::from_mat4(p.bone_to_world[b]), glam::DMat3::from_mat4(e.bone_to_world[b]));
                swing += (a.y_axis.dot(t.y_axis)).clamp(-1.0, 1.0).acos().to_degrees();
                let q = glam::DQuat::from_mat3(&(a.transpose() * t)).normalize();
                twist += (2.0 * q.y.atan2(q.w)).abs().to_degrees().min(360.0 - (2.0 * q.y.atan2(q.w)).abs().to_degrees());
            }
        }
        let count = (refined.len() * given.skeleton.len()).max(1) as f64;
        (swing / count, twist / count)
    };
    let (gs, gt) = split(&|f| given.frames[f].pose.clone());
    let (rs, rt) = split(&|f| refined.iter().find(|(g, _)| *g == f).map(|(_, p)| p.clone()).unwrap_or_else(|| given.frames[f].pose.clone()));
    println!("bone directions in the world (swing): given {gs:.3}, refined {rs:.3} degrees; turns about the bones (twist): given {gt:.3}, refined {rt:.3}");
    // The error shared by every training frame (each bone's mean over them, which the avatar's
    // content takes up as well as the motion) and each frame's own.
    let shared_and_own = |poses: Vec<&umbra::skeleton::Pose>| {
        let pairs: Vec<_> = poses.into_iter().zip(&refined).map(|(p, (f, _))| (p, &truth.frames[*f].pose)).collect();
        let (mean, own) = turns_between(&given.skeleton, &pairs);
        let bones = mean.len().max(1) as f64;
        let shared = mean.iter().map(|m| m.length().to_degrees()).sum::<f64>() / bones;
        let frames: f64 = own.iter().flatten().map(|t| t.length_squared()).sum::<f64>() / (own.len().max(1) as f64 * bones);
        (shared, frames.sqrt().to_degrees())
    };
    let (gs, gf) = shared_and_own(refined.iter().map(|(f, _)| &given.frames[*f].pose).collect());
    let (rs, rf) = shared_and_own(refined.iter().map(|(_, p)| p).collect());
    println!("shared by the training frames (each bone's mean error, mean over bones): given {gs:.3}, refined {rs:.3} degrees; each frame's own (rms): given {gf:.3}, refined {rf:.3}");
    cameras(&given, &truth, &state)
}

/// Each training camera's pose against the true scene's, given and refined (when refined): its
/// turn from the true camera's (degrees), and how far it sees the true bones' heads of its
/// training frames from where the true camera sees them (pixels), the error a fit feels (a
/// few millimetres of a centre look like a hundredth of a degree of a turn from metres away).
fn cameras(given: &Scene, truth: &Scene, state: &serde_json::Value) -> Result<(), Box<dyn std::error::Error>> {
    let Some(mut poses) = CameraPoses::new(given) else { return Ok(()) };
    if state["cameras"].is_null() {
        return Ok(());
    }
    poses.restore(&state["cameras"]).map_err(|e| format!("cameras: {e}"))?;
    let turn = |a: &umbra::scene::Camera, b: &umbra::scene::Camera| {
        let (ra, rb) = (glam::DMat3::from_mat4(a.camera_to_world), glam::DMat3::from_mat4(b.camera_to_world));
        glam::DQuat::from_mat3(&(ra.transpose() * rb)).normalize().to_scaled_axis().length().to_degrees()
    };
    // Pixels between where `camera` and `exact` see the true heads of `camera`'s training frames.
    let pixels = |c: usize, camera: &umbra::scene::Camera, exact: &umbra::scene::Camera| {
        let (mut sum, mut n) = (0.0, 0.0);
        for view in given.views.iter().filter(|v| v.camera == c && v.split == umbra::scene::Split::Train) {
            for m in &truth.frames[view.frame].pose.bone_to_world {
                if let (Some(a), Some(b)) = (camera.project(m.w_axis.truncate()), exact.project(m.w_axis.truncate())) {
                    sum += (a - b).length();
                    n += 1.0;
                }
            }
        }
        sum / f64::max(n, 1.0)
    };
    // Each training image's true camera: the true scene's image of the same name.
    let stem = |v: &umbra::scene::View| v.path.file_stem().map(|s| s.to_owned());
    let (mut before, mut after, mut n) = ((0.0, 0.0), (0.0, 0.0), 0.0);
    for (c, camera) in given.cameras.iter().enumerate().filter(|(c, _)| poses.row(*c).is_some()) {
        let view = given.views.iter().find(|v| v.camera == c && v.split == umbra::scene::Split::Train).ok_or("a refined camera without a training image")?;
        let exact = truth.views.iter().find(|t| stem(t) == stem(view)).map(|t| &truth.cameras[t.camera]).ok_or("the true scene lacks a training image")?;
        let refined = poses.corrected_camera(c, camera);
        let (b, a) = ((turn(camera, exact), pixels(c, camera, exact)), (turn(&refined, exact), pixels(c, &refined, exact)));
        println!("  {:<14} turn {:.3} -> {:.3} degrees, the bones seen {:.3} -> {:.3} px off", camera.name, b.0, a.0, b.1, a.1);
        before = (before.0 + b.0, before.1 + b.1);
        after = (after.0 + a.0, after.1 + a.1);
        n += 1.0;
    }
    println!("cameras given:   turn {:.3} degrees, the bones seen {:.3} px off (mean over {n} cameras)", before.0 / n, before.1 / n);
    println!("cameras refined: turn {:.3} degrees, the bones seen {:.3} px off", after.0 / n, after.1 / n);
    Ok(())
}
