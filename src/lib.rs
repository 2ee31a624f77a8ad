//! defvol: deformable volumes for robot and surgical-simulation stacks.
//!
//! `ARCHITECTURE.md` draws the layers. From the ground up, in the ground crate `defvol-core`
//! and re-exported here under their own names: [`math`] (the scalar type); the data, [`mesh`]
//! and [`volume`], and [`io`] for their files. Then, in this crate: [`gpu`], the wgpu plumbing
//! that knows no stage; the stages, each one folder with its CPU path, its GPU host code,
//! its shader and their agreement tests: [`solver`], [`warp`], [`dpcm`], [`render`];
//! [`backend`], the one CPU-or-GPU choice a run hands every stage; [`scene`], what a run
//! loads; [`pipeline`], the stages chained for the node without ROS; then the records and
//! the wire: [`msgs`], [`record`], [`session`], [`shm`], [`ros`]; and [`bench`](mod@bench).

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

pub use defvol_core::{io, math, mesh, volume};

pub mod backend;
pub mod bench;
pub mod dpcm;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod msgs;
pub mod pipeline;
pub mod record;
pub mod render;
pub mod ros;
pub mod scene;
pub mod session;
#[cfg(feature = "shm")]
pub mod shm;
pub mod solver;
pub mod warp;
