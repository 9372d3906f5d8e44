//! Procedural characters with exact ground truth: a skeleton with a rest pose and a motion
//! cycle, and a surface that is the smooth union of tapered capsules around the posed bones
//! (and, for the dressed human, of loose garments carried by bones: `clothing`), with an
//! analytic signed distance, normal and a spatially varying albedo.

use super::clothing::{self, Garment};
use crate::skeleton::{Bone, Pose, Skeleton};
use glam::{DMat3, DMat4, DQuat, DVec3};
use std::f64::consts::PI;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    /// A human walking, in tight clothes (17 bones).
    Human,
    /// A four-legged animal trotting (12 bones).
    Quadruped,
    /// The human in loose clothes: a bell skirt, a backpack and a bun 15-30 cm from any bone.
    Dressed,
}

/// What the clothes look like.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Pattern {
    /// One colour per bone, gently modulated (the shipped 64x64 scenes).
    #[default]
    Plain,
    /// Fine, high-contrast clothing in bone-local coordinates: 6 cm checkers on the shirt and
    /// sleeves, 4 cm stripes across the trousers, so that a blurred fit loses PSNR.
    Clothing,
}

impl Pattern {
    pub fn is_plain(&self) -> bool {
        *self == Pattern::Plain
    }
}

/// How a bone swings over the motion cycle: `amplitude * sin(2 pi phase + offset) + bias`
/// radians about its rest-frame X axis (Z for `roll`).
#[derive(Clone, Copy, Debug)]
struct Swing {
    amplitude: f64,
    offset: f64,
    bias: f64,
    /// Knees and elbows only bend one way: clamp the swing at zero from below.
    one_sided: bool,
}

const STILL: Swing = Swing { amplitude: 0.0, offset: 0.0, bias: 0.0, one_sided: false };

#[derive(Clone, Debug)]
struct BoneSpec {
    name: &'static str,
    parent: Option<usize>,
    head: DVec3,
    tail: DVec3,
    radius_head: f64,
    radius_tail: f64,
    colour: [f64; 3],
    swing: Swing,
}

/// A character: skeleton, rest frames, motion, surface and albedo.
#[derive(Clone, Debug)]
pub struct Character {
    pub kind: Kind,
    pub skeleton: Skeleton,
    specs: Vec<BoneSpec>,
    rest: Vec<DMat4>,
    /// Smooth-union width (metres) of the log-sum-exp blend between bone capsules.
    blend: f64,
    pub pattern: Pattern,
    /// Loose garments, blended into the surface like the capsules.
    garments: Vec<Garment>,
    /// How much larger than the specification the character is built (lengths, motion and
    /// clothing patterns scale with it; angles do not).
    pub scale: f64,
}

fn bone(name: &'static str, parent: Option<usize>, head: [f64; 3], tail: [f64; 3], radii: (f64, f64), colour: [f64; 3], swing: Swing) -> BoneSpec {
    BoneSpec { name, parent, head: DVec3::from_array(head), tail: DVec3::from_array(tail), radius_head: radii.0, radius_tail: radii.1, colour, swing }
}

fn swing(amplitude: f64, offset: f64, bias: f64) -> Swing {
    Swing { amplitude, offset, bias, one_sided: false }
}

fn bend(amplitude: f64, offset: f64, bias: f64) -> Swing {
    Swing { amplitude, offset, bias, one_sided: true }
}

