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
    Srgb8 {
        width: usize,
        height: usize,
        bytes: Vec<[u8; 3]>,
    },
    /// An 8-bit image whose black pixels are not kept (a scene's background is black): only
    /// the runs of other pixels, row-major, with where each run's bytes begin. Lossless.
    Runs(Runs),
    Linear(RgbImage),
}

/// The runs of an image's pixels that are not black (`Photo::Runs`).
#[derive(Clone, Debug, PartialEq)]
pub struct Runs {
    width: usize,
    height: usize,
    /// Each run's first pixel and one past its last (row-major indices), ascending.
    starts: Vec<u32>,
    ends: Vec<u32>,
    /// Where each run's pixels begin in `bytes`.
    offsets: Vec<u32>,
    bytes: Vec<[u8; 3]>,
}

impl Runs {
    /// `bytes` (row-major, `width x height`) without its black pixels.
    pub fn of(width: usize, height: usize, bytes: &[[u8; 3]]) -> Runs {
        let mut runs = Runs { width, height, starts: Vec::new(), ends: Vec::new(), offsets: Vec::new(), bytes: Vec::new() };
        let mut p = 0;
        while p < bytes.len() {
            if bytes[p] == [0; 3] {
                p += 1;
                continue;
            }
            let start = p;
            while p < bytes.len() && bytes[p] != [0; 3] {
                p += 1;
            }
            runs.starts.push(start as u32);
            runs.ends.push(p as u32);
            runs.offsets.push(runs.bytes.len() as u32);
            runs.bytes.extend_from_slice(&bytes[start..p]);
        }
        runs
    }

    /// Pixel `p`'s bytes (black where no run holds it).
    fn get(&self, p: usize) -> [u8; 3] {
        let k = self.starts.partition_point(|&s| s as usize <= p);
        match k {
            0 => [0; 3],
            _ if p < self.ends[k - 1] as usize => self.bytes[self.offsets[k - 1] as usize + p - self.starts[k - 1] as usize],
            _ => [0; 3],
        }
    }

    /// Bytes it holds in memory.
    fn size(&self) -> usize {
        3 * self.bytes.len() + 12 * self.starts.len()
    }

    /// Every pixel's bytes, row-major.
    fn walk(&self) -> impl Iterator<Item = [u8; 3]> + '_ {
        let mut run = 0;
        (0..self.width * self.height).map(move |p| {
            while run < self.ends.len() && self.ends[run] as usize <= p {
                run += 1;
            }
            match run < self.starts.len() && self.starts[run] as usize <= p {
                true => self.bytes[self.offsets[run] as usize + p - self.starts[run] as usize],
                false => [0; 3],
            }
        })
    }
}

impl Photo {
    pub fn width(&self) -> usize {
        match self {
            Photo::Srgb8 { width, .. } => *width,
            Photo::Runs(runs) => runs.width,
            Photo::Linear(image) => image.width,
        }
    }

    pub fn height(&self) -> usize {
        match self {
            Photo::Srgb8 { height, .. } => *height,
            Photo::Runs(runs) => runs.height,
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
            Photo::Runs(runs) => {
                let table = srgb8_table();
                runs.get(p).map(|c| table[c as usize])
            }
            Photo::Linear(image) => image.pixels[p],
        }
    }

    /// The pixel at column `x`, row `y`, in linear RGB.
    pub fn get(&self, x: usize, y: usize) -> [f32; 3] {
        self.pixel(y * self.width() + x)
    }

