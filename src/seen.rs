//! Which points of a surface a set of cameras sees: the surface rasterised into a depth buffer
//! per camera at `OVERSAMPLE` times its resolution (at most `MOST_BUFFER_SIDE`; depth interpolated as 1/z across each
//! triangle, as perspective does). A point is seen by a camera when it faces the camera, lands
//! in its image and lies no more than `TOLERANCE` buffer pixels' footprints behind the nearest
//! surface there (a point on a slanted triangle is off its pixel's centre, where the buffer
//! holds the depth). What a capture saw of a pose (`SeenInFrames`): the surface carried into
//! every training frame by its skinning, and seen there by that frame's training cameras.

use crate::isosurface::Mesh;
use crate::scene::{Camera, Scene, Split};
use crate::skeleton::{skin_direction, skin_point, skin_points};
use glam::{DMat3, DMat4, DVec2, DVec3};
use rayon::prelude::*;

/// Buffer pixels per image pixel, along each side.
pub const OVERSAMPLE: usize = 4;
/// The longest side of a depth buffer (pixels): a capture's images larger than this over
/// `OVERSAMPLE` are rasterised at less than `OVERSAMPLE` times their size, so a 1024-pixel
/// capture's 240 buffers take 250 MB, not 16 GB.
pub const MOST_BUFFER_SIDE: usize = 512;
/// How far (buffer pixels' footprints at the point's depth) a seen point may lie behind the
/// buffer's nearest surface: a surface at 80 degrees to the view moves 2.8 footprints in depth
/// across half a pixel.
pub const TOLERANCE: f64 = 3.0;

/// A camera's map from the world to its pixels, with its rotation inverted once
/// (`Camera::project` inverts it at every call): what rasterising and testing a whole mesh
/// against a camera repeat hundreds of thousands of times.
struct Pinhole {
    to_camera: DMat3,
    centre: DVec3,
    camera: Camera,
}

impl Pinhole {
    fn new(camera: Camera) -> Self {
        Self { to_camera: DMat3::from_mat4(camera.camera_to_world).inverse(), centre: camera.centre(), camera }
    }

    /// A world point's depth along the optical axis and its continuous pixel position (of no
    /// meaning where the depth is not positive).
    fn depth_and_pixel(&self, world: DVec3) -> (f64, DVec2) {
        let c = self.to_camera * (world - self.centre);
        let camera = &self.camera;
        (c.z, DVec2::new(camera.fx * c.x / c.z + camera.cx, camera.fy * c.y / c.z + camera.cy))
    }
}

/// The depth buffers of one surface, one per camera.
pub struct Seen {
    views: Vec<(Pinhole, Vec<f32>)>,
}

impl Seen {
    /// `mesh` rasterised into every camera (at `OVERSAMPLE` times its resolution, at most
    /// `MOST_BUFFER_SIDE`), the cameras on every thread.
    pub fn new(mesh: &Mesh, cameras: &[Camera]) -> Self {
        let views = cameras
            .par_iter()
            .map(|camera| {
                let scale = (OVERSAMPLE as f64).min(MOST_BUFFER_SIDE as f64 / camera.width.max(camera.height) as f64);
                let size = |side: usize| ((side as f64 * scale).round() as usize).max(1);
                let pinhole = Pinhole::new(camera.resized(size(camera.width), size(camera.height)));
                let depth = depth_buffer(mesh, &pinhole);
                (pinhole, depth)
            })
            .collect();
        Self { views }
    }

    /// Whether some camera sees the surface point `point` whose outward normal is `normal`.
    pub fn sees(&self, point: DVec3, normal: DVec3) -> bool {
        self.views.iter().any(|(pinhole, depth)| {
            if normal.dot(pinhole.centre - point) <= 0.0 {
                return false;
            }
            let camera = &pinhole.camera;
            let (z, p) = pinhole.depth_and_pixel(point);
            if z <= 1e-12 || !(p.x >= 0.0 && p.y >= 0.0 && p.x < camera.width as f64 && p.y < camera.height as f64) {
                return false;
            }
            let nearest = depth[p.y as usize * camera.width + p.x as usize] as f64;
            z <= nearest + TOLERANCE * z / camera.fx.min(camera.fy)
        })
    }
}

