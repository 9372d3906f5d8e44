//! The (ray, Gaussian) optical-depth kernel over eight Gaussians at once: structure-of-arrays
//! blocks, an erfc and an exp written as branch-free lane arithmetic (so the compiler turns
//! every step into vector instructions), an AVX-512 or AVX2 build chosen at run time where the
//! CPU has it, exponentials below e^-30 taken as zero (they kept subnormal numbers in the
//! arithmetic, which the CPU handles by microcode, 1.8x slower), and a per-lane error estimate that hands any pair the f32 lanes could get wrong to the scalar
//! integral (`integral::optical_depth_whitened`, f64 geometry), so accuracy is what it was.
//!
//! The maths is the scalar integral's (see `integral`): re-anchor the ray at its closest
//! approach to the mean, whiten, and take `A exp(-m^2/2) sqrt(pi/2) / |W d| (erf(b) - erf(a))`
//! with the difference of erfs taken on the tail side. Two things differ and are why the
//! lanes can be wrong where the scalar path is not: the geometry is f32 (a far-away origin or a
//! needle-thin Gaussian loses digits), and short intervals (the scalar path's Gauss-Legendre
//! case) are not handled here at all. Both are detected per lane and sent back.

use super::integral::{optical_depth_whitened, WhitenedGaussian};
use super::ray::{segment_within, ShadowRay};

/// Gaussians per block: two SSE registers, one AVX register.
pub const LANES: usize = 8;

/// A lane whose estimated relative error stays below this is accepted whatever its size (the
/// accuracy tests ask for 1e-4: a margin of 5 over an estimate that is itself an overestimate).
const ACCEPTED_RELATIVE_ERROR: f32 = 2e-5;

/// Eight Gaussians, structure of arrays. Unused lanes are marked absent and never integrated.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(32))]
pub struct Block {
    mean: [[f32; LANES]; 3],
    /// `whiten[k][j]`: component j of the Gaussian's k-th axis divided by its k-th scale.
    whiten: [[[f32; LANES]; 3]; 3],
    amplitude: [f32; LANES],
    /// The largest inverse scale (1 / the thinnest axis), for the error estimate.
    inverse_min_scale: [f32; LANES],
    /// Squared distance beyond which the lane is culled; negative: always culled.
    cull_radius_squared: [f32; LANES],
    /// 1 for a lane that holds a Gaussian, 0 for the padding of the last block.
    present: [f32; LANES],
    /// A sphere holding every lane's cull sphere (radius squared negative: all lanes culled).
    centre: [f32; 3],
    radius_squared: f32,
}

impl Block {
    /// Packs up to eight Gaussians and their cull radii.
    pub fn pack(gaussians: &[WhitenedGaussian<f32>], cull_radius_squared: &[f32]) -> Self {
        let mut b = Block { cull_radius_squared: [-1.0; LANES], ..Default::default() };
        for (i, (g, &r2)) in gaussians.iter().zip(cull_radius_squared).take(LANES).enumerate() {
            for j in 0..3 {
                b.mean[j][i] = g.mean[j];
                for k in 0..3 {
                    b.whiten[k][j][i] = (g.axes[k][j] as f64 * g.inverse_scales[k] as f64) as f32;
                }
            }
            b.amplitude[i] = g.amplitude;
            b.inverse_min_scale[i] = g.inverse_scales.iter().fold(0.0f32, |m, &s| m.max(s));
            b.cull_radius_squared[i] = r2;
            b.present[i] = 1.0;
        }
        let kept: Vec<([f32; 3], f32)> = gaussians.iter().zip(cull_radius_squared).filter(|(_, &r2)| r2 >= 0.0).map(|(g, &r2)| (g.mean, r2.sqrt())).collect();
        if kept.is_empty() {
            b.radius_squared = -1.0;
        } else {
            let n = kept.len() as f32;
            b.centre = [0, 1, 2].map(|j| kept.iter().map(|(m, _)| m[j]).sum::<f32>() / n);
            let radius = kept.iter().map(|(m, r)| (0..3).map(|j| (m[j] - b.centre[j]).powi(2)).sum::<f32>().sqrt() + r).fold(0.0f32, f32::max);
            // Rounded up so that no lane's own test can pass where the block's fails.
            b.radius_squared = (radius * (1.0 + 1e-5)).powi(2);
        }
        b
    }
}