fn human_specs() -> Vec<BoneSpec> {
    let skin = [0.80, 0.62, 0.50];
    let shirt = [0.20, 0.45, 0.75];
    let trousers = [0.30, 0.30, 0.35];
    let shoes = [0.55, 0.25, 0.15];
    let hair = [0.35, 0.22, 0.12];
    vec![
        bone("pelvis", None, [0.0, 0.92, 0.0], [0.0, 1.04, 0.0], (0.13, 0.12), trousers, STILL),
        bone("spine", Some(0), [0.0, 1.04, 0.0], [0.0, 1.24, 0.0], (0.12, 0.12), shirt, swing(0.04, 0.5, 0.0)),
        bone("chest", Some(1), [0.0, 1.24, 0.0], [0.0, 1.44, 0.0], (0.13, 0.12), shirt, STILL),
        bone("neck", Some(2), [0.0, 1.44, 0.0], [0.0, 1.53, 0.0], (0.05, 0.05), skin, STILL),
        bone("head", Some(3), [0.0, 1.53, 0.0], [0.0, 1.73, 0.02], (0.09, 0.10), hair, swing(0.05, 1.0, 0.0)),
        bone("upper_arm_l", Some(2), [0.19, 1.40, 0.0], [0.23, 1.12, 0.0], (0.05, 0.045), shirt, swing(-0.45, 0.0, 0.0)),
        bone("forearm_l", Some(5), [0.23, 1.12, 0.0], [0.25, 0.88, 0.0], (0.04, 0.035), skin, bend(-0.35, 0.0, -0.25)),
        bone("hand_l", Some(6), [0.25, 0.88, 0.0], [0.26, 0.80, 0.0], (0.035, 0.03), skin, STILL),
        bone("upper_arm_r", Some(2), [-0.19, 1.40, 0.0], [-0.23, 1.12, 0.0], (0.05, 0.045), shirt, swing(0.45, 0.0, 0.0)),
        bone("forearm_r", Some(8), [-0.23, 1.12, 0.0], [-0.25, 0.88, 0.0], (0.04, 0.035), skin, bend(0.35, 0.0, -0.25)),
        bone("hand_r", Some(9), [-0.25, 0.88, 0.0], [-0.26, 0.80, 0.0], (0.035, 0.03), skin, STILL),
        bone("thigh_l", Some(0), [0.09, 0.92, 0.0], [0.10, 0.50, 0.0], (0.075, 0.06), trousers, swing(0.5, 0.0, 0.0)),
        bone("shin_l", Some(11), [0.10, 0.50, 0.0], [0.10, 0.09, 0.0], (0.055, 0.045), trousers, bend(0.7, -1.2, 0.0)),
        bone("foot_l", Some(12), [0.10, 0.06, -0.04], [0.10, 0.05, 0.16], (0.045, 0.04), shoes, swing(0.15, -0.8, 0.0)),
        bone("thigh_r", Some(0), [-0.09, 0.92, 0.0], [-0.10, 0.50, 0.0], (0.075, 0.06), trousers, swing(-0.5, 0.0, 0.0)),
        bone("shin_r", Some(14), [-0.10, 0.50, 0.0], [-0.10, 0.09, 0.0], (0.055, 0.045), trousers, bend(-0.7, -1.2, 0.0)),
        bone("foot_r", Some(15), [-0.10, 0.06, -0.04], [-0.10, 0.05, 0.16], (0.045, 0.04), shoes, swing(-0.15, -0.8, 0.0)),
    ]
}

fn quadruped_specs() -> Vec<BoneSpec> {
    let coat = [0.70, 0.50, 0.28];
    let belly = [0.85, 0.78, 0.65];
    let dark = [0.30, 0.22, 0.18];
    let legs = [0.60, 0.42, 0.25];
    vec![
        bone("body", None, [0.0, 0.55, -0.32], [0.0, 0.58, 0.30], (0.16, 0.17), coat, swing(0.03, 0.0, 0.0)),
        bone("neck", Some(0), [0.0, 0.60, 0.30], [0.0, 0.78, 0.45], (0.09, 0.075), belly, swing(0.06, 0.7, 0.0)),
        bone("head", Some(1), [0.0, 0.80, 0.45], [0.0, 0.74, 0.68], (0.09, 0.055), dark, swing(0.05, 1.4, 0.0)),
        bone("tail", Some(0), [0.0, 0.58, -0.40], [0.0, 0.66, -0.70], (0.04, 0.02), dark, swing(0.3, 0.3, 0.0)),
        bone("front_upper_l", Some(0), [0.10, 0.50, 0.25], [0.11, 0.28, 0.27], (0.055, 0.045), legs, swing(0.45, 0.0, 0.0)),
        bone("front_lower_l", Some(4), [0.11, 0.28, 0.27], [0.11, 0.03, 0.27], (0.04, 0.03), dark, bend(-0.5, 1.0, 0.0)),
        bone("front_upper_r", Some(0), [-0.10, 0.50, 0.25], [-0.11, 0.28, 0.27], (0.055, 0.045), legs, swing(-0.45, 0.0, 0.0)),
        bone("front_lower_r", Some(6), [-0.11, 0.28, 0.27], [-0.11, 0.03, 0.27], (0.04, 0.03), dark, bend(0.5, 1.0, 0.0)),
        bone("hind_upper_l", Some(0), [0.10, 0.50, -0.28], [0.11, 0.27, -0.25], (0.065, 0.05), legs, swing(-0.45, 0.0, 0.0)),
        bone("hind_lower_l", Some(8), [0.11, 0.27, -0.25], [0.11, 0.03, -0.29], (0.045, 0.03), dark, bend(0.5, 1.0, 0.0)),
        bone("hind_upper_r", Some(0), [-0.10, 0.50, -0.28], [-0.11, 0.27, -0.25], (0.065, 0.05), legs, swing(0.45, 0.0, 0.0)),
        bone("hind_lower_r", Some(10), [-0.11, 0.27, -0.25], [-0.11, 0.03, -0.29], (0.045, 0.03), dark, bend(-0.5, 1.0, 0.0)),
    ]
}

