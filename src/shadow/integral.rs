//! The closed-form integral of one anisotropic Gaussian's density along a ray segment.
//!
//! With the density `G(x) = A exp(-1/2 |W (x - mu)|^2)`, `W = S^-1 R^T` (S the per-axis scales,
//! R the rotation whose columns are the Gaussian's axes in world space), the ray
//! `x(t) = o + t d` whitens to `p(t) = W (o - mu) + t W d`. Along it the density is a 1D
//! Gaussian with mean `t* = -(W(o - mu)) . (W d) / |W d|^2` (that is
//! `d^T S^-1 (mu - o) / d^T S^-1 d`, the supplement's mean with its sign slip fixed),
//! standard deviation `1 / |W d|` and peak `A exp(-m^2 / 2)`, where `m` is the Mahalanobis
//! distance of closest approach. So the optical depth over `[t0, t1]` is
//!
//! `tau = A exp(-m^2/2) sqrt(pi/2) / |W d| (erf(b) - erf(a))`, `a, b = (t0, t1 - t*) |W d| / sqrt 2`.
//!
//! Numerically: the ray is first re-anchored at its point nearest the mean (so a far-away
//! origin loses no digits); `m^2` is the squared length of the perpendicular component,
//! never a difference of two large terms; `erf(b) - erf(a)` is taken on the tail side with
//! `erfc` and, for short intervals, by Gauss-Legendre quadrature of `exp(-u^2)` around the
//! interval's centre, so nothing cancels.

use super::real::Real;
use std::f64::consts::PI;

/// The smallest scale honoured; smaller (or zero, or negative) scales are clamped to it, so a
/// degenerate Gaussian is a very thin one rather than a division by zero.
pub const MIN_SCALE: f64 = 1e-9;

/// A Gaussian in world space, ready for ray queries. Axes and inverse scales are kept apart
/// (not multiplied into one whitening matrix) so that rounding to `R` adds no error that
/// cancels when a needle-thin Gaussian is whitened.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WhitenedGaussian<R: Real> {
    pub mean: [R; 3],
    /// Row k is the Gaussian's k-th axis in world space.
    pub axes: [[R; 3]; 3],
    pub inverse_scales: [R; 3],
    pub amplitude: R,
}

impl<R: Real> WhitenedGaussian<R> {
    /// From a world-space mean, rotation (columns are the Gaussian's axes), scales and amplitude.
    pub fn new(mean: [f64; 3], rotation_columns: [[f64; 3]; 3], scales: [f64; 3], amplitude: f64) -> Self {
        let inverse_scales = scales.map(|s| R::of(1.0 / if s > MIN_SCALE { s } else { MIN_SCALE }));
        Self { mean: mean.map(R::of), axes: rotation_columns.map(|c| c.map(R::of)), inverse_scales, amplitude: R::of(amplitude) }
    }
}

impl WhitenedGaussian<f32> {
    /// The density at a world point, all in f32: what a ray marcher at the closed form's
    /// precision evaluates (the shadow benchmark's comparison).
    pub fn density(&self, x: [f32; 3]) -> f32 {
        self.amplitude * (-0.5 * self.mahalanobis_squared(x)).exp()
    }

    /// The squared Mahalanobis distance of a world point from the mean.
    fn mahalanobis_squared(&self, x: [f32; 3]) -> f32 {
        let r = [x[0] - self.mean[0], x[1] - self.mean[1], x[2] - self.mean[2]];
        (0..3)
            .map(|k| {
                let u = (self.axes[k][0] * r[0] + self.axes[k][1] * r[1] + self.axes[k][2] * r[2]) * self.inverse_scales[k];
                u * u
            })
            .sum()
    }

    /// The logarithm of `density`, finite however far `x` lies.
    pub fn log_density(&self, x: [f32; 3]) -> f32 {
        self.amplitude.ln() - 0.5 * self.mahalanobis_squared(x)
    }
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Whitens a world vector: its component along each axis divided by that axis's scale.
fn whiten<R: Real>(g: &WhitenedGaussian<R>, v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|k| dot(g.axes[k].map(R::to_f64), v) * g.inverse_scales[k].to_f64())
}

