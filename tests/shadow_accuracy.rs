//! The closed-form Gaussian ray integral against independent references: adaptive-free
//! composite Gauss-Legendre quadrature in f64 (nodes found by Newton's method here, positions
//! in double-double), statrs's erf as an oracle for libm's, and the f32 and burn paths against
//! the f64 one. Thousands of random cases plus stress ranges; never NaN or infinity.

mod common;

use glam::{DMat3, DQuat, DVec3};
use umbra::gaussians::PosedGaussian;
use umbra::random::Stream;
use umbra::shadow::{erf_difference, optical_depth, optical_depth_f32, transmittance_f64, ShadowCaster, ShadowRay};

/// Gauss-Legendre nodes and weights on [-1, 1] by Newton iteration on P_n.
fn legendre(n: usize) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for i in 0..n {
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut derivative = 0.0;
        for _ in 0..100 {
            let (mut p0, mut p1) = (1.0, x);
            for k in 2..=n {
                let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            derivative = n as f64 * (x * p1 - p0) / (x * x - 1.0);
            let dx = p1 / derivative;
            x -= dx;
            if dx.abs() < 1e-16 {
                break;
            }
        }
        out.push((x, 2.0 / ((1.0 - x * x) * derivative * derivative)));
    }
    out
}

fn two_sum(a: f64, b: f64) -> (f64, f64) {
    let s = a + b;
    let bb = s - a;
    (s, (a - (s - bb)) + (b - bb))
}

fn two_product(a: f64, b: f64) -> (f64, f64) {
    let p = a * b;
    (p, a.mul_add(b, -p))
}

struct Case {
    mean: DVec3,
    axes: DMat3,
    scales: DVec3,
    amplitude: f64,
    origin: DVec3,
    direction: DVec3,
    t0: f64,
    t1: f64,
}

impl Case {
    fn closed_form(&self) -> f64 {
        let cols = [self.axes.x_axis.to_array(), self.axes.y_axis.to_array(), self.axes.z_axis.to_array()];
        optical_depth(self.mean.to_array(), cols, self.scales.to_array(), self.amplitude, self.origin.to_array(), self.direction.to_array(), self.t0, self.t1)
    }

    /// Quadrature of the density along the ray, independent of the closed form's algebra.
    fn quadrature(&self, nodes: &[(f64, f64)]) -> f64 {
        let inverse_covariance = |v: DVec3| -> f64 { (0..3).map(|k| (self.axes.col(k).dot(v) / self.scales[k]).powi(2)).sum() };
        let offset = self.origin - self.mean;
        // Where the mass is along the ray (only used to place the integration window).
        let mut quadratic = 0.0;
        let mut linear = 0.0;
        for k in 0..3 {
            let axis = self.axes.col(k);
            let s2 = self.scales[k] * self.scales[k];
            quadratic += axis.dot(self.direction).powi(2) / s2;
            linear += axis.dot(self.direction) * axis.dot(offset) / s2;
        }
        let centre = -linear / quadratic;
        let sigma = 1.0 / quadratic.sqrt();
        let (u0, u1) = (self.t0 - centre, self.t1 - centre);
        let lo = u0.max(-40.0 * sigma);
        let hi = u1.min(lo.max(0.0) + 40.0 * sigma);
        #[allow(clippy::neg_cmp_op_on_partial_ord)] // NaN bounds too: as in the library
        if !(hi > lo) {
            return 0.0;
        }
        // x(t) - mean at t = centre + u, in double-double so that a far origin cancels exactly.
        let position = |u: f64| -> DVec3 {
            let mut v = [0.0; 3];
            #[allow(clippy::needless_range_loop)] // one index into four arrays
            for i in 0..3 {
                let (a, a_err) = two_sum(self.origin[i], -self.mean[i]);
                let (b, b_err) = two_product(centre, self.direction[i]);
                let (s, s_err) = two_sum(a, b);
                v[i] = s + (s_err + a_err + b_err + u * self.direction[i]);
            }
            DVec3::from_array(v)
        };
        let panels = (((hi - lo) / (0.5 * sigma)).ceil() as usize).clamp(1, 4000);
        let width = (hi - lo) / panels as f64;
        let mut total = 0.0;
        for p in 0..panels {
            let mid = lo + (p as f64 + 0.5) * width;
            for &(x, w) in nodes {
                let u = mid + 0.5 * width * x;
                total += w * 0.5 * width * self.amplitude * (-0.5 * inverse_covariance(position(u))).exp();
            }
        }
        total
    }
}

