//! A capture's cameras, frames and light as scene/1's JSON: the capture's world turned so its up
//! is +Y and scaled to metres, images of one camera sharing it, each clip frame's bones aligned
//! to their bone rule.

use super::{bones, bvh, CaptureImage, CaptureLight, Intrinsics};
use glam::DMat4;
use serde_json::{json, Value};

/// The capture's world in scene/1's: turned so its up is +Y, scaled to metres.
pub(super) struct World {
    pub(super) up: DMat4,
    pub(super) metres: f64,
}

impl World {
    /// A rigid transform whose translation is in capture units, in scene/1's world.
    fn apply(&self, m: DMat4) -> DMat4 {
        let turned = self.up * m;
        let mut out = turned;
        out.w_axis = (turned.w_axis.truncate() * self.metres).extend(1.0);
        out
    }
}

impl World {
    /// The scene's `capture` key (umbra's own, `scene::CaptureWorld`): the capture's units and
    /// its world turned into scene/1's, so that what a fit writes back (the refined motion) can
    /// be in the capture's terms.
    pub(super) fn json(&self) -> Value {
        json!({"metres_per_unit": self.metres, "to_scene": rows(&self.up)})
    }
}

fn rows(m: &DMat4) -> Value {
    json!((0..4).map(|r| m.row(r).to_array().to_vec()).collect::<Vec<_>>())
}

/// The scene's cameras (images with the same intrinsics and pose share one) and each image's.
pub(super) fn cameras(images: &[CaptureImage], intrinsics: &[Intrinsics], world: &World) -> (Vec<Value>, Vec<usize>) {
    let mut kept: Vec<(Intrinsics, DMat4)> = Vec::new();
    let mut of = Vec::with_capacity(images.len());
    for (image, k) in images.iter().zip(intrinsics) {
        let pose = world.apply(image.camera_to_world);
        let same = |(i, p): &(Intrinsics, DMat4)| i == k && p.abs_diff_eq(pose, 1e-9);
        match kept.iter().position(same) {
            Some(c) => of.push(c),
            None => {
                of.push(kept.len());
                kept.push((k.clone(), pose));
            }
        }
    }
    let values = kept
        .iter()
        .enumerate()
        .map(|(c, (k, pose))| json!({"name": format!("cam{c:02}"), "width": k.width, "height": k.height, "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "camera_to_world": rows(pose)}))
        .collect();
    (values, of)
}

/// Clip frame `k` as a scene/1 frame: each bone's frame in metres, +Y up.
pub(super) fn frame_json(motion: &bvh::Motion, rig: &bones::Rig, k: usize, world: &World) -> Value {
    let joints = motion.joint_to_world(k);
    let bones: Vec<Value> = joints.iter().zip(&rig.alignments).map(|(j, a)| rows(&world.apply(*j * *a))).collect();
    json!({"index": k, "time": motion.time(k), "bone_to_world": bones})
}

/// The capture's light: unknown, of the kind asked.
pub(super) fn light_json(light: CaptureLight) -> (&'static str, Value) {
    match light {
        CaptureLight::Sun => ("sun", json!({"type": "directional"})),
        CaptureLight::Point => ("lamp", json!({"type": "point"})),
        CaptureLight::Uniform => ("uniform", json!({"type": "uniform", "radiance": [1.0, 1.0, 1.0]})),
    }
}
