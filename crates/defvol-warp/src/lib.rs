//! Grid warp (seed 003): the source volume resampled through a deformed tetrahedral mesh.
//!
//! Each output voxel x₁ inside a deformed tet takes the source value at x₀, the point with
//! the same barycentric coordinates in the rest tet. Per tet both mappings fold into one
//! affine map from output voxel index to source voxel index, and the barycentric
//! coordinates into four affine functions of the output index, all computed in f64.
//!
//! Rasterization schemes (all make the same inside decisions, b_m ≥ 0 for all m, evaluated
//! by the same expression):
//! - `Spans` (the default): per row of the tet's box, the exact interval where all four
//!   barycentric coordinates are non-negative; only inside voxels are visited.
//! - `Culling`: the seed's 8-bit half-space masks on coarse points every 8 voxels; cells
//!   whose 8 corner masks share a bit are skipped, the rest tested voxel by voxel.
//! - `Bbox`: every voxel of the tet's box tested (the seed's baseline).
//!
//! Output slices are processed in parallel, each visiting the tets that overlap it in tet
//! order, so a run is deterministic and a voxel on a shared face takes the later tet's value.
//! `kernels.rs` holds the per-tet and per-voxel arithmetic (the twin of `warp.wgsl`),
//! `cpu.rs` the CPU path, `gpu.rs` the GPU one, and [`engine`] runs either.

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

pub use defvol_core::volume::bspline;
mod cpu;
pub mod engine;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod kernels;

use serde::{Deserialize, Serialize};

pub use bspline::DisplacementVolume;
pub use defvol_core::volume::trilinear;
use defvol_core::volume::VolumeError;
pub use defvol_core::volume::{tricubic, Sampling, SAMPLE_TOLERANCE};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WarpError {
    #[error("{got} deformed positions for a mesh of {expected} nodes")]
    NodeCount { got: usize, expected: usize },
    #[error("deformed node {node} is not finite")]
    NonFiniteNode { node: usize },
    #[error("output grid {dims:?} needs {needed_mib} MiB, above the limit of {limit_mib} MiB")]
    TooLarge { dims: [usize; 3], needed_mib: u64, limit_mib: u64 },
    #[error("displacement volume {index}: {why}")]
    BadDisplacement { index: usize, why: String },
    #[error("output buffer holds {got} samples; the grid has {expected}")]
    BufferSize { got: usize, expected: usize },
    #[error(transparent)]
    Volume(#[from] VolumeError),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Scheme {
    Spans,
    Culling,
    Bbox,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WarpOptions {
    pub scheme: Scheme,
    pub sampling: Sampling,
    /// Value of output voxels outside every deformed tet.
    pub background: f32,
    /// Output voxels no tet covers keep the source's value there (for meshes covering
    /// part of the volume) instead of the background.
    pub keep_uncovered: bool,
    pub displacements: Vec<DisplacementVolume>,
    /// Refuse output grids larger than this (bytes of f32 samples).
    pub max_bytes: u64,
    /// Which inner loops run on the CPU (the GPU has one kernel).
    pub path: WarpPath,
}

/// The CPU warp's inner loops: the fast ones, or the simplest (the scalar twin of
/// `warp.wgsl`, one voxel and one output slice at a time), which the fast path is tested
/// against bit for bit and which rules the lanes out where a result is in doubt.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WarpPath {
    /// Eight-lane samples where the CPU has AVX2, tets through 1 MiB slabs of slices.
    #[default]
    Fast,
    Scalar,
}

impl Default for WarpOptions {
    fn default() -> Self {
        Self {
            scheme: Scheme::Spans,
            sampling: Sampling::Trilinear,
            background: 0.0,
            keep_uncovered: false,
            displacements: Vec::new(),
            max_bytes: 4 << 30,
            path: WarpPath::Fast,
        }
    }
}

/// Work done by one warp.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct WarpStats {
    pub voxels: u64,
    /// Voxels whose barycentric coordinates were evaluated.
    pub candidates: u64,
    /// Voxel writes from inside a tet.
    pub inside: u64,
    /// Deformed tets skipped as inverted or degenerate.
    pub skipped_tets: u64,
}

impl std::ops::AddAssign for WarpStats {
    fn add_assign(&mut self, o: Self) {
        self.voxels += o.voxels;
        self.candidates += o.candidates;
        self.inside += o.inside;
        self.skipped_tets += o.skipped_tets;
    }
}

pub use cpu::*;
pub use kernels::{tet_maps, Sampler, TetMap, CELL, INSIDE_TOLERANCE};
