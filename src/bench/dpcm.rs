//! `defvol bench dpcm`: the seed's Table 1 case (1100 x 1100 phyxels, 1 to 300 markers),
//! four and eight neighbours, elastic and plastic; and run time against error over dt.

use std::time::Instant;

use serde_json::json;

use super::{cpu_description, time_stats, BenchRow, ErrorMeasure};
use crate::dpcm::{DpcmConfig, DpcmError, Interaction, Surface, Topology};
use crate::dpcm::{Pattern, Script};

/// The seed's Table 1: (markers, Hz) on a GeForce 8800 GTX, 1100 x 1100 phyxels.
pub const SEED_TABLE_1: [(usize, f64); 5] = [(1, 690.0), (20, 220.0), (50, 104.0), (100, 55.0), (300, 23.0)];

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Physics {
    /// Damped springs to the ground and between phyxels (the water preset).
    Elastic,
    /// A plastic ground link under the same neighbour links (the fossil preset's kind).
    Plastic,
}

pub struct DpcmBenchOptions {
    pub size: [usize; 2],
    pub markers: Vec<usize>,
    pub topologies: Vec<Topology>,
    pub physics: Vec<Physics>,
    pub steps: usize,
    /// Time steps of the accuracy sweep (each against dt/16).
    pub dts: Vec<f64>,
    pub gpu: Option<crate::backend::Backend>,
    /// GPU steps per submission, a row each.
    pub batches: Vec<usize>,
}

/// The benchmark grid: the water preset's physics, markers wandering over the grid.
pub fn bench_config(
    size: [usize; 2],
    topology: Topology,
    physics: Physics,
    markers: usize,
) -> Result<DpcmConfig, DpcmError> {
    let mut c = DpcmConfig::preset("water")?;
    (c.width, c.height) = (size[0], size[1]);
    c.links.topology = topology;
    if physics == Physics::Plastic {
        c.ground = Interaction::Plastic { stiffness: 20.0, damping: 0.02, threshold: 3e-4 };
    }
    c.script = Script { markers, pattern: Pattern::Wander, speed: 0.2, depth: 0.001, leave_after: None };
    Ok(c)
}

/// One CPU step under the script's markers at `t`.
fn step_script(surface: &mut Surface, config: &DpcmConfig, t: f64) {
    let markers = config.script.markers_at(config, t);
    surface.step(&markers);
}

/// Settles for 20 steps, then times `steps` steps in batches of up to `batch` per
/// submission, waiting for each batch; ms per step and what the timed steps cost in round
/// trips.
#[cfg(feature = "gpu")]
fn time_gpu_batches(
    surface: &mut crate::dpcm::gpu::GpuSurface,
    ctx: &crate::gpu::GpuContext,
    config: &DpcmConfig,
    steps: usize,
    batch: usize,
) -> Result<(Vec<f64>, Option<super::GpuCost>), DpcmError> {
    let gpu_error = |e: crate::dpcm::gpu::GpuDpcmError| DpcmError::Gpu(e.to_string());
    let run_batch = |surface: &mut crate::dpcm::gpu::GpuSurface, first: usize, n: usize| {
        let markers: Vec<_> =
            (first..first + n).map(|s| config.script.markers_at(config, s as f64 * config.dt)).collect();
        surface.step_batch(&markers).map_err(gpu_error)?;
        ctx.wait();
        Ok::<_, DpcmError>(())
    };
    run_batch(surface, 0, 20)?;
    let meter = super::GpuMeter::on(ctx);
    let mut samples = Vec::with_capacity(steps.div_ceil(batch));
    for first in (0..steps).step_by(batch) {
        let n = batch.min(steps - first);
        let start = Instant::now();
        run_batch(surface, 20 + first, n)?;
        samples.push(start.elapsed().as_secs_f64() * 1e3 / n as f64);
    }
    Ok((samples, meter.finish(steps)))
}

