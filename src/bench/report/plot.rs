//! One stage's rows drawn as an SVG with plotters: a panel per case (and error metric) with
//! run time against error on log-log axes (PSNR on a linear axis, higher is better), one
//! curve per scheme and backend in the same colour in every panel, all panels on the same
//! time axis; beneath them a strip, on that time axis too, for what has no error to draw:
//! rows without one (hollow circles) and the seeds' published figures (lettered triangles).
//! The node's latencies are drawn as distributions, all in one panel.
//!
//! What a reader (or a test) relies on: each panel starts with its caption, the case; a
//! series' curve is the only polyline of stroke width 2, in the colour of its legend square;
//! the numbers on the axes are the tick values, parseable as they stand.

use std::ops::Range;

use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters_svg::SVGBackend;

use super::rows::{labels, seed_points, series_of, Row, SeedPoint, Series, LATENCY_PANEL};

const PANEL_WIDTH: u32 = 560;
const PANEL_HEIGHT: u32 = 360;
const COLUMNS: u32 = 2;
const LEGEND_WIDTH: u32 = 480;
const TITLE_HEIGHT: u32 = 50;
const STRIP_HEIGHT: u32 = 120;
const Y_LABELS: u32 = 80;
const MARGIN: u32 = 12;
const CURVE_WIDTH: u32 = 2;
/// The caption over the strip.
pub const STRIP_CAPTION: &str =
    "no error to draw: rows without an error value or with exactly 0 (circles), the seeds' figures (triangles)";

type Area<'a> = DrawingArea<SVGBackend<'a>, Shift>;
type DrawResult = Result<(), Box<dyn std::error::Error>>;

/// What one stage's figure draws: its rows, their series, the series' distinct labels (label
/// i is colour i), the seeds, the shared time axis.
struct Figure<'r> {
    rows: &'r [&'r Row],
    series: Vec<Series>,
    labels: Vec<String>,
    seeds: Vec<SeedPoint>,
    times: Range<f64>,
}

impl<'r> Figure<'r> {
    fn new(stage: &str, rows: &'r [&'r Row]) -> Self {
        let series = series_of(rows);
        let labels = labels(&series).into_iter().map(str::to_owned).collect();
        let seeds = seed_points(stage);
        let times = time_range(rows, &seeds, stage == "node");
        Self { rows, series, labels, seeds, times }
    }

    fn colour(&self, s: &Series) -> RGBColor {
        palette(self.labels.iter().position(|l| *l == s.label).unwrap_or(0))
    }
}

fn palette(index: usize) -> RGBColor {
    let c = Palette99::pick(index).to_rgba();
    RGBColor(c.0, c.1, c.2)
}

/// A series as the report draws it, for other sinks (the rerun log).
#[derive(Debug, Clone, PartialEq)]
pub struct DrawnSeries {
    pub panel: String,
    pub label: String,
    pub rgb: [u8; 3],
    /// (median ms, error) of the rows drawn on the curve, in the curve's order.
    pub points: Vec<(f64, f64)>,
    /// The errors are decibels (PSNR, drawn on a linear axis), not ratios.
    pub decibels: bool,
    /// Median ms of the rows with no error to draw (the strip).
    pub timed_only: Vec<f64>,
}

/// The series of one stage's rows, with their colours and points as the SVG draws them.
pub fn drawn_series(stage: &str, rows: &[&Row]) -> Vec<DrawnSeries> {
    let figure = Figure::new(stage, rows);
    figure
        .series
        .iter()
        .map(|s| {
            let c = figure.colour(s);
            let of_series = s.rows.iter().map(|&i| figure.rows[i]);
            DrawnSeries {
                panel: s.panel.clone(),
                label: s.label.clone(),
                rgb: [c.0, c.1, c.2],
                points: curve_points(&figure, s, None),
                decibels: of_series.clone().filter_map(plotted_error).any(|(m, _)| is_decibels(m)),
                timed_only: of_series.filter(|r| plotted_error(r).is_none()).map(|r| r.time_ms.median).collect(),
            }
        })
        .collect()
}

