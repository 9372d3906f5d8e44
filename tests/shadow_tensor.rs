//! The burn tensor path of the shadow integral: agrees with the scalar f64 path, its erfc
//! approximation is pinned to libm, and its gradients match finite differences of the f64 path.

mod common;

use burn::tensor::{Device, Tensor, TensorData};
use glam::{DMat3, DQuat, DVec3};
use umbra::gaussians::PosedGaussian;
use umbra::random::Stream;
use umbra::shadow::tensor::{erfc_nonnegative, optical_depth as tensor_depth, transmittance, transmittance_from, GaussianTensors, RaySegments};
use umbra::shadow::{optical_depth, ShadowCaster, ShadowRay};

fn device() -> Device {
    Device::flex().autodiff()
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().unwrap()
}

fn tensor1(v: Vec<f32>, d: &Device) -> Tensor<1> {
    let n = v.len();
    Tensor::from_data(TensorData::new(v, [n]), d)
}

fn tensor2(v: Vec<f32>, cols: usize, d: &Device) -> Tensor<2> {
    let n = v.len() / cols;
    Tensor::from_data(TensorData::new(v, [n, cols]), d)
}

fn random_unit(s: &mut Stream) -> DVec3 {
    DVec3::new(s.uniform() - 0.5, s.uniform() - 0.5, s.uniform() - 0.5).normalize()
}

fn body_like_gaussians(n: usize, seed: u64) -> Vec<PosedGaussian> {
    let mut s = Stream::new(seed, 3, 4);
    (0..n)
        .map(|_| PosedGaussian {
            mean: DVec3::new(s.uniform() - 0.5, s.uniform() * 1.6, s.uniform() - 0.5) * 0.8,
            axes: DMat3::from_quat(DQuat::from_axis_angle(random_unit(&mut s), s.uniform() * 6.0)),
            scales: DVec3::new(0.02 + 0.1 * s.uniform(), 0.02 + 0.1 * s.uniform(), 0.02 + 0.1 * s.uniform()),
            amplitude: 2.0 + 20.0 * s.uniform(),
        })
        .collect()
}

fn shadow_rays(n: usize, seed: u64, finite: bool) -> Vec<ShadowRay> {
    let mut s = Stream::new(seed, 5, 6);
    (0..n)
        .map(|_| {
            let origin = DVec3::new(s.uniform() - 0.5, s.uniform() * 1.6, s.uniform() - 0.5) * 0.9;
            let direction = (random_unit(&mut s) + DVec3::Y * 0.5).normalize();
            ShadowRay {
                origin: origin.as_vec3().to_array(),
                direction: direction.as_vec3().to_array(),
                t0: 0.01,
                t1: if finite { 0.3 + 2.0 * s.uniform() as f32 } else { f32::INFINITY },
            }
        })
        .collect()
}

fn segments(rays: &[ShadowRay], finite: bool, d: &Device) -> RaySegments {
    RaySegments {
        origins: tensor2(rays.iter().flat_map(|r| r.origin).collect(), 3, d),
        directions: tensor2(rays.iter().flat_map(|r| r.direction).collect(), 3, d),
        t0: tensor1(rays.iter().map(|r| r.t0).collect(), d),
        t1: finite.then(|| tensor1(rays.iter().map(|r| r.t1).collect(), d)),
    }
}

#[test]
fn erfc_approximation_tracks_libm_to_f32_rounding() {
    let d = device();
    let xs: Vec<f32> = (0..4000).map(|k| k as f32 * 0.0025).collect();
    let n = xs.len();
    let t: Tensor<3> = Tensor::from_data(TensorData::new(xs.clone(), [1, 1, n]), &d);
    let got = values(erfc_nonnegative(t));
    for (x, g) in xs.iter().zip(got) {
        let reference = libm::erfc(*x as f64);
        if reference > 1e-30 {
            // 1.2e-7 in exact arithmetic; in f32 the exponent's argument (about -x^2) carries an
            // absolute rounding error of order ulp(x^2), which exp turns into a relative one.
            let x2 = (*x as f64) * (*x as f64);
            assert!(((g as f64 - reference) / reference).abs() < 6e-7 + 1.5e-7 * x2, "erfc({x}) = {g} vs {reference}");
        }
    }
}