/// The rest frame of a bone: origin at its head, +Y along it, +X as close to world +X as possible.
fn rest_frame(head: DVec3, tail: DVec3) -> DMat4 {
    let y = (tail - head).normalize();
    let reference = if y.x.abs() > 0.9 { DVec3::Z } else { DVec3::X };
    let x = (reference - y * reference.dot(y)).normalize();
    let z = x.cross(y);
    DMat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), head.extend(1.0))
}

impl Character {
    pub fn new(kind: Kind) -> Self {
        let specs = match kind {
            Kind::Human | Kind::Dressed => human_specs(),
            Kind::Quadruped => quadruped_specs(),
        };
        let garments = if kind == Kind::Dressed { clothing::dressed_human() } else { Vec::new() };
        let skeleton = Skeleton { bones: specs.iter().map(|s| Bone { name: s.name.into(), parent: s.parent, length: (s.tail - s.head).length() }).collect() };
        let rest = specs.iter().map(|s| rest_frame(s.head, s.tail)).collect();
        Self { kind, skeleton, specs, rest, blend: 0.025, pattern: Pattern::Plain, garments, scale: 1.0 }
    }

    /// The same character `scale` times larger (a child at 0.6, a giant at 3): every length of
    /// the body, its garments, its motion's bob and its clothing patterns; the same angles.
    pub fn scaled(self, scale: f64) -> Self {
        let specs: Vec<BoneSpec> = self
            .specs
            .iter()
            .map(|b| BoneSpec {
                head: b.head * scale,
                tail: b.tail * scale,
                radius_head: b.radius_head * scale,
                radius_tail: b.radius_tail * scale,
                ..b.clone()
            })
            .collect();
        let skeleton = Skeleton { bones: specs.iter().map(|s| Bone { name: s.name.into(), parent: s.parent, length: (s.tail - s.head).length() }).collect() };
        let rest = specs.iter().map(|s| rest_frame(s.head, s.tail)).collect();
        let garments = self.garments.iter().map(|g| Garment { shape: g.shape.scaled(scale), ..*g }).collect();
        Self { skeleton, specs, rest, blend: self.blend * scale, garments, scale: self.scale * scale, ..self }
    }

    pub fn with_pattern(self, pattern: Pattern) -> Self {
        Self { pattern, ..self }
    }

    /// The albedo of bone `i`'s clothing at bone-local point `local`, before blending.
    fn bone_albedo(&self, i: usize, local: DVec3) -> DVec3 {
        let spec = &self.specs[i];
        // Patterns are laid out on the unscaled body, so they scale with it.
        let local = local / self.scale;
        let base = DVec3::from_array(spec.colour);
        let cell = |v: f64, size: f64| (v / size).floor() as i64;
        match (self.pattern, spec.name) {
            (Pattern::Clothing, "spine" | "chest" | "upper_arm_l" | "upper_arm_r") => {
                let odd = (cell(local.x, 0.06) + cell(local.y, 0.06) + cell(local.z, 0.06)).rem_euclid(2) == 1;
                if odd {
                    DVec3::new(0.85, 0.83, 0.78)
                } else {
                    base
                }
            }
            (Pattern::Clothing, "pelvis" | "thigh_l" | "thigh_r" | "shin_l" | "shin_r") => {
                if cell(local.y, 0.04).rem_euclid(2) == 1 {
                    DVec3::new(0.80, 0.62, 0.22)
                } else {
                    DVec3::new(0.12, 0.12, 0.16)
                }
            }
            _ => base * (0.82 + 0.18 * (local.y * 38.0 + i as f64).sin() * (local.x * 25.0).cos() * (local.z * 31.0 + 0.5).sin()),
        }
    }

