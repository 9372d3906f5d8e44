//! Adam in one pass over a parameter's values: burn's Adam (the same state, so the same
//! checkpoint record, and the same f32 arithmetic in the same order) with its thirteen
//! element-wise tensor operations fused into one loop over the host's memory, split over the
//! cores. On a device that keeps its tensors (a GPU) the loop would need the values brought
//! down: there it is burn's tensor operations, which a GPU runs in parallel anyway.
//!
//! Why: a grid's feature tables are a million values, and Adam's tensor operations each read and
//! wrote all of them on one thread: with the rest of the update, 3.5-4.6 ms of a 40-50 ms step.

use burn::optim::{AdamState, AdaptiveMomentumState, LearningRate, Optimizer};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

/// Values per task of the fused loop: a few cache-sized blocks, enough to spread over the cores
/// without a task's overhead showing.
const CHUNK: usize = 1 << 15;

/// Adam's constants (burn's decay rates, `host_adam::BETAS`; `epsilon` a caller's).
#[derive(Clone, Copy, Debug)]
pub struct FusedAdam {
    beta_1: f32,
    beta_2: f32,
    epsilon: f32,
}

impl FusedAdam {
    /// Adam with burn's decay rates and `epsilon` guarding the second moment.
    pub fn new(epsilon: f32) -> Self {
        let (beta_1, beta_2) = super::host_adam::BETAS;
        Self { beta_1: beta_1 as f32, beta_2: beta_2 as f32, epsilon }
    }

    /// A whole module's optimiser of this Adam.
    pub fn init(self) -> burn::optim::ModuleOptimizer {
        burn::optim::ModuleOptimizer::from(self)
    }

    /// Step `time` (from 1) factors: the first moment's bias correction folded with the
    /// second's square root, and the guard scaled as burn scales it.
    fn factors(&self, time: usize) -> (f32, f32) {
        let time = time.min(i32::MAX as usize) as i32;
        let correction_2 = (1.0 - self.beta_2.powi(time)).sqrt();
        (correction_2 / (1.0 - self.beta_1.powi(time)), self.epsilon * correction_2)
    }
}

impl Optimizer for FusedAdam {
    type State<const D: usize> = AdamState<D>;

    fn step<const D: usize>(&self, lr: LearningRate, tensor: Tensor<D>, grad: Tensor<D>, state: Option<Self::State<D>>) -> (Tensor<D>, Option<Self::State<D>>) {
        let device = tensor.device();
        let moments = state.map(|s| (s.momentum.time, s.momentum.moment_1, s.momentum.moment_2));
        let (tensor, time, m, v) = match crate::backend::on_host(&device) {
            true => self.on_host(lr, tensor, grad, moments, &device),
            false => self.by_tensors(lr, tensor, grad, moments),
        };
        (tensor, Some(AdamState::new(AdaptiveMomentumState::new(time, m, v))))
    }

    fn to_device<const D: usize>(mut state: Self::State<D>, device: &Device) -> Self::State<D> {
        state.momentum = state.momentum.to_device(device);
        state
    }
}

/// A parameter, its step count and its two moments.
type Stepped<const D: usize> = (Tensor<D>, usize, Tensor<D>, Tensor<D>);

impl FusedAdam {
    /// The step as burn's Adam takes it, by tensor operations.
    fn by_tensors<const D: usize>(&self, lr: LearningRate, tensor: Tensor<D>, grad: Tensor<D>, moments: Option<(usize, Tensor<D>, Tensor<D>)>) -> Stepped<D> {
        let (time, m, v) = match moments {
            Some((time, m, v)) => (
                time + 1,
                m.mul_scalar(self.beta_1).add(grad.clone().mul_scalar(1.0 - self.beta_1)),
                v.mul_scalar(self.beta_2).add(grad.square().mul_scalar(1.0 - self.beta_2)),
            ),
            None => (1, grad.clone().mul_scalar(1.0 - self.beta_1), grad.square().mul_scalar(1.0 - self.beta_2)),
        };
        let (factor, guard) = self.factors(time);
        let delta = m.clone().mul_scalar(factor).div(v.clone().sqrt().add_scalar(guard)).mul_scalar(lr);
        (tensor - delta, time, m, v)
    }

