//! Stress (issue 11): the field, the renderer and the losses far outside the body and on batches
//! that hold nothing, and whole fits at absurd learning rates: every output stays finite, or
//! the fit stops with an error that names the loss, never a panic. Seconds in all.

mod common;

use burn::tensor::{Tensor, TensorData};
use common::TempDir;
use glam::DVec3;
use umbra::backend::Backend;
use umbra::field::{FieldConfig, PoseTensors};
use umbra::fit_error::FitError;
use umbra::render::{render, RaySet, Sampling};
use umbra::synth::character::{Character, Kind};
use umbra::synth::TrainingLight;
use umbra::train::Trainer;

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
}

fn all_finite(v: &[f32]) -> bool {
    v.iter().all(|x| x.is_finite())
}

#[test]
fn the_field_and_the_renderer_stay_finite_far_away_and_on_rays_that_miss() {
    let device = Backend::Flex.device();
    let character = Character::new(Kind::Human);
    let pose = character.pose(0.3, 0.2, DVec3::ZERO);
    let (lo, hi) = pose.bounds(&character.skeleton);
    let lengths: Vec<f32> = character.skeleton.bones.iter().map(|b| b.length as f32).collect();
    let pose_tensors = PoseTensors::new(&pose, &character.skeleton, &device);
    for config in [FieldConfig::with_grid(lengths, (hi - lo).length() as f32), FieldConfig::for_bones(character.skeleton.len())] {
        let field = config.init(&device, 3);
        // Points at the body, 1 km away, and far along each axis in both directions.
        let mut points = vec![0.0f32, 1.0, 0.0, 1000.0, 0.0, 0.0, -1000.0, 5.0, 0.0, 0.0, 0.0, 1000.0, 1e4, -1e4, 1e4];
        points.extend([0.2f32, 0.9, -0.1]);
        let n = points.len() / 3;
        let (sdf, gradient) = field.sdf_and_gradient(Tensor::from_data(TensorData::new(points, [n, 3]), &device), &pose_tensors);
        let (sdf, gradient) = (values(sdf), values(gradient));
        assert!(all_finite(&sdf) && all_finite(&gradient), "{sdf:?} {gradient:?}");
        assert!(sdf[1] > 100.0, "a point 1 km away is far outside: {}", sdf[1]);
        let density = values(field.density(Tensor::from_data(TensorData::new(sdf.clone(), [n]), &device)));
        assert!(all_finite(&density) && density.iter().all(|d| *d >= 0.0), "{density:?}");

        // Rays that miss every bound (an empty interval), one from 1 km away, one grazing.
        let mut rays = RaySet::default();
        rays.push(DVec3::new(0.0, 1.0, 3.0), DVec3::new(0.0, 0.0, -1.0), None);
        rays.push(DVec3::new(1000.0, 1.0, 0.0), DVec3::new(-1.0, 0.0, 0.0), Some((999.0, 1001.0)));
        rays.push(DVec3::new(0.0, 1.0, 3.0), DVec3::new(0.0, 0.0, -1.0), Some((2.5, 3.5)));
        let sampling = Sampling { coarse: 8, probe: 8, fine: 8, albedo_floor: umbra::render::ALBEDO_WEIGHT_FLOOR, cull: false };
        let jitter = vec![0.5; rays.len() * sampling.draws()];
        let out = render(&field, &pose_tensors, &rays, sampling, &jitter, Some(umbra::field::GRADIENT), &device);
        let accumulation = values(out.accumulation);
        assert!(all_finite(&accumulation) && all_finite(&values(out.albedo)) && all_finite(&values(out.normal.unwrap())), "{accumulation:?}");
        assert!(accumulation[0].abs() < 1e-6, "a ray with an empty interval collects nothing: {}", accumulation[0]);
    }
}

#[test]
fn losses_of_an_all_background_batch_are_finite() {
    let device = Backend::Flex.device();
    let zeros2 = || Tensor::<2>::zeros([4, 3], &device);
    let zeros1 = || Tensor::<1>::zeros([4], &device);
    for value in [
        umbra::losses::rgb(zeros2(), zeros2()),
        umbra::losses::mask(zeros1(), zeros1(), None),
        umbra::losses::grey(zeros2(), zeros1()),
        umbra::losses::eikonal(zeros2()),
    ] {
        let v = values(value);
        assert!(all_finite(&v), "{v:?}");
    }
}

/// A short fit of a tiny scene with every learning rate multiplied by `factor`.
fn fit_with_rates(factor: f64) -> Result<(), FitError> {
    let dir = TempDir::new("rates");
    let scene = umbra::scene::Scene::load(&common::tiny_synth(dir.path(), TrainingLight::Sun, 24, 2, vec![], 5)).unwrap();
    let text = format!(
        "iterations = 12\nrays_per_batch = 64\nsamples_per_ray = 8\nfine_samples_per_ray = 8\nprobe_samples_per_ray = 8\ndensity_points = 16\nregulariser_points = 16\nlight_from = 4\n\
         [learning_rates]\nfield = {}\ngaussians = {}\nlight = {}\nfeatures = {}\n[losses]\nmask = 1.0\nrgb = 1.0\ndensity = 1.0\neikonal = 0.1\ncurvature = 0.05\n",
        2e-3 * factor,
        5e-3 * factor,
        2e-2 * factor,
        1e-2 * factor
    );
    let schedule = umbra::schedule::Schedule::parse(&text, std::path::Path::new("rates.toml")).unwrap();
    let mut trainer = Trainer::new(scene, schedule, Backend::Flex, 2)?;
    for _ in 0..12 {
        trainer.iterate()?;
    }
    Ok(())
}

