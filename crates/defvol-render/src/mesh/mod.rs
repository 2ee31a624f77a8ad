//! The tetrahedral-mesh raycaster (seed 000, section 5): node scalars or the source volume
//! seen through the deformed mesh. The CPU walk (`cpu.rs`; pre-integrated, eight rays side
//! by side in `lanes.rs`) with the linear fields it integrates (`field.rs`), each tet's
//! planes and field (`geometry.rs`), its entries into the mesh (`entry.rs`) and the tets'
//! order in memory (`order.rs`); the source read inside each tet (`look.rs`; eight rays
//! side by side in `source_lanes.rs`) and set up from a volume (`source.rs`, seed 002); the
//! GPU twin (`gpu.rs` + `tet_raycast.wgsl`, `tet_bins.wgsl` and the shared
//! `../camera_tools.wgsl`).

mod cpu;
mod entry;
mod field;
mod geometry;
#[cfg(feature = "gpu")]
pub mod gpu;
#[cfg(target_arch = "x86_64")]
mod lanes;
mod look;
mod order;
pub mod source;
#[cfg(target_arch = "x86_64")]
mod source_lanes;

pub use cpu::*;
