//! Gaussian shadow casting: the closed-form optical depth of anisotropic Gaussians along ray
//! segments and the transmittance `exp(-sum tau)` that makes shadows. One scalar implementation
//! (`integral`, generic over f32/f64) serves the public API and is the reference of the CPU
//! path's eight-lane kernel (`lanes`); the burn tensor
//! path (`tensor`) applies the same formulas to batches and is pinned to the scalar one by tests.

mod cpu;
mod integral;
pub mod lanes;
mod ray;
pub mod real;
pub mod tensor;

pub use cpu::{own_shares, transmittance_f64, transmittance_f64_from, ShadowCaster, OWN_SHARE_FLOOR};
use glam::{DMat3, DVec3};
pub use ray::ShadowRay;

pub use integral::{erf_difference, optical_depth, optical_depth_f32, optical_depth_whitened, WhitenedGaussian, MIN_SCALE};

/// A Gaussian in world space (a `gaussians::GaussianSet` posed): what the integral casts
/// shadows with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PosedGaussian {
    pub mean: DVec3,
    /// Columns are the Gaussian's axes in world space.
    pub axes: DMat3,
    pub scales: DVec3,
    pub amplitude: f64,
}

impl PosedGaussian {
    pub fn rotation_columns(&self) -> [[f64; 3]; 3] {
        [self.axes.x_axis.to_array(), self.axes.y_axis.to_array(), self.axes.z_axis.to_array()]
    }

    /// The density at a world point.
    pub fn density(&self, x: DVec3) -> f64 {
        self.log_density(x).exp()
    }

    /// The logarithm of the density at a world point, finite however far it lies.
    pub fn log_density(&self, x: DVec3) -> f64 {
        let local = self.axes.transpose() * (x - self.mean);
        let whitened = local / self.scales.max(DVec3::splat(MIN_SCALE));
        self.amplitude.ln() - 0.5 * whitened.length_squared()
    }
}
