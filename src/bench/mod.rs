//! `defvol bench`: run time against error, one JSON object per measurement
//! (format in `../shared/conventions.md`), plus a human table.

pub mod dpcm;
pub mod node;
pub mod render;

use std::time::Instant;

use nalgebra::Vector3;
use serde::Serialize;
use serde_json::json;

use crate::engine::{BackendChoice, Engine, EngineError};
use crate::mesh::generate::{self, CellSplit};
use crate::solver::{FixedNodes, Integrator, MassSpringModel, Material, Preconditioner, SolverError, SolverParams};

#[derive(Debug, Clone, Serialize)]
pub struct TimeMs {
    pub min: f64,
    pub median: f64,
    pub max: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct ErrorMeasure {
    pub metric: &'static str,
    pub value: f64,
    pub reference: &'static str,
}

/// One benchmark measurement, as the conventions fix it.
#[derive(Debug, Clone, Serialize)]
pub struct BenchRow {
    pub stage: &'static str,
    pub case: String,
    pub backend: String,
    pub device: String,
    pub params: serde_json::Value,
    pub runs: usize,
    pub time_ms: TimeMs,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<ErrorMeasure>,
    pub work: serde_json::Value,
}

pub fn time_stats(mut samples: Vec<f64>) -> TimeMs {
    samples.sort_by(f64::total_cmp);
    let median = if samples.is_empty() { 0.0 } else { samples[samples.len() / 2] };
    TimeMs { min: samples.first().copied().unwrap_or(0.0), median, max: samples.last().copied().unwrap_or(0.0) }
}

/// The seed's Table 1 sizes (tets).
pub const SEED_SIZES: [usize; 5] = [80, 14_000, 35_000, 112_000, 157_000];

/// The benchmark cantilever: a 0.3 x 0.06 x 0.06 m beam clamped at x = 0, soft tissue
/// density, k = 1000 N/m per spring, under gravity. 80 tets gives the seed's Bar.
pub fn cantilever(target_tets: usize) -> Result<MassSpringModel, SolverError> {
    let mesh = if target_tets <= 80 {
        generate::bar(0.3)
    } else {
        generate::lattice_for_box(Vector3::zeros(), Vector3::new(0.3, 0.06, 0.06), target_tets, CellSplit::Five)
    }
    .map_err(|e| SolverError::BadParameter { name: "mesh".into(), value: target_tets as f64, why: e.to_string() })?;
    let fixed = FixedNodes::Plane { normal: [1.0, 0.0, 0.0], offset: 0.0 }.select(mesh.nodes())?;
    MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 1000.0, damping: 0.5 }, 1000.0, &fixed, None)
}

pub fn cpu_description() -> String {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split(':').nth(1)).map(|s| s.trim().to_owned()))
        .unwrap_or_else(|| std::env::consts::ARCH.to_owned());
    format!("{model}, {} threads", rayon::current_num_threads())
}

pub struct SolverBenchOptions {
    pub sizes: Vec<usize>,
    pub steps: usize,
    pub backends: Vec<BackendChoice>,
    pub allow_software_gpu: bool,
    pub tolerances: Vec<f64>,
    pub dts: Vec<f64>,
    pub explicit_dt: f64,
    pub preconditioners: Vec<Preconditioner>,
}

struct Run {
    positions: Vec<Vector3<f64>>,
    step_ms: Vec<f64>,
    cg_iterations: f64,
    backend: String,
}

fn run(choice: BackendChoice, allow_software_gpu: bool, model: &MassSpringModel, params: SolverParams, steps: usize) -> Result<Run, EngineError> {
    let mut engine = Engine::new(choice, allow_software_gpu, model, params, Vec::new())?;
    // Settle: the first step pays for allocation, pipeline compilation and warm caches.
    engine.step()?;
    let mut step_ms = Vec::with_capacity(steps);
    let mut iterations = 0u64;
    for _ in 1..steps {
        let start = Instant::now();
        let report = engine.step()?;
        step_ms.push(start.elapsed().as_secs_f64() * 1e3);
        iterations += report.cg_iterations as u64;
    }
    Ok(Run { positions: engine.positions(), step_ms, cg_iterations: iterations as f64 / (steps.max(2) - 1) as f64, backend: engine.name() })
}