    /// The pose at `phase` (cycles; 1.0 is one full stride) with the body `heading` radians
    /// about +Y and moved by `offset`.
    pub fn pose(&self, phase: f64, heading: f64, offset: DVec3) -> Pose {
        let angle = 2.0 * PI * phase;
        let bob = 0.015 * self.scale * (2.0 * angle).cos();
        let root = DMat4::from_rotation_translation(DQuat::from_rotation_y(heading), offset + DVec3::new(0.0, bob, 0.0));
        let mut world: Vec<DMat4> = Vec::with_capacity(self.specs.len());
        for (i, spec) in self.specs.iter().enumerate() {
            let mut a = spec.swing.amplitude * (angle + spec.swing.offset).sin() + spec.swing.bias;
            if spec.swing.one_sided {
                a = if spec.swing.amplitude >= 0.0 { a.max(0.0) } else { a.min(0.0) };
            }
            let local_motion = DMat4::from_quat(DQuat::from_rotation_x(a));
            let parent_world = match spec.parent {
                Some(p) => world[p] * self.rest[p].inverse(),
                None => root,
            };
            world.push(parent_world * self.rest[i] * local_motion);
        }
        Pose { bone_to_world: world }
    }

    /// Signed distance to the surface, its gradient (the unit normal off the medial axis) and
    /// the per-bone blend weights, for a world point in a given pose.
    pub fn sdf(&self, pose: &Pose, p: DVec3) -> (f64, DVec3) {
        let k = self.blend;
        let mut parts = [(0.0f64, DVec3::ZERO); 32];
        let mut smallest = f64::INFINITY;
        for (i, spec) in self.specs.iter().enumerate() {
            let (d, g) = tapered_capsule(pose, &self.skeleton, i, spec, p);
            parts[i] = (d, g);
            smallest = smallest.min(d);
        }
        for (j, garment) in self.garments.iter().enumerate() {
            let (d, g) = garment_distance(pose, garment, p);
            parts[self.specs.len() + j] = (d, g);
            smallest = smallest.min(d);
        }
        // Log-sum-exp smooth minimum, shifted by the smallest distance for stability.
        let mut sum = 0.0;
        let mut gradient = DVec3::ZERO;
        for &(d, g) in &parts[..self.specs.len() + self.garments.len()] {
            let w = (-(d - smallest) / k).exp();
            sum += w;
            gradient += g * w;
        }
        (smallest - k * sum.ln(), gradient / sum)
    }

    /// The outward unit normal at a surface point.
    pub fn normal(&self, pose: &Pose, p: DVec3) -> DVec3 {
        self.sdf(pose, p).1.normalize()
    }

    /// Albedo at a surface point: the blend-weighted colours of the nearby bones (each by its
    /// `Pattern` in the bone's local frame), kept within [0.1, 0.9].
    pub fn albedo(&self, pose: &Pose, p: DVec3) -> DVec3 {
        let k = self.blend;
        let mut best = f64::INFINITY;
        let mut parts = [(0.0f64, DVec3::ZERO); 32];
        for (i, spec) in self.specs.iter().enumerate() {
            let d = tapered_capsule(pose, &self.skeleton, i, spec, p).0;
            parts[i] = (d, self.bone_albedo(i, pose.to_local(i, p)));
            best = best.min(d);
        }
        for (j, garment) in self.garments.iter().enumerate() {
            let d = garment_distance(pose, garment, p).0;
            let local = pose.to_local(garment.bone, p) / self.scale;
            // The same gentle modulation as a plain bone's colour, so the albedo has texture.
            let colour = DVec3::from_array(garment.colour) * (0.85 + 0.15 * (local.y * 31.0 + j as f64).sin() * (local.x * 23.0).cos());
            parts[self.specs.len() + j] = (d, colour);
            best = best.min(d);
        }
        let mut sum = 0.0;
        let mut colour = DVec3::ZERO;
        for &(d, c) in &parts[..self.specs.len() + self.garments.len()] {
            let w = (-(d - best) / k).exp();
            sum += w;
            colour += c * w;
        }
        (colour / sum).clamp(DVec3::splat(0.1), DVec3::splat(0.9))
    }

