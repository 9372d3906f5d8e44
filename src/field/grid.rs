//! Multiresolution feature grids in bone-local coordinates, the capacity of the `grid` field.
//!
//! Every bone owns a box around its segment (its reach follows the body's size; the root's, which
//! carries loose clothing, reaches as far as the training masks show the body), and every
//! level a grid over each box, from a coarse cell of a tenth of the body's extent down to a
//! fine one of 1/160. A level whose grids fit its table is stored densely; a finer one is
//! hashed (instant-NGP's spatial hash, the bone index hashed in). A point is looked up only in
//! the `top_bones` bones nearest to it (their softmax skinning weights over distance to the
//! segment, renormalised over those bones), trilinearly in each level, and the weighted
//! corners summed into `levels x features` values that a small MLP decodes.
//!
//! On the CPU backends the lookup is planned on the host (`lookup`): which table rows, with which coefficient
//! (skinning weight x trilinear weight) and, when asked, the coefficient's exact derivative
//! along the three world axes, so the features' spatial tangents are closed form and the SDF
//! gradient stays exact. The tensor side is then one fused op (`interpolate`) whose backward
//! scatters into the table. The sample points are constants of the plan: gradients reach the
//! table, not the points. Where nothing is differentiated (a ray's search for the body, most of
//! a step's points, and every lookup of a render) the plan is never stored: each point's
//! corners are summed as they are found (`features_on_host`). A device that keeps its tensors
//! (a GPU) plans and sums the same lookup with tensor ops instead (`Route`, `tensor_encode`).

use burn::module::{Module, Param};
use burn::tensor::{Device, Int, Tensor, TensorData};

pub use super::host_lookup::features_on_host;
pub use super::layout::{GridConfig, Level, RootSkinning, RootTable, FINEST_PER_EXTENT, MAX_TOP_BONES, REACH_PER_EXTENT};
pub use super::lookup::{lookup, lookup_carried, saturate, Lookup, Skinning};

pub use crate::skeleton::{BoneFrame, MotionIncrement, ViewIncrement};

/// The learnable table: `levels x 2^table_log2` rows of `features`.
#[derive(Module, Debug)]
pub struct FeatureGrid {
    pub table: Param<Tensor<2>>,
    /// The root's learned skinning preference (`RootSkinning`): one logit per vertex.
    pub root_preference: Option<Param<Tensor<2>>>,
    #[module(skip)]
    pub config: GridConfig,
    /// How many levels, coarsest first, contribute (fractional: the next one fades in); the
    /// trainer sets it for a coarse-to-fine schedule, all of them otherwise.
    #[module(skip)]
    pub active_levels: f32,
    /// How the lookup runs (`Route`).
    #[module(skip)]
    pub route: Route,
}

/// How a grid lookup runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Route {
    /// The CPU backends plan on the host and sum by the fused op (`interpolate`); a device
    /// that keeps its tensors (a GPU) plans and sums by tensor ops (`Tensors`).
    #[default]
    Fused,
    /// The host's plan sent up and summed by tensor ops: the composite the fused op replaced
    /// (the step benchmark's "before", and the fused op's reference).
    Composite,
    /// Planned and summed by tensor ops on any device, as a GPU runs it.
    Tensors,
}

/// Points `[N, 3]` on the host, and N (NaN-filled if the backend cannot give them, which the fit
/// then reports as a non-finite loss rather than a panic).
fn host_points(points: Tensor<2>) -> (Vec<f32>, usize) {
    let [n, _] = points.dims();
    (crate::backend::host_values(points), n)
}

/// What the grid gives a batch of points: features `[N, W]` and the prior `[N]`, with their
/// derivatives along the world axes (`[3N, W]` axis-major, `[3, N]`) when asked.
pub struct GridFeatures {
    pub features: Tensor<2>,
    pub prior: Tensor<1>,
    pub tangents: Option<(Tensor<2>, Tensor<2>)>,
}

impl FeatureGrid {
    /// Plans the lookup of `points` (a tensor) in the posed bones `frames`.
    fn plan(&self, points: Tensor<2>, frames: &[BoneFrame], skinning: Skinning, tangents: bool) -> (Lookup, usize) {
        let (values, n) = host_points(points);
        (lookup(&self.config, &self.active_layout(), frames, skinning, &values, tangents), n)
    }

