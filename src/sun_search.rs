//! A global search for the light, run once when it starts to be fitted: a sun's direction or
//! a point light's position.
//!
//! Gradient descent on the direction alone finds the nearest minimum of the photometric loss,
//! and with one camera that is often a wrong one: the sun slides behind the character along the
//! viewing direction, every visible normal faces away from it, and the albedo absorbs the
//! shading. This module scores every direction of a sphere-covering set (then a finer set
//! around the best) on surface samples of several frames: points, normals and albedo from the
//! field, the training colour, and the Gaussians' closed-form transmittance toward the
//! candidate (so cast shadows count). Each candidate's score is the residual of the image
//! formation `albedo (a + k max(0, n.l) T)` with the ambient `a` and sun strength `k` solved by
//! least squares per channel (both non-negative): a direction is good when its shading pattern
//! and cast shadows explain the images, whatever the light's strength. The winner seeds the
//! gradient descent, which refines it.
//!
//! A point light is searched the same way over positions: the sphere's directions from the
//! body's centre times a geometric ladder of distances in units of the body's extent, its
//! shading `max(0, n.l) T / r^2` with the shadow ray ending at the light. The near lamps that
//! 1 / r^2 makes hard to find by descent (the falloff across the body is what places them) are
//! on the ladder's lower rungs.

use crate::shadow::{ShadowCaster, ShadowRay};
use glam::DVec3;
use rayon::prelude::*;

/// One visible surface point of a training image.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceSample {
    /// Which caster set (frame) shadows it.
    pub frame: usize,
    pub point: [f32; 3],
    pub normal: [f32; 3],
    pub albedo: [f32; 3],
    /// The training image's colour there.
    pub colour: [f32; 3],
}

/// A scored candidate: a direction toward a sun, or a point light's position (its direction
/// then the one from the body's centre).
#[derive(Clone, Copy, Debug, serde::Serialize, serde::Deserialize)]
pub struct Candidate {
    pub direction: [f64; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position: Option<[f64; 3]>,
    /// Mean squared residual per sample and channel.
    pub residual: f64,
    /// The light's strength the least squares gave (mean over channels): a sun's irradiance or
    /// a point light's intensity, relative to the albedo as it stands.
    #[serde(default)]
    pub strength: f64,
}

/// Where a candidate light is, as the shading of a sample needs it.
#[derive(Clone, Copy, Debug)]
pub enum Toward {
    Sun(DVec3),
    Point(DVec3),
}

/// The search's outcome: the best direction and how many were scored.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SearchReport {
    pub best: Candidate,
    /// The best candidate of the coarse set (before refinement).
    pub coarse_best: Candidate,
    pub candidates: usize,
    pub samples: usize,
}

/// `n` directions spread evenly over the sphere (a Fibonacci lattice).
pub fn sphere(n: usize) -> Vec<DVec3> {
    crate::light::fibonacci_sphere(n, 0.0)
}

