//! The neural field against an independent f64 re-implementation of its maths: the SDF it
//! computes, its spatial gradient by forward-mode tangents (against f64 central differences)
//! and the parameter gradient of the Eikonal loss through those tangents.

use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;
use umbra::field::{AvatarField, FieldConfig, GradientMethod, PoseTensors};
use umbra::random::Stream;
use umbra::skeleton::{Pose, Skeleton};
use umbra::synth::character::{Character, Kind};

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
}

/// The field's weights as f64, read out of the module: `(weight [in][out] row-major, bias)`.
struct Reference {
    config: FieldConfig,
    layers: Vec<(Vec<f64>, Vec<f64>, usize, usize)>,
}

impl Reference {
    fn new(field: &AvatarField) -> Self {
        let mut layers = Vec::new();
        for layer in field.hidden.iter().chain(std::iter::once(&field.output)) {
            let [i, o] = layer.weight.val().dims();
            let w = values(layer.weight.val()).into_iter().map(f64::from).collect();
            let b = layer.bias.as_ref().map(|b| values(b.val()).into_iter().map(f64::from).collect()).unwrap_or(vec![0.0; o]);
            layers.push((w, b, i, o));
        }
        Self { config: field.config.clone(), layers }
    }

    /// The SDF at `x`, written from the field's description: bone-local coordinates, softmax
    /// skinning over squared distance to the bone segments, capsule prior, Fourier features,
    /// ReLU MLP, residual scaled by 0.1.
    fn sdf(&self, skeleton: &Skeleton, pose: &Pose, x: DVec3) -> f64 {
        let c = &self.config;
        let bones = skeleton.len();
        let locals: Vec<DVec3> = (0..bones).map(|b| pose.to_local(b, x)).collect();
        let squared: Vec<f64> = (0..bones)
            .map(|b| {
                let l = locals[b];
                let along = l.y.clamp(0.0, skeleton.bones[b].length);
                DVec3::new(l.x, l.y - along, l.z).length_squared()
            })
            .collect();
        let width = c.skinning_width as f64;
        let logits: Vec<f64> = squared.iter().map(|d| -d / (2.0 * width * width)).collect();
        let top = logits.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let total: f64 = logits.iter().map(|l| (l - top).exp()).sum();
        let weights: Vec<f64> = logits.iter().map(|l| (l - top).exp() / total).collect();
        let prior = (0..bones).map(|b| weights[b] * (squared[b] + 1e-8).sqrt()).sum::<f64>() - c.prior_radius as f64;
        let mut features = Vec::new();
        for b in 0..bones {
            features.extend(locals[b].to_array().map(|v| v * weights[b]));
        }
        for &f in &c.frequencies {
            for b in 0..bones {
                features.extend(locals[b].to_array().map(|v| (v * f as f64).sin() * weights[b]));
            }
            for b in 0..bones {
                features.extend(locals[b].to_array().map(|v| (v * f as f64).cos() * weights[b]));
            }
        }
        let mut h = features;
        for (k, (w, bias, i, o)) in self.layers.iter().enumerate() {
            let mut next = bias.clone();
            for (r, value) in h.iter().enumerate().take(*i) {
                for col in 0..*o {
                    next[col] += value * w[r * o + col];
                }
            }
            if k + 1 < self.layers.len() {
                next.iter_mut().for_each(|v| *v = v.max(0.0));
            }
            h = next;
        }
        prior + 0.1 * h[0]
    }

    fn gradient(&self, skeleton: &Skeleton, pose: &Pose, x: DVec3, step: f64) -> DVec3 {
        let d = |e: DVec3| (self.sdf(skeleton, pose, x + e * step) - self.sdf(skeleton, pose, x - e * step)) / (2.0 * step);
        DVec3::new(d(DVec3::X), d(DVec3::Y), d(DVec3::Z))
    }
}

/// A field whose MLP residual matters (the initial one is near zero by design).
fn lively_field(bones: usize, device: &Device) -> AvatarField {
    let mut field = FieldConfig::for_bones(bones).init(device, 11);
    let scaled = (field.output.weight.val() * 60.0).into_data();
    field.output.weight = Param::from_tensor(Tensor::from_data(scaled, device));
    field
}

/// Points near the posed body: around random bone segments, within the skinning's reach.
fn points_near(character: &Character, pose: &Pose, count: usize, seed: u64) -> Vec<DVec3> {
    let mut s = Stream::new(seed, 1, 2);
    (0..count)
        .map(|_| {
            let b = (s.uniform() * character.skeleton.len() as f64) as usize % character.skeleton.len();
            let (head, tail) = pose.segment(&character.skeleton, b);
            let on = head + (tail - head) * s.uniform();
            on + DVec3::new(s.uniform() - 0.5, s.uniform() - 0.5, s.uniform() - 0.5) * 0.2
        })
        .collect()
}

fn to_tensor(points: &[DVec3], device: &Device) -> Tensor<2> {
    let flat: Vec<f32> = points.iter().flat_map(|p| p.as_vec3().to_array()).collect();
    Tensor::from_data(TensorData::new(flat, [points.len(), 3]), device)
}