/// What a capture's training images saw of one pose's surface: per training frame, the bones'
/// moves there and the surface carried there (linear blend skinning) as its cameras see it.
pub struct SeenInFrames {
    frames: Vec<(Vec<DMat4>, Seen)>,
}

impl SeenInFrames {
    /// `mesh` of `scene`'s frame `frame`, with its vertices' skinning weights `(bone, weight)`.
    pub fn new(mesh: &Mesh, skinning: &[Vec<(usize, f32)>], scene: &Scene, frame: usize) -> Self {
        let from = &scene.frames[frame].pose;
        let frames = scene
            .training_frames()
            .into_par_iter()
            .map(|target| {
                let moves = from.moves_to(&scene.frames[target].pose);
                let moved = Mesh { vertices: skin_points(&mesh.vertices, skinning, &moves), triangles: mesh.triangles.clone() };
                let mut cameras: Vec<usize> = scene.views_in(Split::Train).filter(|v| v.frame == target).map(|v| v.camera).collect();
                cameras.sort_unstable();
                cameras.dedup();
                let cameras: Vec<Camera> = cameras.iter().map(|&c| scene.cameras[c].clone()).collect();
                (moves, Seen::new(&moved, &cameras))
            })
            .collect();
        Self { frames }
    }

    /// Whether some training image saw the surface point `point` (outward normal `normal`,
    /// skinning `weights`), carried into its frame.
    pub fn sees(&self, point: DVec3, normal: DVec3, weights: &[(usize, f32)]) -> bool {
        self.frames.iter().any(|(moves, seen)| seen.sees(skin_point(point, weights, moves), skin_direction(normal, weights, moves)))
    }
}

/// The depth (along the optical axis) of the nearest triangle at each pixel's centre; infinity
/// where none lies. Triangles reaching behind the camera are left out (a body is in front).
/// Each vertex is projected once, not once per triangle it corners.
fn depth_buffer(mesh: &Mesh, pinhole: &Pinhole) -> Vec<f32> {
    let (w, h) = (pinhole.camera.width, pinhole.camera.height);
    let projected: Vec<(f64, DVec2)> = mesh.vertices.iter().map(|&v| pinhole.depth_and_pixel(v)).collect();
    let mut depth = vec![f32::INFINITY; w * h];
    for triangle in &mesh.triangles {
        let corners = triangle.map(|v| projected[v]);
        let (z, p) = (corners.map(|c| c.0), corners.map(|c| c.1));
        if z.iter().any(|&z| z <= 1e-9) {
            continue;
        }
        let area = edge(p[0], p[1], p[2]);
        if area.abs() < 1e-18 {
            continue;
        }
        let (lo, hi) = (p[0].min(p[1]).min(p[2]), p[0].max(p[1]).max(p[2]));
        let x0 = (lo.x - 0.5).ceil().max(0.0) as usize;
        let y0 = (lo.y - 0.5).ceil().max(0.0) as usize;
        let x1 = ((hi.x - 0.5).floor().min(w as f64 - 1.0)).max(-1.0);
        let y1 = ((hi.y - 0.5).floor().min(h as f64 - 1.0)).max(-1.0);
        if x1 < 0.0 || y1 < 0.0 {
            continue;
        }
        for y in y0..=y1 as usize {
            for x in x0..=x1 as usize {
                let q = DVec2::new(x as f64 + 0.5, y as f64 + 0.5);
                let b = [edge(p[1], p[2], q) / area, edge(p[2], p[0], q) / area, edge(p[0], p[1], q) / area];
                if b.iter().any(|&b| b < 0.0) {
                    continue;
                }
                let at = (1.0 / (b[0] / z[0] + b[1] / z[1] + b[2] / z[2])) as f32;
                let cell = &mut depth[y * w + x];
                *cell = cell.min(at);
            }
        }
    }
    depth
}

