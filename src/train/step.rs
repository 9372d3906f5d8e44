//! One training step: forward, the schedule's weighted losses, backward, one Adam step per named
//! parameter group, the light kept in its cone, the field's moving average updated.

use super::host_adam::{HostLeaves, Leaves};
use super::motion::MotionCorrections;
use super::phase_clock::PhaseClock;
use super::{Batch, TrainState, Trainer};
use crate::avatar::Avatar;
use crate::field::{AvatarField, PoseTensors};
use crate::fit_error::FitError;
use crate::gaussians::GaussianParams;
use crate::losses::{Input, Inputs};
use crate::messages::StepStats;
use crate::render::{render_in_parts, sum_gradients, Deferred, Parts};
use crate::shading::LightKind;
use crate::skeleton::{MotionIncrement, ViewIncrement};
use burn::optim::GradientsParams;
use burn::tensor::{Int, Tensor, TensorData};
use std::time::Instant;

/// The step's losses: name, weight and value, in the order they are summed.
type Terms<'a> = Vec<(&'a str, f64, Tensor<1>)>;

/// The step (m on the reference human, scaled with the body) over which a step differences the
/// SDF's gradient to carry the cameras' increment into the shading normals: about the finest
/// grid cell, so the slope is the surface's bend, not one cell's trilinear kink.
const NORMAL_STENCIL_ON_HUMAN: f64 = 0.01;

impl Trainer {
    /// One step on `batch` from `state`: forward, the weighted losses, backward, one Adam step
    /// per group. The batch carries every random number the step uses (`draw_batch`). The state
    /// comes back whatever happens; when the step fails (a loss or a parameter not finite) it
    /// holds the failed update, which a fit does not keep: it stops at its last checkpoint.
    pub fn step(&self, batch: Batch, mut state: TrainState) -> (TrainState, Result<StepStats, FitError>) {
        let start = Instant::now();
        let mut clock = PhaseClock::start();
        let it = state.iteration;
        // Coarse-to-fine protects the light's recovery: without a light to fit, every level
        // works from the start.
        if let Some(grid) = state.model.field.grid.as_mut() {
            grid.active_levels = if self.fit_light { self.schedule.active_levels(grid.config.levels, it) } else { grid.config.levels as f32 };
        }
        // The cameras' colours go up as one leaf a step, once colour is fitted.
        let colours = state.camera_colours.as_ref().filter(|_| self.schedule.weight("rgb", it) > 0.0).map(|c| (c, c.leaf(&self.device)));
        // The frame's motion correction, while it is refined.
        let refined = state.motion.as_ref().filter(|_| self.schedule.needs(Input::Motion, it) && batch.corrected.is_some());
        let motion_row = refined.and_then(|m| m.row(self.frames[batch.frame].position).map(|k| (m, k)));
        let cameras = state.cameras.as_ref().filter(|_| !batch.rays.cameras.is_empty());
        let (terms, parts, leaves) = self.losses(&state.model, &batch, it, &mut state.error_maps, colours.clone(), motion_row, cameras, &mut clock);
        let colour_leaf = colours.map(|(_, leaf)| leaf);
        let mut total = terms[0].2.clone() * terms[0].1;
        for (_, weight, value) in terms.iter().skip(1) {
            total = total + value.clone() * *weight;
        }
        // The total and every term come down with what the update reports, in the step's one
        // read: read before the backward pass, they would hold a device idle while the host
        // waited on them. A diverged step stops the fit, which keeps its last checkpoint.
        let losses = Tensor::cat(std::iter::once(&total).chain(terms.iter().map(|(_, _, v)| v)).map(|v| v.clone().detach().narrow(0, 0, 1)).collect(), 0);
        clock.mark(7);
        let grads = parts.backward(&total, self.parts_backward_at_once);
        clock.mark(8);
        // The host's leaves step after the device's update (neither reads the other), so that
        // their gradients come down with what the update reports, in one read.
        let host_leaves = HostLeaves::of(colour_leaf, leaves, &grads);
        let model = state.model;
        state.model = self.update(model, grads, parts.into_forks(), batch.light, &mut state.optimisers, it);
        let extra = [Some(losses), host_leaves.pending.joined(), (!state.model.gaussians.is_empty()).then(|| state.model.gaussians.rows())];
        let (light, sum, [losses, gradients, gaussians]) = self.read_after_update(&state.model, extra);
        let value = |k: usize| losses.get(k).map_or(f64::NAN, |&v| v as f64);
        let mut stats = StepStats {
            total: value(0),
            terms: terms.iter().enumerate().map(|(k, (n, _, _))| (n.to_string(), value(k + 1))).collect(),
            ..StepStats::default()
        };
        if !stats.total.is_finite() {
            let bad = stats.terms.iter().find(|(_, v)| !v.is_finite()).map(|(n, _)| format!("the {n} loss")).unwrap_or_else(|| "the total loss".into());
            state.gaussians_read = None;
            return (state, Err(FitError::NonFinite { iteration: it, what: bad, checkpoint: String::new() }));
        }
        self.step_host_leaves(&host_leaves, host_leaves.pending.split(&gradients), &mut state, &batch, it);
        state.gaussians_read = state.model.gaussians.set_from_rows(&gaussians);
        if self.fit_light {
            stats.light = light;
        }
        if let Some(name) = crate::avatar::first_non_finite_of(&state.model, sum) {
            return (state, Err(FitError::NonFinite { iteration: it, what: format!("the parameter {name} after the update"), checkpoint: String::new() }));
        }
        state.iteration += 1;
        self.update_average(&mut state);
        clock.mark(9);
        stats.phases = clock.spans;
        stats.phase_cpu = clock.cpu_spans;
        stats.seconds = start.elapsed().as_secs_f64();
        (state, Ok(stats))
    }

