//! The template-free neural field (burn, backend chosen by the `Device`): a point is encoded
//! relative to the posed bones, with soft skinning weights from its distance to the bone
//! segments, and an MLP decodes the encoding into a residual signed distance (on a capsule
//! prior) and an albedo in [0, 1] (the `grid` field with a second MLP for the albedo, so the
//! surface's regularisers do not smooth the albedo). VolSDF turns the SDF into density with a
//! Laplace CDF of learnable scale beta. The field knows nothing of lights.
//!
//! Two encodings, chosen by the schedule's `[field] kind`: `mlp` expresses the point in every
//! bone's frame with a few Fourier frequencies (capacity is the MLP's width); `grid` looks it up
//! in multiresolution feature grids of its nearest bones (`grid`; capacity is the tables').
//! Both give the SDF's exact spatial gradient by forward-mode tangents.

mod config;
pub mod grid;
pub mod host_lookup;
pub mod interpolate;
pub mod layout;
pub mod lookup;
pub mod plan;
pub mod tensor_encode;
pub mod tensor_lookup;

use grid::{FeatureGrid, GridConfig, Skinning};

use burn::module::{Module, Param};
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::{relu, sigmoid, softmax};
use burn::tensor::{Device, Int, Tensor, TensorData};

pub use crate::skeleton::PoseTensors;
pub use config::{FieldConfig, ROOT_REACH_PER_WIDTH};

#[derive(Module, Debug)]
pub struct AvatarField {
    /// The feature grids of a `grid` field.
    pub grid: Option<FeatureGrid>,
    pub hidden: Vec<Linear>,
    pub output: Linear,
    /// The albedo's own decoder, when the config has one (`albedo_layers`).
    pub albedo_hidden: Vec<Linear>,
    pub albedo_output: Option<Linear>,
    /// `ln(beta - min_beta) / BETA_RATE`.
    pub beta_raw: Param<Tensor<1>>,
    #[module(skip)]
    pub config: FieldConfig,
}

/// The encoding of `N` points and what its derivatives need. 4D tensors are
/// `[1, N, B, _]`; tangents add a leading axis of 3 (the world axes) by broadcasting.
struct Encoding {
    features: Tensor<2>,
    prior: Tensor<1>,
    local: Tensor<4>,
    offset: Tensor<4>,
    weights: Tensor<4>,
    distance: Tensor<4>,
}

impl Encoding {
    /// Derivatives of the features `[3N, F]` (axis-major) and of the prior `[3, N]` along the
    /// three world axes, by the chain rule through each step of `AvatarField::encode`.
    fn tangents(&self, config: &FieldConfig, pose: &PoseTensors) -> (Tensor<2>, Tensor<2>) {
        let [_, n, b, _] = self.local.dims();
        // d local_j / d x_k = R[k, j]: row k of each bone's rotation.
        let d_local = pose.rotations.clone().swap_dims(0, 1).unsqueeze_dim::<4>(1).expand([3, n, b, 3]); // [3, N, B, 3]
                                                                                                         // The offset moves with the local point, except for its y inside the segment, where the
                                                                                                         // closest point slides along; but that y is 0 there, so offset . d_local is exact.
        let d_distance_squared = (self.offset.clone() * d_local.clone()).sum_dim(3) * 2.0; // [3, N, B, 1]
        let d_logits = d_distance_squared.clone() * config.sharpness();
        let weights = self.weights.clone();
        let d_weights = weights.clone() * (d_logits.clone() - (weights.clone() * d_logits).sum_dim(2));
        let d_distance = d_distance_squared / (self.distance.clone() * 2.0);
        let d_prior = (d_weights.clone() * self.distance.clone() + weights.clone() * d_distance).sum_dim(2).reshape([3, n]);
        let flat = |t: Tensor<4>| t.reshape([3 * n, b * 3]);
        let mut parts = vec![flat(d_local.clone() * weights.clone() + self.local.clone() * d_weights.clone())];
        for &f in &config.frequencies {
            let phase = self.local.clone() * f;
            let (sin, cos) = (phase.clone().sin(), phase.cos());
            let d_phase = d_local.clone() * f;
            parts.push(flat(cos.clone() * d_phase.clone() * weights.clone() + sin.clone() * d_weights.clone()));
            parts.push(flat((sin * d_phase).neg() * weights.clone() + cos * d_weights.clone()));
        }
        (Tensor::cat(parts, 1), d_prior)
    }
}

/// How the SDF's spatial gradient (normals, Eikonal, curvature) is taken.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GradientMethod {
    /// Exact, by forward-mode tangents through the encoding and the MLP.
    Tangents,
    /// Central differences with this step (m): six evaluations per point.
    CentralDifferences(f32),
}

