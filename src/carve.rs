//! The meshed surface cut to the capture's visual hull. The field's zero level set can hold
//! sheets where no image constrains it (far from the body, where every training ray saw
//! background and the density stayed near zero, so no render shows them), which a mesh would
//! otherwise carry. A point of the true body projects inside every mask of its frame, so a
//! vertex that projects into images of its frame outside their masks (widened by `MASK_MARGIN`
//! pixels for the masks' own edge; two images, or the only one that sees it, for a mask may
//! hold a segmenter's stray cut) is not the body: every triangle that holds one is cut, and the vertices no triangle holds any more go with them. An image whose mask
//! keeps clear of its border frames the whole body, so a vertex beyond that image's border is
//! not the body either; where the body runs off an image, that image says nothing beyond it.
//!
//! A pose without training images of its own (a test pose, another scene's) has few masks or
//! none, and the field can hold sheets there that no training ray ever met. Its vertices are
//! also moved into every training frame by their skinning (linear blend of the bones' moves),
//! and a vertex outside the masks of more than a quarter of the training images that judge it
//! is cut.

use crate::imageio::Mask;
use crate::isosurface::Mesh;
use crate::scene::{Scene, Split, View};
use glam::DVec3;

/// How many pixels beyond a mask's edge still count as inside (a silhouette's antialiased edge
/// and the fit's sub-pixel offsets).
pub const MASK_MARGIN: usize = 2;

/// The share of the training images judging a vertex moved into their frames that may see it
/// outside their masks before it is cut. The fitted surface of a training frame, judged this
/// way without its own images, keeps every vertex its own hull keeps at a quarter (five shipped
/// captures); at a tenth the dressed human's hands by its skirt go. A sheet beside the body is
/// seen outside by most images, over the body by those that look through it.
pub const OUTSIDE_SHARE: f64 = 0.25;

/// A carved mesh and what it kept.
pub struct Carved {
    pub mesh: Mesh,
    /// The original index of each kept vertex.
    pub kept: Vec<usize>,
    pub triangles_cut: usize,
    /// How many masked images of the frame judged the vertices.
    pub views: usize,
    /// How many training images judged the vertices moved into their frames (0 for a frame
    /// with training images of its own).
    pub training_views: usize,
    /// The kept vertices' skinning, when the carve was given it.
    pub skinning: Option<Vec<Vec<(usize, f32)>>>,
}

/// Per vertex of a mesh, its skinning weights `(bone, weight)` in the meshed pose.
pub type Skinning = [Vec<(usize, f32)>];

/// Whether a frame has no masked training image of its own, so that `carve` judges its
/// vertices in the training frames too (and wants their skinning).
pub fn needs_skinning(scene: &Scene, frame: usize) -> bool {
    !scene.views.iter().any(|v| v.frame == frame && v.split == Split::Train && v.mask.is_some())
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

/// Per vertex, whether the view's mask puts it outside the body (`None` where the view says
/// nothing: behind its camera, or off an image whose mask runs off it); `None` for a view
/// without a usable mask.
fn judge(vertices: &[DVec3], scene: &Scene, view: &View) -> Option<Vec<Option<bool>>> {
    let mask = view.mask.as_ref()?;
    let camera = &scene.cameras[view.camera];
    if (mask.width, mask.height) != (camera.width, camera.height) {
        return None;
    }
    let inside = widened(mask, MASK_MARGIN);
    let frames_body = !touches_border(&inside, mask.width, mask.height);
    let verdict = |v: &DVec3| {
        let p = camera.project(*v)?;
        if p.x < 0.0 || p.y < 0.0 || p.x >= mask.width as f64 || p.y >= mask.height as f64 {
            return frames_body.then_some(true);
        }
        Some(!inside[p.y as usize * mask.width + p.x as usize])
    };
    Some(vertices.iter().map(verdict).collect())
}

/// Whether each vertex lies outside the masks of the frame it projects into: outside two of
/// them, or the only one that judges it. One image's mask alone never cuts what the others see
/// inside theirs: a segmenter's stray cut (a blob bitten from an arm) stays one image's error.
fn outside_hull(vertices: &[DVec3], scene: &Scene, frame: usize) -> (Vec<bool>, usize) {
    let (mut outside, mut judged) = (vec![0u32; vertices.len()], vec![0u32; vertices.len()]);
    let mut views = 0;
    for verdicts in scene.views.iter().filter(|v| v.frame == frame).filter_map(|view| judge(vertices, scene, view)) {
        views += 1;
        for ((out, seen), verdict) in outside.iter_mut().zip(judged.iter_mut()).zip(verdicts) {
            *seen += verdict.is_some() as u32;
            *out += (verdict == Some(true)) as u32;
        }
    }
    (outside.iter().zip(&judged).map(|(&o, &j)| o >= 2 || (o == 1 && j == 1)).collect(), views)
}

/// Whether each vertex, moved by its skinning from frame `frame` into each training frame,
/// lies outside the masks of more than `OUTSIDE_SHARE` of the training images that judge it.
fn outside_training_hulls(vertices: &[DVec3], skinning: &Skinning, scene: &Scene, frame: usize) -> (Vec<bool>, usize) {
    let (mut outside, mut judged) = (vec![0u32; vertices.len()], vec![0u32; vertices.len()]);
    let mut views = 0;
    let from = &scene.frames[frame].pose;
    for target in scene.training_frames() {
        let moved = crate::skeleton::skin_points(vertices, skinning, &from.moves_to(&scene.frames[target].pose));
        let training = scene.views.iter().filter(|v| v.frame == target && v.split == Split::Train);
        for verdicts in training.filter_map(|view| judge(&moved, scene, view)) {
            views += 1;
            for ((out, seen), verdict) in outside.iter_mut().zip(judged.iter_mut()).zip(verdicts) {
                *seen += verdict.is_some() as u32;
                *out += (verdict == Some(true)) as u32;
            }
        }
    }
    (outside.iter().zip(&judged).map(|(&o, &j)| o as f64 > OUTSIDE_SHARE * j as f64).collect(), views)
}

/// `mesh` (meshed in `scene`'s frame `frame`) cut to the frame's visual hull and, given its
/// vertices' skinning for a frame without training images (`needs_skinning`), to the training
/// frames' hulls too.
pub fn carve(mesh: &Mesh, scene: &Scene, frame: usize, skinning: Option<&Skinning>) -> Carved {
    let (mut outside, views) = outside_hull(&mesh.vertices, scene, frame);
    let mut training_views = 0;
    if let Some(skinning) = skinning.filter(|s| s.len() == mesh.vertices.len()) {
        let (elsewhere, judged) = outside_training_hulls(&mesh.vertices, skinning, scene, frame);
        training_views = judged;
        outside.iter_mut().zip(elsewhere).for_each(|(o, e)| *o |= e);
    }
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
    let skinning = skinning.filter(|s| s.len() == mesh.vertices.len()).map(|s| kept.iter().map(|&v| s[v].clone()).collect());
    Carved { mesh: Mesh { vertices, triangles }, kept, triangles_cut, views, training_views, skinning }
}
