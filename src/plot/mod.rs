//! Small PNG charts (lines and points on linear or log axes, with a legend and marked
//! iterations; horizontal bars) and labelled contact sheets, so that results people look at
//! are pictures: loss curves with the schedule's stages, time-versus-error trade-offs, renders
//! beside their truth.

mod canvas;
mod sheet;

pub use canvas::{Canvas, TextSize};
pub use sheet::Sheet;

pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    /// Draw connecting lines (else markers only).
    pub lines: bool,
}

/// A vertical line across a chart at `x`, labelled: where a stage of a schedule begins.
pub struct Mark {
    pub x: f64,
    pub label: String,
}

pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_x: bool,
    pub log_y: bool,
    pub series: Vec<Series>,
    pub marks: Vec<Mark>,
}

/// Twelve colours told apart at a glance (near-black first, then Tableau's ten and one more),
/// so that a chart's series up to twelve never share one.
pub const COLOURS: [[u8; 3]; 12] = [
    [30, 30, 30],
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [188, 189, 34],
    [23, 190, 207],
    [255, 187, 120],
];

const GRID: [u8; 3] = [225, 225, 225];
const INK: [u8; 3] = [0, 0, 0];
const MARK: [u8; 3] = [110, 110, 110];

/// A tick value as a person reads it.
fn label(v: f64) -> String {
    let a = v.abs();
    if v == 0.0 {
        "0".into()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{v:.0e}")
    } else if a >= 100.0 || (v.fract() == 0.0 && a >= 1.0) {
        format!("{v:.0}")
    } else {
        // Two significant digits, trailing zeros dropped: 2.5, 0.25, 0.1, 0.001.
        let digits = (1 - a.log10().floor() as i64).max(0) as usize;
        let text = format!("{v:.digits$}");
        let text = if text.contains('.') { text.trim_end_matches('0').trim_end_matches('.') } else { &text };
        text.to_string()
    }
}

/// An axis: the data's range in axis units (log10 on a log axis) and its ticks.
struct Axis {
    lo: f64,
    hi: f64,
    log: bool,
    /// Tick positions in axis units.
    ticks: Vec<f64>,
}

/// The least of 1, 2 or 5 times a power of ten that is at least `span / 6`.
fn nice_step(span: f64) -> f64 {
    let raw = span / 6.0;
    let power = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0].into_iter().map(|m| m * power).find(|&s| s >= raw).unwrap_or(10.0 * power)
}

impl Axis {
    /// The axis over `values` (already finite and, on a log axis, positive), widened by `pad`
    /// of its span on each side (0: it starts and ends where the data does).
    fn new(values: impl Iterator<Item = f64>, log: bool, pad: f64) -> Axis {
        let to_axis = |v: f64| if log { v.log10() } else { v };
        let (mut lo, mut hi) = values.map(to_axis).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
        if !lo.is_finite() {
            (lo, hi) = (0.0, 1.0);
        }
        if hi - lo < 1e-12 {
            (lo, hi) = (lo - 0.5, hi + 0.5);
        }
        let span = hi - lo;
        let (lo, hi) = (lo - pad * span, hi + pad * span);
        let ticks = if log && hi - lo >= 1.0 {
            let step = ((hi - lo) / 6.0).ceil().max(1.0);
            let first = (lo / step).ceil() * step;
            (0..).map(|k| first + k as f64 * step).take_while(|&t| t <= hi + 1e-9).collect()
        } else if log {
            // Less than a decade: 1, 2 and 5 times powers of ten inside it.
            let mut ticks: Vec<f64> = (lo.floor() as i32..=hi.ceil() as i32)
                .flat_map(|e| [1.0, 2.0, 5.0].map(|m| (m * 10f64.powi(e)).log10()))
                .filter(|t| *t >= lo - 1e-9 && *t <= hi + 1e-9)
                .collect();
            if ticks.len() < 2 {
                ticks = vec![lo, hi];
            }
            ticks
        } else {
            let step = nice_step(hi - lo);
            let first = (lo / step).ceil() * step;
            (0..).map(|k| first + k as f64 * step).take_while(|&t| t <= hi + 1e-9 * step).collect()
        };
        Axis { lo, hi, log, ticks }
    }

    fn value(&self, t: f64) -> f64 {
        if self.log {
            10f64.powf(t)
        } else {
            t
        }
    }

    /// A data value on the axis, in axis units.
    fn of(&self, v: f64) -> f64 {
        if self.log {
            v.max(1e-300).log10()
        } else {
            v
        }
    }
}

