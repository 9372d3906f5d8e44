//! What a tracker's bias costs an avatar shown in exact poses (`cargo run --release --example
//! biased_truth -- TRUE_SCENE GIVEN_SCENE OUT`): writes OUT, TRUE_SCENE with every frame posed
//! as GIVEN_SCENE's training motion errs on average (each bone's mean turn from the true one over
//! the training frames, the root's mean shift), its images, masks and plates copied. A fit's
//! content takes up an error every training frame shares as well as the motion can (a bone's
//! content turned in its frame), so the images cannot tell it; `umbra eval RUN --scene OUT` of
//! a fit of TRUE_SCENE shows what carrying it costs the test images (`docs/measurements.md`).
//! GIVEN_SCENE is the same capture imported with a tracker's errors (`umbra synth --export
//! nerfstudio --errors joints=2.5,root=1`, the same seed).

use std::path::Path;
use umbra::scene::{Scene, Split};
use umbra::train::motion::turns_between;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(truth_dir), Some(given), Some(out)) = (args.get(1), args.get(2), args.get(3)) else {
        return Err("usage: biased_truth TRUE_SCENE GIVEN_SCENE OUT".into());
    };
    let (truth_dir, out) = (Path::new(truth_dir), Path::new(out));
    if out.exists() {
        return Err(format!("{} exists: give a new folder", out.display()).into());
    }
    let truth = Scene::load(truth_dir)?;
    let given = Scene::load(Path::new(given))?;
    let mut frames: Vec<usize> = truth.views.iter().filter(|v| v.split == Split::Train).map(|v| v.frame).collect();
    frames.sort_unstable();
    frames.dedup();
    let pairs = frames.iter().map(|&f| Ok((pose(&truth, f)?, pose(&given, f)?))).collect::<Result<Vec<_>, &str>>()?;
    let (bias, _) = turns_between(&truth.skeleton, &pairs);
    let root = |p: &umbra::skeleton::Pose| p.bone_to_world.first().map(|m| m.w_axis.truncate()).unwrap_or_default();
    let shift = pairs.iter().map(|(t, g)| root(g) - root(t)).sum::<glam::DVec3>() / pairs.len().max(1) as f64;
    let degrees: Vec<f64> = bias.iter().map(|b| b.length().to_degrees()).collect();
    println!(
        "the given motion's bias over {} training frames: each bone's mean turn {:.3} degrees on average, at most {:.3}; the root {:.3} cm",
        frames.len(),
        degrees.iter().sum::<f64>() / degrees.len().max(1) as f64,
        degrees.iter().fold(0.0f64, |m, &d| m.max(d)),
        shift.length() * 100.0
    );
    let turns: Vec<[f64; 3]> = bias.iter().map(|b| b.to_array()).collect();
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(truth_dir.join("scene.json"))?)?;
    let written = json["frames"].as_array_mut().ok_or("scene.json: frames is not a list")?;
    for (frame, written) in truth.frames.iter().zip(written.iter_mut()) {
        let biased = frame.pose.corrected(&truth.skeleton, &turns, shift.to_array());
        let rows = |m: &glam::DMat4| (0..4).map(|r| m.row(r).to_array().to_vec()).collect::<Vec<_>>();
        written["bone_to_world"] = serde_json::json!(biased.bone_to_world.iter().map(rows).collect::<Vec<_>>());
    }
    std::fs::create_dir_all(out)?;
    for dir in ["images", "masks", "plates"] {
        copy_dir(&truth_dir.join(dir), &out.join(dir))?;
    }
    umbra::imageio::write_atomic(&out.join("scene.json"), serde_json::to_string_pretty(&json)?.as_bytes())?;
    println!("wrote {}", out.display());
    Ok(())
}

/// Frame `f`'s pose in `scene`.
fn pose(scene: &Scene, f: usize) -> Result<&umbra::skeleton::Pose, &'static str> {
    scene.frames.get(f).map(|frame| &frame.pose).ok_or("the given scene has fewer frames")
}

/// Copies `from`'s files into `to` (none when `from` does not exist).
fn copy_dir(from: &Path, to: &Path) -> std::io::Result<()> {
    if !from.is_dir() {
        return Ok(());
    }
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from)? {
        let entry = entry?;
        if entry.file_type()?.is_file() {
            std::fs::copy(entry.path(), to.join(entry.file_name()))?;
        }
    }
    Ok(())
}
