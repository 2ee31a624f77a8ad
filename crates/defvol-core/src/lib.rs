//! defvol's ground crate: what every stage stands on and nothing above it.
//!
//! [`math`], the scalar type; the data, [`mesh`] (tetrahedral meshes) and [`volume`]
//! (scalar volumes on ITK's voxel grid); and [`io`], their files. It knows no GPU, no stage
//! and nothing of ROS: Cargo holds it to that, since it depends on none of them.

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

pub mod io;
pub mod math;
pub mod mesh;
pub mod volume;
