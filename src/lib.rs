//! defvol: deformable volumes for robot and surgical-simulation stacks.
//!
//! `ARCHITECTURE.md` draws the layers. From the ground up, re-exported here under their own
//! names: in the ground crate `defvol-core`, [`math`] (the scalar type), the data, [`mesh`]
//! and [`volume`], and [`io`] for their files; in the plumbing crate `defvol-gpu`, [`gpu`],
//! the wgpu plumbing that knows no stage, and [`backend`], the one CPU-or-GPU choice a run
//! hands every stage. Then the stages, a crate each with its CPU path, its GPU host code, its
//! shader and their agreement tests: [`solver`], [`warp`], [`dpcm`], [`render`]. In this
//! crate: [`scene`], what a run loads; [`pipeline`], the stages chained for the node without
//! ROS; then the records and the wire: [`msgs`], [`record`], [`session`], [`shm`], [`ros`];
//! and [`bench`](mod@bench).

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

pub use defvol_core::{io, math, mesh, volume};
pub use defvol_dpcm as dpcm;
pub use defvol_gpu::backend;
#[cfg(feature = "gpu")]
pub use defvol_gpu::gpu;
pub use defvol_render as render;
pub use defvol_solver as solver;
pub use defvol_warp as warp;

pub mod bench;
pub mod logging;
pub mod msgs;
pub mod pipeline;
pub mod record;
pub mod ros;
pub mod scene;
pub mod session;
#[cfg(feature = "shm")]
pub mod shm;