impl Chart {
    /// Whether a point can be drawn on this chart's axes.
    fn drawable(&self, (x, y): (f64, f64)) -> bool {
        x.is_finite() && y.is_finite() && (!self.log_x || x > 0.0) && (!self.log_y || y > 0.0)
    }

    /// Renders the chart to a canvas of `width` x `height` pixels: the plot, the legend to its
    /// right, the marks as dashed lines labelled at their top.
    pub fn render(&self, width: usize, height: usize) -> Canvas {
        let mut canvas = Canvas::new(width, height);
        let points: Vec<(f64, f64)> = self.series.iter().flat_map(|s| s.points.iter().copied()).filter(|&p| self.drawable(p)).collect();
        // A linear x axis starts and ends where the data does; values get a margin.
        let x_axis = Axis::new(points.iter().map(|p| p.0), self.log_x, if self.log_x { 0.02 } else { 0.0 });
        let y_axis = Axis::new(points.iter().map(|p| p.1), self.log_y, 0.05);
        let (small, normal) = (TextSize::Small, TextSize::Normal);
        let tick_width = y_axis.ticks.iter().map(|&t| Canvas::text_width(&label(y_axis.value(t)), small)).max().unwrap_or(0);
        let legend_width = self.series.iter().map(|s| Canvas::text_width(&s.name, small)).max().unwrap_or(0) + 34;
        let (left, right) = ((tick_width + 16) as f64, (width as i64 - legend_width - 16) as f64);
        let (top, bottom) = (TextSize::Title.height() as f64 + normal.height() as f64 + 22.0, height as f64 - 2.0 * small.height() as f64 - 22.0);
        let px = |t: f64| left + (t - x_axis.lo) / (x_axis.hi - x_axis.lo) * (right - left);
        let py = |t: f64| bottom - (t - y_axis.lo) / (y_axis.hi - y_axis.lo) * (bottom - top);
        for &t in &y_axis.ticks {
            canvas.line((left, py(t)), (right, py(t)), GRID);
            let text = label(y_axis.value(t));
            canvas.text(left as i64 - 8 - Canvas::text_width(&text, small), py(t) as i64 - small.height() / 2, &text, small, INK);
        }
        for &t in &x_axis.ticks {
            canvas.line((px(t), top), (px(t), bottom), GRID);
            let text = label(x_axis.value(t));
            canvas.text(px(t) as i64 - Canvas::text_width(&text, small) / 2, bottom as i64 + 6, &text, small, INK);
        }
        canvas.line((left, bottom), (right, bottom), INK);
        canvas.line((left, top), (left, bottom), INK);
        canvas.text(8, 6, &self.title, TextSize::Title, INK);
        let y_name = format!("{}{}", self.y_label, if self.log_y { " (log scale)" } else { "" });
        canvas.text(8, top as i64 - normal.height() - 6, &y_name, normal, INK);
        let x_name = format!("{}{}", self.x_label, if self.log_x { " (log scale)" } else { "" });
        canvas.text(((left + right) / 2.0) as i64 - Canvas::text_width(&x_name, normal) / 2, height as i64 - normal.height() - 4, &x_name, normal, INK);
        for (k, mark) in self.marks.iter().enumerate() {
            let t = x_axis.of(mark.x);
            if !(x_axis.lo..=x_axis.hi).contains(&t) {
                continue;
            }
            canvas.dashed_vertical(px(t), top, bottom, MARK);
            // Staggered, so that marks close together keep their labels apart.
            let y = top as i64 + 4 + (k % 3) as i64 * (small.height() + 2);
            canvas.text(px(t) as i64 + 4, y, &mark.label, small, MARK);
        }
        for (i, s) in self.series.iter().enumerate() {
            let c = COLOURS[i % COLOURS.len()];
            let pts: Vec<(f64, f64)> = s.points.iter().filter(|&&p| self.drawable(p)).map(|&(x, y)| (px(x_axis.of(x)), py(y_axis.of(y)))).collect();
            if s.lines {
                for w in pts.windows(2) {
                    canvas.thick_line(w[0], w[1], c);
                }
            } else {
                for &(x, y) in &pts {
                    canvas.fill(x as i64 - 3, y as i64 - 3, x as i64 + 4, y as i64 + 4, c);
                }
            }
            let y = top as i64 + i as i64 * (small.height() + 6);
            canvas.fill(right as i64 + 16, y + 4, right as i64 + 40, y + small.height() - 4, c);
            canvas.text(right as i64 + 46, y, &s.name, small, INK);
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
        let small = TextSize::Small;
        let bar = small.height() + 2;
        let (gap, top) = (12i64, TextSize::Title.height() + 20);
        let left = self.labels.iter().map(|l| Canvas::text_width(l, small)).max().unwrap_or(0) + 20;
        let group = bar * self.series.len().max(1) as i64 + gap;
        let height = (top + group * self.labels.len() as i64 + 20 + (small.height() + 6) * self.series.len() as i64) as usize;
        let mut canvas = Canvas::new(width, height);
        canvas.text(10, 8, &self.title, TextSize::Title, INK);
        let max = self.series.iter().flat_map(|(_, v)| v.iter().copied()).filter(|v| v.is_finite()).fold(0.0f64, f64::max).max(1e-12);
        let span = (width as i64 - left - 130).max(10) as f64;
        for (i, label) in self.labels.iter().enumerate() {
            let y = top + group * i as i64;
            canvas.text(10, y, label, small, INK);
            for (k, (_, values)) in self.series.iter().enumerate() {
                let v = values.get(i).copied().unwrap_or(0.0);
                let y = y + bar * k as i64;
                let end = left + (v.max(0.0) / max * span).round() as i64;
                canvas.fill(left, y + 1, end.max(left + 1), y + bar - 1, COLOURS[(k + 1) % COLOURS.len()]);
                canvas.text(end + 6, y + 1, &format!("{} {}", label_value(v), self.unit), small, INK);
            }
        }
        let legend = top + group * self.labels.len() as i64 + 10;
        for (k, (name, _)) in self.series.iter().enumerate() {
            let y = legend + (small.height() + 6) * k as i64;
            canvas.fill(10, y + 3, 34, y + small.height() - 3, COLOURS[(k + 1) % COLOURS.len()]);
            canvas.text(40, y, name, small, INK);
        }
        canvas
    }
}

/// A bar's value: three significant digits.
fn label_value(v: f64) -> String {
    if v.abs() >= 100.0 {
        format!("{v:.0}")
    } else if v.abs() >= 10.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.2}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_linear_axis_starts_where_its_data_does_and_ticks_on_round_numbers() {
        let axis = Axis::new([0.0, 2900.0].into_iter(), false, 0.0);
        assert_eq!((axis.lo, axis.hi), (0.0, 2900.0));
        assert_eq!(axis.ticks, [0.0, 500.0, 1000.0, 1500.0, 2000.0, 2500.0]);
        let log = Axis::new([1e-4, 3.0].into_iter(), true, 0.0);
        assert!(log.ticks.iter().all(|t| t.fract() == 0.0) && log.ticks.len() >= 4, "{:?}", log.ticks);
        assert_eq!(label(0.25), "0.25");
        assert_eq!(label(2500.0), "2500");
        assert_eq!(label(1e-4), "1e-4");
        assert_eq!((label(0.1), label(0.001), label(2.5), label(0.0125)), ("0.1".into(), "0.001".into(), "2.5".into(), "0.013".into()));
    }

