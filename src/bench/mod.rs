//! `defvol bench`: run time against error, one JSON object per measurement
//! (format in `docs/conventions.md`), plus a human table.

pub mod dpcm;
pub mod node;
pub mod render;
mod solver;
mod warp;

pub use solver::{solver, table_row, SolverBenchOptions, TABLE_HEADER};
pub use warp::{warp, warp_table_row, WarpBenchOptions, WarpCase, WARP_TABLE_HEADER};

use nalgebra::Vector3;
use serde::Serialize;

use crate::mesh::generate::{self, CellSplit};
use crate::solver::{FixedNodes, MassSpringModel, Material, SolverError};

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
    Ok(cantilever_with_tets(target_tets)?.0)
}

/// [`cantilever`] and how many tets its mesh has (the lattice's nearest to the target).
pub fn cantilever_with_tets(target_tets: usize) -> Result<(MassSpringModel, usize), SolverError> {
    let mesh = if target_tets <= 80 {
        generate::bar(0.3)
    } else {
        generate::lattice_for_box(Vector3::zeros(), Vector3::new(0.3, 0.06, 0.06), target_tets, CellSplit::Five)
    }
    .map_err(|e| SolverError::BadParameter {
        name: "mesh".into(),
        value: target_tets as f64,
        why: e.to_string(),
    })?;
    let fixed = FixedNodes::Plane { normal: [1.0, 0.0, 0.0], offset: 0.0 }.select(mesh.nodes())?;
    let material = Material::Uniform { stiffness: 1000.0, damping: 0.5 };
    Ok((MassSpringModel::new(&mesh, &material, 1000.0, &fixed, None)?, mesh.tets().len()))
}

pub fn cpu_description() -> String {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_owned())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_owned());
    format!("{model}, {} threads", rayon::current_num_threads())
}

/// Relative error of `positions` against `reference`: max node distance / max displacement.
pub fn relative_error(model: &MassSpringModel, positions: &[Vector3<f64>], reference: &[Vector3<f64>]) -> f64 {
    let scale = reference.iter().zip(&model.rest).map(|(r, x0)| (r - x0).norm()).fold(0.0, f64::max);
    let worst = positions.iter().zip(reference).map(|(p, r)| (p - r).norm()).fold(0.0, f64::max);
    worst / scale.max(f64::MIN_POSITIVE)
}