#[test]
fn tensor_and_cpu_paths_agree() {
    let d = device();
    let gaussians = body_like_gaussians(40, 1);
    let caster = ShadowCaster::new(&gaussians, 1e-7);
    let g = GaussianTensors::from_posed(&gaussians, &d);
    for finite in [false, true] {
        let rays = shadow_rays(300, 2 + finite as u64, finite);
        let t = values(transmittance(&g, &segments(&rays, finite, &d)));
        let mut worst = 0.0f32;
        for (ray, tensor_value) in rays.iter().zip(t) {
            let cpu = caster.transmittance(ray, false);
            worst = worst.max((cpu - tensor_value).abs());
            // And the f64 sum as the reference for both.
            let exact = umbra::shadow::transmittance_f64(&gaussians, ray);
            assert!((exact - cpu as f64).abs() < 1e-6, "cpu vs f64: {cpu} vs {exact}");
        }
        assert!(worst < 2e-6, "finite={finite}: worst |T_cpu - T_tensor| = {worst:e}");
    }
}

#[test]
fn culling_changes_transmittance_by_less_than_its_tolerance() {
    let gaussians = body_like_gaussians(300, 9);
    let tolerance = 1e-5;
    let caster = ShadowCaster::new(&gaussians, tolerance);
    let rays = shadow_rays(500, 10, false);
    let mut skipped = 0;
    for ray in &rays {
        let (all, n_all) = caster.optical_depth(ray, false);
        let (culled, n_culled) = caster.optical_depth(ray, true);
        skipped += n_all - n_culled;
        assert!(((-all).exp() - (-culled).exp()).abs() as f64 <= tolerance + 1e-6, "{all} vs {culled}");
    }
    assert!(skipped > rays.len() * 100, "culling skips most pairs: {skipped}");
}

