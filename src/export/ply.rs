//! `umbra export-gaussians`: the fitted shadow Gaussians posed in one frame, in the binary PLY
//! layout of 3D Gaussian splatting, so splat viewers show the shadow proxy: `x y z`, `nx ny nz`
//! (zero), `f_dc_0..2` (degree-0 spherical harmonics of a neutral grey: the Gaussians carry no
//! colour), `opacity` as a logit, `scale_0..2` as natural logs of the standard deviations (m),
//! `rot_0..3` as a unit quaternion (w, x, y, z) whose rotation's columns are the axes.
//!
//! A splat's opacity is one number where a Gaussian's is not: it is taken as the opacity of the
//! Gaussian's optical depth through its centre along a line as long as the geometric mean of its
//! axes, `tau = a sqrt(2 pi) (s1 s2 s3)^(1/3)` (`a` the peak density per metre as shadows use
//! it), so `opacity = 1 - exp(-tau)`.

use crate::shadow::PosedGaussian;
use glam::{DMat3, DQuat};

/// How every PLY `export-gaussians` writes begins: what lets a later export replace it.
pub const HEADER_START: &str = "ply\nformat binary_little_endian 1.0\ncomment umbra export-gaussians\n";

/// The properties of a vertex, in order (all `float`).
pub const PROPERTIES: [&str; 17] =
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"];

/// The least and most opacity written (a logit of +-13.8): a splat viewer's sigmoid stays finite.
const OPACITY_BOUND: f64 = 1e-6;

/// The optical depth a splat's opacity stands for (see the module's comment).
pub fn splat_optical_depth(g: &PosedGaussian) -> f64 {
    g.amplitude * (2.0 * std::f64::consts::PI).sqrt() * (g.scales.x * g.scales.y * g.scales.z).cbrt()
}

/// The logit of the opacity of optical depth `tau`: `ln(e^tau - 1)`, bounded.
fn opacity_logit(tau: f64) -> f64 {
    let opacity = (-(-tau).exp_m1()).clamp(OPACITY_BOUND, 1.0 - OPACITY_BOUND);
    (opacity / (1.0 - opacity)).ln()
}

/// The 17 values of one Gaussian's vertex.
fn vertex(g: &PosedGaussian) -> [f32; 17] {
    // A right-handed frame for the quaternion (the axes' order is free, a reflection is not).
    let axes = if g.axes.determinant() < 0.0 { DMat3::from_cols(g.axes.x_axis, g.axes.y_axis, -g.axes.z_axis) } else { g.axes };
    let q = DQuat::from_mat3(&axes).normalize();
    let s = g.scales.max(glam::DVec3::splat(f64::MIN_POSITIVE));
    let v =
        [g.mean.x, g.mean.y, g.mean.z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, opacity_logit(splat_optical_depth(g)), s.x.ln(), s.y.ln(), s.z.ln(), q.w, q.x, q.y, q.z];
    v.map(|x| x as f32)
}

/// The PLY file (binary little endian) of `gaussians`.
pub fn ply_bytes(gaussians: &[PosedGaussian], frame: usize) -> Vec<u8> {
    let mut header = format!("{HEADER_START}comment frame {frame}\nelement vertex {}\n", gaussians.len());
    for name in PROPERTIES {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str("end_header\n");
    let mut bytes = header.into_bytes();
    for g in gaussians {
        for value in vertex(g) {
            bytes.extend_from_slice(&value.to_le_bytes());
        }
    }
    bytes
}
