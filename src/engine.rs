//! One handle over the solver backends (CPU f32, CPU f64 reference, GPU), chosen at run
//! time with the adapter policy: a GPU request without a usable adapter falls back to the
//! CPU path with one log line.

use nalgebra::Vector3;

use crate::solver::{MassSpringModel, Simulation, SolverError, SolverParams, StepReport, Tool};

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BackendChoice {
    /// GPU when a hardware adapter exists, else CPU.
    Auto,
    Cpu,
    /// CPU in f64: the reference path.
    CpuF64,
    /// GPU; with --allow-software-gpu a CPU adapter (llvmpipe) counts.
    Gpu,
}

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EngineError {
    #[error(transparent)]
    Solver(#[from] SolverError),
    #[cfg(feature = "gpu")]
    #[error(transparent)]
    Gpu(#[from] crate::gpu::solver::GpuSolverError),
}

pub enum Engine {
    Cpu(Simulation<f32>),
    CpuF64(Simulation<f64>),
    #[cfg(feature = "gpu")]
    Gpu(Box<crate::gpu::solver::GpuSimulation>),
}

impl Engine {
    pub fn new(choice: BackendChoice, allow_software_gpu: bool, model: &MassSpringModel, params: SolverParams, tools: Vec<Tool>) -> Result<Self, EngineError> {
        match choice {
            BackendChoice::Cpu => Ok(Engine::Cpu(Simulation::new(model, params, tools)?)),
            BackendChoice::CpuF64 => Ok(Engine::CpuF64(Simulation::new(model, params, tools)?)),
            BackendChoice::Auto | BackendChoice::Gpu => Self::gpu_or_cpu(choice, allow_software_gpu, model, params, tools),
        }
    }

    #[cfg(feature = "gpu")]
    fn gpu_or_cpu(choice: BackendChoice, allow_software_gpu: bool, model: &MassSpringModel, params: SolverParams, tools: Vec<Tool>) -> Result<Self, EngineError> {
        let choice = crate::gpu_policy::GpuChoice { allow_software: allow_software_gpu, required: choice == BackendChoice::Gpu };
        match choice.context() {
            Some(ctx) => {
                tracing::info!("solver on GPU: {}", ctx.describe());
                let sim = crate::gpu::solver::GpuSimulation::new(std::sync::Arc::new(ctx), model, params, tools)?;
                Ok(Engine::Gpu(Box::new(sim)))
            }
            None => Ok(Engine::Cpu(Simulation::new(model, params, tools)?)),
        }
    }

    #[cfg(not(feature = "gpu"))]
    fn gpu_or_cpu(_: BackendChoice, _: bool, model: &MassSpringModel, params: SolverParams, tools: Vec<Tool>) -> Result<Self, EngineError> {
        tracing::info!("built without the `gpu` feature; running the CPU path");
        Ok(Engine::Cpu(Simulation::new(model, params, tools)?))
    }

    pub fn name(&self) -> String {
        match self {
            Engine::Cpu(_) => "cpu".into(),
            Engine::CpuF64(_) => "cpu-f64".into(),
            #[cfg(feature = "gpu")]
            Engine::Gpu(g) => format!("gpu: {}", g.context().describe()),
        }
    }

    pub fn step(&mut self) -> Result<StepReport, EngineError> {
        Ok(match self {
            Engine::Cpu(s) => s.step()?,
            Engine::CpuF64(s) => s.step()?,
            #[cfg(feature = "gpu")]
            Engine::Gpu(g) => g.step()?,
        })
    }

    pub fn tool_mut(&mut self, index: usize) -> Result<&mut Tool, SolverError> {
        match self {
            Engine::Cpu(s) => s.tool_mut(index),
            Engine::CpuF64(s) => s.tool_mut(index),
            #[cfg(feature = "gpu")]
            Engine::Gpu(g) => g.tool_mut(index),
        }
    }

    pub fn positions(&self) -> Vec<Vector3<f64>> {
        match self {
            Engine::Cpu(s) => s.positions_f64(),
            Engine::CpuF64(s) => s.positions_f64(),
            #[cfg(feature = "gpu")]
            Engine::Gpu(g) => g.mirror().positions_f64(),
        }
    }
}