fn log_uniform(s: &mut Stream, lo: f64, hi: f64) -> f64 {
    (lo.ln() + (hi.ln() - lo.ln()) * s.uniform()).exp()
}

fn unit(s: &mut Stream) -> DVec3 {
    loop {
        let v = DVec3::new(s.uniform() * 2.0 - 1.0, s.uniform() * 2.0 - 1.0, s.uniform() * 2.0 - 1.0);
        if v.length_squared() > 1e-4 && v.length_squared() <= 1.0 {
            return v.normalize();
        }
    }
}

/// Random Gaussians and rays over the stress ranges of the issue.
fn cases(n: usize, seed: u64) -> Vec<(String, Case)> {
    let mut s = Stream::new(seed, 1, 2);
    let mut out = Vec::new();
    for i in 0..n {
        let scales = DVec3::new(log_uniform(&mut s, 1e-4, 10.0), log_uniform(&mut s, 1e-4, 10.0), log_uniform(&mut s, 1e-4, 10.0));
        let scales = if i % 3 == 0 { DVec3::splat(scales.x) * DVec3::new(1.0, 1.5, 0.7) } else { scales };
        let rotation = DQuat::from_axis_angle(unit(&mut s), s.uniform() * std::f64::consts::TAU);
        let axes = DMat3::from_quat(rotation);
        let mean = (unit(&mut s)) * s.uniform() * 3.0;
        let amplitude = log_uniform(&mut s, 1e-2, 1e3);
        let longest = axes.col(if scales.x >= scales.y && scales.x >= scales.z {
            0
        } else if scales.y >= scales.z {
            1
        } else {
            2
        });
        let reach = scales.max_element();
        let kind = i % 8;
        let (name, origin, direction) = match kind {
            0 => ("inside", mean + axes * (scales * DVec3::new(s.uniform() - 0.5, s.uniform() - 0.5, s.uniform() - 0.5)), unit(&mut s)),
            1 => {
                // Behind: the ray points away from the Gaussian.
                let away = unit(&mut s);
                ("behind", mean + away * reach * (1.0 + 3.0 * s.uniform()), (away + unit(&mut s) * 0.3).normalize())
            }
            2 => {
                let d = unit(&mut s);
                let miss = axes * (scales * unit(&mut s) * 2.0);
                ("far 1e3 m", mean - d * 1e3 + miss - d * miss.dot(d), d)
            }
            3 => {
                // Grazing: passes 3-6 standard deviations from the centre.
                let d = unit(&mut s);
                let side = d.any_orthonormal_vector();
                let sigma_side = 1.0 / (0..3).map(|k| (axes.col(k).dot(side) / scales[k]).powi(2)).sum::<f64>().sqrt();
                ("grazing", mean + side * sigma_side * (3.0 + 3.0 * s.uniform()) - d * reach * 5.0, d)
            }
            4 => ("parallel to longest axis", mean - longest * reach * (2.0 + s.uniform()) + axes * (scales * unit(&mut s) * 0.5), longest),
            5 => ("axis-aligned ray", mean + DVec3::new(0.0, 0.0, -2.0 * reach) + axes * (scales * unit(&mut s)), DVec3::Z),
            _ => ("random", mean + unit(&mut s) * reach * 4.0 * s.uniform(), unit(&mut s)),
        };
        let along = (mean - origin).dot(direction);
        let sigma_along = reach;
        let (segment, t0, t1) = match i % 5 {
            0 => ("[0, inf)", 0.0, f64::INFINITY),
            1 => ("finite", (along - sigma_along * 2.0 * s.uniform()).max(0.0), along + sigma_along * 3.0 * s.uniform()),
            2 => ("t0 = t1", along, along),
            3 => ("short", along + 0.1 * sigma_along * s.uniform(), along + 0.1 * sigma_along * s.uniform() + 1e-6 * sigma_along),
            _ => ("ends inside", 0.0, along + sigma_along * (s.uniform() - 0.5)),
        };
        let (t0, t1) = if t1 < t0 { (t1, t0) } else { (t0, t1) };
        out.push((format!("{name}, {segment}"), Case { mean, axes, scales, amplitude, origin, direction, t0: t0.max(0.0), t1 }));
    }
    out
}

