//! The cameras a relight or a free render looks through: a turntable around the body, the
//! world's up as the cameras show it, and a camera resized to another image size.

use crate::scene::Scene;
use glam::DVec3;
use std::f64::consts::PI;

/// `count` cameras evenly on a circle around the body in `frame`, looking at the centre of its
/// bones' box, for a turntable: the circle lies at the scene's cameras' mean height above
/// that centre and their mean distance from the vertical through it (`world_up`), starts at the first camera's side, and every camera has the first one's image
/// size and focal length.
/// Made one at a time: a motion render takes as many as it has frames, whatever `count` is.
pub fn orbit_cameras(scene: &Scene, frame: usize, count: usize) -> impl Iterator<Item = crate::scene::Camera> {
    let (lo, hi) = scene.frames[frame].pose.bounds(&scene.skeleton);
    let centre = (lo + hi) * 0.5;
    let up = world_up(&scene.cameras);
    let n = scene.cameras.len().max(1) as f64;
    let offsets: Vec<DVec3> = scene.cameras.iter().map(|c| c.centre() - centre).collect();
    let height = offsets.iter().map(|o| o.dot(up)).sum::<f64>() / n;
    let across = |o: &DVec3| *o - up * o.dot(up);
    let radius = offsets.iter().map(|o| across(o).length()).sum::<f64>() / n;
    let start = offsets.first().and_then(|o| across(o).try_normalize()).unwrap_or_else(|| up.any_orthonormal_vector());
    let (width, image_height, focal) = scene.cameras.first().map_or((128, 128, 128.0), |c| (c.width, c.height, c.fx));
    (0..count).map(move |k| {
        let turn = glam::DQuat::from_axis_angle(up, 2.0 * PI * k as f64 / count as f64);
        let eye = centre + up * height + turn * start * radius.max(1e-6);
        crate::scene::Camera::look_at(&format!("orbit{k:03}"), eye, centre, up, width, image_height, focal)
    })
}

pub use crate::scene::world_up;