    /// `encode` where nothing asks for a gradient (the table is not tracked): planned and summed
    /// in one pass on the host (`features_on_host`), the same values (a test pins them).
    fn encode_without_gradients(&self, points: Tensor<2>, frames: &[BoneFrame], skinning: Skinning) -> GridFeatures {
        let device = points.device();
        let (values, n) = host_points(points);
        let preference = self.root_preference.as_ref().map(|p| p.val());
        let lookup = super::interpolate::HostLookup {
            config: self.config.clone(),
            levels: self.active_layout(),
            frames: frames.to_vec(),
            skinning,
            points: values,
            fade: self.fade(),
            preference: preference.is_some(),
        };
        let preference = preference.unwrap_or_else(|| Tensor::zeros([1, 1], &device));
        let out = super::interpolate::lookup_without_gradients(self.table.val(), preference, lookup);
        let w = self.config.width();
        GridFeatures { features: out.clone().slice([0..n, 0..w]), prior: out.slice([0..n, w..w + 1]).reshape([n]), tangents: None }
    }

    /// The layout with each level marked active or not (coarse to fine).
    pub(super) fn active_layout(&self) -> Vec<Level> {
        let mut levels = self.config.layout();
        for (l, level) in levels.iter_mut().enumerate() {
            level.active = (l as f32) < self.active_levels;
        }
        levels
    }

    /// Each level's weight: levels beyond `active_levels` are faded out (coarse to fine).
    pub(super) fn fade(&self) -> Vec<f32> {
        (0..self.config.levels).map(|l| (self.active_levels - l as f32).clamp(0.0, 1.0)).collect()
    }

    /// Looks `points` up in the posed bones `frames`. With a `motion` increment, a tracked lookup
    /// that asks for no tangents carries it (`encode_moving`).
    pub fn encode(&self, points: Tensor<2>, frames: &[BoneFrame], skinning: Skinning, tangents: bool, motion: Option<&MotionIncrement>) -> GridFeatures {
        self.encode_carrying(points, frames, skinning, tangents, motion, None)
    }

    /// `encode`, the tracked lookup also carrying a `view` increment of the cameras when it
    /// follows these points (`ViewIncrement::points`).
    pub fn encode_carrying(
        &self,
        points: Tensor<2>,
        frames: &[BoneFrame],
        skinning: Skinning,
        tangents: bool,
        motion: Option<&MotionIncrement>,
        view: Option<&ViewIncrement>,
    ) -> GridFeatures {
        let device = points.device();
        let tracked = self.table.val().is_require_grad();
        let view = view.filter(|v| v.points() == points.dims()[0]);
        let route = match self.route {
            Route::Fused if !crate::backend::on_host(&device) => Route::Tensors,
            route => route,
        };
        if route != Route::Fused {
            return self.encode_by_tensors(points, frames, skinning, tangents, motion, view, route == Route::Composite);
        }
        if (motion.is_some() || view.is_some()) && !tangents && tracked {
            return self.encode_moving(points, frames, skinning, motion, view);
        }
        if !tangents && !tracked {
            return self.encode_without_gradients(points, frames, skinning);
        }
        let (plan, n) = self.plan(points, frames, skinning, tangents);
        let (per_bone, per_bone_tangents, plan) = self.interpolate_fused(plan, n, tangents, None);
        let prior = Tensor::from_data(TensorData::new(plan.prior.clone(), [n]), &device);
        let skin = self.skin_of(&plan, n, tangents, &device);
        let (features, feature_tangents) = self.blend(skin, n, per_bone, per_bone_tangents, None);
        let tangents = feature_tangents.map(|t| {
            let prior_tangents: Tensor<2> = Tensor::from_data(TensorData::new(plan.prior_tangents, [n, 3]), &device);
            (t, prior_tangents.transpose())
        });
        GridFeatures { features, prior, tangents }
    }

