//! The loss terms of the supplement (section 4.1), each a function of tensors: RGB L1, mask,
//! grey, Gaussian density fit, the sigma (eq. 5) and mean (eq. 6) regularisers, ambient,
//! Eikonal and curvature. Weights come from the schedule; `train` adds them up.

use burn::tensor::Tensor;

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
    }
}
