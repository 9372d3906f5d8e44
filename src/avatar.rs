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

/// The path (`field.hidden.0.weight`, ...) of the first parameter holding a NaN or an
/// infinity: the update that put it there must not reach a checkpoint.
pub fn first_non_finite<M: Module>(module: &M) -> Option<String> {
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