/// The method the fit and the renderer use: tangents, measured cheaper than central
/// differences (`umbra bench eikonal`) and exact.
pub const GRADIENT: GradientMethod = GradientMethod::Tangents;

/// The SDF of a batch of points and the decoder inputs and outputs their albedo is made from
/// (`AvatarField::decode`, `AvatarField::albedo_at`).
pub struct Decoded {
    pub sdf: Tensor<1>,
    features: Tensor<2>,
    shared: Tensor<2>,
}

impl Decoded {
    /// Several batches' decodings as one, in order.
    pub fn cat(parts: Vec<Decoded>) -> Decoded {
        let (mut sdf, mut features, mut shared) = (Vec::new(), Vec::new(), Vec::new());
        for part in parts {
            sdf.push(part.sdf);
            features.push(part.features);
            shared.push(part.shared);
        }
        Decoded { sdf: Tensor::cat(sdf, 0), features: Tensor::cat(features, 0), shared: Tensor::cat(shared, 0) }
    }
}

/// What the field says at a batch of points.
pub struct FieldOutput {
    pub sdf: Tensor<1>,
    pub albedo: Tensor<2>,
}

/// The least beta of a field not sized to a body (`FieldConfig::for_bones`).
pub const MIN_BETA: f32 = 2e-3;

/// The least beta of a fitted body, per metre of its extent (0.5 mm for a 1.8 m human). The
/// learned beta sits on its floor, and at the floor a surface still shows a fringe where camera
/// rays graze it: a ray passing at distance d outside a limb of radius R collects an optical
/// depth of about `sqrt(pi R / 2 beta) exp(-d / beta)`. At the earlier 2 mm that fringe was
/// half a pixel wide around every silhouette of human-sun-128 and held most of its foreground
/// error (2116 dim pixels outside the true masks of its 8 novel-pose images; 600-860 at this
/// floor). A quarter of the width needs a sampler that finds the surface within a fraction
/// of a millimetre: the probe round (`render::Sampling::probe`). Measured with it, seeds
/// 0 / 1 / 2, foreground novel-pose PSNR: human-sun 24.23 / 25.26 / 25.80 dB at 2 mm without
/// probes -> 27.47 / 26.45 / 26.31 (light 1.70 / 1.94 / 1.78 degrees); human-sun-128 22.21 /
/// 22.22 / 23.65 -> 23.23 / 22.34 / 20.69 (within its seed-to-seed spread; at seed 2 the
/// albedo's colours stay washed out). A floor of 0.2 mm: 21.42 dB and the sun 3.5 degrees off.
pub const MIN_BETA_PER_EXTENT: f32 = 1.0 / 3600.0;

/// How much faster than the network's weights beta moves under Adam (whose step does not
/// depend on the gradient's scale): beta must fall from its start (3 cm) to a few millimetres
/// within the fit's first few hundred steps, or every silhouette keeps a halo as wide as the
/// Laplace tail (2-3 beta on each side); at the field's rate that takes over a thousand.
const BETA_RATE: f32 = 10.0;

impl AvatarField {
    /// How far beyond the posed bones' box the field can hold a surface (m), and the cell a mesh
    /// of it needs (m), on a body of `extent`: the grids' reach (the root's, when its grids reach
    /// loose body) and their finest cell; for the `mlp` field, the grids' defaults.
    pub fn surface_reach_and_cell(&self, extent: f64) -> (f64, f64) {
        match &self.config.grid {
            Some(grid) => {
                let root = grid.root.filter(|r| r.features_reach_body).map(|r| r.reach).unwrap_or(0.0);
                (grid.reach.max(root) as f64, grid.finest_cell as f64)
            }
            None => (extent * grid::REACH_PER_EXTENT as f64, extent / grid::FINEST_PER_EXTENT as f64),
        }
    }

    fn config(&self) -> &FieldConfig {
        &self.config
    }

    /// SDF (metres) and albedo of world points in a pose.
    pub fn forward(&self, points: Tensor<2>, pose: &PoseTensors) -> FieldOutput {
        let decoded = self.decode(points, pose);
        let albedo = self.albedo_at(&decoded, None);
        FieldOutput { sdf: decoded.sdf, albedo }
    }

    /// The SDF of world points in a pose, with what their albedo needs kept for `albedo_at`,
    /// so that a renderer can ask for the albedo only where the compositing weights matter.
    pub fn decode(&self, points: Tensor<2>, pose: &PoseTensors) -> Decoded {
        let (features, prior, _) = self.features(points, pose, false);
        let (sdf, shared) = self.decode_sdf(features.clone(), prior);
        Decoded { sdf, features, shared }
    }

