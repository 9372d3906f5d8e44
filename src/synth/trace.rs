//! Exact image formation for synthetic scenes: sphere tracing of the character's analytic SDF,
//! analytic normals, hard shadows by a shadow ray, and the scene format's shading formula;
//! uniform and environment lights by Monte Carlo over cosine-weighted directions with visibility.

use super::character::Character;
use crate::light::Light;
use crate::scene::Ray;
use crate::skeleton::Pose;
use glam::DVec3;

/// How far off the surface shadow and secondary rays start (metres), so a surface does not
/// shadow itself through rounding.
pub const SHADOW_OFFSET: f64 = 1e-3;
const HIT_EPSILON: f64 = 1e-7;
const MAX_STEPS: usize = 512;

/// A posed character to trace against.
pub struct Traced<'a> {
    pub character: &'a Character,
    pub pose: &'a Pose,
    centre: DVec3,
    radius: f64,
}

/// What a camera ray sees at a surface.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub t: f64,
    pub point: DVec3,
    pub normal: DVec3,
}

impl<'a> Traced<'a> {
    pub fn new(character: &'a Character, pose: &'a Pose) -> Self {
        let (centre, radius) = character.bounding_sphere(pose);
        Self { character, pose, centre, radius }
    }

    /// The `[t_in, t_out]` interval of the ray inside the bounding sphere, if any.
    fn bounds(&self, ray: &Ray, t_max: f64) -> Option<(f64, f64)> {
        let oc = ray.origin - self.centre;
        let b = oc.dot(ray.direction);
        let c = oc.length_squared() - self.radius * self.radius;
        let disc = b * b - c;
        if disc <= 0.0 {
            return None;
        }
        let root = disc.sqrt();
        let (t0, t1) = ((-b - root).max(0.0), (-b + root).min(t_max));
        (t1 > t0).then_some((t0, t1))
    }

    /// The first surface crossing along the ray within `t_max`.
    pub fn intersect(&self, ray: &Ray, t_max: f64) -> Option<Hit> {
        let (mut t, t_end) = self.bounds(ray, t_max)?;
        for _ in 0..MAX_STEPS {
            let p = ray.at(t);
            let (d, gradient) = self.character.sdf(self.pose, p);
            if d < HIT_EPSILON {
                // Polish the root with Newton steps along the ray (the SDF is smooth here).
                for _ in 0..3 {
                    let (d, g) = self.character.sdf(self.pose, ray.at(t));
                    let slope = g.dot(ray.direction);
                    if slope.abs() < 1e-3 {
                        break;
                    }
                    t -= d / slope;
                }
                let point = ray.at(t);
                return Some(Hit { t, point, normal: self.character.normal(self.pose, point) });
            }
            let _ = gradient;
            // The blended SDF is Lipschitz to within the capsules' taper: step 0.9 of it.
            t += d * 0.9;
            if t > t_end {
                return None;
            }
        }
        None
    }

    /// Whether anything blocks the segment from `point` (offset along `normal`) toward `direction`.
    pub fn visible(&self, point: DVec3, normal: DVec3, direction: DVec3, t_max: f64) -> bool {
        let origin = point + normal * SHADOW_OFFSET;
        self.intersect(&Ray { origin, direction }, t_max).is_none()
    }
}

pub use crate::random::Stream;

/// A cosine-weighted direction about `normal`, sample `k` of `n` stratified on a square grid.
pub fn cosine_direction(normal: DVec3, k: usize, n: usize, stream: &mut Stream) -> DVec3 {
    let side = (n as f64).sqrt().floor().max(1.0) as usize;
    let (cell_x, cell_y) = if k < side * side { (k % side, k / side) } else { (0, 0) };
    let cells = if k < side * side { side as f64 } else { 1.0 };
    let u1 = (cell_x as f64 + stream.uniform()) / cells;
    let u2 = (cell_y as f64 + stream.uniform()) / cells;
    let r = u1.sqrt();
    let phi = 2.0 * std::f64::consts::PI * u2;
    let (tangent, bitangent) = normal.any_orthonormal_pair();
    (tangent * (r * phi.cos()) + bitangent * (r * phi.sin()) + normal * (1.0 - u1).max(0.0).sqrt()).normalize()
}

/// Outgoing radiance of a Lambertian point per the scene format's image formation.
pub fn shade(traced: &Traced, hit: &Hit, albedo: DVec3, light: &Light, samples: usize, stream: &mut Stream) -> DVec3 {
    match light {
        Light::Directional { direction, irradiance, ambient } => {
            let cosine = hit.normal.dot(*direction).max(0.0);
            let lit = if cosine > 0.0 && traced.visible(hit.point, hit.normal, *direction, f64::INFINITY) { 1.0 } else { 0.0 };
            albedo * (*ambient + *irradiance * (cosine * lit))
        }
        Light::Point { position, intensity, ambient } => {
            let to_light = *position - hit.point;
            let r = to_light.length();
            let direction = to_light / r;
            let cosine = hit.normal.dot(direction).max(0.0);
            let lit = if cosine > 0.0 && traced.visible(hit.point, hit.normal, direction, r - SHADOW_OFFSET) { 1.0 } else { 0.0 };
            albedo * (*ambient + *intensity / (r * r) * (cosine * lit))
        }
        // A scene's unknown light has nothing to trace but its ambient.
        Light::Unknown { ambient, .. } => albedo * *ambient,
        Light::Uniform { radiance } => {
            let open = (0..samples).filter(|&k| traced.visible(hit.point, hit.normal, cosine_direction(hit.normal, k, samples, stream), f64::INFINITY)).count();
            albedo * *radiance * (open as f64 / samples.max(1) as f64)
        }
        Light::Environment { scale, map, .. } => {
            let mut sum = DVec3::ZERO;
            for k in 0..samples {
                let d = cosine_direction(hit.normal, k, samples, stream);
                if traced.visible(hit.point, hit.normal, d, f64::INFINITY) {
                    sum += map.lookup(d);
                }
            }
            albedo * sum * (*scale / samples.max(1) as f64)
        }
    }
}
