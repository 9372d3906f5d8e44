//! Rebinding: each Gaussian moves to the bone that carries it inside the body, and the mean
//! regulariser's targets follow.

use super::Trainer;
use crate::fit_error::FitError;
use crate::gaussians::GaussianParams;
use burn::tensor::{Device, Tensor, TensorData};

/// The bones `chosen` for Gaussians now on bones `current`, except that every bone that has a
/// Gaussian keeps one: of a bone all of whose Gaussians would leave, the one its own motion
/// carries best (least `outside[g][bone]`, the mean distance outside the surface) stays. The
/// density fit pulls the Gaussians of a hand hanging beside a skirt into the skirt, and
/// rebinding them all to the pelvis or a thigh left the hand with none, casting no shadow in
/// any pose (human-dressed seed 2: the right hand); the one kept is pulled back by the mean
/// regulariser toward its bone. A Gaussian sent back stays, so this ends.
fn keep_every_bone(mut chosen: Vec<usize>, current: &[usize], outside: &[Vec<f64>]) -> Vec<usize> {
    loop {
        let emptied = current.iter().copied().find(|&b| !chosen.contains(&b));
        let Some(bone) = emptied else { return chosen };
        let best = (0..current.len()).filter(|&g| current[g] == bone).min_by(|&x, &y| outside[x][bone].total_cmp(&outside[y][bone]));
        match best {
            Some(g) => chosen[g] = bone,
            None => return chosen,
        }
    }
}

/// How much farther outside the surface (m on the reference human, on average over the frames)
/// than the best bone a Gaussian's own bone may carry it before the Gaussian moves
/// (`Trainer::rebind_gaussians`): a few millimetres, below the surface's own noise, so that
/// bones that carry it equally well (spine and chest for a point of the back) do not trade it.
const REBIND_TOLERANCE: f64 = 0.005;

/// Where the mean regulariser pulls each Gaussian, bone-local (m): a Gaussian seeded on loose
/// body (`seeds_on_loose_body`) toward its seed, the `root`-local `anchors[g]`, also after
/// rebinding moved it to another bone (the seed re-expressed in that bone's frame in the
/// rebinding's `reference` pose, where the move kept the Gaussian in place); any other toward
/// its bone's centre. A rule of the Gaussian's index and bone alone, so a resumed fit pulls as
/// the straight one does.
pub(super) fn mean_targets(
    bones: &[usize],
    anchors: &[Option<glam::DVec3>],
    root: Option<usize>,
    reference: Option<&crate::skeleton::Pose>,
    skeleton: &crate::skeleton::Skeleton,
    device: &Device,
) -> Tensor<2> {
    let centres: Vec<f32> = bones
        .iter()
        .enumerate()
        .flat_map(|(g, &b)| match (anchors.get(g).copied().flatten(), root, reference) {
            (Some(anchor), Some(root), _) if b == root => anchor.as_vec3().to_array(),
            (Some(anchor), Some(root), Some(pose)) => pose.to_local(b, pose.to_world(root, anchor)).as_vec3().to_array(),
            _ => [0.0, skeleton.bones[b].length as f32 / 2.0, 0.0],
        })
        .collect();
    Tensor::from_data(TensorData::new(centres, [bones.len(), 3]), device)
}