/// `erf(b) - erf(a)` for `a <= b` (b may be +infinity), without cancellation, evaluated in
/// the precision of `R` from f64 limits (so a short interval keeps its width exactly).
pub fn erf_difference<R: Real>(a: f64, b: f64) -> R {
    if !(b > a) {
        return R::ZERO;
    }
    let half_width = (b - a) * 0.5;
    let centre = a + half_width;
    // Short interval: integrate exp(-u^2) = exp(-c^2) exp(-2 c v - v^2), v = u - c, by
    // Gauss-Legendre. The criteria keep the integrand's variation within e^2 over the interval,
    // where the rule is exact to far below the precision of R; outside them the tail-side
    // difference below loses at most a factor of about 2 in relative precision.
    if half_width <= 0.25 && (centre * half_width).abs() <= 0.5 {
        let (c, h) = (R::of(centre), R::of(half_width));
        let mut sum = R::ZERO;
        for &(node, weight) in R::LEGENDRE {
            let v = h * R::of(node);
            sum = sum + R::of(weight) * (-(R::of(2.0) * c * v + v * v)).exp();
        }
        return R::of(2.0 / PI.sqrt()) * (-(c * c)).exp() * h * sum;
    }
    let (a, b) = (R::of(a), R::of(b));
    if a >= R::ZERO {
        a.erfc() - b.erfc()
    } else if b <= R::ZERO {
        (-b).erfc() - (-a).erfc()
    } else {
        b.erf() + (-a).erf()
    }
}

/// Optical depth of a whitened Gaussian along `origin + t direction`, t in `[t0, t1]`.
/// `t1` may be `+infinity` (a ray toward a directional light); `t1 <= t0` gives 0. The
/// direction need not be unit length: t is then measured in units of its length.
#[inline]
pub fn optical_depth_whitened<R: Real>(g: &WhitenedGaussian<R>, origin: [R; 3], direction: [R; 3], t0: R, t1: R) -> R {
    if !(t1 > t0) {
        return R::ZERO;
    }
    let mean = g.mean.map(R::to_f64);
    let d = direction.map(R::to_f64);
    let d_squared = dot(d, d);
    // Re-anchor at the Euclidean closest approach s to the mean; the segment shifts by -s.
    let s = (0..3).map(|k| (mean[k] - origin[k].to_f64()) * d[k]).sum::<f64>() / d_squared;
    let near = [0, 1, 2].map(|k| R::offset(origin[k], s, direction[k], g.mean[k]));
    let o = whiten(g, near);
    let w = whiten(g, d);
    let length = dot(w, w).sqrt();
    let unit = w.map(|c| c / length);
    let along = dot(o, unit);
    let perpendicular = [o[0] - along * unit[0], o[1] - along * unit[1], o[2] - along * unit[2]];
    let mahalanobis_squared = dot(perpendicular, perpendicular);
    let a = ((t0.to_f64() - s) * length + along) * std::f64::consts::FRAC_1_SQRT_2;
    let b = ((t1.to_f64() - s) * length + along) * std::f64::consts::FRAC_1_SQRT_2;
    g.amplitude * R::of(-0.5 * mahalanobis_squared).exp() * R::of((PI / 2.0).sqrt() / length) * erf_difference::<R>(a, b)
}

/// Optical depth (the integral of density) of one Gaussian along a ray segment, in f64.
///
/// * `mean`: world-space centre; `rotation_columns`: the Gaussian's three axes in world space
///   (the columns of its rotation matrix); `scales`: standard deviation along each axis
///   (values below [`MIN_SCALE`] are clamped to it); `amplitude`: density at the centre (1/m).
/// * `origin`, `direction` (unit), segment `[t0, t1]` with `t1` possibly `f64::INFINITY`.
///
/// Exact up to rounding: relative error below 1e-9 over the ranges the tests sweep (scales
/// 1e-4..10 m, origins inside, behind and 1e3 m away, grazing and axis-parallel rays).
#[allow(clippy::too_many_arguments)] // a Gaussian's four parts and a segment's four, as the maths names them
pub fn optical_depth(
    mean: [f64; 3],
    rotation_columns: [[f64; 3]; 3],
    scales: [f64; 3],
    amplitude: f64,
    origin: [f64; 3],
    direction: [f64; 3],
    t0: f64,
    t1: f64,
) -> f64 {
    optical_depth_whitened(&WhitenedGaussian::<f64>::new(mean, rotation_columns, scales, amplitude), origin, direction, t0, t1)
}

/// The same integral in f32, as used by the rendering hot loops.
#[allow(clippy::too_many_arguments)] // as `optical_depth`
pub fn optical_depth_f32(
    mean: [f32; 3],
    rotation_columns: [[f32; 3]; 3],
    scales: [f32; 3],
    amplitude: f32,
    origin: [f32; 3],
    direction: [f32; 3],
    t0: f32,
    t1: f32,
) -> f32 {
    let g = WhitenedGaussian::<f32>::new(mean.map(f64::from), rotation_columns.map(|c| c.map(f64::from)), scales.map(f64::from), amplitude as f64);
    optical_depth_whitened(&g, origin, direction, t0, t1)
}
