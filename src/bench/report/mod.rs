//! `defvol bench report`: the stages' rows drawn as run time against error, one SVG per
//! stage and a page that shows them all with the machine, the build and the date, so the
//! folder can be attached to a paper or an issue as it is.

mod plot;
mod rows;
mod tables;

use std::path::{Path, PathBuf};

pub use plot::{drawn_series, latency_quantiles, stage_svg, tick_text, DrawnSeries};
pub use rows::{parse_rows, seed_points, series_of, Row, Series, Skipped, STAGES};
pub use tables::{block, rewrite_block, summary, tables, SUMMARY, TABLES};

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("cannot write {path}: {source}")]
    Write { path: PathBuf, source: std::io::Error },
    #[error("cannot draw the {stage} plot: {why}")]
    Draw { stage: String, why: String },
    #[error("cannot read {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path} has no `<!-- bench tables: begin -->` or `<!-- bench summary: begin -->` block (each with its `end` marker) to rewrite")]
    NoBlock { path: PathBuf },
}

/// What the page says of where the rows come from.
#[derive(Debug, Clone)]
pub struct About {
    /// defvol's version and build profile.
    pub build: String,
    /// When the report was written (RFC 3339, UTC).
    pub date: String,
    /// The command that made the rows or the report.
    pub command: String,
}

/// The files a report wrote.
#[derive(Debug, Clone, Default)]
pub struct Written {
    pub svgs: Vec<PathBuf>,
    pub page: PathBuf,
    pub rows: PathBuf,
}

/// Writes into `dir`: `<stage>.svg` for each stage with rows, `rows.jsonl` (the rows drawn,
/// so the report can be redrawn with `--from`) and `index.html`; with no rows, a page that
/// says so.
pub fn write_report(dir: &Path, rows: &[Row], skipped: &[Skipped], about: &About) -> Result<Written, ReportError> {
    std::fs::create_dir_all(dir).map_err(|source| ReportError::Write { path: dir.to_owned(), source })?;
    let mut written = Written { page: dir.join("index.html"), rows: dir.join("rows.jsonl"), ..Default::default() };
    let mut figures = Vec::new();
    for stage in STAGES {
        let of_stage: Vec<&Row> = rows.iter().filter(|r| r.stage == stage).collect();
        if of_stage.is_empty() {
            continue;
        }
        let svg = stage_svg(stage, &of_stage)
            .map_err(|e| ReportError::Draw { stage: stage.to_owned(), why: e.to_string() })?;
        let path = dir.join(format!("{stage}.svg"));
        write(&path, &svg)?;
        figures.push((stage, of_stage.len(), series_of(&of_stage).len()));
        written.svgs.push(path);
    }
    write(&written.rows, &rows.iter().map(|r| format!("{}\n", r.line)).collect::<String>())?;
    write(&written.page, &page(&figures, rows, skipped, about))?;
    Ok(written)
}

fn write(path: &Path, text: &str) -> Result<(), ReportError> {
    std::fs::write(path, text).map_err(|source| ReportError::Write { path: path.to_owned(), source })
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// The page: where the rows come from, then each stage's figure.
fn page(figures: &[(&str, usize, usize)], rows: &[Row], skipped: &[Skipped], about: &About) -> String {
    let mut devices: Vec<&str> = rows.iter().map(|r| r.device.as_str()).collect();
    devices.sort_unstable();
    devices.dedup();
    let mut html = String::from("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>defvol benchmarks</title></head>\n<body style=\"font-family: sans-serif\">\n<h1>defvol: run time against error</h1>\n<ul>\n");
    html += &format!("<li>machine: {}</li>\n", escape(&crate::bench::cpu_description()));
    for device in &devices {
        html += &format!("<li>rows measured on: {}</li>\n", escape(device));
    }
    html += &format!(
        "<li>build: {}</li>\n<li>date: {}</li>\n<li>command: <code>{}</code></li>\n</ul>\n",
        escape(&about.build),
        escape(&about.date),
        escape(&about.command)
    );
    html += "<p>Each curve is one scheme on one backend, its points the sweep (CG tolerance, time step, ray step); the error is against each stage's f64 reference. Rows with no error to draw and the seed papers' published figures sit on the time axis below each plot.</p>\n";
    if figures.is_empty() {
        html += "<p><strong>No benchmark rows: nothing to draw.</strong></p>\n";
    }
    for (stage, count, series) in figures {
        html += &format!("<h2>{stage}</h2>\n<p>{count} rows, {series} series.</p>\n<img src=\"{stage}.svg\" alt=\"{stage}: run time against error\">\n");
    }
    if !skipped.is_empty() {
        html += "<h2>Lines skipped</h2>\n<ul>\n";
        for s in skipped {
            html += &format!("<li>{}</li>\n", escape(&s.to_string()));
        }
        html += "</ul>\n";
    }
    html + "</body></html>\n"
}

/// Rewrites the `bench tables` and `bench summary` blocks of each Markdown page from `rows`;
/// a page with neither is an error, and no page is written until all were read.
pub fn rewrite_pages(pages: &[PathBuf], rows: &[Row]) -> Result<(), ReportError> {
    let blocks = [(TABLES, tables(rows)), (SUMMARY, summary(rows))];
    let mut rewritten = Vec::new();
    for path in pages {
        let text = std::fs::read_to_string(path).map_err(|source| ReportError::Read { path: path.clone(), source })?;
        let mut page = text.clone();
        for (name, block) in &blocks {
            page = rewrite_block(&page, name, block).unwrap_or(page);
        }
        if blocks.iter().all(|(name, _)| block(&text, name).is_none()) {
            return Err(ReportError::NoBlock { path: path.clone() });
        }
        rewritten.push((path, page));
    }
    for (path, page) in rewritten {
        write(path, &page)?;
    }
    Ok(())
}
