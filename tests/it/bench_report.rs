//! `defvol bench report`: the SVGs read back as XML, each curve's points mapped back through
//! the axes' own tick labels to data and compared with the JSON rows it was drawn from.

use std::path::Path;
use std::process::Command;

use defvol::bench::report::{parse_rows, series_of, Row};

/// One panel of a report SVG: what follows its caption up to the next one.
#[derive(Debug, Default)]
struct Panel {
    caption: String,
    /// Series curves (polylines of stroke width 2): stroke colour, points.
    curves: Vec<(String, Vec<(f64, f64)>)>,
    /// Numeric tick labels: (pixel, value) along x and along y.
    x_ticks: Vec<(f64, f64)>,
    y_ticks: Vec<(f64, f64)>,
    /// Hollow circles: stroke colour, centre x.
    hollow: Vec<(String, f64)>,
}

/// What a report SVG shows, in pixels, as a reader finds it.
#[derive(Debug, Default)]
struct Drawn {
    panels: Vec<Panel>,
    /// Legend squares and their labels: (label, fill colour).
    legend: Vec<(String, String)>,
    /// Letters beside the seeds' triangles, and the triangles (strip and legend).
    seed_letters: usize,
    triangles: usize,
}

impl Drawn {
    fn panel(&self, caption: &str) -> &Panel {
        self.panels.iter().find(|p| p.caption == caption).unwrap_or_else(|| panic!("no panel `{caption}`"))
    }

    fn colour(&self, label: &str) -> &str {
        &self.legend.iter().find(|(l, _)| l == label).unwrap_or_else(|| panic!("{label} not in the legend")).1
    }

    fn curves(&self) -> usize {
        self.panels.iter().map(|p| p.curves.len()).sum()
    }
}

fn number(node: roxmltree::Node, attribute: &str) -> f64 {
    node.attribute(attribute).unwrap().parse().unwrap()
}

/// Reads a report SVG whose panels are captioned with `captions`.
fn read_svg(path: &Path, captions: &[&str]) -> Drawn {
    let text = std::fs::read_to_string(path).unwrap();
    let doc = roxmltree::Document::parse(&text).unwrap_or_else(|e| panic!("{} is not XML: {e}", path.display()));
    let mut drawn = Drawn::default();
    for node in doc.descendants().filter(|n| n.is_element()) {
        if drawn.panels.is_empty() {
            let content = node.text().unwrap_or("").trim();
            if node.tag_name().name() == "text" && captions.contains(&content) {
                drawn.panels.push(Panel { caption: content.to_owned(), ..Default::default() });
            }
            continue;
        }
        let panel = drawn.panels.last_mut().unwrap();
        match node.tag_name().name() {
            "polyline" if node.attribute("stroke-width") == Some("2") => {
                let points = node
                    .attribute("points")
                    .unwrap()
                    .split_whitespace()
                    .map(|p| p.split_once(',').map(|(x, y)| (x.parse().unwrap(), y.parse().unwrap())).unwrap())
                    .collect();
                panel.curves.push((node.attribute("stroke").unwrap().to_owned(), points));
            }
            "polygon" => drawn.triangles += 1,
            "circle" if node.attribute("fill") == Some("none") => {
                panel.hollow.push((node.attribute("stroke").unwrap().to_owned(), number(node, "cx")));
            }
            "text" => read_text(node, captions, &mut drawn),
            _ => {}
        }
    }
    drawn
}

fn read_text(node: roxmltree::Node, captions: &[&str], drawn: &mut Drawn) {
    let content = node.text().unwrap_or("").trim();
    let panel = drawn.panels.last_mut().unwrap();
    if captions.contains(&content) {
        drawn.panels.push(Panel { caption: content.to_owned(), ..Default::default() });
    } else if let Ok(value) = content.parse::<f64>() {
        match node.attribute("text-anchor") {
            Some("middle") => panel.x_ticks.push((number(node, "x"), value)),
            Some("end") => panel.y_ticks.push((number(node, "y"), value)),
            other => panic!("a number `{content}` anchored {other:?}"),
        }
    } else if content.len() == 1 && content.chars().all(|c| c.is_ascii_uppercase()) {
        drawn.seed_letters += 1;
    } else if let Some(square) = node.prev_sibling_element().filter(|n| n.tag_name().name() == "rect") {
        if square.attribute("fill") != Some("#FFFFFF") {
            drawn.legend.push((content.to_owned(), square.attribute("fill").unwrap().to_owned()));
        }
    }
}

