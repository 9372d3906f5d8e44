//! The grid's lookup by tensor ops alone, as a device that keeps its tensors runs it (a GPU):
//! the plan made there (`lookup_on_device`) or, for the composite reference on the CPU, the
//! host's plan sent up (`TensorLookup::upload`); the planned rows gathered, weighed, summed and
//! blended, with burn's autodiff for the gradients to the table, the root's preference and a
//! carried shift of the points. Nothing comes down to the host.

use super::grid::{carried_shift, carried_terms, FeatureGrid, GridFeatures, Lookup, Skin, Skinning};
use super::tensor_lookup::{lookup_on_device, TensorLookup};
use crate::skeleton::{BoneFrame, MotionIncrement, ViewIncrement};
use burn::tensor::{Device, Int, Tensor, TensorData};

impl TensorLookup {
    /// The host's plan of `n` points in `k` bones on `device`; what it did not plan (the
    /// gradients of a plan without tangents) as zeros.
    pub fn upload(plan: &Lookup, n: usize, k: usize, device: &Device) -> Self {
        let planned = |values: &[f32]| {
            (values.len() == n * k * 3).then(|| Tensor::<1>::from_data(TensorData::new(values.to_vec(), [n * k * 3]), device).reshape([n, k, 3]))
        };
        let floats = |values: &[f32], count: usize| match values.len() == count {
            true => Tensor::<1>::from_data(TensorData::new(values.to_vec(), [count]), device),
            false => Tensor::zeros([count], device),
        };
        let ints = |values: &[u32]| {
            let values: Vec<i64> = values.iter().map(|&v| v as i64).collect();
            let count = values.len();
            Tensor::<1, Int>::from_data(TensorData::new(values, [count]), device)
        };
        let corners = plan.rows.len();
        let bones = match plan.bones.len() == n * k {
            true => ints(&plan.bones).reshape([n, k]),
            false => Tensor::zeros([n, k], device),
        };
        TensorLookup {
            bones,
            rows: ints(&plan.rows),
            coefficients: floats(&plan.coefficients, corners),
            coefficient_tangents: (plan.coefficient_tangents.len() == corners * 3)
                .then(|| floats(&plan.coefficient_tangents, corners * 3).reshape([corners, 3])),
            logits: floats(&plan.logits, n * k).reshape([n, k]),
            logit_tangents: planned(&plan.logit_tangents),
            root_slot: floats(&plan.root_slot, n * k).reshape([n, k]),
            root_rows: ints(&plan.root_rows),
            root_coefficients: floats(&plan.root_coefficients, n * 8),
            root_coefficient_tangents: floats(&plan.root_coefficient_tangents, n * 24).reshape([n * 8, 3]),
            prior: floats(&plan.prior, n),
            prior_slot_tangents: planned(&plan.prior_slot_tangents),
        }
    }
}

