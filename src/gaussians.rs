//! Bone-anchored anisotropic 3D Gaussians: each belongs to a bone and has a mean and rotation
//! in that bone's frame, three per-axis scales and an amplitude (density at its centre).
//! A set is posed by a frame's `bone_to_world` and serialises to and from JSON.

use crate::scene::json::{self, At, SceneError};
use crate::skeleton::{Pose, Skeleton};
use glam::{DMat3, DQuat, DVec3};
use serde::{Deserialize, Serialize};
use std::path::Path;

pub const FORMAT: &str = "umbra-gaussians/1";

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Gaussian {
    pub bone: usize,
    /// Mean in the bone's local frame (metres).
    pub mean: [f64; 3],
    /// Rotation in the bone's local frame, unit quaternion `[x, y, z, w]`.
    pub rotation: [f64; 4],
    /// Standard deviation along each of the Gaussian's own axes (metres).
    pub scales: [f64; 3],
    /// Density at the centre (1/m).
    pub amplitude: f64,
}

#[derive(Clone, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct GaussianSet {
    pub gaussians: Vec<Gaussian>,
}

pub use crate::shadow::PosedGaussian;

impl GaussianSet {
    /// `per_bone` Gaussians spread along each bone from head to tail, isotropic with `std`.
    pub fn along_bones(skeleton: &Skeleton, per_bone: usize, std: f64, amplitude: f64) -> Self {
        let mut gaussians = Vec::with_capacity(skeleton.len() * per_bone);
        for (bone, b) in skeleton.bones.iter().enumerate() {
            for k in 0..per_bone {
                let y = b.length * (k as f64 + 0.5) / per_bone as f64;
                gaussians.push(Gaussian { bone, mean: [0.0, y, 0.0], rotation: [0.0, 0.0, 0.0, 1.0], scales: [std; 3], amplitude });
            }
        }
        Self { gaussians }
    }

    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

    /// The same Gaussians, each moved to bone `bones[i]` where it differs, unchanged in world
    /// space in `pose`: its mean and rotation re-expressed in the new bone's frame.
    pub fn rebound(&self, bones: &[usize], pose: &Pose) -> Self {
        let frame_rotation = |bone: usize| DQuat::from_mat3(&DMat3::from_mat4(pose.bone_to_world[bone])).normalize();
        let gaussians = self
            .gaussians
            .iter()
            .zip(bones)
            .map(|(g, &bone)| {
                if bone == g.bone {
                    return g.clone();
                }
                let world = pose.bone_to_world[g.bone].transform_point3(DVec3::from_array(g.mean));
                let mean = pose.bone_to_world[bone].inverse().transform_point3(world);
                let rotation = frame_rotation(bone).inverse() * frame_rotation(g.bone) * DQuat::from_array(g.rotation).normalize();
                Gaussian { bone, mean: mean.to_array(), rotation: rotation.normalize().to_array(), ..g.clone() }
            })
            .collect();
        Self { gaussians }
    }

    /// Places every Gaussian in world space with its bone's transform.
    pub fn pose(&self, pose: &Pose) -> Vec<PosedGaussian> {
        self.gaussians
            .iter()
            .map(|g| {
                let m = pose.bone_to_world[g.bone];
                let bone_rotation = DMat3::from_mat4(m);
                let local = DMat3::from_quat(DQuat::from_array(g.rotation).normalize());
                PosedGaussian {
                    mean: m.transform_point3(DVec3::from_array(g.mean)),
                    axes: bone_rotation * local,
                    scales: DVec3::from_array(g.scales),
                    amplitude: g.amplitude,
                }
            })
            .collect()
    }

    pub fn to_json(&self) -> String {
        let body = serde_json::json!({ "format": FORMAT, "gaussians": self.gaussians });
        serde_json::to_string_pretty(&body).unwrap_or_default()
    }

    /// Writes the set atomically.
    pub fn save(&self, path: &Path) -> std::io::Result<()> {
        crate::imageio::write_atomic(path, self.to_json().as_bytes())
    }

    /// Reads a set, checking every value; `bones` is the skeleton size the set must fit.
    pub fn load(path: &Path, bones: Option<usize>) -> Result<Self, SceneError> {
        let text = crate::files::read_text(path, crate::files::SCENE_BYTES).map_err(|e| SceneError {
            file: path.to_path_buf(),
            path: String::new(),
            message: format!("cannot read: {e}"),
        })?;
        Self::parse(&text, path, bones)
    }