impl Trainer {
    /// Moves every Gaussian to the bone that keeps it inside the body. A Gaussian starts on a
    /// bone and fits the field's density wherever that is, so loose clothing is first reached
    /// by the Gaussians of whatever bone is near (a skirt's by the hands' and thighs'); bound
    /// to a bone that does not carry it, it swings off the body in other poses, casting
    /// shadows and bounding samples where the body is not. Each Gaussian's mean, as placed in
    /// the first training frame, is carried rigidly by every bone in turn through up to
    /// `SEARCH_FRAMES` training frames, and scored by how far outside the field's surface it
    /// ends on average. Among the bones within `REBIND_TOLERANCE` of the best, it stays on its
    /// own if it is one, else goes to the one nearest it; but a bone keeps at least one of its
    /// Gaussians (`keep_every_bone`). Returns how many moved.
    pub fn rebind_gaussians(&mut self) -> Result<usize, FitError> {
        if let Some(state) = self.state.as_mut() {
            state.gaussians_read = None;
        }
        let model = self.state.as_ref().map(|s| &s.model).ok_or_else(|| FitError::Input("the model was lost by an interrupted step".into()))?;
        let set = model.gaussians.to_set();
        let bone_count = self.scene.skeleton.len();
        let count = self.frames.len().clamp(1, Self::SEARCH_FRAMES);
        let reference = self.rebinding_reference().cloned().ok_or_else(|| FitError::Input("no training frame to rebind the Gaussians in".into()))?;
        let placed: Vec<glam::DVec3> = set.pose(&reference).iter().map(|g| g.mean).collect();
        // outside[g][b]: the mean distance outside the surface of Gaussian g carried by bone b.
        let mut outside = vec![vec![0.0f64; bone_count]; set.len()];
        for k in 0..count {
            let data = &self.frames[k * self.frames.len() / count];
            let pose = &self.scene.frames[data.position].pose;
            // Each bone's motion from the reference frame to this one.
            let motion: Vec<glam::DMat4> = (0..bone_count).map(|b| pose.bone_to_world[b] * reference.bone_to_world[b].inverse()).collect();
            let carried: Vec<f32> = placed.iter().flat_map(|&x| motion.iter().flat_map(move |m| m.transform_point3(x).as_vec3().to_array())).collect();
            let n = carried.len() / 3;
            let points = Tensor::<2>::from_data(TensorData::new(carried, [n, 3]), &self.device);
            let sdf = crate::backend::host_values(model.field.sdf(points, &data.pose_tensors));
            for (i, d) in sdf.iter().enumerate() {
                outside[i / bone_count][i % bone_count] += (*d as f64).max(0.0) / count as f64;
            }
        }
        let tolerance = REBIND_TOLERANCE * self.body_unit();
        let bones: Vec<usize> = set
            .gaussians
            .iter()
            .enumerate()
            .map(|(g, gaussian)| {
                let best = outside[g].iter().copied().fold(f64::INFINITY, f64::min);
                let near_best = |b: usize| outside[g][b] <= best + tolerance;
                if near_best(gaussian.bone) {
                    return gaussian.bone;
                }
                let distance = |b: usize| reference.distance_to_bone(&self.scene.skeleton, b, placed[g]);
                (0..bone_count).filter(|&b| near_best(b)).min_by(|&a, &b| distance(a).total_cmp(&distance(b))).unwrap_or(gaussian.bone)
            })
            .collect();
        let current: Vec<usize> = set.gaussians.iter().map(|g| g.bone).collect();
        let bones = keep_every_bone(bones, &current, &outside);
        let moved = bones.iter().zip(&set.gaussians).filter(|(b, g)| **b != g.bone).count();
        if moved > 0 {
            if let Some(model) = self.state.as_mut().map(|s| &mut s.model) {
                model.gaussians.rebind(&bones, &reference);
            }
            self.mean_targets = mean_targets(&bones, &self.anchors, self.loose_root, self.rebinding_reference(), &self.scene.skeleton, &self.device);
        }
        Ok(moved)
    }

    /// Sets the Gaussians' bones (from a checkpoint's `state.json`), checked against the set's
    /// size and the skeleton.
    pub fn set_gaussian_bones(&mut self, bones: &[usize]) -> Result<(), String> {
        let bone_count = self.scene.skeleton.len();
        let model = self.state.as_mut().map(|s| &mut s.model).ok_or("no model")?;
        if bones.len() != model.gaussians.len() {
            return Err(format!("expected {} Gaussians' bones, found {}", model.gaussians.len(), bones.len()));
        }
        if let Some(b) = bones.iter().find(|&&b| b >= bone_count) {
            return Err(format!("bone {b} is not in the skeleton's {bone_count}"));
        }
        model.gaussians.bones = bones.to_vec();
        self.mean_targets = mean_targets(bones, &self.anchors, self.loose_root, self.rebinding_reference(), &self.scene.skeleton, &self.device);
        Ok(())
    }

    /// The pose the Gaussians are rebound in (`rebind_gaussians`): the first training frame's.
    fn rebinding_reference(&self) -> Option<&crate::skeleton::Pose> {
        self.frames.first().map(|f| &self.scene.frames[f.position].pose)
    }

    /// How many Gaussians were seeded on loose body (`seeds_on_loose_body`).
    pub fn loose_gaussians(&self) -> usize {
        self.anchors.iter().filter(|a| a.is_some()).count()
    }