/// The least-squares line value = a + b·pixel through the tick labels (values through
/// `scale`), and how far one pixel moves along it.
fn axis(ticks: &[(f64, f64)], scale: fn(f64) -> f64) -> impl Fn(f64) -> f64 {
    assert!(ticks.len() >= 2, "an axis needs two labelled ticks, has {ticks:?}");
    let n = ticks.len() as f64;
    let (mx, my) = (ticks.iter().map(|t| t.0).sum::<f64>() / n, ticks.iter().map(|t| scale(t.1)).sum::<f64>() / n);
    let sxy: f64 = ticks.iter().map(|t| (t.0 - mx) * (scale(t.1) - my)).sum();
    let sxx: f64 = ticks.iter().map(|t| (t.0 - mx).powi(2)).sum();
    let b = sxy / sxx;
    for t in ticks {
        assert!((my + b * (t.0 - mx) - scale(t.1)).abs() < 1.0 * b.abs(), "tick {t:?} off its axis");
    }
    move |pixel| my + b * (pixel - mx)
}

/// Asserts `value` (through `scale`) lies within 1.5 pixels of where `pixel` says.
fn assert_at(what: &str, pixel: f64, value: f64, map: &impl Fn(f64) -> f64, scale: fn(f64) -> f64) {
    let per_pixel = (map(1.0) - map(0.0)).abs();
    let off = (map(pixel) - scale(value)).abs();
    assert!(off <= 1.5 * per_pixel, "{what}: drawn at {} (pixel {pixel}), row says {}", map(pixel), scale(value));
}

fn log10(v: f64) -> f64 {
    v.log10()
}

fn linear(v: f64) -> f64 {
    v
}

fn plotted(row: &Row) -> Option<f64> {
    let e = row.error.as_ref()?;
    (e.metric.ends_with("_db") || e.value > 0.0).then_some(e.value)
}

const STRIP: &str =
    "no error to draw: rows without an error value or with exactly 0 (circles), the seeds' figures (triangles)";

