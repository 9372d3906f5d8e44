//! A field's shape (`FieldConfig`): its encoding, widths, the grid's settings and the beta it
//! starts from and keeps above; what a checkpoint records to rebuild the field it fitted.

use super::*;

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
    pub(super) fn sharpness(&self) -> f32 {
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

fn default_residual_scale() -> f32 {
    0.1
}

fn default_min_beta() -> f32 {
    MIN_BETA
}
