//! Adam on a few numbers kept on the host, in rows of three with their moments: the cameras'
//! colours and turns (`camera_colour`, `camera_pose`: `CameraRows`, a row per training camera)
//! and the motion's corrections (`motion`), too small to be worth a parameter group on the
//! device; their gradients brought to the host with the step's check after its update, all in
//! one read (`PendingGradients`), and the step of each (`Trainer::step_host_leaves`).

use super::{Batch, TrainState};
use burn::tensor::Tensor;

/// Adam's decay rates (burn's defaults; `fused_adam` takes them too) and its guard against a
/// zero second moment.
pub(super) const BETAS: (f64, f64) = (0.9, 0.999);
const EPSILON: f64 = 1e-8;

/// Step `t` (from 1) of Adam at `rate` on `values`, with `gradient` and the moments `first` and
/// `second` (all one row per value row).
pub fn step(values: &mut [[f64; 3]], first: &mut [[f64; 3]], second: &mut [[f64; 3]], gradient: &[[f64; 3]], t: u64, rate: f64) {
    let (b1, b2) = BETAS;
    let t = t.min(i32::MAX as u64) as i32;
    let (c1, c2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
    for (((value, m), v), g) in values.iter_mut().zip(first.iter_mut()).zip(second.iter_mut()).zip(gradient) {
        for c in 0..3 {
            m[c] = b1 * m[c] + (1.0 - b1) * g[c];
            v[c] = b2 * v[c] + (1.0 - b2) * g[c] * g[c];
            value[c] -= rate * (m[c] / c1) / ((v[c] / c2).sqrt() + EPSILON);
        }
    }
}

/// A row of three numbers per training camera with their Adam moments: the cameras' colours
/// (`camera_colour`) and turns (`camera_pose`), kept by a checkpoint under the cameras they
/// belong to.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraRows {
    /// Per scene camera, its row (none for a camera without training images).
    rows: Vec<Option<usize>>,
    /// Per row, its scene camera.
    cameras: Vec<usize>,
    pub values: Vec<[f64; 3]>,
    first: Vec<[f64; 3]>,
    second: Vec<[f64; 3]>,
    steps: u64,
}

impl CameraRows {
    /// Zeros for each camera of the scene's training images, in their first image's order; none
    /// for fewer than two (one camera has nothing to be told apart from).
    pub fn of_training_cameras(scene: &crate::scene::Scene) -> Option<Self> {
        let mut rows = vec![None; scene.cameras.len()];
        let mut cameras = Vec::new();
        for view in scene.views.iter().filter(|v| v.split == crate::scene::Split::Train) {
            if rows.get(view.camera).is_some_and(|r| r.is_none()) {
                rows[view.camera] = Some(cameras.len());
                cameras.push(view.camera);
            }
        }
        (cameras.len() >= 2).then(|| Self::zeros(rows, cameras))
    }

    /// Zeros for `cameras`, scene camera `c`'s row `rows[c]`.
    pub fn zeros(rows: Vec<Option<usize>>, cameras: Vec<usize>) -> Self {
        let zeros = vec![[0.0; 3]; cameras.len()];
        Self { rows, cameras, values: zeros.clone(), first: zeros.clone(), second: zeros, steps: 0 }
    }

    /// Scene camera `camera`'s row, if it has one.
    pub fn row(&self, camera: usize) -> Option<usize> {
        self.rows.get(camera).copied().flatten()
    }

    /// The scene cameras, one per row.
    pub fn cameras(&self) -> &[usize] {
        &self.cameras
    }

    /// The Adam steps taken.
    #[cfg(test)]
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// One Adam step of `rate` on `gradient` (`[cameras, 3]`, row-major); none when it is not
    /// one finite row per camera.
    pub fn step(&mut self, gradient: &[f32], rate: f64) {
        if gradient.len() != 3 * self.cameras.len() || gradient.iter().any(|g| !g.is_finite()) {
            return;
        }
        self.steps += 1;
        let rows: Vec<[f64; 3]> = gradient.chunks(3).map(|g| [g[0] as f64, g[1] as f64, g[2] as f64]).collect();
        step(&mut self.values, &mut self.first, &mut self.second, &rows, self.steps, rate);
    }

    /// The state a checkpoint keeps, the values under `key`.
    pub fn to_json(&self, key: &str) -> serde_json::Value {
        serde_json::json!({"cameras": self.cameras, key: self.values, "first": self.first, "second": self.second, "steps": self.steps})
    }

