//! The evaluation's geometry check: the fitted surface of up to `GEOMETRY_FRAMES` frames
//! meshed (`eval::frame_surface`) and scored against the scene's ground-truth meshes, with how
//! much of it the training images saw.

use super::in_order_while_rendering;
use crate::avatar::Avatar;
use crate::fit_error::{io, FitError};
use crate::messages::TrainMessage;
use crate::scene::Scene;
use crate::skeleton::PoseTensors;
use glam::DVec3;
use serde_json::json;

/// Samples per surface for the geometry error.
const GEOMETRY_SAMPLES: usize = 20_000;

/// The most frames whose fitted surface an evaluation meshes and compares with the scene's
/// ground-truth meshes (evenly spread over those that have one).
const GEOMETRY_FRAMES: usize = 6;

/// The fitted surface (`eval::surface_mesh`) against every ground-truth mesh of the scene's
/// frames, one entry per frame with a mesh (metres, degrees). The frames are meshed on rayon's
/// threads (a frame's marching, carve and comparison run on one) and reported in order.
pub(super) fn geometry_scores(
    scene: &Scene,
    model: &Avatar,
    device: &burn::tensor::Device,
    on: &mut impl FnMut(TrainMessage),
) -> Result<serde_json::Value, FitError> {
    let with_meshes: Vec<usize> = (0..scene.frames.len()).filter(|&f| scene.frames[f].mesh.is_some()).collect();
    // Evenly spread, at most GEOMETRY_FRAMES: meshing every frame of a long capture took longer
    // than its training.
    let count = with_meshes.len().min(GEOMETRY_FRAMES);
    let chosen: Vec<usize> = (0..count).map(|k| with_meshes[k * with_meshes.len() / count]).collect();
    let mut out = Vec::new();
    if chosen.is_empty() {
        return Ok(json!(out));
    }
    on(TrainMessage::Meshed { done: 0, total: chosen.len() });
    in_order_while_rendering(
        chosen.len(),
        |k| frame_geometry(scene, model, device, chosen[k]),
        |done, scored| {
            out.extend(scored?);
            on(TrainMessage::Meshed { done: done + 1, total: chosen.len() });
            Ok::<(), FitError>(())
        },
    )?;
    Ok(json!(out))
}

/// `geometry_scores`' entry for frame `position` (`None` when it has no mesh).
fn frame_geometry(scene: &Scene, model: &Avatar, device: &burn::tensor::Device, position: usize) -> Result<Option<serde_json::Value>, FitError> {
    let frame = &scene.frames[position];
    let Some(path) = &frame.mesh else { return Ok(None) };
    let truth = crate::geometry::load_obj(path).map_err(|e| io(path, e))?;
    let (fitted, carved) = crate::eval::frame_surface(model, scene, position, device)?;
    // What the training images saw of it: carried into their frames by its skinning (the
    // carve's, when it needed it too).
    let bones = PoseTensors::new(&frame.pose, &scene.skeleton, device).frames;
    let skinning = |p: DVec3| model.field.skinning_weights(&bones, p.as_vec3().to_array());
    let vertex_skinning = carved.skinning.unwrap_or_else(|| fitted.vertices.iter().map(|&v| skinning(v)).collect());
    let seen = crate::seen::SeenInFrames::new(&fitted, &vertex_skinning, scene, position);
    let sees = |p: DVec3, n: DVec3| seen.sees(p, n, &skinning(p));
    let scores = crate::geometry::compare(&fitted, &truth, GEOMETRY_SAMPLES, position as u64, Some(&sees));
    Ok(Some(json!({
        "frame": position, "index": frame.index, "mesh": path, "accuracy": scores.map(|s| s.accuracy), "completeness": scores.map(|s| s.completeness),
        "chamfer": scores.map(|s| s.chamfer), "normal_angle": scores.map(|s| s.normal_angle), "within_2cm": scores.map(|s| s.within_2cm),
        "seen": scores.and_then(|s| s.seen), "seen_within_2cm": scores.and_then(|s| s.seen_within_2cm),
        "closed": fitted.is_closed_manifold(),
    })))
}
