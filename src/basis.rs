//! A visibility basis for interactive relighting (the one-light-at-a-time idea of the
//! relightable-characters supplement): for one pose and view, each covered pixel's visibility
//! toward a fixed set of directions (a spherical Fibonacci lattice), the Gaussians' closed-form
//! transmittance along each, computed once. Relighting the view by any environment map, uniform
//! sky, sun or point light is then a weighted sum over the directions, with no shadow ray
//! traced: an environment's texels are binned into the directions' cells (each cell the
//! texels nearest its direction), a sun's or point light's direction takes the visibility of
//! its nearest directions, blended so that it moves smoothly as the light moves. The cosine is
//! exact in every case (each pixel keeps its normal); what the basis approximates is where
//! visibility changes within a cell (a shadow's edge from a sun lands within about a cell's
//! width, 6 degrees at 1,024 directions) and a point light's shadow ray, which here does not
//! end at the light.

use crate::eval::Surfel;
use crate::imageio::RgbImage;
use crate::light::{fibonacci_sphere, uv_to_direction, EnvironmentMap, Light};
use crate::shadow::PosedGaussian;
use crate::shadow::{ShadowCaster, ShadowRay};
use glam::DVec3;
use rayon::prelude::*;
use std::f64::consts::PI;

/// Directions of a view's basis by default: cells of 4 pi / 1024 sr, about 6.3 degrees across.
pub const DIRECTIONS: usize = 1024;

/// Map positions per direction's cell below which an environment's texels are split before
/// they are binned (`TransferBasis::relight`): a 32 x 16 map binned whole into 1,024 cells
/// left most cells empty and the furnace 1.6% dark.
const SUBSAMPLES_PER_CELL: f64 = 16.0;

/// Columns of the (u, v) table that finds a direction's cell (`TransferBasis::cell_of`); the
/// table is twice as wide as tall, as an equirectangular map.
const TABLE_COLUMNS: usize = 256;

/// One view's transfer: per covered pixel its reflectance, normal and visibility toward every
/// direction of the lattice (0 below the pixel's horizon, never traced).
pub struct TransferBasis {
    pub width: usize,
    pub height: usize,
    pub directions: Vec<DVec3>,
    /// Pixel index (row by row) of each covered pixel.
    pixels: Vec<usize>,
    reflectance: Vec<DVec3>,
    /// What each pixel's shaded value is composited with (`eval::Surfel::coverage`).
    coverage: Vec<f32>,
    normals: Vec<DVec3>,
    /// Surface points (m): a point light's distance and direction differ per pixel.
    points: Vec<DVec3>,
    /// `pixels.len() x directions.len()` transmittances, pixel after pixel.
    visibility: Vec<f32>,
    /// Each (u, v) table cell's nearest direction.
    table: Vec<u32>,
    /// Per direction, the others within `NEIGHBOUR_SPACINGS` lattice spacings.
    neighbours: Vec<Vec<u32>>,
}

/// How far (in lattice spacings, plus a table cell's diagonal) a direction's neighbours reach:
/// a light within one spacing of a direction is within one spacing, the lattice's covering
/// radius (under one spacing) and a table cell of the table's nearest direction to it.
const NEIGHBOUR_SPACINGS: f64 = 2.0;

/// `TransferBasis::parts`: covered pixel indices, reflectance, unit normals, visibility rows
/// and coverage.
pub type BasisParts<'a> = (&'a [usize], &'a [DVec3], &'a [DVec3], &'a [f32], &'a [f32]);

impl TransferBasis {
    /// The basis of one view (`camera`, `frame`) of a fitted avatar: its surfels as the view
    /// renders draw them (`eval::surfels`), the fitted light's shadow casters in that pose.
    pub fn of_view(
        model: &crate::avatar::Avatar,
        scene: &crate::scene::Scene,
        camera: usize,
        frame: usize,
        directions: usize,
        device: &burn::tensor::Device,
    ) -> Self {
        let albedo_scale = crate::run::albedo_scale(scene, model);
        let surfels = crate::eval::surfels(model, scene, camera, frame, crate::eval::VIEW_SAMPLING, albedo_scale, device);
        let casters = model.light.shadow_casters_posed(&model.gaussians.to_set().pose(&scene.frames[frame].pose));
        let view = &scene.cameras[camera];
        Self::new(&surfels, view.width, view.height, &casters, model.light.shadow_start, directions)
    }

