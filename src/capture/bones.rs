//! The bones a clip's joints make. umbra's bone starts at its joint and runs along its local +Y
//! for its length; a clip's joint only has a frame and children. The rule, one for every clip:
//!
//! - a joint's bone points at its **bone child**: its only child; at a branch, for the root the
//!   child with the most joints below it (the spine, over the legs; ties to the first listed),
//!   for any other joint the child whose offset turns least from the joint's own offset from
//!   its parent (the neck, over the shoulders, continuing the spine); a leaf's at its End Site;
//! - its length is that child's (or End Site's) distance, its frame the joint's turned by the
//!   shortest rotation taking +Y onto that offset: fixed in the joint's frame, so the bone
//!   moves rigidly with the joint.
//!
//! A leaf without an End Site (the format requires one) is refused.

use super::bvh::{Joint, Motion};
use glam::{DMat4, DQuat, DVec3};

/// The least bone length (file units scaled to metres elsewhere): a child at its parent's own
/// place gives no direction, and scene/1 needs a length > 0.
const LEAST_LENGTH: f64 = 1e-6;

/// Per joint: its bone's length (file units) and the fixed turn from the joint's frame to the
/// bone's.
pub struct Rig {
    pub lengths: Vec<f64>,
    pub alignments: Vec<DMat4>,
}

fn children(joints: &[Joint], j: usize) -> Vec<usize> {
    (0..joints.len()).filter(|&c| joints[c].parent == Some(j)).collect()
}

fn below(joints: &[Joint], j: usize) -> usize {
    children(joints, j).iter().map(|&c| 1 + below(joints, c)).sum()
}

/// Joint `j`'s bone child (`None` for a leaf).
pub fn bone_child(joints: &[Joint], j: usize) -> Option<usize> {
    let children = children(joints, j);
    match (children.len(), joints[j].parent) {
        (0, _) => None,
        (1, _) => Some(children[0]),
        (_, None) => children.iter().copied().max_by_key(|&c| (below(joints, c), std::cmp::Reverse(c))),
        (_, Some(_)) => {
            let incoming = joints[j].offset.normalize_or(DVec3::Y);
            let turn = |c: usize| -joints[c].offset.normalize_or_zero().dot(incoming);
            children.iter().copied().min_by(|&a, &b| turn(a).total_cmp(&turn(b)).then(a.cmp(&b)))
        }
    }
}

/// The bones of `motion`'s joints by the rule above.
pub fn rig(motion: &Motion) -> Result<Rig, String> {
    let joints = &motion.joints;
    let mut lengths = Vec::with_capacity(joints.len());
    let mut alignments = Vec::with_capacity(joints.len());
    for (j, joint) in joints.iter().enumerate() {
        let towards = match bone_child(joints, j) {
            Some(c) => joints[c].offset,
            None => joint.end_site.ok_or_else(|| format!("joint {:?} has no children and no End Site: its bone has no length", joint.name))?,
        };
        let length = towards.length();
        let direction = if length > LEAST_LENGTH { towards / length } else { DVec3::Y };
        lengths.push(length.max(LEAST_LENGTH));
        alignments.push(DMat4::from_quat(DQuat::from_rotation_arc(DVec3::Y, direction)));
    }
    Ok(Rig { lengths, alignments })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn joint(name: &str, parent: Option<usize>, offset: [f64; 3]) -> Joint {
        Joint { name: name.into(), parent, offset: DVec3::from_array(offset), channels: Vec::new(), end_site: Some(DVec3::new(0.0, 5.0, 0.0)) }
    }

    #[test]
    fn branches_follow_the_spine_and_the_neck() {
        let joints = vec![
            joint("hips", None, [0.0, 90.0, 0.0]),
            joint("leg_l", Some(0), [10.0, -5.0, 0.0]),
            joint("spine", Some(0), [0.0, 10.0, 0.0]),
            joint("chest", Some(2), [0.0, 20.0, 0.0]),
            joint("arm_l", Some(3), [15.0, 15.0, 0.0]),
            joint("neck", Some(3), [0.0, 20.0, 0.0]),
            joint("head", Some(5), [0.0, 8.0, 0.0]),
            joint("shin_l", Some(1), [0.0, -40.0, 0.0]),
        ];
        // hips: the spine holds 4 joints below it, the leg 1.
        assert_eq!(bone_child(&joints, 0), Some(2));
        // chest: the neck continues the spine; the arm (the longer offset) turns 45 degrees.
        assert_eq!(bone_child(&joints, 3), Some(5));
        assert_eq!(bone_child(&joints, 6), None);
        let rig = rig(&Motion { joints: joints.clone(), frame_time: 1.0, frames: vec![vec![]] }).unwrap();
        // The leg's bone points down its shin: +Y turned onto -Y.
        assert!((rig.alignments[1].transform_vector3(DVec3::Y) - DVec3::NEG_Y).length() < 1e-12);
        assert_eq!(rig.lengths[1], 40.0);
        assert_eq!(rig.lengths[6], 5.0);
    }
}
