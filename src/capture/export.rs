//! A scene as a capture as people have them: nerfstudio's `transforms.json` (OpenGL camera
//! axes), a BVH and plates with a background where the masks say none is body. What `umbra synth
//! --export nerfstudio` writes, so that importing it can be checked against the scene itself.

use super::{input, ImportError};
use crate::imageio::RgbImage;
use crate::scene::Scene;
use std::path::Path;

/// Seconds between the clip's frames (the scene's frames in order, whatever their times).
pub const FRAME_TIME: f64 = 1.0 / 30.0;

/// A plate's background at pixel `(x, y)` (linear RGB): stripes and a gradient, nothing a mask
/// could be confused with.
fn background(x: usize, y: usize) -> [f32; 3] {
    let (x, y) = (x as f32, y as f32);
    let checker = if ((x / 6.0).floor() + (y / 6.0).floor()) as i64 % 2 == 0 { 0.1 } else { 0.0 };
    [0.25 + 0.15 * (x * 0.21).sin() + checker, 0.35 + 0.1 * (y * 0.17).cos(), 0.3 + checker]
}

/// Writes the images of `scene`'s first training light as a capture in `dir` (new or empty): the
/// plates (`images/`), masks (`masks/`), `transforms.json` and `motion.bvh`, lengths in `units`
/// per metre. Returns how many images.
pub fn write_capture(scene: &Scene, dir: &Path, units: f64) -> Result<usize, ImportError> {
    let light = scene.training_lights().first().map(|l| l.to_string()).ok_or_else(|| input(&scene.root, "no training images"))?;
    let chosen: Vec<usize> = (0..scene.views.len()).filter(|&k| scene.views[k].light == light).collect();
    for sub in ["images", "masks"] {
        std::fs::create_dir_all(dir.join(sub)).map_err(|e| input(&dir.join(sub), e.to_string()))?;
    }
    let stem = |k: usize| scene.views[k].path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| format!("image{k}"));
    for &k in &chosen {
        let view = &scene.views[k];
        let mut plate = RgbImage::new(view.colour.width(), view.colour.height());
        for (p, pixel) in plate.pixels.iter_mut().enumerate() {
            let inside = view.mask.as_ref().is_none_or(|m| m.foreground[p]);
            *pixel = if inside { view.colour.pixel(p) } else { background(p % plate.width, p / plate.width) };
        }
        let path = dir.join(format!("images/{}.png", stem(k)));
        let bytes = crate::imageio::encode_png_rgb(&plate)?;
        crate::imageio::write_atomic(&path, &bytes).map_err(|e| input(&path, e.to_string()))?;
        if let Some(mask) = &view.mask {
            let path = dir.join(format!("masks/{}.png", stem(k)));
            let bytes = crate::imageio::encode_png_mask(mask)?;
            crate::imageio::write_atomic(&path, &bytes).map_err(|e| input(&path, e.to_string()))?;
        }
    }
    let names = |k: usize| (format!("images/{}.png", stem(k)), scene.views[k].mask.as_ref().map(|_| format!("masks/{}.png", stem(k))));
    let transforms = super::nerfstudio::write(scene, &chosen, units, FRAME_TIME, names);
    let text = serde_json::to_string_pretty(&transforms).map_err(|e| input(dir, e.to_string()))?;
    crate::imageio::write_atomic(&dir.join("transforms.json"), text.as_bytes()).map_err(|e| input(dir, e.to_string()))?;
    let frames: Vec<Vec<glam::DMat4>> = scene.frames.iter().map(|f| f.pose.bone_to_world.clone()).collect();
    let bvh = super::bvh::write(&scene.skeleton, &frames, FRAME_TIME, units).map_err(|e| input(&scene.root, e))?;
    crate::imageio::write_atomic(&dir.join("motion.bvh"), bvh.as_bytes()).map_err(|e| input(dir, e.to_string()))?;
    Ok(chosen.len())
}