/// Settles for 20 steps, then times `steps` steps one by one.
fn time_steps(surface: &mut Surface, config: &DpcmConfig, steps: usize) -> Vec<f64> {
    // On a pool worker, as a run loop should be: the stepping thread is one of the two
    // that compute, instead of a third one waking them for every step.
    rayon::scope(|_| time_steps_on_worker(surface, config, steps))
}

fn time_steps_on_worker(surface: &mut Surface, config: &DpcmConfig, steps: usize) -> Vec<f64> {
    for s in 0..20 {
        step_script(surface, config, s as f64 * config.dt);
    }
    let mut samples = Vec::with_capacity(steps);
    for s in 20..20 + steps {
        let start = Instant::now();
        step_script(surface, config, s as f64 * config.dt);
        samples.push(start.elapsed().as_secs_f64() * 1e3);
    }
    samples
}

pub fn run(opts: &DpcmBenchOptions, mut emit: impl FnMut(&BenchRow)) -> Result<(), DpcmError> {
    let cpu = cpu_description();
    #[cfg(feature = "gpu")]
    let gpu = opts.gpu.as_ref().and_then(crate::backend::Backend::context).cloned();
    #[cfg(not(feature = "gpu"))]
    let _ = &opts.gpu;
    for &physics in &opts.physics {
        for &topology in &opts.topologies {
            for &markers in &opts.markers {
                let config = bench_config(opts.size, topology, physics, markers)?;
                let seed_hz = SEED_TABLE_1.iter().find(|(k, _)| *k == markers).map(|(_, hz)| *hz);
                let case = format!("{}x{}_{}markers", opts.size[0], opts.size[1], markers);
                let params = json!({"topology": topology, "physics": format!("{physics:?}").to_lowercase(), "dt": config.dt, "seed_gpu_hz": seed_hz});
                let work = json!({"phyxels": opts.size[0] * opts.size[1], "markers": markers});
                let mut surface = Surface::new(&config)?;
                let samples = time_steps(&mut surface, &config, opts.steps);
                #[cfg(feature = "gpu")]
                let cpu_heights = surface.heights();
                let cpu_row = BenchRow {
                    stage: "dpcm",
                    case,
                    backend: "cpu".into(),
                    device: cpu.clone(),
                    params,
                    runs: samples.len(),
                    time_ms: time_stats(samples),
                    error: None,
                    work,
                    gpu: None,
                };
                emit(&cpu_row);
                #[cfg(feature = "gpu")]
                if let Some(ctx) = &gpu {
                    let row = BenchRow { backend: "gpu".into(), device: ctx.describe(), ..cpu_row };
                    gpu_rows(ctx, &config, opts, &cpu_heights, &row, &mut emit)?;
                }
            }
        }
    }
    accuracy_sweep(opts, &cpu, &mut emit)
}

/// The GPU twin's rows beside the CPU's `row`, one per batch size: ms per step, error
/// against the CPU's heights after as many steps, round trips per step.
#[cfg(feature = "gpu")]
fn gpu_rows(
    ctx: &std::sync::Arc<crate::gpu::GpuContext>,
    config: &DpcmConfig,
    opts: &DpcmBenchOptions,
    cpu_heights: &[f32],
    row: &BenchRow,
    emit: &mut impl FnMut(&BenchRow),
) -> Result<(), DpcmError> {
    for &batch in &opts.batches {
        let mut surface =
            crate::dpcm::gpu::GpuSurface::new(ctx.clone(), config).map_err(|e| DpcmError::Gpu(e.to_string()))?;
        let (samples, cost) = time_gpu_batches(&mut surface, ctx, config, opts.steps, batch)?;
        let heights = surface.read_heights().map_err(|e| DpcmError::Gpu(e.to_string()))?;
        let peak = cpu_heights.iter().fold(0.0f32, |m, z| m.max(z.abs())).max(f32::MIN_POSITIVE);
        let worst = heights.iter().zip(cpu_heights).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        let mut params = row.params.clone();
        params["batch"] = json!(batch);
        emit(&BenchRow {
            params,
            runs: samples.len(),
            time_ms: time_stats(samples),
            error: Some(ErrorMeasure { metric: "max_abs_over_peak", value: f64::from(worst / peak), reference: "cpu" }),
            gpu: cost,
            ..row.clone()
        });
    }
    Ok(())
}

