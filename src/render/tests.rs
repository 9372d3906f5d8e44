use super::samples::*;
use super::*;

#[test]
fn a_views_coarse_pass_skips_only_samples_the_sdf_shows_empty_or_the_rounds_before_show_hidden() {
    use crate::skeleton::{Bone, Pose, Skeleton};
    use glam::{DMat4, DQuat};
    let skeleton =
        Skeleton { bones: vec![Bone { name: "spine".into(), parent: None, length: 0.5 }, Bone { name: "arm".into(), parent: Some(0), length: 0.3 }] };
    let pose = Pose { bone_to_world: vec![DMat4::IDENTITY, DMat4::from_rotation_translation(DQuat::from_rotation_z(1.2), DVec3::new(0.0, 0.4, 0.0))] };
    let device = Device::flex();
    let mut field = crate::field::FieldConfig::with_grid(vec![0.5, 0.3], 1.0).init(&device, 3);
    // A fitted field's sharp surface (beta at its floor), not a fresh field's haze.
    field.beta_raw = burn::module::Param::from_tensor(Tensor::from_data(TensorData::new(vec![-1e3f32], [1]), &device));
    let tensors = PoseTensors::new(&pose, &skeleton, &device);
    // Rays from 2 m away toward a lattice around the bones: through the body and beside it.
    let eye = DVec3::new(0.1, 0.3, 2.0);
    let mut rays = RaySet::default();
    // Each ray four times, its bounds shifted by a quarter of a sample's spacing each time, so
    // that some rays cross the body between two samples of the first round.
    for k in 0..256 {
        let target = DVec3::new(-0.5 + (k % 8) as f64 / 7.0, -0.2 + (k / 8 % 8) as f64 / 7.0, 0.0);
        let shift = (k / 64) as f64 * 0.02;
        rays.push(eye, (target - eye).normalize(), Some((1.0 + shift, 3.0 + shift)));
    }
    let (r, s) = (rays.len(), 24);
    let coarse = stratified(&rays, s, &vec![0.5; r * s]);
    let (density, decoded, row) = coarse_densities(&field, &tensors, &rays, &coarse, s, &device);
    let (origins, directions) = ray_tensors(&rays, &device);
    let (full, _) = densities(&field, &tensors, &origins, &directions, &coarse.t, r);
    let before = transmittance_before(&coarse, &full, r);
    let (mut skipped, mut kept, mut hidden, mut hidden_even) = (0, 0, 0, 0);
    for i in 0..r {
        let samples = i * s..(i + 1) * s;
        let empty = full[samples.clone()].iter().zip(&coarse.delta[samples.clone()]).all(|(d, delta)| d * delta < EMPTY_OPTICAL_DEPTH);
        if empty && samples.clone().any(|k| row[k] == NOT_DECODED) {
            // Skipped: every other sample (the whole ray is empty in one full pass).
            skipped += 1;
            assert!(samples.clone().all(|k| ((k % s) % 2 == 1) == (row[k] == NOT_DECODED)), "ray {i}");
            continue;
        }
        kept += 1;
        for k in samples {
            if row[k] == NOT_DECODED {
                // Hidden: a later round's sample the full pass puts behind the surface.
                hidden += 1;
                hidden_even += usize::from((k % s) % 2 == 0);
                assert!((k % s) % 4 != 0 && density[k] == 0.0, "sample {k}");
                assert!(before[k] < CULL_TRANSMITTANCE, "sample {k} left out, {} of the ray passes it", before[k]);
            } else {
                assert!((density[k] - full[k]).abs() <= 1e-5 * full[k].abs().max(1e-3), "sample {k}: {} against {}", density[k], full[k]);
            }
        }
    }
    assert!(
        skipped > 0 && kept > 0 && hidden_even > 0 && hidden > hidden_even,
        "{skipped} rays skipped, {kept} kept, {hidden} samples hidden ({hidden_even} even)"
    );
    assert_eq!(decoded.sdf.dims()[0], row.iter().filter(|&&k| k != NOT_DECODED).count());
}

fn one_ray(near: f32, far: f32) -> RaySet {
    RaySet { origins: vec![0.0; 3], directions: vec![0.0, 0.0, 1.0], near: vec![near], far: vec![far], cameras: Vec::new() }
}