/// Twice the signed area of `abc` (the edge function of `c` against `ab`).
fn edge(a: DVec2, b: DVec2, c: DVec2) -> f64 {
    (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::isosurface::{bisect, extract, Grid};
    use glam::DMat4;

    fn sphere(centre: DVec3, radius: f64, cell: f64) -> Mesh {
        let grid = Grid::covering(centre - DVec3::splat(radius + 2.0 * cell), centre + DVec3::splat(radius + 2.0 * cell), cell);
        let f = |p: DVec3| (p - centre).length() - radius;
        let values: Vec<f64> = grid.points().into_iter().map(f).collect();
        extract(&grid, &values, |c| bisect(c, 30, |points| points.iter().map(|&p| f(p) < 0.0).collect()))
    }

    /// A camera at `centre` looking at the origin (x right, y down, z forward).
    fn camera(centre: DVec3) -> Camera {
        let forward = (-centre).normalize();
        let right = forward.cross(DVec3::Y).normalize();
        let down = forward.cross(right);
        let camera_to_world = DMat4::from_cols(right.extend(0.0), down.extend(0.0), forward.extend(0.0), centre.extend(1.0));
        Camera { name: "c".into(), width: 64, height: 64, fx: 80.0, fy: 80.0, cx: 32.0, cy: 32.0, camera_to_world }
    }

    /// Whether the segment from `p` to `eye` passes through a ball (other than where it starts).
    fn blocked(p: DVec3, eye: DVec3, centre: DVec3, radius: f64) -> bool {
        let d = eye - p;
        let (a, b, c) = (d.dot(d), 2.0 * d.dot(p - centre), (p - centre).length_squared() - radius * radius);
        let disc = b * b - 4.0 * a * c;
        if disc <= 0.0 {
            return false;
        }
        let (t0, t1) = ((-b - disc.sqrt()) / (2.0 * a), (-b + disc.sqrt()) / (2.0 * a));
        (t0 > 1e-3 && t0 < 1.0) || (t1 > 1e-3 && t1 < 1.0)
    }

    /// Two balls, the smaller half hidden behind the larger: each point's verdict against rays
    /// to the camera cast at the analytic balls (an independent reference), away from the
    /// shadow's edge and the horizon, where a pixel decides.
    #[test]
    fn a_ball_behind_another_is_seen_only_where_analytic_rays_reach_it() {
        let (front, back) = ((DVec3::new(0.0, 0.0, 0.3), 0.25), (DVec3::new(0.15, 0.0, -0.3), 0.2));
        let eye = DVec3::new(0.0, 0.0, 3.0);
        let mesh = {
            let (a, b) = (sphere(front.0, front.1, 0.01), sphere(back.0, back.1, 0.01));
            let offset = a.vertices.len();
            Mesh {
                vertices: a.vertices.iter().chain(&b.vertices).copied().collect(),
                triangles: a.triangles.iter().copied().chain(b.triangles.iter().map(|t| t.map(|v| v + offset))).collect(),
            }
        };
        let seen = Seen::new(&mesh, &[camera(eye)]);
        let (mut checked, mut agreed, mut hidden) = (0, 0, 0);
        let mut stream = crate::random::Stream::new(3, 0, 0);
        for _ in 0..4000 {
            let (ball, other) = if stream.uniform() < 0.5 { (front, back) } else { (back, front) };
            let normal = DVec3::new(stream.uniform() - 0.5, stream.uniform() - 0.5, stream.uniform() - 0.5).normalize();
            let point = ball.0 + normal * ball.1;
            let facing = normal.dot((eye - point).normalize());
            // Clear of the horizon, and of the edge of the other ball's occlusion (a margin of
            // a few buffer pixels' footprints: 2 cm).
            let d = eye - point;
            let along = (other.0 - point).dot(d) / d.length_squared();
            let miss = (point + d * along.clamp(0.0, 1.0) - other.0).length() - other.1;
            if facing.abs() < 0.2 || miss.abs() < 0.02 {
                continue;
            }
            let truth = facing > 0.0 && !blocked(point, eye, other.0, other.1);
            checked += 1;
            hidden += usize::from(facing > 0.0 && !truth);
            agreed += usize::from(seen.sees(point, normal) == truth);
        }
        assert!(checked > 2000 && hidden > 100, "{checked} points checked, {hidden} hidden behind the other ball");
        assert_eq!(agreed, checked, "the depth buffer against analytic rays");
    }
}