    /// The state from `to_json(key)`'s output, refused when it is not of these cameras.
    pub fn restore(&mut self, value: &serde_json::Value, key: &str) -> Result<(), String> {
        let cameras: Vec<usize> = serde_json::from_value(value["cameras"].clone()).map_err(|e| format!("cameras: {e}"))?;
        if cameras != self.cameras {
            return Err(format!("cameras {cameras:?}, the scene's training cameras are {:?}", self.cameras));
        }
        let rows = |key: &str| -> Result<Vec<[f64; 3]>, String> {
            let rows: Vec<[f64; 3]> = serde_json::from_value(value[key].clone()).map_err(|e| format!("{key}: {e}"))?;
            match rows.len() == cameras.len() && rows.iter().flatten().all(|v| v.is_finite()) {
                true => Ok(rows),
                false => Err(format!("{key}: one finite [x, y, z] per camera")),
            }
        };
        self.values = rows(key)?;
        self.first = rows("first")?;
        self.second = rows("second")?;
        self.steps = value["steps"].as_u64().ok_or("steps: missing")?;
        Ok(())
    }
}

/// The gradients of some leaves, still on the device, to come down in one copy with whatever
/// else the step reads (a GPU waits on every read): per leaf its length, none where the
/// backward pass did not reach it.
pub struct PendingGradients {
    lengths: Vec<Option<usize>>,
    parts: Vec<Tensor<1>>,
}

impl PendingGradients {
    pub fn of(leaves: &[&Tensor<2>], grads: &burn::tensor::Gradients) -> Self {
        let found: Vec<Option<Tensor<1>>> = leaves
            .iter()
            .map(|t| {
                t.grad(grads).map(|g| {
                    let n = g.shape().num_elements();
                    g.reshape([n])
                })
            })
            .collect();
        let lengths = found.iter().map(|g| g.as_ref().map(|g| g.dims()[0])).collect();
        Self { lengths, parts: found.into_iter().flatten().collect() }
    }

    /// The reached gradients end to end (`[sum of lengths]`), or none when none was reached.
    pub fn joined(&self) -> Option<Tensor<1>> {
        (!self.parts.is_empty()).then(|| Tensor::cat(self.parts.clone(), 0))
    }

    /// Per leaf its gradient from `values`, `joined`'s values read (NaN where too few).
    pub fn split(&self, values: &[f32]) -> Vec<Option<Vec<f32>>> {
        let mut at = 0;
        self.lengths
            .iter()
            .map(|n| {
                n.map(|n| {
                    let part = values.get(at..at + n).map_or_else(|| vec![f32::NAN; n], <[f32]>::to_vec);
                    at += n;
                    part
                })
            })
            .collect()
    }
}

/// A leaf's gradient (zeros where it has none) and the sum of its increments' (zeros where
/// none was reached), from `read`, their gradients in `host_gradients`' order.
pub fn leaf_and_increments(rows: usize, read: &mut impl Iterator<Item = Option<Vec<f32>>>, increments: usize) -> (Vec<f32>, Vec<f32>) {
    let leaf = read.next().flatten().unwrap_or_else(|| vec![0.0; rows]);
    let mut through_render = vec![0.0f32; rows];
    for g in read.take(increments).flatten() {
        through_render.iter_mut().zip(g).for_each(|(a, b)| *a += b);
    }
    (leaf, through_render)
}

/// The motion's leaves of a step: the corrected frame, its correction's leaf and the
/// increments the render carried.
pub(super) type MotionLeaves = (usize, Tensor<2>, Vec<Tensor<2>>);

/// The cameras' leaves of a step: their corrections' leaf and the increments the render carried.
pub(super) type CameraLeaves = (Tensor<2>, Vec<Tensor<2>>);

/// The host-side leaves a step's backward pass fills: the motion's and the cameras'.
#[derive(Default)]
pub(super) struct Leaves {
    pub(super) motion: Option<MotionLeaves>,
    pub(super) cameras: Option<CameraLeaves>,
}

/// The leaves the host's Adam steps after a step (`Trainer::step_host_leaves`), their gradients
/// pending on the device: the cameras' colours when fitted, the batch frame's motion correction
/// (its frame's row, the leaf's values, how many increments its render parts carried) and the
/// cameras' turns (the leaf's values, its increments).
pub(super) struct HostLeaves {
    colours: bool,
    motion: Option<(usize, usize, usize)>,
    cameras: Option<(usize, usize)>,
    pub(super) pending: PendingGradients,
}

