//! Benchmark rows read back from JSON lines, and how a stage's rows fall into series: one
//! curve per scheme and backend, its points the sweep (tolerances, steps, time steps).

use serde::Deserialize;

/// The stages a report draws, in its order.
pub const STAGES: [&str; 5] = ["solver", "warp", "dpcm", "render", "node"];

/// One row of `defvol bench <stage> --json`, as the conventions fix it.
#[derive(Debug, Clone, Deserialize)]
pub struct Row {
    pub stage: String,
    pub case: String,
    pub backend: String,
    pub device: String,
    #[serde(default)]
    pub params: serde_json::Value,
    /// Timed runs; 0 marks a row the bench could not measure here (its note says why).
    #[serde(default)]
    pub runs: Option<usize>,
    pub time_ms: Times,
    #[serde(default)]
    pub error: Option<RowError>,
    #[serde(default)]
    pub work: serde_json::Value,
    /// The day it was measured (UTC); rows from before rows were dated have none.
    #[serde(default)]
    pub date: Option<String>,
    /// The `defvol bench` command that measured it.
    #[serde(default)]
    pub command: Option<String>,
    /// The JSON line as read, kept whole (work, GPU costs) for the report's `rows.jsonl`.
    #[serde(skip)]
    pub line: String,
}

#[derive(Debug, Clone, Deserialize)]
pub struct Times {
    pub min: f64,
    pub median: f64,
    pub max: f64,
}

#[derive(Debug, Clone, Deserialize)]
pub struct RowError {
    pub metric: String,
    pub value: f64,
    pub reference: String,
}

/// A line that is not a benchmark row, named so the user can find it.
#[derive(Debug, Clone, PartialEq)]
pub struct Skipped {
    pub source: String,
    pub line: usize,
    pub why: String,
}

impl std::fmt::Display for Skipped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} line {}: {}", self.source, self.line, self.why)
    }
}

/// The rows of JSON-lines `text` (from `source`), and the lines skipped with why (blank
/// lines are passed over).
pub fn parse_rows(text: &str, source: &str) -> (Vec<Row>, Vec<Skipped>) {
    let (mut rows, mut skipped) = (Vec::new(), Vec::new());
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        match parse_row(line) {
            Ok(row) => rows.push(row),
            Err(why) => skipped.push(Skipped { source: source.to_owned(), line: n + 1, why }),
        }
    }
    (rows, skipped)
}

fn parse_row(line: &str) -> Result<Row, String> {
    let mut row: Row = serde_json::from_str(line).map_err(|e| format!("not a benchmark row ({e})"))?;
    row.line = line.to_owned();
    if !STAGES.contains(&row.stage.as_str()) {
        return Err(format!("stage `{}` is not one of {}", row.stage, STAGES.join(", ")));
    }
    let t = &row.time_ms;
    if row.runs == Some(0) {
        let note = row.params.get("note").and_then(|n| n.as_str()).unwrap_or("no note");
        return Err(format!("`{}` was not measured ({note})", row.case));
    }
    if ![t.min, t.median, t.max].iter().all(|v| v.is_finite() && *v > 0.0) {
        return Err(format!("time_ms must be positive and finite, got {:?}", [t.min, t.median, t.max]));
    }
    if let Some(e) = &row.error {
        if !e.value.is_finite() {
            return Err(format!("error value of `{}` is not finite", e.metric));
        }
    }
    Ok(row)
}

/// The params that tell one curve of a stage from another; the rest are its sweep
/// (tolerances, time steps, ray steps, sampling) or measurements (prepare times, notes).
fn series_params(stage: &str) -> &'static [&'static str] {
    match stage {
        "solver" => &["integrator", "preconditioner", "batch"],
        "warp" => &["scheme", "path", "dims"],
        "dpcm" => &["topology", "physics", "batch"],
        "render" => &["mode", "shading", "preintegrated"],
        _ => &[],
    }
}

/// Rows of one stage that make one curve: one scheme on one backend, in one panel (a case).
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// The panel it is drawn in: its rows' case (the node's distributions share one).
    pub panel: String,
    /// Backend and scheme: the same label is the same colour in every panel.
    pub label: String,
    pub rows: Vec<usize>,
}

/// The panel the node's latency distributions share.
pub const LATENCY_PANEL: &str = "latency";