/// Run time against error over the time step: the water physics on a 256² grid for 0.2 s
/// with one marker, each dt against the same run at dt/16 (f32 round-off is far below).
fn accuracy_sweep(opts: &DpcmBenchOptions, cpu: &str, emit: &mut impl FnMut(&BenchRow)) -> Result<(), DpcmError> {
    if opts.dts.is_empty() {
        return Ok(());
    }
    let duration = 0.2;
    let run = |dt: f64| -> Result<(Vec<f32>, Vec<f64>), DpcmError> {
        let mut config = bench_config([256, 256], Topology::Eight, Physics::Elastic, 1)?;
        config.dt = dt;
        let mut surface = Surface::new(&config)?;
        let steps = (duration / dt).round() as usize;
        let mut samples = Vec::with_capacity(steps);
        for s in 0..steps {
            let start = Instant::now();
            step_script(&mut surface, &config, s as f64 * dt);
            samples.push(start.elapsed().as_secs_f64() * 1e3);
        }
        Ok((surface.heights().to_vec(), samples))
    };
    let finest = opts.dts.iter().copied().fold(f64::INFINITY, f64::min) / 16.0;
    let (reference, _) = run(finest)?;
    let peak = reference.iter().fold(0.0f32, |m, z| m.max(z.abs())).max(f32::MIN_POSITIVE);
    for &dt in &opts.dts {
        let (heights, samples) = match run(dt) {
            Ok(r) => r,
            Err(e @ DpcmError::Unstable { .. }) => {
                tracing::warn!("dt = {dt} s left out of the sweep: {e}");
                continue;
            }
            Err(e) => return Err(e),
        };
        let worst = heights.iter().zip(&reference).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        let total_ms: f64 = samples.iter().sum();
        emit(&BenchRow {
            stage: "dpcm",
            case: "256x256_dt_sweep".into(),
            backend: "cpu".into(),
            device: cpu.to_owned(),
            params: json!({"topology": "eight", "physics": "elastic", "dt": dt, "simulated_s": duration, "total_ms": total_ms}),
            runs: samples.len(),
            time_ms: time_stats(samples),
            error: Some(ErrorMeasure {
                metric: "max_abs_over_peak",
                value: f64::from(worst / peak),
                reference: "dt/16",
            }),
            work: json!({"phyxels": 256 * 256, "markers": 1}),
            gpu: None,
        });
    }
    Ok(())
}

pub const TABLE_HEADER: &str =
    "case                     backend  params                         median ms   steps/s   seed GPU Hz      error";

pub fn table_row(row: &BenchRow) -> String {
    let p = &row.params;
    let batch = p["batch"].as_u64().map_or(String::new(), |b| format!(" batch={b}"));
    let params = format!(
        "{} {} dt={}{batch}",
        p["topology"].as_str().unwrap_or("?"),
        p["physics"].as_str().unwrap_or("?"),
        p["dt"]
    );
    let seed = p["seed_gpu_hz"].as_f64().map_or("-".to_owned(), |hz| format!("{hz:.0}"));
    let error = row.error.as_ref().map_or("-".to_owned(), |e| format!("{:.2e}", e.value));
    format!(
        "{:<24} {:<8} {:<30} {:>9.3} {:>9.0} {:>13} {:>10}",
        row.case,
        row.backend,
        params,
        row.time_ms.median,
        1e3 / row.time_ms.median,
        seed,
        error
    )
}
