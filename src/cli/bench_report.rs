//! `defvol bench report DIR`: runs the stages' benchmarks (each as `defvol bench <stage>
//! --json`, so a report times exactly what the stage's own command times) or reads rows
//! already written, then draws them (`defvol::bench::report`).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

use defvol::bench::report::{self, About, Row, Skipped, STAGES};

#[derive(clap::Args)]
pub struct ReportArgs {
    /// Folder the report is written into (made if missing).
    dir: PathBuf,
    /// Draw the rows of these JSON-lines files (`defvol bench <stage> --json` output)
    /// instead of running the benchmarks; a line that is not a row is named and skipped.
    #[arg(long, num_args = 1..)]
    from: Vec<PathBuf>,
    /// Markdown pages whose `bench tables` and `bench summary` blocks are rewritten from the
    /// rows (`docs/performance.md`, `README.md`).
    #[arg(long, value_delimiter = ',')]
    pages: Vec<PathBuf>,
    /// Stages to run (without `--from`).
    #[arg(long, value_delimiter = ',', default_value = "solver,warp,dpcm,render,node", conflicts_with = "from")]
    stages: Vec<String>,
    /// Tiny sizes (seconds, not minutes): the shape of the report, not its figures.
    #[arg(long, conflicts_with = "from")]
    quick: bool,
    /// GPU rows beside the CPU ones in every stage (no usable adapter is an error).
    #[arg(long, conflicts_with = "from")]
    gpu: bool,
    /// Let a software adapter (lavapipe, llvmpipe) run the GPU rows: correctness, not speed.
    #[arg(long, requires = "gpu")]
    allow_software_gpu: bool,
    /// Also log the plotted points to a rerun recording (.rrd): per stage, panel and series,
    /// x = log10 ms and y = log10 error (PSNR in dB as it is).
    #[cfg(feature = "rerun")]
    #[arg(long)]
    rerun: Option<PathBuf>,
}

/// A stage's arguments for `--quick`.
fn quick_args(stage: &str) -> &'static [&'static str] {
    match stage {
        "solver" => &["--sizes", "80,600", "--steps", "3", "--tolerances", "1e-2,1e-4"],
        "warp" => &["--tets", "40", "--dims", "32,24,20", "--runs", "2", "--samplings", "trilinear,tricubic"],
        "dpcm" => &["--size", "64,64", "--markers", "1,20", "--steps", "5", "--dts", "0.001,0.0005", "--batch", "1"],
        "render" => &["--sizes", "32", "--steps", "2,1", "--runs", "2", "--meshes", "600", "--source-meshes"],
        "node" => &["--tets", "600", "--steps", "100", "--settle", "20", "--volume-mib", "1", "--volume-frames", "5"],
        _ => &[],
    }
}

/// A stage's arguments for GPU rows beside its CPU rows.
fn gpu_args(stage: &str) -> &'static [&'static str] {
    match stage {
        "solver" | "node" => &["--backends", "cpu,gpu"],
        _ => &["--gpu"],
    }
}

pub fn run(args: &ReportArgs) -> Result<()> {
    let (rows, skipped, failed) = if args.from.is_empty() { run_stages(args)? } else { read_rows(&args.from)? };
    for s in &skipped {
        tracing::warn!("skipped {s}");
    }
    let about = About {
        build: format!(
            "defvol {} ({}, {}-{})",
            env!("CARGO_PKG_VERSION"),
            if cfg!(debug_assertions) { "debug build" } else { "optimized build" },
            std::env::consts::ARCH,
            std::env::consts::OS
        ),
        date: jiff::Timestamp::now().strftime("%Y-%m-%d %H:%M:%S UTC").to_string(),
        command: std::env::args().collect::<Vec<_>>().join(" "),
    };
    let written = report::write_report(&args.dir, &rows, &skipped, &about)?;
    report::rewrite_pages(&args.pages, &rows)?;
    #[cfg(feature = "rerun")]
    if let Some(path) = &args.rerun {
        log_to_rerun(path, &rows)?;
    }
    println!("{} rows, {} plots: {}", rows.len(), written.svgs.len(), written.page.display());
    if !failed.is_empty() {
        bail!("the {} benchmark failed (the report holds the other stages' rows)", failed.join(", "));
    }
    Ok(())
}

