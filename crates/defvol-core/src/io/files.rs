//! Writing files whole: a temporary name beside the target, renamed at the end, so a
//! failure or a kill never leaves a half file under the final name.

use std::path::{Path, PathBuf};

use super::error::IoError;

pub(crate) fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(String::new, |n| n.to_string_lossy().to_lowercase())
}

/// A temporary name beside `path` with the same extensions (writers that choose
/// compression by extension see the right one) and no other dot in its stem.
pub(crate) fn temporary_beside(path: &Path) -> PathBuf {
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let name = file_name(path);
    let extensions = if name.ends_with(".nii.gz") { "nii.gz" } else { name.rsplit('.').next().unwrap_or("tmp") };
    let unique =
        format!(".defvol-partial-{}-{}.{extensions}", std::process::id(), NEXT.fetch_add(1, Ordering::Relaxed));
    path.parent().unwrap_or(Path::new(".")).join(unique)
}

/// Moves a finished temporary file to its final name.
pub(crate) fn commit(temporary: &Path, path: &Path) -> Result<(), IoError> {
    std::fs::rename(temporary, path).map_err(|e| {
        let _ = std::fs::remove_file(temporary);
        IoError::Io { path: path.to_owned(), source: e }
    })
}

/// Writes `bytes` to exactly `path`, through a temporary file beside it.
pub(crate) fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    let temporary = temporary_beside(path);
    if let Err(source) = std::fs::write(&temporary, bytes) {
        let _ = std::fs::remove_file(&temporary);
        return Err(IoError::Io { path: path.to_owned(), source });
    }
    commit(&temporary, path)
}
