//! The loss terms of the supplement (section 4.1), each a function of tensors: RGB L1, mask,
//! grey, Gaussian density fit, the sigma (eq. 5) and mean (eq. 6) regularisers, ambient,
//! Eikonal and curvature. Weights come from the schedule; `train` adds them up.

use burn::tensor::Tensor;

/// `mean |c - target|` over rays and channels.
pub fn rgb(colour: Tensor<2>, target: Tensor<2>) -> Tensor<1> {
    (colour - target).abs().mean().reshape([1])
}

/// Cauchy weights `1 / (1 + (e / c)^2)` of pixels with errors `errors` (each pixel's mean
/// absolute error over its channels), `c` = `tuning` robust standard deviations of the errors
/// of the pixels whose `foreground` is set (1.4826 x their median: the batch's own scale, so
/// no threshold in image units). What they are for: with an L1 loss every pixel's error pulls
/// the light by the same amount whatever its size, so pixels the shading cannot explain at
/// all (a rounded rim, a silhouette a pixel off, a hand where the truth has skirt: wrong
/// normals or wrong geometry, whose error the albedo cannot take up) pull the light steadily one
/// way, while the pixels whose shading is right, their error taken up by the albedo, barely
/// hold it. Weighting the light's share of the gradient lets the light follow the pixels the
/// model explains. No foreground (or a zero median) leaves every weight 1.
pub fn cauchy_weights(errors: &[f32], foreground: &[bool], tuning: f32) -> Vec<f32> {
    let mut inside: Vec<f32> = errors.iter().zip(foreground).filter(|(e, f)| **f && e.is_finite()).map(|(e, _)| *e).collect();
    if inside.is_empty() {
        return vec![1.0; errors.len()];
    }
    let middle = inside.len() / 2;
    let (_, median, _) = inside.select_nth_unstable_by(middle, |a, b| a.total_cmp(b));
    let scale = tuning * 1.4826 * *median;
    if !(scale > 0.0 && scale.is_finite()) {
        return vec![1.0; errors.len()];
    }
    errors.iter().map(|e| if e.is_finite() { 1.0 / (1.0 + (e / scale) * (e / scale)) } else { 0.0 }).collect()
}

/// Linear radiance to sRGB-encoded values in [0, 1], the images' own encoding: the tensor form
/// of `imageio::linear_to_srgb` (a test pins the two), for an RGB loss in the space the eye and
/// the 8-bit scores see (`Schedule::rgb_space`).
pub fn srgb(linear: Tensor<2>) -> Tensor<2> {
    let v = linear.clamp(0.0, 1.0);
    let toe = v.clone() * 12.92;
    let curve = v.clone().clamp_min(SRGB_TOE).powf_scalar(1.0 / 2.4) * 1.055 - 0.055;
    curve.mask_where(v.lower_equal_elem(SRGB_TOE), toe)
}

/// A centre-sampled pixel in the image's encoding (`imageio::composite_centre_sample`, which
/// a test pins this to): `coverage x srgb(colour / coverage)` from the colour composited over
/// black and the coverage, the chance the ray meets the body.
pub fn srgb_centre_sample(premultiplied: Tensor<2>, coverage: Tensor<1>) -> Tensor<2> {
    let [p, _] = premultiplied.dims();
    let coverage = coverage.clamp(0.0, 1.0).reshape([p, 1]);
    srgb(premultiplied / coverage.clone().clamp_min(MIN_COVERAGE)) * coverage
}

/// The least coverage a colour is divided by (a ray that meets nothing has colour 0 too).
const MIN_COVERAGE: f32 = 1e-6;

/// Where the sRGB curve's linear toe ends.
const SRGB_TOE: f32 = 0.003_130_8;

/// `mean |accumulation - mask|`.
pub fn mask(accumulation: Tensor<1>, mask: Tensor<1>) -> Tensor<1> {
    (accumulation - mask).abs().mean().reshape([1])
}

/// The mask loss of pixels that average their area (`scene::footprint`): away from the
/// silhouette (`edge` 0) `|coverage - mask|`; along it (`edge` 1) a pixel may be partly covered
/// whatever its mask, which says only that coverage is above one half (mask 1) or at most one
/// half (mask 0), so only the wrong side of one half costs.
pub fn mask_area(coverage: Tensor<1>, mask: Tensor<1>, edge: Tensor<1>) -> Tensor<1> {
    let inside = (coverage.clone() - mask.clone()).abs() * (edge.clone().neg() + 1.0);
    let side = mask * 2.0 - 1.0;
    let wrong_side = ((coverage.neg() + 0.5) * side).clamp_min(0.0) * edge;
    (inside + wrong_side).mean().reshape([1])
}

