//! A capture's photographs into a scene's images: each read (PNG, JPEG or EXR), its mask found
//! (the camera file's `mask_path`, `--masks DIR/<stem>.png`, else the image's alpha), the lens
//! distortion removed, downscaled by a whole factor to `--max-size`, the background blacked by
//! the mask, and written under the image's own name; in parallel, one image in memory per thread.

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

/// Processes and writes every image into `dir` (`images/`, `masks/`); returns each image's
/// path and mask path relative to `dir`. `on(done, total)` after each.
pub fn write(images: &[CaptureImage], photos: &Photos, dir: &Path, on: &(dyn Fn(usize, usize) + Sync)) -> Result<Vec<(String, Option<String>)>, ImportError> {
    for sub in ["images", "masks"] {
        std::fs::create_dir_all(dir.join(sub)).map_err(|e| input(&dir.join(sub), e.to_string()))?;
    }
    let done = AtomicUsize::new(0);
    (0..images.len())
        .into_par_iter()
        .map(|i| {
            let written = write_one(&images[i], photos, i, dir);
            on(done.fetch_add(1, Ordering::Relaxed) + 1, images.len());
            written
        })
        .collect()
}

fn write_one(image: &CaptureImage, photos: &Photos, i: usize, dir: &Path) -> Result<(String, Option<String>), ImportError> {
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
    let (colour, mask) = if image.distortion.is_none() {
        (colour, mask)
    } else {
        let undistorted = super::distortion::undistort_colour(&colour, k, &image.distortion);
        (undistorted, mask.map(|m| super::distortion::undistort_mask(&m, k, &image.distortion)))
    };
    // The background blacked at full size, then again after downscaling: a pixel on the
    // silhouette averages body and black, as a renderer's pixel over its area does.
    let black_outside = |colour: &mut RgbImage, mask: &Option<Mask>| {
        if let Some(m) = mask {
            for (pixel, &inside) in colour.pixels.iter_mut().zip(&m.foreground) {
                if !inside {
                    *pixel = [0.0; 3];
                }
            }
        }
    };
    let mut colour = colour;
    black_outside(&mut colour, &mask);
    let f = photos.factors[i];
    let (mut colour, mask) = (colour.downscaled(f), mask.map(|m| downscale_mask(&m, f)));
    black_outside(&mut colour, &mask);
    let stem = &image.key;
    let exr = image.path.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr"));
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
    Ok((path, mask_path))
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
