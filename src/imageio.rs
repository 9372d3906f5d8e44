//! Image files in and out: sRGB PNG and linear EXR decoded to linear f32 RGB, masks by the
//! > 127 rule, and atomic writes (temp file, then rename) for everything umbra produces.

use std::io::Write;
use std::path::Path;

/// A linear RGB image, row-major, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<[f32; 3]>,
}

impl RgbImage {
    pub fn new(width: usize, height: usize) -> Self {
        Self { width, height, pixels: vec![[0.0; 3]; width * height] }
    }

    /// The mean of each `f` x `f` block (linear light); a remainder row or column is dropped.
    pub fn downscaled(&self, f: usize) -> RgbImage {
        if f <= 1 {
            return self.clone();
        }
        let (w, h) = (self.width / f, self.height / f);
        let mut out = RgbImage::new(w, h);
        let n = (f * f) as f32;
        for y in 0..h {
            for x in 0..w {
                let mut sum = [0.0f32; 3];
                for dy in 0..f {
                    for dx in 0..f {
                        let p = self.pixels[(y * f + dy) * self.width + x * f + dx];
                        for c in 0..3 {
                            sum[c] += p[c];
                        }
                    }
                }
                out.pixels[y * w + x] = sum.map(|s| s / n);
            }
        }
        out
    }

    /// Shrunk by a whole factor (block means) to at most `side` pixels on its longer side, and
    /// at least one on its shorter: a thumbnail for a contact sheet.
    pub fn thumbnail(&self, side: usize) -> RgbImage {
        let f = self.width.max(self.height).div_ceil(side.max(1)).min(self.width.min(self.height)).max(1);
        self.downscaled(f)
    }

    pub fn get(&self, x: usize, y: usize) -> [f32; 3] {
        self.pixels[y * self.width + x]
    }

    pub fn set(&mut self, x: usize, y: usize, value: [f32; 3]) {
        self.pixels[y * self.width + x] = value;
    }

    /// Copies `image` in with its top-left corner at `(x0, y0)`, clipped to this image.
    pub fn blit(&mut self, image: &RgbImage, x0: usize, y0: usize) {
        for y in 0..image.height.min(self.height.saturating_sub(y0)) {
            for x in 0..image.width.min(self.width.saturating_sub(x0)) {
                self.set(x0 + x, y0 + y, image.get(x, y));
            }
        }
    }

    /// `gain` times the absolute difference to `other` per channel, clamped to 1 (both the
    /// same size), so that small errors show in a side-by-side sheet.
    pub fn difference(&self, other: &RgbImage, gain: f32) -> RgbImage {
        let pixels = self.pixels.iter().zip(&other.pixels).map(|(a, b)| std::array::from_fn(|k| ((a[k] - b[k]).abs() * gain).min(1.0))).collect();
        RgbImage { width: self.width, height: self.height, pixels }
    }
}

/// A foreground mask, row-major, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct Mask {
    pub width: usize,
    pub height: usize,
    pub foreground: Bits,
}

/// Booleans packed 64 to a word: a mask costs a bit a pixel, not a byte. Reads as a slice of
/// `bool` does (`bits[k]`, `len`, `iter`), is collected from booleans.
#[derive(Clone, Default, PartialEq, Eq)]
pub struct Bits {
    words: Vec<u64>,
    len: usize,
}

impl Bits {
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn get(&self, k: usize) -> bool {
        k < self.len && self.words[k / 64] >> (k % 64) & 1 == 1
    }

    pub fn iter(&self) -> impl Iterator<Item = &bool> + '_ {
        (0..self.len).map(|k| if self.get(k) { &true } else { &false })
    }
}

impl std::ops::Index<usize> for Bits {
    type Output = bool;

    /// Bit `k`; out of range panics, as a slice's index does.
    fn index(&self, k: usize) -> &bool {
        assert!(k < self.len, "bit {k} of {}", self.len);
        if self.get(k) {
            &true
        } else {
            &false
        }
    }
}

impl FromIterator<bool> for Bits {
    fn from_iter<I: IntoIterator<Item = bool>>(values: I) -> Self {
        let mut bits = Bits::default();
        for (k, value) in values.into_iter().enumerate() {
            if k % 64 == 0 {
                bits.words.push(0);
            }
            bits.words[k / 64] |= (value as u64) << (k % 64);
            bits.len = k + 1;
        }
        bits
    }
}

impl From<Vec<bool>> for Bits {
    fn from(values: Vec<bool>) -> Self {
        values.into_iter().collect()
    }
}

impl<'a> IntoIterator for &'a Bits {
    type Item = &'a bool;
    type IntoIter = Box<dyn Iterator<Item = &'a bool> + 'a>;