/// Relative error of `positions` against `reference`: max node distance / max displacement.
pub fn relative_error(model: &MassSpringModel, positions: &[Vector3<f64>], reference: &[Vector3<f64>]) -> f64 {
    let scale = reference.iter().zip(&model.rest).map(|(r, x0)| (r - x0).norm()).fold(0.0, f64::max);
    let worst = positions.iter().zip(reference).map(|(p, r)| (p - r).norm()).fold(0.0, f64::max);
    worst / scale.max(f64::MIN_POSITIVE)
}

/// Implicit Euler over CG tolerances and time steps, and the explicit schemes at their
/// stable step, each against an f64 run of the same scheme and step converged to 1e-10.
// Without the `gpu` feature, solver errors are the only engine errors.
#[cfg_attr(not(feature = "gpu"), allow(unreachable_patterns))]
pub fn solver(opts: &SolverBenchOptions, mut emit: impl FnMut(&BenchRow)) -> Result<(), EngineError> {
    let device = cpu_description();
    for &size in &opts.sizes {
        let model = cantilever(size)?;
        let case = format!("cantilever{}", model.node_count());
        let tets = size;
        let mut configs: Vec<SolverParams> = Vec::new();
        for &dt in &opts.dts {
            for &tol in &opts.tolerances {
                for &preconditioner in &opts.preconditioners {
                    configs.push(SolverParams { integrator: Integrator::ImplicitEuler, dt, cg_tolerance: tol, cg_max_iterations: 5000, preconditioner, ..Default::default() });
                }
            }
        }
        for integrator in [Integrator::ExplicitEuler, Integrator::Verlet, Integrator::VelocityVerlet] {
            configs.push(SolverParams { integrator, dt: opts.explicit_dt, ..Default::default() });
        }
        let mut references: Vec<((Integrator, u64), Option<Vec<Vector3<f64>>>)> = Vec::new();
        for params in configs {
            let key = (params.integrator, params.dt.to_bits());
            if !references.iter().any(|(k, _)| *k == key) {
                let tight = SolverParams { cg_tolerance: 1e-10, cg_max_iterations: 20_000, ..params.clone() };
                match run(BackendChoice::CpuF64, false, &model, tight, opts.steps) {
                    Ok(reference) => references.push((key, Some(reference.positions))),
                    Err(EngineError::Solver(e)) => {
                        tracing::warn!("{case} {} h={}: unstable, skipped ({e})", params.integrator.name(), params.dt);
                        references.push((key, None));
                    }
                    Err(e) => return Err(e),
                }
            }
            let Some((_, Some(reference))) = references.iter().find(|(k, _)| *k == key) else { continue };
            for &backend in &opts.backends {
                let result = match run(backend, opts.allow_software_gpu, &model, params.clone(), opts.steps) {
                    Ok(r) => r,
                    Err(EngineError::Solver(e)) => {
                        tracing::warn!("{case} {}: {e}", params.integrator.name());
                        continue;
                    }
                    Err(e) => return Err(e),
                };
                let device_name = if result.backend.starts_with("gpu") { result.backend.clone() } else { device.clone() };
                emit(&BenchRow {
                    stage: "solver",
                    case: case.clone(),
                    backend: if result.backend.starts_with("gpu") { "gpu".into() } else { result.backend.clone() },
                    device: device_name,
                    params: json!({"integrator": params.integrator.name(), "dt": params.dt, "cg_tolerance": params.cg_tolerance, "steps": opts.steps, "preconditioner": preconditioner_name(&result.backend, &params)}),
                    runs: result.step_ms.len(),
                    time_ms: time_stats(result.step_ms),
                    error: Some(ErrorMeasure { metric: "max_node_distance_over_max_displacement", value: relative_error(&model, &result.positions, reference), reference: "f64" }),
                    work: json!({"tets": tets, "nodes": model.node_count(), "springs": model.springs.len(), "cg_iterations_mean": result.cg_iterations}),
                });
            }
        }
    }
    Ok(())
}