#[test]
fn libm_erf_agrees_with_statrs_and_quadrature() {
    let nodes = legendre(20);
    let mut worst_statrs = 0.0f64;
    let mut worst_quadrature = 0.0f64;
    for k in 0..=600 {
        let x = -6.0 + 12.0 * k as f64 / 600.0;
        let (e, c) = (libm::erf(x), libm::erfc(x));
        worst_statrs = worst_statrs.max(((e - statrs::function::erf::erf(x)) / e.abs().max(1e-300)).abs());
        worst_statrs = worst_statrs.max(((c - statrs::function::erf::erfc(x)) / c).abs());
        // erf(x) = 2/sqrt(pi) int_0^x exp(-u^2) du, composite 20-point Gauss-Legendre.
        let panels = 40;
        let mut q = 0.0;
        for p in 0..panels {
            let (a, b) = (x * p as f64 / panels as f64, x * (p + 1) as f64 / panels as f64);
            for &(n, w) in &nodes {
                let u = 0.5 * (a + b) + 0.5 * (b - a) * n;
                q += w * 0.5 * (b - a) * (-u * u).exp();
            }
        }
        q *= 2.0 / std::f64::consts::PI.sqrt();
        if x != 0.0 {
            worst_quadrature = worst_quadrature.max(((e - q) / q).abs());
        }
    }
    // statrs documents about 1e-10 relative accuracy; measured here its worst is ~1.03e-10.
    assert!(worst_statrs < 3e-10, "libm vs statrs: {worst_statrs:e}");
    assert!(worst_quadrature < 1e-13, "libm vs quadrature: {worst_quadrature:e}");
}

#[test]
fn erf_difference_never_cancels() {
    let nodes = legendre(20);
    let mut worst = 0.0f64;
    let mut s = Stream::new(7, 7, 7);
    for i in 0..4000 {
        let a = (s.uniform() - 0.5) * 16.0;
        let width = match i % 4 {
            0 => 1e-9,
            1 => 1e-4 * s.uniform(),
            2 => s.uniform(),
            _ => 10.0 * s.uniform(),
        };
        let b = a + width;
        let got: f64 = erf_difference(a, b);
        // Quadrature of 2/sqrt(pi) exp(-u^2) over [a, b], shifted by its larger end's decay.
        let panels = 8;
        let mut q = 0.0;
        for p in 0..panels {
            let (lo, hi) = (a + width * p as f64 / panels as f64, a + width * (p + 1) as f64 / panels as f64);
            for &(n, w) in &nodes {
                let u = 0.5 * (lo + hi) + 0.5 * (hi - lo) * n;
                q += w * 0.5 * (hi - lo) * (-u * u).exp();
            }
        }
        q *= 2.0 / std::f64::consts::PI.sqrt();
        if q > 1e-290 {
            worst = worst.max(((got - q) / q).abs());
        }
    }
    assert!(worst < 1e-12, "erf_difference relative error {worst:e}");
    assert_eq!(erf_difference::<f64>(2.0, 2.0), 0.0);
    assert!((erf_difference::<f64>(-1.0, f64::INFINITY) - (1.0 + libm::erf(1.0))).abs() < 1e-15);
    assert!((erf_difference::<f64>(20.0, f64::INFINITY) / libm::erfc(20.0) - 1.0).abs() < 1e-15);
    // Far tails underflow to zero, never to NaN.
    assert_eq!(erf_difference::<f64>(30.0, f64::INFINITY), 0.0);
    assert_eq!(erf_difference::<f32>(12.0, 13.0), 0.0);
}

