//! The differentiable tensor path of the shadow integral (burn), for training: the optical
//! depth of every (ray, Gaussian) pair of a batch and the rays' transmittance, with gradients
//! to every Gaussian parameter, to ray origins and directions (and so to a light direction).
//! Same formulas as `integral`; `tests/shadow_accuracy.rs` pins the two together.

use burn::tensor::{Device, Tensor, TensorData};
use std::f64::consts::PI;

/// Posed Gaussians as tensors: world means `[G, 3]`, whitening matrices `[G, 3, 3]` (row k is
/// axis k divided by scale k) and amplitudes `[G]`.
#[derive(Clone, Debug)]
pub struct GaussianTensors {
    pub means: Tensor<2>,
    pub whiten: Tensor<3>,
    pub amplitudes: Tensor<1>,
}

impl GaussianTensors {
    /// From world means `[G, 3]`, rotations `[G, 3, 3]` whose columns are the axes, scales
    /// `[G, 3]` (positive) and amplitudes `[G]`: every input keeps its gradient.
    pub fn from_world(means: Tensor<2>, rotations: Tensor<3>, scales: Tensor<2>, amplitudes: Tensor<1>) -> Self {
        let whiten = rotations.swap_dims(1, 2) / scales.clamp_min(super::MIN_SCALE as f32).unsqueeze_dim::<3>(2);
        Self { means, whiten, amplitudes }
    }

    /// Constant tensors of a posed set (no gradients), for rendering or tests.
    pub fn from_posed(posed: &[crate::shadow::PosedGaussian], device: &Device) -> Self {
        let n = posed.len();
        let means: Vec<f32> = posed.iter().flat_map(|g| g.mean.to_array().map(|v| v as f32)).collect();
        let rotations: Vec<f32> = posed.iter().flat_map(|g| g.axes.transpose().to_cols_array().map(|v| v as f32)).collect();
        let scales: Vec<f32> = posed.iter().flat_map(|g| g.scales.to_array().map(|v| v as f32)).collect();
        let amplitudes: Vec<f32> = posed.iter().map(|g| g.amplitude as f32).collect();
        Self::from_world(
            Tensor::from_data(TensorData::new(means, [n, 3]), device),
            // `axes.transpose()` in column-major order is `axes` in row-major order.
            Tensor::from_data(TensorData::new(rotations, [n, 3, 3]), device),
            Tensor::from_data(TensorData::new(scales, [n, 3]), device),
            Tensor::from_data(TensorData::new(amplitudes, [n]), device),
        )
    }