/// The preconditioner a run really used: the GPU path has block Jacobi only; explicit
/// schemes solve nothing.
fn preconditioner_name(backend: &str, params: &SolverParams) -> &'static str {
    match (params.integrator, params.preconditioner) {
        (Integrator::ImplicitEuler, _) if backend.starts_with("gpu") => "block_jacobi",
        (Integrator::ImplicitEuler, Preconditioner::BlockJacobi) => "block_jacobi",
        (Integrator::ImplicitEuler, Preconditioner::Amg) => "amg",
        _ => "none",
    }
}

/// The human table row for one measurement.
pub fn table_row(row: &BenchRow) -> String {
    let steps_per_s = if row.time_ms.median > 0.0 { 1e3 / row.time_ms.median } else { f64::INFINITY };
    format!(
        "{:<18} {:<8} {:<60} {:>10.3} {:>9.1} {:>10.2e} {:>8}",
        row.case,
        row.backend,
        row.params.to_string(),
        row.time_ms.median,
        steps_per_s,
        row.error.as_ref().map_or(f64::NAN, |e| e.value),
        row.work.get("cg_iterations_mean").and_then(|v| v.as_f64()).map_or("-".into(), |v| format!("{v:.1}"))
    )
}

pub const TABLE_HEADER: &str = "case               backend  params                                                        median ms   steps/s      error  CG its";

/// The warp benchmark's deformations of a mesh embedding the volume's box.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WarpCase {
    Upright,
    /// Rotated 45° about x, then 45° about y, around the box centre (the seed's Figure 3).
    Rotated45,
    /// A smooth bend: z shifted by a parabola in x.
    Bend,
}

impl WarpCase {
    pub const ALL: [WarpCase; 3] = [WarpCase::Upright, WarpCase::Rotated45, WarpCase::Bend];
    pub fn name(self) -> &'static str {
        match self {
            WarpCase::Upright => "upright",
            WarpCase::Rotated45 => "rot45",
            WarpCase::Bend => "bend",
        }
    }
    pub fn deform(self, nodes: &[Vector3<f64>], centre: Vector3<f64>, half: Vector3<f64>) -> Vec<Vector3<f64>> {
        use nalgebra::Rotation3;
        let rot = Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_4) * Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_4);
        nodes
            .iter()
            .map(|p| match self {
                WarpCase::Upright => *p,
                WarpCase::Rotated45 => centre + rot * (p - centre),
                WarpCase::Bend => {
                    let u = (p.x - centre.x) / half.x;
                    p + Vector3::new(0.0, 0.0, 0.25 * half.z * u * u)
                }
            })
            .collect()
    }
}

pub struct WarpBenchOptions {
    pub tets: Vec<usize>,
    pub cases: Vec<WarpCase>,
    pub schemes: Vec<crate::warp::Scheme>,
    pub samplings: Vec<crate::warp::Sampling>,
    pub dims: [usize; 3],
    pub runs: usize,
    pub incremental: bool,
    /// Also run the GPU path (spans, trilinear) where an adapter is allowed.
    pub gpu: Option<crate::gpu_policy::GpuChoice>,
}

