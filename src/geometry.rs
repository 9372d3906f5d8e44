//! Geometry error of a fitted surface against a ground-truth mesh: both surfaces sampled by
//! area (seeded), every sample's exact distance to the other surface's nearest triangle (found
//! through a uniform grid of that surface's triangles, searched ring by ring), the
//! two means (accuracy: fitted to truth; completeness: truth to fitted), their average (the
//! Chamfer distance) and the mean angle between a fitted sample's normal and the normal of the
//! truth's nearest triangle.

use crate::isosurface::Mesh;
use crate::random::Stream;
use glam::DVec3;
use std::collections::HashMap;
use std::path::Path;

/// The geometry scores of one pose (metres and degrees).
#[derive(Clone, Copy, Debug, serde::Serialize, PartialEq)]
pub struct GeometryScores {
    /// Mean distance from the fitted surface to the truth.
    pub accuracy: f64,
    /// Mean distance from the truth to the fitted surface.
    pub completeness: f64,
    /// Their average.
    pub chamfer: f64,
    /// Mean angle (degrees) between fitted normals and the truth's nearest triangle's normal.
    pub normal_angle: f64,
    /// The share of the fitted surface (by area) within `CLOSE` of the truth.
    pub within_2cm: f64,
    /// Given which points the training images saw: the share of the fitted surface they saw,
    /// and the share of that within `CLOSE` of the truth. What no image shows (under a skirt,
    /// between arm and body) the images cannot place.
    pub seen: Option<f64>,
    pub seen_within_2cm: Option<f64>,
}

/// Whether a surface point (with its outward normal) is seen (`seen::SeenInFrames::sees`).
pub type SeenTest<'a> = &'a dyn Fn(DVec3, DVec3) -> bool;

/// The distance (m) within which the fitted surface counts as on the truth (`within_2cm`).
pub const CLOSE: f64 = 0.02;

/// The largest OBJ read (a ground-truth body of a million triangles is about 60 MB).
pub const OBJ_BYTES: u64 = 256 << 20;

/// The largest coordinate (m) a ground-truth mesh may hold: a body is metres across, and its
/// squared distances must stay finite in the geometry scores.
pub const OBJ_MAX_COORDINATE: f64 = 1e6;

/// Reads an OBJ's triangles (polygons are triangulated; every object of the file), refusing
/// one with no triangle, a vertex that is not finite or beyond `OBJ_MAX_COORDINATE`, or a face
/// that names a missing vertex. The error says what is wrong (callers name the file).
pub fn load_obj(path: &Path) -> Result<Mesh, String> {
    let text = crate::files::read_text(path, OBJ_BYTES).map_err(|e| e.to_string())?;
    let options = tobj::LoadOptions { triangulate: true, single_index: true, ..Default::default() };
    let (models, _) =
        tobj::load_obj_buf(&mut std::io::Cursor::new(text.as_bytes()), &options, |_| Ok(Default::default())).map_err(|e| format!("not a readable OBJ: {e}"))?;
    let mut mesh = Mesh::default();
    for model in models {
        let base = mesh.vertices.len();
        if model.mesh.positions.len() % 3 != 0 {
            return Err("a vertex has fewer than three coordinates".into());
        }
        for p in model.mesh.positions.chunks(3) {
            let v = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            if !v.is_finite() || v.abs().max_element() > OBJ_MAX_COORDINATE {
                return Err(format!("vertex {} is {v} (not finite, or beyond {OBJ_MAX_COORDINATE:e} m)", mesh.vertices.len() + 1));
            }
            mesh.vertices.push(v);
        }
        for t in model.mesh.indices.chunks(3) {
            let tri = [base + t[0] as usize, base + t[1] as usize, base + t[2] as usize];
            if t.len() < 3 || tri.iter().any(|&i| i >= mesh.vertices.len()) {
                return Err("a face refers to a missing vertex".into());
            }
            mesh.triangles.push(tri);
        }
    }
    if mesh.triangles.is_empty() {
        return Err("holds no triangles".into());
    }
    Ok(mesh)
}

/// A point on a mesh and the triangle it lies on.
#[derive(Clone, Copy, Debug)]
struct Sample {
    point: DVec3,
    triangle: usize,
}

fn triangle_area(mesh: &Mesh, t: &[usize; 3]) -> f64 {
    let [a, b, c] = t.map(|i| mesh.vertices[i]);
    0.5 * (b - a).cross(c - a).length()
}

fn triangle_normal(mesh: &Mesh, t: usize) -> DVec3 {
    let [a, b, c] = mesh.triangles[t].map(|i| mesh.vertices[i]);
    (b - a).cross(c - a).normalize_or_zero()
}