    #[test]
    fn text_is_drawn_in_the_font_and_series_get_distinct_colours() {
        let mut canvas = Canvas::new(120, 40);
        canvas.text(2, 2, "umbra 0.1", TextSize::Normal, INK);
        let inked = (0..40).flat_map(|y| (0..120).map(move |x| (x, y))).filter(|&(x, y)| canvas.pixel(x, y) != [255; 3]).count();
        // Anti-aliased glyphs: some pixels partly inked, and the text is not a block.
        let grey = (0..40).flat_map(|y| (0..120).map(move |x| (x, y))).filter(|&(x, y)| canvas.pixel(x, y)[0] > 0 && canvas.pixel(x, y)[0] < 255).count();
        assert!(inked > 60 && inked < 9 * 20 * 20 / 2 && grey > 10, "{inked} inked, {grey} grey");
        let distinct: std::collections::BTreeSet<[u8; 3]> = COLOURS.into_iter().collect();
        assert_eq!(distinct.len(), COLOURS.len());
    }

    #[test]
    fn a_chart_draws_its_marks_within_the_plot() {
        let chart = Chart {
            title: "t".into(),
            x_label: "iteration".into(),
            y_label: "loss".into(),
            log_x: false,
            log_y: true,
            series: vec![Series { name: "total".into(), points: (0..100).map(|i| (i as f64, 1.0 / (1.0 + i as f64))).collect(), lines: true }],
            marks: vec![Mark { x: 50.0, label: "light".into() }, Mark { x: 500.0, label: "beyond".into() }],
        };
        let canvas = chart.render(400, 300);
        let marked = (0..300).filter(|&y| (0..400).any(|x| canvas.pixel(x, y) == MARK)).count();
        assert!(marked > 50, "the mark's dashes and label: {marked} rows");
    }
}
