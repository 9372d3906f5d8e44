//! The meshed surface cut to the capture's visual hull. The field's zero level set can hold
//! sheets where no image constrains it (far from the body, where every training ray saw
//! background and the density stayed near zero, so no render shows them), which a mesh would
//! otherwise carry. A point of the true body projects inside every mask of its frame, so a
//! vertex that projects into an image of its frame outside that image's mask (widened by
//! `MASK_MARGIN` pixels for the masks' own edge) is not the body: every triangle that holds
//! one is cut, and the vertices no triangle holds any more go with them. An image whose mask
//! keeps clear of its border frames the whole body, so a vertex beyond that image's border is
//! not the body either; where the body runs off an image, that image says nothing beyond it.

use crate::imageio::Mask;
use crate::isosurface::Mesh;
use crate::scene::Scene;
use glam::DVec3;

/// How many pixels beyond a mask's edge still count as inside (a silhouette's antialiased edge
/// and the fit's sub-pixel offsets).
pub const MASK_MARGIN: usize = 2;

/// A carved mesh and what it kept.
pub struct Carved {
    pub mesh: Mesh,
    /// The original index of each kept vertex.
    pub kept: Vec<usize>,
    pub triangles_cut: usize,
    /// How many masked images of the frame judged the vertices.
    pub views: usize,
}

impl Carved {
    /// `values` (one per original vertex) for the kept vertices.
    pub fn keep<T: Copy>(&self, values: &[T]) -> Vec<T> {
        self.kept.iter().map(|&v| values[v]).collect()
    }
}

/// `mask` widened by `margin` pixels (a square neighbourhood).
fn widened(mask: &Mask, margin: usize) -> Vec<bool> {
    let (w, h) = (mask.width, mask.height);
    let mut rows = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            rows[y * w + x] = (x.saturating_sub(margin)..=(x + margin).min(w - 1)).any(|xx| mask.foreground[y * w + xx]);
        }
    }
    let mut out = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            out[y * w + x] = (y.saturating_sub(margin)..=(y + margin).min(h - 1)).any(|yy| rows[yy * w + x]);
        }
    }
    out
}

/// Whether a (widened) mask reaches its image's border.
fn touches_border(inside: &[bool], w: usize, h: usize) -> bool {
    (0..w).any(|x| inside[x] || inside[(h - 1) * w + x]) || (0..h).any(|y| inside[y * w] || inside[y * w + w - 1])
}

/// Whether each vertex lies outside some mask of the frame it projects into.
fn outside_hull(vertices: &[DVec3], scene: &Scene, frame: usize) -> (Vec<bool>, usize) {
    let mut outside = vec![false; vertices.len()];
    let mut views = 0;
    for view in scene.views.iter().filter(|v| v.frame == frame) {
        let Some(mask) = &view.mask else { continue };
        let camera = &scene.cameras[view.camera];
        if (mask.width, mask.height) != (camera.width, camera.height) {
            continue;
        }
        views += 1;
        let inside = widened(mask, MASK_MARGIN);
        let frames_body = !touches_border(&inside, mask.width, mask.height);
        for (v, out) in vertices.iter().zip(outside.iter_mut()) {
            let Some(p) = camera.project(*v) else { continue };
            if p.x < 0.0 || p.y < 0.0 || p.x >= mask.width as f64 || p.y >= mask.height as f64 {
                *out |= frames_body;
                continue;
            }
            if !inside[p.y as usize * mask.width + p.x as usize] {
                *out = true;
            }
        }
    }
    (outside, views)
}

/// `mesh` (meshed in `scene`'s frame `frame`) cut to the frame's visual hull.
pub fn carve(mesh: &Mesh, scene: &Scene, frame: usize) -> Carved {
    let (outside, views) = outside_hull(&mesh.vertices, scene, frame);
    let triangles: Vec<[usize; 3]> = mesh.triangles.iter().copied().filter(|t| t.iter().all(|&v| !outside[v])).collect();
    let triangles_cut = mesh.triangles.len() - triangles.len();
    let mut index = vec![usize::MAX; mesh.vertices.len()];
    let mut kept = Vec::new();
    for t in &triangles {
        for &v in t {
            if index[v] == usize::MAX {
                index[v] = kept.len();
                kept.push(v);
            }
        }
    }
    let vertices = kept.iter().map(|&v| mesh.vertices[v]).collect();
    let triangles = triangles.iter().map(|t| t.map(|v| index[v])).collect();
    Carved { mesh: Mesh { vertices, triangles }, kept, triangles_cut, views }
}