    /// A tracked lookup that carries a motion increment: the same features and prior, with the
    /// increment's gradient. A bone moved by `m` carries its content with it, so a point's
    /// lookup in each chosen bone is made as if the point had moved by `-m` of that bone: its
    /// features there, that bone's skinning logit and its part of the capsule prior (the
    /// field in the corrected pose, to first order, where bones blend too). The shifts reach the
    /// trilinear corners through the fused op's backward (`interpolate_carrying`), the logits,
    /// the prior and the root's preference through their planned world derivatives; second
    /// derivatives are not followed.
    ///
    /// A `view` increment moves the camera each point is seen from: the point is looked up
    /// where the moved camera sees it (`ViewIncrement::seen_shift`), in every bone alike.
    fn encode_moving(
        &self,
        points: Tensor<2>,
        frames: &[BoneFrame],
        skinning: Skinning,
        motion: Option<&MotionIncrement>,
        view: Option<&ViewIncrement>,
    ) -> GridFeatures {
        let device = points.device();
        let (values, n) = host_points(points.clone());
        let levels = self.active_layout();
        let mut plan = lookup_carried(&self.config, &levels, frames, skinning, &values);
        let k = self.config.top();
        let bones = frames.len();
        let chosen: Vec<i64> = plan.bones.iter().map(|&b| (b as usize).min(bones.saturating_sub(1)) as i64).collect();
        let shift = carried_shift(points, k, Tensor::<1, Int>::from_data(TensorData::new(chosen, [n * k]), &device), motion, view);
        let slot_tangents = |values: &[f32]| Tensor::<3>::from_data(TensorData::new(values.to_vec(), [n, k, 3]), &device);
        let root_slot = Tensor::from_data(TensorData::new(plan.root_slot.clone(), [n, k]), &device);
        let (logit_shift, prior_shift, root_shift) =
            carried_terms(&shift, slot_tangents(&plan.logit_tangents), slot_tangents(&plan.prior_slot_tangents), root_slot);
        let prior = Tensor::<1>::from_data(TensorData::new(plan.prior.clone(), [n]), &device) + prior_shift;
        let carried = super::plan::Carried {
            slots: k,
            levels: self.config.levels,
            fractions: std::mem::take(&mut plan.cell_fractions),
            axes: plan.bones.iter().flat_map(|&b| frames.get(b as usize).map_or([[f32::NAN; 3]; 3], |frame| frame.axes).into_iter().flatten()).collect(),
            per_cell: levels.iter().map(|level| 1.0 / level.cell).collect(),
        };
        let (per_bone, _, plan) = self.interpolate_fused(plan, n, false, Some((shift.reshape([n, 3 * k]), carried)));
        let skin = self.skin_of(&plan, n, true, &device);
        let (features, _) = self.blend(skin, n, per_bone, None, Some((logit_shift, root_shift)));
        GridFeatures { features, prior, tangents: None }
    }

    /// Each chosen bone's features (`[N, K W]`) and their tangents (`[3N, K W]`) by the fused
    /// op (`interpolate`); with a `shift` of the points (`[N, 3]`) and its cells
    /// (`plan::Carried`), carrying its gradient instead of giving tangents.
    #[allow(clippy::type_complexity)]
    fn interpolate_fused(
        &self,
        mut plan: Lookup,
        n: usize,
        tangents: bool,
        shift: Option<(Tensor<2>, super::plan::Carried)>,
    ) -> (Tensor<2>, Option<Tensor<2>>, Lookup) {
        let config = &self.config;
        let groups = config.top() * config.levels;
        let derivatives = std::mem::take(&mut plan.coefficient_tangents);
        let carrying = shift.is_some();
        let (shift, carried) = shift.unzip();
        let derivatives = (tangents && !carrying).then_some(derivatives);
        let fused = super::plan::Plan {
            points: n,
            levels: groups,
            corners: 8,
            features: config.features,
            rows: std::mem::take(&mut plan.rows),
            coefficients: std::mem::take(&mut plan.coefficients),
            tangents: derivatives,
            carried,
            fade: self.fade().into_iter().cycle().take(groups).collect(),
            table_parts: config.levels,
        };
        let out = match shift {
            Some(shift) => super::interpolate::interpolate_carrying(self.table.val(), shift, fused),
            None => super::interpolate::interpolate(self.table.val(), fused),
        };
        let width = groups * config.features;
        let per_bone = out.clone().slice([0..n, 0..width]);
        let per_bone_tangents = (tangents && !carrying).then(|| out.slice([n..4 * n, 0..width]));
        (per_bone, per_bone_tangents, plan)
    }

