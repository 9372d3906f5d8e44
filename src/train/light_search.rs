//! The light search at the start of the light stage: every training light starts from the best
//! of a sphere of sun directions (or point-light positions around the body), scored on surface
//! samples with the Gaussians' cast shadows; a sun then stays in a cone around it.

use super::Trainer;
use crate::field::PoseTensors;
use crate::fit_error::FitError;
use crate::render::{ray_bounds, render, RaySet};
use crate::shading::LightKind;
use burn::module::Module;
use burn::tensor::{Tensor, TensorData};

/// How far (in the search lattice's spacings, 7.2 degrees at 256 directions) gradient descent
/// may take the sun from the search's best. The search scores directions with the albedo still
/// grey and the geometry early, so it can be off by more than its lattice's spacing (dog-sun:
/// 14 degrees), and the gradient must be free to correct that; with one camera the gradient
/// also drifts wherever it is free to. Measured at 1, 2 and 3 spacings: human-mono (seed 0)
/// 0.90 / 2.71 / 5.09 degrees, dog-sun 7.51 / 2.72 / 2.60; at 2, human-mono seeds 1 and 2:
/// 1.02 and 1.01.
pub const SUN_CONE_SPACINGS: f64 = 2.0;

impl Trainer {
    /// Training frames for the sun search: up to this many, evenly spread over the capture.
    pub(super) const SEARCH_FRAMES: usize = 8;
    /// Foreground rays per search frame.
    const SEARCH_RAYS: usize = 256;

    /// Searches every training light (`search_one`).
    pub(super) fn search_lights(&mut self) -> Result<(), FitError> {
        if let Some(state) = self.state.as_mut() {
            state.gaussians_read = None;
        }
        for k in 0..self.cones.len() {
            self.search_one(k)?;
        }
        Ok(())
    }

    /// Scores sun directions over the sphere (or point light positions around the body) on
    /// surface samples of several frames under training light `k` (with the Gaussians' cast
    /// shadows) and starts that light from the best (`sun_search`).
    fn search_one(&mut self, light: usize) -> Result<(), FitError> {
        let model = self.model()?.valid();
        let (samples, casters) = self.surface_samples(&model, light);
        if samples.is_empty() {
            return Ok(());
        }
        self.start_from_search(&model, light, &samples, &casters)
    }

    /// Surface samples (point, normal, albedo, colour) of up to `SEARCH_FRAMES` training frames
    /// under training light `light`, and each frame's shadow casters as the light casts them.
    fn surface_samples(&mut self, model: &crate::avatar::Avatar, light: usize) -> (Vec<crate::sun_search::SurfaceSample>, Vec<crate::shadow::ShadowCaster>) {
        let device = self.device.clone().without_autodiff();
        let set = model.gaussians.to_set();
        let count = self.frames.len().clamp(1, Self::SEARCH_FRAMES);
        let mut samples = Vec::new();
        let mut casters = Vec::new();
        for k in 0..count {
            let data = &self.frames[k * self.frames.len() / count];
            let pose = &self.corrected_pose(data.position);
            // Bounds and shadows from the Gaussians as the light casts them (density scaled).
            let posed = model.light_at(light).shadow_casters_posed(&set.pose(pose));
            let views: Vec<usize> = data.views.iter().copied().filter(|&v| self.view_light[v] == Some(light)).collect();
            if views.is_empty() {
                continue;
            }
            let mut rays = RaySet::default();
            let mut colours = Vec::new();
            for _ in 0..Self::SEARCH_RAYS {
                let v = views[self.stream.below(views.len())];
                let pool = &self.views[v].foreground;
                if pool.is_empty() {
                    continue;
                }
                let pixel = pool.get(self.stream.below(pool.len())) as usize;
                let view = &self.scene.views[v];
                let camera = &self.scene.cameras[view.camera];
                let ray = camera.pixel_ray(pixel % camera.width, pixel / camera.width);
                if let Some(bounds) = ray_bounds(ray.origin, ray.direction, &posed, self.min_bound_radius()) {
                    rays.push(ray.origin, ray.direction, Some(bounds));
                    colours.push(view.colour.pixel(pixel));
                }
            }
            if rays.is_empty() {
                continue;
            }
            let sampling = self.schedule.sampling(self.iteration());
            let jitter: Vec<f32> = (0..rays.len() * sampling.draws()).map(|_| self.stream.uniform() as f32).collect();
            let pose_tensors = PoseTensors::new(pose, &self.scene.skeleton, &device);
            let deferred = render(&model.field, &pose_tensors, &rays, sampling, &jitter, Some(self.gradient), &device);
            let host = |t: Tensor<2>| crate::backend::host_values(t);
            let accumulation = crate::backend::host_values(deferred.accumulation);
            let (points, albedo) = (host(deferred.surface), host(deferred.albedo));
            let normals = deferred.normal.map(host).unwrap_or_default();
            let frame = casters.len();
            for (i, colour) in colours.iter().enumerate() {
                // Only rays that found the surface: a grazing ray's point and normal are blends.
                if accumulation.get(i).is_none_or(|a| *a < 0.9) || normals.len() < 3 * (i + 1) || points.len() < 3 * (i + 1) {
                    continue;
                }
                let three = |v: &[f32]| [v[3 * i], v[3 * i + 1], v[3 * i + 2]];
                let n = three(&normals);
                let length = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                if length.is_nan() || length <= 1e-6 {
                    continue;
                }
                samples.push(crate::sun_search::SurfaceSample {
                    frame,
                    point: three(&points),
                    normal: n.map(|c| c / length),
                    albedo: three(&albedo),
                    colour: *colour,
                });
            }
            casters.push(crate::shadow::ShadowCaster::new(&posed, 1e-3));
        }
        (samples, casters)
    }

