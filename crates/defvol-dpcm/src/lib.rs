//! The dynamic particle coating method (seed 004): a grid of phyxels, each a mass on a
//! one-dimensional link to its fixed point, coupled to its neighbours and engraved by
//! markers that push it one way.
//!
//! Heights Z are the distance from a phyxel's fixed point to its mass (metres), Z = rest
//! height at rest; the state is kept as u = Z - rest height, exactly 0 at rest. [`Surface`] runs the CPU path (`cpu.rs`, rayon over bands of rows, each phyxel
//! stepped by `kernels.rs`); the GPU twin is `gpu.rs` with `dpcm.wgsl`, and [`engine`] runs either. Markers are binned into [`kernels::TILE`]² tiles, so a step costs the grid
//! plus each marker's footprint, never grid × markers.

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

mod config;
mod cpu;
pub mod engine;
mod error;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod kernels;
pub mod markers;
pub mod render;
mod texture;

pub use config::*;
pub use cpu::*;
pub use error::DpcmError;
pub use texture::{load_texture, ParamTexture, TexturedParameter};