    /// What the host's plan blends with (`Skin`), up on the table's device; the root's
    /// preference by the fused op, with its world gradients when `preference_tangents`.
    fn skin_of(&self, plan: &Lookup, n: usize, preference_tangents: bool, device: &Device) -> Skin {
        let k = self.config.top();
        let preference = self.root_preference.as_ref().map(|table| {
            let lookup = super::plan::Plan {
                points: n,
                levels: 1,
                corners: 8,
                features: 1,
                rows: plan.root_rows.clone(),
                coefficients: plan.root_coefficients.clone(),
                tangents: preference_tangents.then(|| plan.root_coefficient_tangents.clone()),
                carried: None,
                fade: vec![1.0],
                table_parts: 1,
            };
            super::interpolate::interpolate(table.val(), lookup)
        });
        let logit_tangents =
            (!plan.logit_tangents.is_empty()).then(|| Tensor::<2>::from_data(TensorData::new(plan.logit_tangents.clone(), [n * k, 3]), device));
        Skin {
            logits: Tensor::from_data(TensorData::new(plan.logits.clone(), [n, k]), device),
            logit_tangents,
            root_slot: Tensor::from_data(TensorData::new(plan.root_slot.clone(), [n, k]), device),
            preference,
        }
    }

    /// The features (`[N, W]`) as the chosen bones' features weighted by the skinning: a
    /// softmax of the planned logits (plus `logit_shift`, when the points carry a shift) plus the
    /// root's learned preference; and their tangents (`[3N, W]`), through the weights'
    /// gradients too.
    pub(super) fn blend(
        &self,
        skin: Skin,
        n: usize,
        per_bone: Tensor<2>,
        per_bone_tangents: Option<Tensor<2>>,
        carried: Option<(Tensor<2>, Tensor<2>)>,
    ) -> (Tensor<2>, Option<Tensor<2>>) {
        let config = &self.config;
        let (k, w) = (config.top(), config.width());
        let Skin { logits, logit_tangents, root_slot, preference } = skin;
        // A carried shift: the logits' (`[N, K]`) and the root's lookup's (`[N, 3]`).
        let (logits, root_shift) = match carried {
            Some((logit_shift, root_shift)) => (logits + logit_shift, Some(root_shift)),
            None => (logits, None),
        };
        let logits = match (&preference, root_shift) {
            (Some(p), Some(shift)) => {
                let along = (p.clone().slice([n..4 * n, 0..1]).reshape([3, n]).transpose() * shift).sum_dim(1);
                logits + root_slot.clone() * (p.clone().slice([0..n, 0..1]) + along)
            }
            (Some(p), None) => logits + root_slot.clone() * p.clone().slice([0..n, 0..1]),
            (None, _) => logits,
        };
        let weights = burn::tensor::activation::softmax(logits, 1); // [N, K]
        let per_bone = per_bone.reshape([n, k, w]);
        let features = (per_bone.clone() * weights.clone().reshape([n, k, 1])).sum_dim(1).reshape([n, w]);
        let feature_tangents = per_bone_tangents.map(|d_per_bone| {
            let device = d_per_bone.device();
            let d_logits = logit_tangents.unwrap_or_else(|| Tensor::zeros([n * k, 3], &device)).transpose().reshape([3, n, k]);
            let d_logits = match &preference {
                Some(p) => d_logits + root_slot.unsqueeze_dim::<3>(0) * p.clone().slice([n..4 * n, 0..1]).reshape([3, n, 1]),
                None => d_logits,
            };
            let weights = weights.unsqueeze_dim::<3>(0); // [1, N, K]
            let d_weights = weights.clone() * (d_logits.clone() - (weights.clone() * d_logits).sum_dim(2)); // [3, N, K]
            let through_weights = d_weights.reshape([3, n, k, 1]) * per_bone.unsqueeze_dim::<4>(0);
            let through_features = weights.reshape([1, n, k, 1]) * d_per_bone.reshape([3, n, k, w]);
            (through_weights + through_features).sum_dim(2).reshape([3 * n, w])
        });
        (features, feature_tangents)
    }
}