    /// The basis of a view from its `surfels` (`eval::surfels`, row by row, `width x height`:
    /// the pixels it draws, their reflectance weighted by their coverage), the shadow
    /// `casters` in its pose and the shadow ray's start off the surface (m).
    pub fn new(surfels: &[Option<Surfel>], width: usize, height: usize, casters: &[PosedGaussian], shadow_start: f32, count: usize) -> Self {
        let directions = fibonacci_sphere(count.max(1), 0.0);
        let covered: Vec<(usize, Surfel)> = surfels.iter().take(width * height).enumerate().filter_map(|(p, s)| s.map(|s| (p, s))).collect();
        let caster = ShadowCaster::new(casters, 1e-4);
        let visibility: Vec<f32> = covered
            .par_iter()
            .flat_map_iter(|(_, s)| {
                let origin = (s.point + s.normal * shadow_start as f64).as_vec3().to_array();
                let caster = &caster;
                let shares = caster.shares_at(s.point.as_vec3().to_array());
                directions.iter().map(move |d| {
                    if s.normal.dot(*d) <= 0.0 {
                        return 0.0;
                    }
                    let ray = ShadowRay { origin, direction: d.as_vec3().to_array(), t0: shadow_start, t1: f32::INFINITY };
                    caster.transmittance_from(&shares, &ray, true)
                })
            })
            .collect();
        let rows = TABLE_COLUMNS / 2;
        let table = (0..rows * TABLE_COLUMNS)
            .into_par_iter()
            .map(|k| {
                let d = uv_to_direction(((k % TABLE_COLUMNS) as f64 + 0.5) / TABLE_COLUMNS as f64, ((k / TABLE_COLUMNS) as f64 + 0.5) / rows as f64);
                nearest(&directions, d) as u32
            })
            .collect();
        let cell_diagonal = std::f64::consts::SQRT_2 * 2.0 * PI / TABLE_COLUMNS as f64;
        let reach = (NEIGHBOUR_SPACINGS * (4.0 * PI / directions.len() as f64).sqrt() + cell_diagonal).min(PI).cos();
        let neighbours = directions
            .par_iter()
            .enumerate()
            .map(|(i, a)| directions.iter().enumerate().filter(|&(j, b)| j != i && a.dot(*b) > reach).map(|(j, _)| j as u32).collect())
            .collect();
        Self {
            width,
            height,
            neighbours,
            directions,
            pixels: covered.iter().map(|(p, _)| *p).collect(),
            reflectance: covered.iter().map(|(_, s)| s.reflectance).collect(),
            coverage: covered.iter().map(|(_, s)| s.coverage as f32).collect(),
            normals: covered.iter().map(|(_, s)| s.normal).collect(),
            points: covered.iter().map(|(_, s)| s.point).collect(),
            visibility,
            table,
        }
    }

    /// Covered pixels.
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    /// The view (linear RGB) under `light`: `reflectance x (ambient + E max(0, n.l) V)` for a
    /// sun or point light (V blended from the nearest directions; a light grazing the horizon
    /// blends in directions below it, whose V is 0, where its cosine is near 0 anyway),
    /// `reflectance x (1/pi) sum_k
    /// L_k Omega_k max(0, n.w_k) V_k` for a sky (`L_k Omega_k` the light of direction k's cell).
    pub fn relight(&self, light: &Light) -> RgbImage {
        let mut image = RgbImage::new(self.width, self.height);
        let k = self.directions.len();
        let values: Vec<DVec3> = match light {
            Light::Directional { direction, irradiance, ambient } => {
                let l = direction.normalize();
                let blend = self.blend(l);
                (0..self.len())
                    .into_par_iter()
                    .map(|p| {
                        let v: f64 = blend.iter().map(|&(j, w)| w * self.visibility[p * k + j] as f64).sum();
                        self.reflectance[p] * (*ambient + *irradiance * (self.normals[p].dot(l).max(0.0) * v))
                    })
                    .collect()
            }
            Light::Point { position, intensity, ambient } => (0..self.len())
                .into_par_iter()
                .map(|p| {
                    let to_light = *position - self.points[p];
                    let distance = to_light.length().max(1e-3);
                    let l = to_light / distance;
                    let v: f64 = self.blend(l).iter().map(|&(j, w)| w * self.visibility[p * k + j] as f64).sum();
                    self.reflectance[p] * (*ambient + *intensity / (distance * distance) * (self.normals[p].dot(l).max(0.0) * v))
                })
                .collect(),
            Light::Uniform { .. } | Light::Environment { .. } => self.sky(&self.sky_light(light).unwrap_or_default()),
            // Nothing to relight by but its ambient (commands refuse unknown lights first).
            Light::Unknown { ambient, .. } => self.reflectance.iter().map(|r| *r * *ambient).collect(),
        };
        for ((p, v), &coverage) in self.pixels.iter().zip(values).zip(&self.coverage) {
            image.pixels[*p] = crate::imageio::composite_centre_sample(v.as_vec3().to_array(), coverage);
        }
        image
    }

