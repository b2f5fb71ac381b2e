//! Speed-against-accuracy charts (`isowalld bench accuracy`): one log-log panel per scene, one
//! curve per method, the Pareto front of each panel as a dashed black line; written as PNG and SVG.
//!
//! Text is drawn with an embedded font (a Basic Latin subset of DejaVu Sans, see
//! `daemon/assets/`), so charts render the same everywhere, with no system fonts or fontconfig.

use anyhow::{anyhow, Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;

/// DejaVu Sans, Basic Latin and a few symbols (licence: daemon/assets/DejaVuSans-LICENSE.txt).
const FONT: &[u8] = include_bytes!("../../assets/DejaVuSans-subset.ttf");
pub(crate) const FAMILY: &str = "sans-serif";

/// How a series' points are marked.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Marker {
    Circle,
    Square,
    Triangle,
}

/// One curve: its points (x, y), joined in the order given (e.g. of sample count).
#[derive(Clone, Debug)]
pub struct Series {
    pub label: String,
    /// Short notes drawn beside points (e.g. the sample count), parallel to `points`; empty for none.
    pub notes: Vec<String>,
    pub color: (u8, u8, u8),
    pub marker: Marker,
    pub points: Vec<(f64, f64)>,
}

/// One panel (one scene).
#[derive(Clone, Debug)]
pub struct Panel {
    pub title: String,
    pub series: Vec<Series>,
}

/// A grid of panels sharing axis descriptions and a legend.
#[derive(Clone, Debug)]
pub struct Chart {
    pub title: String,
    pub subtitle: String,
    pub x_desc: String,
    pub y_desc: String,
    pub panels: Vec<Panel>,
}

/// The non-dominated points of `points` when both coordinates are to be minimised: no other point
/// is at most as large in both and smaller in one. Sorted by x (so y falls along the front); equal
/// points appear once; points with a non-finite coordinate are ignored.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut p: Vec<(f64, f64)> =
        points.iter().copied().filter(|(x, y)| x.is_finite() && y.is_finite()).collect();
    p.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let mut front: Vec<(f64, f64)> = Vec::new();
    for q in p {
        // Sorted by x then y: q is dominated iff some earlier point has y <= q.y, i.e. iff the
        // front's last (lowest so far) y is <= q.y.
        if front.last().is_none_or(|l| q.1 < l.1) {
            front.push(q);
        }
    }
    front
}

/// Writes `chart` as a PNG of `size` pixels.
pub fn write_png(chart: &Chart, path: &Path, size: (u32, u32)) -> Result<()> {
    let (w, h) = size;
    let mut buf = vec![255u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        draw(&root, chart)?;
        root.present().map_err(|e| anyhow!("{e}"))?;
    }
    let img = image::RgbImage::from_raw(w, h, buf).expect("buffer is w*h*3");
    img.save_with_format(path, image::ImageFormat::Png)
        .with_context(|| format!("cannot write {}", path.display()))
}

/// Writes `chart` as an SVG of `size` (pixels, as its view box).
pub fn write_svg(chart: &Chart, path: &Path, size: (u32, u32)) -> Result<()> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        draw(&root, chart)?;
        root.present().map_err(|e| anyhow!("{e}"))?;
    }
    std::fs::write(path, svg).with_context(|| format!("cannot write {}", path.display()))
}

/// Columns and rows of the panel grid.
pub fn grid(panels: usize) -> (usize, usize) {
    let cols = panels.clamp(1, 3);
    (cols, panels.max(1).div_ceil(cols))
}

/// A size that gives each panel about 440x360 pixels.
pub fn default_size(chart: &Chart) -> (u32, u32) {
    let (cols, rows) = grid(chart.panels.len());
    let legend_rows = (legend_entries(chart).len() + 1).div_ceil(legend_columns(cols * 440)) as u32;
    (cols as u32 * 440, rows as u32 * 360 + TITLE_H + legend_rows * LEGEND_ROW_H + 12)
}

const TITLE_H: u32 = 74;
const LEGEND_ROW_H: u32 = 22;