/// `n` directions evenly over the cap of half-angle `angle` (radians) around `centre`.
pub fn cap(centre: DVec3, angle: f64, n: usize) -> Vec<DVec3> {
    let c = centre.normalize();
    let (u, v) = c.any_orthonormal_pair();
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let lowest = angle.cos();
    (0..n)
        .map(|k| {
            let z = 1.0 - (1.0 - lowest) * (k as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = golden * k as f64;
            (c * z + u * (r * phi.cos()) + v * (r * phi.sin())).normalize()
        })
        .collect()
}

/// Least squares of `y = a x + k x s` with `a, k >= 0` over `(x, s, y)` triples; returns the
/// squared residual and `k`.
fn residual(triples: impl Iterator<Item = (f64, f64, f64)>) -> (f64, f64) {
    let (mut xx, mut xxs, mut xsxs, mut xy, mut xsy, mut yy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for (x, s, y) in triples {
        let z = x * s;
        xx += x * x;
        xxs += x * z;
        xsxs += z * z;
        xy += x * y;
        xsy += z * y;
        yy += y * y;
    }
    // Squared residual of coefficients (a, k): yy - 2(a xy + k xsy) + a^2 xx + 2 a k xxs + k^2 xsxs.
    let sse = |a: f64, k: f64| (yy - 2.0 * (a * xy + k * xsy) + a * a * xx + 2.0 * a * k * xxs + k * k * xsxs).max(0.0);
    let det = xx * xsxs - xxs * xxs;
    if det > 1e-12 * xx.max(1e-30) * xsxs.max(1e-30) {
        let a = (xy * xsxs - xsy * xxs) / det;
        let k = (xsy * xx - xy * xxs) / det;
        if a >= 0.0 && k >= 0.0 {
            return (sse(a, k), k);
        }
    }
    // On the boundary: ambient only, or sun only.
    let a = if xx > 0.0 { (xy / xx).max(0.0) } else { 0.0 };
    let k = if xsxs > 0.0 { (xsy / xsxs).max(0.0) } else { 0.0 };
    if sse(a, 0.0) <= sse(0.0, k) {
        (sse(a, 0.0), 0.0)
    } else {
        (sse(0.0, k), k)
    }
}

/// Each sample's Gaussians and their shares of the density at it (`ShadowCaster::shares_at`
/// in its frame's caster): the same for every candidate light, so found once per search.
fn shares_of(samples: &[SurfaceSample], casters: &[ShadowCaster]) -> Vec<Vec<(usize, f32)>> {
    samples.par_iter().with_min_len(64).map(|s| casters.get(s.frame).map(|c| c.shares_at(s.point)).unwrap_or_default()).collect()
}

/// The residual of a candidate light on `samples`, shadowed by `casters[frame]` less each
/// sample's own Gaussians (`shares`, from `shares_of`), and the light's least-squares
/// strength; `start` is the shadow ray's offset off the surface (as in training).
fn score(samples: &[SurfaceSample], shares: &[Vec<(usize, f32)>], casters: &[ShadowCaster], light: Toward, start: f32) -> (f64, f64) {
    let shading: Vec<f64> = samples
        .par_iter()
        .zip(shares)
        .with_min_len(64)
        .map(|(s, shares)| {
            let point = DVec3::from_array(s.point.map(|c| c as f64));
            let (l, t1, falloff) = match light {
                Toward::Sun(d) => (d.normalize(), f32::INFINITY, 1.0),
                Toward::Point(p) => {
                    let r = (p - point).length().max(1e-6);
                    ((p - point) / r, r as f32, 1.0 / (r * r))
                }
            };
            let l = l.as_vec3().to_array();
            let cosine = s.normal[0] * l[0] + s.normal[1] * l[1] + s.normal[2] * l[2];
            if cosine <= 0.0 || t1 <= start {
                return 0.0;
            }
            let origin = [0, 1, 2].map(|a| s.point[a] + s.normal[a] * start);
            let ray = ShadowRay { origin, direction: l, t0: start, t1 };
            let visibility = casters.get(s.frame).map(|c| c.transmittance_from(shares, &ray, true)).unwrap_or(1.0);
            (cosine * visibility) as f64 * falloff
        })
        .collect();
    let (mut total, mut strength) = (0.0, 0.0);
    for c in 0..3 {
        let (sse, k) = residual(samples.iter().zip(&shading).map(|(s, &k)| (s.albedo[c] as f64, k, s.colour[c] as f64)));
        total += sse;
        strength += k / 3.0;
    }
    (total / (3 * samples.len().max(1)) as f64, strength)
}

/// Scores candidates; a non-finite score (a NaN sample) ranks last and stays representable
/// in JSON.
fn scored(
    samples: &[SurfaceSample],
    shares: &[Vec<(usize, f32)>],
    casters: &[ShadowCaster],
    start: f32,
    lights: Vec<(DVec3, Option<DVec3>)>,
) -> Vec<Candidate> {
    lights
        .into_iter()
        .map(|(direction, position)| {
            let toward = position.map_or(Toward::Sun(direction), Toward::Point);
            let (residual, strength) = score(samples, shares, casters, toward, start);
            let residual = Some(residual).filter(|r| r.is_finite()).unwrap_or(f64::MAX);
            Candidate { direction: direction.to_array(), position: position.map(|p| p.to_array()), residual, strength }
        })
        .collect()
}

fn best_of(candidates: &[Candidate]) -> Option<Candidate> {
    candidates.iter().copied().min_by(|a, b| a.residual.total_cmp(&b.residual))
}

/// Scores `coarse` directions over the sphere, then `fine` in a cap around the best (of the
/// coarse set's spacing), and returns the best of all.
pub fn search(samples: &[SurfaceSample], casters: &[ShadowCaster], coarse: usize, fine: usize, start: f32) -> SearchReport {
    let suns = |directions: Vec<DVec3>| directions.into_iter().map(|d| (d, None)).collect();
    let shares = shares_of(samples, casters);
    let first = scored(samples, &shares, casters, start, suns(sphere(coarse.max(1))));
    let fallback = Candidate { direction: [0.0, 1.0, 0.0], position: None, residual: f64::MAX, strength: 0.0 };
    let coarse_best = best_of(&first).unwrap_or(fallback);
    // The coarse set's spacing: each direction covers 4 pi / n steradians.
    let spacing = (4.0 / coarse.max(1) as f64).sqrt();
    let second = scored(samples, &shares, casters, start, suns(cap(DVec3::from_array(coarse_best.direction), spacing, fine)));
    let best = best_of(&second).filter(|b| b.residual < coarse_best.residual).unwrap_or(coarse_best);
    SearchReport { best, coarse_best, candidates: first.len() + second.len(), samples: samples.len() }
}

/// Rungs of the point light's distance ladder, and their ratio: from a third of the body's
/// extent from its centre (a lamp within arm's reach) to about 8 extents, where a point light
/// is nearly a sun.
const RUNGS: usize = 10;
const RUNG_RATIO: f64 = std::f64::consts::SQRT_2;
const NEAREST_RUNG: f64 = 0.35;

/// A point light's position: `directions` over the sphere from `centre` times the distance
/// ladder (in units of `extent`, the body's size), then a cap of `fine` directions around
/// the best times five finer rungs around its distance.
pub fn search_point(
    samples: &[SurfaceSample],
    casters: &[ShadowCaster],
    centre: DVec3,
    extent: f64,
    directions: usize,
    fine: usize,
    start: f32,
) -> SearchReport {
    let at = |dirs: Vec<DVec3>, distances: &[f64]| -> Vec<(DVec3, Option<DVec3>)> {
        dirs.iter().flat_map(|&d| distances.iter().map(move |&r| (d, Some(centre + d * r)))).collect()
    };
    let ladder: Vec<f64> = (0..RUNGS).map(|k| extent * NEAREST_RUNG * RUNG_RATIO.powi(k as i32)).collect();
    let shares = shares_of(samples, casters);
    let first = scored(samples, &shares, casters, start, at(sphere(directions.max(1)), &ladder));
    let fallback = Candidate { direction: [0.0, 1.0, 0.0], position: Some((centre + DVec3::Y * extent).to_array()), residual: f64::MAX, strength: 0.0 };
    let coarse_best = best_of(&first).unwrap_or(fallback);
    let distance = coarse_best.position.map_or(extent, |p| (DVec3::from_array(p) - centre).length());
    let finer: Vec<f64> = (-2..=2).map(|j| distance * RUNG_RATIO.powf(j as f64 / 4.0)).collect();
    let spacing = (4.0 / directions.max(1) as f64).sqrt();
    let second = scored(samples, &shares, casters, start, at(cap(DVec3::from_array(coarse_best.direction), spacing, fine), &finer));
    let best = best_of(&second).filter(|b| b.residual < coarse_best.residual).unwrap_or(coarse_best);
    SearchReport { best, coarse_best, candidates: first.len() + second.len(), samples: samples.len() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattices_cover_the_sphere_and_the_cap() {
        let s = sphere(200);
        assert!(s.iter().all(|d| (d.length() - 1.0).abs() < 1e-12));
        // Every direction of a fine probe set is within 12 degrees of some lattice direction.
        for probe in sphere(997) {
            let nearest = s.iter().map(|d| d.dot(probe)).fold(-1.0f64, f64::max);
            assert!(nearest > 12f64.to_radians().cos(), "{probe:?}");
        }
        let centre = DVec3::new(0.3, -0.2, 0.9).normalize();
        let c = cap(centre, 0.2, 50);
        assert!(c.iter().all(|d| d.dot(centre) >= 0.2f64.cos() - 1e-12));
        assert!(c.iter().any(|d| d.dot(centre) < 0.15f64.cos()), "the cap is spread to its edge");
    }

    #[test]
    fn least_squares_recovers_ambient_and_sun_and_respects_signs() {
        let xs: Vec<f64> = (0..50).map(|k| 0.3 + 0.01 * k as f64).collect();
        let ss: Vec<f64> = (0..50).map(|k| (k * 7 % 11) as f64 / 10.0).collect();
        let ys: Vec<f64> = xs.iter().zip(&ss).map(|(x, s)| x * (0.2 + 0.9 * s)).collect();
        let energy: f64 = ys.iter().map(|y| y * y).sum();
        let triples = |ys: &[f64]| xs.iter().zip(&ss).zip(ys).map(|((&x, &s), &y)| (x, s, y)).collect::<Vec<_>>();
        let (sse, k) = residual(triples(&ys).into_iter());
        assert!(sse < 1e-12 * energy && (k - 0.9).abs() < 1e-9, "{sse} {k}");
        // A sun that darkens (negative k) is not allowed: the residual is that of a >= 0, k = 0.
        let ys_neg: Vec<f64> = xs.iter().zip(&ss).map(|(x, s)| x * (0.9 - 0.5 * s)).collect();
        let best_ambient = xs.iter().zip(&ys_neg).map(|(x, y)| x * y).sum::<f64>() / xs.iter().map(|x| x * x).sum::<f64>();
        let expected: f64 = xs.iter().zip(&ys_neg).map(|(x, y)| (y - best_ambient * x).powi(2)).sum();
        assert!((residual(triples(&ys_neg).into_iter()).0 - expected).abs() < 1e-12);
    }

    /// Samples of the half of a unit sphere a camera on +z sees (the case that misleads
    /// gradient descent), two albedos, shaded by `shade(normal)`.
    fn visible_half(shade: impl Fn(DVec3) -> f64) -> Vec<SurfaceSample> {
        sphere(800)
            .into_iter()
            .filter(|n| n.z > 0.05)
            .enumerate()
            .map(|(k, n)| {
                let albedo = if k % 3 == 0 { [0.8, 0.3, 0.2] } else { [0.4, 0.6, 0.7] };
                let s = shade(n) as f32;
                SurfaceSample { frame: 0, point: n.as_vec3().to_array(), normal: n.as_vec3().to_array(), albedo, colour: albedo.map(|a| a * s) }
            })
            .collect()
    }

    /// A sphere of samples lit by a known sun, no casters, seen from one side: the search finds
    /// the sun within 5 degrees (the monocular target), even one behind the visible half.
    #[test]
    fn the_search_finds_the_sun_of_a_lit_sphere() {
        for sun in [DVec3::new(0.45, 0.8, 0.4), DVec3::new(-0.7, -0.2, 0.68), DVec3::new(0.0, 0.1, -1.0)] {
            let sun = sun.normalize();
            let samples = visible_half(|n| 0.25 + n.dot(sun).max(0.0));
            let report = search(&samples, &[], 256, 64, 0.01);
            let error = DVec3::from_array(report.best.direction).angle_between(sun).to_degrees();
            assert!(error < 5.0, "sun {sun:?}: found {:?}, {error:.1} degrees off", report.best.direction);
        }
    }

    /// The same for a point light 0.8-2 radii off the surface of a unit sphere: its position
    /// within a tenth of its distance from the centre.
    #[test]
    fn the_search_finds_a_near_point_light() {
        for lamp in [DVec3::new(0.8, 1.2, 0.9), DVec3::new(-1.5, 0.4, 0.5), DVec3::new(0.2, 2.5, -1.0)] {
            let samples = visible_half(|n| {
                let to = lamp - n;
                0.2 + 2.0 * n.dot(to.normalize()).max(0.0) / to.length_squared()
            });
            let report = search_point(&samples, &[], DVec3::ZERO, 2.0, 128, 32, 0.01);
            let found = DVec3::from_array(report.best.position.unwrap());
            let error = (found - lamp).length();
            assert!(error < 0.1 * lamp.length(), "lamp {lamp:?}: found {found:?}, {error:.3} off");
            assert!((report.best.strength - 2.0).abs() < 0.5, "strength {}", report.best.strength);
        }
    }
}