/// The RGB loss of pixels that average their area: `rgb`'s L1, except for background pixels
/// along the silhouette, whose black says nothing of the colour (a pixel at most half covered
/// is black in the format's images, though its area holds some of the body).
pub fn rgb_area(colour: Tensor<2>, target: Tensor<2>, mask: Tensor<1>, edge: Tensor<1>) -> Tensor<1> {
    let [p, _] = colour.dims();
    let unknown = (mask.neg() + 1.0) * edge;
    let weight = (unknown.neg() + 1.0).reshape([p, 1]);
    ((colour - target).abs() * weight).mean().reshape([1])
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

    #[test]
    fn cauchy_weights_follow_the_foregrounds_own_scale() {
        // Foreground errors 0.01, 0.02, 0.03 (median 0.02, c = 2 x 1.4826 x 0.02); the background
        // pixel's 0.5 does not count toward the scale but is weighted by it.
        let errors = [0.01, 0.02, 0.03, 0.5, 0.0];
        let foreground = [true, true, true, false, true];
        let w = cauchy_weights(&errors, &foreground, 2.0);
        let c = 2.0 * 1.4826 * 0.02f32;
        for (e, w) in errors.iter().zip(&w) {
            assert!((w - 1.0 / (1.0 + (e / c) * (e / c))).abs() < 1e-6, "{e}: {w}");
        }
        assert!((w[4] - 1.0).abs() < 1e-7 && w[3] < 0.02);
        // An error of c weighs one half; the weights do not change when every error is scaled.
        let half = cauchy_weights(&[c, 0.0, c, c], &[true, false, false, false], 1.0 / 1.4826);
        assert!((half[0] - 0.5).abs() < 1e-6, "{half:?}");
        let scaled: Vec<f32> = errors.iter().map(|e| e * 7.0).collect();
        for (a, b) in cauchy_weights(&scaled, &foreground, 2.0).iter().zip(&w) {
            assert!((a - b).abs() < 1e-5);
        }
        // Nothing to measure a scale on: every weight 1; a non-finite error weighs nothing.
        assert_eq!(cauchy_weights(&[0.3, 0.2], &[false, false], 2.0), vec![1.0, 1.0]);
        assert_eq!(cauchy_weights(&[0.0, 0.0, 0.4], &[true, true, false], 2.0), vec![1.0, 1.0, 1.0]);
        assert_eq!(cauchy_weights(&[0.1, f32::NAN, 0.1], &[true, true, true], 2.0)[1], 0.0);
    }

    #[test]
    fn area_losses_cost_only_the_wrong_side_of_half_covered_along_the_silhouette() {
        // Coverage, mask, edge: an inner pixel off by 0.2; an edge pixel of mask 1 at 0.7 (right
        // side, free) and at 0.3 (0.2 short); an edge pixel of mask 0 at 0.4 (free) and at 0.9
        // (0.4 over); an outer pixel at 0.1.
        let coverage = t1(&[0.8, 0.7, 0.3, 0.4, 0.9, 0.1]);
        let mask = t1(&[1.0, 1.0, 1.0, 0.0, 0.0, 0.0]);
        let edge = t1(&[0.0, 1.0, 1.0, 1.0, 1.0, 0.0]);
        let expected = (0.2 + 0.0 + 0.2 + 0.0 + 0.4 + 0.1) / 6.0;
        assert!((value(mask_area(coverage, mask.clone(), edge.clone())) - expected).abs() < 1e-6);
        // RGB: the background pixels along the silhouette (3 and 4) do not count.
        let colour = t2(&[0.5; 18], 3);
        let target = t2(&[0.0; 18], 3);
        let expected = 0.5 * 12.0 / 18.0;
        assert!((value(rgb_area(colour, target, mask, edge)) - expected).abs() < 1e-6);
    }

    #[test]
    fn the_srgb_encoding_is_the_images_encoding() {
        // Both sides of the toe, its end, the ends of the range and beyond them.
        let linear = [0.0f32, 0.001, 0.003_130_8, 0.004, 0.02, 0.214_041, 0.5, 0.9, 1.0, 1.7, -0.2, 0.05];
        let encoded = srgb(t2(&linear, 3)).into_data().try_to_vec::<f32>().unwrap();
        for (v, e) in linear.iter().zip(&encoded) {
            assert!((e - crate::imageio::linear_to_srgb(*v)).abs() < 1e-6, "{v}: {e} vs {}", crate::imageio::linear_to_srgb(*v));
        }
        // 0.214041 is code 0.5 (imageio's known point).
        assert!((encoded[5] - 0.5).abs() < 1e-5);
    }

    #[test]
    fn a_centre_sample_is_composited_as_its_image_stores_it() {
        let colour = [0.3f32, 0.02, 0.0, 0.01, 0.5, 0.25, 0.6, 0.6, 0.6, 0.0, 0.0, 0.0];
        let coverage = [1.0f32, 0.05, 0.5, 0.0];
        let got = srgb_centre_sample(t2(&colour, 3), t1(&coverage)).into_data().try_to_vec::<f32>().unwrap();
        for (k, &a) in coverage.iter().enumerate() {
            let want = crate::imageio::composite_centre_sample([colour[3 * k], colour[3 * k + 1], colour[3 * k + 2]], a);
            for c in 0..3 {
                assert!((got[3 * k + c] - crate::imageio::linear_to_srgb(want[c])).abs() < 1e-5, "pixel {k}: {} vs {}", got[3 * k + c], want[c]);
            }
        }
        // A faint fringe stays faint in the image's encoding: a twentieth of the surface's code.
        let fringe = crate::imageio::linear_to_srgb(crate::imageio::composite_centre_sample([0.025; 3], 0.05)[0]);
        assert!((fringe - 0.05 * crate::imageio::linear_to_srgb(0.5)).abs() < 1e-6);
    }

    fn close(a: f32, b: f64) {
        assert!((a as f64 - b).abs() < 1e-6 * b.abs().max(1.0), "{a} vs {b}");
    }

    #[test]
    fn each_loss_matches_hand_computed_values() {
        close(value(rgb(t2(&[0.5, 0.5, 0.5, 0.0, 0.2, 1.0], 3), t2(&[0.25, 0.5, 1.0, 0.0, 0.0, 0.0], 3))), (0.25 + 0.0 + 0.5 + 0.0 + 0.2 + 1.0) / 6.0);
        close(value(mask(t1(&[0.9, 0.1, 0.5]), t1(&[1.0, 0.0, 0.0]))), (0.1 + 0.1 + 0.5) / 3.0);
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