/// Consecutive blocks under one bounding sphere (Morton order keeps them near each other):
/// with culling, a ray that misses it skips them all, so that a ray tests about sqrt(blocks)
/// spheres and the blocks of the groups it meets instead of every block's sphere. A two-level
/// hierarchy; results are those of the blocks alone, since a group's sphere holds theirs.
#[derive(Clone, Copy, Debug)]
pub struct Group {
    centre: [f32; 3],
    /// Negative: every lane of every block in the group is culled.
    radius_squared: f32,
    first: usize,
    end: usize,
}

/// `blocks` in groups of `size` (at least 1).
pub fn group(blocks: &[Block], size: usize) -> Vec<Group> {
    let size = size.max(1);
    (0..blocks.len())
        .step_by(size)
        .map(|first| {
            let end = (first + size).min(blocks.len());
            let kept: Vec<&Block> = blocks[first..end].iter().filter(|b| b.radius_squared >= 0.0).collect();
            if kept.is_empty() {
                return Group { centre: [0.0; 3], radius_squared: -1.0, first, end };
            }
            let n = kept.len() as f32;
            let centre = [0, 1, 2].map(|j| kept.iter().map(|b| b.centre[j]).sum::<f32>() / n);
            let radius =
                kept.iter().map(|b| (0..3).map(|j| (b.centre[j] - centre[j]).powi(2)).sum::<f32>().sqrt() + b.radius_squared.sqrt()).fold(0.0f32, f32::max);
            // A wider margin than a block's over its lanes (1e-5): the test is the same f32
            // arithmetic, but a group's sphere is larger, and a group that rounding culled
            // would take blocks the blocks' own tests keep.
            Group { centre, radius_squared: (radius * (1.0 + 1e-3)).powi(2), first, end }
        })
        .collect()
}

/// Blocks per group for `blocks` blocks: the square root balances the groups' tests against
/// the blocks' tests inside the groups a ray meets.
pub fn group_size(blocks: usize) -> usize {
    ((blocks as f64).sqrt().round() as usize).max(1)
}

/// What one ray collected from a run of blocks.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Collected {
    pub depth: f32,
    /// Pairs integrated (not culled).
    pub integrated: usize,
    /// Of those, pairs the lanes handed to the scalar integral.
    pub scalar: usize,
}

/// Sums the optical depth of every Gaussian in `blocks` along `ray`. `gaussians` is the same
/// set in block order (lane i of block k is `gaussians[k * LANES + i]`), for the lanes that
/// go back to the scalar integral; `budget` is the absolute error a lane may add. Runs the
/// fastest build this CPU has.
pub fn optical_depth(blocks: &[Block], groups: &[Group], gaussians: &[WhitenedGaussian<f32>], ray: &ShadowRay, cull: bool, budget: f32) -> Collected {
    optical_depth_built(kernel_build(), blocks, groups, gaussians, ray, cull, budget).unwrap_or_else(|| collect(blocks, groups, gaussians, ray, cull, budget))
}

/// `optical_depth` by one chosen build; `None` when this CPU cannot run it (so the tests can
/// pin every build the machine has to the others).
pub fn optical_depth_built(
    build: Build,
    blocks: &[Block],
    groups: &[Group],
    gaussians: &[WhitenedGaussian<f32>],
    ray: &ShadowRay,
    cull: bool,
    budget: f32,
) -> Option<Collected> {
    if !build.available() {
        return None;
    }
    match build {
        Build::Baseline => Some(collect(blocks, groups, gaussians, ray, cull, budget)),
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `available` has checked the CPU for the features the build enables.
        Build::Avx2 => Some(unsafe { optical_depth_avx2(blocks, groups, gaussians, ray, cull, budget) }),
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Build::Avx512 => Some(unsafe { optical_depth_avx512(blocks, groups, gaussians, ray, cull, budget) }),
        #[cfg(not(target_arch = "x86_64"))]
        _ => None,
    }
}

