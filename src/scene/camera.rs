//! Pinhole cameras in OpenCV axes (+X right, +Y down, +Z forward): rays through pixel centres
//! `(i + 0.5, j + 0.5)` and projection of world points to pixels.

use glam::{DMat3, DMat4, DVec2, DVec3};

#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub name: String,
    pub width: usize,
    pub height: usize,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub camera_to_world: DMat4,
}

/// A ray with a unit direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: DVec3,
    pub direction: DVec3,
}

impl Ray {
    pub fn at(&self, t: f64) -> DVec3 {
        self.origin + self.direction * t
    }
}

impl Camera {
    pub fn centre(&self) -> DVec3 {
        self.camera_to_world.w_axis.truncate()
    }

    /// The ray through the centre of pixel column `i`, row `j`.
    pub fn pixel_ray(&self, i: usize, j: usize) -> Ray {
        self.ray_through(DVec2::new(i as f64 + 0.5, j as f64 + 0.5))
    }

    /// The ray through a continuous pixel position (x right, y down, pixel corners at integers).
    pub fn ray_through(&self, pixel: DVec2) -> Ray {
        let local = DVec3::new((pixel.x - self.cx) / self.fx, (pixel.y - self.cy) / self.fy, 1.0);
        let direction = self.camera_to_world.transform_vector3(local).normalize();
        Ray { origin: self.centre(), direction }
    }

    /// Camera-space coordinates of a world point (z is the depth along the optical axis).
    pub fn to_camera(&self, world: DVec3) -> DVec3 {
        let linear = DMat3::from_mat4(self.camera_to_world);
        linear.inverse() * (world - self.centre())
    }

    /// The continuous pixel position of a world point, `None` behind the camera.
    pub fn project(&self, world: DVec3) -> Option<DVec2> {
        let c = self.to_camera(world);
        if c.z <= 1e-12 {
            return None;
        }
        Some(DVec2::new(self.fx * c.x / c.z + self.cx, self.fy * c.y / c.z + self.cy))
    }

    /// The same camera with a `width x height` image: the focal lengths and principal point
    /// scaled with each side, so every world point lands at the same fraction of the image.
    pub fn resized(&self, width: usize, height: usize) -> Self {
        let (sx, sy) = (width as f64 / self.width as f64, height as f64 / self.height as f64);
        Self { width, height, fx: self.fx * sx, fy: self.fy * sy, cx: self.cx * sx, cy: self.cy * sy, ..self.clone() }
    }

    /// A camera at `eye` looking at `target`, image +Y pointing as close to world -`up` as possible.
    pub fn look_at(name: &str, eye: DVec3, target: DVec3, up: DVec3, width: usize, height: usize, focal: f64) -> Self {
        let forward = (target - eye).normalize();
        let right = forward.cross(up).normalize();
        let down = forward.cross(right);
        let camera_to_world = DMat4::from_cols(right.extend(0.0), down.extend(0.0), forward.extend(0.0), eye.extend(1.0));
        Self { name: name.into(), width, height, fx: focal, fy: focal, cx: width as f64 / 2.0, cy: height as f64 / 2.0, camera_to_world }
    }
}

/// The world's up as the cameras show it. A camera that looks down at a body is pitched, so
/// its own up leans toward the body, but its image rows stay level (no roll): every camera's
/// right axis is horizontal, and up is the direction across all of them (the cross products of
/// pairs of right axes, each turned to the cameras' mean up, summed). With one camera, or all
/// facing one way, the cameras' mean up (a camera's image +Y points down).
pub fn world_up(cameras: &[Camera]) -> DVec3 {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centre_pixel_looks_forward_and_projects_back() {
        let cam = Camera::look_at("c", DVec3::new(0.0, 1.0, 3.0), DVec3::new(0.0, 1.0, 0.0), DVec3::Y, 64, 48, 80.0);
        let ray = cam.ray_through(DVec2::new(32.0, 24.0));
        assert!((ray.direction - DVec3::new(0.0, 0.0, -1.0)).length() < 1e-12);
        let pixel = cam.pixel_ray(10, 40);
        let p = cam.project(pixel.at(2.5)).unwrap();
        assert!((p - DVec2::new(10.5, 40.5)).length() < 1e-9);
    }

    #[test]
    fn a_resized_camera_sees_each_point_at_the_same_fraction_of_its_image() {
        let mut cam = Camera::look_at("c", DVec3::new(0.3, 1.0, 3.0), DVec3::new(0.0, 1.1, 0.0), DVec3::Y, 64, 48, 80.0);
        cam.cx = 30.5;
        cam.fy = 83.0;
        let big = cam.resized(256, 96);
        for p in [DVec3::new(0.2, 1.4, 0.1), DVec3::new(-0.4, 0.7, -0.3)] {
            let (a, b) = (cam.project(p).unwrap(), big.project(p).unwrap());
            assert!((a.x / 64.0 - b.x / 256.0).abs() < 1e-12 && (a.y / 48.0 - b.y / 96.0).abs() < 1e-12, "{a} {b}");
        }
        // The ray through a pixel's centre at the new size is the old one through that place.
        let ray = big.pixel_ray(100, 40);
        let old = cam.ray_through(DVec2::new(100.5 * 64.0 / 256.0, 40.5 * 48.0 / 96.0));
        assert!((ray.direction - old.direction).length() < 1e-12);
    }

    #[test]
    fn image_y_points_down_in_the_world() {
        let cam = Camera::look_at("c", DVec3::new(0.0, 1.0, 3.0), DVec3::new(0.0, 1.0, 0.0), DVec3::Y, 64, 64, 80.0);
        let above = cam.project(DVec3::new(0.0, 1.5, 0.0)).unwrap();
        let right = cam.project(DVec3::new(0.5, 1.0, 0.0)).unwrap();
        assert!(above.y < 32.0, "points above the centre land in upper rows");
        assert!(right.x > 32.0, "world +X is image right when looking down -Z");
    }
}
