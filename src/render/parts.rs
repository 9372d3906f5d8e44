//! A training step's render split over threads: the rays in parts, each part rendered through
//! a fork of the field on its own thread, and the forks' gradients summed back into the one
//! field's.

use super::*;

/// Fewest rays a part of a split render holds: below this a second thread costs more than it saves.
const MIN_RAYS_PER_PART: usize = 64;

/// `render`, the rays cut into up to `parts` runs rendered at once on as many threads, their
/// outputs joined in ray order. Why: most of a step's tensor operations run on one thread
/// (flex parallelises matrix products, not the element-wise work between them), so a second
/// core sat idle. Every ray's samples and arithmetic are its own, so the result is the unsplit
/// render's (a test pins them). Each part renders through its own fork of `field` (the same
/// parameters, same ids, as leaves of a graph of its own: burn's autodiff graph client is not
/// safe for several threads registering nodes of one shared graph), so after the backward pass
/// the parameters' gradients are the sum of the field's and of every returned fork's
/// (`sum_gradients`). One part: `field` itself, no forks.
#[allow(clippy::too_many_arguments)]
pub fn render_in_parts(
    field: &AvatarField,
    pose: &PoseTensors,
    rays: &RaySet,
    sampling: Sampling,
    jitter: &[f32],
    normals: Option<GradientMethod>,
    device: &Device,
    parts: usize,
) -> (Deferred, Vec<AvatarField>) {
    let r = rays.len();
    let parts = parts.min(r / MIN_RAYS_PER_PART).max(1);
    if parts == 1 {
        return (render(field, pose, rays, sampling, jitter, normals, device), Vec::new());
    }
    use rayon::prelude::*;
    let per_part = r.div_ceil(parts);
    let forks: Vec<AvatarField> = (0..parts).map(|_| field.clone().fork(device)).collect();
    // A motion or view increment, like the field, is a leaf of each part's own graph.
    let poses: Vec<PoseTensors> = (0..parts)
        .map(|_| PoseTensors { motion: pose.motion.as_ref().map(|m| m.fork()), view: pose.view.as_ref().map(|v| v.fork()), ..pose.clone() })
        .collect();
    let rendered: Vec<Deferred> = forks
        .par_iter()
        .zip(&poses)
        .enumerate()
        .map(|(k, (fork, pose))| {
            let (lo, hi) = (k * per_part, ((k + 1) * per_part).min(r));
            render(fork, pose, &rays.range(lo, hi), sampling, &sampling.jitter_of(jitter, r, lo, hi), normals, device)
        })
        .collect();
    (Deferred::cat(rendered), forks)
}

/// The gradients of `module`'s parameters, summed over it and its `forks` (the same
/// parameters as leaves of other graphs: `render::render_in_parts`).
pub fn sum_gradients<M: Module>(grads: &mut burn::tensor::Gradients, module: &M, forks: &[M]) -> burn::optim::GradientsParams {
    use burn::optim::GradientsParams;
    struct Adder {
        into: GradientsParams,
        from: GradientsParams,
    }
    impl burn::module::ModuleVisitor for Adder {
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            if let Some(g) = self.from.remove::<D>(param.id) {
                let sum = match self.into.remove::<D>(param.id) {
                    Some(sum) => sum + g,
                    None => g,
                };
                self.into.register(param.id, sum);
            }
        }
    }
    let mut adder = Adder { into: GradientsParams::from_module(grads, module), from: GradientsParams::new() };
    for fork in forks {
        adder.from = GradientsParams::from_module(grads, fork);
        module.visit(&mut adder);
    }
    adder.into
}
