//! The grid's interpolation as a backend's own tensor ops, for a device that keeps its tensors
//! to itself (a GPU): the planned table rows gathered, weighed and summed, and in the backward
//! the output's gradient weighed and scatter-added into the table. Only the plan goes up (its
//! rows and coefficients, the levels' fades folded in); the table and the gradients stay on the
//! device. The CPU backends sum on the host instead (`interpolate`), where the same work without
//! the `[points x corners, features]` intermediates is several times faster.

use super::interpolate::Plan;
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
    let gathered = B::float_select(table, 0, rows::<B>(plan, &device));
    let blocks = plan.output_rows() / plan.points;
    let sums = (0..blocks).map(|b| weighted_sum::<B>(gathered.clone(), faded::<B>(plan, block_weight(plan, b), &device), plan)).collect();
    B::float_cat(sums, 0)
}

/// The table's gradient (`[table_rows, F]`) from the output's (`[output_rows, W]`).
pub fn backward<B: Backend>(grad: FloatTensor<B>, plan: &Plan, table_rows: usize) -> FloatTensor<B> {
    let device = grad.device();
    let blocks = plan.output_rows() / plan.points;
    let contributions = (0..blocks)
        .map(|b| {
            let weights = B::float_expand(faded::<B>(plan, block_weight(plan, b), &device), Shape::new([plan.rows.len(), plan.features]));
            B::float_mul(per_corner::<B>(grad.clone(), b, plan), weights)
        })
        .reduce(B::float_add)
        .expect("a plan has a block of values");
    let zeros = B::float_zeros(Shape::new([table_rows, plan.features]), &device, FloatDType::F32);
    B::float_select_assign(zeros, 0, rows::<B>(plan, &device), contributions, IndexingUpdateOp::Add)
}

/// The gradient (`[N, 3]`) of a shift of the points from the output's: per corner, its table row
/// against the output's gradient, times its faded world derivative (`Carried::per_corner`).
pub fn shift_backward<B: Backend>(grad: FloatTensor<B>, table: FloatTensor<B>, plan: &Plan) -> FloatTensor<B> {
    let device = grad.device();
    let Some(carried) = &plan.carried else {
        return B::float_zeros(Shape::new([plan.points, 3]), &device, FloatDType::F32);
    };
    let gathered = B::float_select(table, 0, rows::<B>(plan, &device));
    let along = B::float_sum_dim(B::float_mul(gathered, per_corner::<B>(grad, 0, plan)), 1);
    let carried = carried.per_corner(plan);
    let axes: Vec<FloatTensor<B>> = (0..3).map(|axis| B::float_mul(along.clone(), faded::<B>(plan, |at| carried[at * 3 + axis], &device))).collect();
    let per_corner = B::float_cat(axes, 1);
    let summed = B::float_sum_dim(B::float_reshape(per_corner, Shape::new([plan.points, plan.levels * plan.corners, 3])), 1);
    B::float_reshape(summed, Shape::new([plan.points, 3]))
}

#[cfg(feature = "gpu")]
mod device_ops {
    use super::super::interpolate::{GridOps, HostLookup, Plan};
    use super::{backward, forward, shift_backward};
    use burn::backend::tensor::FloatTensor;
    use burn::backend::Cube;
    use std::sync::Arc;

    /// On a device the plan goes up and the sums run there; the lookup without
    /// gradients, a host algorithm, still brings the table down.
    impl GridOps for Cube {
        fn grid_interpolate(table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self> {
            forward::<Self>(table, &plan)
        }

        fn grid_interpolate_carrying(table: FloatTensor<Self>, _shift: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self> {
            forward::<Self>(table, &plan)
        }

        fn grid_shift_backward(grad: FloatTensor<Self>, table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self> {
            shift_backward::<Self>(grad, table, &plan)
        }

        fn grid_interpolate_backward(grad: FloatTensor<Self>, plan: Arc<Plan>, table_rows: usize) -> FloatTensor<Self> {
            backward::<Self>(grad, &plan, table_rows)
        }

        fn grid_lookup(table: FloatTensor<Self>, preference: FloatTensor<Self>, lookup: Arc<HostLookup>) -> FloatTensor<Self> {
            lookup.run::<Self>(table, preference)
        }
    }
}
