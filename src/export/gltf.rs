//! A fitted avatar as a skinned, animated glTF 2.0 binary (`umbra export-avatar`): the surface
//! meshed in the scene's first frame (the bind pose), one joint node per bone (the bones'
//! hierarchy, each node's transform its bone's frame in its parent's), inverse bind matrices
//! from the bind pose, per vertex the four largest of the field's own skinning weights
//! (`AvatarField::skinning_weights`, renormalised), vertex colours from the fitted albedo, and
//! one animation of every joint's translation and rotation per frame of a motion.

use crate::isosurface::Mesh;
use crate::skeleton::{Pose, Skeleton};
use glam::DVec3;
use serde_json::{json, Value};

/// The surface in the bind pose and what skins it.
pub struct SkinnedMesh {
    pub mesh: Mesh,
    pub normals: Vec<DVec3>,
    /// Linear reflectance per vertex.
    pub colours: Vec<DVec3>,
    /// Per vertex the four (bone, weight) pairs, weights summing to 1.
    pub weights: Vec<[(usize, f32); 4]>,
}

/// The four largest weights of `weights`, renormalised (slots without weight: joint 0).
pub fn four_largest(mut weights: Vec<(usize, f32)>) -> [(usize, f32); 4] {
    weights.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let mut out = [(0usize, 0.0f32); 4];
    for (slot, w) in out.iter_mut().zip(weights) {
        *slot = w;
    }
    let sum: f32 = out.iter().map(|w| w.1).sum();
    if sum > 0.0 {
        out.iter_mut().for_each(|w| w.1 /= sum);
    } else {
        out[0].1 = 1.0;
    }
    // A slot without weight names joint 0 (what viewers expect of an unused influence).
    out.iter_mut().filter(|w| w.1 == 0.0).for_each(|w| w.0 = 0);
    out
}

/// The binary buffer as it is filled, and the JSON arrays that describe it.
struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Builder {
    /// Appends `bytes` as a buffer view (4-byte aligned) and an accessor over it; returns the
    /// accessor's index.
    fn accessor(&mut self, bytes: &[u8], target: Option<u32>, mut accessor: Value) -> usize {
        while self.bin.len() % 4 != 0 {
            self.bin.push(0);
        }
        let mut view = json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len()});
        if let Some(target) = target {
            view["target"] = json!(target);
        }
        self.bin.extend_from_slice(bytes);
        accessor["bufferView"] = json!(self.views.len());
        self.views.push(view);
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    fn floats(&mut self, values: &[f32], kind: &str, count: usize, target: Option<u32>, bounds: bool) -> usize {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let mut accessor = json!({"componentType": FLOAT, "count": count, "type": kind});
        if bounds {
            let width = values.len() / count.max(1);
            let column = |c: usize| values.iter().skip(c).step_by(width.max(1));
            accessor["min"] = json!((0..width).map(|c| column(c).copied().fold(f32::INFINITY, f32::min)).collect::<Vec<_>>());
            accessor["max"] = json!((0..width).map(|c| column(c).copied().fold(f32::NEG_INFINITY, f32::max)).collect::<Vec<_>>());
        }
        self.accessor(&bytes, target, accessor)
    }
}

/// The generator every GLB `export-avatar` writes names: what lets a later export replace it.
pub const GENERATOR: &str = "umbra export-avatar";

const FLOAT: u32 = 5126;
const UNSIGNED_SHORT: u32 = 5123;
const UNSIGNED_INT: u32 = 5125;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;

/// A bone's frame in its parent's (a root's in the world) as translation and rotation.
fn local_trs(skeleton: &Skeleton, pose: &Pose, b: usize) -> ([f32; 3], [f32; 4]) {
    let local = match skeleton.bones[b].parent {
        Some(p) => pose.bone_to_world[p].inverse() * pose.bone_to_world[b],
        None => pose.bone_to_world[b],
    };
    let (_, rotation, translation) = local.to_scale_rotation_translation();
    let q = rotation.normalize();
    (translation.as_vec3().to_array(), [q.x as f32, q.y as f32, q.z as f32, q.w as f32])
}

fn flat3(v: &[DVec3]) -> Vec<f32> {
    v.iter().flat_map(|p| p.as_vec3().to_array()).collect()
}

