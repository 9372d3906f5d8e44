//! A scene's frames as a BVH clip in centimetres, each joint's frame its bone's (`cargo run
//! --release --example clip_of_scene -- SCENE OUT.bvh [test]`): every frame, or with `test`
//! the frames of its test images. Such a clip drives a fit of that scene directly (`umbra
//! render RUN --motion OUT.bvh`), so its renders can be set against the fit's own.

use umbra::scene::{Scene, Split};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(scene), Some(out)) = (args.get(1), args.get(2)) else {
        return Err("usage: clip_of_scene SCENE OUT.bvh [test]".into());
    };
    let scene = Scene::load(std::path::Path::new(scene))?;
    let mut chosen: Vec<usize> = match args.get(3).map(String::as_str) {
        Some("test") => scene.views_in(Split::Test).map(|v| v.frame).collect(),
        _ => (0..scene.frames.len()).collect(),
    };
    chosen.sort_unstable();
    chosen.dedup();
    let frames: Vec<_> = chosen.iter().map(|&f| scene.frames[f].pose.bone_to_world.clone()).collect();
    let clip = umbra::capture::bvh::write(&scene.skeleton, &frames, 1.0 / 30.0, 100.0)?;
    std::fs::write(out, clip)?;
    println!("{} frames ({:?}) into {out}", chosen.len(), chosen);
    Ok(())
}