#[test]
fn closed_form_matches_quadrature_to_1e9_over_stress_ranges() {
    let nodes = legendre(20);
    let mut worst = (0.0f64, String::new());
    let mut count = 0;
    for (name, case) in cases(4000, 11) {
        let got = case.closed_form();
        assert!(got.is_finite() && got >= 0.0, "{name}: {got}");
        let reference = case.quadrature(&nodes);
        let error = (got - reference).abs() / reference.abs().max(1e-280);
        if reference > 1e-280 {
            count += 1;
        }
        if error > worst.0 {
            worst = (error, name.clone());
        }
    }
    assert!(count > 2000, "enough cases with a non-negligible reference: {count}");
    assert!(worst.0 < 1e-9, "worst relative error {:e} ({})", worst.0, worst.1);
}

#[test]
fn zero_length_and_degenerate_inputs_stay_finite() {
    let axes = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    assert_eq!(optical_depth([0.0; 3], axes, [0.1; 3], 5.0, [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], 1.0, 1.0), 0.0);
    assert_eq!(optical_depth([0.0; 3], axes, [0.1; 3], 5.0, [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], 2.0, 1.0), 0.0);
    for scales in [[0.0, 0.1, 0.1], [0.0, 0.0, 0.0], [1e-12, 1e3, 1.0], [-1.0, 0.2, 0.2]] {
        let v = optical_depth([0.0; 3], axes, scales, 5.0, [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], 0.0, f64::INFINITY);
        let v32 = optical_depth_f32(
            [0.0; 3],
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            scales.map(|s| s as f32),
            5.0,
            [0.0, 0.0, -1.0],
            [0.0, 0.0, 1.0],
            0.0,
            f32::INFINITY,
        );
        assert!(v.is_finite() && v >= 0.0 && v32.is_finite() && v32 >= 0.0, "{scales:?}: {v} {v32}");
    }
    // Whole line through an isotropic Gaussian: A s sqrt(2 pi).
    let full = optical_depth([0.0; 3], axes, [0.2; 3], 3.0, [0.0, 0.0, -5.0], [0.0, 0.0, 1.0], 0.0, f64::INFINITY);
    assert!((full / (3.0 * 0.2 * (2.0 * std::f64::consts::PI).sqrt()) - 1.0).abs() < 1e-14);
}

/// The f32 inputs of a case and the f64 closed form on exactly those inputs.
fn f32_case(case: &Case) -> (PosedGaussian, ShadowRay, f64) {
    let g = |v: DVec3| v.as_vec3().as_dvec3();
    let posed = PosedGaussian {
        mean: g(case.mean),
        axes: DMat3::from_cols(g(case.axes.x_axis), g(case.axes.y_axis), g(case.axes.z_axis)),
        scales: g(case.scales),
        amplitude: case.amplitude as f32 as f64,
    };
    let ray = ShadowRay {
        origin: case.origin.as_vec3().to_array(),
        direction: case.direction.normalize().as_vec3().to_array(),
        t0: case.t0 as f32,
        t1: case.t1 as f32,
    };
    let reference = f64_depth(&posed, &ray);
    (posed, ray, reference)
}

/// The f32 tolerance the CPU paths are held to: relative 1e-4, or 1e-6 in transmittance.
fn f32_error(got: f64, reference: f64) -> Option<f64> {
    let relative = (got - reference).abs() / reference.max(1e-300);
    let transmittance = ((-got).exp() - (-reference).exp()).abs();
    (relative > 1e-4 && transmittance > 1e-6).then(|| relative.min(transmittance / 1e-2))
}

/// The f64 closed form's optical depth of one Gaussian along an f32 ray.
fn f64_depth(g: &PosedGaussian, ray: &ShadowRay) -> f64 {
    let (t0, t1) = (ray.t0 as f64, ray.t1 as f64);
    optical_depth(g.mean.to_array(), g.rotation_columns(), g.scales.to_array(), g.amplitude, ray.origin.map(f64::from), ray.direction.map(f64::from), t0, t1)
}

