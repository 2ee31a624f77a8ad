//! The volume raycaster (seed 000's ray casting of a regular grid): the CPU path
//! (`cpu.rs`), its GPU twin (`gpu.rs` + `raycast.wgsl`, with the shared
//! `../camera_tools.wgsl`), and the f64 reference the tests hold both to.

mod cpu;
#[cfg(feature = "gpu")]
pub mod gpu;

pub use cpu::*;