/// Every row of `stage` in `dir`'s rows.jsonl is in its SVG where its values put it: the
/// rows with an error on their series' curve in their case's panel (one curve a series, in
/// its legend colour), the rest as hollow circles on the strip's time axis; the seeds'
/// figures as lettered triangles.
fn assert_drawn_as_rows_say(dir: &Path, stage: &str, seeds: usize) {
    let (all, skipped) = parse_rows(&std::fs::read_to_string(dir.join("rows.jsonl")).unwrap(), "rows.jsonl");
    assert!(skipped.is_empty(), "{skipped:?}");
    let rows: Vec<&Row> = all.iter().filter(|r| r.stage == stage).collect();
    assert!(!rows.is_empty(), "no {stage} rows");
    let mut captions: Vec<&str> = rows.iter().map(|r| r.case.as_str()).collect();
    captions.push(STRIP);
    let drawn = read_svg(&dir.join(format!("{stage}.svg")), &captions);
    let decibels = rows.iter().any(|r| r.error.as_ref().is_some_and(|e| e.metric.ends_with("_db")));
    let y_scale = if decibels { linear } else { log10 };
    let strip = drawn.panel(STRIP);
    let strip_x = axis(&strip.x_ticks, log10);
    let mut curves = 0;
    for s in series_of(&rows) {
        let colour = drawn.colour(&s.label);
        let mut expected: Vec<(f64, f64)> =
            s.rows.iter().filter_map(|&i| plotted(rows[i]).map(|e| (rows[i].time_ms.median, e))).collect();
        // Drawn from the largest error to the smallest (in decibels: the lowest PSNR first).
        expected.sort_by(|a, b| if decibels { a.1.total_cmp(&b.1) } else { b.1.total_cmp(&a.1) });
        if !expected.is_empty() {
            let panel = drawn.panel(&s.panel);
            let (x, y) = (axis(&panel.x_ticks, log10), axis(&panel.y_ticks, y_scale));
            let mine: Vec<_> = panel.curves.iter().filter(|(c, _)| c == colour).collect();
            assert_eq!(mine.len(), 1, "{} in {}: one curve", s.label, s.panel);
            assert_eq!(mine[0].1.len(), expected.len(), "{}: its points", s.label);
            for (&(px, py), &(time, error)) in mine[0].1.iter().zip(&expected) {
                assert_at(&s.label, px, time, &x, log10);
                assert_at(&s.label, py, error, &y, y_scale);
            }
            curves += 1;
        }
        let missing: Vec<f64> =
            s.rows.iter().filter(|&&i| plotted(rows[i]).is_none()).map(|&i| rows[i].time_ms.median).collect();
        let mut circles: Vec<f64> = strip.hollow.iter().filter(|(c, _)| c == colour).map(|h| h.1).collect();
        for time in missing {
            let at = circles
                .iter()
                .position(|cx| (strip_x(*cx) - time.log10()).abs() <= 1.5 * (strip_x(1.0) - strip_x(0.0)).abs());
            circles.remove(at.unwrap_or_else(|| {
                panic!("{}: the row at {time} ms without an error is not on the time axis", s.label)
            }));
        }
    }
    assert_eq!(drawn.curves(), curves, "{stage}: curves beyond the series'");
    let hollow: usize = drawn.panels.iter().map(|p| p.hollow.len()).sum();
    assert_eq!(hollow, rows.iter().filter(|r| plotted(r).is_none()).count(), "{stage}: circles beyond the rows'");
    assert_eq!(
        (drawn.triangles, drawn.seed_letters),
        (seeds + seeds, seeds),
        "{stage}: seed figures (a triangle in the strip and one in the legend each)"
    );
}

fn report(args: &[&str]) -> (tempfile::TempDir, std::process::Output) {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_defvol"))
        .args(["bench", "report"])
        .arg(dir.path().join("report"))
        .args(args)
        .current_dir(dir.path())
        .output()
        .unwrap();
    (dir, out)
}

/// Each node row is a curve in its legend colour through the latency quantiles it lists.
fn assert_latencies_drawn_as_rows_say(dir: &Path) {
    let (all, _) = parse_rows(&std::fs::read_to_string(dir.join("rows.jsonl")).unwrap(), "rows.jsonl");
    let rows: Vec<&Row> = all.iter().filter(|r| r.stage == "node").collect();
    let drawn = read_svg(&dir.join("node.svg"), &["latency"]);
    let panel = drawn.panel("latency");
    let (x, y) = (axis(&panel.x_ticks, log10), axis(&panel.y_ticks, linear));
    assert_eq!(panel.curves.len(), rows.len());
    for row in rows {
        let label = format!("{} · {}", row.backend, row.case);
        let colour = drawn.colour(&label);
        let curve = &panel.curves.iter().find(|(c, _)| c == colour).unwrap().1;
        let quantiles = row.params["quantiles_ms"].as_array().unwrap();
        assert_eq!(curve.len(), quantiles.len(), "{label}");
        for (&(px, py), q) in curve.iter().zip(quantiles) {
            assert_at(&label, px, q[1].as_f64().unwrap(), &x, log10);
            assert_at(&label, py, q[0].as_f64().unwrap(), &y, linear);
        }
    }
}

