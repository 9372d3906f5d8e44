//! The zero level set of a sampled signed distance as a triangle mesh: marching tetrahedra on a
//! regular grid (six tetrahedra per cube sharing its main diagonal, so neighbouring cubes agree
//! along faces and the mesh is closed and manifold wherever the surface stays inside the grid),
//! with every crossing placed by a caller-supplied refinement of all crossings at once (exact
//! bisection of an analytic SDF, or batched bisection of a fitted field), the grid's values
//! sampled whole only near the surface (`narrow_band_values`), and OBJ output.

use glam::DVec3;
use std::collections::HashMap;
use std::fmt::Write;

/// The six tetrahedra of a cube, as corner indices (corner bit 0 = +x, bit 1 = +y, bit 2 = +z).
const TETRAHEDRA: [[usize; 4]; 6] = [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]];

/// A regular grid of sample points.
#[derive(Clone, Debug)]
pub struct Grid {
    pub origin: DVec3,
    pub cell: f64,
    /// Points along x, y and z.
    pub counts: [usize; 3],
}

impl Grid {
    /// The grid of cell `cell` covering the box `[lo, hi]`.
    pub fn covering(lo: DVec3, hi: DVec3, cell: f64) -> Self {
        let cells = ((hi - lo) / cell).ceil();
        Self { origin: lo, cell, counts: [cells.x as usize + 1, cells.y as usize + 1, cells.z as usize + 1] }
    }

    pub fn len(&self) -> usize {
        self.counts[0] * self.counts[1] * self.counts[2]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn index(&self, i: usize, j: usize, k: usize) -> usize {
        (k * self.counts[1] + j) * self.counts[0] + i
    }

    fn at(&self, i: usize, j: usize, k: usize) -> DVec3 {
        self.origin + DVec3::new(i as f64, j as f64, k as f64) * self.cell
    }

    /// Every sample point, x fastest (the order `extract` reads its values in).
    pub fn points(&self) -> Vec<DVec3> {
        let mut out = Vec::with_capacity(self.len());
        for k in 0..self.counts[2] {
            for j in 0..self.counts[1] {
                for i in 0..self.counts[0] {
                    out.push(self.at(i, j, k));
                }
            }
        }
        out
    }
}

/// Points of a coarse block's side, in the grid's cells, of `narrow_band_values`.
pub const BAND_BLOCK: usize = 4;

/// How far, as a multiple of a block's diagonal, a block's nearest corner value must lie from
/// zero for `narrow_band_values` to leave the block's inside unsampled: a signed distance
/// changes no faster than distance (its gradient has length 1 where it is one), and half again
/// as much is left for a fitted field's that is steeper.
pub const BAND_LIPSCHITZ: f64 = 1.5;

/// The values of a signed distance `sdf` (a batch of points in, their values out) at every
/// point of `grid` (in `Grid::points` order) for `extract`, sampled only where the surface may
/// be: first at the corners of blocks of `BAND_BLOCK` cells a side, then at every point of the
/// blocks whose corners change sign or come within `BAND_LIPSCHITZ` block diagonals of zero.
/// The other blocks hold no surface, and their points get the value of one of their corners
/// (all of one sign), so `extract` finds the same crossings as from the grid sampled whole.
pub fn narrow_band_values<E>(grid: &Grid, mut sdf: impl FnMut(&[DVec3]) -> Result<Vec<f64>, E>) -> Result<Vec<f64>, E> {
    // The coarse sample indices along each axis: every BAND_BLOCK-th point and the last.
    let coarse = |n: usize| -> Vec<usize> {
        let mut at: Vec<usize> = (0..n).step_by(BAND_BLOCK).collect();
        if at.last() != Some(&(n.saturating_sub(1))) && n > 0 {
            at.push(n - 1);
        }
        at
    };
    let axes = [coarse(grid.counts[0]), coarse(grid.counts[1]), coarse(grid.counts[2])];
    let mut corners = Vec::with_capacity(axes.iter().map(Vec::len).product());
    for &k in &axes[2] {
        for &j in &axes[1] {
            corners.extend(axes[0].iter().map(|&i| grid.at(i, j, k)));
        }
    }
    let corner_values = sdf(&corners)?;
    // A value the field did not return counts as zero: its blocks are sampled whole.
    let corner_value = |a: usize, b: usize, c: usize| corner_values.get((c * axes[1].len() + b) * axes[0].len() + a).copied().unwrap_or(0.0);
    let mut values = vec![f64::NAN; grid.len()];
    let mut wanted = vec![false; grid.len()];
    for c in 0..axes[2].len().saturating_sub(1) {
        for b in 0..axes[1].len().saturating_sub(1) {
            for a in 0..axes[0].len().saturating_sub(1) {
                let (i0, i1, j0, j1, k0, k1) = (axes[0][a], axes[0][a + 1], axes[1][b], axes[1][b + 1], axes[2][c], axes[2][c + 1]);
                let v: Vec<f64> = (0..8).map(|q| corner_value(a + (q & 1), b + ((q >> 1) & 1), c + ((q >> 2) & 1))).collect();
                let diagonal = grid.cell * (((i1 - i0).pow(2) + (j1 - j0).pow(2) + (k1 - k0).pow(2)) as f64).sqrt();
                let one_sign = v.iter().all(|&x| x < 0.0) || v.iter().all(|&x| !(x < 0.0));
                let far = v.iter().all(|x| x.abs() > BAND_LIPSCHITZ * diagonal);
                for k in k0..=k1 {
                    for j in j0..=j1 {
                        for i in i0..=i1 {
                            let id = grid.index(i, j, k);
                            if one_sign && far {
                                if values[id].is_nan() {
                                    values[id] = v[0];
                                }
                            } else {
                                wanted[id] = true;
                            }
                        }
                    }
                }
            }
        }
    }
    let ids: Vec<usize> = (0..grid.len()).filter(|&id| wanted[id]).collect();
    let points: Vec<DVec3> =
        ids.iter().map(|&id| grid.at(id % grid.counts[0], (id / grid.counts[0]) % grid.counts[1], id / (grid.counts[0] * grid.counts[1]))).collect();
    for (id, value) in ids.into_iter().zip(sdf(&points)?) {
        values[id] = value;
    }
    Ok(values)
}

/// A grid edge the surface crosses: its end with a negative value and its end without.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Crossing {
    pub inside: DVec3,
    pub outside: DVec3,
}