    pub fn parse(text: &str, file: &Path, bones: Option<usize>) -> Result<Self, SceneError> {
        let value = json::parse(text, file)?;
        let doc = At::root(&value, file);
        let format = doc.field("format")?;
        if format.str()? != FORMAT {
            return Err(format.error(format!("unsupported format {:?}, expected {FORMAT:?}", format.str()?)));
        }
        let mut gaussians = Vec::new();
        for item in doc.field("gaussians")?.array()? {
            let bone_node = item.field("bone")?;
            let bone = match bones {
                Some(n) => bone_node.index(n, "skeleton.bones")?,
                None => bone_node.i64().and_then(|b| usize::try_from(b).map_err(|_| bone_node.error("must be >= 0")))?,
            };
            let mean = item.field("mean")?.vec3()?.to_array();
            let rotation_node = item.field("rotation")?;
            let q = rotation_node.array()?;
            if q.len() != 4 {
                return Err(rotation_node.error("expected a quaternion [x, y, z, w]"));
            }
            let rotation = [q[0].f64()?, q[1].f64()?, q[2].f64()?, q[3].f64()?];
            let norm = rotation.iter().map(|c| c * c).sum::<f64>().sqrt();
            if (norm - 1.0).abs() > 1e-3 {
                return Err(rotation_node.error(format!("quaternion must have unit length, found {norm}")));
            }
            let scales_node = item.field("scales")?;
            let scales = scales_node.vec3()?;
            if scales.min_element() <= 0.0 {
                return Err(scales_node.error("scales must be > 0"));
            }
            let amplitude_node = item.field("amplitude")?;
            let amplitude = amplitude_node.f64()?;
            if amplitude < 0.0 {
                return Err(amplitude_node.error("amplitude must be >= 0"));
            }
            gaussians.push(Gaussian { bone, mean, rotation, scales: scales.to_array(), amplitude });
        }
        Ok(Self { gaussians })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::Bone;

    #[test]
    fn json_round_trip_and_errors() {
        let skeleton = Skeleton { bones: vec![Bone { name: "a".into(), parent: None, length: 0.4 }] };
        let mut set = GaussianSet::along_bones(&skeleton, 3, 0.05, 10.0);
        set.gaussians[1].rotation = DQuat::from_rotation_z(0.4).to_array();
        let text = set.to_json();
        let back = GaussianSet::parse(&text, Path::new("g.json"), Some(1)).unwrap();
        assert_eq!(back, set);
        let broken = text.replacen("\"bone\": 0", "\"bone\": 3", 1);
        let err = GaussianSet::parse(&broken, Path::new("g.json"), Some(1)).unwrap_err();
        assert_eq!(err.path, "gaussians[0].bone");
    }

    #[test]
    fn posing_moves_the_mean_with_the_bone() {
        let skeleton = Skeleton { bones: vec![Bone { name: "a".into(), parent: None, length: 1.0 }] };
        let set = GaussianSet::along_bones(&skeleton, 1, 0.1, 1.0);
        let m = glam::DMat4::from_rotation_translation(DQuat::from_rotation_z(std::f64::consts::FRAC_PI_2), DVec3::new(1.0, 0.0, 0.0));
        let posed = set.pose(&Pose { bone_to_world: vec![m] });
        assert!((posed[0].mean - DVec3::new(0.5, 0.0, 0.0)).length() < 1e-12);
        assert!((posed[0].density(posed[0].mean) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn a_rebound_gaussian_stays_where_it_was_in_world_space() {
        let skeleton = Skeleton { bones: vec![Bone { name: "a".into(), parent: None, length: 0.5 }, Bone { name: "b".into(), parent: Some(0), length: 0.4 }] };
        let mut set = GaussianSet::along_bones(&skeleton, 2, 0.05, 10.0);
        for (k, g) in set.gaussians.iter_mut().enumerate() {
            g.rotation = DQuat::from_euler(glam::EulerRot::XYZ, 0.3 * k as f64, -0.2, 0.7).to_array();
            g.scales = [0.02, 0.05, 0.09];
        }
        let pose = Pose {
            bone_to_world: vec![
                glam::DMat4::from_rotation_translation(DQuat::from_rotation_y(0.8), DVec3::new(0.1, 1.0, -0.2)),
                glam::DMat4::from_rotation_translation(DQuat::from_euler(glam::EulerRot::ZXY, 1.1, 0.4, -0.3), DVec3::new(0.3, 0.6, 0.1)),
            ],
        };
        // Every Gaussian to the other bone.
        let bones: Vec<usize> = set.gaussians.iter().map(|g| 1 - g.bone).collect();
        let moved = set.rebound(&bones, &pose);
        assert!(moved.gaussians.iter().zip(&bones).all(|(g, &b)| g.bone == b));
        for (before, after) in set.pose(&pose).iter().zip(moved.pose(&pose)) {
            assert!((before.mean - after.mean).length() < 1e-12);
            for x in [DVec3::X, DVec3::Y, DVec3::Z] {
                let p = before.mean + x * 0.03;
                assert!((before.density(p) - after.density(p)).abs() < 1e-9 * before.amplitude, "the same density around it");
            }
        }
        // Another pose moves it with its new bone.
        let other = Pose { bone_to_world: vec![pose.bone_to_world[0], glam::DMat4::from_translation(DVec3::new(0.0, 2.0, 0.0))] };
        let on_b = moved.gaussians.iter().position(|g| g.bone == 1).unwrap();
        let shift = moved.pose(&other)[on_b].mean - moved.pose(&pose)[on_b].mean;
        assert!(shift.length() > 0.1);
    }

    #[test]
    fn posed_values_are_the_posed_gaussians_off_the_graph() {
        let skeleton = Skeleton { bones: vec![Bone { name: "a".into(), parent: None, length: 0.5 }, Bone { name: "b".into(), parent: Some(0), length: 0.4 }] };
        let mut set = GaussianSet::along_bones(&skeleton, 2, 0.05, 10.0);
        set.gaussians[1].rotation = DQuat::from_rotation_x(0.6).to_array();
        let pose = Pose {
            bone_to_world: vec![
                glam::DMat4::from_rotation_translation(DQuat::from_rotation_y(0.8), DVec3::new(0.1, 1.0, -0.2)),
                glam::DMat4::from_rotation_translation(DQuat::from_rotation_z(1.1), DVec3::new(0.3, 0.6, 0.1)),
            ],
        };
        let device = burn::tensor::Device::flex().autodiff();
        let params = GaussianParams::from_set(&set, 0.9, &device);
        let pose = crate::skeleton::PoseTensors::new(&pose, &skeleton, &device);
        let (tracked, values) = (params.posed(&pose), params.posed_values(&pose));
        let flat = |t: burn::tensor::Tensor<3>| t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
        assert_eq!(flat(tracked.whiten.clone()), flat(values.whiten.clone()));
        assert_eq!(flat(tracked.means.clone().unsqueeze()), flat(values.means.clone().unsqueeze()));
        // The parameters get a gradient through the tracked means, none through the values
        // (whose whitening would give the log scales one).
        let grads = (tracked.means.sum() + values.whiten.sum() + values.amplitudes.sum()).backward();
        assert!(params.means.val().grad(&grads).is_some());
        assert!(params.log_scales.val().grad(&grads).is_none() && params.log_amplitudes.val().grad(&grads).is_none());
    }
}

/// Learnable Gaussians (burn module): bone-local means `[G, 3]` in body units, quaternions
/// `[G, 4]` (x, y, z, w), log scales `[G, 3]` and log amplitudes `[G]`; each belongs to a fixed
/// bone. Means in body units (metres over `unit`, `skeleton::body_length(1, extent)`) make an
/// optimizer's step the same fraction of any body.
#[derive(burn::module::Module, Debug)]
pub struct GaussianParams {
    pub means: burn::module::Param<burn::tensor::Tensor<2>>,
    pub rotations: burn::module::Param<burn::tensor::Tensor<2>>,
    pub log_scales: burn::module::Param<burn::tensor::Tensor<2>>,
    pub log_amplitudes: burn::module::Param<burn::tensor::Tensor<1>>,
    #[module(skip)]
    pub bones: Vec<usize>,
    /// Metres per body unit.
    #[module(skip)]
    pub unit: f32,
}

mod learnable {
    use super::{Gaussian, GaussianParams, GaussianSet};
    use crate::shadow::tensor::GaussianTensors;
    use crate::skeleton::PoseTensors;
    use burn::module::Param;
    use burn::tensor::{Device, Int, Tensor, TensorData};

    /// Values a Gaussian in `GaussianParams::rows`.
    const ROW: usize = 11;

    impl GaussianParams {
        /// Learnable copies of `set` on a body whose unit is `unit` metres.
        pub fn from_set(set: &GaussianSet, unit: f32, device: &Device) -> Self {
            let n = set.len();
            let flat = |f: &dyn Fn(&Gaussian) -> Vec<f32>| set.gaussians.iter().flat_map(f).collect::<Vec<f32>>();
            Self {
                means: Param::from_tensor(Tensor::from_data(TensorData::new(flat(&|g| g.mean.map(|v| v as f32 / unit).to_vec()), [n, 3]), device)),
                rotations: Param::from_tensor(Tensor::from_data(TensorData::new(flat(&|g| g.rotation.map(|v| v as f32).to_vec()), [n, 4]), device)),
                log_scales: Param::from_tensor(Tensor::from_data(TensorData::new(flat(&|g| g.scales.map(|v| (v as f32).ln()).to_vec()), [n, 3]), device)),
                log_amplitudes: Param::from_tensor(Tensor::from_data(TensorData::new(flat(&|g| vec![(g.amplitude as f32).ln()]), [n]), device)),
                bones: set.gaussians.iter().map(|g| g.bone).collect(),
                unit,
            }
        }

        /// Bone-local means in metres.
        pub fn means_metres(&self) -> Tensor<2> {
            self.means.val() * self.unit
        }

        pub fn len(&self) -> usize {
            self.bones.len()
        }

        pub fn is_empty(&self) -> bool {
            self.bones.is_empty()
        }

        pub fn scales(&self) -> Tensor<2> {
            self.log_scales.val().exp()
        }

        pub fn amplitudes(&self) -> Tensor<1> {
            self.log_amplitudes.val().exp()
        }

        /// Rotation matrices `[G, 3, 3]` (row-major; columns are the Gaussians' local axes).
        pub fn rotation_matrices(&self) -> Tensor<3> {
            let q = self.rotations.val();
            let n = self.len();
            let q = q.clone() / (q.clone() * q).sum_dim(1).sqrt().clamp_min(1e-8);
            let c = |k: usize| q.clone().narrow(1, k, 1);
            let (x, y, z, w) = (c(0), c(1), c(2), c(3));
            let two = |a: Tensor<2>| a * 2.0;
            let entries = vec![
                (two(y.clone() * y.clone() + z.clone() * z.clone())).neg() + 1.0,
                two(x.clone() * y.clone() - z.clone() * w.clone()),
                two(x.clone() * z.clone() + y.clone() * w.clone()),
                two(x.clone() * y.clone() + z.clone() * w.clone()),
                (two(x.clone() * x.clone() + z.clone() * z.clone())).neg() + 1.0,
                two(y.clone() * z.clone() - x.clone() * w.clone()),
                two(x.clone() * z.clone() - y.clone() * w.clone()),
                two(y.clone() * z.clone() + x.clone() * w.clone()),
                (two(x.clone() * x + y.clone() * y)).neg() + 1.0,
            ];
            Tensor::cat(entries, 1).reshape([n, 3, 3])
        }

        fn bone_index(&self, device: &Device) -> Tensor<1, Int> {
            Tensor::from_data(TensorData::new(self.bones.iter().map(|&b| b as i64).collect::<Vec<i64>>(), [self.len()]), device)
        }

        /// World-space Gaussians in a pose, as values off the autodiff graph: the parameters
        /// read as fresh leaves, since posing them and detaching the result would leave the
        /// posing's operations in their graph until some backward reached them.
        pub fn posed_values(&self, pose: &PoseTensors) -> GaussianTensors {
            fn leaf<const D: usize>(p: &Param<Tensor<D>>) -> Param<Tensor<D>> {
                Param::from_tensor(p.val().without_autodiff().autodiff()).set_require_grad(false)
            }
            let values = Self {
                means: leaf(&self.means),
                rotations: leaf(&self.rotations),
                log_scales: leaf(&self.log_scales),
                log_amplitudes: leaf(&self.log_amplitudes),
                bones: self.bones.clone(),
                unit: self.unit,
            };
            values.posed(pose)
        }

        /// World-space Gaussians in a pose, differentiable in every parameter.
        pub fn posed(&self, pose: &PoseTensors) -> GaussianTensors {
            let device = self.means.val().device();
            let index = self.bone_index(&device);
            let n = self.len();
            let bone_rotation = pose.rotations.clone().select(0, index.clone());
            let bone_translation = pose.translations.clone().select(0, index);
            let means = bone_rotation.clone().matmul(self.means_metres().reshape([n, 3, 1])).reshape([n, 3]) + bone_translation;
            let rotations = bone_rotation.matmul(self.rotation_matrices());
            GaussianTensors::from_world(means, rotations, self.scales(), self.amplitudes())
        }

        /// The mixture density `sum_g A_g exp(-|W_g (x - mu_g)|^2 / 2)` at world points `[N, 3]`.
        pub fn mixture_density(posed: &GaussianTensors, points: Tensor<2>) -> Tensor<1> {
            let [p, _] = points.dims();
            let n = posed.len();
            let rows = posed.whiten.clone().reshape([n * 3, 3]).transpose();
            let whitened_points = points.matmul(rows).reshape([p, n, 3]);
            let whitened_means = (posed.whiten.clone() * posed.means.clone().unsqueeze_dim::<3>(1)).sum_dim(2).reshape([1, n, 3]);
            let d = whitened_points - whitened_means;
            let m2 = (d.clone() * d).sum_dim(2).reshape([p, n]);
            ((m2 * -0.5).exp() * posed.amplitudes.clone().reshape([1, n])).sum_dim(1).reshape([p])
        }

        /// Moves Gaussian `i` to bone `bones[i]`, unchanged in world space in `pose`
        /// (`GaussianSet::rebound`). The parameters keep their identities, so the optimizer's
        /// state carries over (its moments were taken in the old bones' frames: a step's worth
        /// of mismatch, which Adam's decay forgets).
        pub fn rebind(&mut self, bones: &[usize], pose: &crate::skeleton::Pose) {
            let set = self.to_set().rebound(bones, pose);
            let device = self.means.val().device();
            let n = set.len();
            let means: Vec<f32> = set.gaussians.iter().flat_map(|g| g.mean.map(|v| (v / self.unit as f64) as f32)).collect();
            let rotations: Vec<f32> = set.gaussians.iter().flat_map(|g| g.rotation.map(|v| v as f32)).collect();
            // New values under the same identities, still trained.
            self.means = self.means.clone().map(|_| Tensor::from_data(TensorData::new(means, [n, 3]), &device).require_grad());
            self.rotations = self.rotations.clone().map(|_| Tensor::from_data(TensorData::new(rotations, [n, 4]), &device).require_grad());
            self.bones = bones.to_vec();
        }

        /// The current values as one flat tensor (`ROW` a Gaussian: mean, rotation, scales,
        /// amplitude), read in one copy: a training step's batch needs them, and on a GPU
        /// every read is a wait (the step reads them with its check after the update).
        pub fn rows(&self) -> Tensor<1> {
            let n = self.len();
            Tensor::cat(vec![self.means_metres(), self.rotations.val(), self.scales(), self.amplitudes().reshape([n, 1])], 1).reshape([n * ROW])
        }

        /// The set from `rows`' values read (none unless there are as many as it gives).
        pub fn set_from_rows(&self, rows: &[f32]) -> Option<GaussianSet> {
            if rows.len() != self.len() * ROW {
                return None;
            }
            let gaussians = self
                .bones
                .iter()
                .zip(rows.chunks_exact(ROW))
                .map(|(&bone, row)| {
                    let row: Vec<f64> = row.iter().map(|&v| f64::from(v)).collect();
                    let q = glam::DQuat::from_array([row[3], row[4], row[5], row[6]]).normalize();
                    Gaussian { bone, mean: [row[0], row[1], row[2]], rotation: q.to_array(), scales: [row[7], row[8], row[9]], amplitude: row[10] }
                })
                .collect();
            Some(GaussianSet { gaussians })
        }

        /// The current values as a plain set (for JSON, culling bounds and the CPU shadow path).
        pub fn to_set(&self) -> GaussianSet {
            if self.is_empty() {
                return GaussianSet { gaussians: Vec::new() };
            }
            // `host_values` gives every value (NaN where the copy failed).
            self.set_from_rows(&crate::backend::host_values(self.rows())).unwrap_or_default()
        }
    }
}
