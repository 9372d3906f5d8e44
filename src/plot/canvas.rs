//! An RGB canvas in 8-bit sRGB with lines, boxes and text in a real font (Noto Sans Mono,
//! pre-rasterised with anti-aliasing by the `noto-sans-mono-bitmap` crate: no system font and no
//! rasteriser needed), saved as PNG.

use noto_sans_mono_bitmap::{get_raster, get_raster_width, FontWeight, RasterHeight};
use std::path::Path;

/// Text sizes: labels, legends and axis names, titles (bold).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TextSize {
    Small,
    Normal,
    Title,
}

impl TextSize {
    fn raster(self) -> (FontWeight, RasterHeight) {
        match self {
            TextSize::Small => (FontWeight::Regular, RasterHeight::Size16),
            TextSize::Normal => (FontWeight::Regular, RasterHeight::Size20),
            TextSize::Title => (FontWeight::Bold, RasterHeight::Size24),
        }
    }

    /// The height of a line of text, pixels.
    pub fn height(self) -> i64 {
        self.raster().1.val() as i64
    }

    /// The advance of one character, pixels (the font is monospaced).
    pub fn advance(self) -> i64 {
        let (weight, height) = self.raster();
        get_raster_width(weight, height) as i64
    }
}

pub struct Canvas {
    pub width: usize,
    pub height: usize,
    pixels: Vec<[u8; 3]>,
}

impl Canvas {
    pub fn new(width: usize, height: usize) -> Self {
        Self { width, height, pixels: vec![[255; 3]; width * height] }
    }

    pub fn set(&mut self, x: i64, y: i64, c: [u8; 3]) {
        self.blend(x, y, c, 255);
    }

    /// `c` over the pixel with opacity `alpha` / 255.
    pub fn blend(&mut self, x: i64, y: i64, c: [u8; 3], alpha: u8) {
        if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height || alpha == 0 {
            return;
        }
        let pixel = &mut self.pixels[y as usize * self.width + x as usize];
        let a = alpha as u32;
        *pixel = std::array::from_fn(|k| ((c[k] as u32 * a + pixel[k] as u32 * (255 - a) + 127) / 255) as u8);
    }

    pub fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), c: [u8; 3]) {
        let steps = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
        for k in 0..=steps {
            let t = k as f64 / steps as f64;
            self.set((x0 + (x1 - x0) * t).round() as i64, (y0 + (y1 - y0) * t).round() as i64, c);
        }
    }

    /// A line two pixels wide.
    pub fn thick_line(&mut self, a: (f64, f64), b: (f64, f64), c: [u8; 3]) {
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let (ox, oy) = if dx.abs() >= dy.abs() { (0.0, 1.0) } else { (1.0, 0.0) };
        self.line(a, b, c);
        self.line((a.0 + ox, a.1 + oy), (b.0 + ox, b.1 + oy), c);
    }

    /// A vertical dashed line from `y0` to `y1` at `x`.
    pub fn dashed_vertical(&mut self, x: f64, y0: f64, y1: f64, c: [u8; 3]) {
        let x = x.round() as i64;
        for y in y0.round() as i64..=y1.round() as i64 {
            if (y / 4) % 2 == 0 {
                self.set(x, y, c);
            }
        }
    }

    /// `s` with its top-left corner at (`x`, `y`).
    pub fn text(&mut self, x: i64, y: i64, s: &str, size: TextSize, c: [u8; 3]) {
        let (weight, height) = size.raster();
        for (i, ch) in s.chars().enumerate() {
            let Some(glyph) = get_raster(ch, weight, height).or_else(|| get_raster('?', weight, height)) else { continue };
            let left = x + i as i64 * size.advance();
            for (row, intensities) in glyph.raster().iter().enumerate() {
                for (col, &alpha) in intensities.iter().enumerate() {
                    self.blend(left + col as i64, y + row as i64, c, alpha);
                }
            }
        }
    }

    /// The width `s` takes in `size`, pixels.
    pub fn text_width(s: &str, size: TextSize) -> i64 {
        s.chars().count() as i64 * size.advance()
    }

    pub fn fill(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: [u8; 3]) {
        for y in y0..y1 {
            for x in x0..x1 {
                self.set(x, y, c);
            }
        }
    }

    /// An image in linear RGB at (`x`, `y`), encoded to sRGB, each pixel `scale` x `scale`.
    pub fn image(&mut self, x: i64, y: i64, image: &crate::imageio::RgbImage, scale: usize) {
        for (p, c) in image.pixels.iter().enumerate() {
            let srgb = c.map(crate::imageio::linear_to_srgb8);
            let (px, py) = ((p % image.width * scale) as i64, (p / image.width * scale) as i64);
            self.fill(x + px, y + py, x + px + scale as i64, y + py + scale as i64, srgb);
        }
    }

    pub fn save_png(&self, path: &Path) -> Result<(), String> {
        let raw: Vec<u8> = self.pixels.iter().flatten().copied().collect();
        let png = crate::imageio::encode_png_raw(&raw, self.width, self.height, image::ExtendedColorType::Rgb8).map_err(|e| e.to_string())?;
        crate::imageio::write_atomic(path, &png).map_err(|e| format!("{}: {e}", path.display()))
    }

    /// The pixel at (`x`, `y`) (tests and sheets).
    pub fn pixel(&self, x: usize, y: usize) -> [u8; 3] {
        self.pixels[y * self.width + x]
    }
}
