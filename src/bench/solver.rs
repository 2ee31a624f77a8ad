//! `defvol bench solver`: implicit Euler over CG tolerances, time steps and
//! preconditioners, and the explicit schemes, each against an f64 run converged to 1e-10.

use std::time::Instant;

use nalgebra::Vector3;
use serde_json::json;

use super::{cantilever_with_mesh, cpu_description, relative_error, time_stats, BenchRow, ErrorMeasure};
use crate::backend::{Backend, BackendChoice, RunsOn};
use crate::mesh::TetMesh;
use crate::solver::{Integrator, MassSpringModel, Preconditioner, SolverEngine, SolverEngineError, SolverParams};

pub struct SolverBenchOptions {
    pub sizes: Vec<usize>,
    pub steps: usize,
    /// Each resolved once (`gpu` with no usable adapter is an error).
    pub backends: Vec<BackendChoice>,
    pub allow_software_gpu: bool,
    pub tolerances: Vec<f64>,
    pub dts: Vec<f64>,
    pub explicit_dt: f64,
    /// Explicit steps per batch (one GPU submission where the solver can batch them).
    pub explicit_batch: u32,
    pub preconditioners: Vec<Preconditioner>,
}

/// A reference run's scheme and time step (its bits).
type ReferenceKey = (Integrator, u64);

struct Run {
    positions: Vec<Vector3<f64>>,
    /// The first step: the preconditioner's setup (the multigrid hierarchy, its upload), the
    /// pipelines' compilation, the first solve.
    setup_ms: f64,
    step_ms: Vec<f64>,
    cg_iterations: f64,
    backend: RunsOn,
    device: String,
    gpu: Option<super::GpuCost>,
}

/// `backend`: the run's, or `None` for the f64 reference; after a settling step the rest
/// in batches of up to `batch`, ms per step.
fn run(
    backend: Option<&Backend>,
    model: &MassSpringModel,
    params: SolverParams,
    steps: usize,
    batch: u32,
) -> Result<Run, SolverEngineError> {
    let mut engine = match backend {
        Some(backend) => SolverEngine::new(backend, model, params, Vec::new())?,
        None => SolverEngine::reference_f64(model, params, Vec::new())?,
    };
    // Settle: the first step pays for allocation, pipeline compilation, the preconditioner's
    // setup and warm caches; timed apart.
    let start = Instant::now();
    engine.step()?;
    let setup_ms = start.elapsed().as_secs_f64() * 1e3;
    let meter = backend.and_then(|b| super::GpuMeter::start(b, engine.runs_on()));
    let mut step_ms = Vec::with_capacity(steps);
    let mut iterations = 0u64;
    for first in (1..steps).step_by(batch as usize) {
        let n = batch.min((steps - first) as u32);
        let start = Instant::now();
        let report = engine.step_batch(n)?;
        step_ms.push(start.elapsed().as_secs_f64() * 1e3 / f64::from(n));
        iterations += report.cg_iterations as u64;
    }
    let gpu = meter.and_then(|m| m.finish(steps.saturating_sub(1)));
    Ok(Run {
        gpu,
        setup_ms,
        positions: engine.positions(),
        step_ms,
        cg_iterations: iterations as f64 / (steps.max(2) - 1) as f64,
        backend: engine.runs_on(),
        device: engine.name(),
    })
}

