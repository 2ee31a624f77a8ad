//! The DPCM on whichever backend is available: the GPU twin when asked for and possible,
//! else the CPU surface.

use super::{DpcmConfig, DpcmError, Marker, StepStats, Surface};
use crate::engine::BackendChoice;
#[cfg(feature = "gpu")]
use crate::gpu_policy::GpuChoice;

pub enum DpcmEngine {
    Cpu(Surface),
    #[cfg(feature = "gpu")]
    Gpu {
        surface: crate::gpu::dpcm::GpuSurface,
        name: String,
        /// The initial rest heights, for the displacement.
        initial: Vec<f32>,
    },
}

impl DpcmEngine {
    /// `Auto` takes a hardware GPU when there is one; `Gpu` falls back to the CPU with a
    /// warning; `Cpu`/`CpuF64` run the CPU surface (it is f32 by design, as the seed).
    pub fn new(config: &DpcmConfig, backend: BackendChoice, allow_software_gpu: bool) -> Result<Self, DpcmError> {
        let surface = Surface::new(config)?;
        #[cfg(feature = "gpu")]
        if matches!(backend, BackendChoice::Auto | BackendChoice::Gpu) {
            let choice = GpuChoice { allow_software: allow_software_gpu, required: backend == BackendChoice::Gpu };
            if let Some(ctx) = choice.context() {
                let name = ctx.describe();
                match crate::gpu::dpcm::GpuSurface::from_surface(std::sync::Arc::new(ctx), &surface) {
                    Ok(gpu) => return Ok(Self::Gpu { surface: gpu, name, initial: surface.heights().to_vec() }),
                    Err(e) => tracing::warn!("GPU DPCM not used: {e}; the CPU path runs"),
                }
            }
        }
        #[cfg(not(feature = "gpu"))]
        let _ = (backend, allow_software_gpu);
        Ok(Self::Cpu(surface))
    }

    pub fn name(&self) -> String {
        match self {
            Self::Cpu(_) => format!("cpu ({} threads)", rayon::current_num_threads()),
            #[cfg(feature = "gpu")]
            Self::Gpu { name, .. } => format!("gpu {name}"),
        }
    }

    pub fn step(&mut self, markers: &[Marker]) -> StepStats {
        match self {
            Self::Cpu(s) => s.step(markers),
            #[cfg(feature = "gpu")]
            Self::Gpu { surface, .. } => surface.step(markers),
        }
    }

    /// Z(n) (read back from the GPU).
    pub fn heights(&self) -> Result<Vec<f32>, DpcmError> {
        match self {
            Self::Cpu(s) => Ok(s.heights().to_vec()),
            #[cfg(feature = "gpu")]
            Self::Gpu { surface, .. } => surface.read_heights().map_err(|e| DpcmError::Gpu(e.to_string())),
        }
    }

    /// Z(n) and Z(n) minus the initial rest height.
    pub fn heights_and_displacement(&self) -> Result<(Vec<f32>, Vec<f32>), DpcmError> {
        match self {
            Self::Cpu(s) => Ok((s.heights().to_vec(), s.displacement())),
            #[cfg(feature = "gpu")]
            Self::Gpu { initial, .. } => {
                let z = self.heights()?;
                let d = z.iter().zip(initial).map(|(z, r)| z - r).collect();
                Ok((z, d))
            }
        }
    }
}
