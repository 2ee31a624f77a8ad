//! Criterion: the surface contact's cost per query against the mesh's size. A 2 mm sphere
//! pressed 1 mm into the top of the cantilever bar (as a step's detection sees it between
//! refits), and the whole-surface refit the hierarchy gets once the nodes drift half a
//! spacing: the first should stay flat from 5,000 to 50,000 tets, the second grows.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use defvol::bench::cantilever;
use defvol::solver::contact::{ContactParams, Surface, ToolCore};
use nalgebra::Vector3;

fn contact(c: &mut Criterion) {
    let mut group = c.benchmark_group("surface_contact");
    for size in [5_000, 50_000] {
        let Ok(model) = cantilever(size) else { continue };
        let mut surface = Surface::new(&model.boundary, &model.rest);
        let top = model.rest.iter().map(|p| p.z).fold(f64::NEG_INFINITY, f64::max);
        let centre = Vector3::new(0.15, 0.03, top + 0.001);
        let tool =
            ToolCore { tool: 0, core: ContactParams { a: centre, b: centre, radius: 0.002, stiffness: 20_000.0 } };
        let x = &model.rest[..];
        group.bench_with_input(BenchmarkId::new("detect", size), &size, |b, _| {
            b.iter(|| surface.detect(std::slice::from_ref(&tool), x, 0.001))
        });
        group.bench_with_input(BenchmarkId::new("refit", size), &size, |b, _| b.iter(|| surface.refit(x)));
    }
    group.finish();
}

criterion_group!(benches, contact);
criterion_main!(benches);
