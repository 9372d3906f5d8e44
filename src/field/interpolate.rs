//! The grid's interpolation as one op with an analytic backward: the weighted sum of a planned
//! lookup's table rows, for the features and, when planned, their three spatial tangents.
//!
//! As a composite of tensor ops (`select` of `N x corners` rows, a product, a sum, and for the
//! tangents the same over three axes) a training step materialised `[N x corners, F]` and
//! `[3, N x corners, F]` intermediates and scatter-added as many rows in the backward. Here the
//! forward gathers on the host straight into `[N, W]` (plus `[3N, W]`), and the backward
//! scatters the output's gradient into the table once. A lookup nobody differentiates skips the
//! plan altogether (`grid_lookup`: skinning, corners and sums in one pass per point). The CPU
//! backends (flex, ndarray) run both on the host, flex lending its tensors' memory without a
//! copy; a GPU backend would get its own kernels behind the same trait.
// burn-ndarray is deprecated upstream but stays our `--backend ndarray`.
#![allow(deprecated)]

use super::host_lookup::add_row;
use super::layout::{GridConfig, Level};
use super::lookup::Skinning;
use crate::skeleton::BoneFrame;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{binary, unary, Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
#[cfg(feature = "gpu")]
use burn::backend::Cube;
use burn::backend::{backend_extension, Autodiff, AutodiffBackend, Backend, Dispatch, Flex, NdArray, TensorMetadata};
use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;
use std::sync::Arc;

/// A planned interpolation of `points` points: per point and level, `corners` table rows with
/// their coefficients (point-major, then level, then corner) and, when the tangents are
/// wanted, each coefficient's derivative along the three world axes; `fade` weighs each level
/// (coarse to fine).
#[derive(Debug)]
pub struct Plan {
    pub points: usize,
    pub levels: usize,
    pub corners: usize,
    pub features: usize,
    pub rows: Vec<u32>,
    pub coefficients: Vec<f32>,
    pub tangents: Option<Vec<f32>>,
    /// What the coefficients' world derivatives follow from when the lookup carries a shift of
    /// its points (`interpolate_carrying`): only the shift's gradient reads it.
    pub carried: Option<Carried>,
    pub fade: Vec<f32>,
    /// The table's rows are this many equal runs, group `g`'s rows lying in run
    /// `g % table_parts` (the grid's table is level-major: its level count; 1 for any table).
    pub table_parts: usize,
}

/// A carried lookup's cells, from which each corner coefficient's world derivative follows: a
/// group is a (slot, level) pair (`groups = slots x levels`, slot-major), a slot one of the
/// point's chosen bones. Per cell (point, group) the point's fractions along the slot's bone's
/// local axes, plus 2 on an axis outside the grid (no derivative there); per point and slot the
/// bone's local axes in the world (row-major 3 x 3: row m is axis m); per level 1 / its cell
/// size. 3 floats a cell against the 24 of per-corner derivatives.
#[derive(Debug)]
pub struct Carried {
    /// Chosen bones per point, and levels per bone: `slots x levels` groups.
    pub slots: usize,
    pub levels: usize,
    pub fractions: Vec<f32>,
    pub axes: Vec<f32>,
    pub per_cell: Vec<f32>,
}

/// Corner `k`'s (bit 0 the x side, bit 1 y, bit 2 z) trilinear weight's derivatives along the
/// cell's three fractions `f`.
fn corner_slopes(f: [f32; 3], k: usize) -> [f32; 3] {
    let bit = [k & 1, (k >> 1) & 1, k >> 2];
    let factor = [0, 1, 2].map(|m| if bit[m] == 1 { f[m] } else { 1.0 - f[m] });
    [0, 1, 2].map(|m| {
        let sign = if bit[m] == 1 { 1.0 } else { -1.0 };
        sign * factor[(m + 1) % 3] * factor[(m + 2) % 3]
    })
}

impl Carried {
    /// Cell `(point, group)`'s fractions, and the derivative of each fraction along the world
    /// (row m: the slot's bone's axis m over the level's cell size; zero outside the grid).
    fn cell(&self, point: usize, group: usize) -> ([f32; 3], [[f32; 3]; 3]) {
        let cell = point * self.slots * self.levels + group;
        let raw = [0, 1, 2].map(|m| self.fractions.get(cell * 3 + m).copied().unwrap_or(f32::NAN));
        let (slot, level) = (group / self.levels, group % self.levels);
        let at = (point * self.slots + slot) * 9;
        let scale = self.per_cell.get(level).copied().unwrap_or(f32::NAN);
        let rows = [0, 1, 2].map(|m| match raw[m] < 2.0 {
            true => [0, 1, 2].map(|x| self.axes.get(at + m * 3 + x).copied().unwrap_or(f32::NAN) * scale),
            false => [0.0; 3],
        });
        (raw.map(|v| if v < 2.0 { v } else { v - 2.0 }), rows)
    }

    /// Each corner coefficient's world derivative (`[P, 3]`, as `Plan::tangents`): what a device
    /// multiplies out where the host contracts the corners first (`Plan::shift_backward`).
    pub fn per_corner(&self, plan: &Plan) -> Vec<f32> {
        let mut out = vec![0.0f32; plan.rows.len() * 3];
        for i in 0..plan.points {
            for g in 0..plan.levels {
                let (f, rows) = self.cell(i, g);
                for k in 0..plan.corners {
                    let slopes = corner_slopes(f, k);
                    let at = ((i * plan.levels + g) * plan.corners + k) * 3;
                    for x in 0..3 {
                        out[at + x] = (0..3).map(|m| slopes[m] * rows[m][x]).sum();
                    }
                }
            }
        }
        out
    }
}

impl Plan {
    /// Output rows: the features, then the tangents axis-major when planned.
    pub fn output_rows(&self) -> usize {
        self.points * self.blocks()
    }

    /// Output blocks of `points` rows: the features, and the three tangents when planned.
    pub fn blocks(&self) -> usize {
        if self.tangents.is_some() {
            4
        } else {
            1
        }
    }

    fn width(&self) -> usize {
        self.levels * self.features
    }

    /// The weighted sums (`[output_rows, W]`, row-major) of `table` (`[T, F]`, row-major).
    fn forward(&self, table: &[f32]) -> Vec<f32> {
        let (n, w, c) = (self.points, self.width(), self.corners);
        let mut out = vec![0.0f32; self.output_rows() * w];
        let (values, tangents) = out.split_at_mut(n * w);
        // Points in chunks across threads: each point owns its output rows.
        const CHUNK: usize = 256;
        let tangent_chunks: Vec<&mut [f32]> = match self.tangents {
            Some(_) => tangents.chunks_mut(n * w).collect(),
            None => Vec::new(),
        };
        let per_point = self.levels * c;
        values.par_chunks_mut(CHUNK * w).enumerate().for_each(|(chunk, values)| {
            for (k, row_out) in values.chunks_mut(w).enumerate() {
                let i = chunk * CHUNK + k;
                let rows = &self.rows[i * per_point..(i + 1) * per_point];
                let coefficients = &self.coefficients[i * per_point..(i + 1) * per_point];
                self.accumulate(table, rows, coefficients.iter().copied(), row_out);
            }
        });
        if let Some(d) = &self.tangents {
            // One axis per task: each writes its own `[N, W]` block.
            tangent_chunks.into_par_iter().enumerate().for_each(|(axis, block)| {
                for (i, row_out) in block.chunks_mut(w).enumerate() {
                    let rows = &self.rows[i * per_point..(i + 1) * per_point];
                    let d = &d[i * per_point * 3..(i + 1) * per_point * 3];
                    self.accumulate(table, rows, d.iter().skip(axis).step_by(3).copied(), row_out);
                }
            });
        }
        out
    }

    /// One point's weighted sum into `row_out` (`[W]`): level by level, each of its corners'
    /// table rows (`rows`, `levels x corners`) times its coefficient and the level's fade. A row
    /// outside the table (never planned) reads NaN, so it cannot pass unseen.
    fn accumulate(&self, table: &[f32], rows: &[u32], coefficients: impl Iterator<Item = f32>, row_out: &mut [f32]) {
        let (f, c) = (self.features, self.corners);
        let mut coefficients = coefficients;
        for ((out, level_rows), &fade) in row_out.chunks_mut(f).zip(rows.chunks(c)).zip(&self.fade) {
            for &row in level_rows {
                add_row(table, row as usize, coefficients.next().unwrap_or(0.0) * fade, out);
            }
        }
    }

    /// The table's gradient (`[table_rows, F]`) from the output's (`[output_rows, W]`). The
    /// table's rows are level-major (`table_parts` runs), so each thread takes a run of
    /// consecutive levels and fills their rows alone: no per-thread copies of the table to zero
    /// and add up (4-8 MB each, a quarter of this op's time).
    fn backward(&self, grad: &[f32], table_rows: usize) -> Vec<f32> {
        let (n, w, f, c) = (self.points, self.width(), self.features, self.corners);
        let parts = self.table_parts.max(1);
        let part_rows = table_rows / parts;
        let tasks = rayon::current_num_threads().clamp(1, parts);
        // Task t's levels, and the slice of the table holding their rows.
        let levels_of = |t: usize| (t * parts / tasks)..((t + 1) * parts / tasks);
        let mut total = vec![0.0f32; table_rows * f];
        let mut slices = Vec::with_capacity(tasks);
        let mut rest = total.as_mut_slice();
        for t in 0..tasks {
            let take = if t + 1 == tasks { rest.len() } else { levels_of(t).len() * part_rows * f };
            let (slice, tail) = rest.split_at_mut(take);
            slices.push(slice);
            rest = tail;
        }
        slices.into_par_iter().enumerate().for_each(|(t, values)| {
            let levels = levels_of(t);
            let (first, count) = (levels.start * part_rows, values.len() / f);
            let groups: Vec<usize> = (0..self.levels).filter(|g| levels.contains(&(g % parts))).collect();
            for i in 0..n {
                for &g in &groups {
                    let fade = self.fade[g];
                    for j in 0..c {
                        let at = (i * self.levels + g) * c + j;
                        // A row outside this task's run (or the table) is a level left out of
                        // the plan: row 0, coefficient 0, nothing to add.
                        let Some(row) = (self.rows[at] as usize).checked_sub(first).filter(|&r| r < count) else { continue };
                        for q in 0..f {
                            let column = g * f + q;
                            let mut sum = self.coefficients[at] * grad[i * w + column];
                            if let Some(d) = &self.tangents {
                                for axis in 0..3 {
                                    sum += d[at * 3 + axis] * grad[(n + axis * n + i) * w + column];
                                }
                            }
                            values[row * f + q] += sum * fade;
                        }
                    }
                }
            }
        });
        total
    }
}

impl Plan {
    /// The gradient (`[N, 3]`, row-major) of a shift of the points, to first order, from the
    /// output's (`[N, W]`): per point, each corner's table row against the output's gradient,
    /// times the level's fade and the coefficient's world derivative, contracted per cell along
    /// its fractions before it is turned into the world (`Carried`).
    fn shift_backward(&self, grad: &[f32], table: &[f32]) -> Vec<f32> {
        let (w, f, c) = (self.width(), self.features, self.corners);
        let Some(carried) = &self.carried else { return vec![0.0; 3 * self.points] };
        let per_point = self.levels * c;
        let mut out = vec![0.0f32; 3 * self.points];
        // Points in chunks across threads: each point owns its three values.
        const CHUNK: usize = 256;
        out.par_chunks_mut(3 * CHUNK).enumerate().for_each(|(chunk, shifts)| {
            for (k, shift) in shifts.chunks_mut(3).enumerate() {
                let i = chunk * CHUNK + k;
                for g in 0..self.levels {
                    let fade = self.fade[g];
                    let grad = &grad[i * w + g * f..i * w + (g + 1) * f];
                    // A level faded out, or one whose output nothing weighs, moves nothing.
                    if fade == 0.0 || grad.iter().all(|&v| v == 0.0) {
                        continue;
                    }
                    // The corners contracted along the cell's fractions first, then turned
                    // into the world once per cell.
                    let (fractions, rows) = carried.cell(i, g);
                    let mut along_fractions = [0.0f32; 3];
                    for j in 0..c {
                        let row = self.rows[i * per_point + g * c + j] as usize;
                        let along: f32 = match table.get(row * f..(row + 1) * f) {
                            Some(entry) => entry.iter().zip(grad).map(|(t, g)| t * g).sum(),
                            None => f32::NAN,
                        };
                        let slopes = corner_slopes(fractions, j);
                        for m in 0..3 {
                            along_fractions[m] += along * slopes[m];
                        }
                    }
                    for (axis, s) in shift.iter_mut().enumerate() {
                        *s += fade * (0..3).map(|m| along_fractions[m] * rows[m][axis]).sum::<f32>();
                    }
                }
            }
        });
        out
    }
}

/// A float tensor's values on the host (NaN-filled if the backend cannot give them, which the
/// fit then reports as a non-finite loss rather than a panic).
fn host<B: Backend>(tensor: FloatTensor<B>) -> Vec<f32> {
    let count = tensor.shape().num_elements();
    burn::tensor::try_read_sync(B::float_into_data(tensor))
        .and_then(|r| r.ok())
        .and_then(|data| data.convert::<f32>().try_into_vec::<f32>().ok())
        .unwrap_or_else(|| vec![f32::NAN; count])
}

/// Host access to a backend's float tensors: `with_host` lends a tensor's values as a slice,
/// without a copy where the backend keeps them on the host in order (flex's contiguous f32
/// tensors: the feature table, 4-8 MB, was copied once per lookup, a tenth of a training step).
pub(super) trait HostValues: Backend {
    fn with_host<R>(tensor: FloatTensor<Self>, f: impl FnOnce(&[f32]) -> R) -> R {
        f(&host::<Self>(tensor))
    }

    fn from_host(values: Vec<f32>, shape: [usize; 2], device: &Self::Device) -> FloatTensor<Self> {
        Self::float_from_data(TensorData::new(values, shape), device)
    }
}

impl HostValues for NdArray {}

/// The lookup without gradients brings the device's table down and its features up.
#[cfg(feature = "gpu")]
impl HostValues for Cube {}

impl HostValues for Flex {
    fn with_host<R>(tensor: FloatTensor<Self>, f: impl FnOnce(&[f32]) -> R) -> R {
        match tensor.as_slice::<f32>() {
            Some(values) => f(values),
            None => f(&host::<Self>(tensor)),
        }
    }
}

fn forward_on_host<B: HostValues>(table: FloatTensor<B>, plan: &Plan) -> FloatTensor<B> {
    let device = table.device();
    let values = B::with_host(table, |table| plan.forward(table));
    B::from_host(values, [plan.output_rows(), plan.width()], &device)
}

fn backward_on_host<B: HostValues>(grad: FloatTensor<B>, plan: &Plan, table_rows: usize) -> FloatTensor<B> {
    let device = grad.device();
    let values = B::with_host(grad, |grad| plan.backward(grad, table_rows));
    B::from_host(values, [table_rows, plan.features], &device)
}

fn shift_backward_on_host<B: HostValues>(grad: FloatTensor<B>, table: FloatTensor<B>, plan: &Plan) -> FloatTensor<B> {
    let device = grad.device();
    let values = B::with_host(grad, |grad| B::with_host(table, |table| plan.shift_backward(grad, table)));
    B::from_host(values, [plan.points, 3], &device)
}

/// A lookup with no gradients wanted (`grid::features_on_host`): the points, the posed bones and
/// the grid's layout.
#[derive(Debug)]
pub struct HostLookup {
    pub config: GridConfig,
    pub levels: Vec<Level>,
    pub frames: Vec<BoneFrame>,
    pub skinning: Skinning,
    pub points: Vec<f32>,
    pub fade: Vec<f32>,
    /// Whether `preference` is the root's preference grid (otherwise a placeholder).
    pub preference: bool,
}

impl HostLookup {
    pub(super) fn run<B: HostValues>(&self, table: FloatTensor<B>, preference: FloatTensor<B>) -> FloatTensor<B> {
        let device = table.device();
        let n = self.points.len() / 3;
        let values = B::with_host(table, |table| {
            B::with_host(preference, |preference| {
                let preference = self.preference.then_some(preference);
                super::host_lookup::features_on_host(&self.config, &self.levels, &self.frames, self.skinning, &self.points, table, preference, &self.fade)
            })
        });
        B::from_host(values, [n, self.config.width() + 1], &device)
    }
}

/// The interpolation op; `Autodiff` adds its analytic backward.
#[backend_extension(Flex, NdArray, Cube: cfg(feature = "gpu"), Autodiff)]
pub trait GridOps: Backend {
    /// `[output_rows, levels x features]`: the plan's weighted sums of `table`'s rows.
    fn grid_interpolate(table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self>;
    /// `[table_rows, features]`: the table's gradient from the interpolation's (`grad`).
    fn grid_interpolate_backward(grad: FloatTensor<Self>, plan: Arc<Plan>, table_rows: usize) -> FloatTensor<Self>;
    /// `[N, levels x features + 1]`: the features and the prior of a lookup with no gradients,
    /// straight from `table` and the root's `preference` grid.
    fn grid_lookup(table: FloatTensor<Self>, preference: FloatTensor<Self>, lookup: Arc<HostLookup>) -> FloatTensor<Self>;
    /// `grid_interpolate` of points that carry a zero-valued `shift` (`[N, 3]`): the same values,
    /// with a gradient to the shift (`grid_shift_backward`) as well as to the table.
    fn grid_interpolate_carrying(table: FloatTensor<Self>, shift: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self>;
    /// `[N, 3]`: the shift's gradient from the interpolation's (`grad`) and the `table`.
    fn grid_shift_backward(grad: FloatTensor<Self>, table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self>;
}

/// `GridOps` for `$backend` by its `forward`, `backward` and `shift_backward` (the host's here,
/// the device's in `on_device`); the lookup without gradients runs on the host.
macro_rules! grid_ops {
    ($backend:ty, $forward:path, $backward:path, $shift_backward:path) => {
        impl $crate::field::interpolate::GridOps for $backend {
            fn grid_interpolate(table: FloatTensor<Self>, plan: std::sync::Arc<Plan>) -> FloatTensor<Self> {
                $forward(table, &plan)
            }

            fn grid_interpolate_carrying(table: FloatTensor<Self>, _shift: FloatTensor<Self>, plan: std::sync::Arc<Plan>) -> FloatTensor<Self> {
                $forward(table, &plan)
            }

            fn grid_shift_backward(grad: FloatTensor<Self>, table: FloatTensor<Self>, plan: std::sync::Arc<Plan>) -> FloatTensor<Self> {
                $shift_backward(grad, table, &plan)
            }

            fn grid_interpolate_backward(grad: FloatTensor<Self>, plan: std::sync::Arc<Plan>, table_rows: usize) -> FloatTensor<Self> {
                $backward(grad, &plan, table_rows)
            }

            fn grid_lookup(
                table: FloatTensor<Self>,
                preference: FloatTensor<Self>,
                lookup: std::sync::Arc<$crate::field::interpolate::HostLookup>,
            ) -> FloatTensor<Self> {
                lookup.run::<Self>(table, preference)
            }
        }
    };
}
// Used by `on_device` in the GPU build.
#[cfg_attr(not(feature = "gpu"), allow(unused_imports))]
pub(super) use grid_ops;

grid_ops!(Flex, forward_on_host::<Flex>, backward_on_host::<Flex>, shift_backward_on_host::<Flex>);
grid_ops!(NdArray, forward_on_host::<NdArray>, backward_on_host::<NdArray>, shift_backward_on_host::<NdArray>);

#[derive(Debug)]
struct Interpolate;

impl<B: Backend + GridOps> Backward<B, 1> for Interpolate {
    /// The plan and the table's row count.
    type State = (Arc<Plan>, usize);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let (plan, table_rows) = ops.state;
        unary::<B, _>(ops.parents, ops.node, grads, |grad| B::grid_interpolate_backward(grad, plan, table_rows));
    }
}

#[derive(Debug)]
struct Carry;

impl<B: Backend + GridOps> Backward<B, 2> for Carry {
    /// The plan, the table's row count and the table's values.
    type State = (Arc<Plan>, usize, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let (plan, table_rows, table) = ops.state;
        let shift_plan = plan.clone();
        binary::<B, _, _>(
            ops.parents,
            ops.node,
            grads,
            |grad| B::grid_interpolate_backward(grad, plan, table_rows),
            |grad| B::grid_shift_backward(grad, table, shift_plan),
        );
    }
}

impl<B: Backend + GridOps, C: CheckpointStrategy> GridOps for Autodiff<B, C> {
    fn grid_interpolate_carrying(table: FloatTensor<Self>, shift: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self> {
        let table_rows = table.shape()[0];
        let (table_node, shift_node) = (table.node(), shift.node());
        let inner = table.into_primitive();
        let out = B::grid_interpolate(inner.clone(), plan.clone());
        match Carry.prepare::<C>([table_node, shift_node]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish((plan, table_rows, inner), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    /// Not itself differentiated (the carrying interpolation's backward calls it on the inner
    /// backend).
    fn grid_shift_backward(grad: FloatTensor<Self>, table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self> {
        let (grad, table) = (<Self as AutodiffBackend>::inner(grad), <Self as AutodiffBackend>::inner(table));
        <Self as AutodiffBackend>::from_inner(B::grid_shift_backward(grad, table, plan))
    }

    fn grid_interpolate(table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self> {
        let table_rows = table.shape()[0];
        let node = table.node();
        let out = B::grid_interpolate(table.into_primitive(), plan.clone());
        match Interpolate.prepare::<C>([node]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish((plan, table_rows), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    /// Not itself differentiated (the interpolation's backward calls it on the inner backend).
    fn grid_interpolate_backward(grad: FloatTensor<Self>, plan: Arc<Plan>, table_rows: usize) -> FloatTensor<Self> {
        <Self as AutodiffBackend>::from_inner(B::grid_interpolate_backward(<Self as AutodiffBackend>::inner(grad), plan, table_rows))
    }

    /// A constant of the graph: only asked for where no gradient is wanted.
    fn grid_lookup(table: FloatTensor<Self>, preference: FloatTensor<Self>, lookup: Arc<HostLookup>) -> FloatTensor<Self> {
        let (table, preference) = (<Self as AutodiffBackend>::inner(table), <Self as AutodiffBackend>::inner(preference));
        <Self as AutodiffBackend>::from_inner(B::grid_lookup(table, preference, lookup))
    }
}

/// Interpolates `table` (`[T, F]`) by `plan`: `[output_rows, levels x features]`, with
/// gradients to the table when it is tracked.
pub fn interpolate(table: Tensor<2>, plan: Plan) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as GridOps>::grid_interpolate(table.into_dispatch(), Arc::new(plan)))
}

/// `interpolate` of points that carry `shift` (`[N, 3]`, zero in value): the same values, with
/// the gradient to the shift as well (the plan's `carried` coefficient derivatives).
pub fn interpolate_carrying(table: Tensor<2>, shift: Tensor<2>, plan: Plan) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as GridOps>::grid_interpolate_carrying(table.into_dispatch(), shift.into_dispatch(), Arc::new(plan)))
}

/// The features and prior (`[N, W + 1]`) of `lookup`'s points from `table` and the root's
/// `preference` grid (any tensor when `lookup.preference` is false), without gradients.
pub fn lookup_without_gradients(table: Tensor<2>, preference: Tensor<2>, lookup: HostLookup) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as GridOps>::grid_lookup(table.into_dispatch(), preference.into_dispatch(), Arc::new(lookup)))
}