impl FeatureGrid {
    /// `encode_carrying` by tensor ops: planned on the points' device, or on the host and sent
    /// up when `host_plan` (the composite reference).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn encode_by_tensors(
        &self,
        points: Tensor<2>,
        frames: &[BoneFrame],
        skinning: Skinning,
        tangents: bool,
        motion: Option<&MotionIncrement>,
        view: Option<&ViewIncrement>,
        host_plan: bool,
    ) -> GridFeatures {
        let device = points.device();
        let [n, _] = points.dims();
        let k = self.config.top();
        let carrying = (motion.is_some() || view.is_some()) && !tangents && self.table.val().is_require_grad();
        let levels = self.active_layout();
        // The points are the plan's constants, as on the host: gradients reach the table.
        let plan = match host_plan {
            true => {
                let values = crate::backend::host_values(points.clone());
                TensorLookup::upload(&super::grid::lookup(&self.config, &levels, frames, skinning, &values, tangents || carrying), n, k, &device)
            }
            false => lookup_on_device(&self.config, &levels, frames, skinning, points.clone().detach(), tangents || carrying),
        };
        let shift = carrying.then(|| carried_shift(points, k, plan.bones.clone().reshape([n * k]), motion, view));
        let (per_bone, per_bone_tangents) = self.sum_corners(&plan, n, tangents, shift.as_ref());
        let preference = self.preference_by_tensors(&plan, n, tangents || carrying);
        // (A carrying lookup is planned with its world gradients.)
        let (carried, prior) = match (&shift, &plan.logit_tangents, &plan.prior_slot_tangents) {
            (Some(shift), Some(logit_tangents), Some(prior_slot_tangents)) => {
                let (logit_shift, prior_shift, root_shift) = carried_terms(shift, logit_tangents.clone(), prior_slot_tangents.clone(), plan.root_slot.clone());
                (Some((logit_shift, root_shift)), plan.prior.clone() + prior_shift)
            }
            _ => (None, plan.prior.clone()),
        };
        let skin = Skin {
            logits: plan.logits.clone(),
            logit_tangents: plan.logit_tangents.clone().map(|t| t.reshape([n * k, 3])),
            root_slot: plan.root_slot.clone(),
            preference,
        };
        let (features, feature_tangents) = self.blend(skin, n, per_bone, per_bone_tangents, carried);
        let tangents = feature_tangents.zip(plan.prior_tangents()).map(|(t, prior)| (t, prior.transpose()));
        GridFeatures { features, prior, tangents }
    }

    /// Each chosen bone's features (`[N, K W]`) and, when `tangents`, their world derivatives
    /// (`[3N, K W]`, axis-major): the planned rows gathered, weighed by their coefficients and
    /// summed per level, each level faded. A carried `shift` (`[N, K, 3]`, zero in value) moves
    /// each coefficient by its world derivative along its slot's shift, for the shift's gradient.
    fn sum_corners(&self, plan: &TensorLookup, n: usize, tangents: bool, shift: Option<&Tensor<3>>) -> (Tensor<2>, Option<Tensor<2>>) {
        let device = plan.coefficients.device();
        let (k, l, f) = (self.config.top(), self.config.levels, self.config.features);
        let (groups, corners) = (k * l, n * k * l * 8);
        let gathered = self.table.val().select(0, plan.rows.clone()); // [P, F]
        let fade: Vec<f32> = self.fade().into_iter().cycle().take(groups).flat_map(|w| std::iter::repeat_n(w, f)).collect();
        let fade: Tensor<2> = Tensor::from_data(TensorData::new(fade, [1, groups * f]), &device);
        let sum = |weights: Tensor<2>| (gathered.clone() * weights).reshape([n, groups, 8, f]).sum_dim(2).reshape([n, groups * f]) * fade.clone();
        let coefficients = plan.coefficients.clone().reshape([corners, 1]);
        let coefficients = match (shift, &plan.coefficient_tangents) {
            (Some(shift), Some(d)) => {
                let along = shift.clone().reshape([n, k, 1, 1, 3]).expand([n, k, l, 8, 3]).reshape([corners, 3]);
                coefficients + (d.clone() * along).sum_dim(1)
            }
            _ => coefficients,
        };
        let per_bone = sum(coefficients);
        let per_bone_tangents = match (tangents, &plan.coefficient_tangents) {
            (true, Some(d)) => Some(Tensor::cat((0..3).map(|x| sum(d.clone().slice([0..corners, x..x + 1]))).collect(), 0)),
            _ => None,
        };
        (per_bone, per_bone_tangents)
    }

    /// The root's learned preference at each point (`[N, 1]`, or with its world gradients
    /// `[4N, 1]`), from the planned corners.
    fn preference_by_tensors(&self, plan: &TensorLookup, n: usize, tangents: bool) -> Option<Tensor<2>> {
        self.root_preference.as_ref().map(|table| {
            let gathered = table.val().select(0, plan.root_rows.clone()); // [N 8, 1]
            let sum = |weights: Tensor<2>| (gathered.clone() * weights).reshape([n, 8]).sum_dim(1);
            let value = sum(plan.root_coefficients.clone().reshape([n * 8, 1]));
            match tangents {
                true => {
                    let d = &plan.root_coefficient_tangents;
                    let mut parts = vec![value];
                    parts.extend((0..3).map(|x| sum(d.clone().slice([0..n * 8, x..x + 1]))));
                    Tensor::cat(parts, 0)
                }
                false => value,
            }
        })
    }
}