    /// Each direction's cell's light (radiance x solid angle) from a sky: a uniform light's
    /// radiance over 4 pi / K each, an environment's texels binned (`sky_cells`); `None` for a
    /// sun or a point light.
    pub fn sky_light(&self, light: &Light) -> Option<Vec<DVec3>> {
        let k = self.directions.len();
        match light {
            Light::Uniform { radiance } => Some(vec![*radiance * (4.0 * PI / k as f64); k]),
            Light::Environment { map, scale, .. } => Some(self.sky_cells(map, *scale)),
            Light::Directional { .. } | Light::Point { .. } | Light::Unknown { .. } => None,
        }
    }

    /// Each direction's cell's light from an environment map (radiance x solid angle, summed
    /// over the texels nearest the direction): a map with fewer texels than
    /// `SUBSAMPLES_PER_CELL` per cell has each texel split into s x s parts first, so every
    /// cell gets light from its own directions.
    pub fn sky_cells(&self, map: &EnvironmentMap, scale: f64) -> Vec<DVec3> {
        let k = self.directions.len();
        let mut cells = vec![DVec3::ZERO; k];
        let (w, h) = (map.image.width, map.image.height);
        let s = ((SUBSAMPLES_PER_CELL * k as f64 / (w * h).max(1) as f64).sqrt().ceil() as usize).clamp(1, 8);
        for y in 0..h {
            let solid_angle = map.texel_solid_angle(y) * scale / (s * s) as f64;
            for x in 0..w {
                let [r, g, b] = map.image.pixels[y * w + x];
                let light = DVec3::new(r as f64, g as f64, b as f64) * solid_angle;
                for (i, j) in (0..s * s).map(|q| (q % s, q / s)) {
                    let (u, v) = ((x as f64 + (i as f64 + 0.5) / s as f64) / w as f64, (y as f64 + (j as f64 + 0.5) / s as f64) / h as f64);
                    cells[self.cell_of_uv(u, v)] += light;
                }
            }
        }
        cells
    }

    /// The basis's arrays, for a viewer that relights it elsewhere (`report`): covered pixel
    /// indices, reflectance, unit normals, the visibility rows (pixel after pixel) and the
    /// coverage each pixel's value is composited with.
    pub fn parts(&self) -> BasisParts<'_> {
        (&self.pixels, &self.reflectance, &self.normals, &self.visibility, &self.coverage)
    }

    /// `reflectance x (1/pi) sum_k light_k max(0, n.w_k) V_k`, `light_k` each direction's
    /// cell's light (radiance x solid angle).
    fn sky(&self, light: &[DVec3]) -> Vec<DVec3> {
        let k = self.directions.len();
        (0..self.len())
            .into_par_iter()
            .map(|p| {
                let n = self.normals[p];
                let row = &self.visibility[p * k..(p + 1) * k];
                let mut sum = DVec3::ZERO;
                for ((d, l), &v) in self.directions.iter().zip(light).zip(row) {
                    if v > 0.0 {
                        sum += *l * (n.dot(*d).max(0.0) * v as f64);
                    }
                }
                self.reflectance[p] * sum / PI
            })
            .collect()
    }

    /// The cell (nearest direction) of the equirectangular position `(u, v)`.
    fn cell_of_uv(&self, u: f64, v: f64) -> usize {
        let rows = TABLE_COLUMNS / 2;
        let column = ((u * TABLE_COLUMNS as f64) as usize).min(TABLE_COLUMNS - 1);
        let row = ((v * rows as f64) as usize).min(rows - 1);
        self.table[row * TABLE_COLUMNS + column] as usize
    }

    /// The directions near `l` and their weights (summing to 1): a tent over the angle, out to
    /// one lattice spacing, so the blend changes continuously as `l` moves.
    /// Only the table's nearest direction to `l` and its neighbours are tried (a point light
    /// blends per pixel).
    fn blend(&self, l: DVec3) -> Vec<(usize, f64)> {
        let spacing = (4.0 * PI / self.directions.len() as f64).sqrt();
        let (u, v) = crate::light::direction_to_uv(l);
        let near = self.cell_of_uv(u, v);
        let weights: Vec<(usize, f64)> = std::iter::once(near)
            .chain(self.neighbours[near].iter().map(|&j| j as usize))
            .filter(|&j| self.directions[j].dot(l) > spacing.cos())
            .map(|j| (j, 1.0 - self.directions[j].dot(l).clamp(-1.0, 1.0).acos() / spacing))
            .collect();
        let total: f64 = weights.iter().map(|w| w.1).sum();
        if total <= 0.0 {
            return vec![(nearest(&self.directions, l), 1.0)];
        }
        weights.into_iter().map(|(j, w)| (j, w / total)).collect()
    }
}

