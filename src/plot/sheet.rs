//! Contact sheets with their labels: a title, a name over each column and beside each row,
//! the images enlarged by a whole factor to at least `MIN_CELL` pixels so small captures stay
//! legible.

use super::{Canvas, TextSize};
use crate::imageio::RgbImage;

/// The least side of a cell, pixels: smaller images are enlarged (pixel for pixel) to it.
pub const MIN_CELL: usize = 128;

pub struct Sheet<'a> {
    pub title: String,
    pub columns: Vec<String>,
    /// A label and its images, one per column (`None`: that cell is empty).
    pub rows: Vec<(String, Vec<Option<&'a RgbImage>>)>,
}

impl Sheet<'_> {
    pub fn render(&self) -> Canvas {
        let (small, title) = (TextSize::Small, TextSize::Title);
        let images = || self.rows.iter().flat_map(|(_, cells)| cells.iter().flatten());
        let side = images().map(|i| i.width.max(i.height)).max().unwrap_or(1).max(1);
        let scale = MIN_CELL.div_ceil(side).max(1);
        let cell_w = images().map(|i| i.width).max().unwrap_or(0) * scale;
        let cell_h = images().map(|i| i.height).max().unwrap_or(0) * scale;
        let columns = self.rows.iter().map(|(_, c)| c.len()).max().unwrap_or(0).max(self.columns.len());
        let header_width = self.columns.iter().map(|c| Canvas::text_width(c, small) as usize).max().unwrap_or(0);
        let cell_w = cell_w.max(header_width + 8);
        let gap = 4;
        let left = self.rows.iter().map(|(l, _)| Canvas::text_width(l, small) as usize).max().unwrap_or(0) + 16;
        let top = title.height() as usize + small.height() as usize + 22;
        let width = (left + columns * (cell_w + gap)).max(Canvas::text_width(&self.title, title) as usize + 16);
        let height = top + self.rows.len() * (cell_h + gap) + 4;
        let mut canvas = Canvas::new(width, height);
        let ink = [0, 0, 0];
        canvas.text(8, 6, &self.title, title, ink);
        for (c, name) in self.columns.iter().enumerate() {
            let x = left + c * (cell_w + gap) + cell_w / 2;
            canvas.text(x as i64 - Canvas::text_width(name, small) / 2, (top - small.height() as usize - 6) as i64, name, small, ink);
        }
        for (r, (label, cells)) in self.rows.iter().enumerate() {
            let y = top + r * (cell_h + gap);
            canvas.text(8, (y + cell_h / 2) as i64 - small.height() / 2, label, small, ink);
            for (c, image) in cells.iter().enumerate() {
                let x = left + c * (cell_w + gap);
                match image {
                    Some(image) => canvas.image(x as i64, y as i64, image, scale),
                    None => canvas.fill(x as i64, y as i64, (x + cell_w) as i64, (y + cell_h) as i64, [235, 235, 235]),
                }
            }
        }
        canvas
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sheet_enlarges_small_images_and_keeps_their_pixels() {
        let mut image = RgbImage::new(16, 8);
        image.set(3, 2, [1.0, 0.0, 0.0]);
        let sheet = Sheet { title: "renders".into(), columns: vec!["truth".into(), "render".into()], rows: vec![("c00 f0".into(), vec![Some(&image), None])] };
        let canvas = sheet.render();
        // 16 px wide: enlarged 8x, so its red pixel covers an 8 x 8 block.
        let (w, h) = (canvas.width, canvas.height);
        let red = (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).filter(|&(x, y)| canvas.pixel(x, y) == [255, 0, 0]).count();
        assert_eq!(red, 64);
        assert!(w > 2 * 128 && h > 64);
    }
}