/// The builds of the kernel: one source compiled for three instruction sets. No step is fused
/// (no `mul_add`), so all three round alike and return the same bits (a test pins them).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Build {
    /// Eight lanes still fill only 256-bit registers, but AVX-512VL's 32 of them (against
    /// AVX2's 16) hold the block's live values without spilling them to the stack.
    Avx512,
    Avx2,
    Baseline,
}

impl Build {
    pub const ALL: [Build; 3] = [Build::Avx512, Build::Avx2, Build::Baseline];

    pub fn name(self) -> &'static str {
        match self {
            Build::Avx512 => "8 lanes, AVX-512",
            Build::Avx2 => "8 lanes, AVX2",
            Build::Baseline => "8 lanes, baseline ISA",
        }
    }

    /// Whether this CPU runs the build (std caches the detection).
    pub fn available(self) -> bool {
        match self {
            Build::Baseline => true,
            #[cfg(target_arch = "x86_64")]
            Build::Avx2 => std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma"),
            #[cfg(target_arch = "x86_64")]
            Build::Avx512 => Build::Avx2.available() && std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512vl"),
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }
}

/// The fastest build this CPU runs.
pub fn kernel_build() -> Build {
    Build::ALL.into_iter().find(|b| b.available()).unwrap_or(Build::Baseline)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn optical_depth_avx2(blocks: &[Block], groups: &[Group], gaussians: &[WhitenedGaussian<f32>], ray: &ShadowRay, cull: bool, budget: f32) -> Collected {
    collect(blocks, groups, gaussians, ray, cull, budget)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
fn optical_depth_avx512(blocks: &[Block], groups: &[Group], gaussians: &[WhitenedGaussian<f32>], ray: &ShadowRay, cull: bool, budget: f32) -> Collected {
    collect(blocks, groups, gaussians, ray, cull, budget)
}

#[inline(always)]
fn collect(blocks: &[Block], groups: &[Group], gaussians: &[WhitenedGaussian<f32>], ray: &ShadowRay, cull: bool, budget: f32) -> Collected {
    let mut out = Collected::default();
    let mut lanes = Lanes::default();
    let toward_infinity = ray.t1 == f32::INFINITY;
    // With culling, the blocks of a group whose sphere the ray misses are never looked at.
    let whole = [Group { centre: [0.0; 3], radius_squared: f32::INFINITY, first: 0, end: blocks.len() }];
    let groups = if cull && !groups.is_empty() { groups } else { &whole };
    let visited = groups
        .iter()
        .filter(|g| g.radius_squared == f32::INFINITY || segment_within(g.centre, ray, g.radius_squared))
        .flat_map(|g| g.first.min(blocks.len())..g.end.min(blocks.len()));
    for k in visited {
        let block = &blocks[k];
        if cull && !segment_within(block.centre, ray, block.radius_squared) {
            continue;
        }
        // A ray to a sun (t1 infinite) skips erfc(b) = 0: its own build of the block kernel.
        let any = match (toward_infinity, cull) {
            (true, true) => block_depth::<true, true>(block, ray, budget, &mut lanes),
            (true, false) => block_depth::<true, false>(block, ray, budget, &mut lanes),
            (false, true) => block_depth::<false, true>(block, ray, budget, &mut lanes),
            (false, false) => block_depth::<false, false>(block, ray, budget, &mut lanes),
        };
        if !any {
            continue;
        }
        // Sums over the lanes without a branch per lane; the rare lanes sent to the scalar
        // integral are visited one by one.
        let (mut depth, mut integrated, mut scalar) = (0.0f32, 0.0f32, 0.0f32);
        for i in 0..LANES {
            depth += lanes.depth[i] * (1.0 - lanes.scalar[i]);
            integrated += lanes.integrate[i];
            scalar += lanes.scalar[i];
        }
        out.depth += depth;
        out.integrated += integrated as usize;
        if scalar > 0.0 {
            out.scalar += scalar as usize;
            for i in (0..LANES).filter(|&i| lanes.scalar[i] != 0.0) {
                if let Some(g) = gaussians.get(k * LANES + i) {
                    out.depth += optical_depth_whitened(g, ray.origin, ray.direction, ray.t0, ray.t1);
                }
            }
        }
    }
    out
}

/// Per-lane results of one block: depth, and flags (1.0 or 0.0, so that they stay in vector
/// registers) for "integrate this lane" and "its depth must come from the scalar integral".
#[derive(Default)]
struct Lanes {
    depth: [f32; LANES],
    integrate: [f32; LANES],
    scalar: [f32; LANES],
}

/// One ray against one block; false when every lane is culled (nothing to read).
/// `TOWARD_INFINITY`: the caller has checked that the segment's end is infinite; `CULL`:
/// lanes whose cull sphere the segment misses are skipped. Both are compile-time so that each
/// combination is its own branch-free loop.
#[inline(always)]
fn block_depth<const TOWARD_INFINITY: bool, const CULL: bool>(b: &Block, ray: &ShadowRay, budget: f32, out: &mut Lanes) -> bool {
    let [ox, oy, oz] = ray.origin;
    let [dx, dy, dz] = ray.direction;
    let (t0, t1) = (ray.t0, ray.t1);
    let inverse_d2 = 1.0 / (dx * dx + dy * dy + dz * dz);
    // An empty or reversed segment integrates to zero (as in the scalar integral).
    let nonempty = if t1 > t0 { 1.0f32 } else { 0.0 };
    if CULL {
        let mut any = 0.0f32;
        for i in 0..LANES {
            let v = [b.mean[0][i] - ox, b.mean[1][i] - oy, b.mean[2][i] - oz];
            // The cull test of the scalar path (`ray::segment_within`), lane by lane.
            let along_world = (v[0] * dx + v[1] * dy + v[2] * dz).max(t0).min(t1);
            let e = [v[0] - along_world * dx, v[1] - along_world * dy, v[2] - along_world * dz];
            let r2 = b.cull_radius_squared[i];
            let inside = b.present[i] != 0.0 && r2 >= 0.0 && e[0] * e[0] + e[1] * e[1] + e[2] * e[2] <= r2;
            let integrate = if inside { 1.0 } else { 0.0 };
            out.integrate[i] = integrate;
            any += integrate;
        }
        if any == 0.0 {
            return false;
        }
    } else {
        out.integrate = b.present;
    }
    for i in 0..LANES {
        let v = [b.mean[0][i] - ox, b.mean[1][i] - oy, b.mean[2][i] - oz];
        // Closest approach s; `near` is the ray's point there, relative to the mean.
        let s = (v[0] * dx + v[1] * dy + v[2] * dz) * inverse_d2;
        let near = [s * dx - v[0], s * dy - v[1], s * dz - v[2]];
        let w_ = &b.whiten;
        // Written out (no `[0, 1, 2].map`): a closure the optimiser declines to inline would
        // turn the whole loop scalar.
        let whiten = |k: usize, x: [f32; 3]| w_[k][0][i] * x[0] + w_[k][1][i] * x[1] + w_[k][2][i] * x[2];
        let o = [whiten(0, near), whiten(1, near), whiten(2, near)];
        let w = [whiten(0, ray.direction), whiten(1, ray.direction), whiten(2, ray.direction)];
        let length = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
        let inverse_length = 1.0 / length;
        let along = (o[0] * w[0] + o[1] * w[1] + o[2] * w[2]) * inverse_length;
        let scale = along * inverse_length;
        let p = [o[0] - scale * w[0], o[1] - scale * w[1], o[2] - scale * w[2]];
        let m2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2];
        let a = ((t0 - s) * length + along) * std::f32::consts::FRAC_1_SQRT_2;
        let b_ = ((t1 - s) * length + along) * std::f32::consts::FRAC_1_SQRT_2;
        let (ta, gauss_a) = erfc_parts(a.abs());
        let (tb, gauss_b) = if TOWARD_INFINITY { (0.0, 0.0) } else { erfc_parts(b_.abs()) };
        let (ea, eb) = (ta * gauss_a, tb * gauss_b);
        let difference = if a >= 0.0 {
            ea - eb
        } else if b_ <= 0.0 {
            eb - ea
        } else {
            (1.0 - ea) + (1.0 - eb)
        };
        let peak = b.amplitude[i] * (SQRT_FRAC_PI_2 * inverse_length);
        let prefactor = peak * exp_or_zero(-0.5 * m2);
        let depth = prefactor * difference;

        // Error estimate. f32 rounding moves the whitened point by about eps times the
        // magnitudes it was computed from: the world offsets (the ray's anchor, |s| + |near|)
        // scaled by the thinnest axis, and the terms of a and b. An error delta in m moves
        // exp(-m^2/2) by a relative m delta; in a or b it moves erf(b) - erf(a) by
        // 2/sqrt(pi) exp(-x^2) delta, and exp(-x^2) <= 3.6 exp(P(t) - x^2) (P >= -1.27). The
        // whitened length carries eps times the thinnest axis's inverse scale over itself.
        let near_size = near[0].abs() + near[1].abs() + near[2].abs();
        let magnitude = b.inverse_min_scale[i] * (s.abs() + near_size) + along.abs() + length * (t0 - s).abs();
        let delta = f32::EPSILON * magnitude;
        let m = m2.sqrt();
        // exp and erfc themselves: their arguments (m^2/2, x^2) are f32 numbers, good to eps
        // times their size, on top of the approximations' own 3e-7 (exp) and 5e-7 (erfc).
        let relative = delta * m + 4.0 * f32::EPSILON * (b.inverse_min_scale[i] * inverse_length + m2) + 3e-7;
        let erfc_error = |e: f32, x: f32| e * (5e-7 + f32::EPSILON * (x * x).min(1e4));
        let tail = if TOWARD_INFINITY { 0.0 } else { erfc_error(eb, b_) };
        let error = depth * relative + prefactor * ((4.1 * delta) * (gauss_a + gauss_b) + erfc_error(ea, a) + tail) + CUT_DEPTH * peak;
        let half_width = 0.5 * (b_ - a);
        let centre = a + half_width;
        // The scalar path's short-interval case (Gauss-Legendre there; cancellation here).
        let short = half_width <= 0.25 && (centre * half_width).abs() <= 0.5;
        let trusted = (error <= ACCEPTED_RELATIVE_ERROR * depth || error <= budget) && (0.0..f32::INFINITY).contains(&depth);
        out.scalar[i] = if (short || !trusted) && nonempty != 0.0 { out.integrate[i] } else { 0.0 };
        out.depth[i] = if (0.0..f32::INFINITY).contains(&depth) { depth * out.integrate[i] * nonempty } else { 0.0 };
    }
    true
}

const SQRT_FRAC_PI_2: f32 = 1.253_314_1;

/// erfc(x) for x >= 0 (x = +inf gives 0) by the Chebyshev fit of Numerical Recipes (Press et
/// al., "erfcc": relative error below 1.2e-7 for every x >= 0), `t exp(-x^2 + P(t))` with
/// `t = 1 / (1 + x/2)`: one division, one exp, no branch.
#[inline(always)]
pub fn erfc_nonnegative(x: f32) -> f32 {
    let (t, exponent) = erfc_exponent(x);
    t * exp(exponent)
}

/// erfc(x) as the kernel takes it, in two factors: `t` and `exp(P(t) - x^2)` (the second also
/// bounds exp(-x^2)), zero below e^-30 (`NEGLIGIBLE_EXPONENT`).
#[inline(always)]
fn erfc_parts(x: f32) -> (f32, f32) {
    let (t, exponent) = erfc_exponent(x);
    (t, exp_or_zero(exponent))
}

/// `t = 1 / (1 + x/2)` and erfc's exponent `P(t) - x^2`.
#[inline(always)]
fn erfc_exponent(x: f32) -> (f32, f32) {
    let t = 1.0 / (1.0 + 0.5 * x);
    let p = -1.265_512_2
        + t * (1.000_023_7
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06 + t * (0.278_868_07 + t * (-1.135_204 + t * (1.488_515_9 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let x2 = x * x;
    // x^2 rounds by half an ulp (relative 6e-8), which at x = 9 (erfc 4e-37) is 5e-6 of the
    // exponent's argument's value: the error FMA would remove, kept for portability.
    (t, p - x2)
}

/// Exponents below which the kernel takes e^x as zero. Far from a ray a Gaussian's factors
/// fall toward f32's smallest numbers, and their products (a depth, a depth times the error
/// estimate's relative terms) below its normal range, where every vector operation on them
/// costs the CPU a microcode assist: on a body's sun rays the kernel ran 1.8x slower for it.
/// Above e^-30 each factor, and each product the kernel forms, stays normal for amplitudes
/// down to 1e-5; what the cut drops is in the error estimate (`CUT_DEPTH`).
const NEGLIGIBLE_EXPONENT: f32 = -30.0;
/// e^-30: the most a cut exponential was worth. The three a lane takes (the Gaussian's
/// profile across the ray and the two erfc tails) each move `erf(b) - erf(a)` (at most 2) by
/// at most this times the peak depth `A sqrt(pi/2) / |W d|`; 8 bounds their sum and the
/// error estimate's own use of the tails.
const CUT_DEPTH: f32 = 8.0 * 9.357_623e-14;

#[inline(always)]
fn exp_or_zero(x: f32) -> f32 {
    if x < NEGLIGIBLE_EXPONENT {
        0.0
    } else {
        exp(x)
    }
}

/// e^x for x <= 88 (larger overflows to infinity, below -87.3 returns 0: such depths are
/// below f32's normal range and add nothing a transmittance can show). Cody-Waite reduction
/// by ln 2 and a degree-7 polynomial on |r| <= ln(2)/2: relative error about 2 ulp.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    const LOG2_E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Round to nearest by adding and subtracting 1.5 * 2^23 (no rounding instruction needed).
    const SHIFTER: f32 = 12_582_912.0;
    // max then min, not clamp: a NaN comes out as the lower bound rather than NaN.
    #[allow(clippy::manual_clamp)]
    let clamped = x.max(-87.3).min(88.7);
    let shifted = clamped * LOG2_E + SHIFTER;
    let k = shifted - SHIFTER;
    let r = (clamped - k * LN2_HI) - k * LN2_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    // 2^k from its exponent bits; k is in [-126, 128]: split in two halves so 128 stays finite.
    // k itself is read from the low bits of `shifted` (an integer conversion `as i32` would
    // saturate lane by lane and keep the compiler from vectorising).
    // Wrapping arithmetic: no overflow is possible in this range, and a checked build (debug
    // assertions) would otherwise test every lane one by one.
    let ki = (shifted.to_bits() as i32).wrapping_sub(SHIFTER.to_bits() as i32);
    let half = ki >> 1;
    let scale_a = f32::from_bits((half.wrapping_add(127) as u32) << 23);
    let scale_b = f32::from_bits((ki.wrapping_sub(half).wrapping_add(127) as u32) << 23);
    let value = p * scale_a * scale_b;
    if x < -87.3 {
        0.0
    } else if x > 88.7 {
        f32::INFINITY
    } else {
        value
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn erfc_matches_libm_to_its_documented_accuracy() {
        let mut worst = 0.0f64;
        for i in 0..=20_000 {
            let x = i as f64 * 9.0 / 20_000.0;
            let got = erfc_nonnegative(x as f32) as f64;
            // The reference at the f32 input, so input rounding is not counted.
            let reference = libm::erfc(x as f32 as f64);
            // The bound the kernel's error estimate uses: 5e-7, plus x^2 rounded to f32.
            let bound = 5e-7 + f32::EPSILON as f64 * x * x;
            worst = worst.max((got - reference).abs() / reference / bound);
        }
        assert!(worst <= 1.0, "erfc error {worst} times its bound");
        assert_eq!(erfc_nonnegative(f32::INFINITY), 0.0);
        assert_eq!(erfc_nonnegative(12.0), 0.0);
    }

    #[test]
    fn exp_matches_libm_over_its_range() {
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let x = -87.0 + i as f64 * (175.0 / 200_000.0);
            let x32 = x as f32;
            let reference = (x32 as f64).exp();
            worst = worst.max((exp(x32) as f64 - reference).abs() / reference);
        }
        assert!(worst < 3e-7, "exp relative error {worst:e}");
        assert_eq!(exp(-200.0), 0.0);
        assert_eq!(exp(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp(100.0), f32::INFINITY);
        assert!((exp(0.0) - 1.0).abs() < 1e-7);
    }
}
