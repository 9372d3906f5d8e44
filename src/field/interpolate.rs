//! The grid's interpolation as one op with an analytic backward: the weighted sum of a planned
//! lookup's table rows, for the features and, when planned, their three spatial tangents.
//!
//! As a composite of tensor ops (`select` of `N x corners` rows, a product, a sum, and for the
//! tangents the same over three axes) a training step materialised `[N x corners, F]` and
//! `[3, N x corners, F]` intermediates and scatter-added as many rows in the backward. Here the
//! forward gathers on the host straight into `[N, W]` (plus `[3N, W]`), and the backward
//! scatters the output's gradient into the table once. A lookup nobody differentiates skips the
//! plan altogether (`grid_lookup`: skinning, corners and sums in one pass per point). The CPU
//! backends (flex, ndarray) run both on the host (the plan's arithmetic, `plan`), flex lending
//! its tensors' memory without a copy. A device that keeps its tensors (a GPU) never calls the
//! op: it plans and sums with tensor ops (`tensor_encode`). This file holds the op: the trait,
//! its autodiff backward and the host's plumbing.
// burn-ndarray is deprecated upstream but stays our `--backend ndarray`.
#![allow(deprecated)]

use super::layout::{GridConfig, Level};
use super::lookup::Skinning;
use super::plan::Plan;
use crate::skeleton::BoneFrame;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{binary, unary, Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Autodiff, AutodiffBackend, Backend, Dispatch, Flex, NdArray, TensorMetadata};
use burn::tensor::{Tensor, TensorData};
use std::sync::Arc;

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
    B::from_host(values, [plan.points, plan.shift_width()], &device)
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
#[backend_extension(Flex, NdArray, Autodiff)]
pub trait GridOps: Backend {
    /// `[output_rows, levels x features]`: the plan's weighted sums of `table`'s rows.
    fn grid_interpolate(table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self>;
    /// `[table_rows, features]`: the table's gradient from the interpolation's (`grad`).
    fn grid_interpolate_backward(grad: FloatTensor<Self>, plan: Arc<Plan>, table_rows: usize) -> FloatTensor<Self>;
    /// `[N, levels x features + 1]`: the features and the prior of a lookup with no gradients,
    /// straight from `table` and the root's `preference` grid.
    fn grid_lookup(table: FloatTensor<Self>, preference: FloatTensor<Self>, lookup: Arc<HostLookup>) -> FloatTensor<Self>;
    /// `grid_interpolate` of points that carry a zero-valued `shift` of their lookup in each
    /// chosen bone (`[N, 3 S]`): the same values, with a gradient to the shift
    /// (`grid_shift_backward`) as well as to the table.
    fn grid_interpolate_carrying(table: FloatTensor<Self>, shift: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self>;
    /// `[N, 3 S]`: the shift's gradient from the interpolation's (`grad`) and the `table`.
    fn grid_shift_backward(grad: FloatTensor<Self>, table: FloatTensor<Self>, plan: Arc<Plan>) -> FloatTensor<Self>;
}

/// `GridOps` for `$backend` by its `forward`, `backward` and `shift_backward`; the lookup
/// without gradients runs on the host.
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

/// `interpolate` of points that carry `shift` (`[N, 3 S]`, zero in value, per chosen bone): the same values, with
/// the gradient to the shift as well (the plan's `carried` coefficient derivatives).
pub fn interpolate_carrying(table: Tensor<2>, shift: Tensor<2>, plan: Plan) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as GridOps>::grid_interpolate_carrying(table.into_dispatch(), shift.into_dispatch(), Arc::new(plan)))
}

/// The features and prior (`[N, W + 1]`) of `lookup`'s points from `table` and the root's
/// `preference` grid (any tensor when `lookup.preference` is false), without gradients.
pub fn lookup_without_gradients(table: Tensor<2>, preference: Tensor<2>, lookup: HostLookup) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as GridOps>::grid_lookup(table.into_dispatch(), preference.into_dispatch(), Arc::new(lookup)))
}
