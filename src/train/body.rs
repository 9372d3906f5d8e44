//! What the training masks say of the body beyond its bones: loose clothing's reach (which the
//! root's grids must cover) and the points where Gaussians are seeded on it.

use crate::scene::{Scene, Split};

/// Lattice steps per body extent (the posed bones' diagonal) when the training masks are
/// searched for body beyond the bones' grids (`masked_reach_beyond_bones`): 3 cm on a human,
/// a tenth of what a box reaches beyond its bone.
const HULL_STEPS_PER_EXTENT: f64 = 64.0;

/// The points of the `root` bone's frame (root-local, m, one per lattice cell) where the body
/// lies farther than `reach` from every bone, as the training masks show it; none for a body
/// tight on its bones.
///
/// Each training frame's visual hull (a lattice over the frame's bones widened by twice
/// `reach`; a point is in it when every masked training view of the frame sees it inside its
/// mask) proposes the points farther than `reach` from every bone that some view shows beyond
/// the bones: the ray through the point's pixel passes farther than `reach` from every bone,
/// so that pixel's body is not the bones'. A few views leave phantoms in a hull (inside every
/// mask, no body there: under a dog's belly, where no camera looks), and a tight body explains
/// every one of their pixels; dog-sun's 7-view hull reached 0.44 m from its bones without this
/// test. Phantoms beside real clothing (behind a skirt, along one camera's cone) can still pass
/// it; they lie wherever the cameras' cones cross the body, so they move with the pose, while
/// clothing the root carries stays put in the root's frame: a proposal counts only when, in the
/// root's frame, the hull holds it in at least half of the frames where it lies beyond every
/// bone (`LOOSE_CONSENSUS`).
pub fn masked_body_beyond_bones(scene: &Scene, reach: f64, root: usize) -> Vec<glam::DVec3> {
    use rayon::prelude::*;
    let skeleton = &scene.skeleton;
    let distance = crate::skeleton::distance_to_segment;
    // Per masked training frame: the frame, its bones' segments (asked for at every lattice
    // point) and its masked training views.
    type Segments = Vec<(glam::DVec3, glam::DVec3)>;
    let frames: Vec<(&crate::scene::Frame, Segments, Vec<&crate::scene::View>)> = scene
        .frames
        .iter()
        .enumerate()
        .map(|(position, frame)| {
            let segments = (0..skeleton.len()).map(|b| frame.pose.segment(skeleton, b)).collect();
            (frame, segments, scene.views.iter().filter(|v| v.frame == position && v.split == Split::Train && v.mask.is_some()).collect())
        })
        .filter(|(_, _, views): &(_, _, Vec<_>)| !views.is_empty())
        .collect();
    let inside_every_mask = |views: &[&crate::scene::View], p: glam::DVec3| {
        views.iter().all(|v| {
            let camera = &scene.cameras[v.camera];
            let Some(mask) = v.mask.as_ref() else { return false };
            camera.project(p).is_some_and(|px| {
                let (x, y) = (px.x.floor(), px.y.floor());
                x >= 0.0 && y >= 0.0 && (x as usize) < mask.width && (y as usize) < mask.height && mask.foreground[y as usize * mask.width + x as usize]
            })
        })
    };
    let beyond_every_bone = |segments: &[(glam::DVec3, glam::DVec3)], p: glam::DVec3| segments.iter().all(|&s| distance(p, s) > reach);
    // A view shows body beyond the bones at `p` when the ray through p's pixel passes farther
    // than `reach` from every bone: a body tight on its bones explains every mask pixel, so a
    // phantom of the hull (inside every mask, yet no body there) never passes this test.
    let far_beyond = 4.0 * (scene.body_extent() + reach);
    let shown_beyond_bones = |segments: &[(glam::DVec3, glam::DVec3)], views: &[&crate::scene::View], p: glam::DVec3| {
        views.iter().any(|v| {
            let camera = &scene.cameras[v.camera];
            camera.project(p).is_some_and(|px| {
                let ray = camera.ray_through(px.floor() + glam::DVec2::splat(0.5));
                let ray = (ray.origin, ray.at((p - ray.origin).length() + far_beyond));
                segments.iter().all(|&s| crate::skeleton::segment_distance(ray, s) > reach)
            })
        })
    };
    // Proposals, root-local, from every frame's hull.
    let proposals: Vec<glam::DVec3> = frames
        .par_iter()
        .flat_map_iter(|(frame, segments, views)| {
            let (lo, hi) = frame.pose.bounds(skeleton);
            let step = (hi - lo).length() / HULL_STEPS_PER_EXTENT;
            let (lo, hi) = (lo - glam::DVec3::splat(2.0 * reach), hi + glam::DVec3::splat(2.0 * reach));
            let counts = ((hi - lo) / step).ceil().as_uvec3();
            let mut found = Vec::new();
            for k in 0..counts.z {
                for j in 0..counts.y {
                    for i in 0..counts.x {
                        let p = lo + glam::DVec3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5) * step;
                        if beyond_every_bone(segments, p) && inside_every_mask(views, p) && shown_beyond_bones(segments, views, p) {
                            found.push(frame.pose.to_local(root, p));
                        }
                    }
                }
            }
            found
        })
        .collect();
    // One proposal per cell of a root-local lattice (frames propose the same points over and over).
    let cell = scene.body_extent() / HULL_STEPS_PER_EXTENT;
    let proposals: Vec<glam::DVec3> =
        proposals.into_iter().map(|p| ((p / cell).round().as_i64vec3().to_array(), p)).collect::<std::collections::HashMap<_, _>>().into_values().collect();
    // The consensus over frames, in the root's frame.
    let held = |local: &glam::DVec3| {
        let (mut beyond, mut inside) = (0usize, 0usize);
        for (frame, segments, views) in &frames {
            let p = frame.pose.to_world(root, *local);
            if beyond_every_bone(segments, p) {
                beyond += 1;
                inside += inside_every_mask(views, p) as usize;
            }
        }
        inside as f64 >= LOOSE_CONSENSUS * beyond as f64
    };
    let mut held: Vec<glam::DVec3> = proposals.into_par_iter().filter(|p| held(p)).collect();
    // The map's order is arbitrary: sorted, so whatever is seeded from the points is the same
    // in every run (a resumed fit rebuilds it).
    held.sort_by(|a, b| a.to_array().partial_cmp(&b.to_array()).unwrap_or(std::cmp::Ordering::Equal));
    held
}