/// The series of `rows` (all of one stage): same case, backend, device and series params.
/// The device joins the label only where the rows come from more than one machine.
pub fn series_of(rows: &[&Row]) -> Vec<Series> {
    let several_devices = rows.iter().any(|r| r.device != rows[0].device);
    let mut series: Vec<Series> = Vec::new();
    for (i, row) in rows.iter().enumerate() {
        let panel = if row.stage == "node" { LATENCY_PANEL.to_owned() } else { row.case.clone() };
        let label = series_label(row, several_devices);
        match series.iter_mut().find(|s| s.label == label && s.panel == panel) {
            Some(s) => s.rows.push(i),
            None => series.push(Series { panel, label, rows: vec![i] }),
        }
    }
    series
}

/// The distinct series labels, in order: index i is colour i.
pub fn labels(series: &[Series]) -> Vec<&str> {
    let mut labels: Vec<&str> = Vec::new();
    for s in series {
        if !labels.contains(&s.label.as_str()) {
            labels.push(&s.label);
        }
    }
    labels
}

fn series_label(row: &Row, with_device: bool) -> String {
    let mut parts = vec![row.backend.clone()];
    if row.stage == "node" {
        parts.push(row.case.clone());
    }
    parts.extend(scheme_parts(row));
    if with_device {
        parts.push(format!("({})", row.device));
    }
    parts.join(" · ")
}

/// The row's scheme: the values of its stage's series params (`amg`, `spans`, …).
pub fn scheme(row: &Row) -> String {
    scheme_parts(row).join(" · ")
}

fn scheme_parts(row: &Row) -> Vec<String> {
    let mut parts = Vec::new();
    for key in series_params(&row.stage) {
        match row.params.get(*key) {
            Some(serde_json::Value::String(s)) => parts.push(s.clone()),
            Some(serde_json::Value::Bool(true)) => parts.push((*key).to_owned()),
            Some(serde_json::Value::Bool(false)) => {}
            Some(v) if !v.is_null() => parts.push(format!("{key} {v}")),
            _ => {}
        }
    }
    parts
}

/// A published figure from the source papers: time only (they give no error).
#[derive(Debug, Clone, PartialEq)]
pub struct SeedPoint {
    pub label: String,
    pub time_ms: f64,
    /// Its size in the unit the stage's rows count (`size_key`): tets, voxels or markers.
    pub size: f64,
}

/// Frames per second as milliseconds a frame.
fn per_second(label: impl Into<String>, hz: f64, size: f64) -> SeedPoint {
    SeedPoint { label: label.into(), time_ms: 1000.0 / hz, size }
}

/// The `work` entry that sizes a stage's rows, as its published figures are sized.
pub fn size_key(stage: &str) -> &'static str {
    match stage {
        "dpcm" => "markers",
        _ => "tets",
    }
}

/// The papers' published figures for a stage: the mass-spring paper's Table 1 (implicit
/// Euler on a GeForce 7800; its raycaster), Gascón et al.'s GTX 680 warp, Sillam et al.'s
/// Table 1 (GeForce 8800 GTX).
pub fn seed_points(stage: &str) -> Vec<SeedPoint> {
    match stage {
        "solver" => vec![
            per_second("GeForce 7800, implicit Euler, Bar 80 tets", 282.0, 80.0),
            per_second("GeForce 7800, implicit Euler, Dolphin 13,766 tets", 113.0, 13_766.0),
            per_second("GeForce 7800, implicit Euler, Knee-small 35,118 tets", 56.0, 35_118.0),
            per_second("GeForce 7800, implicit Euler, Knee 112,299 tets", 22.0, 112_299.0),
            per_second("GeForce 7800, implicit Euler, Foot 156,612 tets", 12.0, 156_612.0),
        ],
        "warp" => vec![SeedPoint { label: "GTX 680, 700 tets, 4.99M voxels".into(), time_ms: 14.86, size: 700.0 }],
        "dpcm" => crate::bench::dpcm::SEED_TABLE_1
            .iter()
            .map(|&(markers, hz)| per_second(format!("8800 GTX, 1100x1100, {markers} markers"), hz, markers as f64))
            .collect(),
        "render" => vec![
            per_second("GeForce 7800 raycaster, Knee 112,299 tets", 11.2, 112_299.0),
            per_second("GeForce 7800 raycaster, Foot 156,612 tets", 6.2, 156_612.0),
        ],
        _ => Vec::new(),
    }
}
