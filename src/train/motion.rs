//! The training motion refined while fitting: per training frame, a correction of each bone's
//! rotation in its parent's frame (a rotation vector, radians) and of the skeleton's position
//! (in levers: a limb's length on this body), learned with the field from the stage the
//! schedule's motion terms start at. A step renders its frame's pose as corrected so far and
//! carries a zero increment of it through the field's lookups (`skeleton::MotionIncrement`);
//! the increment's gradient is turned into the correction's and one Adam step is taken on the
//! host (a frame's corrections are `3 (bones + 1)` numbers). The motion's terms
//! (`losses::TERMS`: `motion_prior`, `motion_smoothness`) hold a correction near the given
//! motion and the corrected motion smooth in time (its second differences near zero). Test
//! frames and new
//! motion are used as given.

use super::motion_noise::Rows;
use crate::losses::MotionInput;
use crate::scene::{Scene, Split};
use crate::skeleton::{Pose, Skeleton};
use burn::tensor::{Device, Tensor, TensorData};
use glam::{DMat3, DQuat, DVec3};

/// The lever (m on the reference human, scaled with the body) the skeleton's shift is measured
/// in: a turn of one radian moves a point this far from its joint as far as a shift of one.
pub const LEVER_ON_HUMAN: f64 = 0.3;

/// How far a bone's mean correction must stand out of its frames' scatter for the poses the
/// avatar is shown in to carry it: it is kept in proportion `1 - SHARED_TURN_EVIDENCE e^2 / m^2` (`m` the mean turn, `e`
/// its standard error, the frames' scatter over the square root of their count), none of it
/// within `sqrt(2)` standard errors. A tracker's errors drawn anew each frame leave a mean about
/// one standard error long, which exact poses must not be turned by; a turn the field took up
/// is shared by every frame alike, a few standard errors long. On the 64-pixel captures
/// (`docs/measurements.md`) a factor of 1 turned exact test poses by a tracker's mean and cost
/// them 1.6 dB; 4 gave up 0.5-0.9 dB of what the exact capture gains.
pub const SHARED_TURN_EVIDENCE: f64 = 2.0;

/// The training frames' corrections and their optimiser's state.
#[derive(Clone, Debug, PartialEq)]
pub struct MotionCorrections {
    /// Per corrected frame, its scene frame.
    frames: Vec<usize>,
    /// Per corrected frame, the frames before and after it in time (indices here), when it has
    /// both.
    neighbours: Vec<Option<(usize, usize)>>,
    /// Per corrected frame, the given motion's acceleration there: each bone's turn over the
    /// next step less the last step's (radians), the shift's second difference (levers).
    acceleration: Vec<Rows>,
    values: Vec<Rows>,
    first: Vec<Rows>,
    second: Vec<Rows>,
    steps: Vec<u64>,
    lever: f64,
    /// The share of the given motion's second differences that is noise (`noise_share`).
    noise_share: f64,
    /// The given motion's noise per frame (radians per axis, `noise`).
    noise: f64,
}

/// How far the refinement moved the training motion: the bones' turns over every frame
/// (degrees, mean and largest), each bone's, and the skeleton's shift (cm, mean and largest).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct MotionMoved {
    pub frames: usize,
    pub mean_degrees: f64,
    pub largest_degrees: f64,
    pub mean_shift_cm: f64,
    pub largest_shift_cm: f64,
    /// The turns every frame shares (`MotionCorrections::shared_turns`), which every pose is
    /// shown with: degrees, mean and largest over the bones.
    pub shared_mean_degrees: f64,
    pub shared_largest_degrees: f64,
    /// The share of the given motion's second differences that is noise (`noise_share`), and
    /// the smoothness's weight on this capture for the schedule's (`smoothness_scale`).
    pub given_noise_share: f64,
    pub smoothness_scale: f64,
    /// The given motion's noise per frame (degrees per axis, `MotionCorrections::noise`) and
    /// the prior's weight on this capture for the schedule's (`prior_scale`).
    pub given_noise_degrees: f64,
    pub prior_scale: f64,
    /// What that noise leaves alike in every training frame (degrees, a bone's mean error over
    /// them, `motion_noise::bias`): the images cannot tell it from the body, so the avatar
    /// carries it, and motion from elsewhere shows it.
    pub given_bias_degrees: f64,
    pub bones: Vec<BoneMoved>,
}

