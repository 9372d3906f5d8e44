//! The loss terms of the supplement (section 4.1), each a function of tensors: RGB L1, mask,
//! grey, Gaussian density fit, the sigma (eq. 5) and mean (eq. 6) regularisers, ambient,
//! Eikonal and curvature, the refined motion's prior and smoothness, and the refined cameras' prior; and `TERMS`, the one list of them: each term's name (the schedule's
//! `[losses]` key, the losses table's column), what it is computed from (`Input`: a step
//! computes, and a batch draws samples for, only what an active term needs) and its value from
//! a step's `Inputs`. Adding a term is an entry here and its weight in a schedule. Weights come
//! from the schedule; `train` adds the terms up in this order.

use burn::tensor::Tensor;

/// What a term is computed from beyond the rays' coverage, masks, albedos and targets, which
/// every step has: the rest costs a step work (shading, samples, SDF gradients), done only
/// when an active term needs it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Input {
    /// Each ray's colour, shaded and in its camera's colour, over what lies behind the body.
    Colour,
    /// The Gaussians' mixture against the field's density at samples of the rays
    /// (`density_points` of them).
    Density,
    /// The Gaussians' scales (body units).
    Widths,
    /// The Gaussians' means and the points the mean regulariser pulls them to (body units).
    Means,
    /// The light's ambient and its target (a fitted light only).
    Ambient,
    /// The SDF's gradient at samples of the rays (`regulariser_points` of them).
    Gradient,
    /// Unit normals at those samples and at points offset from them.
    NormalPairs,
    /// The batch frame's motion correction, refined with the field (`train::motion`): a step
    /// carries it through the render and the terms that weigh it hold it near the given motion.
    Motion,
    /// The training cameras' pose corrections, refined with the field (`train::camera_pose`):
    /// a step sees each ray from its camera as corrected and carries an increment of them
    /// through the render; the term that weighs them holds them near the given poses.
    Cameras,
}

/// The inputs computed at the regulariser points (`Schedule::regulariser_points`), every
/// `Schedule::regularise_every` steps.
pub const REGULARISER_INPUTS: [Input; 2] = [Input::Gradient, Input::NormalPairs];

/// What a step computed for its batch; a part an active term does not need is absent.
pub struct Inputs {
    pub accumulation: Tensor<1>,
    pub mask: Tensor<1>,
    /// How far each ray's mask is trusted (absent: fully everywhere).
    pub mask_weights: Option<Tensor<1>>,
    pub albedo: Tensor<2>,
    pub target: Tensor<2>,
    pub colour: Option<Tensor<2>>,
    /// (mixture, field density) at every scale the density is fitted at.
    pub densities: Vec<(Tensor<1>, Tensor<1>)>,
    pub widths: Option<Tensor<2>>,
    pub means: Option<(Tensor<2>, Tensor<2>)>,
    pub ambient: Option<(Tensor<1>, f64)>,
    pub gradient: Option<Tensor<2>>,
    pub normal_pairs: Option<(Tensor<2>, Tensor<2>)>,
    /// The batch frame's motion correction and what its terms hold it to.
    pub motion: Option<MotionInput>,
    /// The training cameras' turns about their centres (`[C, 3]`, radians).
    pub cameras: Option<Tensor<2>>,
}

/// The batch frame's motion correction (`[bones + 1, 3]`: each bone's turn in radians, the
/// skeleton's shift in levers), where its neighbouring frames would have it for a smooth motion
/// (the corrected motion's second difference there zero), and how much the smoothness and the
/// prior weigh on this capture for the schedule's weights (`MotionCorrections::smoothness_scale`:
/// the given motion's noise-to-motion ratio; `MotionCorrections::prior_scale`: how sure it is).
#[derive(Clone, Debug)]
pub struct MotionInput {
    pub correction: Tensor<2>,
    pub smooth: Tensor<2>,
    pub smoothness_scale: f64,
    pub prior_scale: f64,
}

/// A loss term: its name, what it needs, its value (none when a step lacks an input).
pub struct Term {
    pub name: &'static str,
    pub needs: &'static [Input],
    /// Evaluated and reported at every step, whatever its weight (the mask: the silhouette's
    /// progress is always worth a column, and a step's total always has a term).
    pub always: bool,
    pub value: fn(&Inputs) -> Option<Tensor<1>>,
}

