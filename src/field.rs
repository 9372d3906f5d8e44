//! The template-free neural field (burn, backend chosen by the `Device`): a point is expressed
//! in every posed bone's local frame, blended by soft skinning weights from its distance to the
//! bone segments, encoded with a few Fourier frequencies and fed to an MLP that predicts a
//! residual signed distance and an albedo in [0, 1]. VolSDF turns the SDF into density with a
//! Laplace CDF of learnable scale beta. The field knows nothing of lights.

use burn::module::{Module, Param};
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::{relu, sigmoid, softmax};
use burn::tensor::{Device, Tensor, TensorData};

/// A frame's bones as tensors: rotations `[B, 3, 3]` (bone-local axes as columns) and head
/// positions `[B, 3]` in world space, plus bone lengths `[B]`.
#[derive(Clone, Debug)]
pub struct PoseTensors {
    pub rotations: Tensor<3>,
    pub translations: Tensor<2>,
    pub lengths: Tensor<1>,
}

impl PoseTensors {
    pub fn new(pose: &crate::skeleton::Pose, skeleton: &crate::skeleton::Skeleton, device: &Device) -> Self {
        let b = skeleton.len();
        // Row-major rotation: element (i, j) is component i of local axis j.
        let rotations: Vec<f32> = pose.bone_to_world.iter().flat_map(|m| glam::DMat3::from_mat4(*m).transpose().to_cols_array().map(|v| v as f32)).collect();
        let translations: Vec<f32> = pose.bone_to_world.iter().flat_map(|m| m.w_axis.truncate().as_vec3().to_array()).collect();
        let lengths: Vec<f32> = skeleton.bones.iter().map(|bone| bone.length as f32).collect();
        Self {
            rotations: Tensor::from_data(TensorData::new(rotations, [b, 3, 3]), device),
            translations: Tensor::from_data(TensorData::new(translations, [b, 3]), device),
            lengths: Tensor::from_data(TensorData::new(lengths, [b]), device),
        }
    }

    pub fn bones(&self) -> usize {
        self.lengths.dims()[0]
    }

    /// Bone-local coordinates of world points: `[N, B, 3]`.
    pub fn to_local(&self, points: Tensor<2>) -> Tensor<3> {
        let [n, _] = points.dims();
        let b = self.bones();
        let relative = points.unsqueeze_dim::<3>(1) - self.translations.clone().unsqueeze_dim::<3>(0); // [N, B, 3]
                                                                                                       // local = R^T (x - t); as rows: local_row = relative_row R.
        relative.swap_dims(0, 1).matmul(self.rotations.clone()).swap_dims(0, 1).reshape([n, b, 3])
    }
}

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct FieldConfig {
    pub bones: usize,
    pub hidden: usize,
    pub layers: usize,
    /// Fourier frequencies (rad/m) of the bone-local encoding.
    pub frequencies: Vec<f32>,
    /// Width (m) of the soft skinning weights over distance to bone segments.
    pub skinning_width: f32,
    /// Radius (m) of the capsule prior the MLP's SDF is a residual of.
    pub prior_radius: f32,
    pub initial_beta: f32,
}

impl FieldConfig {
    pub fn for_bones(bones: usize) -> Self {
        Self { bones, hidden: 64, layers: 3, frequencies: vec![12.0, 25.0, 50.0], skinning_width: 0.05, prior_radius: 0.06, initial_beta: 0.03 }
    }

    pub fn input_width(&self) -> usize {
        self.bones * 3 * (1 + 2 * self.frequencies.len())
    }

    /// A field with weights drawn from our own seeded stream (uniform in +-1/sqrt(fan_in), as
    /// burn's default), so that a fit is reproducible whatever else uses burn's global RNG.
    pub fn init(&self, device: &Device, seed: u64) -> AvatarField {
        let mut stream = crate::synth::trace::Stream::new(seed, 0xF1E1D, 0);
        let mut linear = |fan_in: usize, fan_out: usize, scale: f32| {
            let bound = scale / (fan_in as f32).sqrt();
            let mut draw = |n: usize| (0..n).map(|_| ((stream.uniform() * 2.0 - 1.0) as f32) * bound).collect::<Vec<f32>>();
            let weight = Tensor::<2>::from_data(TensorData::new(draw(fan_in * fan_out), [fan_in, fan_out]), device);
            let bias = Tensor::<1>::from_data(TensorData::new(draw(fan_out), [fan_out]), device);
            let mut layer = LinearConfig::new(fan_in, fan_out).init(device);
            layer.weight = Param::from_tensor(weight);
            layer.bias = Some(Param::from_tensor(bias));
            layer
        };
        let mut hidden = Vec::new();
        let mut width = self.input_width();
        for _ in 0..self.layers {
            hidden.push(linear(width, self.hidden, 1.0));
            width = self.hidden;
        }
        // A near-zero residual at the start: the initial surface is the capsule prior.
        let output = linear(width, 4, 0.01);
        AvatarField {
            hidden,
            output,
            log_beta: Param::from_tensor(Tensor::from_data(TensorData::new(vec![self.initial_beta.ln()], [1]), device)),
            config: self.clone(),
        }
    }
}

