//! A clip (BVH or per-frame joint JSON) driving a fitted skeleton: its joints matched to the
//! bones by name, and each clip frame turned into a pose of the fitted bones.
//!
//! Two cases, told apart by the clip itself:
//! - **Direct**: every bone's joint is the child of its parent bone's joint and sits at the
//!   bone's own head in that joint's frame (within `DIRECT_TOLERANCE`), as in a clip written
//!   from a scene's frames (`bvh::write`: each joint's frame the bone's). Each joint's frame is
//!   then the bone's frame, scaled to metres, and the scene's poses come back exactly.
//! - **Retargeted** (a clip from elsewhere): each bone turns as its joint's bone does under
//!   `umbra import`'s bone rule (`bones`: +Y along the joint's bone, the twist of the joint's
//!   frame), the fixed rest alignment, so a clip in the convention of the capture the avatar
//!   was fitted on drives it as that capture did. The clip's rotations act on the fitted
//!   lengths: each bone's head lies from its parent's in the direction the clip's joints lie,
//!   at the fitted distance (the reference pose's), and the root moves from the reference
//!   pose's place by the clip's root displacement times the ratio of the bodies' sizes (the
//!   summed distances from each bone's head to its parent's, fitted over the clip's).

use super::bones;
use super::bvh::Motion;
use crate::skeleton::{Pose, Skeleton};
use glam::{DMat4, DVec3};

/// How far (m) a clip joint may sit from its bone's head for the clip to drive the bones
/// directly: far above a BVH's 9 printed decimals, far below any body's joint.
pub const DIRECT_TOLERANCE: f64 = 1e-5;

/// A clip's frames as poses of a fitted skeleton.
pub struct Driven {
    pub poses: Vec<Pose>,
    /// Seconds between the clip's frames.
    pub frame_time: f64,
    /// Whether the clip drove the bones' frames directly (else it was retargeted).
    pub direct: bool,
    /// The clip's joints no bone is named after (ignored).
    pub unmatched: Vec<String>,
    /// The fitted body's size over the clip's (1 when direct).
    pub scale: f64,
}

/// A joint name without a namespace (`mixamorig:Hips`, `Armature|Hips`: `hips`), lower case.
fn plain(name: &str) -> String {
    name.rsplit([':', '|']).next().unwrap_or(name).to_lowercase()
}

/// Each bone's joint: the joint of its exact name, else the one of the same plain name.
fn match_joints(skeleton: &Skeleton, motion: &Motion) -> Result<Vec<usize>, String> {
    let mut missing = Vec::new();
    let mut joint_of = Vec::with_capacity(skeleton.len());
    for bone in &skeleton.bones {
        let exact = motion.joints.iter().position(|j| j.name == bone.name);
        match exact.or_else(|| motion.joints.iter().position(|j| plain(&j.name) == plain(&bone.name))) {
            Some(j) => joint_of.push(j),
            None => missing.push(bone.name.clone()),
        }
    }
    if !missing.is_empty() {
        let names: Vec<&str> = motion.joints.iter().map(|j| j.name.as_str()).collect();
        return Err(format!("no joint of the clip for the fitted bones {missing:?} (the clip's joints: {names:?})"));
    }
    Ok(joint_of)
}

/// Bone `b`'s head in its parent's frame in `pose` (zero for a root).
fn offset_in_parent(skeleton: &Skeleton, pose: &Pose, b: usize) -> DVec3 {
    match skeleton.bones[b].parent {
        Some(p) => pose.bone_to_world[p].inverse().transform_point3(pose.bone_to_world[b].w_axis.truncate()),
        None => DVec3::ZERO,
    }
}

/// Whether every bone's joint hangs from its parent bone's joint at the bone's own offset.
fn drives_directly(skeleton: &Skeleton, reference: &Pose, motion: &Motion, joint_of: &[usize], metres: f64) -> bool {
    skeleton.bones.iter().enumerate().all(|(b, bone)| {
        let joint = &motion.joints[joint_of[b]];
        match bone.parent {
            None => joint.parent.is_none(),
            Some(p) => joint.parent == Some(joint_of[p]) && (joint.offset * metres).distance(offset_in_parent(skeleton, reference, b)) < DIRECT_TOLERANCE,
        }
    })
}

