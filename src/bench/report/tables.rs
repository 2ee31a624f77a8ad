//! The report's rows as Markdown, for pages that quote them: every row in a table per stage
//! (`bench tables`), and per stage one headline row beside its paper's published figure
//! (`bench summary`). Each is rewritten between its markers in a page, so a page's figures
//! are always the rows' own.

use super::plot::tick_text;
use super::rows::{scheme, seed_points, size_key, Row, SeedPoint, STAGES};

/// The markers' names: `<!-- bench tables: begin -->` … `<!-- bench tables: end -->`.
pub const TABLES: &str = "bench tables";
pub const SUMMARY: &str = "bench summary";

/// The params that sweep a scheme's accuracy, shown beside it.
fn sweep_params(stage: &str) -> &'static [&'static str] {
    match stage {
        "solver" => &["cg_tolerance"],
        "warp" => &["sampling"],
        "dpcm" => &["dt"],
        "render" => &["step_mm"],
        _ => &[],
    }
}

fn sweep(row: &Row) -> String {
    let value = |key: &&str| match row.params.get(*key)? {
        serde_json::Value::String(s) => Some(format!("{key} {s}")),
        serde_json::Value::Number(n) => Some(format!("{key} {}", tick_text(n.as_f64()?))),
        _ => None,
    };
    sweep_params(&row.stage).iter().filter_map(value).collect::<Vec<_>>().join(", ")
}

fn error(row: &Row) -> String {
    match &row.error {
        Some(e) if e.metric.ends_with("_db") => format!("{:.1} dB ({})", e.value, e.metric),
        Some(e) => format!("{:.1e} ({})", e.value, e.metric),
        None => "—".to_owned(),
    }
}

fn dated(row: &Row) -> &str {
    row.date.as_deref().unwrap_or("undated")
}

fn command(row: &Row) -> String {
    row.command.as_deref().map(|c| format!("`{c}`")).unwrap_or_else(|| "—".to_owned())
}

/// Every row, a table per stage, in the order they were measured.
pub fn tables(rows: &[Row]) -> String {
    let mut text = String::new();
    for stage in STAGES {
        let of_stage: Vec<&Row> = rows.iter().filter(|r| r.stage == stage).collect();
        if of_stage.is_empty() {
            continue;
        }
        text += &format!("\n### {stage}\n\n");
        text += "| case | backend | scheme | sweep | median ms | error | machine | date |\n";
        text += "| --- | --- | --- | --- | --- | --- | --- | --- |\n";
        for r in &of_stage {
            text += &format!(
                "| {} | {} | {} | {} | {} | {} | {} | {} |\n",
                r.case,
                r.backend,
                scheme(r),
                sweep(r),
                tick_text(r.time_ms.median),
                error(r),
                r.device,
                dated(r)
            );
        }
        let mut commands: Vec<String> = of_stage.iter().map(|r| command(r)).collect();
        commands.dedup();
        text += &format!("\nMeasured by {}.\n", commands.join(", "));
    }
    text
}

fn size(row: &Row) -> Option<f64> {
    row.work.get(size_key(&row.stage))?.as_f64()
}

/// Rows that do the work the papers timed: implicit Euler (the solver), the tet walk (the
/// raycaster), a whole warp (not an incremental one).
fn comparable(row: &Row) -> bool {
    let param = |key: &str| row.params.get(key);
    match row.stage.as_str() {
        "solver" => param("integrator").and_then(|v| v.as_str()) == Some("implicit_euler"),
        "render" => param("mode").and_then(|v| v.as_str()) == Some("tet_mesh"),
        "warp" => param("incremental").and_then(|v| v.as_bool()) != Some(true),
        _ => true,
    }
}

/// A stage's headline: among the rows comparable with its papers', the case nearest in size
/// to their largest published one (or the largest case, with none), its fastest row on each
/// backend.
fn headlines<'a>(stage: &str, of_stage: &[&'a Row]) -> Vec<&'a Row> {
    let sized: Vec<(&Row, f64)> =
        of_stage.iter().filter(|r| comparable(r)).filter_map(|r| Some((*r, size(r)?))).collect();
    let largest = sized.iter().map(|(_, s)| *s).reduce(f64::max);
    let Some(target) = seed_points(stage).iter().map(|p| p.size).reduce(f64::max).or(largest) else {
        return Vec::new();
    };
    let distance = |s: f64| (s / target).ln().abs();
    let nearest = sized.iter().map(|(_, s)| distance(*s)).reduce(f64::min);
    let mut chosen: Vec<&Row> = Vec::new();
    for (row, _) in sized.iter().filter(|(_, s)| Some(distance(*s)) == nearest) {
        match chosen.iter_mut().find(|c| c.backend == row.backend) {
            Some(c) if row.time_ms.median < c.time_ms.median => *c = row,
            Some(_) => {}
            None => chosen.push(row),
        }
    }
    chosen
}

/// The published figure nearest the row in size (by ratio).
fn peer(row: &Row) -> Option<SeedPoint> {
    let size = size(row)?;
    let distance = |p: &SeedPoint| (p.size / size).ln().abs();
    seed_points(&row.stage).into_iter().min_by(|a, b| distance(a).total_cmp(&distance(b)))
}

/// Per stage, its headline rows beside the papers' published figure of the nearest size.
pub fn summary(rows: &[Row]) -> String {
    let mut text = String::from("| stage | case | defvol | published beside it | machine | date | command |\n");
    text += "| --- | --- | --- | --- | --- | --- | --- |\n";
    for stage in STAGES {
        let of_stage: Vec<&Row> = rows.iter().filter(|r| r.stage == stage).collect();
        for r in headlines(stage, &of_stage) {
            let published = peer(r).map(|p| format!("{} ms ({})", tick_text(p.time_ms), p.label));
            text += &format!(
                "| {stage} | {} | {} ms, {} {}, error {} | {} | {} | {} | {} |\n",
                r.case,
                tick_text(r.time_ms.median),
                r.backend,
                scheme(r),
                error(r),
                published.unwrap_or_else(|| "—".to_owned()),
                r.device,
                dated(r),
                command(r)
            );
        }
    }
    text
}

/// `page` with the text between the `name` markers replaced by `block`; none when the page
/// has no such markers.
pub fn rewrite_block(page: &str, name: &str, block: &str) -> Option<String> {
    let (begin, end) = (format!("<!-- {name}: begin -->\n"), format!("<!-- {name}: end -->"));
    let (before, rest) = page.split_once(&begin)?;
    let (_, after) = rest.split_once(&end)?;
    Some(format!("{before}{begin}{block}{end}{after}"))
}

/// The text between the `name` markers of `page`.
pub fn block<'a>(page: &'a str, name: &str) -> Option<&'a str> {
    let (begin, end) = (format!("<!-- {name}: begin -->\n"), format!("<!-- {name}: end -->"));
    page.split_once(&begin)?.1.split_once(&end).map(|(block, _)| block)
}