#[test]
fn a_report_of_tiny_benchmarks_draws_each_row_where_its_time_and_error_put_it() {
    let (dir, out) = report(&["--quick", "--stages", "solver,warp,dpcm,render,node"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report = dir.path().join("report");
    for (stage, seeds) in [("solver", 5), ("warp", 1), ("dpcm", 5), ("render", 2)] {
        assert_drawn_as_rows_say(&report, stage, seeds);
    }
    let page = std::fs::read_to_string(report.join("index.html")).unwrap();
    for needle in ["<img src=\"solver.svg\"", "<img src=\"render.svg\"", "build: defvol ", "date: 20", "machine: "] {
        assert!(page.contains(needle), "index.html lacks {needle}:\n{page}");
    }
    assert_latencies_drawn_as_rows_say(&report);
}

fn solver_row(backend: &str, tolerance: f64, time: f64, error: Option<f64>) -> String {
    let error = error.map_or(String::new(), |e| {
        format!(r#","error":{{"metric":"max_node_distance_over_max_displacement","value":{e},"reference":"f64"}}"#)
    });
    format!(
        r#"{{"stage":"solver","case":"cantilever_600tets","backend":"{backend}","device":"test machine","params":{{"cg_tolerance":{tolerance},"integrator":"implicit_euler","preconditioner":"amg"}},"runs":3,"time_ms":{{"min":{time},"median":{time},"max":{time}}}{error},"work":{{}}}}"#
    )
}

/// Solver rows of two series (the gpu one with a row without an error), among lines that
/// are not rows: malformed (line 3), foreign (line 5), and a row with no time (line 8).
fn crafted_lines() -> Vec<String> {
    vec![
        solver_row("cpu", 1e-2, 1.0, Some(1e-3)),
        solver_row("cpu", 1e-3, 2.0, Some(1e-4)),
        "{not json".to_owned(),
        solver_row("cpu", 1e-4, 4.0, Some(1e-5)),
        r#"{"name": "a foreign object", "value": 3}"#.to_owned(),
        solver_row("gpu", 1e-2, 0.5, Some(2e-4)),
        solver_row("gpu", 1e-4, 0.3, None),
        solver_row("gpu", 1e-3, 0.0, Some(1e-4)),
    ]
}

#[test]
fn rows_from_files_are_drawn_and_lines_that_are_not_rows_are_named_and_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let lines = crafted_lines();
    let rows = dir.path().join("rows.jsonl");
    std::fs::write(&rows, lines.join("\n")).unwrap();
    let (out_dir, out) = report(&["--from", rows.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    for line in [3, 5, 8] {
        assert!(stderr.contains(&format!("rows.jsonl line {line}: ")), "line {line} not named:\n{stderr}");
    }
    assert!(stderr.contains("time_ms must be positive"), "{stderr}");
    let report = out_dir.path().join("report");
    assert_drawn_as_rows_say(&report, "solver", 5);
    let drawn = read_svg(&report.join("solver.svg"), &["cantilever_600tets", STRIP]);
    let panel = drawn.panel("cantilever_600tets");
    assert_eq!(panel.curves.iter().map(|c| c.1.len()).collect::<Vec<_>>(), [3, 1]);
    assert_eq!(drawn.panel(STRIP).hollow.len(), 1, "the gpu row without an error is on the time axis");
    let page = std::fs::read_to_string(report.join("index.html")).unwrap();
    assert!(page.contains("5 rows, 2 series") && page.matches("rows.jsonl line ").count() == 3, "{page}");
}

#[test]
fn an_empty_result_set_writes_a_page_that_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let rows = dir.path().join("none.jsonl");
    std::fs::write(&rows, "\n{\"stage\": \"warp\"}\n").unwrap();
    let (out_dir, out) = report(&["--from", rows.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report = out_dir.path().join("report");
    let page = std::fs::read_to_string(report.join("index.html")).unwrap();
    assert!(page.contains("No benchmark rows: nothing to draw.") && page.contains("none.jsonl line 2: "), "{page}");
    let files: Vec<_> = std::fs::read_dir(&report).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(files.len(), 2, "index.html and an empty rows.jsonl, no plot: {files:?}");
}

/// `--rerun`: the points the SVG draws, as rerun 2D points (log10 ms, log10 error) per series,
/// read back by rerun's own CLI.
#[cfg(feature = "rerun")]
#[test]
fn the_rerun_log_holds_each_series_points_as_drawn() {
    if !Command::new("rerun").arg("--version").output().is_ok_and(|o| o.status.success()) {
        assert!(
            std::env::var_os("DEFVOL_REQUIRE_INTEROP").is_none(),
            "the rerun CLI is missing (tests/run.sh installs it)"
        );
        eprintln!("skipped: the rerun CLI (rerun-sdk) is not installed");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let rows = dir.path().join("rows.jsonl");
    std::fs::write(&rows, crafted_lines().join("\n")).unwrap();
    let rrd = dir.path().join("report.rrd");
    let (_out_dir, out) = report(&["--from", rows.to_str().unwrap(), "--rerun", rrd.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let printed = Command::new("rerun").args(["rrd", "print", "-vvv"]).arg(&rrd).output().unwrap();
    let text = String::from_utf8_lossy(&printed.stdout);
    let l = |v: f64| v.log10();
    let entity = "/bench/solver/cantilever_600tets/";
    for (series, expected) in [
        ("cpu___implicit_euler___amg", vec![[l(1.0), l(1e-3)], [l(2.0), l(1e-4)], [l(4.0), l(1e-5)]]),
        ("gpu___implicit_euler___amg", vec![[l(0.5), l(2e-4)]]),
        ("gpu___implicit_euler___amg/no_error", vec![[l(0.3), 0.0]]),
    ] {
        let positions = logged_positions(&text, &format!("{entity}{series}"));
        assert_eq!(positions.len(), expected.len(), "{series}: {positions:?}");
        for (got, want) in positions.iter().zip(&expected) {
            assert!(
                (got[0] - want[0]).abs() < 1e-6 && (got[1] - want[1]).abs() < 1e-6,
                "{series}: {got:?} vs {want:?}"
            );
        }
    }
}

/// The Points2D positions of `entity` in `rerun rrd print -vvv` output: the last `[[x, y], …]`
/// cell of its chunk's data row.
fn logged_positions(printed: &str, entity: &str) -> Vec<[f64; 2]> {
    let header = format!("- {entity} - ");
    let chunk = printed.split("Chunk(").find(|c| c.lines().next().is_some_and(|l| l.contains(&header)));
    let chunk = chunk.unwrap_or_else(|| panic!("no chunk for {entity}"));
    let row = chunk.lines().find(|l| l.contains("row_")).unwrap();
    let cell = &row[row.rfind("[[").unwrap() + 2..row.rfind("]]").unwrap()];
    cell.split("], [")
        .map(|pair| {
            let (x, y) = pair.split_once(", ").unwrap();
            [x.trim().parse().unwrap(), y.trim().parse().unwrap()]
        })
        .collect()
}

/// `--gpu`: every stage's GPU rows beside its CPU rows, a series of their own in the same
/// panels (on the software adapter here: correctness of the drawing, not speed).
#[test]
fn gpu_rows_are_series_of_their_own_beside_the_cpu_ones() {
    let (dir, out) = report(&["--quick", "--stages", "solver,dpcm", "--gpu", "--allow-software-gpu"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    if !out.status.success() && stderr.contains("no GPU adapter") && std::env::var_os("DEFVOL_REQUIRE_GPU").is_none() {
        eprintln!("skipped: no GPU adapter ({stderr})");
        return;
    }
    assert!(out.status.success(), "{stderr}");
    let report = dir.path().join("report");
    for (stage, seeds) in [("solver", 5), ("dpcm", 5)] {
        assert_drawn_as_rows_say(&report, stage, seeds);
        let (rows, _) = parse_rows(&std::fs::read_to_string(report.join("rows.jsonl")).unwrap(), "rows.jsonl");
        let of_stage: Vec<&Row> = rows.iter().filter(|r| r.stage == stage).collect();
        let gpu = series_of(&of_stage).into_iter().filter(|s| s.label.starts_with("gpu")).count();
        assert!(gpu > 0 && gpu < series_of(&of_stage).len(), "{stage}: gpu series beside cpu ones");
    }
}

fn sized_solver_row(tets: usize, backend: &str, time: f64, date: &str) -> String {
    format!(
        r#"{{"stage":"solver","case":"cantilever_{tets}tets","backend":"{backend}","device":"test machine","params":{{"cg_tolerance":0.01,"integrator":"implicit_euler","preconditioner":"amg"}},"runs":3,"time_ms":{{"min":{time},"median":{time},"max":{time}}},"error":{{"metric":"max_node_distance_over_max_displacement","value":0.0002,"reference":"f64"}},"work":{{"tets":{tets}}},"date":"{date}","command":"defvol bench solver --json"}}"#
    )
}

/// The pages' blocks: every row in the tables; in the summary, the fastest row of the
/// largest case on each backend beside the published figure nearest its size.
#[test]
fn the_pages_blocks_are_rewritten_from_the_rows_with_each_rows_machine_and_date() {
    let lines = [
        sized_solver_row(13_120, "cpu", 9.0, "2026-12-01"),
        sized_solver_row(149_040, "cpu", 80.0, "2026-12-02"),
        sized_solver_row(149_040, "cpu", 50.0, "2026-12-03"),
        sized_solver_row(149_040, "gpu", 7.0, "2026-12-04"),
    ];
    let dir = tempfile::tempdir().unwrap();
    let rows = dir.path().join("rows.jsonl");
    std::fs::write(&rows, lines.join("\n")).unwrap();
    let (readme, guide, other) = (dir.path().join("README.md"), dir.path().join("perf.md"), dir.path().join("x.md"));
    std::fs::write(&readme, "# a\n<!-- bench summary: begin -->\nold\n<!-- bench summary: end -->\ntail\n").unwrap();
    std::fs::write(&guide, "intro\n<!-- bench tables: begin -->\n<!-- bench tables: end -->\n").unwrap();
    std::fs::write(&other, "no markers\n").unwrap();
    let pages = format!("{},{}", readme.display(), guide.display());
    let (_out_dir, out) = report(&["--from", rows.to_str().unwrap(), "--pages", &pages]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));

    let readme = std::fs::read_to_string(&readme).unwrap();
    assert!(readme.starts_with("# a\n") && readme.ends_with("-->\ntail\n") && !readme.contains("old"), "{readme}");
    let summary = defvol::bench::report::block(&readme, "bench summary").unwrap();
    let body: Vec<&str> = summary.lines().skip(2).collect();
    assert_eq!(body.len(), 2, "one headline per backend:\n{summary}");
    assert!(body[0].contains("| 50 ms, cpu") && body[0].contains("2026-12-03"), "{}", body[0]);
    assert!(body[1].contains("| 7 ms, gpu") && body[1].contains("2026-12-04"), "{}", body[1]);
    // 1000 / 12 Hz: the Foot's 156,612 tets are nearest 149,040.
    assert!(body.iter().all(|l| l.contains("83.33 ms (GeForce 7800, implicit Euler, Foot")), "{summary}");
    assert!(body.iter().all(|l| l.contains("| test machine |") && l.contains("`defvol bench solver --json`")));

    let guide = std::fs::read_to_string(&guide).unwrap();
    let tables = defvol::bench::report::block(&guide, "bench tables").unwrap();
    for (line, (time, date)) in tables.lines().filter(|l| l.starts_with("| cantilever")).zip([
        ("9", "2026-12-01"),
        ("80", "2026-12-02"),
        ("50", "2026-12-03"),
        ("7", "2026-12-04"),
    ]) {
        assert!(
            line.contains(&format!("| {time} |")) && line.ends_with(&format!("| test machine | {date} |")),
            "{line}"
        );
    }
    assert_eq!(tables.lines().filter(|l| l.starts_with("| cantilever")).count(), 4, "{tables}");

    let (_out_dir, out) = report(&["--from", rows.to_str().unwrap(), "--pages", other.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("x.md has no `<!-- bench tables: begin -->`"), "{stderr}");
}
