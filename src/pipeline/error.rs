//! What can stop the pipeline: each stage's error, named by its stage.

use crate::backend::BackendError;
use crate::dpcm::DpcmError;
use crate::render::engine::RenderEngineError;
use crate::render::RenderError;
use crate::scene::SceneError;
use crate::solver::{SolverEngineError, SolverError};
use crate::volume::VolumeError;
use crate::warp::engine::WarpEngineError;
use crate::warp::WarpError;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PipelineError {
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error("solver: {0}")]
    Engine(#[from] SolverEngineError),
    #[error(transparent)]
    Backend(#[from] BackendError),
    #[error("warp: {0}")]
    WarpEngine(#[from] WarpEngineError),
    #[error("raycast: {0}")]
    RenderEngine(#[from] RenderEngineError),
    #[error("solver: {0}")]
    Solver(#[from] SolverError),
    #[error("warp: {0}")]
    Warp(#[from] WarpError),
    #[error("DPCM: {0}")]
    Dpcm(#[from] DpcmError),
    #[error("raycast: {0}")]
    Render(#[from] RenderError),
    #[error("volume: {0}")]
    Volume(#[from] VolumeError),
    #[error("scene: {0}")]
    Invalid(String),
}
