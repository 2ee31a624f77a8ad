//! One stage's rows drawn as an SVG with plotters: run time against error on log-log axes
//! (a panel per error metric; PSNR on a linear axis, higher is better), one curve per
//! series, and beneath them a strip on the same time axis for what has no error to draw:
//! rows without one (hollow circles) and the seeds' published figures (triangles). The
//! node's latencies are drawn as distributions instead.
//!
//! Conventions a reader (or a test) relies on: a series' curve is the only polyline of
//! stroke width 2, in the colour of its legend square; the numbers on the axes are the
//! tick values, parseable as they stand.

use std::ops::Range;

use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters_svg::SVGBackend;

use super::rows::{seed_points, series_of, Row, SeedPoint, Series};

const WIDTH: u32 = 1200;
const LEGEND_WIDTH: u32 = 480;
const TITLE_HEIGHT: u32 = 50;
const PANEL_HEIGHT: u32 = 400;
const STRIP_HEIGHT: u32 = 110;
/// Room for the y labels, the same in every panel and the strip: they share the time axis.
const Y_LABELS: u32 = 80;
const MARGIN: u32 = 12;
const CURVE_WIDTH: u32 = 2;

type Area<'a> = DrawingArea<SVGBackend<'a>, Shift>;
type DrawResult = Result<(), Box<dyn std::error::Error>>;

/// The SVG of one stage's rows (all of `stage`), titled with the machines they ran on.
pub fn stage_svg(stage: &str, rows: &[&Row]) -> Result<String, Box<dyn std::error::Error>> {
    let series = series_of(rows);
    let seeds = seed_points(stage);
    let metrics = metrics(rows);
    let panels = if stage == "node" { 1 } else { metrics.len() };
    let strip_height = if stage == "node" { 0 } else { STRIP_HEIGHT };
    let height = TITLE_HEIGHT + panels as u32 * PANEL_HEIGHT + strip_height;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (WIDTH, height)).into_drawing_area();
        root.fill(&WHITE)?;
        let root = root.titled(&title(stage, rows), ("sans-serif", 20))?;
        let (charts, legend) = root.split_horizontally(WIDTH - LEGEND_WIDTH);
        let times = time_range(rows, &seeds, stage == "node");
        let (panel_areas, strip) = charts.split_vertically(panels as u32 * PANEL_HEIGHT);
        let areas = panel_areas.split_evenly((panels.max(1), 1));
        if stage == "node" {
            draw_latency_cdf(&areas[0], times.clone(), rows, &series)?;
        } else {
            for (area, metric) in areas.iter().zip(&metrics) {
                draw_error_panel(area, times.clone(), rows, &series, metric)?;
            }
        }
        if stage != "node" {
            draw_strip(&strip, times, rows, &series, &seeds)?;
        }
        draw_legend(&legend, &series, &seeds)?;
        root.present()?;
    }
    Ok(svg)
}

fn title(stage: &str, rows: &[&Row]) -> String {
    let mut devices: Vec<&str> = rows.iter().map(|r| r.device.as_str()).collect();
    devices.dedup();
    let what = if stage == "node" { "latency distribution" } else { "run time against error" };
    match devices.as_slice() {
        [one] => format!("{stage}: {what} — {one}"),
        _ => format!("{stage}: {what} — {} machines", devices.len()),
    }
}