/// The (median ms, error) points of a series' curve (of one metric, or of all), from the
/// coarsest to the finest: the sweep's order, whatever the timing noise.
fn curve_points(figure: &Figure, s: &Series, metric: Option<&str>) -> Vec<(f64, f64)> {
    let mut points: Vec<(f64, f64, bool)> = s
        .rows
        .iter()
        .filter_map(|&i| {
            let r = figure.rows[i];
            let (m, v) = plotted_error(r).filter(|(m, _)| metric.is_none_or(|want| want == *m))?;
            Some((r.time_ms.median, v, is_decibels(m)))
        })
        .collect();
    points.sort_by(|a, b| if a.2 { a.1.total_cmp(&b.1) } else { b.1.total_cmp(&a.1) });
    points.into_iter().map(|(t, v, _)| (t, v)).collect()
}

/// The SVG of one stage's rows (all of `stage`), titled with the machines they ran on.
pub fn stage_svg(stage: &str, rows: &[&Row]) -> Result<String, Box<dyn std::error::Error>> {
    let figure = Figure::new(stage, rows);
    let panels = if stage == "node" { vec![(LATENCY_PANEL.to_owned(), String::new())] } else { panels(&figure) };
    let grid_rows = (panels.len() as u32).div_ceil(COLUMNS).max(1);
    let strip = if stage == "node" { 0 } else { STRIP_HEIGHT };
    let size = (COLUMNS * PANEL_WIDTH + LEGEND_WIDTH, TITLE_HEIGHT + grid_rows * PANEL_HEIGHT + strip);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE)?;
        let root = root.titled(&title(stage, rows), ("sans-serif", 20))?;
        let (charts, legend) = root.split_horizontally(COLUMNS * PANEL_WIDTH);
        let (grid, strip_area) = charts.split_vertically(grid_rows * PANEL_HEIGHT);
        let cells = grid.split_evenly((grid_rows as usize, COLUMNS as usize));
        for ((case, metric), cell) in panels.iter().zip(&cells) {
            match stage {
                "node" => draw_latency_cdf(cell, &figure)?,
                _ => draw_error_panel(cell, &figure, case, metric)?,
            }
        }
        if stage != "node" {
            draw_strip(&strip_area, &figure)?;
        }
        draw_legend(&legend, &figure)?;
        root.present()?;
    }
    Ok(svg)
}

fn title(stage: &str, rows: &[&Row]) -> String {
    let mut devices: Vec<&str> = rows.iter().map(|r| r.device.as_str()).collect();
    devices.sort_unstable();
    devices.dedup();
    let what = if stage == "node" { "latency distribution" } else { "run time against error" };
    match devices.as_slice() {
        [one] => format!("{stage}: {what} — {one}"),
        _ => format!("{stage}: {what} — {} machines", devices.len()),
    }
}

/// (case, metric) of every panel: each case's metrics with a point to draw, in row order.
fn panels(figure: &Figure) -> Vec<(String, String)> {
    let mut panels: Vec<(String, String)> = Vec::new();
    for row in figure.rows {
        if let Some((metric, _)) = plotted_error(row) {
            let panel = (row.case.clone(), metric.to_owned());
            if !panels.contains(&panel) {
                panels.push(panel);
            }
        }
    }
    panels
}

/// Decibel metrics (PSNR) are already logarithmic and grow with accuracy: a linear axis.
fn is_decibels(metric: &str) -> bool {
    metric.ends_with("_db")
}

/// Where a row is drawn in its metric's panel: a positive value, or any value in decibels.
fn plotted_error(row: &Row) -> Option<(&str, f64)> {
    let e = row.error.as_ref()?;
    (is_decibels(&e.metric) || e.value > 0.0).then_some((e.metric.as_str(), e.value))
}