/// `n` points spread over the mesh by area (each triangle's share drawn by its area).
fn sample(mesh: &Mesh, n: usize, seed: u64) -> Vec<Sample> {
    let areas: Vec<f64> = mesh.triangles.iter().map(|t| triangle_area(mesh, t)).collect();
    let mut cumulative = Vec::with_capacity(areas.len());
    let mut total = 0.0;
    for a in &areas {
        total += a;
        cumulative.push(total);
    }
    let mut stream = Stream::new(seed, 0x6E0, 1);
    (0..n)
        .map(|_| {
            let target = stream.uniform() * total;
            let triangle = cumulative.partition_point(|&c| c < target).min(areas.len() - 1);
            let (mut u, mut v) = (stream.uniform(), stream.uniform());
            if u + v > 1.0 {
                (u, v) = (1.0 - u, 1.0 - v);
            }
            let [a, b, c] = mesh.triangles[triangle].map(|i| mesh.vertices[i]);
            Sample { point: a + (b - a) * u + (c - a) * v, triangle }
        })
        .collect()
}

/// The closest point to `p` on triangle `abc` (Ericson, Real-Time Collision Detection 5.1.5).
fn closest_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denominator = 1.0 / (va + vb + vc);
    a + ab * (vb * denominator) + ac * (vc * denominator)
}

/// A mesh's triangles bucketed in a uniform grid (each in every cell its bounding box meets),
/// to find the triangles near a point.
struct Index<'a> {
    mesh: &'a Mesh,
    cell: f64,
    buckets: HashMap<[i64; 3], Vec<usize>>,
}

impl<'a> Index<'a> {
    fn new(mesh: &'a Mesh, cell: f64) -> Self {
        let mut buckets: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
        for (t, tri) in mesh.triangles.iter().enumerate() {
            let [a, b, c] = tri.map(|i| mesh.vertices[i]);
            let (lo, hi) = (Self::key(a.min(b).min(c), cell), Self::key(a.max(b).max(c), cell));
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        buckets.entry([x, y, z]).or_default().push(t);
                    }
                }
            }
        }
        Self { mesh, cell, buckets }
    }

    fn key(p: DVec3, cell: f64) -> [i64; 3] {
        (p / cell).floor().as_i64vec3().to_array()
    }

    /// The distance from `p` to the mesh and the nearest triangle, searching cells ring by
    /// ring around `p`'s: a triangle not met by ring r lies in ring r + 1 or beyond, at least
    /// `r * cell` away, so the search ends once the best distance is within that.
    fn nearest(&self, p: DVec3) -> (f64, usize) {
        let centre = Self::key(p, self.cell);
        let mut best = (f64::INFINITY, 0usize);
        for ring in 0i64..=1 << 16 {
            for dz in -ring..=ring {
                for dy in -ring..=ring {
                    for dx in -ring..=ring {
                        if dx.abs().max(dy.abs()).max(dz.abs()) != ring {
                            continue;
                        }
                        for &t in self.buckets.get(&[centre[0] + dx, centre[1] + dy, centre[2] + dz]).into_iter().flatten() {
                            let [a, b, c] = self.mesh.triangles[t].map(|i| self.mesh.vertices[i]);
                            let d = (closest_on_triangle(p, a, b, c) - p).length();
                            if d < best.0 {
                                best = (d, t);
                            }
                        }
                    }
                }
            }
            if best.0 <= ring as f64 * self.cell {
                break;
            }
        }
        best
    }
}

