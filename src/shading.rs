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

/// What of a vector's length may lie across an axis it is opposite to from f32's rounding alone.
const ACROSS_ROUNDING: f32 = 1e-5;

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

    /// The light with its sun's vector rotated, within the plane of `axis` and the vector, back
    /// onto the cone of half-angle `angle` around `axis` when a step took it outside, its length
    /// kept (ambient, strength and shadow density untouched). On the device: a training step
    /// keeps the sun in the search's cone without reading the light back (a GPU waits on a read).
    pub fn kept_in_cone(mut self, axis: glam::DVec3, angle: f64) -> Self {
        let axis = axis.normalize_or_zero();
        if self.kind != LightKind::Directional || axis == glam::DVec3::ZERO {
            return self;
        }
        self.vector = self.vector.map(|value| {
            let grad = value.is_require_grad();
            let v = value.without_autodiff();
            let device = v.device();
            let constant = |d: glam::DVec3| Tensor::<1>::from_data(TensorData::new(d.as_vec3().to_array().to_vec(), [3]), &device);
            let a = constant(axis);
            let length = (v.clone() * v.clone()).sum().sqrt();
            let along = (v.clone() * a.clone()).sum();
            // Inside the cone, or too short to have a direction: left as it is.
            let inside = along.clone().greater_equal(length.clone() * angle.cos()).bool_or(length.clone().lower_elem(1e-12));
            let across = v.clone() - a.clone() * along;
            let across_length = (across.clone() * across.clone()).sum().sqrt();
            // A vector opposite the axis (to f32's rounding) has no plane with it: any side will do.
            let opposite = across_length.clone().lower_equal(length.clone() * ACROSS_ROUNDING);
            let side = (across / across_length.clamp_min(1e-30)).mask_where(opposite.expand([3]), constant(axis.any_orthonormal_vector()));
            let clamped = (a * angle.cos() + side * angle.sin()) * length;
            let kept = clamped.mask_where(inside.expand([3]), v);
            if grad {
                kept.autodiff().require_grad()
            } else {
                kept
            }
        });
        self
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

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    /// The vector `v` kept within `angle` of `axis`, in f64: rotated toward the axis in their
    /// plane onto the cone's edge, its length kept.
    fn kept_reference(v: DVec3, axis: DVec3, angle: f64) -> DVec3 {
        let axis = axis.normalize();
        if v.length() < 1e-12 || v.normalize().dot(axis) >= angle.cos() {
            return v;
        }
        let across = v - axis * v.dot(axis);
        let side = if across.length() > ACROSS_ROUNDING as f64 * v.length() { across.normalize() } else { axis.any_orthonormal_vector() };
        (axis * angle.cos() + side * angle.sin()) * v.length()
    }

    #[test]
    fn a_sun_outside_its_cone_is_turned_onto_its_edge_on_the_device_and_one_inside_is_left_alone() {
        let device = Device::flex().autodiff();
        let axis = DVec3::new(0.3, 0.9, 0.2);
        let angle = 14f64.to_radians();
        let mut stream = crate::random::Stream::new(5, 0, 0);
        let mut vectors: Vec<DVec3> = (0..200).map(|_| DVec3::new(stream.uniform() - 0.5, stream.uniform() - 0.5, stream.uniform() - 0.5) * 4.0).collect();
        // Inside, on the axis, opposite it, and next to nothing.
        vectors.extend([axis * 0.7 + DVec3::new(0.01, 0.0, -0.02), axis * 3.0, -axis * 1.5, DVec3::new(1e-14, 0.0, 0.0)]);
        let (mut moved, mut kept) = (0, 0);
        for v in vectors {
            let light = FittedLight::new(LightKind::Directional, v.as_vec3().to_array(), [0.0; 3], 1.0, 0.25, &device);
            let before = crate::backend::host_values(light.vector.val());
            let after = light.kept_in_cone(axis, angle);
            assert!(after.vector.val().is_require_grad(), "the vector is still a leaf that learns");
            let got = crate::backend::host_values(after.vector.val());
            let want = kept_reference(DVec3::new(before[0] as f64, before[1] as f64, before[2] as f64), axis, angle);
            let error = (DVec3::new(got[0] as f64, got[1] as f64, got[2] as f64) - want).length();
            assert!(error <= 1e-5 * want.length().max(1e-6), "{v}: {got:?} against {want}");
            if got == before {
                kept += 1;
            } else {
                moved += 1;
                let turned = DVec3::new(got[0] as f64, got[1] as f64, got[2] as f64).normalize().dot(axis.normalize()).acos();
                assert!((turned - angle).abs() < 1e-5, "{v}: {} degrees from the axis", turned.to_degrees());
            }
        }
        assert!(moved > 150 && kept >= 3, "{moved} moved, {kept} left alone");
    }

    #[test]
    fn a_point_light_has_no_cone() {
        let device = Device::flex();
        let light = FittedLight::new(LightKind::Point, [2.0, 0.0, 0.0], [0.0; 3], 1.0, 0.25, &device);
        let before = crate::backend::host_values(light.vector.val());
        let after = light.kept_in_cone(DVec3::Y, 0.1);
        assert_eq!(crate::backend::host_values(after.vector.val()), before);
    }
}