#[test]
fn gradients_match_finite_differences_of_the_f64_path() {
    let d = device();
    let gaussians = body_like_gaussians(6, 21);
    let rays = shadow_rays(12, 22, true);
    let n = gaussians.len();
    // Leaves for every input.
    let means = tensor2(gaussians.iter().flat_map(|g| g.mean.as_vec3().to_array()).collect(), 3, &d).require_grad();
    let rotations: Tensor<3> = Tensor::from_data(
        TensorData::new(gaussians.iter().flat_map(|g| g.axes.transpose().to_cols_array().map(|v| v as f32)).collect::<Vec<_>>(), [n, 3, 3]),
        &d,
    )
    .require_grad();
    let scales = tensor2(gaussians.iter().flat_map(|g| g.scales.as_vec3().to_array()).collect(), 3, &d).require_grad();
    let amplitudes = tensor1(gaussians.iter().map(|g| g.amplitude as f32).collect(), &d).require_grad();
    let origins = tensor2(rays.iter().flat_map(|r| r.origin).collect(), 3, &d).require_grad();
    let directions = tensor2(rays.iter().flat_map(|r| r.direction).collect(), 3, &d).require_grad();
    let t1 = tensor1(rays.iter().map(|r| r.t1).collect(), &d).require_grad();
    let g = GaussianTensors::from_world(means.clone(), rotations.clone(), scales.clone(), amplitudes.clone());
    let segs =
        RaySegments { origins: origins.clone(), directions: directions.clone(), t0: tensor1(rays.iter().map(|r| r.t0).collect(), &d), t1: Some(t1.clone()) };
    // A loss that weights every pair differently, so that each gradient entry is tested.
    let weights: Vec<f32> = (0..rays.len() * n).map(|k| 0.5 + ((k * 7919) % 13) as f32 / 13.0).collect();
    let loss = (tensor_depth(&g, &segs) * tensor2(weights.clone(), n, &d)).sum();
    let grads = loss.backward();

    // The same loss in f64 from plain arrays.
    struct Inputs {
        means: Vec<f64>,
        rotations: Vec<f64>,
        scales: Vec<f64>,
        amplitudes: Vec<f64>,
        origins: Vec<f64>,
        directions: Vec<f64>,
        t1: Vec<f64>,
    }
    let loss64 = |x: &Inputs| -> f64 {
        let mut total = 0.0;
        for (r, ray) in rays.iter().enumerate() {
            for k in 0..n {
                let rot = &x.rotations[k * 9..k * 9 + 9];
                // Row-major rotation: column c is (rot[c], rot[3 + c], rot[6 + c]).
                let cols = [[rot[0], rot[3], rot[6]], [rot[1], rot[4], rot[7]], [rot[2], rot[5], rot[8]]];
                let o = [x.origins[r * 3], x.origins[r * 3 + 1], x.origins[r * 3 + 2]];
                // The tensor path takes directions as given (callers normalise); so does this.
                let dir = [x.directions[r * 3], x.directions[r * 3 + 1], x.directions[r * 3 + 2]];
                let tau = optical_depth(
                    [x.means[k * 3], x.means[k * 3 + 1], x.means[k * 3 + 2]],
                    cols,
                    [x.scales[k * 3], x.scales[k * 3 + 1], x.scales[k * 3 + 2]],
                    x.amplitudes[k],
                    o,
                    dir,
                    ray.t0 as f64,
                    x.t1[r],
                );
                total += tau * weights[r * n + k] as f64;
            }
        }
        total
    };
    let to64 = |t: &Tensor<2>| values(t.clone()).into_iter().map(f64::from).collect::<Vec<_>>();
    let base = Inputs {
        means: to64(&means),
        rotations: values(rotations.clone()).into_iter().map(f64::from).collect(),
        scales: to64(&scales),
        amplitudes: values(amplitudes.clone()).into_iter().map(f64::from).collect(),
        origins: to64(&origins),
        directions: to64(&directions),
        t1: values(t1.clone()).into_iter().map(f64::from).collect(),
    };
    let check = |name: &str, got: Vec<f32>, field: fn(&mut Inputs) -> &mut Vec<f64>| {
        let mut worst = 0.0f64;
        let scale = got.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
        for (i, g) in got.iter().enumerate() {
            let h = 1e-6;
            let mut plus = Inputs { ..clone_inputs(&base) };
            field(&mut plus)[i] += h;
            let mut minus = Inputs { ..clone_inputs(&base) };
            field(&mut minus)[i] -= h;
            let fd = (loss64(&plus) - loss64(&minus)) / (2.0 * h);
            worst = worst.max((*g as f64 - fd).abs() / (fd.abs() + 1e-3 * scale + 1e-6));
        }
        assert!(worst < 2e-3, "{name}: worst relative gradient error {worst:e}");
    };
    fn clone_inputs(x: &Inputs) -> Inputs {
        Inputs {
            means: x.means.clone(),
            rotations: x.rotations.clone(),
            scales: x.scales.clone(),
            amplitudes: x.amplitudes.clone(),
            origins: x.origins.clone(),
            directions: x.directions.clone(),
            t1: x.t1.clone(),
        }
    }
    check("means", values(means.grad(&grads).unwrap()), |x| &mut x.means);
    check("rotations", values(rotations.grad(&grads).unwrap()), |x| &mut x.rotations);
    check("scales", values(scales.grad(&grads).unwrap()), |x| &mut x.scales);
    check("amplitudes", values(amplitudes.grad(&grads).unwrap()), |x| &mut x.amplitudes);
    check("origins", values(origins.grad(&grads).unwrap()), |x| &mut x.origins);
    check("directions", values(directions.grad(&grads).unwrap()), |x| &mut x.directions);
    check("t1", values(t1.grad(&grads).unwrap()), |x| &mut x.t1);
}