#[test]
fn importance_draws_follow_the_weights() {
    // All the mass in the third of four bins: every draw but the floor's lands there.
    let bins = [(0.0, 1.0), (1.0, 2.0), (2.0, 2.5), (2.5, 4.0)];
    let mut out = Vec::new();
    let jitter = vec![0.5; 32];
    importance(&bins, &[0.0, 0.0, 1.0, 0.0], 32, &jitter, &mut out);
    assert_eq!(out.len(), 32);
    let inside = out.iter().filter(|&&t| (2.0..=2.5).contains(&t)).count();
    assert!(inside >= 30, "{inside} of 32 draws in the weighted bin");
    assert!(out.windows(2).all(|w| w[0] <= w[1]), "stratified draws come out in order");
}

#[test]
fn merged_intervals_tile_the_bound_and_probes_sharpen_the_draws() {
    let rays = one_ray(1.0, 3.0);
    let coarse = stratified(&rays, 8, &[0.5; 8]);
    // A surface in the fifth stratum, at t = 2.05: density 0 before it, 1e4 behind.
    let body = |t: f32| if t < 2.05 { 0.0 } else { 1e4 };
    let density: Vec<f32> = coarse.t.iter().map(|&t| body(t)).collect();
    let weights = host_weights(&coarse, &density, 1);
    assert!((weights.iter().sum::<f32>() - 1.0).abs() < 1e-5, "an opaque body takes all the weight");
    let probes = draw(&rays, &coarse, &weights, 16, &[0.5; 16]);
    let probe_density: Vec<f32> = probes.iter().map(|&t| body(t)).collect();
    let (probed, merged_density) = merge(&rays, &coarse.t, 8, &probes, 16, Some((&density, &probe_density)));
    assert_eq!(probed.t.len(), 24);
    assert!(probed.t.windows(2).all(|w| w[0] <= w[1]));
    for (t, d) in probed.t.iter().zip(&merged_density) {
        assert_eq!(*d, body(*t), "densities travel with their samples");
    }
    let covered: f32 = probed.delta.iter().sum();
    assert!((covered - 2.0).abs() < 1e-5, "intervals cover the bound: {covered}");
    for k in 1..probed.t.len() {
        assert!((probed.lo[k] - (probed.lo[k - 1] + probed.delta[k - 1])).abs() < 1e-6, "intervals are contiguous");
    }
    // The coarse pass locates the surface within a stratum (25 cm), the probes within their
    // spacing: the fine draws from the probed weights crowd the surface.
    let fine_coarse = draw(&rays, &coarse, &weights, 16, &[0.5; 16]);
    let fine_probed = draw(&rays, &probed, &host_weights(&probed, &merged_density, 1), 16, &[0.5; 16]);
    let near = |draws: &[f32]| draws.iter().filter(|&&t| (t - 2.05).abs() < 0.02).count();
    assert!(near(&fine_probed) >= 12 && near(&fine_probed) > 3 * near(&fine_coarse), "{} vs {}", near(&fine_probed), near(&fine_coarse));
    let (fine, _) = merge::<f32>(&rays, &coarse.t, 8, &fine_probed, 16, None);
    assert_eq!(fine.t.len(), 24, "the rendered set holds the coarse samples and the fine draws");
}

#[test]
fn host_weights_match_the_differentiable_compositing() {
    let (r, n) = (3, 7);
    let samples = stratified(
        &RaySet { origins: vec![0.0; 3 * r], directions: vec![0.0; 3 * r], near: vec![0.5, 1.0, 0.0], far: vec![2.0, 1.5, 4.0], cameras: Vec::new() },
        n,
        &[0.3; 21],
    );
    let density: Vec<f32> = (0..r * n).map(|k| [0.0, 3.0, 40.0, 0.5, 900.0, 0.0, 12.0][k % n] * (1.0 + k as f32 * 0.1)).collect();
    let device = Device::flex();
    let tensor = compositing_weights(
        Tensor::from_data(TensorData::new(density.clone(), [r, n]), &device),
        Tensor::from_data(TensorData::new(samples.delta.clone(), [r, n]), &device),
    );
    let expected = tensor.into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
    for (a, b) in host_weights(&samples, &density, r).iter().zip(&expected) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
}