/// What the skinning blends a point's bones with: the logits (`[N, K]`) with their world
/// gradients (`[N K, 3]`, when planned), the root's slot (`[N, K]`, 1 where the root is) and
/// the root's learned preference at each point (`[N, 1]`, or `[4N, 1]` with its world
/// gradients axis-major after it).
pub(super) struct Skin {
    pub(super) logits: Tensor<2>,
    pub(super) logit_tangents: Option<Tensor<2>>,
    pub(super) root_slot: Tensor<2>,
    pub(super) preference: Option<Tensor<2>>,
}

/// The shift a carried lookup of `points` (`[N, 3]`) makes in each of its `k` chosen bones
/// (`bones`, `[N K]`): `[N, K, 3]`, where the moved camera sees the point (`view`, in every bone
/// alike) less its bone's motion (`motion`), zero in value.
pub(super) fn carried_shift(points: Tensor<2>, k: usize, bones: Tensor<1, Int>, motion: Option<&MotionIncrement>, view: Option<&ViewIncrement>) -> Tensor<3> {
    let [n, _] = points.dims();
    // Rows of `[N, 3]` once per chosen bone (`[N K, 3]`); each point's motion in each.
    let per_slot = |rows: Tensor<2>| rows.reshape([n, 1, 3]).expand([n, k, 3]).reshape([n * k, 3]);
    let moved_by = |motion: &MotionIncrement| motion.motion_of(points.clone().detach(), k, bones.clone());
    match (motion, view) {
        (Some(motion), Some(view)) => per_slot(view.seen_shift(points.clone())) - moved_by(motion),
        (Some(motion), None) => moved_by(motion).neg(),
        (None, Some(view)) => per_slot(view.seen_shift(points.clone())),
        (None, None) => Tensor::zeros([n * k, 3], &points.device()),
    }
    .reshape([n, k, 3])
}

/// What a carried `shift` (`[N, K, 3]`) moves besides the corners, through the planned world
/// gradients: the logits (`[N, K]`, from `logit_tangents` `[N, K, 3]`), the capsule prior (`[N]`,
/// from `prior_slot_tangents`) and the root's preference lookup (`[N, 3]`, the root's slot's
/// shift).
pub(super) fn carried_terms(
    shift: &Tensor<3>,
    logit_tangents: Tensor<3>,
    prior_slot_tangents: Tensor<3>,
    root_slot: Tensor<2>,
) -> (Tensor<2>, Tensor<1>, Tensor<2>) {
    let [n, k, _] = shift.dims();
    let logit_shift = (logit_tangents * shift.clone()).sum_dim(2).reshape([n, k]);
    let prior_shift = (prior_slot_tangents * shift.clone()).sum_dim(2).sum_dim(1).reshape([n]);
    let root_shift = (shift.clone() * root_slot.reshape([n, k, 1])).sum_dim(1).reshape([n, 3]);
    (logit_shift, prior_shift, root_shift)
}

impl GridConfig {
    /// A grid with features uniform in +-1e-4 (instant-NGP's start) from our own seeded stream.
    pub fn init(&self, device: &Device, seed: u64) -> FeatureGrid {
        let mut stream = crate::random::Stream::new(seed, 0x6121D, 0);
        let n = self.table_rows();
        let values: Vec<f32> = (0..n * self.features).map(|_| ((stream.uniform() * 2.0 - 1.0) * 1e-4) as f32).collect();
        // The root's preference starts at zero: the skinning starts from distances alone.
        let root_preference = self.root.map(|root| {
            let [a, b, c] = root.dims(self.bone_lengths.get(root.bone).copied().unwrap_or(0.0));
            Param::from_tensor(Tensor::zeros([a * b * c, 1], device))
        });
        FeatureGrid {
            table: Param::from_tensor(Tensor::from_data(TensorData::new(values, [n, self.features]), device)),
            root_preference,
            config: self.clone(),
            active_levels: self.levels as f32,
            route: Route::Fused,
        }
    }
}
