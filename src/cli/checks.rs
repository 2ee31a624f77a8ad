//! What a command checks before its work, so that a wrong name costs nothing.

use anyhow::Result;

/// An image output: PNG (what `Rendered::write_png` writes), in a folder that exists.
pub(super) fn check_png_output(path: &std::path::Path) -> Result<()> {
    if !path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")) {
        anyhow::bail!("{}: images are written as PNG; name the file .png", path.display());
    }
    Ok(defvol::io::check_folder(path)?)
}