    /// A sphere (centre, radius) holding the whole surface in this pose.
    pub fn bounding_sphere(&self, pose: &Pose) -> (DVec3, f64) {
        let (lo, hi) = pose.bounds(&self.skeleton);
        let centre = (lo + hi) * 0.5;
        let capsules = self.specs.iter().map(|s| s.radius_head.max(s.radius_tail));
        let garments = self.garments.iter().map(|g| g.shape.reach(self.skeleton.bones[g.bone].length));
        let radius_margin = capsules.chain(garments).fold(0.0, f64::max);
        (centre, (hi - lo).length() * 0.5 + radius_margin + 0.05)
    }
}

/// Distance to a garment in a pose, and its gradient in world space.
fn garment_distance(pose: &Pose, garment: &Garment, p: DVec3) -> (f64, DVec3) {
    let m = &pose.bone_to_world[garment.bone];
    let rotation = DMat3::from_mat4(*m);
    let (d, g) = garment.shape.sdf(rotation.transpose() * (p - m.w_axis.truncate()));
    (d, rotation * g)
}

/// Distance to a capsule around bone `i` whose radius tapers from head to tail, and its gradient.
/// (Not an exact distance where the taper is steep, but Lipschitz to within the taper slope.)
fn tapered_capsule(pose: &Pose, skeleton: &Skeleton, i: usize, spec: &BoneSpec, p: DVec3) -> (f64, DVec3) {
    let m = &pose.bone_to_world[i];
    let rotation = DMat3::from_mat4(*m);
    let local = rotation.transpose() * (p - m.w_axis.truncate());
    let length = skeleton.bones[i].length;
    let h = (local.y / length).clamp(0.0, 1.0);
    let offset = local - DVec3::new(0.0, h * length, 0.0);
    let distance = offset.length();
    let radius = spec.radius_head + (spec.radius_tail - spec.radius_head) * h;
    let direction = if distance > 1e-12 { offset / distance } else { DVec3::X };
    // Between the joints the radius changes with the position along the bone.
    let taper = if local.y > 0.0 && local.y < length { (spec.radius_tail - spec.radius_head) / length } else { 0.0 };
    (distance - radius, rotation * (direction - DVec3::Y * taper))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rest_pose_matches_the_specification_and_is_rigid() {
        for kind in [Kind::Human, Kind::Quadruped, Kind::Dressed] {
            let c = Character::new(kind);
            let pose = c.pose(0.0, 0.0, DVec3::ZERO);
            for m in &pose.bone_to_world {
                crate::skeleton::check_rigid(m, 1e-9).unwrap();
            }
            let moving = c.pose(0.37, 0.4, DVec3::new(0.1, 0.0, 0.2));
            for (i, b) in c.skeleton.bones.iter().enumerate() {
                if let Some(parent) = b.parent {
                    // A child's head stays where it was attached on its parent in every pose.
                    let attach_rest = pose.to_local(parent, pose.to_world(i, DVec3::ZERO));
                    let attach_moving = moving.to_local(parent, moving.to_world(i, DVec3::ZERO));
                    assert!((attach_rest - attach_moving).length() < 1e-9, "{}", b.name);
                }
            }
        }
    }

    #[test]
    fn sdf_gradient_matches_finite_differences() {
        for (kind, p) in [
            (Kind::Human, DVec3::new(0.1, 1.2, 0.1)),
            (Kind::Human, DVec3::new(-0.2, 0.5, 0.05)),
            (Kind::Human, DVec3::new(0.0, 1.7, 0.1)),
            (Kind::Dressed, DVec3::new(0.3, 0.6, 0.1)),
            (Kind::Dressed, DVec3::new(0.05, 1.3, -0.35)),
            (Kind::Dressed, DVec3::new(0.02, 1.72, -0.25)),
        ] {
            let c = Character::new(kind);
            let pose = c.pose(0.2, 0.0, DVec3::ZERO);
            let (_, g) = c.sdf(&pose, p);
            let h = 1e-6;
            let fd = DVec3::new(
                (c.sdf(&pose, p + DVec3::X * h).0 - c.sdf(&pose, p - DVec3::X * h).0) / (2.0 * h),
                (c.sdf(&pose, p + DVec3::Y * h).0 - c.sdf(&pose, p - DVec3::Y * h).0) / (2.0 * h),
                (c.sdf(&pose, p + DVec3::Z * h).0 - c.sdf(&pose, p - DVec3::Z * h).0) / (2.0 * h),
            );
            assert!((g - fd).length() < 1e-6, "{g} vs {fd}");
        }
    }
}
