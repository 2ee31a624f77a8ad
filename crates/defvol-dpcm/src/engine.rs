//! The DPCM surface on the run's backend: the GPU twin when the backend is a GPU (and the
//! grid fits the adapter), else the CPU surface; one interface for both.

use crate::{DpcmConfig, DpcmError, Marker, StepStats, Surface};
use defvol_gpu::backend::{Backend, RunsOn};

pub enum DpcmEngine {
    Cpu(Surface),
    #[cfg(feature = "gpu")]
    Gpu {
        surface: crate::gpu::GpuSurface,
        name: String,
        /// The initial rest heights, for the displacement.
        initial: Vec<f32>,
    },
}

impl DpcmEngine {
    /// The surface of `config` on `backend` (f32 on both, as in the seed).
    pub fn new(config: &DpcmConfig, backend: &Backend) -> Result<Self, DpcmError> {
        let surface = Surface::new(config)?;
        #[cfg(feature = "gpu")]
        {
            let gpu = backend
                .try_gpu("dpcm", |ctx| {
                    crate::gpu::GpuSurface::from_surface(ctx.clone(), &surface).map(|gpu| (gpu, ctx.describe()))
                })
                .map_err(|e| DpcmError::Gpu(e.to_string()))?;
            if let Some((gpu, name)) = gpu {
                return Ok(Self::Gpu { surface: gpu, name, initial: surface.heights() });
            }
        }
        #[cfg(not(feature = "gpu"))]
        let _ = backend;
        Ok(Self::Cpu(surface))
    }

    /// Where this stage runs.
    pub fn runs_on(&self) -> RunsOn {
        match self {
            Self::Cpu(_) => RunsOn::Cpu,
            #[cfg(feature = "gpu")]
            Self::Gpu { .. } => RunsOn::Gpu,
        }
    }

    pub fn name(&self) -> String {
        match self {
            Self::Cpu(_) => format!("cpu ({} threads)", rayon::current_num_threads()),
            #[cfg(feature = "gpu")]
            Self::Gpu { name, .. } => format!("gpu: {name}"),
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
            Self::Cpu(s) => Ok(s.heights()),
            #[cfg(feature = "gpu")]
            Self::Gpu { surface, .. } => surface.read_heights().map_err(|e| DpcmError::Gpu(e.to_string())),
        }
    }

    /// Z(n) and Z(n) minus the initial rest height.
    pub fn heights_and_displacement(&self) -> Result<(Vec<f32>, Vec<f32>), DpcmError> {
        match self {
            Self::Cpu(s) => Ok((s.heights(), s.displacement())),
            #[cfg(feature = "gpu")]
            Self::Gpu { initial, .. } => {
                let z = self.heights()?;
                let d = z.iter().zip(initial).map(|(z, r)| z - r).collect();
                Ok((z, d))
            }
        }
    }
}
