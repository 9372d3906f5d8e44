//! The whole learnable avatar (field, Gaussians, training lights) as one burn module, and the
//! check that none of its parameters holds a NaN or an infinity.

use crate::field::AvatarField;
use crate::gaussians::GaussianParams;
use crate::shading::FittedLight;
use burn::module::Module;
use burn::tensor::Tensor;

/// The whole learnable avatar.
#[derive(Module, Debug)]
pub struct Avatar {
    pub field: AvatarField,
    pub gaussians: GaussianParams,
    /// The first training light (in the order of `Scene::training_lights`).
    pub light: FittedLight,
    /// The other training lights of a capture lit by several (none for one light, so a
    /// one-light checkpoint holds exactly what it did before there could be more).
    pub other_lights: Vec<FittedLight>,
}

impl Avatar {
    /// Training light `k` (0: `light`).
    pub fn light_at(&self, k: usize) -> &FittedLight {
        if k == 0 {
            &self.light
        } else {
            self.other_lights.get(k - 1).unwrap_or(&self.light)
        }
    }

    pub fn light_at_mut(&mut self, k: usize) -> &mut FittedLight {
        if k == 0 || k > self.other_lights.len() {
            &mut self.light
        } else {
            &mut self.other_lights[k - 1]
        }
    }

    /// How many training lights the avatar was fitted under.
    pub fn light_count(&self) -> usize {
        1 + self.other_lights.len()
    }
}

/// The sum of all of `module`'s parameters, on the device (none for a module without
/// parameters): a NaN or an infinity in any of them makes it NaN or infinite, as a hardware add
/// does whatever a compiler's fast maths assumes. A caller reads it with whatever else it reads
/// after an update, then looks for the parameter with `first_non_finite_of` only when it is not
/// finite. One reduction a parameter, where counting the NaN and infinite values took four
/// passes. (A sum of finite values that overflows sends the search looking, and it finds none.)
pub fn parameter_sum<M: Module>(module: &M) -> Option<Tensor<1>> {
    #[derive(Default)]
    struct Sum {
        total: Option<Tensor<1>>,
    }
    impl burn::module::ModuleVisitor for Sum {
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            // Off the autodiff graph: a float op on a detached tensor still registers a node there,
            // and one a parameter a step left behind slowed every later backward pass.
            let sum = param.val().without_autodiff().sum();
            self.total = Some(match self.total.take() {
                Some(total) => total + sum,
                None => sum,
            });
        }
    }
    let mut sum = Sum::default();
    module.visit(&mut sum);
    sum.total
}

/// The path (`field.hidden.0.weight`, ...) of the first parameter holding a NaN or an
/// infinity: the update that put it there must not reach a checkpoint.
pub fn first_non_finite<M: Module>(module: &M) -> Option<String> {
    let sum = parameter_sum(module).map_or(0.0, crate::backend::host_scalar);
    first_non_finite_of(module, sum)
}

/// `first_non_finite` with the module's `parameter_sum` already read: the parameters are read
/// one by one, for the name, only when it is not finite (NaN, a failed read, counts).
pub fn first_non_finite_of<M: Module>(module: &M, sum: f32) -> Option<String> {
    if sum.is_finite() {
        return None;
    }
    #[derive(Default)]
    struct Finder {
        path: Vec<String>,
        found: Option<String>,
    }
    impl burn::module::ModuleVisitor for Finder {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            if self.found.is_some() {
                return;
            }
            let values = crate::backend::host_values(param.val());
            if values.iter().any(|v| !v.is_finite()) {
                self.found = Some(self.path.iter().filter(|p| !p.is_empty()).cloned().collect::<Vec<_>>().join("."));
            }
        }
    }
    let mut finder = Finder::default();
    module.visit(&mut finder);
    finder.found
}

/// A fitted avatar and what rendering it needs to know of its fit: what `render`, `eval`,
/// `relight`, `report` and `export-mesh` work from, without the trainer's state.
#[derive(Clone, Debug)]
pub struct Fitted {
    /// The fitted parameters (the field's moving average applied once it started).
    pub model: Avatar,
    /// The device it was fitted or restored on (with autodiff; `without_autodiff` to render).
    pub device: burn::tensor::Device,
    /// The kind of the training lights as fitted (uniform when no light was fitted), and
    /// whether a light was fitted at all.
    pub light_kind: crate::shading::LightKind,
    pub fit_light: bool,
    /// The pixel footprint the fit modelled.
    pub footprint: crate::scene::Footprint,
    /// The iterations it was fitted for.
    pub iteration: usize,
}

#[cfg(test)]
mod tests {
    use super::{first_non_finite, first_non_finite_of, parameter_sum};
    use burn::module::Param;
    use burn::nn::{Linear, LinearConfig};
    use burn::tensor::{Device, Tensor, TensorData};

    /// Finite parameters pass; a NaN or an infinity in any of them is named by its path.
    #[test]
    fn a_parameter_that_is_not_finite_is_found_and_named() {
        let device = Device::flex().autodiff();
        let layer: Linear = LinearConfig::new(2, 2).init(&device);
        let sum = |m: &Linear| crate::backend::host_scalar(parameter_sum(m).expect("parameters"));
        assert!(sum(&layer).is_finite());
        // Read off the autodiff graph: what a step leaves there slows every later backward pass.
        assert!(!parameter_sum(&layer).expect("parameters").is_autodiff());
        assert_eq!(first_non_finite(&layer), None);
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut broken = layer.clone();
            broken.weight = Param::from_tensor(Tensor::from_data(TensorData::new(vec![0.5, bad, 1e30, -2.0], [2, 2]), &device));
            assert!(!sum(&broken).is_finite(), "{bad}");
            assert_eq!(first_non_finite(&broken).as_deref(), Some("weight"), "{bad}");
            // The name is looked for only when the sum read says so.
            assert_eq!(first_non_finite_of(&broken, 0.0), None);
            assert_eq!(first_non_finite_of(&broken, f32::NAN).as_deref(), Some("weight"));
        }
        // An infinity and a NaN in one tensor, and infinities of both signs in two.
        let mut broken = layer.clone();
        broken.bias = Some(Param::from_tensor(Tensor::from_data(TensorData::new(vec![f32::INFINITY, f32::NAN], [2]), &device)));
        assert_eq!(first_non_finite(&broken).as_deref(), Some("bias"));
        let mut broken = layer.clone();
        broken.weight = Param::from_tensor(Tensor::from_data(TensorData::new(vec![0.5, f32::INFINITY, 1.0, 2.0], [2, 2]), &device));
        broken.bias = Some(Param::from_tensor(Tensor::from_data(TensorData::new(vec![f32::NEG_INFINITY, 1.0], [2]), &device)));
        assert_eq!(first_non_finite(&broken).as_deref(), Some("weight"));
        // Finite values whose sum overflows: the search looks and finds none.
        let mut large = layer.clone();
        large.bias = Some(Param::from_tensor(Tensor::from_data(TensorData::new(vec![f32::MAX, f32::MAX], [2]), &device)));
        assert!(!sum(&large).is_finite());
        assert_eq!(first_non_finite(&large), None);
    }
}
