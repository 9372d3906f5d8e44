//! The cameras a relight or a free render looks through: a turntable around the body, the
//! world's up as the cameras show it, and a camera resized to another image size.

use crate::scene::Scene;
use glam::DVec3;
use std::f64::consts::PI;

/// `count` cameras evenly on a circle around the body in `frame`, looking at the centre of its
/// bones' box, for a turntable: the circle lies at the scene's cameras' mean height above
/// that centre and their mean distance from the vertical through it (`world_up`), starts at the first camera's side, and every camera has the first one's image
/// size and focal length.
pub fn orbit_cameras(scene: &Scene, frame: usize, count: usize) -> Vec<crate::scene::Camera> {
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
    (0..count)
        .map(|k| {
            let turn = glam::DQuat::from_axis_angle(up, 2.0 * PI * k as f64 / count as f64);
            let eye = centre + up * height + turn * start * radius.max(1e-6);
            crate::scene::Camera::look_at(&format!("orbit{k:03}"), eye, centre, up, width, image_height, focal)
        })
        .collect()
}

/// The world's up as the cameras show it. A camera that looks down at a body is pitched, so
/// its own up leans toward the body, but its image rows stay level (no roll): every camera's
/// right axis is horizontal, and up is the direction across all of them (the cross products of
/// pairs of right axes, each turned to the cameras' mean up, summed). With one camera, or all
/// facing one way, the cameras' mean up (a camera's image +Y points down).
pub fn world_up(cameras: &[crate::scene::Camera]) -> DVec3 {
    let mean_up = cameras.iter().map(|c| -c.camera_to_world.y_axis.truncate()).sum::<DVec3>().try_normalize().unwrap_or(DVec3::Y);
    let rights: Vec<DVec3> = cameras.iter().filter_map(|c| c.camera_to_world.x_axis.truncate().try_normalize()).collect();
    let mut across = DVec3::ZERO;
    for (i, a) in rights.iter().enumerate() {
        for b in &rights[i + 1..] {
            let c = a.cross(*b);
            across += if c.dot(mean_up) < 0.0 { -c } else { c };
        }
    }
    if across.length() > 1e-3 * rights.len().max(1) as f64 {
        across.normalize()
    } else {
        mean_up
    }
}