/// The time axis: every row's median (the node: its min to max) and every seed, padded.
fn time_range(rows: &[&Row], seeds: &[SeedPoint], whole: bool) -> Range<f64> {
    let mut values: Vec<f64> = seeds.iter().map(|s| s.time_ms).collect();
    for r in rows {
        if whole {
            values.extend([r.time_ms.min, r.time_ms.max]);
        } else {
            values.push(r.time_ms.median);
        }
    }
    padded_log_range(&values)
}

/// The values' range widened by 2x each way, and to two decades at least, so that every
/// log axis has two labelled powers of ten.
fn padded_log_range(values: &[f64]) -> Range<f64> {
    let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !lo.is_finite() || !hi.is_finite() {
        return 0.1..10.0;
    }
    let (lo, hi) = (lo / 2.0, hi * 2.0);
    let widen = (100.0 / (hi / lo)).max(1.0).sqrt();
    lo / widen..hi * widen
}

fn seed_letters() -> impl Iterator<Item = String> {
    ('A'..='Z').map(String::from)
}

/// A tick value as text that parses back to it: plain where short, else in e-notation.
pub fn tick_text(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 {
        return "0".to_owned();
    }
    if !(1e-3..1e5).contains(&a) {
        return format!("{v:.0e}");
    }
    let decimals = (3 - a.log10().floor() as i32).max(0) as usize;
    let text = format!("{v:.decimals$}");
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_owned()
    } else {
        text
    }
}

/// One case's curves for one metric, on the range of that metric over all cases (panels
/// of one metric compare at a glance).
fn draw_error_panel(area: &Area, figure: &Figure, case: &str, metric: &str) -> DrawResult {
    let values: Vec<f64> =
        figure.rows.iter().filter_map(|r| plotted_error(r)).filter(|(m, _)| *m == metric).map(|(_, v)| v).collect();
    let reference = figure.rows.iter().filter_map(|r| r.error.as_ref()).find(|e| e.metric == metric);
    let y_desc = reference.map_or(metric.to_owned(), |e| format!("{metric} (against {})", e.reference));
    let panel = Panel { case, metric, y_desc: &y_desc };
    if is_decibels(metric) {
        let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        curves(area, figure, &panel, lo - 3.0..hi + 3.0)
    } else {
        curves(area, figure, &panel, padded_log_range(&values).log_scale())
    }
}

struct Panel<'a> {
    case: &'a str,
    metric: &'a str,
    y_desc: &'a str,
}

/// A polyline through each series' points of the panel, a dot at each point.
fn curves<Y>(area: &Area, figure: &Figure, panel: &Panel, y: Y) -> DrawResult
where
    Y: AsRangedCoord<Value = f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let mut chart = ChartBuilder::on(area)
        .margin(MARGIN)
        .caption(panel.case, ("sans-serif", 15))
        .x_label_area_size(40)
        .y_label_area_size(Y_LABELS)
        .build_cartesian_2d(figure.times.clone().log_scale(), y)?;
    chart
        .configure_mesh()
        .x_desc("time per step or frame, ms (median)")
        .y_desc(panel.y_desc)
        .x_label_formatter(&|v| tick_text(*v))
        .y_label_formatter(&|v| tick_text(*v))
        .light_line_style(WHITE)
        .draw()?;
    for s in figure.series.iter().filter(|s| s.panel == panel.case) {
        let points = curve_points(figure, s, Some(panel.metric));
        if points.is_empty() {
            continue;
        }
        let colour = figure.colour(s);
        chart.draw_series(std::iter::once(PathElement::new(points.clone(), colour.stroke_width(CURVE_WIDTH))))?;
        chart.draw_series(points.iter().map(|p| Circle::new(*p, 3, colour.filled())))?;
    }
    Ok(())
}

