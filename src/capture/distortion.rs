//! OpenCV's lens model (`k1 k2 k3` radial, `p1 p2` tangential) and its removal at import: each
//! pixel of the pinhole image takes the distorted image's colour where the lens put that ray.

use super::Intrinsics;
use crate::imageio::{Mask, RgbImage};
use rayon::prelude::*;

/// A camera's lens distortion (`model` as the capture names it; zero coefficients: none).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Distortion {
    pub model: String,
    pub k1: f64,
    pub k2: f64,
    pub k3: f64,
    pub p1: f64,
    pub p2: f64,
}

impl Distortion {
    pub fn is_none(&self) -> bool {
        [self.k1, self.k2, self.k3, self.p1, self.p2].iter().all(|c| *c == 0.0)
    }

    /// Where the lens takes the normalised pinhole point `(x, y)` (OpenCV's `projectPoints`).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        (x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x), y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y)
    }
}

impl Intrinsics {
    /// What makes this camera one no image can come from, if anything: a field of view narrower
    /// than `LEAST_FIELD_OF_VIEW` or wider than `MOST_FIELD_OF_VIEW` degrees across either side
    /// (a focal length of 1e-12 projects everything onto one column), a principal point more
    /// than an image's size from its centre, or a lens model that folds inside the image.
    pub fn problem(&self, distortion: &Distortion) -> Option<String> {
        let fov = |focal: f64, side: usize| 2.0 * (side as f64 / (2.0 * focal)).atan().to_degrees();
        for (axis, focal, side) in [("x", self.fx, self.width), ("y", self.fy, self.height)] {
            let degrees = fov(focal, side);
            if !(LEAST_FIELD_OF_VIEW..=MOST_FIELD_OF_VIEW).contains(&degrees) {
                return Some(format!(
                    "a focal length of {focal} pixels over {side} pixels is a field of view of {degrees:.3} degrees in {axis}: a camera sees {LEAST_FIELD_OF_VIEW} to {MOST_FIELD_OF_VIEW} (are the intrinsics in pixels?)"
                ));
            }
        }
        let (w, h) = (self.width as f64, self.height as f64);
        if !((self.cx - 0.5 * w).abs() <= w && (self.cy - 0.5 * h).abs() <= h) {
            return Some(format!("the principal point ({}, {}) lies more than the image's size from the centre of a {w}x{h} image", self.cx, self.cy));
        }
        let corner =
            [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)].iter().map(|&(x, y)| ((x - self.cx) / self.fx).hypot((y - self.cy) / self.fy)).fold(0.0, f64::max);
        distortion.fold_radius(corner).map(|r| {
            format!(
                "the lens model (k1 {}, k2 {}, k3 {}) folds back on itself at {:.0}% of the way to the image's corner: it maps two directions to one pixel",
                distortion.k1,
                distortion.k2,
                distortion.k3,
                100.0 * r / corner
            )
        })
    }
}

/// The narrowest field of view a camera of a capture has (degrees): a long telephoto's.
pub const LEAST_FIELD_OF_VIEW: f64 = 0.5;

/// The widest a pinhole (undistorted) field of view can be (degrees): 180 is a plane.
pub const MOST_FIELD_OF_VIEW: f64 = 175.0;

impl Distortion {
    /// The first normalised radius up to `reach` where the radial model stops moving outward
    /// (`d/dr [r (1 + k1 r^2 + k2 r^4 + k3 r^6)] <= 0`): past it two rays land on one pixel.
    pub fn fold_radius(&self, reach: f64) -> Option<f64> {
        let slope = |r: f64| {
            let r2 = r * r;
            1.0 + r2 * (3.0 * self.k1 + r2 * (5.0 * self.k2 + r2 * 7.0 * self.k3))
        };
        let steps = 2048;
        (0..=steps).map(|i| reach * i as f64 / steps as f64).find(|&r| !(slope(r) > 0.0))
    }
}

/// The distorted image's continuous pixel position seen by pinhole pixel `(i, j)`'s centre.
fn source(camera: &Intrinsics, distortion: &Distortion, i: usize, j: usize) -> (f64, f64) {
    let x = (i as f64 + 0.5 - camera.cx) / camera.fx;
    let y = (j as f64 + 0.5 - camera.cy) / camera.fy;
    let (xd, yd) = distortion.distort(x, y);
    (camera.fx * xd + camera.cx, camera.fy * yd + camera.cy)
}

/// `image` (taken through `distortion`) as the pinhole camera of the same intrinsics sees it:
/// bilinear between the four pixels around each source position; outside the image, black.
pub fn undistort_colour(image: &RgbImage, camera: &Intrinsics, distortion: &Distortion) -> RgbImage {
    let (w, h) = (image.width, image.height);
    let pixels = (0..w * h)
        .into_par_iter()
        .map(|p| {
            let (u, v) = source(camera, distortion, p % w, p / w);
            // Pixel centres sit at +0.5.
            let (fx, fy) = (u - 0.5, v - 0.5);
            let (x0, y0) = (fx.floor(), fy.floor());
            let (tx, ty) = ((fx - x0) as f32, (fy - y0) as f32);
            let at = |x: f64, y: f64| -> [f32; 3] {
                if x < 0.0 || y < 0.0 || x >= w as f64 || y >= h as f64 {
                    [0.0; 3]
                } else {
                    image.pixels[y as usize * w + x as usize]
                }
            };
            let (a, b, c, d) = (at(x0, y0), at(x0 + 1.0, y0), at(x0, y0 + 1.0), at(x0 + 1.0, y0 + 1.0));
            std::array::from_fn(|k| (a[k] * (1.0 - tx) + b[k] * tx) * (1.0 - ty) + (c[k] * (1.0 - tx) + d[k] * tx) * ty)
        })
        .collect();
    RgbImage { width: w, height: h, pixels }
}

/// `mask` as the pinhole camera sees it: the nearest source pixel's value (outside: background).
pub fn undistort_mask(mask: &Mask, camera: &Intrinsics, distortion: &Distortion) -> Mask {
    let (w, h) = (mask.width, mask.height);
    let foreground = (0..w * h)
        .into_par_iter()
        .map(|p| {
            let (u, v) = source(camera, distortion, p % w, p / w);
            let (x, y) = (u.floor(), v.floor());
            x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64 && mask.foreground[y as usize * w + x as usize]
        })
        .collect::<Vec<bool>>();
    Mask { width: w, height: h, foreground: foreground.into() }
}