/// The kernel's sum as dispatched, checked bit for bit against every build this CPU runs.
fn every_build_alike(caster: &ShadowCaster, ray: &umbra::shadow::ShadowRay, cull: bool, name: &str) -> umbra::shadow::lanes::Collected {
    let collected = caster.collect(ray, cull);
    for build in umbra::shadow::lanes::Build::ALL {
        if let Some(other) = caster.collect_built(build, ray, cull) {
            assert_eq!(collected, other, "{name}: the {} build differs from the dispatched one", build.name());
        }
    }
    collected
}

#[test]
fn vector_kernel_agrees_with_f64_as_the_scalar_f32_path_does() {
    // Each stress case as a one-Gaussian caster whose tolerance (1e-7) lets the f32 lanes add
    // less than the test's transmittance bound: every pair either meets the bound in the lanes
    // or is handed to the scalar integral, and the lanes must take most of them.
    let (mut worst, mut lanes, mut integrated) = ((0.0f64, String::new()), 0usize, 0usize);
    for (name, case) in cases(4000, 23) {
        let (posed, ray, reference) = f32_case(&case);
        let caster = ShadowCaster::new(std::slice::from_ref(&posed), 1e-7);
        let collected = every_build_alike(&caster, &ray, false, &name);
        let got = collected.depth as f64;
        assert!(got.is_finite() && got >= 0.0, "{name}: {got}");
        integrated += collected.integrated;
        lanes += collected.integrated - collected.scalar;
        if let Some(error) = f32_error(got, reference) {
            if error > worst.0 {
                worst = (error, format!("{name}: lanes {got} f64 {reference} (scalar: {})", collected.scalar));
            }
        }
    }
    assert!(worst.1.is_empty(), "vector kernel outside tolerance: {}", worst.1);
    assert_eq!(integrated, 4000);
    assert!(lanes * 2 > integrated, "the lanes took only {lanes} of {integrated} stress pairs");
}

#[test]
fn vector_kernel_takes_nearly_every_pair_of_a_body_and_stays_within_tolerance() {
    // A body-sized cloud and sun rays from in and around it: the renderer's case. Culling and
    // lanes each within half the caster's tolerance of the f64 transmittance; at the
    // renderer's tolerance (1e-4) at most 1 pair in 1000 needs the scalar integral, at 1e-6
    // (a per-pair budget of 5e-9) at most 1 in 50.
    let gaussians = umbra::bench::shadows::body_cloud(96, 1);
    let rays = umbra::bench::shadows::sun_rays(512, 3);
    for (tolerance, scalar_share) in [(1e-4, 1e-3), (1e-6, 2e-2)] {
        let caster = ShadowCaster::new(&gaussians, tolerance);
        let (mut scalar, mut worst) = (0usize, 0.0f64);
        for ray in &rays {
            let c = every_build_alike(&caster, ray, true, "body");
            scalar += c.scalar;
            let got = (-(c.depth as f64)).exp();
            worst = worst.max((got - transmittance_f64(&gaussians, ray)).abs());
        }
        assert!(worst <= tolerance + 1e-6, "tolerance {tolerance:e}: worst transmittance error {worst:e}");
        assert!(scalar as f64 <= scalar_share * (rays.len() * 96) as f64, "tolerance {tolerance:e}: {scalar} pairs went to the scalar integral");
    }
}

