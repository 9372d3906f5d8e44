//! Small PNG charts (lines and points on linear or log axes, with a legend) so that results
//! people look at are pictures: loss curves, time-versus-error trade-offs.

use std::path::Path;

/// 3x5 bitmap glyphs, one row per entry (bit 2 = left column).
fn glyph(c: char) -> [u8; 5] {
    match c.to_ascii_uppercase() {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 2, 2],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        'A' => [2, 5, 7, 5, 5],
        'B' => [6, 5, 6, 5, 6],
        'C' => [3, 4, 4, 4, 3],
        'D' => [6, 5, 5, 5, 6],
        'E' => [7, 4, 6, 4, 7],
        'F' => [7, 4, 6, 4, 4],
        'G' => [3, 4, 5, 5, 3],
        'H' => [5, 5, 7, 5, 5],
        'I' => [7, 2, 2, 2, 7],
        'J' => [1, 1, 1, 5, 2],
        'K' => [5, 5, 6, 5, 5],
        'L' => [4, 4, 4, 4, 7],
        'M' => [5, 7, 7, 5, 5],
        'N' => [6, 5, 5, 5, 5],
        'O' => [2, 5, 5, 5, 2],
        'P' => [6, 5, 6, 4, 4],
        'Q' => [2, 5, 5, 6, 3],
        'R' => [6, 5, 6, 5, 5],
        'S' => [3, 4, 2, 1, 6],
        'T' => [7, 2, 2, 2, 2],
        'U' => [5, 5, 5, 5, 7],
        'V' => [5, 5, 5, 5, 2],
        'W' => [5, 5, 7, 7, 5],
        'X' => [5, 5, 2, 5, 5],
        'Y' => [5, 5, 2, 2, 2],
        'Z' => [7, 1, 2, 4, 7],
        '.' => [0, 0, 0, 0, 2],
        '-' => [0, 0, 7, 0, 0],
        '+' => [0, 2, 7, 2, 0],
        '/' => [1, 1, 2, 4, 4],
        ':' => [0, 2, 0, 2, 0],
        '(' => [1, 2, 2, 2, 1],
        ')' => [4, 2, 2, 2, 4],
        '_' => [0, 0, 0, 0, 7],
        '=' => [0, 7, 0, 7, 0],
        ',' => [0, 0, 0, 2, 4],
        '%' => [5, 1, 2, 4, 5],
        '^' => [2, 5, 0, 0, 0],
        _ => [0; 5],
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
        if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
            self.pixels[y as usize * self.width + x as usize] = c;
        }
    }

    pub fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), c: [u8; 3]) {
        let steps = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
        for k in 0..=steps {
            let t = k as f64 / steps as f64;
            self.set((x0 + (x1 - x0) * t).round() as i64, (y0 + (y1 - y0) * t).round() as i64, c);
        }
    }

    pub fn text(&mut self, x: i64, y: i64, s: &str, scale: i64, c: [u8; 3]) {
        for (i, ch) in s.chars().enumerate() {
            let g = glyph(ch);
            for (row, bits) in g.iter().enumerate() {
                for col in 0..3 {
                    if bits & (4 >> col) != 0 {
                        for dy in 0..scale {
                            for dx in 0..scale {
                                self.set(x + (i as i64 * 4 + col) * scale + dx, y + row as i64 * scale + dy, c);
                            }
                        }
                    }
                }
            }
        }
    }

    pub fn fill(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: [u8; 3]) {
        for y in y0..y1 {
            for x in x0..x1 {
                self.set(x, y, c);
            }
        }
    }

    pub fn save_png(&self, path: &Path) -> Result<(), String> {
        let raw: Vec<u8> = self.pixels.iter().flatten().copied().collect();
        let png = crate::imageio::encode_png_raw(&raw, self.width, self.height, image::ExtendedColorType::Rgb8).map_err(|e| e.to_string())?;
        crate::imageio::write_atomic(path, &png).map_err(|e| format!("{}: {e}", path.display()))
    }
}

pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    /// Draw connecting lines (else markers only).
    pub lines: bool,
}

pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_x: bool,
    pub log_y: bool,
    pub series: Vec<Series>,
}

const COLOURS: [[u8; 3]; 8] = [[31, 119, 180], [214, 39, 40], [44, 160, 44], [255, 127, 14], [148, 103, 189], [140, 86, 75], [227, 119, 194], [23, 190, 207]];

fn label(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if v.abs() >= 1e4 || v.abs() < 1e-2 {
        format!("{v:.0e}")
    } else if v.abs() >= 100.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.2}")
    }
}

