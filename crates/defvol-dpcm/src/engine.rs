//! The DPCM surface on the run's backend: the GPU twin when the backend is a GPU (and the
//! grid fits the adapter), else the CPU surface; one interface for both.

use crate::{DpcmConfig, DpcmError, Marker, StepStats, Surface};
use defvol_gpu::backend::{Backend, RunsOn};

pub enum DpcmEngine {
    Cpu(Box<Surface>),
    #[cfg(feature = "gpu")]
    Gpu {
        surface: Box<crate::gpu::GpuSurface>,
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
                return Ok(Self::Gpu { surface: Box::new(gpu), name, initial: surface.heights() });
            }
        }
        #[cfg(not(feature = "gpu"))]
        let _ = backend;
        Ok(Self::Cpu(Box::new(surface)))
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

    pub fn step(&mut self, markers: &[Marker]) -> Result<StepStats, DpcmError> {
        self.step_many(markers, 1, 1)
    }

    /// `steps` steps under the same markers, up to `batch` of them to a GPU submission;
    /// the last step's stats (none for no steps).
    pub fn step_many(&mut self, markers: &[Marker], steps: usize, batch: usize) -> Result<StepStats, DpcmError> {
        if batch == 0 {
            return Err(DpcmError::BadParameter {
                name: "batch".into(),
                value: 0.0,
                why: "a batch is at least one step".into(),
            });
        }
        match self {
            Self::Cpu(s) => Ok((0..steps).map(|_| s.step(markers)).last().unwrap_or_default()),
            #[cfg(feature = "gpu")]
            Self::Gpu { surface, .. } => {
                let mut last = StepStats::default();
                for start in (0..steps).step_by(batch) {
                    let batch = vec![markers; batch.min(steps - start)];
                    let stats = surface.step_batch(&batch).map_err(|e| DpcmError::Gpu(e.to_string()))?;
                    last = stats.last().copied().unwrap_or_default();
                }
                Ok(last)
            }
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