#[test]
fn own_shares_agree_on_every_path() {
    // Shadow rays from surface points: each Gaussian's optical depth weighted by one less its
    // share of the density at the point, by the tensor path (training, still renders), the CPU
    // kernel with and without culling (sky light, visibility basis, sun search) and in f64.
    let d = device();
    let gaussians = body_like_gaussians(40, 11);
    let caster = ShadowCaster::new(&gaussians, 1e-7);
    let g = GaussianTensors::from_posed(&gaussians, &d);
    for finite in [false, true] {
        let rays = shadow_rays(300, 12 + finite as u64, finite);
        let points: Vec<f32> = rays.iter().flat_map(|r| r.origin).collect();
        let t = values(transmittance_from(&g, &segments(&rays, finite, &d), tensor2(points, 3, &d)));
        let mut owned = 0;
        for (ray, tensor_value) in rays.iter().zip(t) {
            let x = DVec3::from_array(ray.origin.map(f64::from));
            let exact = umbra::shadow::transmittance_f64_from(&gaussians, x, ray);
            let shares = caster.shares_at(ray.origin);
            let cpu = caster.transmittance_from(&shares, ray, false);
            let culled = caster.transmittance_from(&shares, ray, true);
            assert!((exact - cpu as f64).abs() < 1e-6, "cpu vs f64: {cpu} vs {exact}");
            assert!((exact - culled as f64).abs() < 1e-6, "culled cpu vs f64: {culled} vs {exact}");
            assert!((exact - tensor_value as f64).abs() < 2e-6, "tensor vs f64: {tensor_value} vs {exact}");
            // Never darker than the plain transmittance: shares only take optical depth away.
            assert!(exact >= umbra::shadow::transmittance_f64(&gaussians, ray) - 1e-12);
            owned += (exact > umbra::shadow::transmittance_f64(&gaussians, ray) + 1e-3) as usize;
        }
        assert!(owned > 30, "finite={finite}: the shares change {owned} of 300 rays");
    }
}

#[test]
fn a_body_part_does_not_shadow_the_surface_it_makes_but_a_part_near_it_does() {
    // A torso Gaussian (10 cm) and a point on top of it at 1.5 sigma, the sun straight above.
    let torso = PosedGaussian { mean: DVec3::ZERO, axes: DMat3::IDENTITY, scales: DVec3::splat(0.1), amplitude: 50.0 };
    let x = DVec3::new(0.0, 0.15, 0.0);
    let ray = ShadowRay { origin: x.as_vec3().to_array(), direction: [0.0, 1.0, 0.0], t0: 0.005, t1: f32::INFINITY };
    // Its own blob would darken the point by itself; it lights it fully once its share is taken.
    let plain = umbra::shadow::transmittance_f64(&[torso], &ray);
    let own = umbra::shadow::transmittance_f64_from(&[torso], x, &ray);
    assert!(plain < 0.7, "the torso's blur shadows its own top: {plain}");
    assert!(own > 0.999, "not once its share is taken: {own}");
    // An arm 9 cm above the point (3 cm wide) casts its contact shadow all the same: a shadow
    // ray starting as far off the surface as before (7.5 cm, a sweep's choice) would have lost it.
    let arm = PosedGaussian { mean: DVec3::new(0.0, 0.24, 0.0), axes: DMat3::IDENTITY, scales: DVec3::splat(0.03), amplitude: 50.0 };
    let shaded = umbra::shadow::transmittance_f64_from(&[torso, arm], x, &ray);
    assert!(shaded < 0.05, "the arm's contact shadow: {shaded}");
    let caster = ShadowCaster::new(&[torso, arm], 1e-6);
    let cpu = caster.transmittance_from(&caster.shares_at(ray.origin), &ray, true);
    assert!((cpu as f64 - shaded).abs() < 1e-5, "{cpu} vs {shaded}");
}

