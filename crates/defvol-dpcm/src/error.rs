//! What a DPCM surface refuses: a parameter, a file, an unstable step, the GPU.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DpcmError {
    #[error("DPCM parameter `{name}` = {value}: {why}")]
    BadParameter { name: String, value: f64, why: String },
    #[error("DPCM {source_name}: {message}")]
    Parse { source_name: String, message: String },
    #[error("unknown DPCM preset `{0}` (known: water, loose_soil, sand, oil_painting, fossil)")]
    UnknownPreset(String),
    #[error("the DPCM step is unstable: h²/m·λ(K) + 2h/m·λ(C) = {value:.3} must stay below 4 (the explicit Verlet limit); lower dt below {dt_max:.3e} s or soften the links")]
    Unstable { value: f64, dt_max: f64 },
    #[error("{path}: {message}")]
    Texture { path: PathBuf, message: String },
    #[error("the GPU DPCM failed: {0}")]
    Gpu(String),
    #[error("{path}: {source}")]
    File { path: PathBuf, source: std::io::Error },
}