#[test]
fn f32_path_agrees_with_f64_within_1e4_or_1e6_transmittance() {
    let mut worst = (0.0f64, String::new());
    for (name, case) in cases(4000, 23) {
        let f = |v: DVec3| v.as_vec3().to_array();
        let cols32 = [f(case.axes.x_axis), f(case.axes.y_axis), f(case.axes.z_axis)];
        let got = optical_depth_f32(
            f(case.mean),
            cols32,
            f(case.scales),
            case.amplitude as f32,
            f(case.origin),
            f(case.direction.normalize()),
            case.t0 as f32,
            case.t1 as f32,
        );
        assert!(got.is_finite() && got >= 0.0, "{name}: {got}");
        // The f64 reference on exactly the f32 inputs.
        let g = |v: [f32; 3]| v.map(f64::from);
        let direction = DVec3::from_array(g(f(case.direction.normalize())));
        let reference = optical_depth(
            g(f(case.mean)),
            cols32.map(g),
            g(f(case.scales)),
            case.amplitude as f32 as f64,
            g(f(case.origin)),
            direction.to_array(),
            case.t0 as f32 as f64,
            case.t1 as f32 as f64,
        );
        let relative = (got as f64 - reference).abs() / reference.max(1e-300);
        let transmittance = ((-(got as f64)).exp() - (-reference).exp()).abs();
        let error = relative.min(transmittance / 1e-2);
        if relative > 1e-4 && transmittance > 1e-6 && error > worst.0 {
            worst = (error, format!("{name}: f32 {got} f64 {reference}"));
        }
    }
    assert!(worst.1.is_empty(), "f32 outside tolerance: {}", worst.1);
}

#[test]
fn vector_kernel_hands_over_what_its_cut_exponentials_would_drop() {
    // The lanes take e^x below e^-30 as zero (it keeps their arithmetic out of f32's subnormal
    // range). A Gaussian of enormous amplitude far off the ray still casts a real shadow there:
    // its profile across the ray is e^-35, its depth about 1. The lane's error estimate must
    // see what the cut drops and hand the pair to the scalar integral.
    let sigma = 0.01;
    let distance = sigma * 70.0f64.sqrt(); // (distance / sigma)^2 / 2 = 35
    let amplitude = 1.0 / ((-35.0f64).exp() * sigma * (2.0 * std::f64::consts::PI).sqrt());
    let gaussian = PosedGaussian { mean: DVec3::new(distance, 0.0, 0.0), axes: DMat3::IDENTITY, scales: DVec3::splat(sigma), amplitude };
    let ray = ShadowRay { origin: [0.0, -1.0, 0.0], direction: [0.0, 1.0, 0.0], t0: 0.0, t1: f32::INFINITY };
    let reference = f64_depth(&gaussian, &ray);
    assert!((reference - 1.0).abs() < 1e-6, "the case is built to a depth of 1, not {reference}");
    let caster = ShadowCaster::new(std::slice::from_ref(&gaussian), 1e-6);
    for cull in [false, true] {
        let collected = every_build_alike(&caster, &ray, cull, "far, enormous Gaussian");
        assert_eq!(collected.scalar, 1, "the lane kept a pair whose depth it cut (culling {cull})");
        assert!((collected.depth as f64 - reference).abs() <= 1e-5, "depth {} against {reference} (culling {cull})", collected.depth);
    }
}

#[test]
fn groups_of_blocks_cull_nothing_their_blocks_keep() {
    // 1,000 Gaussians (125 blocks): grouped (11 blocks to a group), in groups of 3, and each
    // block on its own must give the same bits for every ray, since a group's sphere holds its
    // blocks' spheres; and the groups must skip something, or they are not tested.
    let gaussians = umbra::bench::shadows::body_cloud(1000, 4);
    let rays = umbra::bench::shadows::sun_rays(256, 5);
    let grouped = ShadowCaster::new(&gaussians, 1e-5);
    let threes = ShadowCaster::new(&gaussians, 1e-5).with_group_size(3);
    let flat = ShadowCaster::new(&gaussians, 1e-5).with_group_size(1);
    for ray in &rays {
        let expected = every_build_alike(&flat, ray, true, "flat");
        assert_eq!(every_build_alike(&grouped, ray, true, "grouped"), expected);
        assert_eq!(every_build_alike(&threes, ray, true, "threes"), expected);
    }
    let integrated: usize = rays.iter().map(|r| flat.collect(r, true).integrated).sum();
    assert!(integrated < rays.len() * 1000 / 2, "culling kept {integrated} of {} pairs: the groups are not exercised", rays.len() * 1000);
}
