//! `defvol bench warp`: the phantom through lattice meshes (seed 003's cases), every scheme
//! and sampling against the f64 warp, the incremental update after a press, and the GPU.

use std::time::Instant;

use nalgebra::Vector3;
use serde_json::json;

use super::{cpu_description, time_stats, BenchRow, ErrorMeasure};
use crate::mesh::generate::{self, CellSplit};

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
        let rot = Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_4)
            * Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_4);
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
    /// Also run the GPU path (spans, trilinear) on this backend.
    pub gpu: Option<crate::backend::Backend>,
    /// Write each case's work (source, mesh in index space, f64 reference) here, for the
    /// peers in `benches/peers/` to run exactly the same warp.
    pub export: Option<std::path::PathBuf>,
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
                if let Some(dir) = &opts.export {
                    let name = format!("lattice{}_{}_{sampling:?}", mesh.tets().len(), case.name()).to_lowercase();
                    let work = WarpWork { source: &source, mesh: &mesh, deformed: &deformed, grid: &grid };
                    export_case(&dir.join(name), &work, &reference)
                        .map_err(|e| w::WarpError::BadDisplacement { index: 0, why: format!("export: {e}") })?;
                }
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
                    let error = out.iter().zip(&reference).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max)
                        / (vmax - vmin) as f64;
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
                        work: json!({"tets": mesh.tets().len(), "voxels": stats.voxels, "inside": stats.inside, "candidates": stats.candidates,
                            "useful_fraction": stats.inside as f64 / stats.candidates.max(1) as f64,
                            "mvoxels_per_s": stats.voxels as f64 / median / 1e3}),
                        gpu: None,
                    });
                }
            }
            #[cfg(feature = "gpu")]
            if let Some(ctx) = opts.gpu.as_ref().and_then(crate::backend::Backend::context) {
                let grid = w::default_grid(&source, &deformed);
                let work = WarpWork { source: &source, mesh: &mesh, deformed: &deformed, grid: &grid };
                for &sampling in &opts.samplings {
                    let options = WarpOptions { sampling, ..Default::default() };
                    let (reference, _) = w::warp_samples::<f64>(&source, &mesh, &deformed, &grid, &options)?;
                    warp_gpu_rows(ctx, &work, &reference, case, &options, opts.runs, &mut emit)?;
                }
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
                        if d < radius {
                            p - Vector3::z() * (0.1 * radius * (1.0 - d / radius))
                        } else {
                            *p
                        }
                    })
                    .collect();
                let options = WarpOptions::default();
                let (shared_source, shared_mesh) =
                    (std::sync::Arc::new(source.clone()), std::sync::Arc::new(mesh.clone()));
                let mut times = Vec::with_capacity(opts.runs);
                let mut stats = w::WarpStats::default();
                let grid = grid_for(&source, &deformed, &pressed);
                let mut out = vec![0f32; grid.len()];
                for run in 0..=opts.runs {
                    let mut inc = w::IncrementalWarp::new(
                        shared_source.clone(),
                        shared_mesh.clone(),
                        &deformed,
                        grid.clone(),
                        options.clone(),
                    )?;
                    inc.write_into(&mut out, None)?;
                    let start = Instant::now();
                    let sequence = inc.advance(&pressed, 1e-9)?;
                    stats = inc.write_into(&mut out, Some(sequence - 1))?;
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
                    work: json!({"tets": mesh.tets().len(), "voxels": stats.voxels, "inside": stats.inside}),
                    gpu: None,
                });
            }
        }
    }
    Ok(())
}

/// GPU rows: the spans scheme with `options`' sampling, `runs` warps each with its
/// read-back, against the f64 `reference` of the same work.
#[cfg(feature = "gpu")]
fn warp_gpu_rows(
    ctx: &std::sync::Arc<crate::gpu::GpuContext>,
    work: &WarpWork,
    reference: &[f64],
    case: WarpCase,
    options: &crate::warp::WarpOptions,
    runs: usize,
    emit: &mut impl FnMut(&BenchRow),
) -> Result<(), crate::warp::WarpError> {
    use crate::warp::gpu::GpuWarp;
    let WarpWork { source, mesh, deformed, grid } = *work;
    let device = ctx.describe();
    let warper = match GpuWarp::new(ctx.clone(), source, mesh, grid.clone(), options, 1.0) {
        Ok(w) => w,
        Err(e) => {
            tracing::warn!("GPU warp unavailable: {e}");
            return Ok(());
        }
    };
    let mut times = Vec::new();
    // Kept from run to run, as the node keeps its shared-memory samples.
    let mut out = vec![0f32; grid.len()];
    let mut meter = None;
    for run in 0..=runs.max(3) {
        if run == 1 {
            meter = Some(super::GpuMeter::on(ctx));
        }
        let start = Instant::now();
        if let Err(e) = warper.warp_into(mesh, deformed, &mut out) {
            tracing::warn!("GPU warp failed: {e}");
            return Ok(());
        }
        if run > 0 {
            times.push(start.elapsed().as_secs_f64() * 1e3);
        }
    }
    let cost = meter.and_then(|m| m.finish(times.len()));
    let (vmin, vmax) = source.range();
    let error =
        out.iter().zip(reference).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max) / (vmax - vmin) as f64;
    let median = time_stats(times.clone()).median;
    emit(&BenchRow {
        stage: "warp",
        case: format!("lattice{}_{}", mesh.tets().len(), case.name()),
        backend: "gpu".into(),
        device,
        params: json!({"scheme": "spans", "sampling": format!("{:?}", options.sampling).to_lowercase(), "dims": grid.dims,
            "includes_readback": true}),
        runs: times.len(),
        time_ms: time_stats(times),
        error: Some(ErrorMeasure { metric: "max_abs_over_range", value: error, reference: "f64" }),
        work: json!({"tets": work.mesh.tets().len(), "voxels": grid.len(), "mvoxels_per_s": grid.len() as f64 / median / 1e3}),
        gpu: cost,
    });
    Ok(())
}