impl HostLeaves {
    pub(super) fn of(colour_leaf: Option<Tensor<2>>, leaves: Leaves, grads: &burn::tensor::Gradients) -> Self {
        let motion = leaves.motion.as_ref().map(|(k, leaf, increments)| (*k, leaf.dims()[0] * 3, increments.len()));
        let cameras = leaves.cameras.as_ref().map(|(leaf, increments)| (leaf.dims()[0] * 3, increments.len()));
        let wanted: Vec<&Tensor<2>> = colour_leaf
            .iter()
            .chain(leaves.motion.iter().flat_map(|(_, leaf, increments)| std::iter::once(leaf).chain(increments)))
            .chain(leaves.cameras.iter().flat_map(|(leaf, increments)| std::iter::once(leaf).chain(increments)))
            .collect();
        Self { colours: colour_leaf.is_some(), motion, cameras, pending: PendingGradients::of(&wanted, grads) }
    }
}

impl super::Trainer {
    /// One host-side Adam step of each of the cameras' colours, the batch frame's motion
    /// correction and the cameras' turns that the step carried, from their gradients
    /// (`gradients`, per leaf of `leaves` in `HostLeaves::of`'s order).
    pub(super) fn step_host_leaves(&self, leaves: &HostLeaves, gradients: Vec<Option<Vec<f32>>>, state: &mut TrainState, batch: &Batch, it: usize) {
        let mut read = gradients.into_iter();
        if leaves.colours {
            if let (Some(gradient), Some(colours)) = (read.next().flatten(), state.camera_colours.as_mut()) {
                colours.step(&gradient, self.schedule.learning_rate("light", it));
            }
        }
        if let Some((k, rows, increments)) = leaves.motion {
            let (leaf, through_render) = leaf_and_increments(rows, &mut read, increments);
            if let (Some(motion), Some((pose, _))) = (state.motion.as_mut(), batch.corrected.as_ref()) {
                motion.step(k, &leaf, &through_render, pose, self.schedule.learning_rate("motion", it));
            }
        }
        if let Some((rows, increments)) = leaves.cameras {
            let (leaf, through_render) = leaf_and_increments(rows, &mut read, increments);
            if let Some(cameras) = state.cameras.as_mut() {
                cameras.step(&leaf, &through_render, self.schedule.learning_rate("cameras", it));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{leaf_and_increments, PendingGradients};
    use burn::tensor::{Device, Tensor, TensorData};

    #[test]
    fn the_host_gradients_wait_to_come_down_in_one_read_each_leaf_its_own() {
        let device = Device::flex().autodiff();
        let leaf = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, [2, 3]), &device).require_grad();
        let (a, unreached, c, d) = (leaf(vec![1.0; 6]), leaf(vec![2.0; 6]), leaf(vec![0.5; 6]), leaf(vec![-1.0; 6]));
        // d(sum 2a + sum 3c^2 + sum d) = 2, 6c = 3, 1.
        let loss = (a.clone() * 2.0).sum() + (c.clone() * c.clone() * 3.0).sum() + d.clone().sum();
        let grads = loss.backward();
        let before = crate::backend::reads_to_host();
        let pending = PendingGradients::of(&[&a, &unreached, &c, &d], &grads);
        assert_eq!(crate::backend::reads_to_host(), before, "nothing read until asked");
        let read = pending.split(&crate::backend::host_values(pending.joined().unwrap()));
        assert_eq!(crate::backend::reads_to_host() - before, 1, "one read for every leaf");
        assert_eq!(read, vec![Some(vec![2.0; 6]), None, Some(vec![3.0; 6]), Some(vec![1.0; 6])]);
        // A leaf and its increments: the unreached one counts as zeros.
        let mut parts = read.into_iter();
        let (first, through) = leaf_and_increments(6, &mut parts, 2);
        assert_eq!((first, through), (vec![2.0; 6], vec![3.0; 6]));
        let (first, through) = leaf_and_increments(6, &mut parts, 0);
        assert_eq!((first, through), (vec![1.0; 6], vec![0.0; 6]));
        // Nothing reached: no read at all.
        let before = crate::backend::reads_to_host();
        let pending = PendingGradients::of(&[&unreached], &grads);
        assert!(pending.joined().is_none());
        assert_eq!(pending.split(&[]), vec![None]);
        assert_eq!(crate::backend::reads_to_host(), before);
    }
}