    pub fn len(&self) -> usize {
        self.means.dims()[0]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A batch of ray segments: origins and unit directions `[R, 3]`, starts `[R]`, ends `[R]` or
/// `None` for semi-infinite rays (toward a directional light).
#[derive(Clone, Debug)]
pub struct RaySegments {
    pub origins: Tensor<2>,
    pub directions: Tensor<2>,
    pub t0: Tensor<1>,
    pub t1: Option<Tensor<1>>,
}

/// erfc(x) for x >= 0, fractional error below 1.2e-7 in exact arithmetic, plus f32 rounding of
/// order 1.5e-7 x^2 (the Chebyshev fit of Press et al., tested against libm), built
/// from elementwise ops so that autodiff differentiates it and no branch yields a NaN.
pub fn erfc_nonnegative(x: Tensor<3>) -> Tensor<3> {
    const C: [f32; 10] =
        [-1.265_512_2, 1.000_023_7, 0.374_091_96, 0.096_784_18, -0.186_288_06, 0.278_868_07, -1.135_204, 1.488_515_9, -0.822_152_23, 0.170_872_77];
    let t = (x.clone() * 0.5 + 1.0).recip();
    let mut poly = t.clone() * C[9];
    for &c in C[1..9].iter().rev() {
        poly = (poly + c) * t.clone();
    }
    t * (poly + C[0] - x.clone() * x).exp()
}

/// Optical depth of every Gaussian along every ray segment: `[R, G]`.
pub fn optical_depth(g: &GaussianTensors, rays: &RaySegments) -> Tensor<2> {
    let r = rays.origins.dims()[0];
    let n = g.len();
    // Whitened direction and origin as matmuls against the stacked whitening rows.
    let rows = g.whiten.clone().reshape([n * 3, 3]).transpose();
    let w = rays.directions.clone().matmul(rows.clone()).reshape([r, n, 3]);
    let whitened_origin = rays.origins.clone().matmul(rows).reshape([r, n, 3]);
    let whitened_mean = (g.whiten.clone() * g.means.clone().unsqueeze_dim::<3>(1)).sum_dim(2).reshape([1, n, 3]);
    // Re-anchor at the Euclidean closest approach s to each mean, as the scalar path does.
    let s = (rays.directions.clone().matmul(g.means.clone().transpose()) - (rays.origins.clone() * rays.directions.clone()).sum_dim(1)).unsqueeze_dim::<3>(2);
    let o = whitened_origin - whitened_mean + w.clone() * s.clone();
    let length = (w.clone() * w.clone()).sum_dim(2).sqrt();
    let unit = w / length.clone();
    let along = (o.clone() * unit.clone()).sum_dim(2);
    let perpendicular = o - unit * along.clone();
    let mahalanobis_squared = (perpendicular.clone() * perpendicular).sum_dim(2);
    let scale = std::f32::consts::FRAC_1_SQRT_2;
    let t0 = rays.t0.clone().reshape([r, 1, 1]);
    let a = ((t0 - s.clone()) * length.clone() + along.clone()) * scale;
    let erfc_a = erfc_nonnegative(a.clone().abs());
    let a_nonnegative = a.clone().greater_equal_elem(0.0);
    let difference = match &rays.t1 {
        // erf(inf) - erf(a): erfc(a) on the tail side, 2 - erfc(-a) otherwise.
        None => (erfc_a.clone().neg() + 2.0).mask_where(a_nonnegative, erfc_a),
        Some(t1) => {
            let b = ((t1.clone().reshape([r, 1, 1]) - s) * length.clone() + along) * scale;
            let erfc_b = erfc_nonnegative(b.clone().abs());
            let straddle = (erfc_a.clone() + erfc_b.clone()).neg() + 2.0;
            let both_negative = erfc_b.clone() - erfc_a.clone();
            let both_positive = erfc_a - erfc_b;
            let empty = b.clone().lower_equal(a.clone());
            straddle.mask_where(b.lower_equal_elem(0.0), both_negative).mask_where(a_nonnegative, both_positive).mask_fill(empty, 0.0)
        }
    };
    let peak = g.amplitudes.clone().reshape([1, n, 1]) * (mahalanobis_squared * -0.5).exp();
    (peak * difference * ((PI / 2.0).sqrt() as f32) / length).reshape([r, n])
}

/// Each Gaussian's share of the mixture's density at surface points `[R, 3]`: `[R, G]`, a
/// softmax of the log densities with shares below `OWN_SHARE_FLOOR` zeroed, no gradients
/// (`cpu::own_shares`, which a test pins it to).
pub fn own_shares(g: &GaussianTensors, points: Tensor<2>) -> Tensor<2> {
    let r = points.dims()[0];
    let n = g.len();
    let whiten = g.whiten.clone().detach();
    let rows = whiten.clone().reshape([n * 3, 3]).transpose();
    let whitened = points.detach().matmul(rows).reshape([r, n, 3]);
    let whitened_mean = (whiten * g.means.clone().detach().unsqueeze_dim::<3>(1)).sum_dim(2).reshape([1, n, 3]);
    let offset = whitened - whitened_mean;
    let mahalanobis_squared = (offset.clone() * offset).sum_dim(2).reshape([r, n]);
    let log_density = g.amplitudes.clone().detach().clamp_min(1e-30).log().reshape([1, n]) - mahalanobis_squared * 0.5;
    let shares = burn::tensor::activation::softmax(log_density, 1);
    shares.clone().mask_fill(shares.lower_elem(super::OWN_SHARE_FLOOR as f32), 0.0)
}

/// Transmittance of shadow rays from surface points `[R, 3]`: each Gaussian's optical depth
/// weighted by one less its share of the density at the ray's point (`own_shares`), `[R]`.
pub fn transmittance_from(g: &GaussianTensors, rays: &RaySegments, points: Tensor<2>) -> Tensor<1> {
    let r = rays.origins.dims()[0];
    let unowned = own_shares(g, points).neg() + 1.0;
    (optical_depth(g, rays) * unowned).sum_dim(1).neg().exp().reshape([r])
}

/// Transmittance `exp(-sum_g tau_g)` of every ray: `[R]`.
pub fn transmittance(g: &GaussianTensors, rays: &RaySegments) -> Tensor<1> {
    let r = rays.origins.dims()[0];
    optical_depth(g, rays).sum_dim(1).neg().exp().reshape([r])
}
