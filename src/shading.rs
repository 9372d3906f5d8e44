//! Deferred shading and the learnable light model: `albedo x (ambient + E max(0, n.l) T)`,
//! with T the transmittance of the posed Gaussians along the shadow ray. A sun is a learnable
//! unit direction with fixed irradiance 1 (its scale is not separable from the albedo's; a
//! capture's further suns learn theirs relative to it); a point light is a learnable position
//! (in body units) and its irradiance at the body's centre; ambient is learnable RGB. Lengths
//! (the shadow ray's start, the Gaussians' density) are on the body's scale. The light knows
//! nothing of the network.

use crate::shadow::tensor::{transmittance_from, GaussianTensors, RaySegments};
use burn::module::Param;
use burn::tensor::activation::softplus;
use burn::tensor::{Device, Tensor, TensorData};

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LightKind {
    Directional,
    Point,
    /// Uniform light: shading is the albedo, no direction, no shadow rays.
    Uniform,
}

#[derive(burn::module::Module, Debug)]
pub struct FittedLight {
    /// Unnormalised direction toward a sun, or a point light's position in body units
    /// (`position` gives metres).
    pub vector: Param<Tensor<1>>,
    pub ambient_raw: Param<Tensor<1>>,
    /// Log of a point light's irradiance at `anchor` (its intensity over the squared distance
    /// to it): moving the light then changes how the light falls across the body, not how
    /// bright the body is, so position and strength are learned apart. For a sun with
    /// `strength_learned`, the log of its irradiance.
    pub log_intensity: Param<Tensor<1>>,
    /// The factor on the Gaussians' optical depth (their density is fitted to tanh-squashed
    /// field density, so a body is optically thinner than a hard shadow needs), through a
    /// sigmoid into [1, 30] so it can sharpen shadows but not run away.
    pub density_scale_raw: Param<Tensor<1>>,
    #[module(skip)]
    pub kind: LightKind,
    /// The body's centre, where a point light's `log_intensity` is measured.
    #[module(skip)]
    pub anchor: [f32; 3],
    /// Whether a sun's irradiance is learned (`log_intensity`) rather than 1: every sun of a
    /// capture lit by several but the first, whose 1 is the scale the albedo is measured in.
    #[module(skip)]
    pub strength_learned: bool,
    /// Where shadow rays start off the surface (m): `SHADOW_START` on the body's scale.
    #[module(skip)]
    pub shadow_start: f32,
    /// The body's length unit (`skeleton::body_length(1, extent)`): the Gaussians' amplitudes
    /// are optical density per unit, so the same body at another size casts the same shadows.
    #[module(skip)]
    pub unit: f32,
}

/// Distance (m, on the reference human: a fit uses `skeleton::body_length` of it, kept in
/// `FittedLight::shadow_start`) the shadow ray starts off the surface, along the normal and
/// along the ray. It was 7.5 cm, to keep a surface from being shadowed by the Gaussians that
/// model its own skin (on human-sun: 3 cm put the sun 4.0 degrees off, 7.5 cm 1.5-1.7), which
/// lost every contact shadow nearer than that. Those Gaussians are now left out by their share
/// of the density at the point (`shadow::own_shares`), so the start only has to clear the
/// blur of the next ones along a limb: 3 cm, about the Gaussians' median scale on the shipped
/// humans (3.4 cm). Measured with the shares, seed 0, 3 cm against 7.5 cm: human-sun sun 1.26
/// against 1.54 degrees, foreground novel pose 28.69 against 28.22 dB, novel view 27.86
/// against 27.02; human-dressed 4.35 against 3.27 degrees, 25.59 against 24.63 dB.
pub const SHADOW_START: f32 = 0.03;

/// A light that casts shadows, as tensors (learnable or fixed): RGB `irradiance` or
/// `intensity` `[3]`, unit `direction` toward a sun or a point light's `position` `[3]`.
pub enum Emitter {
    Sun { direction: Tensor<1>, irradiance: Tensor<1> },
    Point { position: Tensor<1>, intensity: Tensor<1> },
}

/// `value` `[3]` as `[1, 3]` (to broadcast) or, with `weights` `[r]`, as `r` rows whose
/// gradient is scaled row by row by them (the forward values are unchanged).
fn rows_scaled(value: Tensor<1>, r: usize, weights: Option<&Tensor<1>>) -> Tensor<2> {
    match weights {
        None => value.reshape([1, 3]),
        Some(w) => {
            let rows = value.reshape([1, 3]).repeat_dim(0, r);
            rows.clone().detach() + (rows.clone() - rows.detach()) * w.clone().reshape([r, 1])
        }
    }
}