/// Every loss term, in the order a step sums them.
pub const TERMS: [Term; 12] = [
    Term { name: "rgb", needs: &[Input::Colour], always: false, value: |i| Some(rgb(i.colour.clone()?, i.target.clone())) },
    Term { name: "mask", needs: &[], always: true, value: |i| Some(mask(i.accumulation.clone(), i.mask.clone(), i.mask_weights.clone())) },
    Term { name: "grey", needs: &[], always: false, value: |i| Some(grey(i.albedo.clone(), i.mask.clone())) },
    Term {
        name: "density",
        needs: &[Input::Density],
        always: false,
        value: |i| i.densities.iter().map(|(m, f)| density(m.clone(), f.clone())).reduce(|a, b| a + b),
    },
    Term { name: "sigma", needs: &[Input::Widths], always: false, value: |i| Some(sigma(i.widths.clone()?)) },
    Term { name: "mean", needs: &[Input::Means], always: false, value: |i| i.means.clone().map(|(m, c)| mean(m, c)) },
    Term { name: "ambient", needs: &[Input::Ambient], always: false, value: |i| i.ambient.clone().map(|(a, target)| ambient(a, target)) },
    Term { name: "eikonal", needs: &[Input::Gradient], always: false, value: |i| Some(eikonal(i.gradient.clone()?)) },
    Term { name: "curvature", needs: &[Input::NormalPairs], always: false, value: |i| i.normal_pairs.clone().map(|(n, p)| curvature(n, p)) },
    Term { name: "motion_prior", needs: &[Input::Motion], always: false, value: |i| i.motion.clone().map(|m| squared(m.correction) * m.prior_scale) },
    Term {
        name: "motion_smoothness",
        needs: &[Input::Motion],
        always: false,
        value: |i| i.motion.clone().map(|m| squared(m.correction - m.smooth) * m.smoothness_scale),
    },
    Term { name: "camera_prior", needs: &[Input::Cameras], always: false, value: |i| i.cameras.clone().map(squared) },
];

/// The terms' names, in `TERMS`' order.
pub fn names() -> impl Iterator<Item = &'static str> {
    TERMS.iter().map(|t| t.name)
}

/// The term of this name.
pub fn term(name: &str) -> Option<&'static Term> {
    TERMS.iter().find(|t| t.name == name)
}

/// `mean |c - target|` over rays and channels.
pub fn rgb(colour: Tensor<2>, target: Tensor<2>) -> Tensor<1> {
    (colour - target).abs().mean().reshape([1])
}

/// `mean |accumulation - mask|`, each ray's term times its weight when given (a mask trusted
/// less near its edge).
pub fn mask(accumulation: Tensor<1>, mask: Tensor<1>, weights: Option<Tensor<1>>) -> Tensor<1> {
    let error = (accumulation - mask).abs();
    match weights {
        Some(w) => (error * w).mean().reshape([1]),
        None => error.mean().reshape([1]),
    }
}

/// `|albedo - 0.75|` on foreground rays (mean over foreground rays and channels).
pub fn grey(albedo: Tensor<2>, foreground: Tensor<1>) -> Tensor<1> {
    let [r, _] = albedo.dims();
    let weight = foreground.reshape([r, 1]);
    let count = weight.clone().sum().clamp_min(1.0) * 3.0;
    ((albedo - 0.75).abs() * weight).sum().reshape([1]) / count.reshape([1])
}

/// Squared difference of the Gaussian mixture and the field's density, both squashed by tanh
/// (the field's side should be detached so only the Gaussians learn from it). Both come in the
/// units the caller wants the saturation at: optical density per body unit, or that times the
/// shadows' density scale (`Schedule::density_at_shadow_scale`).
pub fn density(mixture: Tensor<1>, field_density: Tensor<1>) -> Tensor<1> {
    let d = mixture.tanh() - field_density.tanh();
    (d.clone() * d).mean().reshape([1])
}

/// Eq. 5 on every scale: `2e-5 / s` below 2 cm, `100 (s - 0.02)^4 + 0.001` above; the mean.
pub fn sigma(scales: Tensor<2>) -> Tensor<1> {
    let small = scales.clone().clamp_min(1e-6).recip() * 2e-5;
    let excess = scales.clone() - 0.02;
    let large = excess.clone() * excess.clone() * excess.clone() * excess * 100.0 + 0.001;
    large.mask_where(scales.lower_equal_elem(0.02), small).mean().reshape([1])
}

/// Eq. 6: `(100 d^4 + 1)^(1/4) - 1` with d the distance of a Gaussian's mean from its bone's
/// centre (both bone-local `[G, 3]`); the mean.
pub fn mean(means: Tensor<2>, centres: Tensor<2>) -> Tensor<1> {
    let d = means - centres;
    let d2 = (d.clone() * d).sum_dim(1);
    ((d2.clone() * d2 * 100.0 + 1.0).sqrt().sqrt() - 1.0).mean().reshape([1])
}

/// `|ambient - target|^2`, mean over channels.
pub fn ambient(ambient: Tensor<1>, target: f64) -> Tensor<1> {
    let d = ambient - target;
    (d.clone() * d).mean().reshape([1])
}

/// `(|grad sdf| - 1)^2`, mean over points.
pub fn eikonal(gradient: Tensor<2>) -> Tensor<1> {
    let norm = crate::render::row_lengths(gradient);
    let d = norm - 1.0;
    (d.clone() * d).mean().reshape([1])
}

/// The sum of squares: of a motion's correction (held near the given motion), or of its
/// distance from where its neighbours would have it (smooth in time).
pub fn squared(v: Tensor<2>) -> Tensor<1> {
    (v.clone() * v).sum().reshape([1])
}