    /// The albedo of decoded points, `[N, 3]`, or of the rows `rows` of them, `[K, 3]`.
    pub fn albedo_at(&self, decoded: &Decoded, rows: Option<Tensor<1, Int>>) -> Tensor<2> {
        let pick = |t: Tensor<2>| match &rows {
            Some(rows) => t.select(0, rows.clone()),
            None => t,
        };
        let logits = match &self.albedo_output {
            Some(head) => {
                let mut y = pick(decoded.features.clone());
                for layer in &self.albedo_hidden {
                    y = relu(layer.forward(y));
                }
                head.forward(y)
            }
            None => pick(decoded.shared.clone()).narrow(1, 1, 3),
        };
        sigmoid(logits + 0.5)
    }

    /// The SDF from the decoder's input and the prior, and the decoder's whole output (with a
    /// shared decoder, the albedo's logits follow the SDF's).
    fn decode_sdf(&self, features: Tensor<2>, prior: Tensor<1>) -> (Tensor<1>, Tensor<2>) {
        let [n, _] = features.dims();
        let mut x = features;
        for layer in &self.hidden {
            x = relu(layer.forward(x));
        }
        let out = self.output.forward(x);
        let sdf = prior + out.clone().narrow(1, 0, 1).reshape([n]) * self.config.residual_scale;
        (sdf, out)
    }

    /// SDF only (without the albedo's decoder, when it has its own).
    pub fn sdf(&self, points: Tensor<2>, pose: &PoseTensors) -> Tensor<1> {
        let (features, prior, _) = self.features(points, pose, false);
        self.decode_sdf(features, prior).0
    }

    pub fn beta(&self) -> Tensor<1> {
        (self.beta_raw.val() * BETA_RATE).exp() + self.config.min_beta
    }

    /// VolSDF density `(1 / beta) Psi_beta(-sdf)`, Psi the Laplace CDF.
    pub fn density(&self, sdf: Tensor<1>) -> Tensor<1> {
        let beta = self.beta();
        let half = (sdf.clone().abs().neg() / beta.clone()).exp() * 0.5;
        let cdf = (half.clone().neg() + 1.0).mask_where(sdf.greater_equal_elem(0.0), half);
        cdf / beta
    }

    /// The SDF and its exact gradient with respect to the point, by forward-mode tangents: the
    /// three unit directions are pushed through the encoding and the MLP alongside the values,
    /// as ordinary tensor ops, so the gradient is itself differentiable in the parameters (the
    /// Eikonal and curvature losses train through it). One pass costs the primal plus three
    /// tangent rows per point in the MLP, against six whole evaluations for central differences.
    pub fn sdf_and_gradient(&self, points: Tensor<2>, pose: &PoseTensors) -> (Tensor<1>, Tensor<2>) {
        let [n, _] = points.dims();
        let device = points.device();
        let (features, prior, tangents) = self.features(points, pose, true);
        // `features` returns tangents whenever asked; zeros only keep this path panic-free.
        let width = features.dims()[1];
        let (feature_tangents, prior_tangents) = tangents.unwrap_or_else(|| (Tensor::zeros([3 * n, width], &device), Tensor::zeros([3, n], &device)));
        let mut x = features;
        let mut dx = feature_tangents; // [3N, F]
        for layer in &self.hidden {
            let z = layer.forward(x);
            let width = z.dims()[1];
            // ReLU passes a tangent only where the unit is active.
            let active = z.clone().greater_elem(0.0).float().unsqueeze_dim::<3>(0); // [1, N, H]
            let dz = dx.matmul(layer.weight.val()).reshape([3, n, width]) * active;
            dx = dz.reshape([3 * n, width]);
            x = relu(z);
        }
        let out = self.output.forward(x).narrow(1, 0, 1).reshape([n]);
        let d_out = dx.matmul(self.output.weight.val().narrow(1, 0, 1)).reshape([3, n]);
        let residual = self.config.residual_scale;
        let sdf = prior + out * residual;
        let gradient = (prior_tangents + d_out * residual).transpose();
        (sdf, gradient)
    }

