//! Gaussian shadow casting: the closed-form optical depth of anisotropic Gaussians along ray
//! segments and the transmittance `exp(-sum tau)` that makes shadows. One scalar implementation
//! (`integral`, generic over f32/f64) serves the public API and is the reference of the CPU
//! path's eight-lane kernel (`lanes`); the burn tensor
//! path (`tensor`) applies the same formulas to batches and is pinned to the scalar one by tests.

mod cpu;
mod integral;
pub mod lanes;
pub mod real;
pub mod tensor;

pub use cpu::{transmittance_f64, ShadowCaster, ShadowRay};
pub use integral::{erf_difference, optical_depth, optical_depth_f32, optical_depth_whitened, WhitenedGaussian, MIN_SCALE};
