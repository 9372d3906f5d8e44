//! The scalar type the shadow maths is written over: one implementation, instantiated for f64
//! (reference and public API) and f32 (hot loops: f32 storage and f32 erf/erfc/exp, with the
//! cheap geometry in f64 because scalar f64 arithmetic costs the same as f32 and a needle-thin
//! Gaussian metres long needs it). erf and erfc come from `libm` (musl's implementations,
//! accurate to about one ulp), not from polynomial fits.

use std::ops::{Add, Div, Mul, Neg, Sub};

pub trait Real:
    Copy
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + std::fmt::Debug
    + Send
    + Sync
    + 'static
{
    const ZERO: Self;
    const ONE: Self;
    /// Gauss-Legendre nodes and weights on [-1, 1] used for short segments (see `erf_difference`).
    const LEGENDRE: &'static [(f64, f64)];
    fn of(v: f64) -> Self;
    fn to_f64(self) -> f64;
    fn sqrt(self) -> Self;
    fn exp(self) -> Self;
    fn abs(self) -> Self;
    fn erf(self) -> Self;
    fn erfc(self) -> Self;
    fn is_finite(self) -> bool;
    /// `origin + s * direction - mean` in f64: the offset of the ray point at `s` from a
    /// Gaussian's mean, without losing the digits that a far-away origin would cancel.
    fn offset(origin: Self, s: f64, direction: Self, mean: Self) -> f64;
}

/// 8-point Gauss-Legendre (exact for degree 15): f64 relative error < 1e-15 on our short segments.
const LEGENDRE_8: [(f64, f64); 8] = [
    (-0.960_289_856_497_536_3, 0.101_228_536_290_376_26),
    (-0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (-0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (-0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (0.960_289_856_497_536_3, 0.101_228_536_290_376_26),
];

/// 5-point Gauss-Legendre (exact for degree 9): relative error < 1e-8 there, below f32's epsilon.
const LEGENDRE_5: [(f64, f64); 5] = [
    (-0.906_179_845_938_664, 0.236_926_885_056_189_1),
    (-0.538_469_310_105_683_1, 0.478_628_670_499_366_5),
    (0.0, 0.568_888_888_888_888_9),
    (0.538_469_310_105_683_1, 0.478_628_670_499_366_5),
    (0.906_179_845_938_664, 0.236_926_885_056_189_1),
];

impl Real for f64 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    const LEGENDRE: &'static [(f64, f64)] = &LEGENDRE_8;
    fn of(v: f64) -> Self {
        v
    }
    fn to_f64(self) -> f64 {
        self
    }
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
    fn exp(self) -> Self {
        f64::exp(self)
    }
    fn abs(self) -> Self {
        f64::abs(self)
    }
    fn erf(self) -> Self {
        libm::erf(self)
    }
    fn erfc(self) -> Self {
        libm::erfc(self)
    }
    fn is_finite(self) -> bool {
        f64::is_finite(self)
    }
    fn offset(origin: Self, s: f64, direction: Self, mean: Self) -> f64 {
        s.mul_add(direction, origin) - mean
    }
}

impl Real for f32 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    const LEGENDRE: &'static [(f64, f64)] = &LEGENDRE_5;
    fn of(v: f64) -> Self {
        v as f32
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
    fn sqrt(self) -> Self {
        f32::sqrt(self)
    }
    fn exp(self) -> Self {
        f32::exp(self)
    }
    fn abs(self) -> Self {
        f32::abs(self)
    }
    fn erf(self) -> Self {
        libm::erff(self)
    }
    fn erfc(self) -> Self {
        libm::erfcf(self)
    }
    fn is_finite(self) -> bool {
        f32::is_finite(self)
    }
    fn offset(origin: Self, s: f64, direction: Self, mean: Self) -> f64 {
        // f32 inputs in f64 arithmetic: the sums lose nothing an f32 result could keep.
        (origin as f64 + s * direction as f64) - mean as f64
    }
}
