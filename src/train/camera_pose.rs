//! Each training camera's pose refined while fitting: a small turn about its centre, learned
//! with the field from the stage the schedule's `camera_prior` term starts at, and held near the
//! calibration's pose by that term. A batch's rays leave their cameras as turned so far, and the
//! render carries a zero increment of every camera's turn (`skeleton::ViewIncrement`) through
//! the field's lookups and into the shading's normals and shadows; its gradient is one host-side
//! Adam step on three numbers a camera. The centre is kept: seen from a few metres, a
//! calibration's millimetres across the view turn the image as a hundredth of a degree does,
//! and along it scale it by a thousandth, while a shift and a turn that swing the camera about
//! the body leave its silhouettes almost as they were, a direction the fit cannot hold (with
//! both refined the centres ran 15 cm off in 1,400 iterations). Nor is the rig's common roll
//! refined: every camera rolled about its viewing axis by `theta . axis` is, to first order, the
//! whole rig turned by `theta` about the body, which the field and the motion take up as well,
//! so the images do not decide it; after each step the turns lose the part such a common turn
//! accounts for (`without_common_roll`). Test views are rendered from their cameras as given.

use super::host_adam::CameraRows;
use crate::scene::{Camera, Ray, Scene};
use burn::tensor::{Device, Tensor, TensorData};
use glam::{DMat3, DMat4, DQuat, DVec3};

/// The training cameras' turns about their centres (radians) and their optimiser's state.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraPoses {
    turns: CameraRows,
    /// Per row, its camera's viewing axis in the world.
    axes: Vec<DVec3>,
}

/// How far the refinement turned each training camera, and over them all (degrees).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct CamerasMoved {
    pub mean_degrees: f64,
    pub largest_degrees: f64,
    pub cameras: Vec<CameraMoved>,
}

/// How far one camera was turned about its centre (degrees).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct CameraMoved {
    pub camera: String,
    pub degrees: f64,
}

/// The rotation of a rotation vector (radians).
fn rotation(turn: [f64; 3]) -> DMat3 {
    DMat3::from_quat(DQuat::from_scaled_axis(DVec3::from_array(turn)))
}

/// The direction `camera` looks along in the world (its axes are OpenCV's: +z forward).
fn viewing_axis(camera: &Camera) -> DVec3 {
    camera.camera_to_world.z_axis.truncate().normalize_or(DVec3::Z)
}

/// `turns` (world rotation vectors, one per camera) less the rolls a common turn of the rig
/// accounts for: with `a_i` each camera's viewing axis, the `theta` that best gives each camera's
/// roll `turn_i . a_i` as `theta . a_i` (least squares), and each turn less `(theta . a_i) a_i`.
/// What is left of the rolls is orthogonal to every common turn's: `sum_i a_i (turn_i . a_i)` is
/// zero. Two cameras leave a common turn about the axis normal to both undecided; a small ridge
/// keeps it at none.
fn without_common_roll(turns: &mut [[f64; 3]], axes: &[DVec3]) {
    let (mut normal, mut rolls) = (DMat3::ZERO, DVec3::ZERO);
    for (turn, &a) in turns.iter().zip(axes) {
        normal += DMat3::from_cols(a * a.x, a * a.y, a * a.z);
        rolls += a * DVec3::from_array(*turn).dot(a);
    }
    let theta = (normal + DMat3::from_diagonal(DVec3::splat(1e-9))).inverse() * rolls;
    if !theta.is_finite() {
        return;
    }
    for (turn, &a) in turns.iter_mut().zip(axes) {
        *turn = (DVec3::from_array(*turn) - a * theta.dot(a)).to_array();
    }
}

impl CameraPoses {
    /// For a scene whose training images come from two or more cameras (none otherwise: one
    /// camera's pose is the body's root seen from it, which the motion holds).
    pub fn new(scene: &Scene) -> Option<Self> {
        let turns = CameraRows::of_training_cameras(scene)?;
        let axes = turns.cameras().iter().map(|&c| scene.cameras.get(c).map_or(DVec3::Z, viewing_axis)).collect();
        Some(Self { turns, axes })
    }

    /// Scene camera `camera`'s row, if it is refined.
    pub fn row(&self, camera: usize) -> Option<usize> {
        self.turns.row(camera)
    }