    /// The skinning weights at world point `point` in the pose of `frames`, as `(bone, weight)`:
    /// the grid's (`lookup::skinning_weights`), or for a field without grids the softmax of the
    /// skinning's logits over every bone.
    pub fn skinning_weights(&self, frames: &[crate::skeleton::BoneFrame], point: [f32; 3]) -> Vec<(usize, f32)> {
        let skinning = self.config.skinning();
        if let Some(grid) = &self.grid {
            return lookup::skinning_weights(&grid.config, frames, skinning, point);
        }
        let logits: Vec<f32> = frames.iter().map(|f| f.distance_squared(point) * skinning.sharpness).collect();
        let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let sum: f32 = logits.iter().map(|l| (l - max).exp()).sum();
        logits.iter().enumerate().map(|(b, l)| (b, (l - max).exp() / sum)).collect()
    }

    /// The decoder's input `[N, F]` and the capsule prior SDF `[N]` of world points in a pose,
    /// by the field's encoding, with their derivatives along the world axes (`[3N, F]`
    /// axis-major and `[3, N]`) when `tangents` says.
    #[allow(clippy::type_complexity)]
    fn features(&self, points: Tensor<2>, pose: &PoseTensors, tangents: bool) -> (Tensor<2>, Tensor<1>, Option<(Tensor<2>, Tensor<2>)>) {
        match &self.grid {
            Some(grid) => {
                let g = grid.encode_carrying(points, &pose.frames, self.config.skinning(), tangents, pose.motion.as_ref(), pose.view.as_ref());
                (g.features, g.prior, g.tangents)
            }
            None => {
                let encoding = self.encode(points, pose);
                let t = tangents.then(|| encoding.tangents(&self.config, pose));
                (encoding.features, encoding.prior, t)
            }
        }
    }

    /// Fourier features in every bone's frame and the capsule prior SDF of world points.
    fn encode(&self, points: Tensor<2>, pose: &PoseTensors) -> Encoding {
        let config = self.config();
        let [n, _] = points.dims();
        let b = pose.bones();
        let local = pose.to_local(points).unsqueeze_dim::<4>(0); // [1, N, B, 3]
                                                                 // Distance to each bone segment [0, L] along local +Y.
        let y = local.clone().narrow(3, 1, 1);
        let lengths = pose.lengths.clone().reshape([1, 1, b, 1]);
        let along = y.clone().clamp_min(0.0).min_pair(lengths.clone());
        let offset = Tensor::cat(vec![local.clone().narrow(3, 0, 1), y.clone() - along, local.clone().narrow(3, 2, 1)], 3);
        let distance_squared = (offset.clone() * offset.clone()).sum_dim(3); // [1, N, B, 1]
        let weights = softmax(distance_squared.clone() * config.sharpness(), 2);
        let distance = (distance_squared + 1e-8).sqrt();
        let prior = (weights.clone() * distance.clone()).sum_dim(2).reshape([n]) - config.prior_radius;
        let flat = |t: Tensor<4>| t.reshape([n, b * 3]);
        let mut parts = vec![flat(local.clone() * weights.clone())];
        for &f in &config.frequencies {
            let phase = local.clone() * f;
            parts.push(flat(phase.clone().sin() * weights.clone()));
            parts.push(flat(phase.cos() * weights.clone()));
        }
        Encoding { features: Tensor::cat(parts, 1), prior, local, offset, weights, distance }
    }

    /// The SDF gradient `[N, 3]` by `method`; differentiable in the parameters either way.
    pub fn sdf_gradient(&self, points: Tensor<2>, pose: &PoseTensors, method: GradientMethod) -> Tensor<2> {
        match method {
            GradientMethod::Tangents => self.sdf_and_gradient(points, pose).1,
            GradientMethod::CentralDifferences(h) => self.sdf_gradient_central(points, pose, h),
        }
    }

    /// The SDF gradient by central differences (step `h`): the reference the tangents are
    /// tested and benchmarked against.
    fn sdf_gradient_central(&self, points: Tensor<2>, pose: &PoseTensors, h: f32) -> Tensor<2> {
        let [n, _] = points.dims();
        let device = points.device();
        let mut offsets = Vec::new();
        for k in 0..3 {
            let mut e = [0.0f32; 3];
            e[k] = h;
            let step: Tensor<2> = Tensor::from_data(TensorData::new(e.to_vec(), [1, 3]), &device);
            offsets.push(points.clone() + step.clone());
            offsets.push(points.clone() - step);
        }
        let all = self.sdf(Tensor::cat(offsets, 0), pose).reshape([6, n]);
        let plus = Tensor::cat(vec![all.clone().narrow(0, 0, 1), all.clone().narrow(0, 2, 1), all.clone().narrow(0, 4, 1)], 0);
        let minus = Tensor::cat(vec![all.clone().narrow(0, 1, 1), all.clone().narrow(0, 3, 1), all.narrow(0, 5, 1)], 0);
        ((plus - minus) / (2.0 * h)).transpose()
    }
}