/// A triangle mesh; triangles counter-clockwise seen from outside.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    pub vertices: Vec<DVec3>,
    pub triangles: Vec<[usize; 3]>,
}

/// Extracts the zero level set of `values` (one per grid point, in `Grid::points` order; a
/// value below zero is inside). `refine` receives every crossed edge once and returns the
/// surface point on each, in the same order.
pub fn extract(grid: &Grid, values: &[f64], refine: impl FnOnce(&[Crossing]) -> Vec<DVec3>) -> Mesh {
    let [nx, ny, nz] = grid.counts;
    let mut crossings: Vec<Crossing> = Vec::new();
    let mut edge_vertex: HashMap<(usize, usize), usize> = HashMap::new();
    // Triangles as crossing indices, with a point inside the surface to orient them by.
    let mut pending: Vec<([usize; 3], DVec3)> = Vec::new();
    if values.len() != grid.len() || nx < 2 || ny < 2 || nz < 2 {
        return Mesh::default();
    }
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let corner = |c: usize| (i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1));
                // Most cells lie wholly inside or outside: none of their tetrahedra is cut.
                let below = (0..8).filter(|&c| {
                    let (a, b, d) = corner(c);
                    values[grid.index(a, b, d)] < 0.0
                });
                if matches!(below.count(), 0 | 8) {
                    continue;
                }
                for tet in TETRAHEDRA {
                    let ids = tet.map(|c| {
                        let (a, b, d) = corner(c);
                        grid.index(a, b, d)
                    });
                    let points = tet.map(|c| {
                        let (a, b, d) = corner(c);
                        grid.at(a, b, d)
                    });
                    let v = ids.map(|id| values[id]);
                    let inside: Vec<usize> = (0..4).filter(|&q| v[q] < 0.0).collect();
                    let outside: Vec<usize> = (0..4).filter(|&q| !(v[q] < 0.0)).collect();
                    if inside.is_empty() || outside.is_empty() {
                        continue;
                    }
                    let mut cut = |p: usize, q: usize| -> usize {
                        let key = (ids[p].min(ids[q]), ids[p].max(ids[q]));
                        *edge_vertex.entry(key).or_insert_with(|| {
                            let (a, b) = if v[p] < 0.0 { (points[p], points[q]) } else { (points[q], points[p]) };
                            crossings.push(Crossing { inside: a, outside: b });
                            crossings.len() - 1
                        })
                    };
                    let centre_inside = inside.iter().map(|&q| points[q]).sum::<DVec3>() / inside.len() as f64;
                    match inside.len() {
                        1 | 3 => {
                            let (single, others) = if inside.len() == 1 { (inside[0], &outside) } else { (outside[0], &inside) };
                            pending.push(([cut(single, others[0]), cut(single, others[1]), cut(single, others[2])], centre_inside));
                        }
                        _ => {
                            let (a, b, c, d) = (inside[0], inside[1], outside[0], outside[1]);
                            let (ac, ad, bc, bd) = (cut(a, c), cut(a, d), cut(b, c), cut(b, d));
                            pending.push(([ac, ad, bd], centre_inside));
                            pending.push(([ac, bd, bc], centre_inside));
                        }
                    }
                }
            }
        }
    }
    let vertices = refine(&crossings);
    let triangles = pending
        .into_iter()
        .map(|(tri, centre_inside)| {
            // Orient so the normal points from inside to outside.
            let (a, b, c) = (vertices[tri[0]], vertices[tri[1]], vertices[tri[2]]);
            if (b - a).cross(c - a).dot(a - centre_inside) < 0.0 {
                [tri[0], tri[2], tri[1]]
            } else {
                tri
            }
        })
        .collect();
    Mesh { vertices, triangles }
}

