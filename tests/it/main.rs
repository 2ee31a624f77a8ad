//! The integration tests, one binary so that a change links once: each module is one area,
//! and `cargo test --test it <module>::` (or `cargo nextest run -E 'test(/^<module>::/)'`)
//! runs that area alone. The tests that need process-wide state are safe side by side:
//! the fuzzers keep their panics on their own threads, and the DDS tests re-run themselves
//! in their own process inside a private network namespace.

mod cli;
mod dicom;
mod dpcm;
mod dpcm_markers;
mod file_interop;
mod fuzz_loaders;
mod haptic;
mod layers;
#[cfg(feature = "ros")]
mod node_dds;
#[cfg(all(feature = "ros", feature = "mcap", feature = "shm"))]
mod readme;
mod render;
#[cfg(feature = "mcap")]
mod session;
#[cfg(feature = "shm")]
mod shm_interop;
mod solver;
mod tool_contact;
mod warp;