#[test]
fn weights_scale_only_what_each_ray_tells_the_light() {
    // Shading with per-ray weights on the light's gradient (`Schedule::error_rays`: 0 or 1): the
    // same colours; the light's gradient (sun direction, irradiance, ambient; point position and
    // intensity) the weighted sum of the rays' own, the albedo's and normals' untouched.
    use umbra::shading::{shade_lambertian, Emitter};
    let d = device();
    let gaussians = body_like_gaussians(12, 5);
    let g = GaussianTensors::from_posed(&gaussians, &d);
    let mut s = Stream::new(9, 1, 2);
    let n = 24;
    let points: Vec<f32> = (0..n * 3).map(|_| (s.uniform() as f32 - 0.5) * 0.8 + 0.4).collect();
    let normals: Vec<f32> = (0..n).flat_map(|_| random_unit(&mut s).as_vec3().to_array()).collect();
    let albedo: Vec<f32> = (0..n * 3).map(|_| 0.2 + 0.7 * s.uniform() as f32).collect();
    let weights: Vec<f32> = (0..n).map(|_| s.uniform() as f32).collect();
    for point_light in [false, true] {
        // Every ray's colour and the gradients of their sum, with `w` (or none).
        let run = |w: Option<&[f32]>, only: Option<usize>| {
            let light = tensor1(if point_light { vec![0.6, 2.2, 0.8] } else { vec![0.45, 0.8, 0.4] }, &d).require_grad();
            let strength = tensor1(vec![0.9, 0.8, 0.7], &d).require_grad();
            let ambient = tensor1(vec![0.2, 0.21, 0.24], &d).require_grad();
            let a = tensor2(albedo.clone(), 3, &d).require_grad();
            let nrm = tensor2(normals.clone(), 3, &d).require_grad();
            let emitter = if point_light {
                Emitter::Point { position: light.clone(), intensity: strength.clone() * 4.0 }
            } else {
                Emitter::Sun { direction: light.clone(), irradiance: strength.clone() }
            };
            let p = tensor2(points.clone(), 3, &d);
            let wt = w.map(|w| tensor1(w.to_vec(), &d));
            let colour = shade_lambertian(a.clone(), p, nrm.clone(), &g, ambient.clone(), &emitter, 0.02, wt.as_ref());
            let picked = match only {
                Some(k) => colour.clone().slice([k..k + 1, 0..3]).sum(),
                None => colour.clone().sum(),
            };
            let grads = picked.backward();
            let grad = |t: &Tensor<1>| values(t.grad(&grads).unwrap());
            (values(colour), [grad(&light), grad(&strength), grad(&ambient)], values(a.grad(&grads).unwrap()), values(nrm.grad(&grads).unwrap()))
        };
        let (plain, _, plain_albedo, plain_normals) = run(None, None);
        let (weighted, light_grads, albedo_grad, normal_grad) = run(Some(&weights), None);
        assert_eq!(plain, weighted, "point light {point_light}: the colours do not change");
        assert_eq!(plain_albedo, albedo_grad);
        for (a, b) in plain_normals.iter().zip(&normal_grad) {
            assert!((a - b).abs() < 1e-6, "the normals' gradient: {a} vs {b}");
        }
        // The weighted sum of each ray's own gradient.
        let mut expected = [vec![0.0f64; 3], vec![0.0; 3], vec![0.0; 3]];
        for (k, w) in weights.iter().enumerate() {
            let (_, own, _, _) = run(None, Some(k));
            for (e, o) in expected.iter_mut().zip(&own) {
                for (e, o) in e.iter_mut().zip(o) {
                    *e += *w as f64 * *o as f64;
                }
            }
        }
        let lit = light_grads[0].iter().any(|v| v.abs() > 1e-3);
        assert!(lit, "the light takes a gradient: {:?}", light_grads[0]);
        for (got, want) in light_grads.iter().zip(&expected) {
            for (g, e) in got.iter().zip(want) {
                assert!((*g as f64 - e).abs() < 1e-4 * (1.0 + e.abs()), "point light {point_light}: {got:?} vs {want:?}");
            }
        }
    }
}