/// `|n(x) - n(x + eps)|^2` of unit normals, mean over points.
pub fn curvature(normal: Tensor<2>, perturbed: Tensor<2>) -> Tensor<1> {
    let d = normal - perturbed;
    (d.clone() * d).sum_dim(1).mean().reshape([1])
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    fn t1(v: &[f32]) -> Tensor<1> {
        Tensor::from_data(TensorData::new(v.to_vec(), [v.len()]), &Device::flex())
    }

    fn t2(v: &[f32], cols: usize) -> Tensor<2> {
        Tensor::from_data(TensorData::new(v.to_vec(), [v.len() / cols, cols]), &Device::flex())
    }

    fn value(t: Tensor<1>) -> f32 {
        t.into_data().try_to_vec::<f32>().unwrap()[0]
    }

    fn close(a: f32, b: f64) {
        assert!((a as f64 - b).abs() < 1e-6 * b.abs().max(1.0), "{a} vs {b}");
    }

    #[test]
    fn each_loss_matches_hand_computed_values() {
        close(value(rgb(t2(&[0.5, 0.5, 0.5, 0.0, 0.2, 1.0], 3), t2(&[0.25, 0.5, 1.0, 0.0, 0.0, 0.0], 3))), (0.25 + 0.0 + 0.5 + 0.0 + 0.2 + 1.0) / 6.0);
        close(value(mask(t1(&[0.9, 0.1, 0.5]), t1(&[1.0, 0.0, 0.0]), None)), (0.1 + 0.1 + 0.5) / 3.0);
        close(value(mask(t1(&[0.9, 0.1, 0.5]), t1(&[1.0, 0.0, 0.0]), Some(t1(&[1.0, 0.0, 0.5])))), (0.1 + 0.0 + 0.25) / 3.0);
        // Only the foreground ray counts: |0.5 - 0.75| + |1 - 0.75| + |0.75 - 0.75| over 3.
        close(value(grey(t2(&[0.5, 1.0, 0.75, 0.0, 0.0, 0.0], 3), t1(&[1.0, 0.0]))), 0.5 / 3.0);
        close(value(density(t1(&[0.0, 100.0]), t1(&[0.5, 100.0]))), (0.5f64.tanh().powi(2) + 0.0) / 2.0);
        // Eq. 5 at 0.01 (2e-5 / 0.01 = 0.002) and at 0.12 (100 * 0.1^4 + 0.001 = 0.011).
        close(value(sigma(t2(&[0.01, 0.12], 2))), (0.002 + 0.011) / 2.0);
        // Eq. 6 at d = 0 and d = 0.5: (100 * 0.0625 + 1)^(1/4) - 1.
        close(value(mean(t2(&[0.0, 0.1, 0.0, 0.3, 0.1, 0.4], 3), t2(&[0.0, 0.1, 0.0, 0.0, 0.1, 0.0], 3))), ((100.0f64 * 0.0625 + 1.0).powf(0.25) - 1.0) / 2.0);
        close(value(ambient(t1(&[0.1, 0.2, 0.4]), 0.1)), (0.0 + 0.01 + 0.09) / 3.0);
        close(value(eikonal(t2(&[3.0, 4.0, 0.0, 0.0, 0.0, 1.0], 3))), (16.0 + 0.0) / 2.0);
        close(value(curvature(t2(&[1.0, 0.0, 0.0], 3), t2(&[0.0, 1.0, 0.0], 3))), 2.0);
        close(value(squared(t2(&[0.1, -0.2, 0.0, 0.3, 0.0, 0.0], 3))), 0.01 + 0.04 + 0.09);
    }

    #[test]
    fn the_motions_smoothness_and_prior_are_weighed_by_the_captures_own_scales() {
        let inputs = |smoothness_scale: f64, prior_scale: f64| Inputs {
            accumulation: t1(&[0.0]),
            mask: t1(&[0.0]),
            mask_weights: None,
            albedo: t2(&[0.0; 3], 3),
            target: t2(&[0.0; 3], 3),
            colour: None,
            densities: vec![],
            widths: None,
            means: None,
            ambient: None,
            gradient: None,
            normal_pairs: None,
            motion: Some(MotionInput { correction: t2(&[0.1, 0.0, -0.2], 3), smooth: t2(&[0.0, 0.1, 0.0], 3), smoothness_scale, prior_scale }),
            cameras: None,
        };
        let of = |name: &str, smoothness: f64, prior: f64| value((term(name).unwrap().value)(&inputs(smoothness, prior)).unwrap());
        close(of("motion_smoothness", 1.0, 1.0), 0.01 + 0.01 + 0.04);
        close(of("motion_smoothness", 7.5, 40.0), 7.5 * 0.06);
        close(of("motion_prior", 7.5, 1.0), 0.01 + 0.04);
        close(of("motion_prior", 1.0, 40.0), 40.0 * (0.01 + 0.04));
    }
}