/// Grid warp of the phantom through lattice meshes, against the f64 reference.
pub fn warp(opts: &WarpBenchOptions, mut emit: impl FnMut(&BenchRow)) -> Result<(), crate::warp::WarpError> {
    use crate::warp::{self as w, WarpOptions};
    let device = cpu_description();
    let source = crate::volume::phantom::phantom(opts.dims, 1.0)?;
    let (lo, hi) = source.bounds();
    let (centre, half) = ((lo + hi) / 2.0, (hi - lo) / 2.0);
    let (vmin, vmax) = source.range();
    for &tets in &opts.tets {
        let mesh = generate::lattice_for_box(lo, hi, tets, CellSplit::Five)
            .map_err(|e| w::WarpError::BadDisplacement { index: 0, why: format!("mesh: {e}") })?;
        for &case in &opts.cases {
            let deformed = case.deform(mesh.nodes(), centre, half);
            let grid = w::default_grid(&source, &deformed);
            for &sampling in &opts.samplings {
                let reference_opts = WarpOptions { sampling, ..Default::default() };
                let (reference, _) = w::warp_samples::<f64>(&source, &mesh, &deformed, &grid, &reference_opts)?;
                for &scheme in &opts.schemes {
                    let options = WarpOptions { scheme, sampling, ..Default::default() };
                    // Settle into a buffer reused from run to run, as a publishing node does.
                    let (mut out, mut stats) = w::warp_samples::<f32>(&source, &mesh, &deformed, &grid, &options)?;
                    let mut times = Vec::with_capacity(opts.runs);
                    for _ in 0..opts.runs {
                        let start = Instant::now();
                        stats = w::warp_into::<f32>(&source, &mesh, &deformed, &grid, &options, &mut out)?;
                        times.push(start.elapsed().as_secs_f64() * 1e3);
                    }
                    let error = out.iter().zip(&reference).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max) / (vmax - vmin) as f64;
                    let median = time_stats(times.clone()).median;
                    emit(&BenchRow {
                        stage: "warp",
                        case: format!("lattice{}_{}", mesh.tets().len(), case.name()),
                        backend: "cpu".into(),
                        device: device.clone(),
                        params: json!({"scheme": format!("{scheme:?}").to_lowercase(), "sampling": format!("{sampling:?}").to_lowercase(), "dims": grid.dims}),
                        runs: times.len(),
                        time_ms: time_stats(times),
                        error: Some(ErrorMeasure { metric: "max_abs_over_range", value: error, reference: "f64" }),
                        work: json!({"voxels": stats.voxels, "inside": stats.inside, "candidates": stats.candidates,
                            "useful_fraction": stats.inside as f64 / stats.candidates.max(1) as f64,
                            "mvoxels_per_s": stats.voxels as f64 / median / 1e3}),
                    });
                }
            }
            #[cfg(feature = "gpu")]
            if let Some(choice) = opts.gpu {
                warp_gpu_rows(choice, &source, &mesh, &deformed, case, &mut emit)?;
            }
            if opts.incremental {
                // A local press: the nodes within 15 % of the half-width of the top centre sink
                // (a tool tip pressing in; a few nodes at these resolutions).
                let tip = centre + Vector3::new(0.0, 0.0, half.z);
                let radius = 0.15 * half.x;
                let pressed: Vec<Vector3<f64>> = deformed
                    .iter()
                    .zip(mesh.nodes())
                    .map(|(p, r)| {
                        let d = (r - tip).norm();
                        if d < radius { p - Vector3::z() * (0.1 * radius * (1.0 - d / radius)) } else { *p }
                    })
                    .collect();
                let options = WarpOptions::default();
                let (shared_source, shared_mesh) = (std::sync::Arc::new(source.clone()), std::sync::Arc::new(mesh.clone()));
                let mut times = Vec::with_capacity(opts.runs);
                let mut stats = w::WarpStats::default();
                for run in 0..=opts.runs {
                    let (mut inc, _) = w::IncrementalWarp::new(shared_source.clone(), shared_mesh.clone(), &deformed, grid_for(&source, &deformed, &pressed), options.clone())?;
                    let start = Instant::now();
                    stats = inc.update(&pressed, 1e-9)?;
                    if run > 0 {
                        times.push(start.elapsed().as_secs_f64() * 1e3);
                    }
                }
                emit(&BenchRow {
                    stage: "warp",
                    case: format!("lattice{}_{}_press", mesh.tets().len(), case.name()),
                    backend: "cpu".into(),
                    device: device.clone(),
                    params: json!({"scheme": "spans", "sampling": "trilinear", "incremental": true}),
                    runs: times.len(),
                    time_ms: time_stats(times),
                    error: None,
                    work: json!({"voxels": stats.voxels, "inside": stats.inside}),
                });
            }
        }
    }
    Ok(())
}