/// The index of the direction nearest `d`.
fn nearest(directions: &[DVec3], d: DVec3) -> usize {
    directions.iter().enumerate().max_by(|a, b| a.1.dot(d).total_cmp(&b.1.dot(d))).map_or(0, |(j, _)| j)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shading::SHADOW_START;
    use glam::DMat3;

    fn surfel(normal: DVec3) -> Option<Surfel> {
        Some(Surfel { point: DVec3::ZERO, normal: normal.normalize(), reflectance: DVec3::new(0.9, 0.5, 0.2), coverage: 1.0 })
    }

    fn normals() -> Vec<DVec3> {
        vec![DVec3::Y, DVec3::new(0.5, 0.55, -0.67).normalize(), DVec3::new(-0.7, 0.2, 0.3).normalize(), DVec3::new(0.1, -0.9, 0.2).normalize()]
    }

    /// The body the test points lie on: a 5 cm Gaussian just under the origin, whose share of
    /// the density there is all but 1, so it shadows none of them (`shadow::own_shares`).
    fn surface() -> PosedGaussian {
        PosedGaussian { mean: DVec3::new(0.0, -0.05, 0.0), axes: DMat3::IDENTITY, scales: DVec3::splat(0.05), amplitude: 20.0 }
    }

    fn blob() -> PosedGaussian {
        PosedGaussian { mean: DVec3::new(0.1, 0.6, -0.2), axes: DMat3::IDENTITY, scales: DVec3::new(0.3, 0.1, 0.3), amplitude: 20.0 }
    }

    fn pixel(image: &RgbImage, p: usize) -> DVec3 {
        let [r, g, b] = image.pixels[p];
        DVec3::new(r as f64, g as f64, b as f64)
    }

    fn close(a: DVec3, b: DVec3, tolerance: f64) {
        assert!((a - b).abs().max_element() <= tolerance * b.abs().max_element().max(1e-3), "{a} vs {b}");
    }

    /// `(1/pi) sum L max(0, n.d) T dOmega` over every texel, T by the f64 closed form (from the
    /// point at the origin, less its own Gaussians' shares).
    fn quadrature(map: &EnvironmentMap, n: DVec3, casters: &[PosedGaussian]) -> DVec3 {
        let (w, h) = (map.image.width, map.image.height);
        let mut sum = DVec3::ZERO;
        for y in 0..h {
            for x in 0..w {
                let d = map.texel_direction(x, y);
                if n.dot(d) <= 0.0 {
                    continue;
                }
                let ray = ShadowRay {
                    origin: (n * SHADOW_START as f64).as_vec3().to_array(),
                    direction: d.as_vec3().to_array(),
                    t0: SHADOW_START,
                    t1: f32::INFINITY,
                };
                let [r, g, b] = map.image.get(x, y);
                sum += DVec3::new(r as f64, g as f64, b as f64)
                    * n.dot(d)
                    * crate::shadow::transmittance_f64_from(casters, DVec3::ZERO, &ray)
                    * map.texel_solid_angle(y);
            }
        }
        sum / PI
    }

    #[test]
    fn a_white_furnace_gives_the_reflectance_back_and_background_stays_black() {
        let mut surfels: Vec<Option<Surfel>> = normals().into_iter().map(surfel).collect();
        surfels.push(None);
        surfels.push(None);
        let basis = TransferBasis::new(&surfels, 3, 2, &[], SHADOW_START, DIRECTIONS);
        assert_eq!(basis.len(), 4);
        let mut white = RgbImage::new(32, 16);
        white.pixels.iter_mut().for_each(|p| *p = [1.0; 3]);
        let white = Light::Environment { path: "white.exr".into(), scale: 1.0, map: EnvironmentMap { image: white } };
        for light in [Light::Uniform { radiance: DVec3::ONE }, white] {
            let image = basis.relight(&light);
            for p in 0..4 {
                close(pixel(&image, p), DVec3::new(0.9, 0.5, 0.2), 0.01);
            }
            assert_eq!(pixel(&image, 4), DVec3::ZERO);
            assert_eq!(pixel(&image, 5), DVec3::ZERO);
        }
    }

    #[test]
    fn an_environment_through_the_basis_matches_dense_quadrature_with_and_without_an_occluder() {
        let map = crate::synth::synthetic_sky(64, 32);
        let light = Light::Environment { path: "sky.exr".into(), scale: 1.0, map: map.clone() };
        let surfels: Vec<Option<Surfel>> = normals().into_iter().map(surfel).collect();
        for casters in [vec![surface()], vec![surface(), blob()]] {
            let image = TransferBasis::new(&surfels, 4, 1, &casters, SHADOW_START, DIRECTIONS).relight(&light);
            for (p, n) in normals().into_iter().enumerate() {
                let expected = quadrature(&map, n, &casters) * DVec3::new(0.9, 0.5, 0.2);
                close(pixel(&image, p), expected, 0.05);
            }
        }
        // The occluder must matter, or the second pass tested nothing.
        let open = TransferBasis::new(&surfels[..1], 1, 1, &[], SHADOW_START, DIRECTIONS).relight(&light);
        let shaded = TransferBasis::new(&surfels[..1], 1, 1, &[surface(), blob()], SHADOW_START, DIRECTIONS).relight(&light);
        assert!(pixel(&shaded, 0).x < 0.7 * pixel(&open, 0).x);
    }

    #[test]
    fn a_sun_or_lamp_through_the_basis_matches_its_own_shadow_ray_away_from_the_shadows_edge() {
        let surfels: Vec<Option<Surfel>> = normals().into_iter().map(surfel).collect();
        let basis = TransferBasis::new(&surfels, 4, 1, &[surface(), blob()], SHADOW_START, DIRECTIONS);
        let reflectance = DVec3::new(0.9, 0.5, 0.2);
        let ambient = DVec3::splat(0.1);
        // Straight through the blob's middle (dark), and well clear of it (lit).
        for direction in [DVec3::new(0.1, 0.6, -0.2).normalize(), DVec3::new(0.8, 0.3, 0.5).normalize()] {
            let sun = Light::Directional { direction, irradiance: DVec3::splat(2.0), ambient };
            let lamp = Light::Point { position: direction * 50.0, intensity: DVec3::splat(2.0 * 2500.0), ambient };
            for light in [sun, lamp] {
                let image = basis.relight(&light);
                for (p, n) in normals().into_iter().enumerate() {
                    let ray = ShadowRay {
                        origin: (n * SHADOW_START as f64).as_vec3().to_array(),
                        direction: direction.as_vec3().to_array(),
                        t0: SHADOW_START,
                        t1: f32::INFINITY,
                    };
                    let t = crate::shadow::transmittance_f64_from(&[surface(), blob()], DVec3::ZERO, &ray);
                    let expected = reflectance * (ambient + DVec3::splat(2.0) * n.dot(direction).max(0.0) * t);
                    close(pixel(&image, p), expected, 0.03);
                }
            }
        }
    }

    #[test]
    fn the_blend_found_through_the_table_is_the_blend_over_every_direction() {
        for count in [64, 1024] {
            let basis = TransferBasis::new(&[surfel(DVec3::Y)], 1, 1, &[], SHADOW_START, count);
            let spacing = (4.0 * PI / count as f64).sqrt();
            let mut stream = crate::random::Stream::new(5, count as u64, 0);
            for _ in 0..500 {
                let l = DVec3::new(stream.uniform() - 0.5, stream.uniform() - 0.5, stream.uniform() - 0.5).normalize();
                let mut every: Vec<usize> = (0..count).filter(|&j| basis.directions[j].dot(l) > spacing.cos()).collect();
                let mut found: Vec<usize> = basis.blend(l).into_iter().map(|(j, _)| j).collect();
                every.sort();
                found.sort();
                assert_eq!(found, every, "{count} directions, light {l}");
            }
        }
    }

    #[test]
    fn a_sun_blends_the_nearest_directions_continuously() {
        let basis = TransferBasis::new(&[surfel(DVec3::Y)], 1, 1, &[surface(), blob()], SHADOW_START, 256);
        let mut last: Option<f64> = None;
        // Sweep the sun across the blob's shadow in steps much finer than the lattice.
        for step in 0..200 {
            let angle = -0.6 + 1.2 * step as f64 / 199.0;
            let direction = DVec3::new(angle.sin(), angle.cos(), 0.0);
            let value = pixel(&basis.relight(&Light::Directional { direction, irradiance: DVec3::ONE, ambient: DVec3::ZERO }), 0).x / direction.y;
            if let Some(last) = last {
                assert!((value - last).abs() < 0.05, "a jump at {angle}: {last} -> {value}");
            }
            last = Some(value);
        }
    }
}