    /// The forward pass and the schedule's losses on `batch` (`losses::TERMS`, each from the
    /// step's `Inputs`; the colour's error, and the mask's, recorded in each pixel's view's
    /// error map), with the parts of the batch rendered on other threads (their forks of the field
    /// and what their backward passes start from).
    #[allow(clippy::too_many_arguments)]
    fn losses<'a>(
        &self,
        model: &Avatar,
        batch: &Batch,
        it: usize,
        error_maps: &mut [Option<crate::error_map::ErrorMap>],
        colours: Option<(&super::camera_colour::CameraColours, Tensor<2>)>,
        motion: Option<(&MotionCorrections, usize)>,
        cameras: Option<&super::camera_pose::CameraPoses>,
        clock: &mut PhaseClock,
    ) -> (Terms<'a>, Parts, Leaves) {
        let device = self.device.clone();
        let needs = |input: Input| self.schedule.needs(input, it);
        // With the motion refined, the render's lookups carry an increment of the pose.
        let increment = motion.zip(batch.corrected.as_ref()).map(|(_, (pose, _))| MotionIncrement::new(&self.scene.skeleton, pose, &device));
        // With the cameras refined, an increment of every camera's pose.
        let view = cameras.map(|c| ViewIncrement::new(c.len(), crate::skeleton::body_length(NORMAL_STENCIL_ON_HUMAN, self.body_extent) as f32, &device));
        let pose = PoseTensors { motion: increment, view, ..self.batch_pose(batch).clone() };
        let (r, rendered) = (batch.rays.len(), batch.rendered);
        let sampling = self.schedule.sampling(it);
        let shading = self.fit_light && needs(Input::Colour);
        let (deferred, parts) = render_in_parts(
            &model.field,
            &pose,
            &batch.rays.first(rendered),
            sampling,
            &batch.jitter,
            shading.then_some(self.gradient),
            &device,
            self.render_threads,
        );
        clock.mark_render(&deferred);
        // Only rays that meet a bound were rendered: the rest are appended as background.
        let background = |t: Tensor<2>| if rendered < r { Tensor::cat(vec![t, Tensor::zeros([r - rendered, 3], &device)], 0) } else { t };
        let accumulation = if rendered < r {
            Tensor::cat(vec![deferred.accumulation.clone(), Tensor::zeros([r - rendered], &device)], 0)
        } else {
            deferred.accumulation.clone()
        };
        // One ray a pixel, in the targets' order.
        let pixels = batch.masks.len();
        let albedo = background(deferred.albedo.clone());
        let target: Tensor<2> = Tensor::from_data(TensorData::new(batch.colours.clone(), [pixels, 3]), &device);
        let mask: Tensor<1> = Tensor::from_data(TensorData::new(batch.masks.clone(), [pixels]), &device);
        // Near a mask's edge with a plate, the render over what lies behind the body.
        let behind = (!batch.backgrounds.is_empty()).then(|| {
            let plate: Tensor<2> = Tensor::from_data(TensorData::new(batch.backgrounds.clone(), [pixels, 3]), &device);
            let weights: Tensor<1> = Tensor::from_data(TensorData::new(batch.mask_weights.clone(), [pixels]), &device);
            (plate, weights)
        });
        let colour = needs(Input::Colour).then(|| {
            let body = match &deferred.normal {
                Some(normal) => background(self.shaded(model, batch, &deferred, normal)),
                None => albedo.clone(),
            };
            self.as_seen(body, batch, colours, &accumulation, behind.as_ref().map(|b| &b.0))
        });
        clock.mark(5);
        let mask_weights = behind.map(|b| b.1);
        let mut inputs = Inputs {
            accumulation,
            mask,
            mask_weights,
            albedo,
            target,
            colour,
            densities: Vec::new(),
            widths: None,
            means: None,
            ambient: None,
            gradient: None,
            normal_pairs: None,
            motion: motion.map(|(m, k)| m.leaf_and_smooth(k, &device)),
            cameras: cameras.map(|c| c.leaf(&device)),
        };
        let leaves = Leaves {
            motion: motion.zip(inputs.motion.as_ref()).map(|((_, k), m)| (k, m.correction.clone(), deferred.motion_leaves.clone())),
            cameras: inputs.cameras.clone().map(|leaf| (leaf, deferred.view_leaves.clone())),
        };
        if self.error_rays > 0.0 {
            record_errors(error_maps, batch, &inputs);
        }
        self.gaussian_inputs(model, batch, it, &deferred, &mut inputs);
        clock.mark(6);
        self.regulariser_inputs(model, batch, it, &deferred, &mut inputs);
        let terms = crate::losses::TERMS
            .iter()
            .filter_map(|term| {
                let weight = self.schedule.weight(term.name, it);
                (term.always || weight > 0.0).then(|| (term.value)(&inputs).map(|value| (term.name, weight, value))).flatten()
            })
            .collect();
        (terms, parts, leaves)
    }

    /// The pose a batch is rendered in: its frame's, as the motion's refinement has corrected it.
    fn batch_pose<'b>(&'b self, batch: &'b Batch) -> &'b PoseTensors {
        batch.corrected.as_ref().map_or(&self.frames[batch.frame].pose_tensors, |c| &c.1)
    }

    /// Each ray's body as its camera saw it: in the camera's colour, then over what lies behind
    /// the body (the plate near a mask's edge, black elsewhere).
    fn as_seen(
        &self,
        body: Tensor<2>,
        batch: &Batch,
        colours: Option<(&super::camera_colour::CameraColours, Tensor<2>)>,
        accumulation: &Tensor<1>,
        plate: Option<&Tensor<2>>,
    ) -> Tensor<2> {
        let body = match colours {
            Some((colours, leaf)) => {
                let cameras: Vec<usize> = batch.sources.iter().map(|s| self.scene.views[s.0].camera).collect();
                body * colours.per_ray(leaf, &cameras, &self.device)
            }
            None => body,
        };
        match plate {
            Some(plate) => body + plate.clone() * (accumulation.clone().neg() + 1.0).reshape([batch.masks.len(), 1]),
            None => body,
        }
    }

    /// The batch's colour under its light, with the shadows cast by the Gaussians' values: they
    /// learn only from their fit to the field's density.
    fn shaded(&self, model: &Avatar, batch: &Batch, deferred: &Deferred, normal: &Tensor<2>) -> Tensor<2> {
        let pose = self.batch_pose(batch);
        let casters = model.gaussians.posed_values(pose);
        let batch_light = model.light_at(batch.light);
        // The pixels drawn where the fit is wrong teach the light nothing: it learns from the
        // same pixels as a batch without them.
        let error_drawn = batch.sources.iter().any(|s| s.2);
        let weights = error_drawn.then(|| {
            let ray_weights: Vec<f32> = batch.sources.iter().take(batch.rendered).map(|source| if source.2 { 0.0 } else { 1.0 }).collect();
            Tensor::<1>::from_data(TensorData::new(ray_weights, [batch.rendered]), &self.device)
        });
        batch_light.shade_weighted(deferred.albedo.clone(), deferred.surface.clone(), normal.clone(), &casters, weights.as_ref())
    }

    /// The Gaussians' inputs the active terms need: their mixture against the field's density
    /// at the density samples, their widths, their means, and the light's ambient.
    fn gaussian_inputs(&self, model: &Avatar, batch: &Batch, it: usize, deferred: &Deferred, inputs: &mut Inputs) {
        let needs = |input: Input| self.schedule.needs(input, it);
        let pose = self.batch_pose(batch);
        if !batch.density_samples.is_empty() {
            // The Gaussians posed in the graph only when a loss reaches them: burn registers every
            // operation on a parameter in the parameter's graph, and what no backward consumes
            // stays there, swept at every backward: 300 steps of an unused posing piled up 18,000
            // nodes, and the first stage's steps took up to twice as long.
            let posed = model.gaussians.posed(pose);
            let count = batch.density_samples.len();
            let idx = Tensor::<1, Int>::from_data(TensorData::new(batch.density_samples.clone(), [count]), &self.device);
            let points = deferred.sample_points.clone().detach().select(0, idx.clone());
            // The Gaussians' amplitudes are optical density per body unit.
            let field_density = deferred.sample_density.clone().detach().select(0, idx) * model.light.unit;
            let mixture = GaussianParams::mixture_density(&posed, points);
            inputs.densities.push((mixture.clone(), field_density.clone()));
            // Also at the density the shadows are cast with, when asked (the first light's
            // scale, detached: the light does not learn from how well the Gaussians fit): the
            // first term keeps the body opaque to them, the second fits away the faint tails
            // outside it that a shadow sees at the light's scale.
            if self.density_at_shadow_scale {
                let scale = model.light.density_scale().detach();
                inputs.densities.push((mixture * scale.clone(), field_density * scale));
            }
        }
        if needs(Input::Widths) {
            inputs.widths = Some(model.gaussians.scales() / model.light.unit);
        }
        if needs(Input::Means) {
            inputs.means = Some((model.gaussians.means.val(), self.mean_targets.clone() / model.light.unit));
        }
        if needs(Input::Ambient) && self.fit_light {
            // The ambient target is a fraction of the batch light's irradiance: for the first
            // light (irradiance 1, or a point light whose strength is free) its ambient itself;
            // for another sun, whose irradiance is learned, its ambient over that irradiance.
            // (The same prior on every light at every step did no better on human-suns.)
            let batch_light = model.light_at(batch.light);
            let ambient = match (batch.light, batch_light.kind) {
                (k, LightKind::Directional) if k > 0 => batch_light.ambient() / batch_light.irradiance(),
                _ => model.light.ambient(),
            };
            inputs.ambient = Some((ambient, self.schedule.ambient_target));
        }
    }

    /// The SDF's gradient at the batch's regulariser samples, and the unit normals there and at
    /// the curvature's offsets from them.
    fn regulariser_inputs(&self, model: &Avatar, batch: &Batch, it: usize, deferred: &Deferred, inputs: &mut Inputs) {
        let q = batch.regulariser_samples.len();
        if q == 0 {
            return;
        }
        let pose = self.batch_pose(batch);
        let idx = Tensor::<1, Int>::from_data(TensorData::new(batch.regulariser_samples.clone(), [q]), &self.device);
        let points = deferred.sample_points.clone().detach().select(0, idx);
        let gradient = model.field.sdf_gradient(points.clone(), pose, self.gradient);
        if !batch.curvature_offsets.is_empty() {
            let perturbed = points + Tensor::<2>::from_data(TensorData::new(batch.curvature_offsets.clone(), [q, 3]), &self.device);
            let g2 = model.field.sdf_gradient(perturbed, pose, self.gradient);
            let unit = crate::render::unit_rows;
            inputs.normal_pairs = Some((unit(gradient.clone()), unit(g2)));
        }
        if self.schedule.needs(Input::Gradient, it) {
            inputs.gradient = Some(gradient);
        }
    }

    /// Backward's gradients applied: one Adam step per group, the light only when its stage
    /// has started (and only the batch's light, the only one in the graph), a sun kept in its
    /// search's cone.
    fn update(
        &self,
        model: Avatar,
        mut grads: burn::tensor::Gradients,
        forks: Vec<AvatarField>,
        light_index: usize,
        optimisers: &mut super::Optimisers,
        it: usize,
    ) -> Avatar {
        let light_active = self.fit_light && it >= self.schedule.light_from;
        let Avatar { mut field, gaussians, light, mut other_lights } = model;
        let mut light = if light_index == 0 { light } else { std::mem::replace(&mut other_lights[light_index - 1], light) };
        // A grid's feature tables have their own learning rate and optimiser.
        let grid = field.grid.take();
        // The forks that rendered parts of the batch on other threads hold gradients of the
        // same parameters: summed into the field's.
        let mut fork_grids = Vec::new();
        let fork_fields: Vec<AvatarField> = forks
            .into_iter()
            .map(|mut fork| {
                fork_grids.extend(fork.grid.take());
                fork
            })
            .collect();
        let g_grid = grid.as_ref().map(|g| sum_gradients(&mut grads, g, &fork_grids));
        let g_field = sum_gradients(&mut grads, &field, &fork_fields);
        // The forks share the parameters' buffers: dropped, they leave the optimisers the only
        // holders, who then update the values where they lie.
        drop((fork_grids, fork_fields));
        let g_gaussians = GradientsParams::from_module(&mut grads, &gaussians);
        let g_light = GradientsParams::from_module(&mut grads, &light);
        let lr = |g: &str| self.schedule.learning_rate(g, it);
        let mut field = optimisers.field.step(lr("field"), field, g_field);
        field.grid = match (grid, g_grid) {
            (Some(grid), Some(g)) => Some(optimisers.features.step(lr("features"), grid, g)),
            (grid, _) => grid,
        };
        let gaussians = optimisers.gaussians.step(lr("gaussians"), gaussians, g_gaussians);
        light = if light_active { optimisers.light.step(lr("light"), light, g_light) } else { light };
        light = match self.cones[light_index] {
            Some((axis, angle)) if light_active => light.kept_in_cone(axis, angle),
            _ => light,
        };
        if light_index > 0 {
            light = std::mem::replace(&mut other_lights[light_index - 1], light);
        }
        Avatar { field, gaussians, light, other_lights }
    }

    /// After the update, in one read: where the light is (`FittedLight::location`, when the fit
    /// has one to report), the sum of the parameters, not finite when the update left one not
    /// finite (`avatar::parameter_sum`; NaN when the read failed), and the values of each of
    /// `extra` (empty where none).
    fn read_after_update<const E: usize>(&self, model: &Avatar, extra: [Option<Tensor<1>>; E]) -> (Option<[f64; 3]>, f32, [Vec<f32>; E]) {
        let location = self.fit_light.then(|| model.light.location_tensor()).flatten();
        let sum = crate::avatar::parameter_sum(model);
        let parts: Vec<Option<Tensor<1>>> = [sum, location].into_iter().chain(extra).collect();
        let lengths: Vec<usize> = parts.iter().map(|t| t.as_ref().map_or(0, |t| t.dims()[0])).collect();
        let reported: Vec<Tensor<1>> = parts.into_iter().flatten().collect();
        let read = match reported.is_empty() {
            true => Vec::new(),
            false => crate::backend::host_values(Tensor::cat(reported, 0)),
        };
        let part = |k: usize| read.get(lengths[..k].iter().sum::<usize>()..lengths[..=k].iter().sum::<usize>()).unwrap_or(&[]);
        let sum = if lengths[0] > 0 { part(0).first().copied().unwrap_or(f32::NAN) } else { 0.0 };
        (crate::shading::location_of(part(1)), sum, std::array::from_fn(|k| part(k + 2).to_vec()))
    }

    /// Moves the field's average toward the parameters of the step just taken, or starts it at
    /// them on the first step of the learning rates' decay (`field_average_half_life`).
    fn update_average(&self, state: &mut TrainState) {
        let half_life = self.schedule.field_average_half_life;
        if half_life <= 0.0 || state.iteration <= self.schedule.field_lr_decay_from {
            return;
        }
        match &mut state.average {
            Some(average) => average.update(&state.model.field, crate::averaging::ParameterAverage::keep_for_half_life(half_life)),
            None => state.average = Some(crate::averaging::ParameterAverage::start(&state.model.field)),
        }
    }
}

/// Each pixel's error (coverage, weighted as the mask is trusted, and colour once it is
/// fitted) into its view's error map.
fn record_errors(error_maps: &mut [Option<crate::error_map::ErrorMap>], batch: &Batch, inputs: &Inputs) {
    let coverage = (inputs.accumulation.clone().detach() - inputs.mask.clone()).abs();
    let coverage = match &inputs.mask_weights {
        Some(weights) => coverage * weights.clone(),
        None => coverage,
    };
    let pixels = batch.masks.len();
    let error = match &inputs.colour {
        Some(c) => coverage + (c.clone().detach() - inputs.target.clone()).abs().mean_dim(1).reshape([pixels]),
        None => coverage,
    };
    let error = crate::backend::host_values(error);
    for (&(v, pixel, _), e) in batch.sources.iter().zip(error) {
        if let Some(map) = error_maps.get_mut(v).and_then(|m| m.as_mut()) {
            map.record(pixel, e);
        }
    }
}
