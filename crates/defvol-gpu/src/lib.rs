//! defvol's GPU plumbing and the backend choice: what every stage shares to run on the GPU,
//! knowing no stage.
//!
//! [`backend`] resolves a run's `auto | cpu | gpu` once into a `Backend` every stage gets;
//! `gpu` (feature `gpu`) holds the wgpu context and adapter policy, limits, kernels and bind
//! groups, buffers, read-back straight into a destination, and node positions on the device.

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

pub mod backend;
#[cfg(feature = "gpu")]
pub mod gpu;