/// How far one bone was turned over the training frames (degrees).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct BoneMoved {
    pub bone: String,
    pub mean_degrees: f64,
    pub largest_degrees: f64,
    /// Its turn shared by every frame (degrees).
    pub shared_degrees: f64,
}

/// A bone's rotation in its parent's frame (the root's in the world) in `pose`.
fn local_rotation(skeleton: &Skeleton, pose: &Pose, bone: usize) -> DMat3 {
    let m = pose.bone_to_world[bone];
    let local = match skeleton.bones[bone].parent.filter(|&p| p < bone) {
        Some(p) => pose.bone_to_world[p].inverse() * m,
        None => m,
    };
    DMat3::from_mat4(local)
}

/// The rotation vector taking `a` to `b` in `a`'s frame.
fn turn_between(a: DMat3, b: DMat3) -> DVec3 {
    DQuat::from_mat3(&(a.transpose() * b)).normalize().to_scaled_axis()
}

impl MotionCorrections {
    /// For the scene's training frames (none without any), the shift measured in the body's
    /// lever (`LEVER_ON_HUMAN` scaled to it).
    pub fn new(scene: &Scene) -> Option<Self> {
        let lever = crate::skeleton::body_length(LEVER_ON_HUMAN, scene.body_extent());
        let mut frames: Vec<usize> = scene.views.iter().filter(|v| v.split == Split::Train).map(|v| v.frame).collect();
        // In time (a frame without a time by its index).
        let when = |f: usize| scene.frames[f].time.unwrap_or(scene.frames[f].index as f64);
        frames.sort_by(|&a, &b| when(a).total_cmp(&when(b)).then(a.cmp(&b)));
        frames.dedup();
        if frames.is_empty() {
            return None;
        }
        let rows = scene.skeleton.len() + 1;
        let n = frames.len();
        let neighbours: Vec<Option<(usize, usize)>> = (0..n).map(|k| (k > 0 && k + 1 < n).then(|| (k - 1, k + 1))).collect();
        let acceleration: Vec<Rows> = (0..n)
            .map(|k| match neighbours[k] {
                Some((before, after)) => {
                    let pose = |j: usize| &scene.frames[frames[j]].pose;
                    let mut out: Rows = (0..scene.skeleton.len())
                        .map(|b| {
                            let r = |j: usize| local_rotation(&scene.skeleton, pose(j), b);
                            (turn_between(r(k), r(after)) - turn_between(r(before), r(k))).to_array()
                        })
                        .collect();
                    let root = |j: usize| pose(j).bone_to_world.first().map(|m| m.w_axis.truncate()).unwrap_or_default();
                    out.push(((root(after) - root(k) * 2.0 + root(before)) / lever).to_array());
                    out
                }
                None => vec![[0.0; 3]; rows],
            })
            .collect();
        let zeros = vec![vec![[0.0; 3]; rows]; n];
        let noise_share = super::motion_noise::noise_share(&acceleration, &neighbours);
        let noise = super::motion_noise::noise(&acceleration, &neighbours, noise_share);
        Some(Self {
            frames,
            neighbours,
            acceleration,
            values: zeros.clone(),
            first: zeros.clone(),
            second: zeros,
            steps: vec![0; n],
            lever,
            noise_share,
            noise,
        })
    }

    /// The share of the given motion's second differences (the bones' turns) that is noise
    /// drawn anew each frame, as a tracker leaves it, rather than the motion's own: from their
    /// correlation with the next frame's, which is -2/3 for independent errors and near 1 for a
    /// motion sampled finely enough to be seen moving. 0 to `motion_noise::MOST_NOISE_SHARE`.
    pub fn noise_share(&self) -> f64 {
        self.noise_share
    }

    /// How much the smoothness term weighs on this capture, for the schedule's weight: the
    /// noise-to-motion ratio of the given motion's second differences, `f / (1 - f)` of the
    /// `noise_share` `f`, as a Wiener filter weighs a signal's smoothness against its noise,
    /// times `motion_noise::SMOOTHNESS_PER_NOISE_RATIO`; never less than 1, the weight that holds back the
    /// refinement's own wander, which a smooth given motion has too.
    pub fn smoothness_scale(&self) -> f64 {
        super::motion_noise::smoothness_scale(self.noise_share)
    }

    /// The given motion's noise per frame (radians per axis): the deviation of a tracker's
    /// errors drawn anew each frame that its second differences show.
    pub fn noise(&self) -> f64 {
        self.noise
    }

