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

pub mod grid;
pub mod interpolate;
pub mod layout;
pub mod lookup;

use grid::{FeatureGrid, GridConfig, Skinning};

use burn::module::{Module, Param};
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::{relu, sigmoid, softmax};
use burn::tensor::{Device, Int, Tensor, TensorData};

pub use crate::skeleton::PoseTensors;

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
    /// Metres of SDF per unit of the decoder's output (the residual on the capsule prior).
    #[serde(default = "default_residual_scale")]
    pub residual_scale: f32,
    /// The least beta (m), so density stays finite and the sampler can resolve the surface.
    #[serde(default = "default_min_beta")]
    pub min_beta: f32,
    /// The grid encoding; `None` for the Fourier (`mlp`) one.
    #[serde(default)]
    pub grid: Option<GridConfig>,
    /// Hidden layers of a separate albedo decoder on the same features (0: the albedo is three
    /// more outputs of the SDF's decoder).
    #[serde(default)]
    pub albedo_layers: usize,
}

/// How far from the root bone (in skinning widths) the `grid` field's skinning sees its
/// distance stop growing (`grid::RootSkinning`): a point on a tight limb (within 1.5 widths of
/// its bone) then gives the root a few percent at most, exp(-(3^2 - 1.5^2) / 2) = 3%, before
/// the root's learned preference moves the border.
pub const ROOT_REACH_PER_WIDTH: f32 = 3.0;

impl FieldConfig {
    /// Checks a recorded field (a checkpoint's `state.json`) for a skeleton of `bones` bones
    /// before a field is built from it: sizes in range and every length finite and positive.
    /// The error names the key.
    pub fn check(&self, bones: usize) -> Result<(), String> {
        if self.bones != bones {
            return Err(format!("bones: {} recorded for a skeleton of {bones}", self.bones));
        }
        if !(1..=4096).contains(&self.hidden) || !(1..=64).contains(&self.layers) || self.albedo_layers > 64 || self.frequencies.len() > 64 {
            return Err(format!(
                "hidden, layers, albedo_layers, frequencies: {}, {}, {}, {} values out of range (1-4096, 1-64, 0-64, at most 64)",
                self.hidden,
                self.layers,
                self.albedo_layers,
                self.frequencies.len()
            ));
        }
        if let Some(f) = self.frequencies.iter().find(|f| !f.is_finite()) {
            return Err(format!("frequencies: {f} is not finite"));
        }
        for (what, value) in [
            ("skinning_width", self.skinning_width),
            ("prior_radius", self.prior_radius),
            ("initial_beta", self.initial_beta),
            ("residual_scale", self.residual_scale),
            ("min_beta", self.min_beta),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(format!("{what}: {value} is not a finite positive number"));
            }
        }
        match &self.grid {
            Some(grid) => grid.check(bones).map_err(|e| format!("grid.{e}")),
            None => Ok(()),
        }
    }

    /// The `mlp` field: Fourier features in every bone's frame into a 3 x 64 MLP.
    pub fn for_bones(bones: usize) -> Self {
        Self {
            bones,
            hidden: 64,
            layers: 3,
            frequencies: vec![12.0, 25.0, 50.0],
            skinning_width: 0.05,
            prior_radius: 0.06,
            initial_beta: 0.03,
            residual_scale: 0.1,
            min_beta: MIN_BETA,
            grid: None,
            albedo_layers: 0,
        }
    }

    /// The `grid` field: feature grids shaped by the body (`GridConfig::for_body`) into a
    /// 2 x 64 decoder for the SDF and another for the albedo. With one decoder for both, the
    /// Eikonal and curvature losses, which want the fine levels' features smooth, also smooth
    /// the albedo, and its checkers and stripes feed bumps into the surface; apart, the SDF's
    /// decoder can ignore features only the albedo needs. human-sun-128, seeds 0 / 1, foreground
    /// novel pose 23.32 / 24.02 -> 24.66 / 24.68 dB, albedo 29.61 / 30.16 -> 31.09 / 30.90 dB.
    pub fn with_grid(bone_lengths: Vec<f32>, extent: f32) -> Self {
        let bones = bone_lengths.len();
        Self { layers: 2, grid: Some(GridConfig::for_body(bone_lengths, extent)), albedo_layers: 2, ..Self::for_bones(bones) }
    }

    pub fn skinning(&self) -> Skinning {
        let root = self.grid.as_ref().and_then(|g| g.root);
        // The prior's cap (the root's, less the capsule's radius).
        let prior_cap = root.filter(|root| root.prior_capped).map(|root| root.cap - self.prior_radius);
        Skinning { sharpness: self.sharpness(), prior_radius: self.prior_radius, root: root.map(|root| (root.bone, root.cap)), prior_cap }
    }

    /// The factor on squared distance in the skinning softmax's logits.
    fn sharpness(&self) -> f32 {
        -0.5 / (self.skinning_width * self.skinning_width)
    }

    pub fn input_width(&self) -> usize {
        match &self.grid {
            Some(grid) => grid.width(),
            None => self.bones * 3 * (1 + 2 * self.frequencies.len()),
        }
    }

    /// A field with weights drawn from our own seeded stream (uniform in +-1/sqrt(fan_in), as
    /// burn's default), so that a fit is reproducible whatever else uses burn's global RNG.
    pub fn init(&self, device: &Device, seed: u64) -> AvatarField {
        let mut stream = crate::random::Stream::new(seed, 0xF1E1D, 0);
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
        let separate = self.albedo_layers > 0;
        let output = linear(width, if separate { 1 } else { 4 }, 0.01);
        let mut albedo_hidden = Vec::new();
        let mut width = self.input_width();
        for _ in 0..self.albedo_layers {
            albedo_hidden.push(linear(width, self.hidden, 1.0));
            width = self.hidden;
        }
        let albedo_output = separate.then(|| linear(width, 3, 0.01));
        AvatarField {
            grid: self.grid.as_ref().map(|g| g.init(device, seed)),
            hidden,
            output,
            albedo_hidden,
            albedo_output,
            beta_raw: Param::from_tensor(Tensor::from_data(TensorData::new(vec![self.initial_beta.ln() / BETA_RATE], [1]), device)),
            config: self.clone(),
        }
    }
}

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

fn default_residual_scale() -> f32 {
    0.1
}

fn default_min_beta() -> f32 {
    MIN_BETA
}

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
                let g = grid.encode(points, &pose.frames, self.config.skinning(), tangents);
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