fn legend_columns(width: usize) -> usize {
    (width / 200).max(1)
}

/// Every distinct label over all panels, in order of first appearance, plus the Pareto front.
fn legend_entries(chart: &Chart) -> Vec<(String, (u8, u8, u8), Marker)> {
    let mut out: Vec<(String, (u8, u8, u8), Marker)> = Vec::new();
    for s in chart.panels.iter().flat_map(|p| &p.series) {
        if !out.iter().any(|(l, _, _)| *l == s.label) {
            out.push((s.label.clone(), s.color, s.marker));
        }
    }
    out
}

fn rgb(c: (u8, u8, u8)) -> RGBColor {
    RGBColor(c.0, c.1, c.2)
}

pub(crate) fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        if plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).is_err() {
            tracing::warn!("the embedded chart font does not load: text will be missing");
        }
    });
}

/// A tick label with at most 3 significant digits and no trailing zeros.
fn tick(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let digits = (2 - v.abs().log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// Tick values for a log axis over [lo, hi]: 1-2-5 per decade (every mantissa 1-9 where that gives
/// fewer than 3 ticks), and light grid lines at every mantissa 1-9.
fn log_ticks(lo: f64, hi: f64) -> (Vec<f64>, Vec<f64>) {
    let pick = |mantissas: &[f64]| -> Vec<f64> {
        let mut out = Vec::new();
        let mut decade = 10f64.powf(lo.log10().floor());
        while decade <= hi {
            for m in mantissas {
                let v = m * decade;
                // Round away the float noise of m * 10^k (e.g. 0.30000000000000004).
                let v = format!("{v:.12e}").parse::<f64>().unwrap_or(v);
                if v >= lo && v <= hi {
                    out.push(v);
                }
            }
            decade *= 10.0;
        }
        out
    };
    let all = pick(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]);
    let mut bold = pick(&[1.0, 2.0, 5.0]);
    if bold.len() < 3 {
        bold = all.clone();
    }
    if bold.len() > 12 {
        bold = pick(&[1.0]);
    }
    (bold, all)
}

/// Log-scale range around `values` (positive ones only), with a margin.
fn log_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
    if !lo.is_finite() {
        return (0.1, 10.0);
    }
    let (lo, hi) = if hi / lo < 1.5 { (lo / 1.5, hi * 1.5) } else { (lo, hi) };
    (lo / 1.25, hi * 1.25)
}

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, chart: &Chart) -> Result<()>
where
    DB::ErrorType: 'static,
{
    register_font();
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| anyhow!("drawing the chart: {e}");
    root.fill(&WHITE).map_err(e)?;
    let (width, height) = root.dim_in_pixel();
    let (cols, rows) = grid(chart.panels.len());
    let entries = legend_entries(chart);
    let lcols = legend_columns(width as usize);
    let legend_h = (entries.len() + 1).div_ceil(lcols) as u32 * LEGEND_ROW_H + 12;
    let (top, rest) = root.split_vertically(TITLE_H);
    let (body, legend) = rest.split_vertically(height.saturating_sub(TITLE_H + legend_h));

    top.draw(&Text::new(chart.title.as_str(), (12, 8), (FAMILY, 20).into_font().color(&BLACK))).map_err(e)?;
    for (i, line) in chart.subtitle.lines().enumerate() {
        let style = (FAMILY, 13).into_font().color(&RGBColor(70, 70, 70));
        top.draw(&Text::new(line, (12, 34 + 17 * i as i32), style)).map_err(e)?;
    }

    let cells = body.split_evenly((rows, cols));
    for (panel, area) in chart.panels.iter().zip(&cells) {
        let xs = panel.series.iter().flat_map(|s| s.points.iter().map(|p| p.0));
        let ys = panel.series.iter().flat_map(|s| s.points.iter().map(|p| p.1));
        let (x0, x1) = log_range(xs);
        let (y0, y1) = log_range(ys);
        let (xt, yt) = (log_ticks(x0, x1), log_ticks(y0, y1));
        let mut cc = ChartBuilder::on(area)
            .caption(panel.title.as_str(), (FAMILY, 15))
            .margin(10)
            .x_label_area_size(38)
            .y_label_area_size(56)
            .build_cartesian_2d(
                (x0..x1).log_scale().with_key_points(xt.0).with_light_points(xt.1),
                (y0..y1).log_scale().with_key_points(yt.0).with_light_points(yt.1),
            )
            .map_err(e)?;
        cc.configure_mesh()
            .x_desc(chart.x_desc.as_str())
            .y_desc(chart.y_desc.as_str())
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .label_style((FAMILY, 11))
            .axis_desc_style((FAMILY, 12))
            .light_line_style(RGBColor(238, 238, 238))
            .bold_line_style(RGBColor(215, 215, 215))
            .draw()
            .map_err(e)?;
        let all: Vec<(f64, f64)> = panel
            .series
            .iter()
            .flat_map(|s| s.points.iter().copied())
            .filter(|&(x, y)| x > 0.0 && y > 0.0)
            .collect();
        let front = pareto_front(&all);
        if front.len() > 1 {
            cc.draw_series(DashedLineSeries::new(front.iter().copied(), 7, 5, BLACK.stroke_width(2)))
                .map_err(e)?;
        }
        for s in &panel.series {
            let pts: Vec<(f64, f64)> =
                s.points.iter().copied().filter(|&(x, y)| x > 0.0 && y > 0.0 && x.is_finite()).collect();
            let c = rgb(s.color);
            let note_style = (FAMILY, 10).into_font().color(&c);
            for (p, note) in s.points.iter().zip(&s.notes).filter(|(_, n)| !n.is_empty()) {
                if p.0 > 0.0 && p.1 > 0.0 {
                    cc.draw_series(std::iter::once(
                        EmptyElement::at(*p) + Text::new(note.clone(), (5, -13), note_style.clone()),
                    ))
                    .map_err(e)?;
                }
            }
            cc.draw_series(LineSeries::new(pts.iter().copied(), c.stroke_width(2))).map_err(e)?;
            let style = c.filled();
            match s.marker {
                Marker::Circle => cc.draw_series(pts.iter().map(|&p| Circle::new(p, 3, style))),
                Marker::Triangle => cc.draw_series(pts.iter().map(|&p| TriangleMarker::new(p, 4, style))),
                Marker::Square => cc.draw_series(
                    pts.iter().map(|&p| EmptyElement::at(p) + Rectangle::new([(-3, -3), (3, 3)], style)),
                ),
            }
            .map_err(e)?;
        }
        // Ring the front's points so they can be told from the curves through them.
        cc.draw_series(front.iter().map(|&p| Circle::new(p, 6, BLACK.stroke_width(1)))).map_err(e)?;
    }

    // Shared legend below the grid.
    let col_w = width as i32 / lcols as i32;
    let mut all = entries.clone();
    all.push(("Pareto front (all methods)".into(), (0, 0, 0), Marker::Circle));
    for (i, (label, color, marker)) in all.iter().enumerate() {
        let (r, c) = (i / lcols, i % lcols);
        let x = 16 + c as i32 * col_w;
        let y = 6 + r as i32 * LEGEND_ROW_H as i32 + LEGEND_ROW_H as i32 / 2;
        let col = rgb(*color);
        if i + 1 == all.len() {
            legend
                .draw(&PathElement::new(vec![(x, y), (x + 9, y)], BLACK.stroke_width(2)))
                .and_then(|_| {
                    legend.draw(&PathElement::new(vec![(x + 14, y), (x + 24, y)], BLACK.stroke_width(2)))
                })
                .and_then(|_| legend.draw(&Circle::new((x + 12, y), 6, BLACK.stroke_width(1))))
                .map_err(e)?;
        } else {
            legend.draw(&PathElement::new(vec![(x, y), (x + 24, y)], col.stroke_width(2))).map_err(e)?;
            let style = col.filled();
            match marker {
                Marker::Circle => legend.draw(&Circle::new((x + 12, y), 3, style)),
                Marker::Square => legend.draw(&Rectangle::new([(x + 9, y - 3), (x + 15, y + 3)], style)),
                Marker::Triangle => legend.draw(&TriangleMarker::new((x + 12, y), 4, style)),
            }
            .map_err(e)?;
        }
        legend
            .draw(&Text::new(label.as_str(), (x + 32, y - 7), (FAMILY, 13).into_font().color(&BLACK)))
            .map_err(e)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_front_of_a_hand_made_set() {
        let pts = [
            (10.0, 0.5),  // front (fastest)
            (20.0, 0.6),  // dominated by (10, 0.5)
            (20.0, 0.2),  // front
            (20.0, 0.2),  // duplicate: once
            (30.0, 0.2),  // dominated: as good, slower
            (40.0, 0.1),  // front
            (50.0, 0.15), // dominated by (40, 0.1)
            (80.0, 0.01), // front
            (f64::NAN, 0.001),
            (5.0, f64::INFINITY),
        ];
        assert_eq!(pareto_front(&pts), vec![(10.0, 0.5), (20.0, 0.2), (40.0, 0.1), (80.0, 0.01)]);
        // Order of the input does not matter.
        let mut rev = pts.to_vec();
        rev.reverse();
        assert_eq!(pareto_front(&rev), pareto_front(&pts));
        assert!(pareto_front(&[]).is_empty());
        assert_eq!(pareto_front(&[(1.0, 1.0)]), vec![(1.0, 1.0)]);
        // Equal times: only the lower error survives.
        assert_eq!(pareto_front(&[(1.0, 2.0), (1.0, 1.0)]), vec![(1.0, 1.0)]);
    }

    #[test]
    fn tick_labels_are_short() {
        assert_eq!(tick(100.0), "100");
        assert_eq!(tick(20.0), "20");
        assert_eq!(tick(0.05), "0.05");
        assert_eq!(tick(0.001), "0.001");
        assert_eq!(tick(1500.0), "1500");
        assert_eq!(tick(2.5), "2.5");
    }

    #[test]
    fn log_ticks_cover_narrow_and_wide_ranges() {
        let (bold, light) = log_ticks(0.08, 0.3);
        assert_eq!(bold, vec![0.08, 0.09, 0.1, 0.2, 0.3]);
        assert_eq!(light, bold);
        let (bold, light) = log_ticks(3.0, 700.0);
        assert_eq!(bold, vec![5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0]);
        assert_eq!(light.len(), 7 + 9 + 7);
    }

    #[test]
    fn writes_png_and_svg_for_a_tiny_chart() {
        let series = |label: &str, color, marker, k: f64| Series {
            label: label.into(),
            notes: vec!["4".into(), String::new(), "16".into()],
            color,
            marker,
            points: vec![(10.0 * k, 0.2 / k), (20.0 * k, 0.1 / k), (40.0 * k, 0.06 / k)],
        };
        let chart = Chart {
            title: "test chart".into(),
            subtitle: "synthetic".into(),
            x_desc: "ms".into(),
            y_desc: "RMSE".into(),
            panels: vec![
                Panel {
                    title: "one".into(),
                    series: vec![
                        series("a", (200, 30, 30), Marker::Triangle, 1.0),
                        series("b", (30, 30, 200), Marker::Circle, 2.0),
                    ],
                },
                Panel { title: "two".into(), series: vec![series("c", (30, 150, 30), Marker::Square, 1.5)] },
            ],
        };
        let dir = tempfile::tempdir().unwrap();
        let (png, svg) = (dir.path().join("c.png"), dir.path().join("c.svg"));
        let size = default_size(&chart);
        write_png(&chart, &png, size).unwrap();
        write_svg(&chart, &svg, size).unwrap();
        let img = image::open(&png).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), size);
        // Not blank: some dark pixels (text, axes) and some coloured ones (curves).
        assert!(img.pixels().filter(|p| p.0.iter().all(|&c| c < 80)).count() > 500);
        assert!(img.pixels().any(|p| p.0 == [200, 30, 30]));
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.starts_with("<svg") && text.len() > 2000);
        assert!(text.contains("test chart") && text.contains("Pareto front"));
    }
}