    fn into_iter(self) -> Self::IntoIter {
        Box::new(self.iter())
    }
}

impl std::fmt::Debug for Bits {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Bits({} of {} set)", self.iter().filter(|&&b| b).count(), self.len)
    }
}

/// Why an image could not be read; the scene reader adds the file and JSON path.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("file not found: {0}")]
    NotFound(String),
    #[error("unsupported image type (expected .png or .exr): {0}")]
    UnsupportedType(String),
    #[error("cannot decode {0}: {1}")]
    Decode(String, String),
    #[error("{0}")]
    Io(String),
}

/// sRGB transfer function, 8-bit code to linear.
pub fn srgb_to_linear(value: f32) -> f32 {
    if value <= 0.04045 {
        value / 12.92
    } else {
        ((value + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear to sRGB-encoded value in [0, 1] (input clamped).
pub fn linear_to_srgb(value: f32) -> f32 {
    let v = if value.is_finite() { value.clamp(0.0, 1.0) } else { 0.0 };
    if v <= 0.003_130_8 {
        v * 12.92
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// A centre-sampled pixel's expected value as its image stores it, from the colour a ray
/// composited over black (`premultiplied`, linear) and the share of it that met the body
/// (`coverage`, the probability that the centre ray hits the surface). Such a pixel is either
/// the surface's colour or black, so the value that errs least in the image's own encoding
/// (sRGB, as the eye, 8-bit PSNR and SSIM see it) is `coverage x sRGB(colour / coverage)`,
/// not the sRGB of the linear blend, which lifts a faint silhouette fringe (a ray passing a
/// few beta outside the surface: coverage 0.05) to a third of the surface's brightness.
/// Returned as the linear value that encodes to it; a wholly covered pixel is unchanged (so an
/// over-bright one keeps its range).
pub fn composite_centre_sample(premultiplied: [f32; 3], coverage: f32) -> [f32; 3] {
    if !(coverage > 0.0) {
        return [0.0; 3];
    }
    if coverage >= 1.0 {
        return premultiplied;
    }
    premultiplied.map(|c| srgb_to_linear(coverage * linear_to_srgb(c / coverage)))
}

/// Linear value to the 8-bit sRGB code a PNG stores (round to nearest).
pub fn linear_to_srgb8(value: f32) -> u8 {
    (linear_to_srgb(value) * 255.0 + 0.5).floor().clamp(0.0, 255.0) as u8
}

pub(crate) fn srgb8_table() -> &'static [f32; 256] {
    static TABLE: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let mut t = [0.0; 256];
        for (i, v) in t.iter_mut().enumerate() {
            *v = srgb_to_linear(i as f32 / 255.0);
        }
        t
    })
}

pub(crate) fn kind(path: &Path) -> Option<&'static str> {
    let ext = path.extension()?.to_str()?.to_ascii_lowercase();
    match ext.as_str() {
        "png" => Some("png"),
        "exr" => Some("exr"),
        _ => None,
    }
}

/// Decoders of third-party crates may panic on hostile input; a corrupt file must be an error.
pub(crate) fn guarded<T>(path: &Path, f: impl FnOnce() -> Result<T, ImageError>) -> Result<T, ImageError> {
    DECODER_GUARDS.with(|depth| depth.set(depth.get() + 1));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    DECODER_GUARDS.with(|depth| depth.set(depth.get() - 1));
    result.unwrap_or_else(|_| Err(ImageError::Decode(path.display().to_string(), "decoder panicked on corrupt data".into())))
}

thread_local! {
    /// How many decoder guards this thread is inside (`guarded`).
    static DECODER_GUARDS: std::cell::Cell<u32> = const { std::cell::Cell::new(0) };
}

/// Whether this thread is inside a third-party decoder's guard, where a panic is caught and
/// becomes a decode error (a fuzzing panic hook lets those unwind: `fuzzing::install_panic_hook`).
pub fn inside_decoder_guard() -> bool {
    DECODER_GUARDS.with(|depth| depth.get() > 0)
}

pub(crate) fn decode_png(path: &Path) -> Result<image::DynamicImage, ImageError> {
    let bytes = std::fs::read(path).map_err(|e| io_error(path, e))?;
    guarded(path, || {
        image::load_from_memory_with_format(&bytes, image::ImageFormat::Png).map_err(|e| ImageError::Decode(path.display().to_string(), e.to_string()))
    })
}

pub(crate) fn io_error(path: &Path, e: std::io::Error) -> ImageError {
    if e.kind() == std::io::ErrorKind::NotFound {
        ImageError::NotFound(path.display().to_string())
    } else {
        ImageError::Io(format!("{}: {e}", path.display()))
    }
}

/// The most pixels an image may declare (an 8K x 8K environment map): a header claiming more
/// is refused before anything is decoded, so a small hostile file cannot take minutes and
/// gigabytes.
pub const MAX_PIXELS: usize = 1 << 26;

/// An image's width and height from its header alone (PNG or EXR), nothing decoded.
pub fn dimensions(path: &Path) -> Result<(usize, usize), ImageError> {
    regular_file(path)?;
    let decode_error = |e: String| ImageError::Decode(path.display().to_string(), e);
    match kind(path) {
        Some("png") => {
            let file = std::fs::File::open(path).map_err(|e| io_error(path, e))?;
            let reader = image::ImageReader::with_format(std::io::BufReader::new(file), image::ImageFormat::Png);
            let (w, h) = guarded(path, || reader.into_dimensions().map_err(|e| decode_error(e.to_string())))?;
            Ok((w as usize, h as usize))
        }
        Some(_) => guarded(path, || {
            let meta = exr::meta::MetaData::read_from_file(path, false).map_err(|e| decode_error(e.to_string()))?;
            let header = meta.headers.first().ok_or_else(|| decode_error("no layer".into()))?;
            Ok((header.layer_size.width(), header.layer_size.height()))
        }),
        None => Err(ImageError::UnsupportedType(path.display().to_string())),
    }
}

/// Refuses a path that is missing, or is not a regular file (a FIFO would block a read).
pub(crate) fn regular_file(path: &Path) -> Result<(), ImageError> {
    match std::fs::metadata(path) {
        Ok(meta) if meta.is_file() => Ok(()),
        Ok(meta) if meta.is_dir() => Err(ImageError::Io(format!("{}: is a folder, not an image", path.display()))),
        Ok(_) => Err(ImageError::Io(format!("{}: is not a regular file (a device, FIFO or socket)", path.display()))),
        Err(_) => Err(ImageError::NotFound(path.display().to_string())),
    }
}

/// Refuses a header that declares more than `MAX_PIXELS`.
pub(crate) fn check_declared_size(path: &Path) -> Result<(), ImageError> {
    let (w, h) = dimensions(path)?;
    if w.saturating_mul(h) > MAX_PIXELS {
        return Err(ImageError::Decode(path.display().to_string(), format!("declares {w}x{h} pixels, more than the {MAX_PIXELS} allowed")));
    }
    Ok(())
}

/// Reads a colour image: sRGB PNG (8 or 16 bit) to linear, EXR as linear (alpha ignored).
pub fn read_rgb(path: &Path) -> Result<RgbImage, ImageError> {
    regular_file(path)?;
    check_declared_size(path)?;
    match kind(path) {
        Some("png") => Ok(linear(decode_png(path)?)),
        Some(_) => read_exr(path),
        None => Err(ImageError::UnsupportedType(path.display().to_string())),
    }
}

/// A decoded sRGB image (8 or 16 bit) in linear RGB, converted in place where the decoder's
/// layout allows (`into_*`): a 16-bit image of 2^26 pixels would otherwise hold a second 400 MB
/// copy while it is converted.
pub(crate) fn linear(img: image::DynamicImage) -> RgbImage {
    let (width, height) = (img.width() as usize, img.height() as usize);
    let pixels = if matches!(img.color(), image::ColorType::Rgb16 | image::ColorType::Rgba16 | image::ColorType::L16 | image::ColorType::La16) {
        img.into_rgb16().pixels().map(|p| p.0.map(|c| srgb_to_linear(c as f32 / 65535.0))).collect()
    } else {
        let table = srgb8_table();
        img.into_rgb8().pixels().map(|p| p.0.map(|c| table[c as usize])).collect()
    };
    RgbImage { width, height, pixels }
}

fn read_exr(path: &Path) -> Result<RgbImage, ImageError> {
    use exr::prelude::*;
    guarded(path, || {
        let image = read_first_rgba_layer_from_file(
            path,
            |resolution, _| RgbImage::new(resolution.width(), resolution.height()),
            |img: &mut RgbImage, position, (r, g, b, _a): (f32, f32, f32, f32)| {
                img.set(position.x(), position.y(), [r, g, b]);
            },
        )
        .map_err(|e| ImageError::Decode(path.display().to_string(), e.to_string()))?;
        Ok(image.layer_data.channel_data.pixels)
    })
}

/// Reads a mask: the first channel of a PNG, foreground where the 8-bit value is > 127.
pub fn read_mask(path: &Path) -> Result<Mask, ImageError> {
    regular_file(path)?;
    if kind(path) != Some("png") {
        return Err(ImageError::UnsupportedType(format!("{} (masks are PNG)", path.display())));
    }
    check_declared_size(path)?;
    let img = decode_png(path)?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    // The first channel: read in place for 8-bit layouts; otherwise to_rgba8 keeps it as is for
    // grey, RGB and RGBA inputs (16-bit scaled to 8).
    let foreground = match &img {
        image::DynamicImage::ImageLuma8(i) => i.as_raw().iter().map(|&v| v > 127).collect(),
        image::DynamicImage::ImageLumaA8(i) => i.as_raw().chunks_exact(2).map(|c| c[0] > 127).collect(),
        image::DynamicImage::ImageRgb8(i) => i.as_raw().chunks_exact(3).map(|c| c[0] > 127).collect(),
        image::DynamicImage::ImageRgba8(i) => i.as_raw().chunks_exact(4).map(|c| c[0] > 127).collect(),
        _ => img.to_rgba8().pixels().map(|p| p.0[0] > 127).collect(),
    };
    Ok(Mask { width, height, foreground })
}

/// Writes `bytes` to `path` atomically: a temp file beside it, then a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let (temp, mut file) = crate::files::create_new_beside(path, "tmp")?;
    let result = (|| {
        file.write_all(bytes)?;
        file.sync_all()?;
        std::fs::rename(&temp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result
}

/// Encodes linear RGB as an 8-bit sRGB PNG.
pub fn encode_png_rgb(image: &RgbImage) -> Result<Vec<u8>, ImageError> {
    let mut raw = Vec::with_capacity(image.pixels.len() * 3);
    for p in &image.pixels {
        raw.extend(p.iter().map(|&c| linear_to_srgb8(c)));
    }
    encode_png_raw(&raw, image.width, image.height, image::ExtendedColorType::Rgb8)
}

/// Encodes a mask as an 8-bit grey PNG (255 foreground, 0 background).
pub fn encode_png_mask(mask: &Mask) -> Result<Vec<u8>, ImageError> {
    let raw: Vec<u8> = mask.foreground.iter().map(|&f| if f { 255 } else { 0 }).collect();
    encode_png_raw(&raw, mask.width, mask.height, image::ExtendedColorType::L8)
}

/// Encodes raw 8-bit samples (already encoded values) as PNG.
pub fn encode_png_raw(raw: &[u8], width: usize, height: usize, color: image::ExtendedColorType) -> Result<Vec<u8>, ImageError> {
    use image::ImageEncoder;
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(raw, width as u32, height as u32, color)
        .map_err(|e| ImageError::Decode("png encoder".into(), e.to_string()))?;
    Ok(out)
}

/// Writes a linear RGB image as a float EXR, atomically.
pub fn write_exr_atomic(path: &Path, image: &RgbImage) -> Result<(), ImageError> {
    // The temp name is made exclusively (nobody's file), then the encoder writes into it.
    let (temp, _) = crate::files::create_new_beside(path, "tmp.exr").map_err(|e| io_error(path, e))?;
    let result = exr::prelude::write_rgb_file(&temp, image.width, image.height, |x, y| {
        let p = image.get(x, y);
        (p[0], p[1], p[2])
    })
    .map_err(|e| ImageError::Io(format!("{}: {e}", path.display())))
    .and_then(|_| std::fs::rename(&temp, path).map_err(|e| io_error(path, e)));
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_round_trips_every_code() {
        for code in 0..=255u8 {
            let linear = srgb_to_linear(code as f32 / 255.0);
            assert_eq!(linear_to_srgb8(linear), code);
        }
    }

    #[test]
    fn differences_are_amplified_and_clamped() {
        let mut a = RgbImage::new(2, 1);
        a.set(1, 0, [0.5, 0.1, 0.0]);
        let d = a.difference(&RgbImage::new(2, 1), 4.0);
        assert_eq!(d.get(1, 0), [1.0, 0.4, 0.0]);
    }

    #[test]
    fn a_centre_sample_is_its_expected_stored_value() {
        // Covered: unchanged, over-bright included. Missed: black.
        assert_eq!(composite_centre_sample([0.3, 1.7, 0.0], 1.0), [0.3, 1.7, 0.0]);
        assert_eq!(composite_centre_sample([0.3, 0.2, 0.1], 0.0), [0.0; 3]);
        assert_eq!(composite_centre_sample([0.3, 0.2, 0.1], f32::NAN), [0.0; 3]);
        // Half covered by a surface of linear 0.8: half its sRGB code (not the code of 0.4).
        let v = composite_centre_sample([0.4; 3], 0.5)[0];
        assert!((linear_to_srgb(v) - 0.5 * linear_to_srgb(0.8)).abs() < 1e-6);
        assert!(linear_to_srgb(v) < linear_to_srgb(0.4) - 0.1);
    }

    #[test]
    fn srgb_known_points() {
        assert!((srgb_to_linear(0.5) - 0.214_041).abs() < 1e-5);
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
    }
}