/// A joint frame in file units as a frame in metres.
fn in_metres(m: DMat4, metres: f64) -> DMat4 {
    let mut out = m;
    out.w_axis = (m.w_axis.truncate() * metres).extend(1.0);
    out
}

/// `driven` when every pose it gives is finite: renders and glTF hold no NaN or infinity.
fn finite(driven: Driven) -> Result<Driven, String> {
    match driven.poses.iter().position(|p| p.bone_to_world.iter().any(|m| !m.is_finite())) {
        Some(k) => Err(format!("frame {k}: the clip poses a bone nowhere (a non-finite transform)")),
        None => Ok(driven),
    }
}

/// `motion`'s frames as poses of `skeleton`, whose `reference` pose (the scene's first frame)
/// gives the fitted offsets and the body's place; `metres` per file unit.
pub fn drive(skeleton: &Skeleton, reference: &Pose, motion: &Motion, metres: f64) -> Result<Driven, String> {
    if motion.frames.is_empty() {
        return Err("the clip has no frames".into());
    }
    let joint_of = match_joints(skeleton, motion)?;
    let unmatched = motion.joints.iter().enumerate().filter(|(j, _)| !joint_of.contains(j)).map(|(_, joint)| joint.name.clone()).collect();
    let frames = 0..motion.frames.len();
    if drives_directly(skeleton, reference, motion, &joint_of, metres) {
        let poses = frames
            .map(|k| {
                let joints = motion.joint_to_world(k);
                Pose { bone_to_world: joint_of.iter().map(|&j| in_metres(joints[j], metres)).collect() }
            })
            .collect();
        return finite(Driven { poses, frame_time: motion.frame_time, direct: true, unmatched, scale: 1.0 });
    }
    let rig = bones::rig(motion)?;
    let lengths: Vec<f64> = (0..skeleton.len()).map(|b| offset_in_parent(skeleton, reference, b).length()).collect();
    // Each body's size: the summed distances from each bone's head to its parent's (pose-free
    // in both, and measured alike).
    let fitted: f64 = lengths.iter().sum();
    let clip: f64 = (0..skeleton.len()).filter(|&b| skeleton.bones[b].parent.is_some()).map(|b| motion.joints[joint_of[b]].offset.length() * metres).sum();
    let scale = fitted / clip;
    if !(scale.is_finite() && scale > 0.0) {
        return Err(format!(
            "the clip's joints that carry the fitted bones have no length between them (their offsets sum to {clip:e} m): nothing to scale the travel by"
        ));
    }
    let start = motion.joint_to_world(0);
    let poses = frames
        .map(|k| {
            let joints = motion.joint_to_world(k);
            let mut bone_to_world: Vec<DMat4> = Vec::with_capacity(skeleton.len());
            for (b, bone) in skeleton.bones.iter().enumerate() {
                let j = joint_of[b];
                let head = match bone.parent {
                    // Where the clip puts the joint seen from its parent bone's joint, at the
                    // fitted distance.
                    Some(p) => {
                        let from = bone_to_world[p].w_axis.truncate();
                        let toward = (joints[j].w_axis - joints[joint_of[p]].w_axis).truncate().normalize_or_zero();
                        from + toward * lengths[b]
                    }
                    None => {
                        let moved = (joints[j].w_axis - start[j].w_axis).truncate() * metres * scale;
                        reference.bone_to_world[b].w_axis.truncate() + moved
                    }
                };
                let mut frame = DMat4::from_mat3(glam::DMat3::from_mat4(joints[j] * rig.alignments[j]));
                frame.w_axis = head.extend(1.0);
                bone_to_world.push(frame);
            }
            Pose { bone_to_world }
        })
        .collect();
    finite(Driven { poses, frame_time: motion.frame_time, direct: false, unmatched, scale })
}
