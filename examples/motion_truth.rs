//! How far a fit's refined training motion, and the motion it was given, lie from the true one
//! (`cargo run --release --example motion_truth -- SCENE TRUE_SCENE RUN`): SCENE is the scene
//! the fit ran on (a capture imported with a tracker's errors: `umbra synth --export nerfstudio
//! --errors joints=2.5,root=1`), TRUE_SCENE the same capture imported without errors (the same
//! seed), RUN the fit's run folder (its checkpoint's corrections). Prints each bone's rotation
//! error (degrees, mean over bones and training frames) and the root's (cm), given and refined.

use std::path::Path;
use umbra::scene::Scene;
use umbra::train::motion::{joint_error, MotionCorrections};

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
    Ok(())
}
