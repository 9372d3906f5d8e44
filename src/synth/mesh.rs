//! Ground-truth meshes of a posed character: marching tetrahedra over its analytic SDF on a
//! regular grid, written as OBJ in world coordinates (for evaluation only).

use super::character::Character;
use crate::skeleton::Pose;
use glam::DVec3;
use std::collections::HashMap;
use std::fmt::Write;

/// The six tetrahedra of a cube, as corner indices (corner bit 0 = +x, bit 1 = +y, bit 2 = +z),
/// all sharing the main diagonal 0-7 so that neighbouring cubes match along faces.
const TETRAHEDRA: [[usize; 4]; 6] = [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]];

/// Extracts the zero level set of the character's SDF in `pose` with cells of `cell` metres.
/// Returns vertices and triangles (counter-clockwise seen from outside).
pub fn extract(character: &Character, pose: &Pose, cell: f64) -> (Vec<DVec3>, Vec<[usize; 3]>) {
    let (lo, hi) = pose.bounds(&character.skeleton);
    let margin = 0.2;
    let origin = lo - DVec3::splat(margin);
    let counts = ((hi - lo + DVec3::splat(2.0 * margin)) / cell).ceil().as_uvec3();
    let (nx, ny, nz) = (counts.x as usize + 1, counts.y as usize + 1, counts.z as usize + 1);
    let at = |i: usize, j: usize, k: usize| origin + DVec3::new(i as f64, j as f64, k as f64) * cell;
    let mut values = vec![0.0; nx * ny * nz];
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                values[(k * ny + j) * nx + i] = character.sdf(pose, at(i, j, k)).0;
            }
        }
    }
    let index = |i: usize, j: usize, k: usize| (k * ny + j) * nx + i;
    let mut vertices = Vec::new();
    let mut edge_vertex: HashMap<(usize, usize), usize> = HashMap::new();
    let mut triangles = Vec::new();
    let mut vertex_on = |a: usize, b: usize, pa: DVec3, pb: DVec3, va: f64, vb: f64, vertices: &mut Vec<DVec3>| -> usize {
        let key = (a.min(b), a.max(b));
        *edge_vertex.entry(key).or_insert_with(|| {
            // The SDF is not linear along the edge: bisect for the exact crossing.
            let (mut inside, mut outside) = if va < 0.0 { (pa, pb) } else { (pb, pa) };
            for _ in 0..24 {
                let mid = (inside + outside) * 0.5;
                if character.sdf(pose, mid).0 < 0.0 {
                    inside = mid;
                } else {
                    outside = mid;
                }
            }
            let _ = vb;
            vertices.push((inside + outside) * 0.5);
            vertices.len() - 1
        })
    };
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let corner = |c: usize| (i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1));
                for tet in TETRAHEDRA {
                    let ids: Vec<usize> = tet
                        .iter()
                        .map(|&c| {
                            let (a, b, d) = corner(c);
                            index(a, b, d)
                        })
                        .collect();
                    let points: Vec<DVec3> = tet
                        .iter()
                        .map(|&c| {
                            let (a, b, d) = corner(c);
                            at(a, b, d)
                        })
                        .collect();
                    let v: Vec<f64> = ids.iter().map(|&id| values[id]).collect();
                    let inside: Vec<usize> = (0..4).filter(|&q| v[q] < 0.0).collect();
                    let outside: Vec<usize> = (0..4).filter(|&q| v[q] >= 0.0).collect();
                    let mut cut = |p: usize, q: usize, vertices: &mut Vec<DVec3>| vertex_on(ids[p], ids[q], points[p], points[q], v[p], v[q], vertices);
                    let emit = |tri: [usize; 3], vertices: &Vec<DVec3>, triangles: &mut Vec<[usize; 3]>| {
                        // Orient so the normal points from inside to outside.
                        let centre_inside = inside.iter().map(|&q| points[q]).sum::<DVec3>() / inside.len() as f64;
                        let (a, b, c) = (vertices[tri[0]], vertices[tri[1]], vertices[tri[2]]);
                        let normal = (b - a).cross(c - a);
                        if normal.dot(a - centre_inside) < 0.0 {
                            triangles.push([tri[0], tri[2], tri[1]]);
                        } else {
                            triangles.push(tri);
                        }
                    };
                    match inside.len() {
                        1 | 3 => {
                            let (single, others) = if inside.len() == 1 { (inside[0], &outside) } else { (outside[0], &inside) };
                            let tri = [cut(single, others[0], &mut vertices), cut(single, others[1], &mut vertices), cut(single, others[2], &mut vertices)];
                            emit(tri, &vertices, &mut triangles);
                        }
                        2 => {
                            let (a, b, c, d) = (inside[0], inside[1], outside[0], outside[1]);
                            let (ac, ad, bc, bd) = (cut(a, c, &mut vertices), cut(a, d, &mut vertices), cut(b, c, &mut vertices), cut(b, d, &mut vertices));
                            emit([ac, ad, bd], &vertices, &mut triangles);
                            emit([ac, bd, bc], &vertices, &mut triangles);
                        }
                        _ => {}
                    }
                }
            }
        }
    }
    (vertices, triangles)
}

/// OBJ text (vertices in world coordinates, 1-based faces).
pub fn to_obj(vertices: &[DVec3], triangles: &[[usize; 3]]) -> String {
    let mut out = String::with_capacity(vertices.len() * 30 + triangles.len() * 20);
    for v in vertices {
        let _ = writeln!(out, "v {:.5} {:.5} {:.5}", v.x, v.y, v.z);
    }
    for t in triangles {
        let _ = writeln!(out, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::Kind;

    #[test]
    fn mesh_vertices_lie_on_the_surface_and_the_surface_is_closed() {
        let c = Character::new(Kind::Quadruped);
        let pose = c.pose(0.1, 0.0, DVec3::ZERO);
        let cell = 0.015;
        let (vertices, triangles) = extract(&c, &pose, cell);
        assert!(triangles.len() > 500);
        for v in &vertices {
            assert!(c.sdf(&pose, *v).0.abs() < 1e-6, "vertex off the surface: {}", c.sdf(&pose, *v).0);
        }
        // Closed: every edge is shared by exactly two triangles.
        let mut edges: HashMap<(usize, usize), usize> = HashMap::new();
        for t in &triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *edges.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
        assert!(edges.values().all(|&n| n == 2), "open or non-manifold edges");
    }
}