    /// Searches light `light` over `samples` and starts it from the best: its direction or
    /// position, its strength, and for a sun the cone it then stays in.
    fn start_from_search(
        &mut self,
        model: &crate::avatar::Avatar,
        light: usize,
        samples: &[crate::sun_search::SurfaceSample],
        casters: &[crate::shadow::ShadowCaster],
    ) -> Result<(), FitError> {
        let start = model.light_at(light).shadow_start;
        let report = match self.light_kind {
            LightKind::Point => {
                let directions = (self.schedule.sun_search / 2).max(1);
                crate::sun_search::search_point(samples, casters, self.body_centre, self.body_extent, directions, 32, start)
            }
            _ => crate::sun_search::search(samples, casters, self.schedule.sun_search, 64, start),
        };
        let mut state = self.state.take().ok_or_else(|| FitError::Input("the training state was lost by an interrupted step".into()))?;
        let model = &mut state.model;
        let device = self.device.clone();
        let vector = match report.best.position {
            Some(position) => position.map(|c| (c / self.body_unit()) as f32),
            None => report.best.direction.map(|c| c as f32),
        };
        // The search's strength as the light's: a point light's as its irradiance at the
        // body's centre; a sun's (after the first, whose irradiance is the scale) relative to
        // the first sun's.
        let log_strength = match (report.best.position, self.searches.first().and_then(|s| s.as_ref())) {
            (Some(p), _) => Some(report.best.strength / (glam::DVec3::from_array(p) - self.body_centre).length().max(1e-6).powi(2)),
            (None, Some(first)) if light > 0 => Some(report.best.strength / first.best.strength),
            _ => None,
        }
        .filter(|s| s.is_finite() && *s > 0.0)
        .map(|s| s.ln() as f32);
        let target = model.light_at_mut(light);
        // The same parameter (its id keys the optimizer's state), a new value.
        target.vector = target.vector.clone().map(|_| Tensor::from_data(TensorData::new(vector.to_vec(), [3]), &device).require_grad());
        if let Some(log) = log_strength {
            target.log_intensity = target.log_intensity.clone().map(|_| Tensor::from_data(TensorData::new(vec![log], [1]), &device).require_grad());
        }
        self.state = Some(state);
        if self.light_kind == LightKind::Directional {
            // Gradient descent refines the direction within SUN_CONE_SPACINGS lattice spacings
            // of the search's best and no farther: with one camera it otherwise slides back to
            // the minimum the search escaped.
            let spacing = (4.0 / self.schedule.sun_search as f64).sqrt();
            self.cones[light] = Some((glam::DVec3::from_array(report.best.direction), spacing * SUN_CONE_SPACINGS));
        }
        self.searches[light] = Some(report);
        Ok(())
    }
}
