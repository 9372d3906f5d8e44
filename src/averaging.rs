//! An exponential moving average of a module's float parameters (Polyak averaging): what a fit
//! shows once its learning rates have fallen, instead of the last step's parameters.
//!
//! Adam moves every parameter by about its learning rate at each step whatever the gradient's
//! size, so even at a tenth of its rate a feature table keeps jittering with the batch's noise
//! and a fit's score wobbles from one checkpoint to the next. The average over the last
//! hundred-odd steps keeps what the steps agree on and cancels what they do not; training goes
//! on from the last step's parameters, unchanged.

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::Tensor;

/// The running average, one flattened tensor per float parameter in the module's visiting
/// order, held without autodiff.
#[derive(Clone)]
pub struct ParameterAverage {
    values: Vec<Tensor<1>>,
}

/// Every float parameter's value, flattened and detached, in visiting order.
fn flattened<M: Module>(module: &M) -> Vec<Tensor<1>> {
    struct Collect(Vec<Tensor<1>>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            // Off the autodiff graph: the average is arithmetic on values, never differentiated.
            let value = param.val().without_autodiff();
            let n = value.shape().num_elements();
            self.0.push(value.reshape([n]));
        }
    }
    let mut collect = Collect(Vec::new());
    module.visit(&mut collect);
    collect.0
}

/// Whether two lists of flattened parameters have the same shapes.
fn same_layout(a: &[Tensor<1>], b: &[Tensor<1>]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.shape() == y.shape())
}

impl ParameterAverage {
    /// An average that starts at the module's parameters.
    pub fn start<M: Module>(module: &M) -> Self {
        Self { values: flattened(module) }
    }

    /// Moves the average toward the module's parameters: `average = keep x average + (1 - keep)
    /// x parameters`. A module of another layout restarts it.
    pub fn update<M: Module>(&mut self, module: &M, keep: f64) {
        let current = flattened(module);
        if !same_layout(&self.values, &current) {
            self.values = current;
            return;
        }
        let keep = keep.clamp(0.0, 1.0);
        self.values = std::mem::take(&mut self.values).into_iter().zip(current).map(|(average, value)| average * keep + value * (1.0 - keep)).collect();
    }

    /// The module with its float parameters replaced by the average (each keeps its id and
    /// whether it takes gradients). `None` when the module's layout is not the average's.
    pub fn applied<M: Module>(&self, module: M) -> Option<M> {
        if !same_layout(&self.values, &flattened(&module)) {
            return None;
        }
        struct Replace<'a>(std::slice::Iter<'a, Tensor<1>>);
        impl ModuleMapper for Replace<'_> {
            fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
                let Some(average) = self.0.next() else { return param };
                param.map(|value| {
                    let replaced = average.clone().reshape(value.shape());
                    match (value.is_autodiff(), value.is_require_grad()) {
                        (true, grad) => replaced.autodiff().set_require_grad(grad),
                        (false, _) => replaced,
                    }
                })
            }
        }
        Some(module.map(&mut Replace(self.values.iter())))
    }

    /// The average's per-step weight on the past for a half-life of `half_life` steps.
    pub fn keep_for_half_life(half_life: f64) -> f64 {
        if half_life > 0.0 {
            0.5f64.powf(1.0 / half_life)
        } else {
            0.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::{Linear, LinearConfig};
    use burn::tensor::{Device, TensorData};

    fn values<M: Module>(module: &M) -> Vec<f32> {
        flattened(module).into_iter().flat_map(crate::backend::host_values).collect()
    }

    fn linear_with(value: f32, device: &Device) -> Linear {
        let layer: Linear = LinearConfig::new(2, 3).init(device);
        layer.map(&mut {
            struct Fill(f32);
            impl ModuleMapper for Fill {
                fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
                    let fill = self.0;
                    param.map(|t| {
                        let shape = t.shape();
                        let n = shape.num_elements();
                        Tensor::<1>::from_data(TensorData::new(vec![fill; n], [n]), &t.device()).reshape(shape)
                    })
                }
            }
            Fill(value)
        })
    }

    #[test]
    fn the_average_follows_the_exponential_recurrence() {
        let device = Device::flex();
        let mut average = ParameterAverage::start(&linear_with(1.0, &device));
        average.update(&linear_with(3.0, &device), 0.75);
        average.update(&linear_with(5.0, &device), 0.75);
        // 1 -> 0.75 + 0.75 = 1.5 -> 1.125 + 1.25 = 2.375
        let applied = average.applied(linear_with(-7.0, &device)).unwrap();
        let got = values(&applied);
        assert_eq!(got.len(), 2 * 3 + 3);
        assert!(got.iter().all(|v| (v - 2.375).abs() < 1e-6), "{got:?}");
    }

    #[test]
    fn a_half_life_halves_the_weight_of_the_past() {
        let keep = ParameterAverage::keep_for_half_life(100.0);
        assert!((keep.powi(100) - 0.5).abs() < 1e-12);
        assert_eq!(ParameterAverage::keep_for_half_life(0.0), 0.0);
    }

    #[test]
    fn an_averaged_module_still_trains_on_the_autodiff_device() {
        let device = Device::flex().autodiff();
        let layer: Linear = LinearConfig::new(2, 3).init(&device);
        let mut average = ParameterAverage::start(&layer);
        average.update(&linear_with(0.5, &device), 0.5);
        let averaged = average.applied(layer).unwrap();
        let input = Tensor::<2>::from_data(TensorData::new(vec![1.0f32, 2.0], [1, 2]), &device);
        let grads = averaged.forward(input).sum().backward();
        let weight = averaged.weight.grad(&grads).expect("the averaged weight takes gradients");
        assert_eq!(weight.into_data().convert::<f32>().try_to_vec::<f32>().unwrap(), vec![1.0, 1.0, 1.0, 2.0, 2.0, 2.0]);
    }

    #[test]
    fn another_layout_is_not_replaced() {
        let device = Device::flex();
        let average = ParameterAverage::start(&linear_with(1.0, &device));
        let other: Linear = LinearConfig::new(4, 3).init(&device);
        assert!(average.applied(other).is_none());
    }
}