/// The node's latencies as distributions: for each row, the fraction of steps answered
/// within a time, through the quantiles it reports.
fn draw_latency_cdf(area: &Area, figure: &Figure) -> DrawResult {
    let mut chart = ChartBuilder::on(area)
        .margin(MARGIN)
        .caption(LATENCY_PANEL, ("sans-serif", 15))
        .x_label_area_size(40)
        .y_label_area_size(Y_LABELS)
        .build_cartesian_2d(figure.times.clone().log_scale(), 0.0..1.05)?;
    chart
        .configure_mesh()
        .x_desc("latency, ms")
        .y_desc("fraction answered within")
        .x_label_formatter(&|v| tick_text(*v))
        .y_label_formatter(&|v| tick_text(*v))
        .light_line_style(WHITE)
        .draw()?;
    for s in &figure.series {
        let colour = figure.colour(s);
        for &i in &s.rows {
            let points = latency_quantiles(figure.rows[i]);
            chart.draw_series(std::iter::once(PathElement::new(points.clone(), colour.stroke_width(CURVE_WIDTH))))?;
            chart.draw_series(points.iter().map(|p| Circle::new(*p, 3, colour.filled())))?;
        }
    }
    Ok(())
}

/// (latency, fraction at or below) of a node row: its `quantiles_ms` where it has them,
/// else its min, median, p99 (where it has one) and max.
pub fn latency_quantiles(row: &Row) -> Vec<(f64, f64)> {
    let listed: Vec<(f64, f64)> = row
        .params
        .get("quantiles_ms")
        .and_then(|q| q.as_array())
        .into_iter()
        .flatten()
        .filter_map(|pair| Some((pair.get(1)?.as_f64()?, pair.get(0)?.as_f64()?)))
        .collect();
    if !listed.is_empty() {
        return listed;
    }
    let t = &row.time_ms;
    let mut points = vec![(t.min, 0.0), (t.median, 0.5)];
    if let Some(p99) = row.params.get("p99_ms").and_then(|v| v.as_f64()) {
        points.push((p99, 0.99));
    }
    points.push((t.max, 1.0));
    points
}

/// What has no error to draw, on the shared time axis: rows without an error value (or
/// exactly 0 on a log axis) as hollow circles in their series' colour, seeds as triangles.
fn draw_strip(area: &Area, figure: &Figure) -> DrawResult {
    let mut chart = ChartBuilder::on(area)
        .margin(MARGIN)
        .caption(STRIP_CAPTION, ("sans-serif", 13))
        .x_label_area_size(30)
        .y_label_area_size(Y_LABELS)
        .build_cartesian_2d(figure.times.clone().log_scale(), 0.0..3.0)?;
    chart.configure_mesh().disable_mesh().disable_y_axis().x_label_formatter(&|v| tick_text(*v)).x_desc("ms").draw()?;
    for s in &figure.series {
        let missing = s.rows.iter().map(|&i| figure.rows[i]).filter(|r| plotted_error(r).is_none());
        let colour = figure.colour(s);
        chart.draw_series(missing.map(|r| Circle::new((r.time_ms.median, 2.0), 4, colour.stroke_width(2))))?;
    }
    let seeds = &figure.seeds;
    chart.draw_series(seeds.iter().map(|s| TriangleMarker::new((s.time_ms, 1.0), 6, BLACK.filled())))?;
    // Lettered as in the legend (letters, not numbers: the axes' numbers are all ticks).
    let letter = ("sans-serif", 11).into_font();
    chart.draw_series(seeds.iter().zip(seed_letters()).map(|(s, l)| Text::new(l, (s.time_ms, 1.9), letter.clone())))?;
    Ok(())
}

fn draw_legend(area: &Area, figure: &Figure) -> DrawResult {
    let text = ("sans-serif", 12).into_font();
    let mut y = 20;
    for (index, label) in figure.labels.iter().enumerate() {
        area.draw(&Rectangle::new([(4, y - 5), (14, y + 5)], palette(index).filled()))?;
        area.draw(&Text::new(label.clone(), (20, y - 6), text.clone()))?;
        y += 18;
    }
    for (seed, letter) in figure.seeds.iter().zip(seed_letters()) {
        area.draw(&TriangleMarker::new((9, y), 5, BLACK.filled()))?;
        let label = format!("{letter} {}: {} ms", seed.label, tick_text(seed.time_ms));
        area.draw(&Text::new(label, (20, y - 6), text.clone()))?;
        y += 18;
    }
    Ok(())
}