/// The image formation of the scene format, for training and relighting alike:
/// `albedo x (ambient + E max(0, n.l) T)`, T the transmittance of `casters` along the shadow
/// ray that starts `start` (m) off the surface, each Gaussian weighted by one less its share
/// of the density at the point (`shadow::own_shares`: a body part does not shadow the surface
/// it makes); a point light's E falls off as 1 / r^2 and its shadow ray ends at the light.
/// With `weights` `[R]`, the light's gradient (direction or position, irradiance, ambient) is
/// scaled ray by ray by them (0 for the rays drawn where the fit is wrong: `Schedule::error_rays`); the
/// colours are the same.
#[allow(clippy::too_many_arguments)]
pub fn shade_lambertian(
    albedo: Tensor<2>,
    points: Tensor<2>,
    normals: Tensor<2>,
    casters: &GaussianTensors,
    ambient: Tensor<1>,
    emitter: &Emitter,
    start: f32,
    weights: Option<&Tensor<1>>,
) -> Tensor<2> {
    let [r, _] = points.dims();
    let device = points.device();
    let (direction, irradiance, t1) = match emitter {
        Emitter::Sun { direction, irradiance } => {
            let direction = match weights {
                None => direction.clone().reshape([1, 3]).repeat_dim(0, r),
                Some(_) => rows_scaled(direction.clone(), r, weights),
            };
            (direction, rows_scaled(irradiance.clone(), r, weights), None)
        }
        Emitter::Point { position, intensity } => {
            let to_light = rows_scaled(position.clone(), r, weights) - points.clone();
            let distance = (to_light.clone() * to_light.clone()).sum_dim(1).sqrt().clamp_min(1e-3);
            let irradiance = rows_scaled(intensity.clone(), r, weights) / (distance.clone() * distance.clone());
            (to_light / distance.clone(), irradiance, Some(distance.reshape([r])))
        }
    };
    let ambient = rows_scaled(ambient, r, weights);
    let cosine = (normals.clone() * direction.clone()).sum_dim(1).clamp_min(0.0);
    let segments = RaySegments { origins: points.clone() + normals * start, directions: direction, t0: Tensor::full([r], start, &device), t1 };
    let visibility = transmittance_from(casters, &segments, points).reshape([r, 1]);
    albedo * (ambient + irradiance * cosine * visibility)
}

fn inverse_softplus(v: f32) -> f32 {
    (v.exp() - 1.0).ln()
}

impl FittedLight {
    /// A light of `kind` starting at `initial` (a direction, or a position in metres) for a
    /// body centred at `anchor` whose extent is `extent` (m).
    pub fn new(kind: LightKind, initial: [f32; 3], anchor: [f32; 3], extent: f64, ambient: f32, device: &Device) -> Self {
        let t = |v: Vec<f32>| Param::from_tensor(Tensor::from_data(TensorData::new(v.clone(), [v.len()]), device));
        let unit = crate::skeleton::body_length(1.0, extent) as f32;
        let vector = match kind {
            LightKind::Point => initial.map(|c| c / unit),
            _ => initial,
        };
        Self {
            vector: t(vector.to_vec()),
            ambient_raw: t(vec![inverse_softplus(ambient); 3]),
            log_intensity: t(vec![0.0]),
            density_scale_raw: t(vec![-2.2]),
            kind,
            anchor,
            strength_learned: false,
            shadow_start: crate::skeleton::body_length(SHADOW_START as f64, extent) as f32,
            unit,
        }
    }

    /// The same light with a learned irradiance (a sun; a point light's is always learned).
    pub fn with_learned_strength(self) -> Self {
        Self { strength_learned: true, ..self }
    }

    /// A sun's irradiance `[3]`: 1, or the learned one.
    pub fn irradiance(&self) -> Tensor<1> {
        let device = self.vector.val().device();
        match self.strength_learned {
            true => self.log_intensity.val().exp().repeat_dim(0, 3),
            false => Tensor::ones([3], &device),
        }
    }

    /// A point light's position (m).
    pub fn position(&self) -> Tensor<1> {
        self.vector.val() * self.unit
    }

    /// A point light's radiant intensity: the irradiance at the anchor times the squared
    /// distance to it.
    pub fn intensity(&self) -> Tensor<1> {
        let device = self.vector.val().device();
        let offset = self.position() - Tensor::from_data(TensorData::new(self.anchor.to_vec(), [3]), &device);
        self.log_intensity.val().exp() * (offset.clone() * offset).sum()
    }