/// The glTF JSON and binary buffer of `skinned` bound in `bind`, animated by `motion` (poses
/// and their times in seconds).
fn document(skeleton: &Skeleton, skinned: &SkinnedMesh, bind: &Pose, motion: &[(f64, Pose)], name: &str) -> (Value, Vec<u8>) {
    let mut b = Builder { bin: Vec::new(), views: Vec::new(), accessors: Vec::new() };
    let n = skinned.mesh.vertices.len();
    let position = b.floats(&flat3(&skinned.mesh.vertices), "VEC3", n, Some(ARRAY_BUFFER), true);
    let unit: Vec<DVec3> = skinned.normals.iter().map(|v| v.try_normalize().unwrap_or(DVec3::Y)).collect();
    let normal = b.floats(&flat3(&unit), "VEC3", n, Some(ARRAY_BUFFER), false);
    let colours: Vec<DVec3> = skinned.colours.iter().map(|c| c.clamp(DVec3::ZERO, DVec3::ONE)).collect();
    let colour = b.floats(&flat3(&colours), "VEC3", n, Some(ARRAY_BUFFER), false);
    let joints: Vec<u8> = skinned.weights.iter().flat_map(|w| w.iter().flat_map(|&(j, _)| (j as u16).to_le_bytes())).collect();
    let joints = b.accessor(&joints, Some(ARRAY_BUFFER), json!({"componentType": UNSIGNED_SHORT, "count": n, "type": "VEC4"}));
    let weights: Vec<f32> = skinned.weights.iter().flat_map(|w| w.map(|(_, w)| w)).collect();
    let weights = b.floats(&weights, "VEC4", n, Some(ARRAY_BUFFER), false);
    let indices: Vec<u8> = skinned.mesh.triangles.iter().flat_map(|t| t.iter().flat_map(|&i| (i as u32).to_le_bytes())).collect();
    let indices =
        b.accessor(&indices, Some(ELEMENT_ARRAY_BUFFER), json!({"componentType": UNSIGNED_INT, "count": skinned.mesh.triangles.len() * 3, "type": "SCALAR"}));
    let inverse_binds: Vec<f32> = bind.bone_to_world.iter().flat_map(|m| m.inverse().as_mat4().to_cols_array()).collect();
    let inverse_binds = b.floats(&inverse_binds, "MAT4", skeleton.len(), None, false);
    // Nodes: one per bone (node b is bone b), then the mesh's.
    let mut nodes: Vec<Value> = (0..skeleton.len())
        .map(|bone| {
            let (t, r) = local_trs(skeleton, bind, bone);
            let children: Vec<usize> = (0..skeleton.len()).filter(|&c| skeleton.bones[c].parent == Some(bone)).collect();
            let mut node = json!({"name": skeleton.bones[bone].name, "translation": t, "rotation": r});
            if !children.is_empty() {
                node["children"] = json!(children);
            }
            node
        })
        .collect();
    nodes.push(json!({"name": name, "mesh": 0, "skin": 0}));
    let roots: Vec<usize> = (0..skeleton.len()).filter(|&c| skeleton.bones[c].parent.is_none()).collect();
    let mut scene_nodes = roots.clone();
    scene_nodes.push(skeleton.len());
    let times: Vec<f32> = motion.iter().map(|(t, _)| *t as f32).collect();
    let input = b.floats(&times, "SCALAR", times.len(), None, true);
    let mut samplers = Vec::new();
    let mut channels = Vec::new();
    for bone in 0..skeleton.len() {
        let trs: Vec<([f32; 3], [f32; 4])> = motion.iter().map(|(_, pose)| local_trs(skeleton, pose, bone)).collect();
        let translations: Vec<f32> = trs.iter().flat_map(|(t, _)| *t).collect();
        let rotations: Vec<f32> = trs.iter().flat_map(|(_, r)| *r).collect();
        for (path, output) in
            [("translation", b.floats(&translations, "VEC3", trs.len(), None, false)), ("rotation", b.floats(&rotations, "VEC4", trs.len(), None, false))]
        {
            channels.push(json!({"sampler": samplers.len(), "target": {"node": bone, "path": path}}));
            samplers.push(json!({"input": input, "output": output, "interpolation": "LINEAR"}));
        }
    }
    let document = json!({
        "asset": {"version": "2.0", "generator": GENERATOR},
        "scene": 0,
        "scenes": [{"name": name, "nodes": scene_nodes}],
        "nodes": nodes,
        "meshes": [{"name": name, "primitives": [{
            "attributes": {"POSITION": position, "NORMAL": normal, "COLOR_0": colour, "JOINTS_0": joints, "WEIGHTS_0": weights},
            "indices": indices,
            "material": 0,
        }]}],
        "materials": [{"name": "albedo", "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "skins": [{"name": "bones", "joints": (0..skeleton.len()).collect::<Vec<_>>(), "inverseBindMatrices": inverse_binds, "skeleton": roots[0]}],
        "animations": [{"name": "motion", "samplers": samplers, "channels": channels}],
        "buffers": [{"byteLength": b.bin.len()}],
        "bufferViews": b.views,
        "accessors": b.accessors,
    });
    (document, b.bin)
}

/// The GLB container: a 12-byte header, the JSON chunk (padded with spaces) and the binary
/// chunk (padded with zeros), each 4-byte aligned.
fn glb(document: &Value, bin: &[u8]) -> Vec<u8> {
    let mut json = serde_json::to_vec(document).unwrap_or_default();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let mut bin = bin.to_vec();
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

/// The skinned, animated avatar as a GLB file's bytes.
pub fn glb_bytes(skeleton: &Skeleton, skinned: &SkinnedMesh, bind: &Pose, motion: &[(f64, Pose)], name: &str) -> Vec<u8> {
    let (document, bin) = document(skeleton, skinned, bind, motion, name);
    glb(&document, &bin)
}

/// Linear blend skinning of the bind-pose vertices into `pose`, as a viewer poses the file.
pub fn skin_vertices(skinned: &SkinnedMesh, bind: &Pose, pose: &Pose) -> Vec<DVec3> {
    crate::skeleton::skin_points(&skinned.mesh.vertices, &skinned.weights, &bind.moves_to(pose))
}
