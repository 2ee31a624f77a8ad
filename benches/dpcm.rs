//! Criterion: one DPCM step on the seed's 1100 x 1100 grid (the water preset's eight
//! damped neighbour links) with 1 and 300 wandering markers, after 50 settling steps so the
//! waves cover the grid. `defvol bench dpcm` has the full table and the GPU rows.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use defvol::bench::dpcm::{bench_config, Physics};
use defvol::dpcm::{Surface, Topology};

fn dpcm(c: &mut Criterion) {
    let mut group = c.benchmark_group("dpcm_step_1100x1100");
    group.sample_size(50);
    for (physics, name) in [(Physics::Elastic, "elastic"), (Physics::Plastic, "plastic")] {
        for markers in [1, 300] {
            let Ok(config) = bench_config([1100, 1100], Topology::Eight, physics, markers) else { continue };
            let Ok(mut surface) = Surface::new(&config) else { continue };
            let mut step = 0u64;
            let mut advance = |surface: &mut Surface| {
                let t = step as f64 * config.dt;
                step += 1;
                surface.step(&config.script.markers_at(&config, t))
            };
            for _ in 0..50 {
                advance(&mut surface);
            }
            group.bench_with_input(BenchmarkId::new(name, markers), &markers, |b, _| b.iter(|| advance(&mut surface)));
        }
    }
    group.finish();
}

criterion_group!(benches, dpcm);
criterion_main!(benches);
