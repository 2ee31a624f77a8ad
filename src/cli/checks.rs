//! What a command checks before its work, so that a wrong name costs nothing.

use std::path::Path;

use anyhow::{bail, Result};
use nalgebra::Vector3;

use defvol::mesh::TetMesh;
use defvol::volume::Volume;

/// Metres per unit of a volume file (medical volumes are in millimetres).
const MILLIMETRE: f64 = 0.001;

/// An image output: PNG (what `Rendered::write_png` writes), in a folder that exists.
pub(super) fn check_png_output(path: &std::path::Path) -> Result<()> {
    if !path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")) {
        anyhow::bail!("{}: images are written as PNG; name the file .png", path.display());
    }
    Ok(defvol::io::check_folder(path)?)
}

/// `--mesh-scale`: a finite factor above zero.
pub(super) fn mesh_scale(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(scale) if scale.is_finite() && scale > 0.0 => Ok(scale),
        Ok(scale) => Err(format!("{scale} must be finite and > 0")),
        Err(e) => Err(e.to_string()),
    }
}

/// A mesh file in the units of the volume it is placed over, and the factor applied:
/// `--mesh-scale` when given, else the unit the file records over the volume's millimetres
/// (volumes are in millimetres, as medical files are), else the file's numbers as they are.
pub(super) fn mesh_over_volume(path: &Path, chosen: Option<f64>) -> Result<(TetMesh, f64)> {
    let read = defvol::io::read_mesh_with_metadata(path)?;
    let recorded = read.metres_per_unit.filter(|_| chosen.is_none());
    let (mesh, scale) = read.into_scaled(MILLIMETRE, chosen, 1.0);
    if let Some(unit) = recorded {
        tracing::info!("{}: the file records {unit} m per unit: x{scale} into millimetres", path.display());
    }
    Ok((mesh, scale))
}

/// The node positions of `path`, a deformed copy of `rest` (the same tets), in `rest`'s
/// units: `--mesh-scale`, else the unit the file records, else `rest`'s own scale (a tool
/// that rewrote the file may have dropped the unit). Read unchecked: a deformation may turn
/// tets inside out, and those are counted and drawn as they lie rather than refused.
pub(super) fn deformed_positions(
    path: &Path,
    rest: &TetMesh,
    chosen: Option<f64>,
    rest_scale: f64,
) -> Result<Vec<Vector3<f64>>> {
    let raw = defvol::io::read_raw_mesh(path)?;
    let corners = |t: &[u32; 4]| {
        let mut t = *t;
        t.sort_unstable();
        t
    };
    let same =
        raw.tets.len() == rest.tets().len() && raw.tets.iter().zip(rest.tets()).all(|(a, b)| corners(a) == corners(b));
    if !same || raw.nodes.len() != rest.nodes().len() {
        bail!(
            "--deformed {}: its tets are not the rest mesh's ({} against {} tets, {} against {} nodes, or in another order)",
            path.display(),
            raw.tets.len(),
            rest.tets().len(),
            raw.nodes.len(),
            rest.nodes().len()
        );
    }
    let scale = chosen.or(raw.metres_per_unit.map(|unit| unit / MILLIMETRE)).unwrap_or(rest_scale);
    let positions: Vec<Vector3<f64>> = raw.nodes.iter().map(|p| p * scale).collect();
    let inverted = rest.inverted(&positions);
    if let Some((tet, ratio)) = inverted.worst {
        tracing::warn!(
            "--deformed {}: {} tets turned inside out (the worst, tet {tet}, at {ratio:.3} of its rest volume), drawn as they lie",
            path.display(),
            inverted.count
        );
    }
    Ok(positions)
}

/// A mesh placed over a volume (after `--mesh-scale`) must meet it: a mesh in metres over
/// a millimetre volume lies in one corner voxel and would give an empty picture or a
/// one-voxel warp, silently.
pub(super) fn check_mesh_meets_volume(what: &str, nodes: &[Vector3<f64>], scale: f64, volume: &Volume) -> Result<()> {
    let (lo, hi) = defvol::mesh::bounds(nodes);
    let (vlo, vhi) = volume.bounds();
    let meets = (0..3).all(|a| lo[a] <= vhi[a] && hi[a] >= vlo[a]);
    // Overlapping boxes still miss when one is a speck in the other: a thousandfold unit slip.
    let (mesh_size, volume_size) = ((hi - lo).max(), (vhi - vlo).max());
    let speck = mesh_size > 0.0 && volume_size / mesh_size > 200.0;
    if meets && !speck {
        return Ok(());
    }
    let hint = match volume_size / mesh_size.max(f64::MIN_POSITIVE) {
        r if (300.0..3000.0).contains(&r) => format!(
            "; it looks like a mesh in metres over a volume in millimetres: try --mesh-scale {}",
            1000.0 * scale
        ),
        _ => String::new(),
    };
    bail!(
        "{what}: the mesh's box {} to {} (file units x {scale}) {} the volume's box {} to {} (the \
         volume's own units, millimetres for medical files){hint}",
        show(&lo),
        show(&hi),
        if meets { "is a speck inside" } else { "does not meet" },
        show(&vlo),
        show(&vhi),
    )
}

fn show(p: &Vector3<f64>) -> String {
    defvol::logging::vector([p.x, p.y, p.z], 4)
}