    pub fn density_scale(&self) -> Tensor<1> {
        burn::tensor::activation::sigmoid(self.density_scale_raw.val()) * 29.0 + 1.0
    }

    pub fn ambient(&self) -> Tensor<1> {
        softplus(self.ambient_raw.val(), 1.0)
    }

    /// Where the light is, as plain numbers: a sun's unit direction, a point light's position
    /// (m); none for uniform light.
    pub fn location(&self) -> Option<[f64; 3]> {
        let values = crate::backend::to_host(self.location_tensor()?).ok()?;
        location_of(&values)
    }

    /// `location` on the device (`[3]`), for a caller that reads it with other values.
    pub fn location_tensor(&self) -> Option<Tensor<1>> {
        match self.kind {
            LightKind::Directional => Some(self.direction()),
            LightKind::Point => Some(self.position()),
            LightKind::Uniform => None,
        }
    }

    pub fn direction(&self) -> Tensor<1> {
        let v = self.vector.val();
        v.clone() / (v.clone() * v).sum().sqrt().clamp_min(1e-8)
    }

    /// Shaded colour `[R, 3]` of surface points `[R, 3]` with normals `[R, 3]` and albedo `[R, 3]`.
    /// `gaussians` should be detached when the Gaussians must learn only from their own fit.
    pub fn shade(&self, albedo: Tensor<2>, points: Tensor<2>, normals: Tensor<2>, gaussians: &GaussianTensors) -> Tensor<2> {
        self.shade_weighted(albedo, points, normals, gaussians, None)
    }

    /// `shade` with the light's gradient scaled ray by ray by `weights` `[R]` (none: `shade`).
    pub fn shade_weighted(
        &self,
        albedo: Tensor<2>,
        points: Tensor<2>,
        normals: Tensor<2>,
        gaussians: &GaussianTensors,
        weights: Option<&Tensor<1>>,
    ) -> Tensor<2> {
        let Some(emitter) = self.emitter() else { return albedo };
        shade_lambertian(albedo, points, normals, &self.shadow_casters(gaussians), self.ambient(), &emitter, self.shadow_start, weights)
    }

    /// The light as an emitter of the image formation; none for uniform light.
    fn emitter(&self) -> Option<Emitter> {
        match self.kind {
            LightKind::Uniform => None,
            LightKind::Directional => Some(Emitter::Sun { direction: self.direction(), irradiance: self.irradiance() }),
            LightKind::Point => Some(Emitter::Point { position: self.position(), intensity: self.intensity().repeat_dim(0, 3) }),
        }
    }

    /// The Gaussians as shadow casters: their optical depth times the fitted density scale,
    /// per metre.
    pub fn shadow_casters(&self, gaussians: &GaussianTensors) -> GaussianTensors {
        GaussianTensors { amplitudes: gaussians.amplitudes.clone() * self.density_scale() / self.unit, ..gaussians.clone() }
    }

    /// The same for posed Gaussians on the CPU (rendering's sky visibility, the sun search).
    pub fn shadow_casters_posed(&self, posed: &[crate::shadow::PosedGaussian]) -> Vec<crate::shadow::PosedGaussian> {
        let scale = crate::backend::host_scalar(self.density_scale()) as f64;
        let per_metre = scale / self.unit as f64;
        posed.iter().map(|g| crate::shadow::PosedGaussian { amplitude: g.amplitude * per_metre, ..*g }).collect()
    }

    /// The light as plain numbers for fit.json: direction or position, ambient, intensity.
    pub fn report(&self) -> serde_json::Value {
        let v = |t: Tensor<1>| crate::backend::host_values(t);
        let ambient = v(self.ambient());
        match self.kind {
            LightKind::Directional => {
                serde_json::json!({"type": "directional", "direction": v(self.direction()), "irradiance": v(self.irradiance()), "ambient": ambient, "shadow_density_scale": v(self.density_scale())})
            }
            LightKind::Point => {
                serde_json::json!({"type": "point", "position": v(self.position()), "intensity": v(self.intensity()).repeat(3), "ambient": ambient, "shadow_density_scale": v(self.density_scale())})
            }
            LightKind::Uniform => serde_json::json!({"type": "uniform", "radiance": [1.0, 1.0, 1.0]}),
        }
    }
}

/// A light's location (`FittedLight::location`) from its three values read from the device;
/// none when they are fewer.
pub fn location_of(values: &[f32]) -> Option<[f64; 3]> {
    Some([*values.first()?, *values.get(1)?, *values.get(2)?].map(f64::from))
}
