//! A capture's photographs into a scene's images: each read (PNG, JPEG or EXR), its mask found
//! (the camera file's `mask_path`, `--masks DIR/<stem>.png`, else the image's alpha), the lens
//! distortion removed, downscaled by a whole factor to `--max-size`, the background blacked by
//! the mask (but near its edge where the camera's plate is known: a static camera's plate is
//! estimated from its frames first), and written under the image's own name; in parallel, one
//! image in memory per thread.

use super::{input, CaptureImage, ImportError, ImportOptions, Intrinsics};
use crate::imageio::{Mask, RgbImage};
use crate::scene::Split;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// Where an image's mask comes from.
#[derive(Clone, Debug)]
enum MaskSource {
    File(PathBuf),
    Alpha,
}

/// What `write` does to each image, decided before anything is read.
pub struct Photos {
    /// Each image's intrinsics after downscaling.
    pub intrinsics: Vec<Intrinsics>,
    factors: Vec<usize>,
    masks: Vec<MaskSource>,
    pub assumed: Vec<String>,
}

/// Plans the images' processing; refuses two images of one name.
pub fn prepare(images: &[CaptureImage], options: &ImportOptions, camera_file: &Path) -> Result<Photos, ImportError> {
    let mut seen = std::collections::HashSet::with_capacity(images.len());
    for image in images {
        if !seen.insert(image.key.as_str()) {
            return Err(input(camera_file, format!("{}: a second image named {:?}: a scene keeps each image's name", image.json_path, image.key)));
        }
    }
    if let Some(dir) = options.masks.as_ref().filter(|d| !d.is_dir()) {
        return Err(input(dir, "--masks: no such folder (nothing was written)"));
    }
    if let Some(most) = options.max_size.filter(|&m| m < super::SMALLEST_MAX_SIZE) {
        return Err(input(camera_file, format!("--max-size {most}: {}", super::parse_max_size(&most.to_string()).err().unwrap_or_default())));
    }
    let masks: Vec<MaskSource> = images
        .iter()
        .map(|image| match (&image.mask, &options.masks) {
            (Some(file), _) => MaskSource::File(file.clone()),
            (None, Some(dir)) => MaskSource::File(mask_in(dir, image)),
            (None, None) => MaskSource::Alpha,
        })
        .collect();
    let factors: Vec<usize> = images
        .iter()
        .map(|image| match options.max_size {
            Some(most) if most > 0 => image.intrinsics.width.max(image.intrinsics.height).div_ceil(most),
            _ => 1,
        })
        .collect();
    let intrinsics = images
        .iter()
        .zip(&factors)
        .map(|(image, &f)| {
            let k = &image.intrinsics;
            let s = f as f64;
            Intrinsics { fx: k.fx / s, fy: k.fy / s, cx: k.cx / s, cy: k.cy / s, width: k.width / f, height: k.height / f }
        })
        .collect();
    let mut assumed = Vec::new();
    let distorted = images.iter().filter(|i| !i.distortion.is_none()).count();
    if distorted > 0 {
        assumed.push(format!("lens distortion removed from {distorted} images (OpenCV's model)"));
    }
    if let Some(&most) = factors.iter().max().filter(|&&f| f > 1) {
        assumed.push(format!("images downscaled up to {most}x to fit --max-size"));
    }
    let from_files = masks.iter().filter(|m| matches!(m, MaskSource::File(_))).count();
    assumed.push(format!("masks: {from_files} from files, {} from the images' alpha", masks.len() - from_files));
    Ok(Photos { intrinsics, factors, masks, assumed })
}

/// An image's mask in `--masks DIR`: at its key's path (`DIR/cam02/000000.png`), else by its
/// file's stem alone (`DIR/000000.png`, a flat folder of masks).
fn mask_in(dir: &Path, image: &CaptureImage) -> PathBuf {
    let keyed = dir.join(format!("{}.png", image.key));
    let stem = image.path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let flat = dir.join(format!("{stem}.png"));
    if !keyed.is_file() && flat.is_file() {
        flat
    } else {
        keyed
    }
}

/// An image as the scene keeps it: its path, its mask's path and its plate's, relative to the
/// scene's folder.
pub type Written = (String, Option<String>, Option<String>);

