//! Batch drawing: pixels of one training frame's views under one training light (a third each
//! from the foreground, the silhouette's band and anywhere, part of that where the fit is still
//! wrong), and every random number the step then uses, so that a step is a function of its batch
//! and the trainer's state.

use super::Trainer;
use crate::fit_error::FitError;
use crate::gaussians::GaussianSet;
use crate::losses::Input;
use crate::render::{ray_bounds, RaySet};

/// Half-width (pixels) of the band around a silhouette that a third of each batch samples:
/// there the surface's position is decided, and uniform sampling hits it rarely (a few
/// percent of a view's pixels).
pub(super) const BOUNDARY_BAND: usize = 2;

/// How far a mask is trusted within `silhouette::EDGE_BAND` of its edge where the plate is
/// known, against 1 elsewhere: there the colour composited over the plate decides the
/// silhouette, and a mask a pixel off or with a stray blob must not.
pub const MASK_TRUST_NEAR_EDGE: f32 = 0.0;

/// Whether the `j`-th draw of a part of the batch is one of the evenly spread `share` of its
/// draws (every (1 / share)-th: 0 takes none, 1 every one).
fn takes_share(j: usize, share: f64) -> bool {
    let j = j as f64;
    (j * share).floor() != ((j + 1.0) * share).floor()
}

/// A training batch: pixels of one frame's views under one training light, and the random
/// numbers the step draws its samples with.
#[derive(Clone)]
pub struct Batch {
    /// The training frame (an index into the trainer's frames) and light.
    pub frame: usize,
    pub light: usize,
    /// The frame's pose as the motion's refinement has corrected it so far, while it is refined
    /// (else the step renders the given pose).
    pub corrected: Option<(crate::skeleton::Pose, crate::field::PoseTensors)>,
    /// Rays that meet a Gaussian's bound first (`hits` of them, only they enter the field),
    /// then the others, which are background: colour and accumulation zero. While the cameras
    /// are refined, they leave their cameras as refined so far, each with its camera's row
    /// (`RaySet::cameras`; empty otherwise).
    pub rays: RaySet,
    pub hits: usize,
    /// How many rays are rendered: the hits (at least one, so the graph is never empty), or
    /// every ray when the trainer renders missed rays too.
    pub rendered: usize,
    /// Per pixel, its colour (linear RGB) and mask.
    pub colours: Vec<f32>,
    pub masks: Vec<f32>,
    /// Per pixel when some view has a plate (else empty): what lies behind the body (linear
    /// RGB; the plate near the mask's edge, black elsewhere) and how far its mask is trusted
    /// (`MASK_TRUST_NEAR_EDGE` near the edge, 1 elsewhere).
    pub backgrounds: Vec<f32>,
    pub mask_weights: Vec<f32>,
    /// Per pixel, its view, its index in the view, and whether it was drawn by the view's
    /// error map (`Schedule::error_rays`).
    pub sources: Vec<(usize, usize, bool)>,
    /// The stratified samples' jitter, `Sampling::draws` per rendered ray.
    pub jitter: Vec<f32>,
    /// Which of the rendered rays' samples the density loss compares (empty when it is off).
    pub density_samples: Vec<i64>,
    /// Which samples the Eikonal and curvature losses take the SDF's gradient at (empty when
    /// both are off), and the curvature's offsets from them (m, 3 per sample; empty when off).
    pub regulariser_samples: Vec<i64>,
    pub curvature_offsets: Vec<f32>,
}

impl Trainer {
    /// Draws the next batch (`pixels`) and every random number its step uses, in the stream's
    /// order: the pixels, the samples' jitter, the density loss's samples, the regularisers'.
    pub fn draw_batch(&mut self) -> Result<Batch, FitError> {
        let it = self.iteration();
        let set = match self.state.as_mut().and_then(|s| s.gaussians_read.take()) {
            Some(set) => set,
            None => self.model()?.gaussians.to_set(),
        };
        let mut batch = self.pixels(&set);
        let rendered = if self.render_missed_rays { batch.rays.len() } else { batch.hits.max(1) };
        let sampling = self.schedule.sampling(it);
        let samples = rendered * sampling.total();
        let jitter: Vec<f32> = (0..rendered * sampling.draws()).map(|_| self.stream.uniform() as f32).collect();
        let needs = |input: Input| self.schedule.needs(input, it);
        let density = needs(Input::Density) && self.schedule.density_points > 0;
        let curvature = needs(Input::NormalPairs);
        let regularised = (needs(Input::Gradient) || curvature) && self.schedule.regulariser_points > 0;
        let density_samples = if density { self.random_indices(self.schedule.density_points, samples) } else { Vec::new() };
        let q = if regularised { self.schedule.regulariser_points } else { 0 };
        let regulariser_samples = self.random_indices(q, samples);
        let reach = self.schedule.curvature_epsilon * self.body_unit();
        let curvature_offsets: Vec<f32> =
            if curvature { (0..q * 3).map(|_| ((self.stream.uniform() - 0.5) * 2.0 * reach) as f32).collect() } else { Vec::new() };
        batch.rendered = rendered;
        Ok(Batch { jitter, density_samples, regulariser_samples, curvature_offsets, ..batch })
    }