#[test]
fn tiny_and_huge_learning_rates_either_fit_or_stop_naming_the_loss() {
    fit_with_rates(1e-9).expect("a fit that barely moves is still a fit");
    // The largest the schedule accepts (every rate below 10): Adam steps of metres.
    match fit_with_rates(400.0) {
        Ok(()) => {}
        Err(FitError::NonFinite { what, .. }) => assert!(what.contains("loss"), "{what}"),
        Err(other) => panic!("a diverging fit must stop as non-finite, not {other}"),
    }
}

#[test]
fn normals_and_the_eikonal_loss_have_finite_gradients_where_the_sdf_is_flat() {
    // An SDF can be flat at a point (the capped prior's slope is zero beyond the root's cap
    // and every decoder unit can be off): the rows' lengths must not send sqrt(0)'s infinite
    // slope, times zero, into the parameters.
    let device = burn::tensor::Device::flex().autodiff();
    let rows = Tensor::<2>::from_data(TensorData::new(vec![0.0f32, 0.0, 0.0, 0.6, 0.0, 0.8, 0.0, 0.0, 0.0], [3, 3]), &device).require_grad();
    let direction = Tensor::<2>::from_data(TensorData::new(vec![0.3f32, -0.2, 0.9], [1, 3]), &device);
    let loss = umbra::losses::eikonal(rows.clone()) + (umbra::render::unit_rows(rows.clone()) * direction).sum().reshape([1]);
    let grads = loss.backward();
    let gradient = values(rows.grad(&grads).unwrap());
    assert!(all_finite(&gradient), "{gradient:?}");
    // The unit row keeps its exact normal.
    let unit = values(umbra::render::unit_rows(rows.inner()));
    assert!((unit[3] - 0.6).abs() < 1e-6 && (unit[5] - 0.8).abs() < 1e-6, "{unit:?}");
}

#[test]
fn a_bone_far_from_the_others_leaves_the_field_and_the_renderer_finite() {
    // One hand posed 1 km from the body (a broken capture's pose): every bone is still looked
    // up, the far bone's grids hash points it never sees, and the body near the others is
    // what it was.
    let device = Backend::Flex.device();
    let character = Character::new(Kind::Human);
    let mut pose = character.pose(0.3, 0.2, DVec3::ZERO);
    let (lo, hi) = pose.bounds(&character.skeleton);
    let extent = (hi - lo).length() as f32;
    let far_bone = character.skeleton.len() - 1;
    pose.bone_to_world[far_bone].w_axis += glam::DVec4::new(1000.0, 0.0, 0.0, 0.0);
    let lengths: Vec<f32> = character.skeleton.bones.iter().map(|b| b.length as f32).collect();
    let pose_tensors = PoseTensors::new(&pose, &character.skeleton, &device);
    let far = pose.bone_to_world[far_bone].w_axis.truncate();
    for config in [FieldConfig::with_grid(lengths.clone(), extent), FieldConfig::for_bones(character.skeleton.len())] {
        let field = config.init(&device, 5);
        let mut points = vec![0.0f32, 1.0, 0.0, 0.2, 0.9, -0.1, far.x as f32, far.y as f32 + 0.05, far.z as f32, 500.0, 1.0, 0.0];
        points.extend([far.x as f32 + 0.3, far.y as f32, far.z as f32 - 0.2]);
        let n = points.len() / 3;
        let (sdf, gradient) = field.sdf_and_gradient(Tensor::from_data(TensorData::new(points, [n, 3]), &device), &pose_tensors);
        let (sdf, gradient) = (values(sdf), values(gradient));
        assert!(all_finite(&sdf) && all_finite(&gradient), "{sdf:?} {gradient:?}");
        let mut rays = RaySet::default();
        rays.push(DVec3::new(0.0, 1.0, 3.0), DVec3::new(0.0, 0.0, -1.0), Some((2.0, 4.0)));
        rays.push(far + DVec3::new(0.0, 0.0, 3.0), DVec3::new(0.0, 0.0, -1.0), Some((2.0, 4.0)));
        let sampling = Sampling { coarse: 8, probe: 8, fine: 8, albedo_floor: umbra::render::ALBEDO_WEIGHT_FLOOR, cull: false };
        let jitter = vec![0.5; rays.len() * sampling.draws()];
        let out = render(&field, &pose_tensors, &rays, sampling, &jitter, Some(umbra::field::GRADIENT), &device);
        assert!(all_finite(&values(out.accumulation)) && all_finite(&values(out.albedo)) && all_finite(&values(out.normal.unwrap())));
    }
}
