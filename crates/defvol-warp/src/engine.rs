//! The node's warp on the run's backend, kept up to date as the mesh moves: the
//! incremental CPU warp, or the GPU warp reading the deformed nodes where they are. One
//! interface: [`WarpEngine::advance`] to new positions, [`WarpEngine::write_into`] any
//! buffer (a shared-memory sample, a host copy), and on the GPU the output on the device.

use std::sync::Arc;

use nalgebra::Vector3;

use crate::{IncrementalWarp, WarpError, WarpOptions, WarpStats};
use defvol_core::mesh::TetMesh;
use defvol_core::volume::{Grid, Volume};
use defvol_gpu::backend::{Backend, BackendError, RunsOn};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WarpEngineError {
    #[error(transparent)]
    Warp(#[from] WarpError),
    #[error(transparent)]
    Backend(#[from] BackendError),
    #[cfg(feature = "gpu")]
    #[error(transparent)]
    Gpu(#[from] crate::gpu::GpuWarpError),
    #[error("the CPU warp needs the deformed positions on the host")]
    NoPositions,
}

pub enum WarpEngine {
    Cpu {
        warp: Box<IncrementalWarp>,
        rest: Arc<TetMesh>,
        to_file: f64,
        /// Nodes that moved less than this (the source's units) leave their tets alone.
        tolerance: f64,
    },
    #[cfg(feature = "gpu")]
    Gpu { warp: Box<crate::gpu::GpuWarp>, sequence: u64 },
}

impl WarpEngine {
    /// `source` through `rest` (in the source's units) onto `grid`. Positions come as
    /// displacements from rest in the units of whoever moves the mesh; `to_file` scales
    /// them to the source's. `tolerance` (source units) is the CPU warp's: nodes moving
    /// less leave their tets' voxels alone.
    pub fn new(
        backend: &Backend,
        source: Arc<Volume>,
        rest: Arc<TetMesh>,
        grid: Grid,
        options: WarpOptions,
        to_file: f64,
        tolerance: f64,
    ) -> Result<Self, WarpEngineError> {
        #[cfg(feature = "gpu")]
        if let Some(warp) = backend.try_gpu("warp", |ctx| {
            crate::gpu::GpuWarp::new(ctx.clone(), &source, &rest, grid.clone(), &options, to_file)
        })? {
            warp.place_host(&vec![Vector3::zeros(); rest.nodes().len()])?;
            warp.run();
            return Ok(Self::Gpu { warp: Box::new(warp), sequence: 0 });
        }
        #[cfg(not(feature = "gpu"))]
        let _ = backend;
        let warp = IncrementalWarp::new(source, rest.clone(), rest.nodes(), grid, options)?;
        Ok(Self::Cpu { warp: Box::new(warp), rest, to_file, tolerance })
    }

    /// Where this stage runs.
    pub fn runs_on(&self) -> RunsOn {
        match self {
            Self::Cpu { .. } => RunsOn::Cpu,
            #[cfg(feature = "gpu")]
            Self::Gpu { .. } => RunsOn::Gpu,
        }
    }

    pub fn grid(&self) -> &Grid {
        match self {
            Self::Cpu { warp, .. } => warp.grid(),
            #[cfg(feature = "gpu")]
            Self::Gpu { warp, .. } => warp.grid(),
        }
    }

    /// The warp the last positions describe.
    pub fn sequence(&self) -> u64 {
        match self {
            Self::Cpu { warp, .. } => warp.sequence(),
            #[cfg(feature = "gpu")]
            Self::Gpu { sequence, .. } => *sequence,
        }
    }

    /// On the GPU: where another stage places the deformed nodes (then [`Self::advance`]
    /// with no host positions).
    #[cfg(feature = "gpu")]
    pub fn device_nodes(&self) -> Option<&Arc<defvol_gpu::gpu::DeviceNodes>> {
        match self {
            Self::Gpu { warp, .. } => Some(warp.nodes()),
            Self::Cpu { .. } => None,
        }
    }

    /// On the GPU: the warped samples on the device, after [`Self::advance`].
    #[cfg(feature = "gpu")]
    pub fn device_output(&self) -> Option<&wgpu::Buffer> {
        match self {
            Self::Gpu { warp, .. } => Some(warp.output()),
            Self::Cpu { .. } => None,
        }
    }

    /// Warps to new positions: `displacements` from rest on the host, or (GPU only) `None`
    /// when the nodes were placed on the device. Returns the new sequence.
    pub fn advance(&mut self, displacements: Option<&[Vector3<f64>]>) -> Result<u64, WarpEngineError> {
        match self {
            Self::Cpu { warp, rest, to_file, tolerance } => {
                let u = displacements.ok_or(WarpEngineError::NoPositions)?;
                if u.len() != rest.nodes().len() {
                    return Err(WarpError::NodeCount { got: u.len(), expected: rest.nodes().len() }.into());
                }
                let deformed: Vec<Vector3<f64>> = rest.nodes().iter().zip(u).map(|(r, u)| r + u * *to_file).collect();
                Ok(warp.advance(&deformed, *tolerance)?)
            }
            #[cfg(feature = "gpu")]
            Self::Gpu { warp, sequence } => {
                if let Some(u) = displacements {
                    warp.place_host(u)?;
                }
                warp.run();
                *sequence += 1;
                Ok(*sequence)
            }
        }
    }

    /// Brings `out` to the current warp; `holds`: the sequence of the warp `out` holds, if
    /// any (the CPU then re-warps only what moved since; the GPU reads the whole volume
    /// back into it).
    pub fn write_into(&self, out: &mut [f32], holds: Option<u64>) -> Result<WarpStats, WarpEngineError> {
        match self {
            Self::Cpu { warp, .. } => Ok(warp.write_into(out, holds)?),
            #[cfg(feature = "gpu")]
            Self::Gpu { warp, sequence } => {
                if holds == Some(*sequence) {
                    return Ok(WarpStats::default());
                }
                Ok(warp.read_into(out)?)
            }
        }
    }

    /// The work of the last warp on the device, or the CPU's skipped tets.
    pub fn stats(&self) -> Result<WarpStats, WarpEngineError> {
        match self {
            Self::Cpu { warp, .. } => Ok(WarpStats {
                voxels: warp.grid().len() as u64,
                skipped_tets: warp.skipped_tets(),
                ..Default::default()
            }),
            #[cfg(feature = "gpu")]
            Self::Gpu { warp, .. } => Ok(warp.stats()?),
        }
    }
}
