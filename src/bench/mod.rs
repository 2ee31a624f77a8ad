//! `defvol bench`: run time against error, one JSON object per measurement
//! (format in `docs/conventions.md`), plus a human table.

pub mod dpcm;
pub mod node;
pub mod render;
pub mod report;
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
    /// A GPU row's round trips per step or frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu: Option<GpuCost>,
}

/// Where a GPU row's time went, per step or frame: GPU time by timestamp queries (where the
/// adapter has them) and the round trips the plumbing counted.
#[derive(Debug, Clone, Serialize)]
pub struct GpuCost {
    pub kernel_ms: Option<f64>,
    pub copy_ms: Option<f64>,
    pub submissions: f64,
    pub readbacks: f64,
    pub bytes_read_back: f64,
    /// "available" or "unavailable" on this adapter; "off" where the node times nothing
    /// (its DDS rows, counted from its diagnostics).
    pub timestamps: &'static str,
}

/// Measures a GPU row: timing on and the counters noted from start to `finish`.
pub struct GpuMeter<'a> {
    #[cfg(feature = "gpu")]
    ctx: &'a crate::gpu::GpuContext,
    #[cfg(feature = "gpu")]
    counters: crate::gpu::GpuCounters,
    #[cfg(not(feature = "gpu"))]
    _backend: std::marker::PhantomData<&'a ()>,
}

impl<'a> GpuMeter<'a> {
    /// A meter for a row whose stage runs `on` this `backend`: none unless on its GPU.
    pub fn start(backend: &'a crate::backend::Backend, on: crate::backend::RunsOn) -> Option<Self> {
        #[cfg(feature = "gpu")]
        return backend.context().filter(|_| on == crate::backend::RunsOn::Gpu).map(|ctx| Self::on(ctx));
        #[cfg(not(feature = "gpu"))]
        {
            let _ = (backend, on);
            None
        }
    }

    /// Starts measuring what `ctx` does. Times measured before are dropped; a failure to
    /// read them is `finish`'s to report, as it reads the same queries.
    #[cfg(feature = "gpu")]
    pub fn on(ctx: &'a crate::gpu::GpuContext) -> Self {
        let _ = ctx.take_times();
        ctx.set_timing(true);
        Self { ctx, counters: ctx.counters() }
    }

    /// What was done since the start, over `units` steps or frames (none, with a warning,
    /// when the timestamps cannot be read).
    pub fn finish(self, units: usize) -> Option<GpuCost> {
        #[cfg(feature = "gpu")]
        {
            self.ctx.set_timing(false);
            let counted = self.ctx.counters().since(&self.counters);
            let times = self.ctx.take_times().map_err(|e| tracing::warn!("reading GPU timestamps failed: {e}")).ok()?;
            let per = |x: f64| x / units.max(1) as f64;
            Some(GpuCost {
                kernel_ms: times.map(|t| per(t.kernel_ms)),
                copy_ms: times.map(|t| per(t.copy_ms)),
                submissions: per(counted.submissions as f64),
                readbacks: per(counted.readbacks as f64),
                bytes_read_back: per(counted.bytes_read_back as f64),
                timestamps: self.ctx.timestamps().name(),
            })
        }
        #[cfg(not(feature = "gpu"))]
        {
            let _ = units;
            None
        }
    }
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
    Ok(cantilever_with_mesh(target_tets)?.0)
}

/// [`cantilever`] and its mesh (the lattice's nearest to the target in tets).
pub fn cantilever_with_mesh(target_tets: usize) -> Result<(MassSpringModel, crate::mesh::TetMesh), SolverError> {
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
    Ok((MassSpringModel::new(&mesh, &material, 1000.0, &fixed, None)?, mesh))
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
