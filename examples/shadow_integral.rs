//! The public shadow API in a few lines: the exact optical depth of one Gaussian along a ray
//! segment (f64 and f32), and the transmittance of a posed set along many shadow rays.
//!
//! `cargo run --example shadow_integral`

use glam::{DMat3, DVec3};
use umbra::gaussians::PosedGaussian;
use umbra::shadow::{optical_depth, optical_depth_f32, ShadowCaster, ShadowRay};

fn main() {
    // An elongated Gaussian 2 m in front of the origin, tilted 30 degrees about Z.
    let axes = DMat3::from_rotation_z(30f64.to_radians());
    let columns = [axes.x_axis.to_array(), axes.y_axis.to_array(), axes.z_axis.to_array()];
    let (mean, scales, amplitude) = ([0.0, 0.0, 2.0], [0.05, 0.2, 0.05], 10.0);
    // A ray toward a sun (semi-infinite) and a segment ending at a point light 2 m away.
    let to_sun = optical_depth(mean, columns, scales, amplitude, [0.0; 3], [0.0, 0.0, 1.0], 0.0, f64::INFINITY);
    let to_lamp = optical_depth(mean, columns, scales, amplitude, [0.0; 3], [0.0, 0.0, 1.0], 0.0, 2.0);
    let f32_value =
        optical_depth_f32([0.0, 0.0, 2.0], columns.map(|c| c.map(|v| v as f32)), [0.05, 0.2, 0.05], 10.0, [0.0; 3], [0.0, 0.0, 1.0], 0.0, f32::INFINITY);
    println!("optical depth to the sun {to_sun:.9} (f32 {f32_value:.6}), to a lamp at the centre {to_lamp:.9} (half: {:.9})", to_sun / 2.0);
    println!("transmittance to the sun {:.6}", (-to_sun).exp());

    let gaussian = PosedGaussian { mean: DVec3::from_array(mean), axes, scales: DVec3::from_array(scales), amplitude };
    let caster = ShadowCaster::new(&[gaussian], 1e-6);
    let rays: Vec<ShadowRay> =
        (0..5).map(|k| ShadowRay { origin: [0.05 * k as f32, 0.0, 0.0], direction: [0.0, 0.0, 1.0], t0: 0.0, t1: f32::INFINITY }).collect();
    for (ray, t) in rays.iter().zip(caster.transmittance_all(&rays, true)) {
        println!("ray at x = {:.2} m: transmittance {t:.6}", ray.origin[0]);
    }
}