type Gathered = (Vec<Row>, Vec<Skipped>, Vec<String>);

fn read_rows(files: &[PathBuf]) -> Result<Gathered> {
    let (mut rows, mut skipped) = (Vec::new(), Vec::new());
    for file in files {
        let text = std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
        let (r, s) = report::parse_rows(&text, &file.display().to_string());
        rows.extend(r);
        skipped.extend(s);
    }
    Ok((rows, skipped, Vec::new()))
}

/// Each stage's benchmark as its own `defvol bench` command; a stage that fails is named
/// and the others' rows kept.
fn run_stages(args: &ReportArgs) -> Result<Gathered> {
    let exe = std::env::current_exe().context("cannot find the defvol binary to run the benchmarks")?;
    let (mut rows, mut skipped, mut failed) = (Vec::new(), Vec::new(), Vec::new());
    for stage in &args.stages {
        if !STAGES.contains(&stage.as_str()) {
            bail!("unknown stage `{stage}` ({})", STAGES.join(", "));
        }
        let mut extra: Vec<&str> = if args.quick { quick_args(stage).to_vec() } else { Vec::new() };
        if args.gpu {
            extra.extend(gpu_args(stage));
            if args.allow_software_gpu {
                extra.push("--allow-software-gpu");
            }
        }
        match run_stage(&exe, stage, &extra) {
            Ok(text) => {
                let (r, s) = report::parse_rows(&text, &format!("defvol bench {stage}"));
                rows.extend(r);
                skipped.extend(s);
            }
            Err(e) => {
                tracing::error!("{e:#}");
                failed.push(stage.clone());
            }
        }
    }
    Ok((rows, skipped, failed))
}

fn run_stage(exe: &Path, stage: &str, extra: &[&str]) -> Result<String> {
    tracing::info!("running defvol bench {stage} {}", extra.join(" "));
    let output = Command::new(exe)
        .args(["bench", stage, "--json"])
        .args(extra)
        .stderr(Stdio::inherit())
        .output()
        .with_context(|| format!("cannot run defvol bench {stage}"))?;
    if !output.status.success() {
        bail!("defvol bench {stage} failed ({})", output.status);
    }
    String::from_utf8(output.stdout).with_context(|| format!("defvol bench {stage} printed non-UTF-8 output"))
}

/// The report's points as rerun 2D points, one entity per series:
/// `bench/<stage>/<panel>/<series>` and `bench/<stage>/<panel>/<series>/no_error` (y = 0).
#[cfg(feature = "rerun")]
fn log_to_rerun(path: &Path, rows: &[Row]) -> Result<()> {
    use defvol::record::rerun_log::RerunLog;
    let log = RerunLog::save(path)?;
    log.log_markdown(
        "bench/axes",
        "x: log10 of the median time per step or frame (ms); y: log10 of the error against the f64 reference \
         (PSNR: dB as it is); `no_error`: rows with no error to draw, at y = 0.",
    )?;
    let name = |text: &str| text.chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '_' }).collect::<String>();
    for stage in STAGES {
        let of_stage: Vec<&Row> = rows.iter().filter(|r| r.stage == stage).collect();
        for s in report::drawn_series(stage, &of_stage) {
            let entity = format!("bench/{stage}/{}/{}", name(&s.panel), name(&s.label));
            let y = |v: f64| if s.decibels { v } else { v.log10() };
            let points: Vec<[f32; 2]> = s.points.iter().map(|&(t, e)| [t.log10() as f32, y(e) as f32]).collect();
            if !points.is_empty() {
                log.log_bench_series(&entity, &points, s.rgb, &s.label)?;
            }
            let timed: Vec<[f32; 2]> = s.timed_only.iter().map(|t| [t.log10() as f32, 0.0]).collect();
            if !timed.is_empty() {
                log.log_bench_series(&format!("{entity}/no_error"), &timed, s.rgb, &s.label)?;
            }
        }
    }
    log.flush()?;
    Ok(())
}
