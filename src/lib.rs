//! defvol: deformable volumes for robot and surgical-simulation stacks.
//!
//! `ARCHITECTURE.md` draws the layers. From the ground up: [`math`] (the scalar type);
//! the data, [`mesh`] and [`volume`], and [`io`] for their files; [`gpu`], the wgpu plumbing
//! that knows no stage; the stages, each one folder with its CPU path, its GPU host code,
//! its shader and their agreement tests: [`solver`], [`warp`], [`dpcm`], [`render`];
//! [`backend`], the one CPU-or-GPU choice a run hands every stage; [`scene`], what a run
//! loads; [`pipeline`], the stages chained for the node without ROS; then the records and
//! the wire: [`msgs`], [`record`], [`session`], [`shm`], [`ros`]; and [`bench`](mod@bench).

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

pub mod backend;
pub mod bench;
pub mod dpcm;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod io;
pub mod math;
pub mod mesh;
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
pub mod volume;
pub mod warp;