/// A two-bone body with a sharp surface and rays through it and beside it, each ray's bounds
/// shifted a little so that rays cross the body between samples.
fn two_bones(device: &Device) -> (AvatarField, PoseTensors, RaySet) {
    use crate::skeleton::{Bone, Pose, Skeleton};
    use glam::{DMat4, DQuat};
    let skeleton =
        Skeleton { bones: vec![Bone { name: "spine".into(), parent: None, length: 0.5 }, Bone { name: "arm".into(), parent: Some(0), length: 0.3 }] };
    let pose = Pose { bone_to_world: vec![DMat4::IDENTITY, DMat4::from_rotation_translation(DQuat::from_rotation_z(1.2), DVec3::new(0.0, 0.4, 0.0))] };
    let mut field = crate::field::FieldConfig::with_grid(vec![0.5, 0.3], 1.0).init(device, 3);
    field.beta_raw = burn::module::Param::from_tensor(Tensor::from_data(TensorData::new(vec![-1e3f32], [1]), device));
    let tensors = PoseTensors::new(&pose, &skeleton, device);
    let eye = DVec3::new(0.1, 0.3, 2.0);
    let mut rays = RaySet::default();
    for k in 0..96 {
        let target = DVec3::new(-0.5 + (k % 8) as f64 / 7.0, -0.2 + (k / 8 % 8) as f64 / 7.0, 0.0);
        rays.push(eye, (target - eye).normalize(), Some((1.0 + (k / 64) as f64 * 0.013, 3.0)));
    }
    (field, tensors, rays)
}

/// The surface search by tensor ops (a GPU's) draws the host's samples: the same coarse
/// strata, probes and fine samples, merged in the same order.
#[test]
fn the_search_by_tensor_ops_draws_the_hosts_samples() {
    let device = Device::flex();
    let (field, pose, rays) = two_bones(&device);
    let r = rays.len();
    let (origins, directions) = ray_tensors(&rays, &device);
    for sampling in [
        Sampling { coarse: 24, probe: 16, fine: 16, albedo_floor: 0.0, cull: false },
        Sampling { coarse: 12, probe: 0, fine: 8, albedo_floor: 0.0, cull: false },
    ] {
        let mut stream = crate::random::Stream::new(5, 2, 0);
        let jitter: Vec<f32> = (0..r * sampling.draws()).map(|_| stream.uniform() as f32).collect();
        let host = locate(&field, &pose, &rays, &origins, &directions, sampling, &jitter, Want::Samples).samples;
        let tensors = search_tensors::search_by_tensors(&field, &pose, &rays, &origins, &directions, sampling, &jitter);
        let read = |t: Tensor<2>| t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
        for (what, a, b) in
            [("t", read(tensors.t.clone()), &host.t), ("lo", read(tensors.lo.clone()), &host.lo), ("delta", read(tensors.delta.clone()), &host.delta)]
        {
            assert_eq!(a.len(), b.len(), "{what}");
            let worst = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
            assert!(worst < 1e-5, "{sampling:?} {what}: differs by {worst}");
        }
        // The fine samples sit where the body is: the search found something to refine.
        let spread = |t: &[f32]| t.windows(2).map(|w| w[1] - w[0]).fold(f32::INFINITY, f32::min);
        assert!(spread(&host.t[..sampling.total()]) < 0.01, "samples crowd a surface");
    }
}

/// A render whose search runs by tensor ops, its differentiable pass over every sample, gives
/// the host's render, culled or not: coverage, depth, albedo and normals.
#[test]
fn a_render_searched_by_tensor_ops_is_the_hosts_render() {
    let device = Device::flex().autodiff();
    let (field, pose, rays) = two_bones(&device);
    let r = rays.len();
    let mut stream = crate::random::Stream::new(8, 2, 0);
    for cull in [false, true] {
        let sampling = Sampling { coarse: 24, probe: 16, fine: 16, albedo_floor: 0.0, cull };
        let jitter: Vec<f32> = (0..r * sampling.draws()).map(|_| stream.uniform() as f32).collect();
        let render = |on_device: bool| render_searching(&field, &pose, &rays, sampling, &jitter, Some(GradientMethod::Tangents), &device, on_device);
        let (a, b) = (render(true), render(false));
        let read = |t: Tensor<2>| t.inner().into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
        let covered = read(b.accumulation.clone().reshape([r, 1]));
        assert!(covered.iter().any(|&c| c > 0.99) && covered.iter().any(|&c| c < 0.01), "rays through and beside the body");
        for (what, x, y) in [
            ("coverage", a.accumulation.reshape([r, 1]), b.accumulation.reshape([r, 1])),
            ("depth", a.depth.reshape([r, 1]), b.depth.reshape([r, 1])),
            ("albedo", a.albedo, b.albedo),
            ("normal", a.normal.unwrap(), b.normal.unwrap()),
        ] {
            let worst = read(x).iter().zip(read(y)).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
            assert!(worst < 1e-4, "cull {cull}: {what} differs by {worst}");
        }
    }
}