/// One warp's inputs.
struct WarpWork<'a> {
    source: &'a crate::volume::Volume,
    mesh: &'a crate::mesh::TetMesh,
    deformed: &'a [Vector3<f64>],
    grid: &'a crate::volume::Grid,
}

/// Writes a warp's work as raw little-endian arrays and a `case.json` naming them: the
/// source (f32, x fastest), the tets (u32), the rest nodes in source index space and the
/// deformed ones in output index space (f64; the warp's own first step), and the f64
/// reference warp (as f32).
fn export_case(dir: &std::path::Path, work: &WarpWork, reference: &[f64]) -> std::io::Result<()> {
    // Points as f64 index triples, little-endian bytes.
    let index = |grid: &crate::volume::Grid, points: &[Vector3<f64>]| -> Vec<u8> {
        let q = points.iter().map(|p| grid.index_from_world(*p));
        q.flat_map(|q| [q.x, q.y, q.z]).flat_map(f64::to_le_bytes).collect()
    };
    let f32s = |values: &[f32]| values.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>();
    let tets: Vec<u8> = work.mesh.tets().iter().flatten().flat_map(|n| n.to_le_bytes()).collect();
    let reference: Vec<f32> = reference.iter().map(|v| *v as f32).collect();
    std::fs::create_dir_all(dir)?;
    std::fs::write(dir.join("source.f32"), f32s(work.source.data()))?;
    std::fs::write(dir.join("tets.u32"), tets)?;
    std::fs::write(dir.join("rest_index.f64"), index(&work.source.grid(), work.mesh.nodes()))?;
    std::fs::write(dir.join("deformed_index.f64"), index(work.grid, work.deformed))?;
    std::fs::write(dir.join("reference.f32"), f32s(&reference))?;
    let (low, high) = work.source.range();
    let case = json!({"source_dims": work.source.dims(), "out_dims": work.grid.dims, "tets": work.mesh.tets().len(),
        "nodes": work.mesh.nodes().len(), "background": 0.0, "source_range": [low, high]});
    std::fs::write(dir.join("case.json"), case.to_string())
}

/// One grid covering both states, so an incremental update never needs to grow it.
fn grid_for(source: &crate::volume::Volume, a: &[Vector3<f64>], b: &[Vector3<f64>]) -> crate::volume::Grid {
    let both: Vec<Vector3<f64>> = a.iter().chain(b).copied().collect();
    crate::warp::default_grid(source, &both)
}

/// Table row for a warp measurement.
pub fn warp_table_row(row: &BenchRow) -> String {
    // A figure a row does not measure (an incremental row's error, say) shows as "-".
    let cell = |v: Option<String>, width: usize| format!("{:>width$}", v.unwrap_or_else(|| "-".into()));
    let work = |key: &str| row.work.get(key).and_then(|v| v.as_f64());
    format!(
        "{:<26} {:<40} {:>10.2} {} {} {} {}",
        row.case,
        row.params.to_string(),
        row.time_ms.median,
        cell(work("mvoxels_per_s").map(|v| format!("{v:.0}")), 12),
        cell(row.error.as_ref().map(|e| format!("{:.2e}", e.value)), 10),
        cell(row.work.get("inside").and_then(|v| v.as_u64()).map(|v| v.to_string()), 9),
        cell(work("useful_fraction").map(|v| format!("{v:.3}")), 6),
    )
}

pub const WARP_TABLE_HEADER: &str = "case                       params                                   median ms  Mvoxels/s      error    inside useful";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_figure_a_row_does_not_measure_shows_as_a_dash_not_nan() {
        let row = BenchRow {
            stage: "warp",
            case: "bend incremental".into(),
            backend: "cpu".into(),
            device: "test".into(),
            params: serde_json::json!({"scheme": "spans"}),
            runs: 3,
            time_ms: crate::bench::TimeMs { min: 1.0, median: 2.0, max: 3.0 },
            error: None,
            work: serde_json::json!({"inside": 42}),
            gpu: None,
        };
        let line = warp_table_row(&row);
        assert!(!line.contains("NaN") && line.contains(" 42 ") && line.ends_with(" -"), "{line}");
    }
}