/// GPU rows: the spans scheme with trilinear sampling, including the read-back.
#[cfg(feature = "gpu")]
fn warp_gpu_rows(
    choice: crate::gpu_policy::GpuChoice,
    source: &crate::volume::Volume,
    mesh: &crate::mesh::TetMesh,
    deformed: &[Vector3<f64>],
    case: WarpCase,
    emit: &mut impl FnMut(&BenchRow),
) -> Result<(), crate::warp::WarpError> {
    use crate::gpu::warp::GpuWarper;
    use crate::warp::{self as w, WarpOptions};
    let Some(ctx) = choice.context() else { return Ok(()) };
    let device = ctx.describe();
    let warper = match GpuWarper::new(std::sync::Arc::new(ctx), source) {
        Ok(w) => w,
        Err(e) => {
            tracing::warn!("GPU warp unavailable: {e}");
            return Ok(());
        }
    };
    let grid = w::default_grid(source, deformed);
    let options = WarpOptions::default();
    let (reference, _) = w::warp_samples::<f64>(source, mesh, deformed, &grid, &options)?;
    let mut times = Vec::new();
    let mut out = Vec::new();
    for run in 0..=3 {
        let start = Instant::now();
        match warper.warp(mesh, deformed, &grid, &options) {
            Ok((data, _)) => out = data,
            Err(e) => {
                tracing::warn!("GPU warp failed: {e}");
                return Ok(());
            }
        }
        if run > 0 {
            times.push(start.elapsed().as_secs_f64() * 1e3);
        }
    }
    let (vmin, vmax) = source.range();
    let error = out.iter().zip(&reference).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max) / (vmax - vmin) as f64;
    let median = time_stats(times.clone()).median;
    emit(&BenchRow {
        stage: "warp",
        case: format!("lattice{}_{}", mesh.tets().len(), case.name()),
        backend: "gpu".into(),
        device,
        params: json!({"scheme": "spans", "sampling": "trilinear", "dims": grid.dims, "includes_readback": true}),
        runs: times.len(),
        time_ms: time_stats(times),
        error: Some(ErrorMeasure { metric: "max_abs_over_range", value: error, reference: "f64" }),
        work: json!({"voxels": grid.len(), "mvoxels_per_s": grid.len() as f64 / median / 1e3}),
    });
    Ok(())
}

/// One grid covering both states, so an incremental update never needs to grow it.
fn grid_for(source: &crate::volume::Volume, a: &[Vector3<f64>], b: &[Vector3<f64>]) -> crate::volume::Grid {
    let both: Vec<Vector3<f64>> = a.iter().chain(b).copied().collect();
    crate::warp::default_grid(source, &both)
}

/// Table row for a warp measurement.
pub fn warp_table_row(row: &BenchRow) -> String {
    format!(
        "{:<26} {:<40} {:>10.2} {:>12.0} {:>10.2e} {:>9} {:>6.3}",
        row.case,
        row.params.to_string(),
        row.time_ms.median,
        row.work.get("mvoxels_per_s").and_then(|v| v.as_f64()).unwrap_or(f64::NAN),
        row.error.as_ref().map_or(f64::NAN, |e| e.value),
        row.work.get("inside").and_then(|v| v.as_u64()).unwrap_or(0),
        row.work.get("useful_fraction").and_then(|v| v.as_f64()).unwrap_or(f64::NAN),
    )
}

pub const WARP_TABLE_HEADER: &str = "case                       params                                   median ms  Mvoxels/s      error    inside useful";