/// Error metrics of the rows, in order of first appearance.
fn metrics(rows: &[&Row]) -> Vec<String> {
    let mut seen: Vec<String> = Vec::new();
    for e in rows.iter().filter_map(|r| r.error.as_ref()) {
        if !seen.contains(&e.metric) {
            seen.push(e.metric.clone());
        }
    }
    if seen.is_empty() {
        seen.push("error".to_owned());
    }
    seen
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

fn colour(index: usize) -> RGBColor {
    let c = Palette99::pick(index).to_rgba();
    RGBColor(c.0, c.1, c.2)
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

fn draw_error_panel(area: &Area, times: Range<f64>, rows: &[&Row], series: &[Series], metric: &str) -> DrawResult {
    let values: Vec<f64> =
        rows.iter().filter_map(|r| plotted_error(r)).filter(|(m, _)| *m == metric).map(|(_, v)| v).collect();
    let reference =
        rows.iter().filter_map(|r| r.error.as_ref()).find(|e| e.metric == metric).map(|e| e.reference.clone());
    let label = match reference {
        Some(reference) => format!("{metric} (against {reference})"),
        None => metric.to_owned(),
    };
    if is_decibels(metric) {
        let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let range = if lo.is_finite() { lo - 3.0..hi + 3.0 } else { 0.0..60.0 };
        curves(area, times, range, &label, rows, series, metric)
    } else {
        curves(area, times, padded_log_range(&values).log_scale(), &label, rows, series, metric)
    }
}

/// The curves of one metric's panel: a polyline through each series' points in time order,
/// a filled circle at each point.
fn curves<Y>(
    area: &Area,
    times: Range<f64>,
    y: Y,
    y_desc: &str,
    rows: &[&Row],
    series: &[Series],
    metric: &str,
) -> DrawResult
where
    Y: AsRangedCoord<Value = f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let mut chart = ChartBuilder::on(area)
        .margin(MARGIN)
        .x_label_area_size(40)
        .y_label_area_size(Y_LABELS)
        .build_cartesian_2d(times.log_scale(), y)?;
    chart
        .configure_mesh()
        .x_desc("time per step or frame, ms (median)")
        .y_desc(y_desc)
        .x_label_formatter(&|v| tick_text(*v))
        .y_label_formatter(&|v| tick_text(*v))
        .light_line_style(WHITE)
        .draw()?;
    for (index, s) in series.iter().enumerate() {
        let mut points: Vec<(f64, f64)> = s
            .rows
            .iter()
            .filter_map(|&i| {
                plotted_error(rows[i]).filter(|(m, _)| *m == metric).map(|(_, v)| (rows[i].time_ms.median, v))
            })
            .collect();
        if points.is_empty() {
            continue;
        }
        points.sort_by(|a, b| a.0.total_cmp(&b.0));
        let style = colour(index).stroke_width(CURVE_WIDTH);
        chart.draw_series(std::iter::once(PathElement::new(points.clone(), style)))?;
        chart.draw_series(points.iter().map(|p| Circle::new(*p, 3, colour(index).filled())))?;
    }
    Ok(())
}

/// The node's latencies as distributions: for each row, the fraction of steps answered
/// within a time, through the quantiles it reports (min, median, p99, max).
fn draw_latency_cdf(area: &Area, times: Range<f64>, rows: &[&Row], series: &[Series]) -> DrawResult {
    let mut chart = ChartBuilder::on(area)
        .margin(MARGIN)
        .x_label_area_size(40)
        .y_label_area_size(Y_LABELS)
        .build_cartesian_2d(times.log_scale(), 0.0..1.05)?;
    chart
        .configure_mesh()
        .x_desc("latency, ms")
        .y_desc("fraction answered within")
        .x_label_formatter(&|v| tick_text(*v))
        .y_label_formatter(&|v| tick_text(*v))
        .light_line_style(WHITE)
        .draw()?;
    for (index, s) in series.iter().enumerate() {
        for &i in &s.rows {
            let points = latency_quantiles(rows[i]);
            chart.draw_series(std::iter::once(PathElement::new(
                points.clone(),
                colour(index).stroke_width(CURVE_WIDTH),
            )))?;
            chart.draw_series(points.iter().map(|p| Circle::new(*p, 3, colour(index).filled())))?;
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
fn draw_strip(area: &Area, times: Range<f64>, rows: &[&Row], series: &[Series], seeds: &[SeedPoint]) -> DrawResult {
    let mut chart = ChartBuilder::on(area)
        .margin(MARGIN)
        .x_label_area_size(30)
        .y_label_area_size(Y_LABELS)
        .caption(
            "no error to draw: rows without an error value or with exactly 0 (circles), the seeds' figures (triangles)",
            ("sans-serif", 13),
        )
        .build_cartesian_2d(times.log_scale(), 0.0..3.0)?;
    chart.configure_mesh().disable_mesh().disable_y_axis().x_label_formatter(&|_| String::new()).draw()?;
    for (index, s) in series.iter().enumerate() {
        let missing = s.rows.iter().filter(|&&i| plotted_error(rows[i]).is_none());
        chart.draw_series(
            missing.map(|&i| Circle::new((rows[i].time_ms.median, 2.0), 4, colour(index).stroke_width(2))),
        )?;
    }
    chart.draw_series(seeds.iter().map(|s| TriangleMarker::new((s.time_ms, 1.0), 6, BLACK.filled())))?;
    // Lettered as in the legend (letters, not numbers: the axes' numbers are all ticks).
    let letter = ("sans-serif", 11).into_font();
    chart.draw_series(seeds.iter().zip(seed_letters()).map(|(s, l)| Text::new(l, (s.time_ms, 1.9), letter.clone())))?;
    Ok(())
}

fn draw_legend(area: &Area, series: &[Series], seeds: &[SeedPoint]) -> DrawResult {
    let text = ("sans-serif", 12).into_font();
    let mut y = 20;
    for (index, s) in series.iter().enumerate() {
        area.draw(&Rectangle::new([(4, y - 5), (14, y + 5)], colour(index).filled()))?;
        area.draw(&Text::new(s.label.clone(), (20, y - 6), text.clone()))?;
        y += 18;
    }
    for (seed, letter) in seeds.iter().zip(seed_letters()) {
        area.draw(&TriangleMarker::new((9, y), 5, BLACK.filled()))?;
        area.draw(&Text::new(
            format!("{letter} {}: {} ms", seed.label, tick_text(seed.time_ms)),
            (20, y - 6),
            text.clone(),
        ))?;
        y += 18;
    }
    Ok(())
}