/// Processes and writes every image into `dir` (`images/`, `masks/`, and `plates/` for the
/// static cameras whose frames show what lies behind the body); `camera_of` is each image's
/// scene camera. `on(done, total)` after each image.
pub fn write(
    images: &[CaptureImage],
    photos: &Photos,
    camera_of: &[usize],
    dir: &Path,
    on: &(dyn Fn(usize, usize) + Sync),
) -> Result<Vec<Written>, ImportError> {
    for sub in ["images", "masks"] {
        std::fs::create_dir_all(dir.join(sub)).map_err(|e| input(&dir.join(sub), e.to_string()))?;
    }
    let plates = plates(images, photos, camera_of, dir)?;
    let done = AtomicUsize::new(0);
    (0..images.len())
        .into_par_iter()
        .map(|i| {
            let plate = plates.get(&camera_of[i]).filter(|_| images[i].split == Split::Train);
            let written = write_one(&images[i], photos, i, plate, dir);
            on(done.fetch_add(1, Ordering::Relaxed) + 1, images.len());
            written
        })
        .collect()
}

/// The most frames of a camera its plate is estimated from (evenly spread over its training
/// images): enough for a median, and a bounded memory at any capture's length.
const PLATE_FRAMES: usize = 32;

/// A plate written for the scene: its path relative to the scene's folder, and the plate.
type WrittenPlate = (String, crate::silhouette::Plate);

/// Each static camera's plate (`silhouette::plate_of`) from its masked training images,
/// written to `plates/camNN.png` (alpha: where it is known); cameras with too few frames or
/// no pixel known have none.
fn plates(images: &[CaptureImage], photos: &Photos, camera_of: &[usize], dir: &Path) -> Result<std::collections::BTreeMap<usize, WrittenPlate>, ImportError> {
    let mut per_camera: std::collections::BTreeMap<usize, Vec<usize>> = std::collections::BTreeMap::new();
    // An EXR capture's light runs past what an 8-bit plate holds: its cameras get none.
    for (i, image) in images.iter().enumerate() {
        if image.split == Split::Train && !is_exr(image) {
            per_camera.entry(camera_of[i]).or_default().push(i);
        }
    }
    let mut plates = std::collections::BTreeMap::new();
    for (camera, members) in per_camera.into_iter().filter(|(_, m)| m.len() >= crate::silhouette::PLATE_SAMPLES) {
        let chosen: Vec<usize> = (0..members.len().min(PLATE_FRAMES)).map(|k| members[k * members.len() / members.len().min(PLATE_FRAMES)]).collect();
        let developed: Vec<(Vec<[u8; 3]>, Mask)> = chosen
            .par_iter()
            .map(|&i| {
                let (colour, mask) = develop(&images[i], photos, i)?;
                let f = photos.factors[i];
                let bytes = colour.downscaled(f).pixels.iter().map(|p| p.map(crate::imageio::linear_to_srgb8)).collect();
                Ok(mask.map(|m| (bytes, downscale_mask(&m, f))))
            })
            .collect::<Result<Vec<_>, ImportError>>()?
            .into_iter()
            .flatten()
            .collect();
        let Some(plate) = crate::silhouette::plate_of(&developed) else { continue };
        let relative = format!("plates/cam{camera:02}.png");
        let rgba: Vec<u8> = plate
            .colour
            .pixels
            .iter()
            .zip(plate.known.foreground.iter())
            .flat_map(|(p, &known)| {
                let [r, g, b] = p.map(crate::imageio::linear_to_srgb8);
                [r, g, b, if known { 255 } else { 0 }]
            })
            .collect();
        let bytes = crate::imageio::encode_png_raw(&rgba, plate.colour.width, plate.colour.height, image::ExtendedColorType::Rgba8)?;
        std::fs::create_dir_all(dir.join("plates")).map_err(|e| input(&dir.join("plates"), e.to_string()))?;
        crate::imageio::write_atomic(&dir.join(&relative), &bytes).map_err(|e| input(&dir.join(&relative), e.to_string()))?;
        plates.insert(camera, (relative, plate));
    }
    Ok(plates)
}