    /// How many cameras are refined.
    pub fn len(&self) -> usize {
        self.turns.cameras().len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A ray of scene camera `camera` as its turned camera casts it: from the same centre,
    /// turned about it (the ray as given for a camera that is not refined).
    pub fn corrected_ray(&self, camera: usize, ray: Ray) -> Ray {
        match self.row(camera) {
            Some(row) => Ray { origin: ray.origin, direction: rotation(self.turns.values[row]) * ray.direction },
            None => ray,
        }
    }

    /// Scene camera `camera` as corrected (as given when it is not refined).
    pub fn corrected_camera(&self, camera: usize, given: &Camera) -> Camera {
        let Some(row) = self.row(camera) else { return given.clone() };
        let mut out = given.clone();
        let centre = given.centre();
        out.camera_to_world =
            DMat4::from_translation(centre) * DMat4::from_mat3(rotation(self.turns.values[row])) * DMat4::from_translation(-centre) * given.camera_to_world;
        out
    }

    /// The turns as a leaf (`[C, 3]`) for the prior that holds them near the given poses.
    pub fn leaf(&self, device: &Device) -> Tensor<2> {
        let values: Vec<f32> = self.turns.values.iter().flatten().map(|&v| v as f32).collect();
        Tensor::from_data(TensorData::new(values, [self.len(), 3]), device).require_grad()
    }

    /// One Adam step of `rate`: `leaf` is the gradient of the leaf (the prior), `increment`
    /// that of the view increment the render carried (each camera's world turn about its
    /// centre; empty when nothing was rendered).
    pub fn step(&mut self, leaf: &[f32], increment: &[f32], rate: f64) {
        if !increment.is_empty() && increment.len() != leaf.len() {
            return;
        }
        let gradient: Vec<f32> = leaf.iter().enumerate().map(|(k, g)| g + increment.get(k).copied().unwrap_or(0.0)).collect();
        self.turns.step(&gradient, rate);
        without_common_roll(&mut self.turns.values, &self.axes);
    }

    /// How far the corrections turned the training cameras (of the scene's `cameras`).
    pub fn moved(&self, scene_cameras: &[Camera]) -> CamerasMoved {
        let cameras: Vec<CameraMoved> = self
            .turns
            .cameras()
            .iter()
            .zip(&self.turns.values)
            .map(|(&c, turn)| CameraMoved {
                camera: scene_cameras.get(c).map(|camera| camera.name.clone()).unwrap_or_default(),
                degrees: DVec3::from_array(*turn).length().to_degrees(),
            })
            .collect();
        let n = cameras.len().max(1) as f64;
        CamerasMoved {
            mean_degrees: cameras.iter().map(|c| c.degrees).sum::<f64>() / n,
            largest_degrees: cameras.iter().map(|c| c.degrees).fold(0.0, f64::max),
            cameras,
        }
    }

    /// The state a checkpoint keeps.
    pub fn to_json(&self) -> serde_json::Value {
        self.turns.to_json("turns")
    }

    /// The state from a checkpoint's `to_json`, refused when it is not this scene's cameras.
    pub fn restore(&mut self, value: &serde_json::Value) -> Result<(), String> {
        self.turns.restore(value, "turns")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn poses(n: usize) -> CameraPoses {
        CameraPoses { turns: CameraRows::zeros((0..n).map(Some).collect(), (0..n).collect()), axes: vec![DVec3::Z; n] }
    }

    /// Eight cameras on a ring about a body, looking at it from a little above.
    fn ring() -> CameraPoses {
        let cameras: Vec<Camera> = (0..8)
            .map(|k| {
                let angle = std::f64::consts::TAU * k as f64 / 8.0;
                let eye = DVec3::new(3.0 * angle.sin(), 1.6, 3.0 * angle.cos());
                Camera::look_at(&format!("c{k}"), eye, DVec3::new(0.0, 1.0, 0.0), DVec3::Y, 64, 64, 50.0)
            })
            .collect();
        let axes = cameras.iter().map(viewing_axis).collect();
        CameraPoses { turns: CameraRows::zeros((0..8).map(Some).collect(), (0..8).collect()), axes }
    }

    /// Rolls that a common turn of the rig accounts for are not refined; a camera's own roll
    /// keeps what no common turn gives, turns across the views (which move the images) are kept
    /// whole, and after any step the rolls left are orthogonal to every common turn's.
    #[test]
    fn the_rigs_common_roll_is_not_refined() {
        let mut p = ring();
        let theta = DVec3::new(0.3, -0.2, 0.9) * 1e-3;
        let mut common: Vec<[f64; 3]> = p.axes.iter().map(|&a| (a * theta.dot(a)).to_array()).collect();
        without_common_roll(&mut common, &p.axes);
        assert!(common.iter().flatten().all(|v| v.abs() < 1e-11), "{common:?}");
        let mut across: Vec<[f64; 3]> = p.axes.iter().enumerate().map(|(k, &a)| (a.cross(DVec3::Y).normalize() * 1e-3 * k as f64).to_array()).collect();
        let given = across.clone();
        without_common_roll(&mut across, &p.axes);
        assert!(across.iter().flatten().zip(given.iter().flatten()).all(|(a, b)| (a - b).abs() < 1e-15));
        let mut own: Vec<[f64; 3]> = vec![[0.0; 3]; 8];
        own[0] = (p.axes[0] * 1e-3).to_array();
        without_common_roll(&mut own, &p.axes);
        let kept = DVec3::from_array(own[0]).dot(p.axes[0]);
        assert!(kept > 5e-4 && kept < 1e-3, "camera 0 keeps most of its roll: {kept}");
        // Steps of any gradient: the rolls left never hold a common turn's.
        let mut stream = crate::random::Stream::new(7, 0, 0);
        for _ in 0..20 {
            let gradient: Vec<f32> = (0..24).map(|_| stream.uniform() as f32 - 0.5).collect();
            p.step(&[0.0; 24], &gradient, 1e-3);
            let normal: DVec3 = (0..8).map(|k| p.axes[k] * DVec3::from_array(p.turns.values[k]).dot(p.axes[k])).sum();
            assert!(normal.length() < 1e-11, "{normal}");
        }
        assert!(p.turns.values.iter().flatten().any(|v| v.abs() > 1e-3), "the turns moved");
    }

    /// A corrected camera casts the corrected rays: each pixel's ray from its centre in the
    /// turned direction, and it projects the points of those rays back to their pixels.
    #[test]
    fn a_corrected_camera_casts_its_corrected_rays() {
        let given = Camera::look_at("c", DVec3::new(0.3, 1.2, 3.0), DVec3::new(0.0, 1.0, 0.0), DVec3::Y, 64, 48, 70.0);
        let mut p = poses(2);
        p.turns.values[0] = [0.01, -0.02, 0.005];
        let corrected = p.corrected_camera(0, &given);
        assert!((corrected.centre() - given.centre()).length() < 1e-12);
        for (i, j) in [(0, 0), (31, 20), (63, 47)] {
            let ray = p.corrected_ray(0, given.pixel_ray(i, j));
            let direct = corrected.pixel_ray(i, j);
            assert!((ray.origin - direct.origin).length() < 1e-12 && (ray.direction - direct.direction).length() < 1e-12);
            let back = corrected.project(ray.at(2.0)).unwrap();
            assert!((back - glam::DVec2::new(i as f64 + 0.5, j as f64 + 0.5)).length() < 1e-9);
            assert!((ray.direction - given.pixel_ray(i, j).direction).length() > 1e-3, "the ray turned");
        }
        assert_eq!(p.corrected_ray(5, given.pixel_ray(3, 4)), given.pixel_ray(3, 4), "a camera without a row is as given");
    }

    /// Adam's first step moves each value by about the rate against its gradient; a non-finite
    /// gradient is not taken; the state survives a checkpoint's round trip and a checkpoint of
    /// other cameras is refused.
    #[test]
    fn turns_step_against_their_gradient_and_survive_a_checkpoint() {
        let mut p = poses(2);
        let leaf = [0.0f32; 6];
        let mut increment = [0.0f32; 6];
        increment[0] = 1.0; // camera 0's turn about x
        increment[3 + 1] = -2.0; // camera 1's about y
        p.step(&leaf, &increment, 1e-3);
        let turns = &p.turns.values;
        assert!((turns[0][0] + 1e-3).abs() < 1e-9 && (turns[1][1] - 1e-3).abs() < 1e-9 && turns[0][1] == 0.0);
        p.step(&leaf, &[f32::NAN; 6], 1e-3);
        assert_eq!(p.turns.steps(), 1);
        let moved = p.moved(&[]);
        assert!((moved.cameras[0].degrees - 1e-3f64.to_degrees()).abs() < 1e-9 && (moved.largest_degrees - 1e-3f64.to_degrees()).abs() < 1e-9, "{moved:?}");
        let mut back = poses(2);
        back.restore(&p.to_json()).unwrap();
        assert_eq!(back, p);
        assert!(back.restore(&serde_json::json!({"cameras": [0, 2]})).is_err());
    }
}
