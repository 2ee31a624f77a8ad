//! What a file can be refused for, and the bound on what a header may claim.

use std::path::{Path, PathBuf};

use crate::mesh::MeshError;
use crate::volume::VolumeError;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum IoError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: unsupported file type (expected one of {expected})")]
    UnsupportedExtension { path: PathBuf, expected: &'static str },
    #[error("{path}: {message}")]
    Malformed { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Unrepresentable { path: PathBuf, message: String },
    #[error("{path}: the folder {folder} does not exist")]
    MissingFolder { path: PathBuf, folder: PathBuf },
    #[error(transparent)]
    Mesh(#[from] MeshError),
    #[error(transparent)]
    Volume(#[from] VolumeError),
}

pub(crate) fn malformed(path: &Path, message: impl Into<String>) -> IoError {
    IoError::Malformed { path: path.to_owned(), message: message.into() }
}

pub(crate) fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> IoError + '_ {
    move |source| IoError::Io { path: path.to_owned(), source }
}

/// The most bytes one array or volume may decode to (a claim beyond it is a broken header).
pub(crate) const MAX_DECODED_BYTES: usize = 1 << 33;
