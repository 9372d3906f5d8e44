//! Photographs in memory and from captures: a scene's colour image kept compact (`Photo`: an
//! 8-bit sRGB PNG as its bytes) and a capture's photo with its alpha as a mask (`read_photo`:
//! PNG, JPEG or EXR). Decoding, bounds and colour conversion are `imageio`'s.

use crate::imageio::{
    check_declared_size, decode_png, guarded, io_error, kind, linear, read_rgb, regular_file, srgb8_table, ImageError, Mask, RgbImage, MAX_PIXELS,
};
use std::path::Path;

/// A scene image as it is kept in memory: an 8-bit sRGB PNG as its bytes (3 bytes a pixel,
/// converted to linear on each read through the same table `read_rgb` uses, so the values are
/// those of the decoded image), anything else (16-bit PNG, EXR) as linear floats.
#[derive(Clone, Debug, PartialEq)]
pub enum Photo {
    Srgb8 { width: usize, height: usize, bytes: Vec<[u8; 3]> },
    Linear(RgbImage),
}

impl Photo {
    pub fn width(&self) -> usize {
        match self {
            Photo::Srgb8 { width, .. } => *width,
            Photo::Linear(image) => image.width,
        }
    }

    pub fn height(&self) -> usize {
        match self {
            Photo::Srgb8 { height, .. } => *height,
            Photo::Linear(image) => image.height,
        }
    }

    /// Pixel `p` (row-major) in linear RGB.
    pub fn pixel(&self, p: usize) -> [f32; 3] {
        match self {
            Photo::Srgb8 { bytes, .. } => {
                let table = srgb8_table();
                bytes[p].map(|c| table[c as usize])
            }
            Photo::Linear(image) => image.pixels[p],
        }
    }

    /// The pixel at column `x`, row `y`, in linear RGB.
    pub fn get(&self, x: usize, y: usize) -> [f32; 3] {
        self.pixel(y * self.width() + x)
    }

    /// Every pixel in linear RGB, row by row.
    pub fn pixels(&self) -> impl Iterator<Item = [f32; 3]> + '_ {
        (0..self.width() * self.height()).map(|p| self.pixel(p))
    }

    /// The image in linear RGB, for what works on whole images (scores, contact sheets).
    pub fn to_rgb(&self) -> RgbImage {
        match self {
            Photo::Linear(image) => image.clone(),
            Photo::Srgb8 { width, height, .. } => RgbImage { width: *width, height: *height, pixels: self.pixels().collect() },
        }
    }

    /// Bytes a pixel takes in memory.
    pub fn bytes_per_pixel(&self) -> usize {
        match self {
            Photo::Srgb8 { .. } => 3,
            Photo::Linear(_) => 12,
        }
    }
}

/// Reads a scene's colour image as `Photo`: an 8-bit sRGB PNG kept as bytes, anything else as
/// `read_rgb` decodes it.
pub fn read_photo_compact(path: &Path) -> Result<Photo, ImageError> {
    regular_file(path)?;
    check_declared_size(path)?;
    if kind(path) != Some("png") {
        return Ok(Photo::Linear(read_rgb(path)?));
    }
    let img = decode_png(path)?;
    if matches!(img.color(), image::ColorType::Rgb16 | image::ColorType::Rgba16 | image::ColorType::L16 | image::ColorType::La16) {
        return Ok(Photo::Linear(linear(img)));
    }
    let (width, height) = (img.width() as usize, img.height() as usize);
    let bytes = img.into_rgb8().pixels().map(|p| p.0).collect();
    Ok(Photo::Srgb8 { width, height, bytes })
}

/// Reads a photograph of a capture: an 8- or 16-bit sRGB PNG or a JPEG to linear RGB, with its
/// alpha as a mask (foreground where the 8-bit alpha is > 127) when it has one; an EXR as linear,
/// without a mask. What `umbra import` reads; scenes themselves hold PNG and EXR only.
pub fn read_photo(path: &Path) -> Result<(RgbImage, Option<Mask>), ImageError> {
    regular_file(path)?;
    let ext = path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).unwrap_or_default();
    let format = match ext.as_str() {
        "png" => image::ImageFormat::Png,
        "jpg" | "jpeg" => image::ImageFormat::Jpeg,
        "exr" => return Ok((read_rgb(path)?, None)),
        _ => return Err(ImageError::UnsupportedType(format!("{} (photos are PNG, JPEG or EXR)", path.display()))),
    };
    let decode_error = |e: String| ImageError::Decode(path.display().to_string(), e);
    let file = std::fs::File::open(path).map_err(|e| io_error(path, e))?;
    let reader = image::ImageReader::with_format(std::io::BufReader::new(file), format);
    let (w, h) = guarded(path, || reader.into_dimensions().map_err(|e| decode_error(e.to_string())))?;
    if (w as usize).saturating_mul(h as usize) > MAX_PIXELS {
        return Err(decode_error(format!("declares {w}x{h} pixels, more than the {MAX_PIXELS} allowed")));
    }
    let bytes = std::fs::read(path).map_err(|e| io_error(path, e))?;
    let img = guarded(path, || image::load_from_memory_with_format(&bytes, format).map_err(|e| decode_error(e.to_string())))?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    let alpha = img.color().has_alpha().then(|| Mask { width, height, foreground: img.to_rgba8().pixels().map(|p| p.0[3] > 127).collect() });
    Ok((linear(img), alpha))
}
