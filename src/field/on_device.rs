//! The grid's interpolation as a backend's own tensor ops, for a device that keeps its tensors
//! to itself (a GPU): the planned table rows gathered, weighed and summed, and in the backward
//! the output's gradient weighed and scatter-added into the table. Only the plan goes up (its
//! rows and coefficients, the levels' fades folded in); the table and the gradients stay on the
//! device. The CPU backends sum on the host instead (`interpolate`), where the same work without
//! the `[points x corners, features]` intermediates is several times faster.

use super::plan::Plan;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Backend, TensorMetadata};
use burn::tensor::{FloatDType, IndexingUpdateOp, Shape, Slice, TensorData};

/// The plan's corner rows, on the table's device.
fn rows<B: Backend>(plan: &Plan, device: &B::Device) -> IntTensor<B> {
    let rows: Vec<i32> = plan.rows.iter().map(|&r| r as i32).collect();
    let count = rows.len();
    B::int_from_data(TensorData::new(rows, [count]), device)
}

/// `[P, 1]` (P = points x levels x corners): per planned corner, `weight(at)` times its level's
/// fade.
fn faded<B: Backend>(plan: &Plan, weight: impl Fn(usize) -> f32, device: &B::Device) -> FloatTensor<B> {
    let per_level = plan.corners;
    let values: Vec<f32> = (0..plan.rows.len()).map(|at| weight(at) * plan.fade[(at / per_level) % plan.levels]).collect();
    B::float_from_data(TensorData::new(values, [plan.rows.len(), 1]), device)
}

/// `[N, levels x features]`: the gathered corner rows (`[P, F]`) weighed by `weights` (`[P, 1]`)
/// and summed over each level's corners.
fn weighted_sum<B: Backend>(gathered: FloatTensor<B>, weights: FloatTensor<B>, plan: &Plan) -> FloatTensor<B> {
    let (n, l, c, f) = (plan.points, plan.levels, plan.corners, plan.features);
    let weights = B::float_expand(weights, Shape::new([n * l * c, f]));
    let summed = B::float_sum_dim(B::float_reshape(B::float_mul(gathered, weights), Shape::new([n, l, c, f])), 2);
    B::float_reshape(summed, Shape::new([n, l * f]))
}

/// `[P, F]`: block `block` of the output's gradient (`[N, levels x features]` rows from
/// `block x N`) repeated for each of a level's corners.
fn per_corner<B: Backend>(grad: FloatTensor<B>, block: usize, plan: &Plan) -> FloatTensor<B> {
    let (n, l, c, f) = (plan.points, plan.levels, plan.corners, plan.features);
    let rows = B::float_slice(grad, &[Slice::from(block * n..(block + 1) * n)]);
    let repeated = B::float_expand(B::float_reshape(rows, Shape::new([n, l, 1, f])), Shape::new([n, l, c, f]));
    B::float_reshape(repeated, Shape::new([n * l * c, f]))
}

/// The weight of corner `at` in output block `block`: its coefficient (block 0) or its
/// derivative along axis `block - 1`.
fn block_weight(plan: &Plan, block: usize) -> impl Fn(usize) -> f32 + '_ {
    move |at| match (block, &plan.tangents) {
        (0, _) => plan.coefficients[at],
        (b, Some(d)) => d[at * 3 + b - 1],
        (_, None) => 0.0,
    }
}

/// The planned weighted sums (`[output_rows, W]`) of `table` (`[T, F]`).
pub fn forward<B: Backend>(table: FloatTensor<B>, plan: &Plan) -> FloatTensor<B> {
    let device = table.device();
    if plan.points == 0 {
        return B::float_zeros(Shape::new([0, plan.levels * plan.features]), &device, FloatDType::F32);
    }
    let gathered = B::float_select(table, 0, rows::<B>(plan, &device));
    let sums = (0..plan.blocks()).map(|b| weighted_sum::<B>(gathered.clone(), faded::<B>(plan, block_weight(plan, b), &device), plan)).collect();
    B::float_cat(sums, 0)
}

/// The table's gradient (`[table_rows, F]`) from the output's (`[output_rows, W]`).
pub fn backward<B: Backend>(grad: FloatTensor<B>, plan: &Plan, table_rows: usize) -> FloatTensor<B> {
    let device = grad.device();
    let zeros = B::float_zeros(Shape::new([table_rows, plan.features]), &device, FloatDType::F32);
    if plan.points == 0 {
        return zeros;
    }
    let contribution = |b: usize| {
        let weights = B::float_expand(faded::<B>(plan, block_weight(plan, b), &device), Shape::new([plan.rows.len(), plan.features]));
        B::float_mul(per_corner::<B>(grad.clone(), b, plan), weights)
    };
    let contributions = (1..plan.blocks()).fold(contribution(0), |sum, b| B::float_add(sum, contribution(b)));
    B::float_select_assign(zeros, 0, rows::<B>(plan, &device), contributions, IndexingUpdateOp::Add)
}

/// The gradient (`[N, 3 S]`) of a shift of the points' lookups in their `S` chosen bones from the
/// output's: per corner, its table row against the output's gradient, times its faded world
/// derivative (`Carried::per_corner`), summed over each slot's levels and corners.
pub fn shift_backward<B: Backend>(grad: FloatTensor<B>, table: FloatTensor<B>, plan: &Plan) -> FloatTensor<B> {
    let device = grad.device();
    let Some(carried) = plan.carried.as_ref().filter(|_| plan.points > 0) else {
        return B::float_zeros(Shape::new([plan.points, plan.shift_width()]), &device, FloatDType::F32);
    };
    let slots = carried.slots.max(1);
    let gathered = B::float_select(table, 0, rows::<B>(plan, &device));
    let along = B::float_sum_dim(B::float_mul(gathered, per_corner::<B>(grad, 0, plan)), 1);
    let carried = carried.per_corner(plan);
    let axes: Vec<FloatTensor<B>> = (0..3).map(|axis| B::float_mul(along.clone(), faded::<B>(plan, |at| carried[at * 3 + axis], &device))).collect();
    let per_corner = B::float_cat(axes, 1);
    let summed = B::float_sum_dim(B::float_reshape(per_corner, Shape::new([plan.points, slots, plan.levels / slots * plan.corners, 3])), 2);
    B::float_reshape(summed, Shape::new([plan.points, 3 * slots]))
}

// On a device the plan goes up and the sums run there; the lookup without gradients, a host
// algorithm, still brings the table down.
#[cfg(feature = "gpu")]
super::interpolate::grid_ops!(burn::backend::Cube, forward::<burn::backend::Cube>, backward::<burn::backend::Cube>, shift_backward::<burn::backend::Cube>);