    /// How much the prior weighs on this capture, for the schedule's weight: as sure as the given
    /// motion is, `(motion_noise::PRIOR_NOISE / noise)^2`, from 1 (a tracker's 2.5 degrees and
    /// more) to `motion_noise::MOST_PRIOR_SCALE` (a motion that shows no noise).
    pub fn prior_scale(&self) -> f64 {
        super::motion_noise::prior_scale(self.noise)
    }

    /// The corrected frame of scene frame `frame`, if it is one.
    pub fn row(&self, frame: usize) -> Option<usize> {
        self.frames.iter().position(|&f| f == frame)
    }

    /// Scene frame `frame`'s given pose as corrected so far (the given one if not corrected).
    pub fn pose(&self, skeleton: &Skeleton, frame: usize, given: &Pose) -> Pose {
        match self.row(frame) {
            Some(k) => {
                let values = &self.values[k];
                let shift = values.last().copied().unwrap_or_default().map(|v| v * self.lever);
                given.corrected(skeleton, &values[..values.len().saturating_sub(1)], shift)
            }
            None => given.clone(),
        }
    }

    /// Each bone's turn shared by every training frame: the mean of its corrections (rotation
    /// vectors in its parent's frame, a few degrees at most, where a mean of rotation vectors is
    /// the mean rotation to second order), kept in the measure that the frames agree on it
    /// (`SHARED_TURN_EVIDENCE`). The skeleton's shift is left out: it moves the body in the
    /// world, which a bone's content cannot trade against.
    pub fn shared_turns(&self) -> Vec<[f64; 3]> {
        shared_turns_of(&self.values)
    }

    /// `shared_turns` of the corrections a checkpoint keeps (`to_json`), whatever its frames.
    pub fn shared_turns_in(value: &serde_json::Value) -> Result<Vec<[f64; 3]>, String> {
        let values: Vec<Rows> = serde_json::from_value(value["values"].clone()).map_err(|e| format!("values: {e}"))?;
        let rows = values.first().map_or(0, |v| v.len());
        if values.iter().any(|v| v.len() != rows || v.iter().flatten().any(|c| !c.is_finite())) {
            return Err(format!("values: {rows} finite [x, y, z] per training frame"));
        }
        Ok(shared_turns_of(&values))
    }

    /// Corrected frame `k`'s correction as a leaf (`[bones + 1, 3]`) whose gradient a step
    /// reads back, and where its neighbours would have it for a smooth motion (the corrected
    /// motion's second difference there zero, to first order: half the neighbours' corrections
    /// plus the given motion's second difference; itself when it lacks a neighbour, which no
    /// term then moves), with how much the smoothness and the prior weigh on this capture.
    pub fn leaf_and_smooth(&self, k: usize, device: &Device) -> MotionInput {
        let values = &self.values[k];
        let rows = values.len();
        let smooth: Vec<f32> = match self.neighbours[k] {
            Some((before, after)) => (0..rows)
                .flat_map(|r| {
                    let (a, b, acc) = (self.values[before][r], self.values[after][r], self.acceleration[k][r]);
                    (0..3).map(move |c| ((a[c] + b[c] + acc[c]) / 2.0) as f32)
                })
                .collect(),
            None => values.iter().flatten().map(|&v| v as f32).collect(),
        };
        let leaf: Vec<f32> = values.iter().flatten().map(|&v| v as f32).collect();
        let leaf = Tensor::from_data(TensorData::new(leaf, [rows, 3]), device).require_grad();
        MotionInput {
            correction: leaf,
            smooth: Tensor::from_data(TensorData::new(smooth, [rows, 3]), device),
            smoothness_scale: self.smoothness_scale(),
            prior_scale: self.prior_scale(),
        }
    }

