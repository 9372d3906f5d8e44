//! The grid's interpolation as one op with an analytic backward: the weighted sum of a planned
//! lookup's table rows, for the features and, when planned, their three spatial tangents.
//!
//! As a composite of tensor ops (`select` of `N x corners` rows, a product, a sum, and for the
//! tangents the same over three axes) a training step materialised `[N x corners, F]` and
//! `[3, N x corners, F]` intermediates and scatter-added as many rows in the backward. Here the
//! forward gathers on the host straight into `[N, W]` (plus `[3N, W]`), and the backward
//! scatters the output's gradient into the table once. The CPU backends (flex, ndarray) run it
//! on the host; a GPU backend would get its own kernel behind the same trait.
// burn-ndarray is deprecated upstream but stays our `--backend ndarray`.
#![allow(deprecated)]

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{unary, Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Autodiff, Backend, Dispatch, Flex, NdArray, TensorMetadata};
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
    pub fade: Vec<f32>,
}

impl Plan {
    /// Output rows: the features, then the tangents axis-major when planned.
    pub fn output_rows(&self) -> usize {
        self.points * if self.tangents.is_some() { 4 } else { 1 }
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
                let coefficient = coefficients.next().unwrap_or(0.0) * fade;
                let start = row as usize * f;
                match table.get(start..start + f) {
                    Some(entry) => out.iter_mut().zip(entry).for_each(|(o, t)| *o += coefficient * t),
                    None => out.iter_mut().for_each(|o| *o = f32::NAN),
                }
            }
        }
    }

    /// The table's gradient (`[table_rows, F]`) from the output's (`[output_rows, W]`).
    fn backward(&self, grad: &[f32], table_rows: usize) -> Vec<f32> {
        let (n, w, f, c) = (self.points, self.width(), self.features, self.corners);
        // Each thread scatters a share of the points into its own table, then they are summed.
        let threads = rayon::current_num_threads().max(1);
        let share = n.div_ceil(threads).max(1);
        let partials: Vec<Vec<f32>> = (0..threads)
            .into_par_iter()
            .map(|t| {
                let mut table = vec![0.0f32; table_rows * f];
                for i in (t * share).min(n)..((t + 1) * share).min(n) {
                    for l in 0..self.levels {
                        let fade = self.fade[l];
                        for j in 0..c {
                            let at = (i * self.levels + l) * c + j;
                            let row = self.rows[at] as usize * f;
                            if row + f > table.len() {
                                continue;
                            }
                            for q in 0..f {
                                let column = l * f + q;
                                let mut sum = self.coefficients[at] * grad[i * w + column];
                                if let Some(d) = &self.tangents {
                                    for axis in 0..3 {
                                        sum += d[at * 3 + axis] * grad[(n + axis * n + i) * w + column];
                                    }
                                }
                                table[row + q] += sum * fade;
                            }
                        }
                    }
                }
                table
            })
            .collect();
        let mut total = vec![0.0f32; table_rows * f];
        for partial in partials {
            total.par_iter_mut().zip(partial.par_iter()).for_each(|(a, b)| *a += b);
        }
        total
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

fn forward_on_host<B: Backend>(table: FloatTensor<B>, plan: &Plan) -> FloatTensor<B> {
    let device = table.device();
    let values = plan.forward(&host::<B>(table));
    B::float_from_data(TensorData::new(values, [plan.output_rows(), plan.width()]), &device)
}

fn backward_on_host<B: Backend>(grad: FloatTensor<B>, plan: &Plan, table_rows: usize) -> FloatTensor<B> {
    let device = grad.device();
    let values = plan.backward(&host::<B>(grad), table_rows);
    B::float_from_data(TensorData::new(values, [table_rows, plan.features]), &device)
}

/// The interpolation op; `Autodiff` adds its analytic backward.
#[backend_extension(Flex, NdArray, Autodiff)]
pub trait GridOps: Backend {
    /// `[output_rows, levels x features]`: the plan's weighted sums of `table`'s rows.
    fn grid_interpolate(table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self>;
}

impl GridOps for Flex {
    fn grid_interpolate(table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self> {
        forward_on_host::<Self>(table, &plan)
    }
}

impl GridOps for NdArray {
    fn grid_interpolate(table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self> {
        forward_on_host::<Self>(table, &plan)
    }
}

#[derive(Debug)]
struct Interpolate;

impl<B: Backend> Backward<B, 1> for Interpolate {
    /// The plan and the table's row count.
    type State = (Arc<Plan>, usize);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let (plan, table_rows) = ops.state;
        unary::<B, _>(ops.parents, ops.node, grads, |grad| backward_on_host::<B>(grad, &plan, table_rows));
    }
}

impl<B: Backend + GridOps, C: CheckpointStrategy> GridOps for Autodiff<B, C> {
    fn grid_interpolate(table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self> {
        let table_rows = table.shape()[0];
        let node = table.node();
        let out = B::grid_interpolate(table.into_primitive(), plan.clone());
        match Interpolate.prepare::<C>([node]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish((plan, table_rows), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

/// Interpolates `table` (`[T, F]`) by `plan`: `[output_rows, levels x features]`, with
/// gradients to the table when it is tracked.
pub fn interpolate(table: Tensor<2>, plan: Plan) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as GridOps>::grid_interpolate(table.into_dispatch(), Arc::new(plan)))
}