/// An image read, checked against its camera, with its mask, and its lens distortion removed:
/// full size, nothing blacked.
fn develop(image: &CaptureImage, photos: &Photos, i: usize) -> Result<(RgbImage, Option<Mask>), ImportError> {
    let (colour, alpha) = crate::photo::read_photo(&image.path)?;
    let k = &image.intrinsics;
    if (colour.width, colour.height) != (k.width, k.height) {
        return Err(input(&image.path, format!("is {}x{}, its camera ({}) says {}x{}", colour.width, colour.height, image.json_path, k.width, k.height)));
    }
    let mask = match &photos.masks[i] {
        MaskSource::File(file) => Some(crate::imageio::read_mask(file)?),
        MaskSource::Alpha => alpha,
    };
    if let Some(m) = &mask {
        if (m.width, m.height) != (k.width, k.height) {
            return Err(input(&image.path, format!("its mask is {}x{}, the image {}x{}", m.width, m.height, k.width, k.height)));
        }
    }
    if mask.is_none() && image.split == Split::Train {
        return Err(input(&image.path, "a training image needs a mask: mask_path in the camera file, --masks DIR with <name>.png, or an alpha channel"));
    }
    Ok(match image.distortion.is_none() {
        true => (colour, mask),
        false => {
            let undistorted = super::distortion::undistort_colour(&colour, k, &image.distortion);
            (undistorted, mask.map(|m| super::distortion::undistort_mask(&m, k, &image.distortion)))
        }
    })
}

/// Blacks every pixel of `colour` that `keep` does not keep.
fn black_unless(colour: &mut RgbImage, keep: impl Fn(usize) -> bool) {
    for (p, pixel) in colour.pixels.iter_mut().enumerate() {
        if !keep(p) {
            *pixel = [0.0; 3];
        }
    }
}

fn write_one(image: &CaptureImage, photos: &Photos, i: usize, plate: Option<&WrittenPlate>, dir: &Path) -> Result<Written, ImportError> {
    let (colour, mask) = develop(image, photos, i)?;
    let f = photos.factors[i];
    let (colour, mask, plate) = match (mask, plate) {
        // With a plate, what the camera saw near the mask's edge is kept (downscaled whole, so
        // an edge pixel averages body and plate, as the fit composites it), where the plate is
        // known: the fit decides the silhouette there.
        (Some(m), Some((relative, plate))) => {
            let (mut colour, m) = (colour.downscaled(f), downscale_mask(&m, f));
            let near = crate::silhouette::near_body(&m, crate::silhouette::EDGE_BAND);
            black_unless(&mut colour, |p| m.foreground[p] || (near[p] && plate.known.foreground[p]));
            (colour, Some(m), Some(relative.clone()))
        }
        // Else the background is blacked at full size, then again after downscaling: a pixel
        // on the silhouette averages body and black, as a renderer's pixel over its area does.
        (mask, _) => {
            let mut colour = colour;
            if let Some(m) = &mask {
                black_unless(&mut colour, |p| m.foreground[p]);
            }
            let (mut colour, mask) = (colour.downscaled(f), mask.map(|m| downscale_mask(&m, f)));
            if let Some(m) = &mask {
                black_unless(&mut colour, |p| m.foreground[p]);
            }
            (colour, mask, None)
        }
    };
    let stem = &image.key;
    let exr = is_exr(image);
    let path = format!("images/{stem}.{}", if exr { "exr" } else { "png" });
    // A key may hold folders (`cam02/000000`): the scene keeps them.
    for sub in ["images", "masks"] {
        let folder = dir.join(sub).join(stem);
        if let Some(parent) = folder.parent() {
            std::fs::create_dir_all(parent).map_err(|e| input(parent, e.to_string()))?;
        }
    }
    if exr {
        crate::imageio::write_exr_atomic(&dir.join(&path), &colour)?;
    } else {
        let bytes = crate::imageio::encode_png_rgb(&colour)?;
        crate::imageio::write_atomic(&dir.join(&path), &bytes).map_err(|e| input(&dir.join(&path), e.to_string()))?;
    }
    let mask_path = match &mask {
        Some(m) => {
            let relative = format!("masks/{stem}.png");
            let bytes = crate::imageio::encode_png_mask(m)?;
            crate::imageio::write_atomic(&dir.join(&relative), &bytes).map_err(|e| input(&dir.join(&relative), e.to_string()))?;
            Some(relative)
        }
        None => None,
    };
    Ok((path, mask_path, plate))
}

/// Whether the image is an EXR (kept as EXR in the scene, linear and unbounded).
fn is_exr(image: &CaptureImage) -> bool {
    image.path.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr"))
}

/// Each `f` x `f` block is body when at least half of it is.
fn downscale_mask(mask: &Mask, f: usize) -> Mask {
    if f <= 1 {
        return mask.clone();
    }
    let (w, h) = (mask.width / f, mask.height / f);
    let foreground = (0..w * h)
        .map(|p| {
            let (x, y) = (p % w, p / w);
            let inside = (0..f * f).filter(|&q| mask.foreground[(y * f + q / f) * mask.width + x * f + q % f]).count();
            2 * inside >= f * f
        })
        .collect();
    Mask { width: w, height: h, foreground }
}