/// Scores `fitted` against `truth` with `n` samples on each (and, given `seen`, the part of the
/// fitted surface it says is seen); `None` when either has no area.
pub fn compare(fitted: &Mesh, truth: &Mesh, n: usize, seed: u64, seen: Option<SeenTest>) -> Option<GeometryScores> {
    let area = |m: &Mesh| -> f64 { m.triangles.iter().map(|t| triangle_area(m, t)).sum() };
    if n == 0 || !(area(fitted) > 0.0) || !(area(truth) > 0.0) {
        return None;
    }
    let (on_fitted, on_truth) = (sample(fitted, n, seed), sample(truth, n, seed + 1));
    // Cells of about four mean triangle edges (from the mean triangle area).
    let cell = |m: &Mesh| 4.0 * (2.0 * area(m) / m.triangles.len() as f64).sqrt();
    let (truth_index, fitted_index) = (Index::new(truth, cell(truth)), Index::new(fitted, cell(fitted)));
    let mut accuracy = 0.0;
    let mut angle = 0.0;
    let mut close = 0usize;
    let (mut seen_count, mut seen_close) = (0usize, 0usize);
    for s in &on_fitted {
        let (d, t) = truth_index.nearest(s.point);
        accuracy += d;
        close += usize::from(d <= CLOSE);
        let normal = triangle_normal(fitted, s.triangle);
        angle += normal.dot(triangle_normal(truth, t)).clamp(-1.0, 1.0).acos().to_degrees();
        if seen.is_some_and(|sees| sees(s.point, normal)) {
            seen_count += 1;
            seen_close += usize::from(d <= CLOSE);
        }
    }
    let completeness: f64 = on_truth.iter().map(|s| fitted_index.nearest(s.point).0).sum();
    let (accuracy, completeness) = (accuracy / n as f64, completeness / n as f64);
    let within_2cm = close as f64 / n as f64;
    let (seen, seen_within_2cm) = match seen {
        Some(_) => (Some(seen_count as f64 / n as f64), (seen_count > 0).then(|| seen_close as f64 / seen_count as f64)),
        None => (None, None),
    };
    Some(GeometryScores { accuracy, completeness, chamfer: 0.5 * (accuracy + completeness), normal_angle: angle / n as f64, within_2cm, seen, seen_within_2cm })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::isosurface::{bisect, extract, Grid};

    fn sphere(radius: f64, centre: DVec3, cell: f64) -> Mesh {
        let grid = Grid::covering(centre - DVec3::splat(radius + 0.1), centre + DVec3::splat(radius + 0.1), cell);
        let f = |p: DVec3| (p - centre).length() - radius;
        let values: Vec<f64> = grid.points().into_iter().map(f).collect();
        extract(&grid, &values, |c| bisect(c, 30, |points| points.iter().map(|&p| f(p) < 0.0).collect()))
    }

    #[test]
    fn concentric_spheres_are_their_radii_apart_with_aligned_normals() {
        let (inner, outer) = (sphere(0.30, DVec3::ZERO, 0.02), sphere(0.32, DVec3::ZERO, 0.03));
        let s = compare(&inner, &outer, 4000, 1, None).unwrap();
        // Faceting: chords of a 2-3 cm grid sit inside the true sphere by well under 1 mm.
        assert!((s.accuracy - 0.02).abs() < 1.5e-3 && (s.completeness - 0.02).abs() < 1.5e-3, "{s:?}");
        assert!(s.normal_angle < 6.0, "{s:?}");
        let same = compare(&inner, &inner, 4000, 2, None).unwrap();
        assert!(compare(&inner, &Mesh::default(), 4000, 2, None).is_none());
        assert!(same.chamfer < 2e-4 && same.normal_angle < 1e-6, "{same:?}");
    }

    #[test]
    fn a_missing_part_costs_completeness_not_accuracy() {
        // The truth has a second sphere the fit lacks.
        let fitted = sphere(0.2, DVec3::ZERO, 0.02);
        let mut truth = fitted.clone();
        let far = sphere(0.1, DVec3::new(0.8, 0.0, 0.0), 0.02);
        let base = truth.vertices.len();
        truth.vertices.extend(far.vertices);
        truth.triangles.extend(far.triangles.iter().map(|t| t.map(|i| i + base)));
        let s = compare(&fitted, &truth, 4000, 3, None).unwrap();
        assert!(s.accuracy < 2e-4, "{s:?}");
        assert!(s.completeness > 0.05, "{s:?}");
        assert_eq!((s.seen, s.seen_within_2cm), (None, None));
    }

    /// Seen scores count only the samples the test passes: half a sphere seen (the side facing
    /// +z), and of it what lies near a truth that holds only that side's cap.
    #[test]
    fn the_seen_part_is_scored_on_its_own() {
        let fitted = sphere(0.2, DVec3::ZERO, 0.01);
        let facing = |_: DVec3, n: DVec3| n.z > 0.0;
        let s = compare(&fitted, &fitted, 8000, 4, Some(&facing)).unwrap();
        assert!((s.seen.unwrap() - 0.5).abs() < 0.02 && s.seen_within_2cm == Some(1.0), "{s:?}");
        // The truth's cap above z = 0.1 is half the seen half's area (2 pi r h); within 2 cm of
        // it, a rim about 1.7 cm high more (0.59 of the seen half).
        let cap = Mesh {
            vertices: fitted.vertices.clone(),
            triangles: fitted.triangles.iter().copied().filter(|t| t.iter().all(|&v| fitted.vertices[v].z > 0.1)).collect(),
        };
        let s = compare(&fitted, &cap, 8000, 5, Some(&facing)).unwrap();
        let (seen_close, all_close) = (s.seen_within_2cm.unwrap(), s.within_2cm);
        // Every close sample is seen (the cap is on the seen side), so the seen share is the
        // whole's over a half.
        assert!((seen_close - all_close / s.seen.unwrap()).abs() < 1e-12, "{s:?}");
        assert!(seen_close > 0.5 && seen_close < 0.7, "{s:?}");
    }

    #[test]
    fn closest_point_on_a_triangle_matches_brute_force() {
        let (a, b, c) = (DVec3::new(0.0, 0.0, 0.0), DVec3::new(1.0, 0.1, 0.0), DVec3::new(0.2, 0.9, 0.3));
        let mut stream = Stream::new(9, 9, 9);
        for _ in 0..500 {
            let p = DVec3::new(stream.uniform() * 3.0 - 1.0, stream.uniform() * 3.0 - 1.0, stream.uniform() * 2.0 - 1.0);
            let got = (closest_on_triangle(p, a, b, c) - p).length();
            let mut brute = f64::INFINITY;
            for i in 0..=200 {
                for j in 0..=(200 - i) {
                    let (u, v) = (i as f64 / 200.0, j as f64 / 200.0);
                    brute = brute.min((a + (b - a) * u + (c - a) * v - p).length());
                }
            }
            assert!(got <= brute + 1e-12 && got > brute - 1e-2, "{got} vs {brute}");
        }
    }
}