    /// One Adam step of `rate` on corrected frame `k`: `leaf` is the gradient of its leaf
    /// (`[bones + 1, 3]`), `increment` that of the increment the render carried (each bone's world
    /// turn about its head, then the world shift, m), `pose` the pose the step rendered.
    pub fn step(&mut self, k: usize, leaf: &[f32], increment: &[f32], pose: &Pose, rate: f64) {
        let rows = self.values[k].len();
        let fine = |g: &[f32]| g.len() == 3 * rows && g.iter().all(|v| v.is_finite());
        if !fine(leaf) || !(increment.is_empty() || fine(increment)) {
            return;
        }
        let row = |g: &[f32], r: usize| DVec3::new(g[3 * r] as f64, g[3 * r + 1] as f64, g[3 * r + 2] as f64);
        // A turn dv in a bone's own frame is a world turn R dv about its head: the world
        // gradient seen from the bone's frame is R^T g. The shift is in levers.
        let gradient: Vec<[f64; 3]> = (0..rows)
            .map(|r| {
                let through_render = match (increment.is_empty(), pose.bone_to_world.get(r)) {
                    (true, _) => DVec3::ZERO,
                    (false, Some(m)) => DMat3::from_mat4(*m).transpose() * row(increment, r),
                    (false, None) => row(increment, r) * self.lever,
                };
                (through_render + row(leaf, r)).to_array()
            })
            .collect();
        self.steps[k] += 1;
        super::host_adam::step(&mut self.values[k], &mut self.first[k], &mut self.second[k], &gradient, self.steps[k], rate);
    }

    /// How far the corrections moved the motion of `skeleton`.
    pub fn moved(&self, skeleton: &Skeleton) -> MotionMoved {
        let degrees = |b: usize| -> Vec<f64> { self.values.iter().filter_map(|v| v.get(b)).map(|t| DVec3::from_array(*t).length().to_degrees()).collect() };
        let turns: Vec<f64> = (0..skeleton.len()).flat_map(degrees).collect();
        let shifts: Vec<f64> = self.values.iter().map(|v| DVec3::from_array(*v.last().unwrap_or(&[0.0; 3])).length() * self.lever * 100.0).collect();
        let mean = |v: &[f64]| if v.is_empty() { 0.0 } else { v.iter().sum::<f64>() / v.len() as f64 };
        let largest = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        let shared: Vec<f64> = self.shared_turns().iter().map(|t| DVec3::from_array(*t).length().to_degrees()).collect();
        let bones = skeleton
            .bones
            .iter()
            .enumerate()
            .map(|(b, bone)| {
                let d = degrees(b);
                BoneMoved {
                    bone: bone.name.clone(),
                    mean_degrees: mean(&d),
                    largest_degrees: largest(&d),
                    shared_degrees: shared.get(b).copied().unwrap_or(0.0),
                }
            })
            .collect();
        MotionMoved {
            frames: self.frames.len(),
            mean_degrees: mean(&turns),
            largest_degrees: largest(&turns),
            mean_shift_cm: mean(&shifts),
            largest_shift_cm: largest(&shifts),
            shared_mean_degrees: mean(&shared),
            shared_largest_degrees: largest(&shared),
            given_noise_share: self.noise_share,
            smoothness_scale: self.smoothness_scale(),
            given_noise_degrees: self.noise.to_degrees(),
            prior_scale: self.prior_scale(),
            given_bias_degrees: super::motion_noise::bias(self.noise, self.frames.len()).to_degrees(),
            bones,
        }
    }

    /// The corrected training motion: each corrected scene frame, in time order, with its pose.
    pub fn refined(&self, scene: &Scene) -> Vec<(usize, Pose)> {
        self.frames.iter().map(|&f| (f, self.pose(&scene.skeleton, f, &scene.frames[f].pose))).collect()
    }

    /// The lever the skeleton's shift is measured in (m).
    pub fn lever(&self) -> f64 {
        self.lever
    }

    /// The scene frames corrected, in time order.
    pub fn frames(&self) -> &[usize] {
        &self.frames
    }

    /// The state a checkpoint keeps.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({"frames": self.frames, "values": self.values, "first": self.first, "second": self.second, "steps": self.steps})
    }

    /// The state from a checkpoint's `to_json`, refused when it is not this scene's frames.
    pub fn restore(&mut self, value: &serde_json::Value) -> Result<(), String> {
        let frames: Vec<usize> = serde_json::from_value(value["frames"].clone()).map_err(|e| format!("frames: {e}"))?;
        if frames != self.frames {
            return Err(format!("frames {frames:?}, the scene's training frames are {:?}", self.frames));
        }
        let rows = self.values.first().map_or(0, |v| v.len());
        let table = |key: &str| -> Result<Vec<Rows>, String> {
            let table: Vec<Rows> = serde_json::from_value(value[key].clone()).map_err(|e| format!("{key}: {e}"))?;
            match table.len() == frames.len() && table.iter().all(|t| t.len() == rows && t.iter().flatten().all(|v| v.is_finite())) {
                true => Ok(table),
                false => Err(format!("{key}: {rows} finite [x, y, z] per training frame")),
            }
        };
        let steps: Vec<u64> = serde_json::from_value(value["steps"].clone()).map_err(|e| format!("steps: {e}"))?;
        if steps.len() != frames.len() {
            return Err("steps: one per training frame".into());
        }
        self.values = table("values")?;
        self.first = table("first")?;
        self.second = table("second")?;
        self.steps = steps;
        Ok(())
    }
}