#[derive(Module, Debug)]
pub struct AvatarField {
    pub hidden: Vec<Linear>,
    pub output: Linear,
    pub log_beta: Param<Tensor<1>>,
    #[module(skip)]
    pub config: FieldConfig,
}

/// What the field says at a batch of points.
pub struct FieldOutput {
    pub sdf: Tensor<1>,
    pub albedo: Tensor<2>,
}

/// The smallest beta, so density stays finite.
pub const MIN_BETA: f32 = 2e-3;

impl AvatarField {
    fn config(&self) -> &FieldConfig {
        &self.config
    }

    /// Encoded features and the capsule prior SDF of world points in a pose.
    fn encode(&self, points: Tensor<2>, pose: &PoseTensors) -> (Tensor<2>, Tensor<1>) {
        let config = self.config();
        let [n, _] = points.dims();
        let b = pose.bones();
        let local = pose.to_local(points);
        // Distance to each bone segment [0, L] along local +Y.
        let y = local.clone().narrow(2, 1, 1);
        let lengths = pose.lengths.clone().reshape([1, b, 1]);
        let along = y.clone().clamp_min(0.0).min_pair(lengths);
        let offset = Tensor::cat(vec![local.clone().narrow(2, 0, 1), y - along, local.clone().narrow(2, 2, 1)], 2);
        let distance_squared = (offset.clone() * offset).sum_dim(2); // [N, B, 1]
        let weights = softmax(distance_squared.clone() * (-0.5 / (config.skinning_width * config.skinning_width)), 1); // [N, B, 1]
        let prior = (weights.clone() * (distance_squared + 1e-8).sqrt()).sum_dim(1).reshape([n]) - config.prior_radius;
        let mut parts = vec![(local.clone() * weights.clone()).reshape([n, b * 3])];
        for &f in &config.frequencies {
            let phase = local.clone() * f;
            parts.push((phase.clone().sin() * weights.clone()).reshape([n, b * 3]));
            parts.push((phase.cos() * weights.clone()).reshape([n, b * 3]));
        }
        (Tensor::cat(parts, 1), prior)
    }

    /// SDF (metres) and albedo of world points in a pose.
    pub fn forward(&self, points: Tensor<2>, pose: &PoseTensors) -> FieldOutput {
        let [n, _] = points.dims();
        let (features, prior) = self.encode(points, pose);
        let mut x = features;
        for layer in &self.hidden {
            x = relu(layer.forward(x));
        }
        let out = self.output.forward(x);
        let sdf = prior + out.clone().narrow(1, 0, 1).reshape([n]) * 0.1;
        let albedo = sigmoid(out.narrow(1, 1, 3) + 0.5);
        FieldOutput { sdf, albedo }
    }

    /// SDF only.
    pub fn sdf(&self, points: Tensor<2>, pose: &PoseTensors) -> Tensor<1> {
        self.forward(points, pose).sdf
    }

    pub fn beta(&self) -> Tensor<1> {
        self.log_beta.val().exp() + MIN_BETA
    }

    /// VolSDF density `(1 / beta) Psi_beta(-sdf)`, Psi the Laplace CDF.
    pub fn density(&self, sdf: Tensor<1>) -> Tensor<1> {
        let beta = self.beta();
        let half = (sdf.clone().abs().neg() / beta.clone()).exp() * 0.5;
        let cdf = (half.clone().neg() + 1.0).mask_where(sdf.greater_equal_elem(0.0), half);
        cdf / beta
    }

    /// The SDF gradient by central differences (step `h`): differentiable in the parameters.
    pub fn sdf_gradient(&self, points: Tensor<2>, pose: &PoseTensors, h: f32) -> Tensor<2> {
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
