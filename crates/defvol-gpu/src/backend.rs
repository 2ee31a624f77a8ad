//! Where the stages run: one choice per run (`auto`, `cpu` or `gpu`, with the software
//! adapter opt-in beside it), resolved once into a [`Backend`] that every stage is handed.
//!
//! `gpu` without a usable adapter is an error that says why; `auto` falls back to the CPU
//! and says so once. A stage that cannot run on the chosen GPU (a volume over the adapter's
//! buffer limit, an option only the CPU path has) is an error under `gpu` and a logged CPU
//! fallback for that stage under `auto` ([`Backend::try_gpu`]).

use std::fmt;

use serde::{Deserialize, Serialize};

/// The backend a run asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BackendChoice {
    /// The GPU when a usable adapter exists, else the CPU.
    #[default]
    Auto,
    Cpu,
    /// The GPU, or an error naming why it cannot be used.
    Gpu,
}

impl BackendChoice {
    /// As the scene and the parameters spell it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Cpu => "cpu",
            Self::Gpu => "gpu",
        }
    }
}

impl std::str::FromStr for BackendChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "auto" => Ok(Self::Auto),
            "cpu" => Ok(Self::Cpu),
            "gpu" => Ok(Self::Gpu),
            other => Err(format!("`{other}` is not a backend (auto, cpu or gpu)")),
        }
    }
}

/// Where a stage runs once the backend is resolved: what engines, diagnostics and
/// benchmark rows report, compared as a value rather than as a string.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RunsOn {
    Cpu,
    Gpu,
}

impl RunsOn {
    /// "cpu" or "gpu", as diagnostics and benchmark rows spell it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Cpu => "cpu",
            Self::Gpu => "gpu",
        }
    }
}

impl fmt::Display for RunsOn {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BackendError {
    #[error("backend gpu: {0}")]
    Unavailable(String),
    #[error("backend gpu: the {stage} stage cannot run on {adapter}: {message}")]
    Stage { stage: &'static str, adapter: String, message: String },
}

/// The resolved choice, handed to every stage. Cloning shares the GPU context, so every
/// stage of a run works on one device and can share its buffers.
#[derive(Clone)]
pub struct Backend {
    kind: Kind,
}

#[derive(Clone)]
enum Kind {
    Cpu,
    #[cfg(feature = "gpu")]
    Gpu {
        ctx: std::sync::Arc<crate::gpu::GpuContext>,
        required: bool,
    },
}

impl fmt::Debug for Backend {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.describe())
    }
}

impl Backend {
    /// Every stage on the CPU.
    pub fn cpu() -> Self {
        Self { kind: Kind::Cpu }
    }

    /// Every stage on `ctx` (tests and benches that opened their own context).
    #[cfg(feature = "gpu")]
    pub fn gpu(ctx: std::sync::Arc<crate::gpu::GpuContext>) -> Self {
        Self { kind: Kind::Gpu { ctx, required: true } }
    }

    /// Resolves `choice` once: opens the adapter for `auto` and `gpu`.
    pub fn choose(choice: BackendChoice, allow_software_gpu: bool) -> Result<Self, BackendError> {
        match choice {
            BackendChoice::Cpu => Ok(Self::cpu()),
            BackendChoice::Auto | BackendChoice::Gpu => Self::open(choice == BackendChoice::Gpu, allow_software_gpu),
        }
    }

    #[cfg(feature = "gpu")]
    fn open(required: bool, allow_software_gpu: bool) -> Result<Self, BackendError> {
        use crate::gpu::{AdapterPolicy, GpuContext};
        let policy = if allow_software_gpu { AdapterPolicy::AllowSoftware } else { AdapterPolicy::HardwareOnly };
        match GpuContext::open(policy) {
            Ok(ctx) => {
                tracing::info!("every stage on the GPU: {}", ctx.describe());
                Ok(Self { kind: Kind::Gpu { ctx: std::sync::Arc::new(ctx), required } })
            }
            Err(e) if required => Err(BackendError::Unavailable(e.to_string())),
            Err(e) => {
                tracing::info!("no usable GPU ({e}); every stage runs on the CPU");
                Ok(Self::cpu())
            }
        }
    }

