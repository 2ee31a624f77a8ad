//! defvol: deformable volumes for robot and surgical-simulation stacks.
//!
//! The algorithms live here, independent of ROS: [`mesh`] and [`volume`] hold the data,
//! [`io`] reads and writes it, [`solver`] deforms meshes, [`dpcm`] engraves phyxel surfaces, [`gpu`] runs the same kernels
//! through wgpu, [`scene`] describes a run and [`bench`] measures it. [`pipeline`] chains the
//! stages for the node, [`msgs`] are the ROS messages, [`record`] writes MCAP and rerun
//! logs, and [`session`] ties a run to its records.

pub mod bench;
pub mod dpcm;
pub mod engine;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod gpu_policy;
pub mod io;
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