/// Bisects every crossing `rounds` times with a batched inside test (`true` where the value is
/// negative), so a field evaluated on tensors pays one call per round, not one per point.
pub fn bisect(crossings: &[Crossing], rounds: usize, mut inside: impl FnMut(&[DVec3]) -> Vec<bool>) -> Vec<DVec3> {
    let mut ends: Vec<(DVec3, DVec3)> = crossings.iter().map(|c| (c.inside, c.outside)).collect();
    for _ in 0..rounds {
        let middles: Vec<DVec3> = ends.iter().map(|(a, b)| (*a + *b) * 0.5).collect();
        let below = inside(&middles);
        for ((end, middle), below) in ends.iter_mut().zip(&middles).zip(below) {
            if below {
                end.0 = *middle;
            } else {
                end.1 = *middle;
            }
        }
    }
    ends.into_iter().map(|(a, b)| (a + b) * 0.5).collect()
}

impl Mesh {
    /// Whether every edge is shared by exactly two triangles, in opposite directions: a closed,
    /// consistently oriented 2-manifold (as a triangle soup over shared vertices).
    pub fn is_closed_manifold(&self) -> bool {
        let mut edges: HashMap<(usize, usize), i32> = HashMap::new();
        for t in &self.triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *edges.entry((a, b)).or_insert(0) += 1;
            }
        }
        edges.iter().all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1))
    }

    /// OBJ text: `v x y z [r g b]` (colours in [0, 1] when given), `vn` when normals are given,
    /// 1-based faces.
    pub fn to_obj(&self, colours: Option<&[DVec3]>, normals: Option<&[DVec3]>) -> String {
        let mut out = String::with_capacity(self.vertices.len() * 60 + self.triangles.len() * 24);
        for (k, v) in self.vertices.iter().enumerate() {
            match colours.and_then(|c| c.get(k)) {
                Some(c) => {
                    let c = c.clamp(DVec3::ZERO, DVec3::ONE);
                    let _ = writeln!(out, "v {:.5} {:.5} {:.5} {:.4} {:.4} {:.4}", v.x, v.y, v.z, c.x, c.y, c.z);
                }
                None => {
                    let _ = writeln!(out, "v {:.5} {:.5} {:.5}", v.x, v.y, v.z);
                }
            }
        }
        if let Some(normals) = normals {
            for n in normals {
                let _ = writeln!(out, "vn {:.5} {:.5} {:.5}", n.x, n.y, n.z);
            }
            for t in &self.triangles {
                let _ = writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}", a = t[0] + 1, b = t[1] + 1, c = t[2] + 1);
            }
        } else {
            for t in &self.triangles {
                let _ = writeln!(out, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sphere(p: DVec3) -> f64 {
        (p - DVec3::new(0.1, 0.2, -0.05)).length() - 0.3
    }

    #[test]
    fn a_sphere_comes_out_closed_oriented_and_on_its_surface() {
        let grid = Grid::covering(DVec3::splat(-0.5), DVec3::splat(0.5), 0.05);
        let values: Vec<f64> = grid.points().into_iter().map(sphere).collect();
        let mesh = extract(&grid, &values, |c| bisect(c, 30, |points| points.iter().map(|&p| sphere(p) < 0.0).collect()));
        assert!(mesh.triangles.len() > 500);
        assert!(mesh.is_closed_manifold());
        for v in &mesh.vertices {
            assert!(sphere(*v).abs() < 1e-8, "{v}");
        }
        // Oriented outward: the signed volume is the sphere's (4/3 pi r^3) to within the
        // faceting.
        let volume: f64 = mesh.triangles.iter().map(|t| mesh.vertices[t[0]].dot(mesh.vertices[t[1]].cross(mesh.vertices[t[2]])) / 6.0).sum();
        let exact = 4.0 / 3.0 * std::f64::consts::PI * 0.3f64.powi(3);
        assert!((volume / exact - 1.0).abs() < 0.03, "volume {volume} against {exact}");
    }

    /// Two balls and a rod thinner than a grid cell, their union's distance (exact outside
    /// the pieces, a lower bound on the distance inside their overlaps).
    fn balls_and_rod(p: DVec3) -> f64 {
        let rod = {
            let (a, b) = (DVec3::new(-0.35, -0.3, 0.0), DVec3::new(0.3, 0.35, 0.1));
            let t = ((p - a).dot(b - a) / (b - a).length_squared()).clamp(0.0, 1.0);
            (p - (a + (b - a) * t)).length() - 0.012
        };
        sphere(p).min((p - DVec3::new(-0.3, -0.25, 0.2)).length() - 0.08).min(rod)
    }

    #[test]
    fn the_narrow_band_finds_the_same_mesh_from_fewer_samples() {
        // Grids of several sizes, so blocks end short of the grid's last point too.
        for (cell, lo, hi) in [(0.008, -0.5, 0.5), (0.007, -0.47, 0.53), (0.011, -0.61, 0.49)] {
            let grid = Grid::covering(DVec3::splat(lo), DVec3::splat(hi), cell);
            let whole: Vec<f64> = grid.points().into_iter().map(balls_and_rod).collect();
            let mut sampled = 0;
            let band = narrow_band_values(&grid, |points| {
                sampled += points.len();
                Ok::<_, ()>(points.iter().map(|&p| balls_and_rod(p)).collect())
            })
            .unwrap();
            let refine = |c: &[Crossing]| bisect(c, 20, |points| points.iter().map(|&p| balls_and_rod(p) < 0.0).collect());
            let (a, b) = (extract(&grid, &whole, refine), extract(&grid, &band, refine));
            assert!(a.triangles.len() > 1000, "{}", a.triangles.len());
            assert_eq!(a.vertices, b.vertices, "cell {cell}");
            assert_eq!(a.triangles, b.triangles, "cell {cell}");
            // Every point of a block near the surface is its true value; the rest only keep
            // their sign.
            assert!(band.iter().zip(&whole).all(|(b, w)| (*b < 0.0) == (*w < 0.0)));
            // Measured: 31%, 27% and 31% of the points.
            assert!(sampled * 5 < grid.len() * 2, "{sampled} of {} points sampled", grid.len());
        }
    }

    #[test]
    fn a_surface_cut_by_the_grid_is_not_closed() {
        let grid = Grid::covering(DVec3::splat(-0.2), DVec3::splat(0.2), 0.05);
        let values: Vec<f64> = grid.points().into_iter().map(sphere).collect();
        let mesh = extract(&grid, &values, |c| bisect(c, 10, |points| points.iter().map(|&p| sphere(p) < 0.0).collect()));
        assert!(!mesh.triangles.is_empty() && !mesh.is_closed_manifold());
    }
}
