//! Which adapters a command may use for its GPU path.

/// A request for the GPU path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GpuChoice {
    /// Let a software adapter (llvmpipe) count as a GPU (tests, CI).
    pub allow_software: bool,
    /// The user asked for the GPU explicitly: falling back to the CPU is a warning.
    pub required: bool,
}

impl GpuChoice {
    /// The GPU context, or `None` with a log line when there is no allowed adapter (or the
    /// crate was built without the `gpu` feature).
    #[cfg(feature = "gpu")]
    pub fn context(self) -> Option<crate::gpu::GpuContext> {
        use crate::gpu::{AdapterPolicy, GpuContext};
        let policy = if self.allow_software { AdapterPolicy::AllowSoftware } else { AdapterPolicy::HardwareOnly };
        match GpuContext::open(policy) {
            Ok(ctx) => Some(ctx),
            Err(e) if self.required => {
                tracing::warn!("GPU path unavailable ({e}); the CPU path runs");
                None
            }
            Err(e) => {
                tracing::info!("no GPU adapter ({e}); the CPU path runs");
                None
            }
        }
    }
}
