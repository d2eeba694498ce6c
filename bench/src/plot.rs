//! Charts for the performance reports: panels of points and lines, written as one PNG.
//!
//! Axes may be logarithmic (values are plotted as their base-10 logarithm and labelled
//! with the values themselves). The font is embedded, so a chart looks the same on every
//! machine.

use std::path::Path;

use anyhow::{anyhow, Context, Result};
use plotters::prelude::*;

/// The embedded font (DejaVu Sans, see `assets/fonts/DejaVu-LICENSE`).
static FONT: &[u8] = include_bytes!("../assets/fonts/DejaVuSans.ttf");

/// A named set of points, drawn as markers, optionally joined by a line.
pub struct Series {
    /// The legend's entry. An empty label gives no entry, and the series is drawn in
    /// the colour of the series before it (the second line of a pair of bounds).
    pub label: String,
    pub points: Vec<(f64, f64)>,
    pub joined: bool,
    /// Markers are drawn only when set; a line without markers is a reference curve.
    pub markers: bool,
}

/// One chart of a figure.
pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_x: bool,
    pub log_y: bool,
    pub series: Vec<Series>,
}

const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 23, 23),
];

/// Draws `panels` in a grid of `columns` and writes the figure to `path` as PNG.
pub fn write_png(
    path: &Path,
    panels: &[Panel],
    columns: usize,
    panel_size: (u32, u32),
) -> Result<()> {
    register_font();
    let columns = columns.clamp(1, panels.len().max(1));
    let rows = panels.len().div_ceil(columns).max(1);
    let (width, height) = (panel_size.0 * columns as u32, panel_size.1 * rows as u32);
    let mut rgb = vec![0u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_error)?;
        let areas = root.split_evenly((rows, columns));
        for (panel, area) in panels.iter().zip(areas.iter()) {
            draw_panel(panel, area)?;
        }
        root.present().map_err(draw_error)?;
    }
    let png = render::Image { width, height, rgb }.to_png();
    // Written as the tables beside it are: the benchmark's own results, which a failed
    // run simply writes again.
    std::fs::write(path, &png).with_context(|| format!("cannot write {}", path.display()))
}

fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // The font is part of the binary; it parses, or the charts are the least of it.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

fn draw_error<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing a chart: {e:?}")
}

/// Maps a value onto its axis (log10 on a log axis).
fn axis(v: f64, log: bool) -> f64 {
    if log {
        v.max(f64::MIN_POSITIVE).log10()
    } else {
        v
    }
}

/// The range covering every point, padded a little.
fn range(values: impl Iterator<Item = f64>) -> std::ops::Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return 0.0..1.0;
    }
    let pad = ((hi - lo) * 0.06).max(1e-3);
    (lo - pad)..(hi + pad)
}

/// A tick label: the value itself, undoing the log of a log axis.
fn tick(v: f64, log: bool) -> String {
    let v = if log { 10f64.powf(v) } else { v };
    if v == 0.0 {
        "0".into()
    } else if v.abs() >= 1000.0 || v.abs() < 0.01 {
        format!("{v:.0e}")
    } else if v.abs() >= 10.0 {
        format!("{v:.0}")
    } else if v.abs() >= 1.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.2}")
    }
}

fn draw_panel<DB: DrawingBackend>(
    panel: &Panel,
    area: &DrawingArea<DB, plotters::coord::Shift>,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let points = || panel.series.iter().flat_map(|s| s.points.iter());
    let x_range = range(points().map(|p| axis(p.0, panel.log_x)));
    let y_range = range(points().map(|p| axis(p.1, panel.log_y)));
    let mut chart = ChartBuilder::on(area)
        .caption(&panel.title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(x_range, y_range)
        .map_err(draw_error)?;
    let (log_x, log_y) = (panel.log_x, panel.log_y);
    chart
        .configure_mesh()
        .x_desc(panel.x_label.as_str())
        .y_desc(panel.y_label.as_str())
        .x_label_formatter(&|v| tick(*v, log_x))
        .y_label_formatter(&|v| tick(*v, log_y))
        .label_style(("sans-serif", 12))
        .axis_desc_style(("sans-serif", 14))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()
        .map_err(draw_error)?;
    let mut next_color = 0;
    let mut color = PALETTE[0];
    for series in &panel.series {
        let labelled = !series.label.is_empty();
        if labelled || next_color == 0 {
            color = PALETTE[next_color % PALETTE.len()];
            next_color += 1;
        }
        let mapped: Vec<(f64, f64)> = series
            .points
            .iter()
            .map(|&(x, y)| (axis(x, log_x), axis(y, log_y)))
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .collect();
        if series.joined {
            let width = if series.markers { 1 } else { 2 };
            let drawn = chart
                .draw_series(LineSeries::new(
                    mapped.iter().copied(),
                    color.stroke_width(width),
                ))
                .map_err(draw_error)?;
            if labelled {
                drawn.label(series.label.as_str()).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
                });
            }
        }
        if series.markers {
            let drawn = chart
                .draw_series(mapped.iter().map(|&p| Circle::new(p, 4, color.filled())))
                .map_err(draw_error)?;
            if !series.joined && labelled {
                drawn
                    .label(series.label.as_str())
                    .legend(move |(x, y)| Circle::new((x + 8, y), 4, color.filled()));
            }
        }
    }
    chart
        .configure_series_labels()
        .label_font(("sans-serif", 12))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(180, 180, 180))
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(draw_error)?;
    Ok(())
}
