//! A scene as a capture as people have them: nerfstudio's `transforms.json` (OpenGL camera
//! axes), a BVH and plates with a background where the masks say none is body, exact or with
//! the errors a real pipeline leaves (`flaws`). What `umbra synth --export nerfstudio` writes,
//! so that importing it can be checked against the scene itself.

use super::flaws::{self, CaptureErrors};
use super::{input, ImportError};
use crate::imageio::RgbImage;
use crate::random::Stream;
use crate::scene::{Scene, Split};
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
/// per metre, with `errors` put into its training images, frames and cameras (drawn from
/// `seed`; `flaws`) and, when there are any, the exact cameras and motion kept beside it in
/// `truth/` with the errors' sizes (`truth/errors.json`). Returns how many images.
pub fn write_capture(scene: &Scene, dir: &Path, units: f64, errors: &CaptureErrors, seed: u64) -> Result<usize, ImportError> {
    let light = scene.training_lights().first().map(|l| l.to_string()).ok_or_else(|| input(&scene.root, "no training images"))?;
    let chosen: Vec<usize> = (0..scene.views.len()).filter(|&k| scene.views[k].light == light).collect();
    for sub in ["images", "masks"] {
        std::fs::create_dir_all(dir.join(sub)).map_err(|e| input(&dir.join(sub), e.to_string()))?;
    }
    let flawed = Flawed::draw(scene, &chosen, errors, seed);
    let stem = |k: usize| scene.views[k].path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| format!("image{k}"));
    let jpeg = |k: usize| errors.jpeg > 0 && scene.views[k].split == Split::Train;
    let names = |k: usize| {
        let plate = format!("images/{}.{}", stem(k), if jpeg(k) { "jpg" } else { "png" });
        (plate, scene.views[k].mask.as_ref().map(|_| format!("masks/{}.png", stem(k))))
    };
    for &k in &chosen {
        let view = &scene.views[k];
        let mut plate = RgbImage::new(view.colour.width(), view.colour.height());
        for (p, pixel) in plate.pixels.iter_mut().enumerate() {
            let inside = view.mask.as_ref().is_none_or(|m| m.foreground[p]);
            *pixel = if inside { view.colour.pixel(p) } else { background(p % plate.width, p / plate.width) };
        }
        let (plate_name, mask_name) = names(k);
        let train = view.split == Split::Train;
        let plate = if train { flaws::coloured(&plate, flawed.colours[view.camera]) } else { plate };
        let bytes = if jpeg(k) { encode_jpeg(&plate, errors.jpeg)? } else { crate::imageio::encode_png_rgb(&plate)? };
        write(&dir.join(&plate_name), &bytes)?;
        if let (Some(mask), Some(name)) = (&view.mask, mask_name) {
            let mask = if train { flaws::segmented_mask(mask, errors, &mut Stream::new(seed, FLAW_MASKS, k as u64)) } else { mask.clone() };
            write(&dir.join(name), &crate::imageio::encode_png_mask(&mask)?)?;
        }
    }
    write_cameras_and_motion(&flawed.scene, dir, units, &chosen, &names)?;
    if !errors.is_none() {
        let truth = dir.join("truth");
        std::fs::create_dir_all(&truth).map_err(|e| input(&truth, e.to_string()))?;
        write_cameras_and_motion(scene, &truth, units, &chosen, &names)?;
        // The sizes asked for, and the colour each camera was given (gain times white balance,
        // per channel, by the synth camera's index: `cNN` in the images' names).
        let mut stated = serde_json::to_value(errors).map_err(|e| input(&truth, e.to_string()))?;
        stated["camera_colours"] = serde_json::json!(flawed.colours);
        let text = serde_json::to_string_pretty(&stated).map_err(|e| input(&truth, e.to_string()))?;
        write(&truth.join("errors.json"), text.as_bytes())?;
    }
    Ok(chosen.len())
}

/// `transforms.json` and `motion.bvh` of `scene`'s cameras and frames into `dir`.
fn write_cameras_and_motion(
    scene: &Scene,
    dir: &Path,
    units: f64,
    chosen: &[usize],
    names: &dyn Fn(usize) -> (String, Option<String>),
) -> Result<(), ImportError> {
    let transforms = super::nerfstudio::write(scene, &scene.cameras, chosen, units, FRAME_TIME, names);
    let text = serde_json::to_string_pretty(&transforms).map_err(|e| input(dir, e.to_string()))?;
    write(&dir.join("transforms.json"), text.as_bytes())?;
    let frames: Vec<Vec<glam::DMat4>> = scene.frames.iter().map(|f| f.pose.bone_to_world.clone()).collect();
    let bvh = super::bvh::write(&scene.skeleton, &frames, FRAME_TIME, units).map_err(|e| input(&scene.root, e))?;
    write(&dir.join("motion.bvh"), bvh.as_bytes())
}

fn write(path: &Path, bytes: &[u8]) -> Result<(), ImportError> {
    crate::imageio::write_atomic(path, bytes).map_err(|e| input(path, e.to_string()))
}

/// A plate as 8-bit sRGB JPEG of `quality`.
fn encode_jpeg(plate: &RgbImage, quality: u8) -> Result<Vec<u8>, ImportError> {
    let raw: Vec<u8> = plate.pixels.iter().flat_map(|p| p.map(crate::imageio::linear_to_srgb8)).collect();
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality.max(1))
        .encode(&raw, plate.width as u32, plate.height as u32, image::ExtendedColorType::Rgb8)
        .map_err(|e| ImportError::Image(crate::imageio::ImageError::Decode("jpeg encoder".into(), e.to_string())))?;
    Ok(out)
}

/// Streams of the draws, apart per kind of error.
const FLAW_FRAMES: u64 = 0xF1A5_0001;
const FLAW_CAMERAS: u64 = 0xF1A5_0002;
const FLAW_MASKS: u64 = 0xF1A5_0003;

/// The scene as the flawed capture states it: its training frames as a tracker leaves them, a
/// calibrated copy of each camera that its training images look through (test images keep the
/// exact one), and each camera's colour.
struct Flawed {
    scene: Scene,
    colours: Vec<[f32; 3]>,
}

impl Flawed {
    fn draw(scene: &Scene, chosen: &[usize], errors: &CaptureErrors, seed: u64) -> Flawed {
        let mut flawed = scene.clone();
        if errors.is_none() {
            return Flawed { scene: flawed, colours: vec![[1.0; 3]; scene.cameras.len()] };
        }
        let tested: std::collections::BTreeSet<usize> = scene.views.iter().filter(|v| v.split != Split::Train).map(|v| v.frame).collect();
        for (f, frame) in flawed.frames.iter_mut().enumerate().filter(|(f, _)| !tested.contains(f)) {
            let mut stream = Stream::new(seed, FLAW_FRAMES, f as u64);
            frame.pose.bone_to_world = flaws::tracked_pose(&scene.skeleton, &frame.pose.bone_to_world, errors, &mut stream);
        }
        let count = scene.cameras.len();
        let mut colours = Vec::with_capacity(count);
        for c in 0..count {
            let mut stream = Stream::new(seed, FLAW_CAMERAS, c as u64);
            let mut camera = scene.cameras[c].clone();
            camera.camera_to_world = flaws::calibrated_camera(camera.camera_to_world, errors, &mut stream);
            camera.name = format!("{}-calibrated", camera.name);
            flawed.cameras.push(camera);
            colours.push(flaws::camera_colour(errors, &mut stream));
        }
        for &k in chosen {
            if flawed.views[k].split == Split::Train {
                flawed.views[k].camera += count;
            }
        }
        Flawed { scene: flawed, colours }
    }
}