    /// The step in one pass over the host's memory: the values, and the moments, updated where
    /// they lie when nothing else holds them (the backend hands its buffer over), split over the
    /// cores. Falls back to the tensor operations when a tensor's values are not f32.
    fn on_host<const D: usize>(
        &self,
        lr: LearningRate,
        tensor: Tensor<D>,
        grad: Tensor<D>,
        moments: Option<(usize, Tensor<D>, Tensor<D>)>,
        device: &Device,
    ) -> Stepped<D> {
        let shape = tensor.shape();
        let n = shape.num_elements();
        let (time, m, v) = match moments {
            Some((time, m, v)) => (time + 1, Some(m), Some(v)),
            None => (1, None, None),
        };
        let zeros = || TensorData::new(vec![0.0f32; n], shape.clone());
        let mut values = tensor.into_data();
        let mut first = m.map_or_else(zeros, |m| m.into_data());
        let mut second = v.map_or_else(zeros, |v| v.into_data());
        let gradient = grad.into_data();
        let (factor, guard) = self.factors(time);
        let back = |data: TensorData| Tensor::<D>::from_data(data, device);
        let slices = (values.as_mut_slice::<f32>(), first.as_mut_slice::<f32>(), second.as_mut_slice::<f32>(), gradient.as_slice::<f32>());
        match slices {
            (Ok(x), Ok(m), Ok(v), Ok(g)) if [x.len(), m.len(), v.len(), g.len()] == [n; 4] => {
                let adam = Constants { beta_1: self.beta_1, beta_2: self.beta_2, factor, guard, lr: lr as f32 };
                x.par_chunks_mut(CHUNK)
                    .zip(m.par_chunks_mut(CHUNK))
                    .zip(v.par_chunks_mut(CHUNK))
                    .zip(g.par_chunks(CHUNK))
                    .for_each(|(((x, m), v), g)| adam.update(x, m, v, g));
            }
            _ => {
                let moments = (time > 1).then(|| (time - 1, back(first), back(second)));
                return self.by_tensors(lr, back(values), back(gradient), moments);
            }
        }
        (back(values), time, back(first), back(second))
    }
}

/// One step's numbers, in f32 as burn's tensor operations hold them.
struct Constants {
    beta_1: f32,
    beta_2: f32,
    factor: f32,
    guard: f32,
    lr: f32,
}

