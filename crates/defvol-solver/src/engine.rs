//! The solver on the run's backend: the GPU twin when the backend is a GPU, the CPU path
//! otherwise, and the f64 CPU reference on request; one interface for the three.

use nalgebra::Vector3;

use super::{LocalModel, MassSpringModel, Simulation, SolverError, SolverParams, StepReport, Tool};
use defvol_gpu::backend::{Backend, BackendError, RunsOn};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SolverEngineError {
    #[error(transparent)]
    Solver(#[from] SolverError),
    #[error(transparent)]
    Backend(#[from] BackendError),
    #[cfg(feature = "gpu")]
    #[error(transparent)]
    Gpu(#[from] super::gpu::GpuSolverError),
}

pub enum SolverEngine {
    Cpu(Simulation<f32>),
    /// The CPU path in f64: the reference.
    CpuF64(Simulation<f64>),
    #[cfg(feature = "gpu")]
    Gpu(Box<super::gpu::GpuSimulation>),
}

impl SolverEngine {
    /// The solver on `backend`.
    pub fn new(
        backend: &Backend,
        model: &MassSpringModel,
        params: SolverParams,
        tools: Vec<Tool>,
    ) -> Result<Self, SolverEngineError> {
        #[cfg(feature = "gpu")]
        if let Some(sim) = backend.try_gpu("solver", |ctx| {
            super::gpu::GpuSimulation::new(ctx.clone(), model, params.clone(), tools.clone())
        })? {
            return Ok(Self::Gpu(Box::new(sim)));
        }
        #[cfg(not(feature = "gpu"))]
        let _ = backend;
        Ok(Self::Cpu(Simulation::new(model, params, tools)?))
    }

    /// The f64 reference path (CPU).
    pub fn reference_f64(
        model: &MassSpringModel,
        params: SolverParams,
        tools: Vec<Tool>,
    ) -> Result<Self, SolverEngineError> {
        Ok(Self::CpuF64(Simulation::new(model, params, tools)?))
    }

    /// Where this stage runs.
    pub fn runs_on(&self) -> RunsOn {
        match self {
            Self::Cpu(_) | Self::CpuF64(_) => RunsOn::Cpu,
            #[cfg(feature = "gpu")]
            Self::Gpu(_) => RunsOn::Gpu,
        }
    }

    /// The path and its device, for logs.
    pub fn name(&self) -> String {
        match self {
            Self::Cpu(_) => format!("cpu ({} threads)", rayon::current_num_threads()),
            Self::CpuF64(_) => format!("cpu-f64 ({} threads)", rayon::current_num_threads()),
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => format!("gpu: {}", g.context().describe()),
        }
    }

    pub fn step(&mut self) -> Result<StepReport, SolverEngineError> {
        Ok(match self {
            Self::Cpu(s) => s.step()?,
            Self::CpuF64(s) => s.step()?,
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => g.step()?,
        })
    }

    /// `steps` steps, explicit ones in one GPU submission where the GPU solver can batch
    /// them (see [`super::gpu::GpuSimulation::step_batch`]); the last step's report.
    pub fn step_batch(&mut self, steps: u32) -> Result<StepReport, SolverEngineError> {
        match self {
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => Ok(g.step_batch(steps)?),
            _ => {
                let mut report = Err(crate::empty_batch());
                for _ in 0..steps {
                    report = Ok(self.step()?);
                }
                Ok(report?)
            }
        }
    }

    pub fn tool_mut(&mut self, index: usize) -> Result<&mut Tool, SolverError> {
        match self {
            Self::Cpu(s) => s.tool_mut(index),
            Self::CpuF64(s) => s.tool_mut(index),
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => g.tool_mut(index),
        }
    }

    /// Puts coupled tool `index`'s simulated tool at its device, at rest (its device's first
    /// pose).
    pub fn seat_simulated_tool(&mut self, index: usize) {
        match self {
            Self::Cpu(s) => s.seat_simulated_tool(index),
            Self::CpuF64(s) => s.seat_simulated_tool(index),
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => g.seat_simulated_tool(index),
        }
    }

    /// Each coupled tool's local model for the force loop, from the last step
    /// (`haptic.rs`), each backend solving its own system for the contact's stiffness.
    pub fn local_models(&mut self) -> Result<Vec<LocalModel>, SolverEngineError> {
        Ok(match self {
            Self::Cpu(s) => s.local_models(),
            Self::CpuF64(s) => s.local_models(),
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => g.local_models().map_err(super::gpu::GpuSolverError::from)?,
        })
    }

    /// Positions after the last step (world units).
    pub fn positions(&self) -> Vec<Vector3<f64>> {
        match self {
            Self::Cpu(s) => s.positions_f64(),
            Self::CpuF64(s) => s.positions_f64(),
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => g.mirror().positions_f64(),
        }
    }

    /// On the GPU: the device buffer of node displacements from rest (one `vec4<f32>` per
    /// node, world units), which the warp and the mesh raycaster read where it is.
    #[cfg(feature = "gpu")]
    pub fn device_displacements(&self) -> Option<&wgpu::Buffer> {
        match self {
            Self::Gpu(g) => Some(g.displacements()),
            _ => None,
        }
    }
}
