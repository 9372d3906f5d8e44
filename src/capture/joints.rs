//! Per-frame joint transforms as JSON: what an SMPL-family tracker gives after forward kinematics
//! (or any tracker that knows where each joint is and how it is turned), without the body model:
//!
//! ```json
//! { "frame_time": 0.0333,
//!   "joints": [ { "name": "pelvis", "parent": null }, { "name": "left_hip", "parent": 0 }, ... ],
//!   "tips": { "head": [0, 0.2, 0] },
//!   "frames": [ { "rotations": [ [[1,0,0],[0,1,0],[0,0,1]], ... ], "positions": [ [0, 0.9, 0], ... ] } ] }
//! ```
//!
//! `rotations` are each joint's world rotation (row-major 3x3), `positions` its world position,
//! one per joint in `joints`' order; a parent comes before its children. A leaf's bone ends at its
//! `tips` entry (in its own frame, like a BVH End Site), else continues its parent's direction
//! for half its parent's length. It becomes a clip (`bvh::Motion`) whose joints carry their
//! positions, so the same bone rule and the same forward kinematics apply.

use super::bvh::{Channel, Joint, Motion};
use crate::scene::json::At;
use crate::scene::SceneError;
use glam::{DMat3, DMat4, DVec3};
use std::path::Path;

/// Reads the joint JSON at `file` as a clip.
pub fn read(file: &Path) -> Result<Motion, SceneError> {
    let value = crate::scene::json::parse(&crate::scene::read_capped(file)?, file)?;
    let root = At::root(&value, file);
    let frame_time = root.field("frame_time")?.positive_f64()?;
    let joint_nodes = root.field("joints")?.non_empty_array()?;
    let mut names: Vec<String> = Vec::new();
    let mut parents = Vec::new();
    for (k, node) in joint_nodes.iter().enumerate() {
        let name = node.field("name")?.str()?.to_string();
        if names.contains(&name) {
            return Err(node.field("name")?.error(format!("a second joint named {name:?}")));
        }
        // null for a root; a missing key is a mistake, not a second root.
        let parent = match node.value.get("parent") {
            None => return Err(node.error("parent: missing (null for a root)")),
            Some(serde_json::Value::Null) => None,
            Some(_) => Some(node.field("parent")?.index(k, "earlier joints")?),
        };
        names.push(name);
        parents.push(parent);
    }
    let mut worlds: Vec<Vec<DMat4>> = Vec::new();
    for frame in root.field("frames")?.non_empty_array()? {
        let rotations = frame.field("rotations")?.array()?;
        let positions = frame.field("positions")?.array()?;
        if rotations.len() != names.len() || positions.len() != names.len() {
            return Err(frame.error(format!("{} rotations and {} positions for {} joints", rotations.len(), positions.len(), names.len())));
        }
        let mut world = Vec::with_capacity(names.len());
        for (r, p) in rotations.iter().zip(&positions) {
            let m = r.rotation()?;
            world.push(DMat4::from_mat3_translation(m, p.vec3()?));
        }
        worlds.push(world);
    }
    let tips = root.opt_field("tips")?;
    let first = &worlds[0];
    let local = |k: usize, world: &[DMat4]| match parents[k] {
        Some(p) => world[p].inverse() * world[k],
        None => world[k],
    };
    let mut joints = Vec::with_capacity(names.len());
    for k in 0..names.len() {
        let offset = local(k, first).w_axis.truncate();
        let has_children = parents.contains(&Some(k));
        let end_site = match tips.as_ref().map(|t| t.opt_field(&names[k])).transpose()?.flatten() {
            Some(tip) => Some(tip.vec3()?),
            None if has_children => None,
            // Onward from its parent, for half the parent's reach to it, in its own frame.
            None => Some(
                DMat3::from_mat4(first[k]).transpose()
                    * (first[k].w_axis.truncate() - parents[k].map(|p| first[p].w_axis.truncate()).unwrap_or(first[k].w_axis.truncate() - DVec3::Y))
                    * 0.5,
            ),
        };
        let channels = vec![Channel::Xposition, Channel::Yposition, Channel::Zposition, Channel::Zrotation, Channel::Xrotation, Channel::Yrotation];
        joints.push(Joint { name: names[k].clone(), parent: parents[k], offset, channels, end_site });
    }
    let frames = worlds
        .iter()
        .map(|world| {
            (0..names.len())
                .flat_map(|k| {
                    let m = local(k, world);
                    let t = m.w_axis.truncate();
                    let [a, b, c] = super::bvh::zxy_degrees(DMat3::from_mat4(m));
                    [t.x, t.y, t.z, a, b, c]
                })
                .collect()
        })
        .collect();
    Ok(Motion { joints, frame_time, frames })
}