/// Implicit Euler over CG tolerances and time steps, and the explicit schemes at their
/// stable step, each against an f64 run of the same scheme and step converged to 1e-10.
pub fn solver(opts: &SolverBenchOptions, mut emit: impl FnMut(&BenchRow)) -> Result<(), SolverEngineError> {
    let device = cpu_description();
    let backends =
        opts.backends.iter().map(|b| Backend::choose(*b, opts.allow_software_gpu)).collect::<Result<Vec<_>, _>>()?;
    for &size in &opts.sizes {
        let (model, mesh) = cantilever_with_mesh(size)?;
        let tets = mesh.tets().len();
        // Named by tets, as the seed's Table 1 and the README count them.
        let case = format!("cantilever_{tets}tets");
        let mut configs: Vec<SolverParams> = Vec::new();
        for &dt in &opts.dts {
            for &tol in &opts.tolerances {
                for &preconditioner in &opts.preconditioners {
                    configs.push(SolverParams {
                        integrator: Integrator::ImplicitEuler,
                        dt,
                        cg_tolerance: tol,
                        cg_max_iterations: 5000,
                        preconditioner,
                        ..Default::default()
                    });
                }
            }
        }
        for integrator in [Integrator::ExplicitEuler, Integrator::Verlet, Integrator::VelocityVerlet] {
            configs.push(SolverParams { integrator, dt: opts.explicit_dt, ..Default::default() });
        }
        // Per (scheme, step): the f64 run's positions, or none where it was unstable.
        let mut references: Vec<(ReferenceKey, Option<Vec<Vector3<f64>>>)> = Vec::new();
        for params in configs {
            let key = (params.integrator, params.dt.to_bits());
            if !references.iter().any(|(k, _)| *k == key) {
                let tight = SolverParams { cg_tolerance: 1e-10, cg_max_iterations: 20_000, ..params.clone() };
                match run(None, &model, tight, opts.steps, 1) {
                    Ok(reference) => references.push((key, Some(reference.positions))),
                    Err(SolverEngineError::Solver(e)) => {
                        tracing::warn!("{case} {} h={}: unstable, skipped ({e})", params.integrator.name(), params.dt);
                        references.push((key, None));
                    }
                    Err(e) => return Err(e),
                }
            }
            let Some((_, Some(reference))) = references.iter().find(|(k, _)| *k == key) else { continue };
            let batch = if params.integrator == Integrator::ImplicitEuler { 1 } else { opts.explicit_batch.max(1) };
            for backend in &backends {
                let result = match run(Some(backend), &model, params.clone(), opts.steps, batch) {
                    Ok(r) => r,
                    Err(SolverEngineError::Solver(e)) => {
                        tracing::warn!("{case} {}: {e}", params.integrator.name());
                        continue;
                    }
                    Err(e) => return Err(e),
                };
                let device_name = if result.backend == RunsOn::Gpu { result.device.clone() } else { device.clone() };
                let work = run_work(&params, &model, &mesh, &result);
                emit(&BenchRow {
                    stage: "solver",
                    case: case.clone(),
                    backend: result.backend.name().into(),
                    device: device_name,
                    params: run_params(&params, opts.steps, batch, result.setup_ms),
                    runs: result.step_ms.len(),
                    time_ms: time_stats(result.step_ms),
                    error: Some(ErrorMeasure {
                        metric: "max_node_distance_over_max_displacement",
                        value: relative_error(&model, &result.positions, reference),
                        reference: "f64",
                    }),
                    work,
                    gpu: result.gpu,
                });
            }
        }
    }
    Ok(())
}

/// What a row ran (and its first step's time, the setup): the CG settings only where a
/// scheme solves a system.
fn run_params(params: &SolverParams, steps: usize, batch: u32, setup_ms: f64) -> serde_json::Value {
    let mut out =
        json!({"integrator": params.integrator.name(), "dt": params.dt, "steps": steps, "setup_ms": setup_ms});
    if params.integrator == Integrator::ImplicitEuler {
        out["cg_tolerance"] = json!(params.cg_tolerance);
        out["preconditioner"] = json!(preconditioner_name(params));
    } else {
        out["batch"] = json!(batch);
    }
    out
}

/// The mesh's size, the tets the run left inside out and, for the implicit scheme, the mean
/// CG iterations per step.
fn run_work(params: &SolverParams, model: &MassSpringModel, mesh: &TetMesh, result: &Run) -> serde_json::Value {
    let inverted = mesh.inverted(&result.positions);
    let mut out = json!({"tets": mesh.tets().len(), "nodes": model.node_count(), "springs": model.springs.len(),
        "inverted_tets": inverted.count});
    if let Some((tet, ratio)) = inverted.worst {
        out["worst_inverted_tet"] = json!({"tet": tet, "volume_over_rest": ratio});
    }
    if params.integrator == Integrator::ImplicitEuler {
        out["cg_iterations_mean"] = json!(result.cg_iterations);
    }
    out
}

/// The preconditioner a run used (on either backend); explicit schemes solve nothing.
fn preconditioner_name(params: &SolverParams) -> &'static str {
    match (params.integrator, params.preconditioner) {
        (Integrator::ImplicitEuler, Preconditioner::BlockJacobi) => "block_jacobi",
        (Integrator::ImplicitEuler, Preconditioner::Amg) => "amg",
        (Integrator::ImplicitEuler, Preconditioner::Auto) => "auto",
        _ => "none",
    }
}

/// The human table row for one measurement.
pub fn table_row(row: &BenchRow) -> String {
    let steps_per_s = if row.time_ms.median > 0.0 { 1e3 / row.time_ms.median } else { f64::INFINITY };
    format!(
        "{:<22} {:<8} {:<96} {:>10.3} {:>9.1} {:>10} {:>8}",
        row.case,
        row.backend,
        row.params.to_string(),
        row.time_ms.median,
        steps_per_s,
        row.error.as_ref().map_or("-".into(), |e| format!("{:.2e}", e.value)),
        row.work.get("cg_iterations_mean").and_then(|v| v.as_f64()).map_or("-".into(), |v| format!("{v:.1}"))
    )
}

pub const TABLE_HEADER: &str =
    "case                   backend  params                                                                                            median ms   steps/s      error   CG its";