    /// Drops the Gaussians seeded on loose body: a run fitted before they were seeded has
    /// only the bones' (`count` of them).
    pub fn without_loose_gaussians(&mut self, count: usize) -> Result<(), String> {
        let seeded = self.loose_gaussians();
        let model = self.state.as_mut().map(|s| &mut s.model).ok_or("no model")?;
        if count + seeded != model.gaussians.len() {
            return Err(format!("{count} Gaussians recorded, this scene starts {} ({seeded} on loose body)", model.gaussians.len()));
        }
        let mut set = model.gaussians.to_set();
        set.gaussians.truncate(count);
        model.gaussians = GaussianParams::from_set(&set, model.gaussians.unit, &self.device);
        self.anchors.truncate(count);
        let bones = model.gaussians.bones.clone();
        self.mean_targets = mean_targets(&bones, &self.anchors, self.loose_root, self.rebinding_reference(), &self.scene.skeleton, &self.device);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::Backend;
    use crate::scene::Scene;

    /// A bone all of whose Gaussians would move keeps the one its motion carries best; bones
    /// that keep one, and moves between them, are left alone; a chain of emptied bones is
    /// undone link by link.
    #[test]
    fn rebinding_leaves_every_bone_a_gaussian() {
        // Gaussians on bones 0, 0, 1, 1, 2 (outside[g][b]: how far outside bone b carries g).
        let current = [0, 0, 1, 1, 2];
        let outside = vec![vec![0.0, 0.1, 0.2], vec![0.0, 0.1, 0.2], vec![0.1, 0.03, 0.0], vec![0.1, 0.02, 0.0], vec![0.0, 0.1, 0.1]];
        // Bone 1 would lose both: the second (0.02 outside on bone 1) stays.
        assert_eq!(keep_every_bone(vec![0, 0, 2, 2, 2], &current, &outside), vec![0, 0, 2, 1, 2]);
        // One of bone 0's moves to bone 2 and bone 2's to bone 0: each still has one.
        assert_eq!(keep_every_bone(vec![0, 2, 1, 1, 0], &current, &outside), vec![0, 2, 1, 1, 0]);
        // Bone 1's go to 2 and bone 2's to 0: bone 2 still has one (bone 1's that stays not).
        assert_eq!(keep_every_bone(vec![0, 0, 2, 2, 0], &current, &outside), vec![0, 0, 2, 1, 0]);
        // A chain: one Gaussian a bone, bone 1's to 2 and bone 2's to 0. Keeping bone 1's
        // empties bone 2, which then keeps its own.
        let outside = vec![vec![0.0; 3]; 3];
        assert_eq!(keep_every_bone(vec![0, 2, 0], &[0, 1, 2], &outside), vec![0, 1, 2]);
    }

    #[test]
    fn a_seeded_gaussian_is_pulled_toward_its_seed_on_whatever_bone_carries_it() {
        let schedule = crate::schedule::Schedule::parse(crate::schedule::DEFAULT_TEXT, std::path::Path::new("default.toml")).unwrap();
        let scene = Scene::load(std::path::Path::new("datasets-synthetic/human-dressed")).unwrap();
        let mut trainer = Trainer::new(scene, schedule, Backend::Flex, 0).unwrap();
        let root = trainer.loose_root.unwrap();
        let seeded = trainer.anchors.iter().position(|a| a.is_some()).unwrap();
        let anchor = trainer.anchors[seeded].unwrap();
        let target = |trainer: &Trainer, g: usize| {
            let rows = trainer.mean_targets.clone().into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
            glam::DVec3::new(rows[3 * g] as f64, rows[3 * g + 1] as f64, rows[3 * g + 2] as f64)
        };
        assert!(target(&trainer, seeded).distance(anchor) < 1e-6, "on the root: its seed");
        // Moved to the chest: the same point of space in the rebinding's pose, chest-local.
        let chest = trainer.scene.skeleton.bones.iter().position(|b| b.name == "chest").unwrap();
        let mut bones = trainer.model().unwrap().gaussians.bones.clone();
        bones[seeded] = chest;
        trainer.set_gaussian_bones(&bones).unwrap();
        let pose = trainer.rebinding_reference().unwrap().clone();
        let moved = target(&trainer, seeded);
        assert!(pose.to_world(chest, moved).distance(pose.to_world(root, anchor)) < 1e-5, "the seed's place, now on the chest");
        assert!(moved.distance(glam::DVec3::new(0.0, trainer.scene.skeleton.bones[chest].length / 2.0, 0.0)) > 0.05, "not the chest's centre");
        // A bone's own Gaussian: its bone's centre.
        let own = (0..bones.len()).find(|&g| trainer.anchors[g].is_none() && bones[g] == chest).unwrap();
        assert!(target(&trainer, own).distance(glam::DVec3::new(0.0, trainer.scene.skeleton.bones[chest].length / 2.0, 0.0)) < 1e-6);
    }
}