#[test]
fn sdf_and_its_tangent_gradient_match_an_f64_reference() {
    let device = Device::flex();
    let character = Character::new(Kind::Human);
    let pose = character.pose(0.3, 0.4, DVec3::new(0.1, 0.0, -0.2));
    let field = lively_field(character.skeleton.len(), &device);
    let reference = Reference::new(&field);
    let pose_tensors = PoseTensors::new(&pose, &character.skeleton, &device);
    let points = points_near(&character, &pose, 400, 3);
    let (sdf, gradient) = field.sdf_and_gradient(to_tensor(&points, &device), &pose_tensors);
    let forward = values(field.sdf(to_tensor(&points, &device), &pose_tensors));
    let (sdf, gradient) = (values(sdf), values(gradient));
    let mut worst_sdf = 0.0f64;
    let mut worst_gradient = 0.0f64;
    let mut largest_residual_slope = 0.0f64;
    for (k, &x) in points.iter().enumerate() {
        let expected = reference.sdf(&character.skeleton, &pose, x);
        worst_sdf = worst_sdf.max((sdf[k] as f64 - expected).abs());
        assert_eq!(sdf[k], forward[k], "the tangent pass must compute the same SDF as forward()");
        let exact = reference.gradient(&character.skeleton, &pose, x, 1e-6);
        let got = DVec3::new(gradient[3 * k] as f64, gradient[3 * k + 1] as f64, gradient[3 * k + 2] as f64);
        worst_gradient = worst_gradient.max((got - exact).length() / exact.length().max(0.1));
        largest_residual_slope = largest_residual_slope.max((exact.length() - 1.0).abs());
    }
    eprintln!("worst SDF error {worst_sdf:.3e} m, worst gradient error {worst_gradient:.3e} (relative), largest |grad| - 1: {largest_residual_slope:.3}");
    assert!(worst_sdf < 1e-6, "SDF off the f64 reference by {worst_sdf}");
    assert!(worst_gradient < 2e-5, "tangent gradient off f64 central differences by {worst_gradient} (relative)");
    // The residual must bend the gradient away from the prior's unit length, or this tested little.
    assert!(largest_residual_slope > 0.2, "the MLP residual barely moves the gradient ({largest_residual_slope})");
    // Central differences (the slower method) agree to their truncation error.
    let central = values(field.sdf_gradient(to_tensor(&points, &device), &pose_tensors, GradientMethod::CentralDifferences(1e-3)));
    let agree =
        (0..points.len()).filter(|&k| (0..3).all(|a| (central[3 * k + a] - gradient[3 * k + a]).abs() < 0.02 * (1.0 + gradient[3 * k + a].abs()))).count();
    assert!(agree * 100 >= points.len() * 95, "only {agree} of {} points agree with central differences", points.len());
}

#[test]
fn the_eikonal_loss_trains_through_the_tangents() {
    let device = Device::flex().autodiff();
    let character = Character::new(Kind::Quadruped);
    let pose = character.pose(0.7, -0.3, DVec3::ZERO);
    let field = lively_field(character.skeleton.len(), &device);
    let pose_tensors = PoseTensors::new(&pose, &character.skeleton, &device);
    let points = points_near(&character, &pose, 64, 9);
    let (_, gradient) = field.sdf_and_gradient(to_tensor(&points, &device), &pose_tensors);
    let loss = umbra::losses::eikonal(gradient);
    let grads = loss.backward();
    let first = field.hidden[0].weight.grad(&grads).map(values).unwrap();
    let out = field.output.weight.grad(&grads).map(values).unwrap();
    // The same loss in f64 from the reference, differentiated by central differences in one
    // weight at a time.
    let reference = Reference::new(&field);
    let eikonal =
        |r: &Reference| points.iter().map(|&x| (r.gradient(&character.skeleton, &pose, x, 1e-6).length() - 1.0).powi(2)).sum::<f64>() / points.len() as f64;
    let mut s = Stream::new(4, 4, 4);
    let mut checked = 0;
    for (layer, analytic) in [(0usize, &first), (reference.layers.len() - 1, &out)] {
        let o = reference.layers[layer].3;
        for _ in 0..6 {
            let mut index = (s.uniform() * analytic.len() as f64) as usize % analytic.len();
            if layer != 0 {
                index -= index % o; // the SDF column of the output layer
            }
            let delta = 1e-4;
            let mut plus = Reference { config: reference.config.clone(), layers: reference.layers.clone() };
            let mut minus = Reference { config: reference.config.clone(), layers: reference.layers.clone() };
            plus.layers[layer].0[index] += delta;
            minus.layers[layer].0[index] -= delta;
            let numeric = (eikonal(&plus) - eikonal(&minus)) / (2.0 * delta);
            let got = analytic[index] as f64;
            assert!((got - numeric).abs() <= 2e-3 * numeric.abs().max(1e-2), "layer {layer} weight {index}: autodiff {got} vs f64 differences {numeric}");
            checked += 1;
        }
    }
    assert_eq!(checked, 12);
}