/// How far pose `a` is from pose `b`: each bone's rotation in its parent's frame (the root's in
/// the world) apart, in degrees, averaged over the bones; and the root's head apart (cm).
pub fn joint_error(skeleton: &Skeleton, a: &Pose, b: &Pose) -> (f64, f64) {
    let bones = skeleton.len().min(a.bone_to_world.len()).min(b.bone_to_world.len());
    if bones == 0 {
        return (0.0, 0.0);
    }
    let degrees: f64 = (0..bones).map(|k| turn_between(local_rotation(skeleton, a, k), local_rotation(skeleton, b, k)).length().to_degrees()).sum();
    let root = (a.bone_to_world[0].w_axis - b.bone_to_world[0].w_axis).truncate().length() * 100.0;
    (degrees / bones as f64, root)
}

/// Each bone's turn from `pairs`' first poses to their second (a rotation vector in its
/// parent's frame, radians), as its mean over the pairs and as each pair's turn less that mean:
/// what a motion's error shares over the frames, which an avatar's content can take up as well
/// as the motion (`docs/measurements.md`), and what each frame has of its own.
pub fn turns_between(skeleton: &Skeleton, pairs: &[(&Pose, &Pose)]) -> (Vec<DVec3>, Vec<Vec<DVec3>>) {
    let n = pairs.len().max(1) as f64;
    let turns: Vec<Vec<DVec3>> = pairs
        .iter()
        .map(|(a, b)| (0..skeleton.len()).map(|k| turn_between(local_rotation(skeleton, a, k), local_rotation(skeleton, b, k))).collect())
        .collect();
    let mean: Vec<DVec3> = (0..skeleton.len()).map(|k| turns.iter().map(|t| t[k]).sum::<DVec3>() / n).collect();
    let own = turns.iter().map(|t| t.iter().zip(&mean).map(|(t, m)| *t - *m).collect()).collect();
    (mean, own)
}

/// `MotionCorrections::shared_turns` of per-frame corrections `values` (bones, then the shift).
fn shared_turns_of(values: &[Rows]) -> Vec<[f64; 3]> {
    let bones = values.first().map_or(0, |v| v.len().saturating_sub(1));
    let n = values.len().max(1) as f64;
    (0..bones)
        .map(|b| {
            let turn = |v: &Rows| DVec3::from_array(v.get(b).copied().unwrap_or_default());
            let mean = values.iter().fold(DVec3::ZERO, |sum, v| sum + turn(v)) / n;
            // The mean's squared standard error: the frames' squared scatter about it over
            // their count, over their count again.
            let error = values.iter().map(|v| (turn(v) - mean).length_squared()).sum::<f64>() / (n * n);
            let keep = match mean.length_squared() {
                0.0 => 0.0,
                squared => (1.0 - SHARED_TURN_EVIDENCE * error / squared).max(0.0),
            };
            (mean * keep).to_array()
        })
        .collect()
}

/// `pose` as the fitted avatar is shown in it: each bone turned by `shared` (`shared_turns`,
/// one per bone; none: the pose as given).
pub fn shown_pose(skeleton: &Skeleton, pose: &Pose, shared: &[[f64; 3]]) -> Pose {
    match turns_any(shared) {
        true => pose.corrected(skeleton, shared, [0.0; 3]),
        false => pose.clone(),
    }
}

/// Whether `shared` turns any bone at all.
pub fn turns_any(shared: &[[f64; 3]]) -> bool {
    shared.iter().flatten().any(|&v| v != 0.0)
}

/// Every frame of `scene` posed as the fitted avatar is shown in it (`shown_pose`).
pub fn show_in(scene: &mut Scene, shared: &[[f64; 3]]) {
    for f in 0..scene.frames.len() {
        scene.frames[f].pose = shown_pose(&scene.skeleton, &scene.frames[f].pose, shared);
    }
}