    /// Every pixel in linear RGB, row by row (runs walked in order, not searched).
    pub fn pixels(&self) -> Box<dyn Iterator<Item = [f32; 3]> + '_> {
        match self {
            Photo::Runs(runs) => {
                let table = srgb8_table();
                Box::new(runs.walk().map(move |b| b.map(|c| table[c as usize])))
            }
            _ => Box::new((0..self.width() * self.height()).map(|p| self.pixel(p))),
        }
    }

    /// The pixels that are not black, with their indices, in order (a scene's background is
    /// black: for an image kept as runs, only what it holds is visited).
    pub fn lit_pixels(&self) -> Box<dyn Iterator<Item = (usize, [f32; 3])> + '_> {
        match self {
            Photo::Runs(runs) => {
                let table = srgb8_table();
                Box::new(runs.starts.iter().zip(&runs.ends).zip(&runs.offsets).flat_map(move |((&start, &end), &offset)| {
                    (start as usize..end as usize).map(move |p| (p, runs.bytes[offset as usize + p - start as usize].map(|c| table[c as usize])))
                }))
            }
            _ => Box::new(self.pixels().enumerate().filter(|(_, c)| c.iter().any(|&v| v != 0.0))),
        }
    }

    /// The image in linear RGB, for what works on whole images (scores, contact sheets).
    pub fn to_rgb(&self) -> RgbImage {
        match self {
            Photo::Linear(image) => image.clone(),
            _ => RgbImage { width: self.width(), height: self.height(), pixels: self.pixels().collect() },
        }
    }

    /// Bytes it holds in memory.
    pub fn size(&self) -> usize {
        match self {
            Photo::Srgb8 { bytes, .. } => 3 * bytes.len(),
            Photo::Runs(runs) => runs.size(),
            Photo::Linear(image) => 12 * image.pixels.len(),
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
    let bytes: Vec<[u8; 3]> = img.into_rgb8().pixels().map(|p| p.0).collect();
    // A scene's black background need not be kept: the runs of the rest, when smaller.
    let runs = Runs::of(width, height, &bytes);
    Ok(match runs.size() < 3 * bytes.len() {
        true => Photo::Runs(runs),
        false => Photo::Srgb8 { width, height, bytes },
    })
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
    if format == image::ImageFormat::Jpeg && !jpeg_is_whole(&bytes) {
        return Err(decode_error("the JPEG is cut short (no end-of-image marker after its last scan): the file is truncated".into()));
    }
    let img = guarded(path, || image::load_from_memory_with_format(&bytes, format).map_err(|e| decode_error(e.to_string())))?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    let alpha = img.color().has_alpha().then(|| Mask { width, height, foreground: img.to_rgba8().pixels().map(|p| p.0[3] > 127).collect() });
    Ok((linear(img), alpha))
}

/// Whether a JPEG's bytes end its last scan: an end-of-image marker (`FF D9`) after the last
/// start-of-scan (`FF DA`). The decoder fills a truncated scan with grey and says nothing; in a
/// scan's coded data `FF` is always followed by `00` or a restart marker, so neither marker can
/// appear there by chance, and an embedded thumbnail's end comes before the image's scans.
pub fn jpeg_is_whole(bytes: &[u8]) -> bool {
    let last = |marker: u8| bytes.windows(2).rposition(|w| w == [0xFF, marker]);
    match (last(0xDA), last(0xD9)) {
        (Some(scan), Some(end)) => end > scan,
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_jpeg_cut_anywhere_in_its_scans_is_not_whole() {
        let mut image = image::RgbImage::new(32, 24);
        for (x, y, p) in image.enumerate_pixels_mut() {
            *p = image::Rgb([(x * 8) as u8, (y * 10) as u8, 77]);
        }
        let mut bytes = Vec::new();
        image::DynamicImage::ImageRgb8(image).write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Jpeg).unwrap();
        assert!(jpeg_is_whole(&bytes));
        let scan = bytes.windows(2).rposition(|w| w == [0xFF, 0xDA]).unwrap();
        for cut in (scan + 2..bytes.len() - 1).step_by(7) {
            assert!(!jpeg_is_whole(&bytes[..cut]), "cut at {cut} of {}", bytes.len());
        }
    }

    #[test]
    fn runs_keep_every_pixel_and_drop_only_black() {
        let (w, h) = (20, 5);
        let bytes: Vec<[u8; 3]> = (0..w * h).map(|p| if (p / 10) % 3 == 0 || p == w * h - 1 { [p as u8, 1, 2] } else { [0; 3] }).collect();
        let dense = Photo::Srgb8 { width: w, height: h, bytes: bytes.clone() };
        let runs = Photo::Runs(Runs::of(w, h, &bytes));
        assert_eq!(runs.to_rgb(), dense.to_rgb());
        assert!(runs.pixels().eq(dense.pixels()) && (0..w * h).all(|p| runs.pixel(p) == dense.pixel(p)));
        assert!(runs.lit_pixels().eq(dense.lit_pixels()) && runs.lit_pixels().count() == bytes.iter().filter(|b| **b != [0; 3]).count());
        assert!(runs.size() < dense.size());
        let black = Runs::of(w, h, &vec![[0; 3]; w * h]);
        assert_eq!(Photo::Runs(black.clone()).pixel(12), [0.0; 3]);
        assert_eq!(black.size(), 0);
    }
}
