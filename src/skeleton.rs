//! The skeleton and its poses: bones (head joint at the origin, extending along local +Y),
//! per-frame rigid `bone_to_world` transforms, the maps between bone-local and world space, and a
//! pose as tensors (`PoseTensors`) and CPU bone frames for the field and the Gaussians.

use burn::tensor::{Device, Int, Tensor, TensorData};
use glam::{DMat3, DMat4, DVec3};
use serde::{Deserialize, Serialize};

/// The extent (m) of the body the fit's lengths were first tuned on: the walking human of the
/// shipped scenes (`Scene::body_extent` of `human-sun`, to the last digit, so a fit of it
/// computes exactly what it did when the lengths were metres). Every length the fit and the
/// renderer use is a fraction of a body's own extent, written in code as its value on that
/// human so the tuned figures stay readable.
pub const HUMAN_EXTENT: f64 = 2.0478165120721195;

/// A length of `metres_on_human` on the reference human, for a body of extent `extent` (m).
pub fn body_length(metres_on_human: f64, extent: f64) -> f64 {
    metres_on_human * extent / HUMAN_EXTENT
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Bone {
    pub name: String,
    /// Index of an earlier bone, `None` for a root.
    pub parent: Option<usize>,
    /// Metres along local +Y from the head joint to the tail.
    pub length: f64,
}

impl Bone {
    /// The bone's centre in its own frame.
    pub fn centre_local(&self) -> DVec3 {
        DVec3::new(0.0, self.length / 2.0, 0.0)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Skeleton {
    pub bones: Vec<Bone>,
}

impl Skeleton {
    pub fn len(&self) -> usize {
        self.bones.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bones.is_empty()
    }
}

/// One frame's pose: a rigid bone-to-world transform per bone, in bone order.
#[derive(Clone, Debug, PartialEq)]
pub struct Pose {
    pub bone_to_world: Vec<DMat4>,
}

impl Pose {
    pub fn to_world(&self, bone: usize, local: DVec3) -> DVec3 {
        self.bone_to_world[bone].transform_point3(local)
    }

    /// World to bone-local, using the rigid inverse (transpose of the rotation).
    pub fn to_local(&self, bone: usize, world: DVec3) -> DVec3 {
        let m = &self.bone_to_world[bone];
        let rotation = DMat3::from_mat4(*m);
        rotation.transpose() * (world - m.w_axis.truncate())
    }

    pub fn direction_to_world(&self, bone: usize, local: DVec3) -> DVec3 {
        self.bone_to_world[bone].transform_vector3(local)
    }

    /// The pose with each bone turned in its own frame by `turns[b]` (a rotation vector,
    /// radians: the correction of its rotation in its parent's frame, its children carried
    /// along, the skeleton's offsets kept) and the whole skeleton moved by `shift` (m, world).
    pub fn corrected(&self, skeleton: &Skeleton, turns: &[[f64; 3]], shift: [f64; 3]) -> Pose {
        let mut out: Vec<DMat4> = Vec::with_capacity(self.bone_to_world.len());
        // Whether a bone moved: one that did not (nor anything above it) keeps its transform to
        // the bit.
        let mut moved: Vec<bool> = Vec::with_capacity(self.bone_to_world.len());
        for (b, m) in self.bone_to_world.iter().enumerate() {
            let turn = turns.get(b).map(|t| DVec3::from_array(*t)).unwrap_or(DVec3::ZERO);
            let parent = skeleton.bones.get(b).and_then(|bone| bone.parent).filter(|&p| p < b);
            let still = turn == DVec3::ZERO && parent.map_or(shift == [0.0; 3], |p| !moved[p]);
            let turn = if turn.length() > 0.0 { DMat4::from_axis_angle(turn.normalize(), turn.length()) } else { DMat4::IDENTITY };
            out.push(match parent {
                _ if still => *m,
                Some(p) => out[p] * (self.bone_to_world[p].inverse() * *m) * turn,
                None => DMat4::from_translation(DVec3::from_array(shift)) * *m * turn,
            });
            moved.push(!still);
        }
        Pose { bone_to_world: out }
    }

    /// Each bone's move from this pose into `to` (`to`'s bone-to-world after this one's inverse).
    pub fn moves_to(&self, to: &Pose) -> Vec<DMat4> {
        to.bone_to_world.iter().zip(&self.bone_to_world).map(|(t, f)| *t * f.inverse()).collect()
    }
}

/// Linear blend skinning: `point` moved by each bone's move (`Pose::moves_to`) in proportion
/// to its weight `(bone, weight)`; weights need not sum to one (they are normalised), and a
/// point without weight stays where it is.
pub fn skin_point(point: DVec3, weights: &[(usize, f32)], moves: &[DMat4]) -> DVec3 {
    let total: f64 = weights.iter().filter(|&&(b, _)| b < moves.len()).map(|w| w.1 as f64).sum();
    if !(total > 0.0) {
        return point;
    }
    weights.iter().filter(|&&(b, _)| b < moves.len()).map(|&(b, w)| moves[b].transform_point3(point) * (w as f64 / total)).sum()
}

/// `skin_point` of every point, each with its own weights.
pub fn skin_points<W: AsRef<[(usize, f32)]>>(points: &[DVec3], weights: &[W], moves: &[DMat4]) -> Vec<DVec3> {
    points.iter().zip(weights).map(|(p, w)| skin_point(*p, w.as_ref(), moves)).collect()
}

/// A direction moved with the same blend (each bone's rotation), made unit again.
pub fn skin_direction(direction: DVec3, weights: &[(usize, f32)], moves: &[DMat4]) -> DVec3 {
    let blend: DVec3 = weights.iter().filter(|&&(b, _)| b < moves.len()).map(|&(b, w)| moves[b].transform_vector3(direction) * w as f64).sum();
    blend.normalize_or(direction)
}

impl Pose {
    /// World-space head and tail joint of a bone.
    pub fn segment(&self, skeleton: &Skeleton, bone: usize) -> (DVec3, DVec3) {
        let head = self.to_world(bone, DVec3::ZERO);
        let tail = self.to_world(bone, DVec3::new(0.0, skeleton.bones[bone].length, 0.0));
        (head, tail)
    }

    /// Distance (m) from `p` to bone `bone`'s segment in this pose.
    pub fn distance_to_bone(&self, skeleton: &Skeleton, bone: usize, p: DVec3) -> f64 {
        distance_to_segment(p, self.segment(skeleton, bone))
    }

    /// Axis-aligned bounds of every bone segment in this pose.
    pub fn bounds(&self, skeleton: &Skeleton) -> (DVec3, DVec3) {
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for bone in 0..skeleton.len() {
            let (a, b) = self.segment(skeleton, bone);
            lo = lo.min(a).min(b);
            hi = hi.max(a).max(b);
        }
        (lo, hi)
    }
}

/// A frame's bones as tensors: rotations `[B, 3, 3]` (bone-local axes as columns) and head
/// positions `[B, 3]` in world space, plus bone lengths `[B]`.
#[derive(Clone, Debug)]
pub struct PoseTensors {
    pub rotations: Tensor<3>,
    pub translations: Tensor<2>,
    pub lengths: Tensor<1>,
    /// The same bones on the CPU, for planning grid lookups.
    pub frames: Vec<BoneFrame>,
    /// A rigid increment of each bone's pose whose gradient a training step reads (the motion's
    /// refinement), when the lookups are to carry one.
    pub motion: Option<MotionIncrement>,
    /// A rigid increment of the camera each ray is seen from, whose gradient a training step
    /// reads (the cameras' refinement), when the render's lookups are to carry one.
    pub view: Option<ViewIncrement>,
}

/// A zero-valued increment of the cameras' poses that gradients flow through: per camera a
/// world turn about its centre (`leaf`, `[C, 3]`, radians). A camera turned so sees the world
/// point `x` of one of its rays where the unturned camera would see `x + w x (x - o)` (`o` the
/// ray's origin, the camera's centre). The render attaches each differentiable sample's camera
/// row and ray origin (`along`); a lookup of other points (the regularisers', the Gaussians'
/// fit) carries nothing of it.
#[derive(Clone, Debug)]
pub struct ViewIncrement {
    pub leaf: Tensor<2>,
    /// The step (m) over which the render differences the SDF's gradient to carry the increment
    /// into a shading normal (`render`): the surface a turned camera sees is shaded with the
    /// normal there, not here.
    pub stencil: f32,
    along: Option<(Tensor<1, Int>, Tensor<2>)>,
}

impl ViewIncrement {
    /// A fresh leaf of zeros for `cameras` cameras, its normals differenced over `stencil` (m).
    pub fn new(cameras: usize, stencil: f32, device: &Device) -> Self {
        Self { leaf: Tensor::zeros([cameras.max(1), 3], device).require_grad(), stencil, along: None }
    }

    /// The same increment as a new leaf (a graph of its own, for another thread).
    pub fn fork(&self) -> Self {
        Self { leaf: Tensor::zeros(self.leaf.dims(), &self.leaf.device()).require_grad(), stencil: self.stencil, along: None }
    }

    /// The increment for a lookup of points each on a ray: per point its camera's row and its
    /// ray's origin (`[N, 3]`, flat).
    pub fn along(&self, rows: &[u32], origins: Vec<f32>) -> Self {
        let device = self.leaf.device();
        let n = rows.len();
        let index = Tensor::<1, Int>::from_data(TensorData::new(rows.iter().map(|&r| r as i64).collect::<Vec<_>>(), [n]), &device);
        let origins = Tensor::from_data(TensorData::new(origins, [n, 3]), &device);
        Self { leaf: self.leaf.clone(), stencil: self.stencil, along: Some((index, origins)) }
    }

    /// Points the increment follows: as many as `along` was given (none before).
    pub fn points(&self) -> usize {
        self.along.as_ref().map_or(0, |(rows, _)| rows.dims()[0])
    }

    /// Where each of `points` (`[N, 3]`, the `along` points) is seen from the turned cameras,
    /// less where it is: `w x (x - o)` (`[N, 3]`; zeros without `along`).
    pub fn seen_shift(&self, points: Tensor<2>) -> Tensor<2> {
        match &self.along {
            Some((rows, origins)) => cross_rows(self.leaf.clone().select(0, rows.clone()), points - origins.clone()),
            None => points.zeros_like(),
        }
    }
}

/// A zero-valued increment of a pose that gradients flow through: per bone a world rotation
/// about its head joint that turns it and every bone below it, and one world translation of
/// the whole skeleton (`leaf`, `[B + 1, 3]`, the translation last). A world point carried by
/// bone `b` moves by `E_b x - P_b + t`, with `E = A w` and `P = A (w x o)` over the bone's chain
/// (`chains`, `A[b, j] = 1` when `j` is `b` or above it; `heads`, each bone's head `o`).
#[derive(Clone, Debug)]
pub struct MotionIncrement {
    pub leaf: Tensor<2>,
    chains: Tensor<2>,
    heads: Tensor<2>,
}

/// `a x b` for rows of `[.., 3]`.
pub fn cross_rows(a: Tensor<2>, b: Tensor<2>) -> Tensor<2> {
    let c = |t: &Tensor<2>, k: usize| t.clone().narrow(1, k, 1);
    Tensor::cat(vec![c(&a, 1) * c(&b, 2) - c(&a, 2) * c(&b, 1), c(&a, 2) * c(&b, 0) - c(&a, 0) * c(&b, 2), c(&a, 0) * c(&b, 1) - c(&a, 1) * c(&b, 0)], 1)
}

impl MotionIncrement {
    /// A fresh leaf of zeros for the bones of `skeleton` posed in `pose`.
    pub fn new(skeleton: &Skeleton, pose: &Pose, device: &Device) -> Self {
        let b = skeleton.len();
        let mut chains = vec![0.0f32; b * b];
        for bone in 0..b {
            let mut j = Some(bone);
            while let Some(k) = j {
                chains[bone * b + k] = 1.0;
                // A parent is an earlier bone (the scene's rule), so the walk ends.
                j = skeleton.bones[k].parent.filter(|&p| p < k);
            }
        }
        let heads: Vec<f32> = pose.bone_to_world.iter().flat_map(|m| m.w_axis.truncate().as_vec3().to_array()).collect();
        MotionIncrement {
            leaf: Tensor::zeros([b + 1, 3], device).require_grad(),
            chains: Tensor::from_data(TensorData::new(chains, [b, b]), device),
            heads: Tensor::from_data(TensorData::new(heads, [b, 3]), device),
        }
    }

    /// The same increment as a new leaf (a graph of its own, for another thread).
    pub fn fork(&self) -> Self {
        let [rows, _] = self.leaf.dims();
        MotionIncrement { leaf: Tensor::zeros([rows, 3], &self.leaf.device()).require_grad(), chains: self.chains.clone(), heads: self.heads.clone() }
    }

    /// How each of `points` (`[N * 3]`, on the host: they carry no gradient here) moves when
    /// carried by each of its `slots` chosen bones, `bones[i * slots + s]` (`[N slots]`):
    /// `E_b x - P_b + t` (`[N slots, 3]`).
    ///
    /// Each bone's motion is one affine map `[E_b]x | t - P_b` (`[B, 3, 4]`, from the leaf by
    /// small `[B, ..]` ops), so a point's is one row picked and one product with `(x, 1)`: a
    /// handful of `[N, ..]` ops where the cross product row by row took some twenty (and as
    /// many again backward): building half a batch's shift took 3.1 ms, now 2.1-2.4.
    pub fn motion_of(&self, points: Tensor<2>, slots: usize, bones: Tensor<1, Int>) -> Tensor<2> {
        let device = self.leaf.device();
        let b = self.heads.dims()[0];
        let [count, _] = points.dims();
        let n = count * slots;
        let turns = self.leaf.clone().narrow(0, 0, b);
        let shift = self.leaf.clone().narrow(0, b, 1);
        let e = self.chains.clone().matmul(turns.clone()); // [B, 3]
        let p = self.chains.clone().matmul(cross_rows(turns, self.heads.clone())); // [B, 3]

        // The matrix [e] with [e] x = e x x, row-major, from e by one product: (0,1) -e_z,
        // (0,2) e_y, (1,0) e_z, (1,2) -e_x, (2,0) -e_y, (2,1) e_x.
        let mut to_cross = [0.0f32; 27];
        for (axis, at, sign) in [(2, 1, -1.0), (1, 2, 1.0), (2, 3, 1.0), (0, 5, -1.0), (1, 6, -1.0), (0, 7, 1.0)] {
            to_cross[axis * 9 + at] = sign;
        }
        let cross: Tensor<2> = Tensor::from_data(TensorData::new(to_cross.to_vec(), [3, 9]), &device);
        let maps = Tensor::cat(vec![e.matmul(cross).reshape([b, 3, 3]), (p.neg() + shift).reshape([b, 3, 1])], 2).reshape([b, 12]);
        let homogeneous = Tensor::cat(vec![points, Tensor::ones([count, 1], &device)], 1).reshape([count, 1, 4]).expand([count, slots, 4]).reshape([n, 1, 4]);
        (maps.select(0, bones).reshape([n, 3, 4]) * homogeneous).sum_dim(2).reshape([n, 3])
    }
}

impl PoseTensors {
    pub fn new(pose: &Pose, skeleton: &Skeleton, device: &Device) -> Self {
        let b = skeleton.len();
        // Row-major rotation: element (i, j) is component i of local axis j.
        let rotations: Vec<f32> = pose.bone_to_world.iter().flat_map(|m| glam::DMat3::from_mat4(*m).transpose().to_cols_array().map(|v| v as f32)).collect();
        let translations: Vec<f32> = pose.bone_to_world.iter().flat_map(|m| m.w_axis.truncate().as_vec3().to_array()).collect();
        let lengths: Vec<f32> = skeleton.bones.iter().map(|bone| bone.length as f32).collect();
        let frames = pose
            .bone_to_world
            .iter()
            .zip(&skeleton.bones)
            .map(|(m, bone)| BoneFrame {
                axes: [m.x_axis, m.y_axis, m.z_axis].map(|a| a.truncate().as_vec3().to_array()),
                origin: m.w_axis.truncate().as_vec3().to_array(),
                length: bone.length as f32,
            })
            .collect();
        Self {
            frames,
            motion: None,
            view: None,
            rotations: Tensor::from_data(TensorData::new(rotations, [b, 3, 3]), device),
            translations: Tensor::from_data(TensorData::new(translations, [b, 3]), device),
            lengths: Tensor::from_data(TensorData::new(lengths, [b]), device),
        }
    }

    pub fn bones(&self) -> usize {
        self.lengths.dims()[0]
    }

    /// Bone-local coordinates of world points: `[N, B, 3]`.
    pub fn to_local(&self, points: Tensor<2>) -> Tensor<3> {
        let [n, _] = points.dims();
        let b = self.bones();
        let relative = points.unsqueeze_dim::<3>(1) - self.translations.clone().unsqueeze_dim::<3>(0); // [N, B, 3]
                                                                                                       // local = R^T (x - t); as rows: local_row = relative_row R.
        relative.swap_dims(0, 1).matmul(self.rotations.clone()).swap_dims(0, 1).reshape([n, b, 3])
    }
}

/// A posed bone on the CPU: its local axes in world space, its head and its length.
#[derive(Clone, Copy, Debug)]
pub struct BoneFrame {
    pub axes: [[f32; 3]; 3],
    pub origin: [f32; 3],
    pub length: f32,
}

impl BoneFrame {
    #[inline(always)]
    pub fn to_local(&self, p: [f32; 3]) -> [f32; 3] {
        let r = [p[0] - self.origin[0], p[1] - self.origin[1], p[2] - self.origin[2]];
        self.axes.map(|a| a[0] * r[0] + a[1] * r[1] + a[2] * r[2])
    }

    /// The squared distance from `p` to the bone's segment (its local y axis from 0 to
    /// `length`).
    #[inline(always)]
    pub fn distance_squared(&self, p: [f32; 3]) -> f32 {
        let local = self.to_local(p);
        let along = local[1] - local[1].clamp(0.0, self.length);
        local[0] * local[0] + along * along + local[2] * local[2]
    }
}

/// Checks that the upper 3x3 is a rotation (orthonormal, determinant +1) to `tolerance`.
pub fn check_rigid(m: &DMat4, tolerance: f64) -> Result<(), String> {
    let r = DMat3::from_mat4(*m);
    let gram = r.transpose() * r;
    let mut worst = 0.0f64;
    for (i, column) in [gram.x_axis, gram.y_axis, gram.z_axis].iter().enumerate() {
        for j in 0..3 {
            let expected = if i == j { 1.0 } else { 0.0 };
            worst = worst.max((column[j] - expected).abs());
        }
    }
    if worst > tolerance {
        return Err(format!("rotation is not orthonormal (|R^T R - I| = {worst:.3e} > {tolerance:.0e}; scale or shear is not allowed)"));
    }
    let det = r.determinant();
    if (det - 1.0).abs() > tolerance {
        return Err(format!("rotation determinant is {det:.6}, expected +1 (a reflection?)"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn local_and_world_round_trip() {
        let m = DMat4::from_rotation_translation(glam::DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0), DVec3::new(1.0, 2.0, -3.0));
        let pose = Pose { bone_to_world: vec![m] };
        let p = DVec3::new(0.2, -0.7, 1.5);
        let back = pose.to_local(0, pose.to_world(0, p));
        assert!((back - p).length() < 1e-12);
    }

    /// A point on one bone moves with it as its bone-local coordinates say; weights split
    /// between two bones blend the two moves; a point without weight stays.
    #[test]
    fn skinning_moves_a_point_with_its_bones() {
        let turn = glam::DQuat::from_euler(glam::EulerRot::XYZ, 0.4, 0.9, -0.2);
        let from = Pose { bone_to_world: vec![DMat4::from_translation(DVec3::new(0.0, 1.0, 0.0)), DMat4::IDENTITY] };
        let to = Pose { bone_to_world: vec![DMat4::from_rotation_translation(turn, DVec3::new(1.0, 0.0, 2.0)), DMat4::from_translation(DVec3::X)] };
        let moves = from.moves_to(&to);
        let p = DVec3::new(0.3, 1.2, -0.4);
        let on_first = skin_point(p, &[(0, 2.0)], &moves);
        assert!((on_first - to.to_world(0, from.to_local(0, p))).length() < 1e-12);
        let blended = skin_point(p, &[(0, 0.25), (1, 0.75)], &moves);
        assert!((blended - (on_first * 0.25 + (p + DVec3::X) * 0.75)).length() < 1e-12);
        assert_eq!(skin_point(p, &[], &moves), p);
        let n = DVec3::new(0.0, 0.6, 0.8);
        assert!((skin_direction(n, &[(0, 1.0)], &moves) - turn * n).length() < 1e-12);
    }

    #[test]
    fn rigid_check_rejects_scale_and_reflection() {
        let scaled = DMat4::from_scale(DVec3::new(1.0, 1.01, 1.0));
        assert!(check_rigid(&scaled, 1e-3).is_err());
        let mirrored = DMat4::from_scale(DVec3::new(1.0, 1.0, -1.0));
        assert!(check_rigid(&mirrored, 1e-3).unwrap_err().contains("determinant"));
        assert!(check_rigid(&DMat4::IDENTITY, 1e-3).is_ok());
    }
}

/// Distance from `p` to the segment from `a` to `b` (a point when they coincide).
pub fn distance_to_segment(p: DVec3, (a, b): (DVec3, DVec3)) -> f64 {
    let ab = b - a;
    let t = ((p - a).dot(ab) / ab.length_squared().max(1e-18)).clamp(0.0, 1.0);
    (p - (a + ab * t)).length()
}

/// Distance between the segment from `p0` to `p1` and the segment from `q0` to `q1` (the
/// closest pair of points, clamped to both; either may be a point). A ray is the segment to a
/// point beyond everything it can meet.
pub fn segment_distance((p0, p1): (DVec3, DVec3), (q0, q1): (DVec3, DVec3)) -> f64 {
    const EPS: f64 = 1e-18;
    let (d1, d2, r) = (p1 - p0, q1 - q0, p0 - q0);
    let (a, e, f) = (d1.length_squared(), d2.length_squared(), d2.dot(r));
    let (s, t) = if a <= EPS && e <= EPS {
        (0.0, 0.0)
    } else if a <= EPS {
        (0.0, (f / e).clamp(0.0, 1.0))
    } else {
        let c = d1.dot(r);
        if e <= EPS {
            ((-c / a).clamp(0.0, 1.0), 0.0)
        } else {
            // The closest points of the two lines, then each clamped in turn.
            let b = d1.dot(d2);
            let denominator = a * e - b * b;
            let s = if denominator > EPS * a * e { ((b * f - c * e) / denominator).clamp(0.0, 1.0) } else { 0.0 };
            let t = (b * s + f) / e;
            if t < 0.0 {
                ((-c / a).clamp(0.0, 1.0), 0.0)
            } else if t > 1.0 {
                (((b - c) / a).clamp(0.0, 1.0), 1.0)
            } else {
                (s, t)
            }
        }
    };
    ((p0 + d1 * s) - (q0 + d2 * t)).length()
}

#[cfg(test)]
mod segment_tests {
    use super::*;

    /// The closest pair by brute force over a fine grid of both parameters.
    fn brute(p: (DVec3, DVec3), q: (DVec3, DVec3)) -> f64 {
        let n = 400;
        let mut best = f64::INFINITY;
        for i in 0..=n {
            let a = p.0.lerp(p.1, i as f64 / n as f64);
            best = best.min(distance_to_segment(a, q));
        }
        best
    }

    #[test]
    fn segment_distance_matches_brute_force_for_crossing_parallel_and_degenerate_segments() {
        let v = |x: f64, y: f64, z: f64| DVec3::new(x, y, z);
        let cases = [
            ((v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0)), (v(0.5, -1.0, 0.3), v(0.5, 1.0, 0.3))), // skew, crossing
            ((v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0)), (v(2.0, 1.0, 0.0), v(3.0, 2.0, 0.5))),  // past the end
            ((v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0)), (v(0.2, 0.5, 0.0), v(2.2, 0.5, 0.0))),  // parallel, overlapping
            ((v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0)), (v(-3.0, 0.5, 0.0), v(-2.0, 0.5, 0.0))), // parallel, apart
            ((v(0.3, 0.2, 0.1), v(0.3, 0.2, 0.1)), (v(-1.0, 1.0, 0.0), v(1.0, -1.0, 0.5))), // a point
            ((v(0.3, 0.2, 0.1), v(0.3, 0.2, 0.1)), (v(1.0, 1.0, 1.0), v(1.0, 1.0, 1.0))),  // two points
            ((v(0.0, 0.0, 0.0), v(0.0, 1.0, 0.0)), (v(5.0, 0.4, -100.0), v(5.0, 0.6, 900.0))), // a long ray
        ];
        for (p, q) in cases {
            let (exact, reference) = (segment_distance(p, q), brute(p, q).min(brute(q, p)));
            assert!((exact - reference).abs() < 1e-5 * (1.0 + reference), "{p:?} {q:?}: {exact} against {reference}");
            assert!((segment_distance(q, p) - exact).abs() < 1e-9, "symmetric");
        }
    }
}
