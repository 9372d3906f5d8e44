//! Ground-truth meshes of a posed character: marching tetrahedra (`isosurface`) over its
//! analytic SDF on a regular grid, written as OBJ in world coordinates (for evaluation only).

use super::character::Character;
use crate::isosurface::{bisect, extract as marching_tetrahedra, Grid, Mesh};
use crate::skeleton::Pose;
use glam::DVec3;

/// Extracts the zero level set of the character's SDF in `pose` with cells of `cell` metres
/// (every crossing bisected 24 times on the exact SDF). Returns vertices and triangles
/// (counter-clockwise seen from outside).
pub fn extract(character: &Character, pose: &Pose, cell: f64) -> (Vec<DVec3>, Vec<[usize; 3]>) {
    let (lo, hi) = pose.bounds(&character.skeleton);
    let (_, radius) = character.bounding_sphere(pose);
    // Beyond the bones by the largest capsule or garment (the bounding sphere's margin).
    let margin = (radius - (hi - lo).length() * 0.5).max(0.2);
    let grid = Grid::covering(lo - DVec3::splat(margin), hi + DVec3::splat(margin), cell);
    let values: Vec<f64> = grid.points().into_iter().map(|p| character.sdf(pose, p).0).collect();
    let mesh =
        marching_tetrahedra(&grid, &values, |crossings| bisect(crossings, 24, |points| points.iter().map(|&p| character.sdf(pose, p).0 < 0.0).collect()));
    (mesh.vertices, mesh.triangles)
}

/// OBJ text (vertices in world coordinates, 1-based faces).
pub fn to_obj(vertices: &[DVec3], triangles: &[[usize; 3]]) -> String {
    Mesh { vertices: vertices.to_vec(), triangles: triangles.to_vec() }.to_obj(None, None)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::Kind;

    #[test]
    fn mesh_vertices_lie_on_the_surface_and_the_surface_is_closed() {
        for kind in [Kind::Quadruped, Kind::Dressed] {
            let c = Character::new(kind);
            let pose = c.pose(0.1, 0.0, DVec3::ZERO);
            let cell = 0.015;
            let (vertices, triangles) = extract(&c, &pose, cell);
            assert!(triangles.len() > 500);
            for v in &vertices {
                assert!(c.sdf(&pose, *v).0.abs() < 1e-6, "vertex off the surface: {}", c.sdf(&pose, *v).0);
            }
            // Closed: every edge is shared by exactly two triangles, in opposite directions.
            assert!(Mesh { vertices, triangles }.is_closed_manifold(), "open or non-manifold edges");
        }
    }
}