    /// Samples pixels from one random training frame, all from its views under one training
    /// light, each pixel as the ray through its centre (the batch's random numbers still to draw).
    fn pixels(&mut self, set: &GaussianSet) -> Batch {
        let frame = self.stream.below(self.frames.len());
        let data = &self.frames[frame];
        // With several lights, the light of a random view of the frame (so each light is drawn
        // as often as it lights training images), and only its views.
        let (light, same_light): (usize, Vec<usize>) = if self.cones.len() > 1 {
            let first = data.views[self.stream.below(data.views.len())];
            let light = self.view_light[first].unwrap_or(0);
            (light, data.views.iter().copied().filter(|&v| self.view_light[v] == Some(light)).collect())
        } else {
            (0, data.views.clone())
        };
        let given = &self.scene.frames[data.position].pose;
        let refined = self.schedule.needs(Input::Motion, self.iteration());
        let corrected = match self.state.as_ref().and_then(|s| s.motion.as_ref()) {
            Some(motion) if refined => {
                let pose = motion.pose(&self.scene.skeleton, data.position, given);
                let tensors = crate::field::PoseTensors::new(&pose, &self.scene.skeleton, &self.device);
                Some((pose, tensors))
            }
            _ => None,
        };
        let posed = set.pose(corrected.as_ref().map_or(given, |c| &c.0));
        let cameras = self.state.as_ref().and_then(|s| s.cameras.as_ref()).filter(|_| self.schedule.needs(Input::Cameras, self.iteration()));
        let pixel_count = self.schedule.rays_per_batch.max(1);
        let mut drawn = Vec::with_capacity(pixel_count);
        let mut colours = Vec::with_capacity(pixel_count * 3);
        let mut masks = Vec::with_capacity(pixel_count);
        let mut sources = Vec::with_capacity(pixel_count);
        let anywhere = super::pixels::PixelRuns::default();
        for k in 0..pixel_count {
            let v = same_light[self.stream.below(same_light.len())];
            let view = &self.scene.views[v];
            let camera = &self.scene.cameras[view.camera];
            let pixels = camera.width * camera.height;
            // A third each from the foreground, the silhouette's band and the whole view.
            let pool = match k % 3 {
                0 => &self.views[v].foreground,
                1 => &self.views[v].boundary,
                _ => &anywhere,
            };
            let j = k / 3;
            // Of the third drawn anywhere, every (1 / error_rays)-th where the fit is wrong.
            let by_error = k % 3 == 2 && takes_share(j, self.error_rays);
            let wrong = match self.state.as_ref().and_then(|s| s.error_maps.get(v)).and_then(|m| m.as_ref()) {
                Some(map) if by_error => Some(map.draw(self.stream.uniform(), self.stream.uniform())),
                _ => None,
            };
            let pixel = match wrong {
                Some(p) => p,
                None if pool.is_empty() => self.stream.below(pixels),
                None => pool.get(self.stream.below(pool.len())) as usize,
            };
            let mask = view.mask.as_ref().map(|m| m.foreground[pixel] as u8 as f32).unwrap_or(0.0);
            let ray = camera.pixel_ray(pixel % camera.width, pixel / camera.width);
            let ray = cameras.map_or(ray, |c| c.corrected_ray(view.camera, ray));
            let bounds = ray_bounds(ray.origin, ray.direction, &posed, self.min_bound_radius());
            let behind = match &view.plate {
                Some(plate) if self.views[v].near_edge.contains(pixel as u32) => Some(plate.colour.pixels[pixel]),
                _ => None,
            };
            drawn.push((ray, bounds, view.colour.pixel(pixel), mask, behind, view.camera));
            sources.push((v, pixel, wrong.is_some()));
        }
        // A stable partition: hits first, in the order drawn.
        let hits = drawn.iter().filter(|d| d.1.is_some()).count();
        let mut order: Vec<usize> = (0..drawn.len()).collect();
        order.sort_by_key(|&d| drawn[d].1.is_none());
        let mut rays = RaySet::default();
        for &d in &order {
            let (ray, bounds, ..) = &drawn[d];
            rays.push(ray.origin, ray.direction, *bounds);
        }
        // Each ray's camera row: a camera not refined (no training view) cannot be drawn here.
        if let Some(cameras) = cameras {
            rays.cameras = order.iter().map(|&d| cameras.row(drawn[d].5).unwrap_or(0) as u32).collect();
        }
        // One ray per pixel: the targets follow the rays' order.
        let (mut backgrounds, mut mask_weights) = (Vec::new(), Vec::new());
        for &d in &order {
            colours.extend(drawn[d].2);
            masks.push(drawn[d].3);
            if self.plates {
                backgrounds.extend(drawn[d].4.unwrap_or([0.0; 3]));
                mask_weights.push(if drawn[d].4.is_some() { MASK_TRUST_NEAR_EDGE } else { 1.0 });
            }
        }
        let sources = order.iter().map(|&d| sources[d]).collect();
        Batch {
            frame,
            light,
            corrected,
            rays,
            hits,
            rendered: 0,
            colours,
            masks,
            backgrounds,
            mask_weights,
            sources,
            jitter: Vec::new(),
            density_samples: Vec::new(),
            regulariser_samples: Vec::new(),
            curvature_offsets: Vec::new(),
        }
    }

    fn random_indices(&mut self, count: usize, below: usize) -> Vec<i64> {
        (0..count).map(|_| self.stream.below(below) as i64).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_share_of_draws_is_spread_evenly() {
        for (share, expected) in [(0.0, 0), (0.25, 25), (0.5, 50), (1.0, 100)] {
            let taken: Vec<usize> = (0..100).filter(|&j| takes_share(j, share)).collect();
            assert_eq!(taken.len(), expected, "{share}");
            // Evenly: no two taken draws closer than 1 / share - 1 apart.
            if share > 0.0 {
                assert!(taken.windows(2).all(|w| (w[1] - w[0]) as f64 >= (1.0 / share).floor()), "{share}: {taken:?}");
            }
        }
    }
}