    #[cfg(not(feature = "gpu"))]
    fn open(required: bool, _allow_software_gpu: bool) -> Result<Self, BackendError> {
        if required {
            return Err(BackendError::Unavailable("defvol was built without the `gpu` feature".into()));
        }
        tracing::info!("built without the `gpu` feature; every stage runs on the CPU");
        Ok(Self::cpu())
    }

    /// Where the stages run, unless one of them fell back ([`Self::try_gpu`]).
    pub fn runs_on(&self) -> RunsOn {
        match self.kind {
            Kind::Cpu => RunsOn::Cpu,
            #[cfg(feature = "gpu")]
            Kind::Gpu { .. } => RunsOn::Gpu,
        }
    }

    /// The device, for logs and benchmark rows.
    pub fn describe(&self) -> String {
        match &self.kind {
            Kind::Cpu => format!("cpu ({} threads)", rayon::current_num_threads()),
            #[cfg(feature = "gpu")]
            Kind::Gpu { ctx, .. } => format!("gpu: {}", ctx.describe()),
        }
    }

    /// The GPU context, when the stages run on a GPU.
    #[cfg(feature = "gpu")]
    pub fn context(&self) -> Option<&std::sync::Arc<crate::gpu::GpuContext>> {
        match &self.kind {
            Kind::Cpu => None,
            Kind::Gpu { ctx, .. } => Some(ctx),
        }
    }

    /// Builds a stage's GPU path when the backend is a GPU. `Ok(None)`: the stage runs on
    /// the CPU (the backend is the CPU, or `auto` and this stage cannot use the GPU, which
    /// is logged); an error when the GPU was asked for and the stage cannot use it.
    #[cfg(feature = "gpu")]
    pub fn try_gpu<T, E: fmt::Display>(
        &self,
        stage: &'static str,
        build: impl FnOnce(&std::sync::Arc<crate::gpu::GpuContext>) -> Result<T, E>,
    ) -> Result<Option<T>, BackendError> {
        let Kind::Gpu { ctx, required } = &self.kind else { return Ok(None) };
        match build(ctx) {
            Ok(stage_on_gpu) => Ok(Some(stage_on_gpu)),
            Err(e) if *required => Err(BackendError::Stage { stage, adapter: ctx.describe(), message: e.to_string() }),
            Err(e) => {
                tracing::warn!("the {stage} stage runs on the CPU: {e}");
                Ok(None)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backend_names_parse_and_unknown_ones_are_named() {
        assert_eq!("GPU".parse::<BackendChoice>(), Ok(BackendChoice::Gpu));
        assert_eq!(" cpu".parse::<BackendChoice>(), Ok(BackendChoice::Cpu));
        let e = "cuda".parse::<BackendChoice>().unwrap_err();
        assert!(e.contains("cuda") && e.contains("auto, cpu or gpu"), "{e}");
    }

    #[test]
    fn gpu_without_a_usable_adapter_is_an_error_and_auto_falls_back() {
        // A hardware adapter is what `gpu` needs; the suite's machine has only lavapipe.
        match Backend::choose(BackendChoice::Gpu, false) {
            Ok(backend) => assert_eq!(backend.runs_on(), RunsOn::Gpu, "a hardware adapter was found"),
            Err(e) => {
                let message = e.to_string();
                assert!(
                    message.contains("backend gpu") && (message.contains("adapter") || message.contains("feature")),
                    "{message}"
                );
                let auto = Backend::choose(BackendChoice::Auto, false).unwrap();
                assert_eq!(auto.runs_on(), RunsOn::Cpu);
            }
        }
    }
}
