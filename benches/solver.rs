//! Criterion: one implicit Euler step (h = 0.01 s, k = 1000 N/m cantilever under gravity) per
//! mesh size and backend, after settling the simulation for 10 steps so CG warm starts are
//! in their steady state. The GPU rows run on a hardware adapter, or on a software one
//! with DEFVOL_BENCH_SOFTWARE_GPU=1.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use defvol::backend::{Backend, BackendChoice};
use defvol::bench::cantilever;
use defvol::solver::{Integrator, SolverEngine, SolverParams};

fn solver(c: &mut Criterion) {
    let sizes: Vec<usize> = std::env::var("DEFVOL_BENCH_SIZES")
        .ok()
        .map(|s| s.split(',').filter_map(|v| v.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![80, 14_000, 35_000]);
    let software = std::env::var_os("DEFVOL_BENCH_SOFTWARE_GPU").is_some();
    // The GPU rows only where an adapter opens: the CPU row covers a machine without one.
    let mut backends = vec![Backend::cpu()];
    backends.extend(Backend::choose(BackendChoice::Gpu, software).ok());
    let mut group = c.benchmark_group("solver_step");
    group.sample_size(10);
    for size in sizes {
        let Ok(model) = cantilever(size) else { continue };
        for integrator in Integrator::ALL {
            let dt = if integrator == Integrator::ImplicitEuler { 0.01 } else { 5e-6 };
            let params = SolverParams { integrator, dt, ..Default::default() };
            for backend in &backends {
                let Ok(mut engine) = SolverEngine::new(backend, &model, params.clone(), Vec::new()) else { continue };
                let settled = (0..10).all(|_| engine.step().is_ok());
                if !settled {
                    continue;
                }
                let label = format!("{}/{}", integrator.name(), engine.runs_on());
                group.bench_with_input(BenchmarkId::new(label, size), &size, |b, _| b.iter(|| engine.step()));
            }
        }
    }
    group.finish();
}

criterion_group!(benches, solver);
criterion_main!(benches);
