//! Criterion: one implicit Euler step (h = 0.01 s, k = 1000 N/m cantilever under gravity) per
//! mesh size and backend, after settling the simulation for 10 steps so CG warm starts are
//! in their steady state. The GPU rows run on a hardware adapter, or on a software one
//! with DEFVOL_BENCH_SOFTWARE_GPU=1.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use defvol::bench::cantilever;
use defvol::engine::{BackendChoice, Engine};
use defvol::solver::{Integrator, SolverParams};

fn solver(c: &mut Criterion) {
    let sizes: Vec<usize> = std::env::var("DEFVOL_BENCH_SIZES")
        .ok()
        .map(|s| s.split(',').filter_map(|v| v.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![80, 14_000, 35_000]);
    let software = std::env::var_os("DEFVOL_BENCH_SOFTWARE_GPU").is_some();
    let mut group = c.benchmark_group("solver_step");
    group.sample_size(10);
    for size in sizes {
        let Ok(model) = cantilever(size) else { continue };
        for integrator in Integrator::ALL {
            let dt = if integrator == Integrator::ImplicitEuler { 0.01 } else { 5e-6 };
            let params = SolverParams { integrator, dt, ..Default::default() };
            for backend in [BackendChoice::Cpu, BackendChoice::Gpu] {
                let Ok(mut engine) = Engine::new(backend, software, &model, params.clone(), Vec::new()) else { continue };
                if backend == BackendChoice::Gpu && engine.name() == "cpu" {
                    continue; // no adapter: the CPU row already covers it
                }
                let settled = (0..10).all(|_| engine.step().is_ok());
                if !settled {
                    continue;
                }
                let label = format!("{}/{}", integrator.name(), if backend == BackendChoice::Cpu { "cpu" } else { "gpu" });
                group.bench_with_input(BenchmarkId::new(label, size), &size, |b, _| b.iter(|| engine.step()));
            }
        }
    }
    group.finish();
}

criterion_group!(benches, solver);
criterion_main!(benches);