impl Constants {
    /// Adam on a block of values: each operation burn's Adam makes, in its order (no fused
    /// multiply-add: the results are its to the bit).
    fn update(&self, x: &mut [f32], m: &mut [f32], v: &mut [f32], g: &[f32]) {
        let (a1, a2) = (1.0 - self.beta_1, 1.0 - self.beta_2);
        for (((x, m), v), &g) in x.iter_mut().zip(m.iter_mut()).zip(v.iter_mut()).zip(g) {
            *m = *m * self.beta_1 + g * a1;
            *v = *v * self.beta_2 + (g * g) * a2;
            let step = (*m * self.factor) / (v.sqrt() + self.guard);
            *x -= step * self.lr;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::{Module, Param};

    #[derive(Module, Debug)]
    struct Table {
        rows: Param<Tensor<2>>,
    }

    fn table(values: &[f32], device: &Device) -> Table {
        Table { rows: Param::from_tensor(Tensor::from_data(TensorData::new(values.to_vec(), [values.len() / 4, 4]), device)) }
    }

    /// The values after `steps` steps of `first` on a loss whose gradient changes with the values;
    /// with `then`, `first`'s state is handed to it halfway through by a checkpoint's record.
    fn run(mut optimiser: burn::optim::ModuleOptimizer, then: Option<burn::optim::ModuleOptimizer>, steps: usize) -> Vec<f32> {
        let device = crate::backend::Backend::Flex.device();
        let n = 4 * 20_000;
        let mut module = table(&start_values(), &device);
        let mut then = then;
        for step in 0..steps {
            if step == steps / 2 {
                if let Some(next) = then.take() {
                    optimiser = next.load_record(optimiser.to_record());
                }
            }
            let target: Vec<f32> = (0..n).map(|k| ((k * 31 + step * 17) % 97) as f32 / 97.0).collect();
            let target = Tensor::<2>::from_data(TensorData::new(target, [n / 4, 4]), &device);
            // Some values get no gradient this step (their moments still decay).
            let weights: Vec<f32> = (0..n).map(|k| if (k + step) % 5 == 0 { 0.0 } else { 1.0 }).collect();
            let weights = Tensor::<2>::from_data(TensorData::new(weights, [n / 4, 4]), &device);
            let loss = ((module.rows.val() - target).powf_scalar(2.0) * weights).sum();
            let mut grads = loss.backward();
            let grads = burn::optim::GradientsParams::from_module(&mut grads, &module);
            module = optimiser.step(1e-2 * (step + 1) as f64, module, grads);
        }
        crate::backend::host_values(module.rows.val())
    }

    fn differing(a: &[f32], b: &[f32]) -> usize {
        assert_eq!(a.len(), b.len());
        a.iter().zip(b).filter(|(x, y)| x.to_bits() != y.to_bits()).count()
    }

    #[test]
    fn the_fused_pass_is_burns_adam_to_the_bit() {
        for epsilon in [1e-15f32, 1e-5] {
            let burns = run(burn::optim::AdamConfig::new().with_epsilon(epsilon).init(), None, 6);
            let fused = run(FusedAdam::new(epsilon).init(), None, 6);
            assert_eq!(differing(&fused, &burns), 0, "epsilon {epsilon}: of {} values", fused.len());
            assert!(fused.iter().zip(&start_values()).filter(|(a, b)| (*a - *b).abs() > 1e-3).count() > fused.len() / 2, "the values moved");
            // A checkpoint written by burn's Adam goes on in the fused one, and back.
            let resumed = run(burn::optim::AdamConfig::new().with_epsilon(epsilon).init(), Some(FusedAdam::new(epsilon).init()), 6);
            assert_eq!(differing(&resumed, &burns), 0, "burn's record resumed by the fused Adam");
            let back = run(FusedAdam::new(epsilon).init(), Some(burn::optim::AdamConfig::new().with_epsilon(epsilon).init()), 6);
            assert_eq!(differing(&back, &burns), 0, "the fused Adam's record resumed by burn's");
        }
        // A different guard changes the result: the comparison can fail.
        let other = run(FusedAdam::new(1e-3).init(), None, 6);
        assert!(differing(&other, &run(FusedAdam::new(1e-5).init(), None, 6)) > 0);
    }

    fn start_values() -> Vec<f32> {
        (0..4 * 20_000).map(|k| ((k * 7919) % 1000) as f32 / 500.0 - 1.0).collect()
    }

    #[test]
    fn the_tensor_operations_are_burns_adam_too() {
        let device = crate::backend::Backend::Flex.device().without_autodiff();
        let adam = FusedAdam::new(1e-8);
        let x = Tensor::<1>::from_data(TensorData::new(vec![0.5f32, -1.0, 2.0, 0.0], [4]), &device);
        let g = Tensor::<1>::from_data(TensorData::new(vec![0.1f32, -0.3, 0.0, 2.0], [4]), &device);
        let (mut by_tensors, mut on_host) = ((x.clone(), None), (x, None));
        for _ in 0..3 {
            let (t, s) = (adam.by_tensors(0.1, by_tensors.0, g.clone(), by_tensors.1), adam.on_host(0.1, on_host.0, g.clone(), on_host.1, &device));
            by_tensors = (t.0, Some((t.1, t.2, t.3)));
            on_host = (s.0, Some((s.1, s.2, s.3)));
        }
        let (a, b) = (crate::backend::host_values(by_tensors.0), crate::backend::host_values(on_host.0));
        assert_eq!(a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), "{a:?} against {b:?}");
        assert_ne!(a[3], 0.0, "a value with a gradient moved");
    }
}