/// How far from the `root` bone's segment the body reaches where it lies farther than `reach`
/// from every bone, as the training masks show it (`masked_body_beyond_bones`), plus a quarter
/// of `reach` so the surface is inside the grid; `None` when nowhere (a body tight on its
/// bones: the grids hold it already).
pub fn masked_reach_beyond_bones(scene: &Scene, reach: f64, root: usize) -> Option<f64> {
    let points = masked_body_beyond_bones(scene, reach, root);
    reach_of(&points, scene.skeleton.bones[root].length, reach)
}

/// The farthest of `points` (root-local) from the root's segment of `length`, plus a quarter
/// of `reach`.
pub(super) fn reach_of(points: &[glam::DVec3], length: f64, reach: f64) -> Option<f64> {
    let segment = (glam::DVec3::ZERO, glam::DVec3::new(0.0, length, 0.0));
    points.iter().map(|&p| crate::skeleton::distance_to_segment(p, segment)).reduce(f64::max).map(|d| d + 0.25 * reach)
}

/// The share of the frames (where a point lies beyond every bone) whose visual hull must hold
/// a point of the root's frame for it to count as loose body (`masked_reach_beyond_bones`).
const LOOSE_CONSENSUS: f64 = 0.5;

/// Farthest-point samples of `points` (the loose body, root-local) until every point lies
/// within `spacing` of a sample or there are `most`: Gaussians' means that cover it evenly.
/// The first is the point farthest from the others' centre, so the spread is the same for
/// the same points.
pub fn seeds_on_loose_body(points: &[glam::DVec3], spacing: f64, most: usize) -> Vec<glam::DVec3> {
    if points.is_empty() || most == 0 {
        return Vec::new();
    }
    let centre = points.iter().copied().sum::<glam::DVec3>() / points.len() as f64;
    let first = (0..points.len()).max_by(|&a, &b| points[a].distance_squared(centre).total_cmp(&points[b].distance_squared(centre))).unwrap_or(0);
    let mut seeds = vec![points[first]];
    let mut nearest: Vec<f64> = points.iter().map(|p| p.distance(points[first])).collect();
    while seeds.len() < most {
        let Some((next, &gap)) = nearest.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)) else { break };
        if gap <= spacing {
            break;
        }
        seeds.push(points[next]);
        for (d, p) in nearest.iter_mut().zip(points) {
            *d = d.min(p.distance(points[next]));
        }
    }
    seeds
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_cover_the_loose_body_within_their_spacing_or_stop_at_the_most() {
        // A shell of lattice points, like a skirt's hem beyond the bones.
        let points: Vec<glam::DVec3> = (0..40)
            .flat_map(|a| (0..8).map(move |h| glam::DVec3::new((a as f64 * 0.157).cos() * 0.4, -0.1 - 0.04 * h as f64, (a as f64 * 0.157).sin() * 0.4)))
            .collect();
        let spacing = 0.15;
        let seeds = seeds_on_loose_body(&points, spacing, 100);
        let gap = |p: &glam::DVec3| seeds.iter().map(|s| s.distance(*p)).fold(f64::INFINITY, f64::min);
        assert!(points.iter().all(|p| gap(p) <= spacing), "every point within the spacing of a seed");
        // No two seeds nearer than the spacing: each was the farthest point left.
        assert!(seeds.iter().enumerate().all(|(i, a)| seeds[..i].iter().all(|b| a.distance(*b) > spacing)));
        assert!(seeds.len() > 5 && seeds.iter().all(|s| points.contains(s)));
        // Capped, and the same points give the same seeds.
        assert_eq!(seeds_on_loose_body(&points, spacing, 3), seeds[..3].to_vec());
        assert!(seeds_on_loose_body(&[], spacing, 10).is_empty());
    }
}