impl Chart {
    /// Renders the chart to a PNG of `width` x `height` pixels.
    pub fn render(&self, width: usize, height: usize) -> Canvas {
        let mut canvas = Canvas::new(width, height);
        let (left, right, top, bottom) = (70.0, width as f64 - 20.0, 40.0, height as f64 - 50.0);
        let tx = |v: f64| if self.log_x { v.max(1e-300).log10() } else { v };
        let ty = |v: f64| if self.log_y { v.max(1e-300).log10() } else { v };
        let finite: Vec<(f64, f64)> = self
            .series
            .iter()
            .flat_map(|s| s.points.iter().copied())
            .filter(|(x, y)| x.is_finite() && y.is_finite() && (!self.log_x || *x > 0.0) && (!self.log_y || *y > 0.0))
            .map(|(x, y)| (tx(x), ty(y)))
            .collect();
        let (mut x0, mut x1, mut y0, mut y1) = finite
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY), |a, p| (a.0.min(p.0), a.1.max(p.0), a.2.min(p.1), a.3.max(p.1)));
        if !x0.is_finite() {
            (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
        }
        if x1 - x0 < 1e-12 {
            x1 = x0 + 1.0;
        }
        if y1 - y0 < 1e-12 {
            y1 = y0 + 1.0;
        }
        let pad = (y1 - y0) * 0.05;
        let (y0, y1) = (y0 - pad, y1 + pad);
        let pad = (x1 - x0) * 0.04;
        let (x0, x1) = (x0 - pad, x1 + pad);
        let px = |x: f64| left + (x - x0) / (x1 - x0) * (right - left);
        let py = |y: f64| bottom - (y - y0) / (y1 - y0) * (bottom - top);
        let grey = [190, 190, 190];
        let black = [0, 0, 0];
        for k in 0..=4 {
            let fy = y0 + (y1 - y0) * k as f64 / 4.0;
            canvas.line((left, py(fy)), (right, py(fy)), grey);
            let value = if self.log_y { 10f64.powf(fy) } else { fy };
            canvas.text(4, py(fy) as i64 - 5, &label(value), 2, black);
            let fx = x0 + (x1 - x0) * k as f64 / 4.0;
            canvas.line((px(fx), top), (px(fx), bottom), grey);
            let value = if self.log_x { 10f64.powf(fx) } else { fx };
            canvas.text(px(fx) as i64 - 12, bottom as i64 + 8, &label(value), 2, black);
        }
        canvas.line((left, bottom), (right, bottom), black);
        canvas.line((left, top), (left, bottom), black);
        canvas.text(left as i64, 8, &self.title, 3, black);
        let x_name = format!("{}{}", self.x_label, if self.log_x { " (log)" } else { "" });
        canvas.text((left + right) as i64 / 2 - 60, height as i64 - 18, &x_name, 2, black);
        let y_name = format!("{}{}", self.y_label, if self.log_y { " (log)" } else { "" });
        canvas.text(right as i64 - 8 * y_name.len() as i64 - 4, top as i64 - 14, &y_name, 2, black);
        for (i, s) in self.series.iter().enumerate() {
            let c = COLOURS[i % COLOURS.len()];
            let pts: Vec<(f64, f64)> = s
                .points
                .iter()
                .filter(|(x, y)| x.is_finite() && y.is_finite() && (!self.log_x || *x > 0.0) && (!self.log_y || *y > 0.0))
                .map(|&(x, y)| (px(tx(x)), py(ty(y))))
                .collect();
            for w in pts.windows(2) {
                if s.lines {
                    canvas.line(w[0], w[1], c);
                }
            }
            if !s.lines {
                for &(x, y) in &pts {
                    for d in -3..=3 {
                        canvas.set(x as i64 + d, y as i64, c);
                        canvas.set(x as i64, y as i64 + d, c);
                    }
                }
            }
            canvas.text(left as i64 + 10, top as i64 + 6 + 14 * i as i64, &s.name, 2, c);
        }
        canvas
    }
}

/// Horizontal bars: one group of bars per label, one bar per series (its colour), values
/// written beside them.
pub struct BarChart {
    pub title: String,
    pub unit: String,
    pub labels: Vec<String>,
    /// Series name and one value per label.
    pub series: Vec<(String, Vec<f64>)>,
}

impl BarChart {
    pub fn render(&self, width: usize) -> Canvas {
        let (bar, gap, left, top) = (12i64, 10i64, 330i64, 40i64);
        let group = bar * self.series.len().max(1) as i64 + gap;
        let height = (top + group * self.labels.len() as i64 + 30 + 16 * self.series.len() as i64) as usize;
        let mut canvas = Canvas::new(width, height);
        canvas.text(10, 10, &self.title, 2, [0, 0, 0]);
        let max = self.series.iter().flat_map(|(_, v)| v.iter().copied()).filter(|v| v.is_finite()).fold(0.0f64, f64::max).max(1e-12);
        let span = (width as i64 - left - 90) as f64;
        for (i, label) in self.labels.iter().enumerate() {
            let y = top + group * i as i64;
            canvas.text(10, y + 2, label, 1, [0, 0, 0]);
            for (k, (_, values)) in self.series.iter().enumerate() {
                let v = values.get(i).copied().unwrap_or(0.0);
                let y = y + bar * k as i64;
                let end = left + (v.max(0.0) / max * span).round() as i64;
                canvas.fill(left, y, end.max(left + 1), y + bar - 2, COLOURS[k % COLOURS.len()]);
                canvas.text(end + 4, y + 2, &format!("{v:.1} {}", self.unit), 1, [0, 0, 0]);
            }
        }
        let legend = top + group * self.labels.len() as i64 + 10;
        for (k, (name, _)) in self.series.iter().enumerate() {
            let y = legend + 16 * k as i64;
            canvas.fill(10, y, 22, y + 10, COLOURS[k % COLOURS.len()]);
            canvas.text(28, y + 2, name, 1, [0, 0, 0]);
        }
        canvas
    }
}
