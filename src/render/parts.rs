//! A training step's render split over threads: the rays in parts, each part rendered through
//! a fork of the field on its own thread, each part's backward pass run on its own thread too,
//! and the forks' gradients summed back into the one field's.

use super::*;

/// Fewest rays a part of a split render holds: below this a second thread costs more than it saves.
const MIN_RAYS_PER_PART: usize = 64;

/// `render`, the rays cut into up to `parts` runs rendered at once on as many threads, their
/// outputs joined in ray order. Why: most of a step's tensor operations run on one thread
/// (flex parallelises matrix products, not the element-wise work between them), so a second
/// core sat idle. Every ray's samples and arithmetic are its own, so the result is the unsplit
/// render's (a test pins them). Each part renders through its own fork of `field` (the same
/// parameters, same ids, as leaves of a graph of its own: burn's autodiff graph client is not
/// safe for several threads registering nodes of one shared graph). The joined outputs are
/// leaves of the losses' graph cut from the parts' graphs (`Parts::backward` carries the
/// gradient across), so the parts' backward passes run on their threads too; after it the
/// parameters' gradients are the sum of the field's and of every fork's (`sum_gradients`).
/// One part: `field` itself, no forks, nothing cut.
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
) -> (Deferred, Parts) {
    let r = rays.len();
    let parts = parts.min(r / MIN_RAYS_PER_PART).max(1);
    if parts == 1 {
        return (render(field, pose, rays, sampling, jitter, normals, device), Parts::default());
    }
    let per_part = r.div_ceil(parts);
    let forks: Vec<AvatarField> = (0..parts).map(|_| field.clone().fork(device)).collect();
    // A motion or view increment, like the field, is a leaf of each part's own graph.
    let poses: Vec<PoseTensors> = (0..parts)
        .map(|_| PoseTensors { motion: pose.motion.as_ref().map(|m| m.fork()), view: pose.view.as_ref().map(|v| v.fork()), ..pose.clone() })
        .collect();
    let jobs = forks.iter().zip(&poses).enumerate().map(|(k, (fork, pose))| {
        move || {
            let (lo, hi) = (k * per_part, ((k + 1) * per_part).min(r));
            cut(render(fork, pose, &rays.range(lo, hi), sampling, &sampling.jitter_of(jitter, r, lo, hi), normals, device))
        }
    });
    let rendered: Vec<(Deferred, Vec<Seam>)> = crate::threads::on_own_threads(jobs.collect());
    let (deferred, seams): (Vec<Deferred>, Vec<Vec<Seam>>) = rendered.into_iter().unzip();
    let leaves = deferred.iter().map(|d| d.motion_leaves.iter().chain(&d.view_leaves).cloned().collect()).collect();
    (Deferred::cat(deferred), Parts { forks, seams, leaves })
}

/// One output of a part's render, flattened: the tensor in the part's graph and the leaf that
/// stands for it in the losses' graph.
type Seam = (Tensor<1>, Tensor<1>);

/// A part's outputs as leaves of a graph of their own (those that carry a gradient; the rest as
/// they are), with the seams that join each back to the part's graph.
fn cut(part: Deferred) -> (Deferred, Vec<Seam>) {
    let mut seams = Vec::new();
    let mut leaf_of = |t: Tensor<1>| {
        if !t.is_tracked() {
            return t;
        }
        let leaf = t.clone().detach().require_grad();
        seams.push((t, leaf.clone()));
        leaf
    };
    let mut cut2 = |t: Tensor<2>| {
        let dims = t.dims();
        leaf_of(t.reshape([dims[0] * dims[1]])).reshape(dims)
    };
    let deferred = Deferred {
        albedo: cut2(part.albedo),
        surface: cut2(part.surface),
        normal: part.normal.map(&mut cut2),
        sample_points: cut2(part.sample_points),
        ..part
    };
    let mut cut1 = |t: Tensor<1>| leaf_of(t);
    let deferred =
        Deferred { accumulation: cut1(deferred.accumulation), depth: cut1(deferred.depth), sample_density: cut1(deferred.sample_density), ..deferred };
    (deferred, seams)
}

/// What a split render leaves for the backward pass: each part's fork of the field, the seams
/// between the losses' graph and the part's, and the increments (motion, view) its render
/// carried. Empty for a render in one part.
#[derive(Default)]
pub struct Parts {
    forks: Vec<AvatarField>,
    seams: Vec<Vec<Seam>>,
    leaves: Vec<Vec<Tensor<2>>>,
}

impl Parts {
    /// The gradients of `loss`: its own graph's backward pass, then every part's on a thread of
    /// its own, from the gradient each seam's leaf received (a part's graph differentiates
    /// `sum(output * gradient)`, whose gradient at the output is that gradient exactly). The
    /// forks' and the increments' gradients are moved into the one returned. Not `at_once`: the
    /// parts' passes one after the other on this thread (a benchmark's baseline; the same sums).
    pub fn backward(&self, loss: &Tensor<1>, at_once: bool) -> burn::tensor::Gradients {
        let mut grads = loss.backward();
        let roots: Vec<Option<Tensor<1>>> = self
            .seams
            .iter()
            .map(|seams| seams.iter().filter_map(|(output, leaf)| leaf.grad_remove(&mut grads).map(|g| (output.clone() * g).sum())).reduce(|a, b| a + b))
            .collect();
        let backward = |root: Option<Tensor<1>>| root.map(|root| root.backward());
        let parts: Vec<Option<burn::tensor::Gradients>> = match at_once {
            true => crate::threads::on_own_threads(roots.into_iter().map(|root| move || backward(root)).collect()),
            false => roots.into_iter().map(backward).collect(),
        };
        for ((fork, leaves), part) in self.forks.iter().zip(&self.leaves).zip(parts) {
            let Some(mut part) = part else { continue };
            fork.visit(&mut Mover { from: &mut part, into: &mut grads });
            for leaf in leaves {
                if let Some(g) = leaf.grad_remove(&mut part) {
                    leaf.grad_replace(&mut grads, g);
                }
            }
        }
        grads
    }

    /// The forks of the field the parts were rendered through.
    pub fn forks(&self) -> &[AvatarField] {
        &self.forks
    }

    /// The forks, taken.
    pub fn into_forks(self) -> Vec<AvatarField> {
        self.forks
    }
}

/// Moves every visited parameter's gradient from one set of gradients to another.
struct Mover<'a> {
    from: &'a mut burn::tensor::Gradients,
    into: &'a mut burn::tensor::Gradients,
}

impl burn::module::ModuleVisitor for Mover<'_> {
    fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
        let tensor = param.val();
        if let Some(g) = tensor.grad_remove(self.from) {
            tensor.grad_replace(self.into, g);
        }
    }
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
