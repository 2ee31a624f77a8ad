//! Mesh and volume files as the field's tools write them.
//!
//! Meshes: VTK XML `.vtu` in every encoding VTK and meshio write (`vtk_xml.rs`), legacy
//! `.vtk` 2.0-5.1 ASCII and binary (`vtk_legacy.rs`), Gmsh 1 ASCII, 2.2 and 4.1 ASCII and
//! binary (`gmsh.rs`), TetGen `.node`/`.ele`; the content, not the extension, picks the
//! parser of a one-file mesh. Hexahedra, wedges and pyramids are split into tets
//! (`solids.rs`); other cells are counted and skipped. Volumes, by extension: NIfTI-1 (the
//! nifti crate), NRRD and MetaImage (text headers read here), DICOM series (dicom-rs,
//! `dicom.rs`).
//!
//! No input crashes the process: every count and size a header gives is checked against the
//! bytes that are there before anything is allocated from it, and arithmetic on header
//! values is checked. Every parser takes bytes (`parse_mesh`, `parse_volume`), so the fuzz
//! tests drive them without files. Writes go to a temporary name beside the target and are
//! renamed at the end: a failure or a kill never leaves a half file under the final name.

mod dicom;
mod dicom_scan;
mod error;
mod files;
mod gmsh;
mod mesh_file;
mod metaimage;
mod nifti_io;
mod nrrd;
mod raw;
mod solids;
mod tetgen;
mod vtk;
mod vtk_legacy;
mod vtk_xml;
mod withheld;

pub use dicom::{parse_dicom, read_dicom, DicomRead, SeriesInfo};
pub use error::IoError;
pub use mesh_file::{CellArray, MeshRead, RawMesh, SkippedCells};
pub use withheld::withhold_found;

use error::{io_error, malformed};
use files::{file_name, write_atomically};
use mesh_file::MeshFile;

use std::path::Path;

use nalgebra::Vector3;

use crate::mesh::TetMesh;
use crate::volume::Volume;

const MESH_TYPES: &str = ".vtu, .vtk, .msh, .node/.ele";
const VOLUME_TYPES: &str = ".nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd";
/// What [`read_volume`] takes, in its errors.
const VOLUME_INPUTS: &str = ".nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd, .dcm, a DICOM folder";

/// The mesh format a file name asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    VtkXml,
    VtkLegacy,
    Gmsh,
}

impl MeshFormat {
    fn of(path: &Path) -> Option<Self> {
        let name = file_name(path);
        if name.ends_with(".vtu") {
            Some(Self::VtkXml)
        } else if name.ends_with(".vtk") {
            Some(Self::VtkLegacy)
        } else if name.ends_with(".msh") {
            Some(Self::Gmsh)
        } else {
            None
        }
    }

    /// The format the bytes say they are, whatever the file is named.
    fn of_content(bytes: &[u8]) -> Option<Self> {
        let start = bytes.iter().position(|b| !b.is_ascii_whitespace()).map_or(&bytes[..0], |i| &bytes[i..]);
        let start = start.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(start);
        if start.starts_with(b"<?xml") || start.starts_with(b"<VTKFile") {
            Some(Self::VtkXml)
        } else if start.starts_with(b"# vtk DataFile") {
            Some(Self::VtkLegacy)
        } else if start.starts_with(b"$MeshFormat") || start.starts_with(b"$NOD") {
            Some(Self::Gmsh)
        } else {
            None
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::VtkXml => "VTK XML",
            Self::VtkLegacy => "legacy VTK",
            Self::Gmsh => "Gmsh",
        }
    }
}

fn parse_mesh_file(path: &Path, bytes: &[u8], format: MeshFormat) -> Result<MeshFile, IoError> {
    let parsed = match format {
        MeshFormat::VtkXml => vtk_xml::parse(bytes),
        MeshFormat::VtkLegacy => vtk_legacy::parse(bytes),
        MeshFormat::Gmsh => gmsh::parse(bytes),
    };
    parsed.map_err(|message| malformed(path, message))
}

/// Parses a one-file mesh (`.vtu`, `.vtk`, `.msh`) from its bytes; `path` names it in errors.
pub fn parse_mesh(path: &Path, bytes: &[u8], format: MeshFormat) -> Result<TetMesh, IoError> {
    Ok(parse_mesh_file(path, bytes, format)?.into_mesh(path)?.mesh)
}

/// Parses a TetGen pair from the bytes of its `.node` and `.ele` files.
pub fn parse_tetgen(path: &Path, node: &[u8], ele: &[u8]) -> Result<TetMesh, IoError> {
    Ok(tetgen::parse(node, ele).map_err(|message| malformed(path, message))?.into_mesh(path)?.mesh)
}

fn read_mesh_file(path: &Path) -> Result<MeshFile, IoError> {
    if file_name(path).ends_with(".node") || file_name(path).ends_with(".ele") {
        let (node_path, ele_path) = (path.with_extension("node"), path.with_extension("ele"));
        let node = std::fs::read(&node_path).map_err(io_error(&node_path))?;
        let (mut mesh, first_index) = tetgen::parse_nodes(&node).map_err(|message| malformed(&node_path, message))?;
        let ele = std::fs::read(&ele_path).map_err(io_error(&ele_path))?;
        tetgen::parse_elements(&mut mesh, first_index, &ele).map_err(|message| malformed(&ele_path, message))?;
        return Ok(mesh);
    }
    let named = MeshFormat::of(path);
    if named.is_none() && !path.is_file() {
        return Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: MESH_TYPES });
    }
    let bytes = std::fs::read(path).map_err(io_error(path))?;
    // The content decides: files saved under another format's extension are common.
    let format = match (MeshFormat::of_content(&bytes), named) {
        (Some(found), Some(named)) if found != named => {
            let (found_name, named_name) = (found.name(), named.name());
            tracing::warn!("{}: named as {named_name} but holds {found_name}; read as {found_name}", path.display());
            found
        }
        (Some(found), _) => found,
        (None, Some(named)) => named,
        (None, None) => return Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: MESH_TYPES }),
    };
    parse_mesh_file(path, &bytes, format)
}

/// A named one-component point array of a mesh file: node values to render when the file
/// holds several (dose, temperature, a segmentation's labels).
pub fn read_mesh_point_array(path: &Path, name: &str) -> Result<Vec<f32>, IoError> {
    let mut file = read_mesh_file(path)?;
    file.drop_unused_nodes();
    let names: Vec<&str> = file.arrays.iter().filter(|a| a.components == 1).map(|a| a.name.as_str()).collect();
    let message = format!("no one-component point array `{name}`; it has {names:?}");
    match file.arrays.iter().find(|a| a.name == name && a.components == 1) {
        Some(array) => Ok(array.values.clone()),
        None => Err(malformed(path, message)),
    }
}

/// Reads a tetrahedral mesh (VTK `.vtu`/`.vtk`, Gmsh `.msh` 1, 2.2 or 4.1, TetGen `.node`/`.ele`).
pub fn read_mesh(path: &Path) -> Result<TetMesh, IoError> {
    Ok(read_mesh_with_metadata(path)?.mesh)
}

/// A mesh file's nodes and tets as read, unchecked ([`RawMesh`]): only a file that cannot be
/// parsed is an error.
pub fn read_raw_mesh(path: &Path) -> Result<RawMesh, IoError> {
    Ok(read_mesh_file(path)?.into_raw(path))
}

/// [`read_mesh`], with the cells of other kinds the file held and the unit it records.
pub fn read_mesh_with_metadata(path: &Path) -> Result<MeshRead, IoError> {
    read_mesh_file(path)?.into_mesh(path)
}

/// Writes `mesh` with node positions `positions` (the deformed state, or the mesh's own).
/// `metres_per_unit` is recorded in VTK files as the field-data array `metres_per_unit`
/// (read back by [`read_mesh_with_metadata`], kept by VTK, ParaView and meshio); Gmsh and
/// TetGen files have no place for it.
pub fn write_mesh(
    path: &Path,
    mesh: &TetMesh,
    positions: Option<&[Vector3<f64>]>,
    metres_per_unit: Option<f64>,
) -> Result<(), IoError> {
    let nodes = positions.unwrap_or(mesh.nodes());
    if nodes.len() != mesh.nodes().len() {
        return Err(malformed(path, format!("{} positions for a mesh of {} nodes", nodes.len(), mesh.nodes().len())));
    }
    let name = file_name(path);
    if name.ends_with(".node") || name.ends_with(".ele") {
        return tetgen::write(path, nodes, mesh.tets());
    }
    let points: Vec<[f64; 3]> = nodes.iter().map(|p| [p.x, p.y, p.z]).collect();
    let bytes = match MeshFormat::of(path) {
        Some(MeshFormat::VtkXml) => vtk::xml(&points, mesh.tets(), vtk::TETRA, mesh.scalars(), metres_per_unit),
        Some(MeshFormat::VtkLegacy) => {
            let title = "defvol tetrahedral mesh";
            vtk::legacy(&points, mesh.tets(), vtk::TETRA, mesh.scalars(), metres_per_unit, title)
        }
        Some(MeshFormat::Gmsh) => gmsh::write(nodes, mesh.tets()),
        None => return Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: MESH_TYPES }),
    };
    write_atomically(path, &bytes)
}

/// Writes a triangle surface in metres with per-vertex scalars (`.vtu` or legacy `.vtk`; the
/// unit recorded as in [`write_mesh`]).
pub fn write_triangles(
    path: &Path,
    nodes: &[[f32; 3]],
    triangles: &[[u32; 3]],
    scalars: Option<&[f32]>,
) -> Result<(), IoError> {
    let points: Vec<[f64; 3]> = nodes.iter().map(|p| p.map(f64::from)).collect();
    let bytes = match MeshFormat::of(path) {
        Some(MeshFormat::VtkXml) => vtk::xml(&points, triangles, vtk::TRIANGLE, scalars, Some(1.0)),
        Some(MeshFormat::VtkLegacy) => {
            vtk::legacy(&points, triangles, vtk::TRIANGLE, scalars, Some(1.0), "defvol surface")
        }
        _ => return Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: ".vtu, .vtk" }),
    };
    write_atomically(path, &bytes)
}

/// Parses a volume of the format `path` names from its bytes; `sidecar` gives the bytes of
/// a file the header names (a detached NRRD or MetaImage data file), or `None`.
pub fn parse_volume(path: &Path, bytes: &[u8], sidecar: &dyn Fn(&str) -> Option<Vec<u8>>) -> Result<Volume, IoError> {
    let name = file_name(path);
    if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        nifti_io::parse(path, bytes)
    } else if name.ends_with(".nrrd") || name.ends_with(".nhdr") {
        nrrd::parse(path, bytes, sidecar)
    } else if name.ends_with(".mha") || name.ends_with(".mhd") {
        metaimage::parse(path, bytes, sidecar)
    } else {
        Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: VOLUME_TYPES })
    }
}

/// Reads a scalar volume (NIfTI-1 `.nii[.gz]`, NRRD `.nrrd`/`.nhdr`, MetaImage `.mha`/`.mhd`,
/// a DICOM series: a folder of slices or a `.dcm` file, its largest series).
pub fn read_volume(path: &Path) -> Result<Volume, IoError> {
    read_volume_series(path, None)
}

/// [`read_volume`]; for DICOM, series `series` (a SeriesInstanceUID) when given.
pub fn read_volume_series(path: &Path, series: Option<&str>) -> Result<Volume, IoError> {
    if is_dicom(path) {
        return Ok(read_dicom(path, series)?.volume);
    }
    if let Some(uid) = series {
        return Err(malformed(path, format!("series {uid} asked for, but this is not a DICOM folder or file")));
    }
    let name = file_name(path);
    if !VOLUME_TYPES.split(", ").any(|ext| name.ends_with(ext)) {
        return Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: VOLUME_INPUTS });
    }
    let bytes = std::fs::read(path).map_err(io_error(path))?;
    let folder = path.parent().unwrap_or(Path::new(".")).to_owned();
    parse_volume(path, &bytes, &|name| std::fs::read(folder.join(name)).ok())
}

/// Whether `path` is read as DICOM: a folder, a `.dcm`/`.dicom` file, or a file with no
/// other volume type's extension and the DICOM preamble's `DICM` mark.
pub fn is_dicom(path: &Path) -> bool {
    let name = file_name(path).to_ascii_lowercase();
    let other_type = VOLUME_TYPES.split(", ").any(|ext| name.ends_with(ext));
    path.is_dir() || name.ends_with(".dcm") || name.ends_with(".dicom") || (!other_type && dicom::has_dicom_mark(path))
}

/// Whether `path` names a mesh file [`read_mesh`] reads (by its extension).
pub fn is_mesh(path: &Path) -> bool {
    let name = file_name(path);
    MeshFormat::of(path).is_some() || name.ends_with(".node") || name.ends_with(".ele")
}

/// Writes a volume as f32 samples in the format the extension names, to exactly `path`
/// (through a temporary file beside it). What the format cannot hold (dims over its
/// limits) is refused by name.
/// What a command checks of a mesh output before its work: a type [`write_mesh`] writes, in
/// a folder that exists.
pub fn check_mesh_output(path: &Path) -> Result<(), IoError> {
    if !is_mesh(path) {
        return Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: MESH_TYPES });
    }
    check_folder(path)
}

/// What a command checks of a volume output before its work: a type [`write_volume`]
/// writes, in a folder that exists.
pub fn check_volume_output(path: &Path) -> Result<(), IoError> {
    let name = file_name(path);
    if !VOLUME_WRITE_TYPES.iter().any(|t| name.ends_with(t)) {
        return Err(IoError::UnsupportedExtension {
            path: path.to_owned(),
            expected: ".nii, .nii.gz, .nrrd, .mha, .mhd",
        });
    }
    check_folder(path)
}

/// The folder an output goes into exists.
pub fn check_folder(path: &Path) -> Result<(), IoError> {
    match path.parent().filter(|p| !p.as_os_str().is_empty()) {
        Some(folder) if !folder.is_dir() => {
            Err(IoError::MissingFolder { path: path.to_owned(), folder: folder.to_owned() })
        }
        _ => Ok(()),
    }
}

const VOLUME_WRITE_TYPES: [&str; 5] = [".nii", ".nii.gz", ".nrrd", ".mha", ".mhd"];

pub fn write_volume(path: &Path, volume: &Volume) -> Result<(), IoError> {
    let name = file_name(path);
    if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        nifti_io::write(path, volume)
    } else if name.ends_with(".nrrd") {
        write_atomically(path, &nrrd::encode(volume)?)
    } else if name.ends_with(".mha") || name.ends_with(".mhd") {
        metaimage::write(path, volume)
    } else {
        Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: ".nii, .nii.gz, .nrrd, .mha, .mhd" })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate;
    use crate::volume::phantom;

    fn sample_volume() -> Volume {
        let v = phantom::phantom([20, 12, 9], 7.5).unwrap();
        let rot = nalgebra::Rotation3::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2).into_inner();
        Volume::new(v.dims(), [0.7, 1.1, 2.5], [-3.0, 4.5, 12.0], rot, v.data().to_vec(), "sample").unwrap()
    }

    #[test]
    fn volume_round_trips_keep_geometry_and_samples() {
        let dir = tempfile::tempdir().unwrap();
        let v = sample_volume();
        for name in ["a.nii", "a.nii.gz", "a.nrrd", "a.mha", "a.mhd"] {
            let path = dir.path().join(name);
            write_volume(&path, &v).unwrap();
            let back = read_volume(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(back.dims(), v.dims(), "{name}");
            assert_eq!(back.data(), v.data(), "{name}");
            for a in 0..3 {
                assert!((back.spacing()[a] - v.spacing()[a]).abs() < 1e-5, "{name} spacing");
                assert!((back.origin()[a] - v.origin()[a]).abs() < 1e-4, "{name} origin {:?}", back.origin());
            }
            assert!((back.direction() - v.direction()).norm() < 1e-5, "{name} direction {}", back.direction());
        }
    }

    #[test]
    fn mesh_round_trips_keep_topology_and_positions() {
        let dir = tempfile::tempdir().unwrap();
        let mut mesh =
            generate::lattice(Vector3::zeros(), Vector3::new(0.3, 0.2, 0.1), [3, 2, 2], generate::CellSplit::Five)
                .unwrap();
        mesh.set_scalars((0..mesh.nodes().len()).map(|i| i as f32 * 0.5).collect()).unwrap();
        for name in ["m.vtu", "m.vtk", "m.msh", "m.node"] {
            let path = dir.path().join(name);
            write_mesh(&path, &mesh, None, None).unwrap();
            let back = read_mesh(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(back.tets(), mesh.tets(), "{name}");
            for (a, b) in back.nodes().iter().zip(mesh.nodes()) {
                assert!((a - b).norm() < 1e-12, "{name}");
            }
            if name.starts_with("m.vt") {
                assert_eq!(back.scalars(), mesh.scalars(), "{name}");
            }
        }
    }

    #[test]
    fn vtk_files_record_the_length_unit_they_were_written_in() {
        let dir = tempfile::tempdir().unwrap();
        let mesh = generate::bar(0.1).unwrap();
        for (name, unit, recorded) in
            [("a.vtu", Some(0.001), Some(0.001)), ("b.vtk", Some(1.0), Some(1.0)), ("c.vtu", None, None)]
        {
            let path = dir.path().join(name);
            write_mesh(&path, &mesh, None, unit).unwrap();
            let back = read_mesh_with_metadata(&path).unwrap();
            assert_eq!(back.metres_per_unit, recorded, "{name}");
            assert_eq!(back.mesh.tets(), mesh.tets(), "{name}: the field data leaves the mesh whole");
        }
        let surface = dir.path().join("s.vtk");
        write_triangles(&surface, &[[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], &[[0, 1, 2]], None).unwrap();
        let text = std::fs::read(&surface).unwrap();
        assert!(text.windows(30).any(|w| w == b"FIELD FieldData 1\nmetres_per_u"), "surfaces record metres");
    }

    #[test]
    fn gmsh_2_2_ascii_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tet.msh");
        std::fs::write(
            &path,
            "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n5\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 1 1 1\n$EndNodes\n\
             $Elements\n3\n1 2 2 0 1 1 2 3\n2 4 2 0 1 1 2 3 4\n3 4 2 0 1 2 3 4 5\n$EndElements\n",
        )
        .unwrap();
        let m = read_mesh(&path).unwrap();
        assert_eq!(m.tets().len(), 2);
        assert_eq!(m.nodes().len(), 5);
    }

    #[test]
    fn a_named_point_array_is_read_and_a_missing_one_named_with_those_there() {
        let dir = tempfile::tempdir().unwrap();
        let mut mesh = crate::mesh::generate::bar(0.3).unwrap();
        let values: Vec<f32> = (0..mesh.nodes().len()).map(|i| 10.0 + i as f32).collect();
        mesh.set_scalars(values.clone()).unwrap();
        for name in ["m.vtu", "m.vtk"] {
            let path = dir.path().join(name);
            write_mesh(&path, &mesh, None, None).unwrap();
            assert_eq!(read_mesh_point_array(&path, "scalar").unwrap(), values, "{name}");
            let err = read_mesh_point_array(&path, "dose").unwrap_err().to_string();
            assert!(err.contains("`dose`") && err.contains("\"scalar\"") && err.contains(name), "{err}");
        }
        // A Gmsh file carries no point arrays: the error lists none.
        let msh = dir.path().join("m.msh");
        write_mesh(&msh, &mesh, None, None).unwrap();
        let err = read_mesh_point_array(&msh, "scalar").unwrap_err().to_string();
        assert!(err.contains("`scalar`") && err.contains("[]"), "{err}");
        assert!(matches!(
            read_mesh_point_array(Path::new("m.stl"), "scalar"),
            Err(IoError::UnsupportedExtension { .. })
        ));
    }

    #[test]
    fn malformed_files_name_the_file_and_the_problem() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.mha");
        std::fs::write(
            &path,
            "ObjectType = Image\nNDims = 3\nDimSize = 4 4\nElementType = MET_FLOAT\nElementDataFile = LOCAL\n",
        )
        .unwrap();
        let e = read_volume(&path).unwrap_err().to_string();
        assert!(e.contains("bad.mha") && e.contains("DimSize"), "{e}");
        let path = dir.path().join("bad.node");
        std::fs::write(&path, "3 3 0 0\n0 0 0 0\n1 1 0 0\n").unwrap();
        let e = read_mesh(&path).unwrap_err().to_string();
        assert!(e.contains("bad.node"), "{e}");
        let e = read_mesh(&dir.path().join("missing.vtu")).unwrap_err().to_string();
        assert!(e.contains("missing.vtu"), "{e}");
        let e = read_volume(Path::new("x.png")).unwrap_err().to_string();
        assert!(e.contains("unsupported"), "{e}");
    }

    #[test]
    fn mesh_validation_errors_carry_the_file_name() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("inv.node");
        std::fs::write(&path, "5 3 0 0\n0 0 0 0\n1 1 0 0\n2 0 1 0\n3 0 0 1\n4 1 1 1\n").unwrap();
        std::fs::write(dir.path().join("inv.ele"), "2 4 0\n0 0 1 2 3\n1 1 3 2 4\n").unwrap();
        let e = read_mesh(&path).unwrap_err().to_string();
        assert!(e.contains("inv.node") && e.contains("tet 1") && e.contains("inverted"), "{e}");
    }

    /// The headers the field's users sent: each is an error naming what was wrong, not an
    /// abort or a panic.
    #[test]
    fn impossible_headers_are_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let huge = dir.path().join("huge.nrrd");
        std::fs::write(
            &huge,
            "NRRD0004\ntype: float\ndimension: 3\nsizes: 100000 100000 100000\nencoding: raw\n\n\0\0\0\0",
        )
        .unwrap();
        let e = read_volume(&huge).unwrap_err().to_string();
        assert!(e.contains("huge.nrrd") && e.contains("100000"), "{e}");
        let overflow = dir.path().join("overflow.nrrd");
        std::fs::write(
            &overflow,
            "NRRD0004\ntype: float\ndimension: 3\nsizes: 4294967296 4294967296 4294967296\nencoding: raw\n\n",
        )
        .unwrap();
        let e = read_volume(&overflow).unwrap_err().to_string();
        assert!(e.contains("overflow.nrrd") && e.contains("4294967296"), "{e}");
        let nodes = dir.path().join("many.node");
        std::fs::write(&nodes, "100000000000 3 0 0\n0 0 0 0\n").unwrap();
        std::fs::write(dir.path().join("many.ele"), "0 4 0\n").unwrap();
        let e = read_mesh(&nodes).unwrap_err().to_string();
        assert!(e.contains("many.node") && e.contains("100000000000"), "{e}");
        let four_d = dir.path().join("4d.mha");
        std::fs::write(&four_d, "NDims = 4\nDimSize = 2 2 2 3\nElementType = MET_FLOAT\nElementDataFile = LOCAL\n")
            .unwrap();
        let e = read_volume(&four_d).unwrap_err().to_string();
        assert!(e.contains("4d.mha") && e.contains("4D"), "{e}");
        let sheared = dir.path().join("sheared.mha");
        std::fs::write(&sheared, "NDims = 3\nDimSize = 1 1 1\nTransformMatrix = 1 0 0 0.5 1 0 0 0 1\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n\x07").unwrap();
        let e = read_volume(&sheared).unwrap_err().to_string();
        assert!(e.contains("sheared.mha") && e.contains("sheared"), "{e}");
    }

    /// The path written is exactly the path asked (a dot in the stem included), through a
    /// temporary file that never lingers; NIfTI-1's dim limit is refused by name.
    #[test]
    fn writes_land_under_exactly_the_name_asked() {
        let dir = tempfile::tempdir().unwrap();
        let v = sample_volume();
        std::fs::write(dir.path().join("scan.nii"), b"someone else's file").unwrap();
        for name in ["scan.v2.nii", "scan.v2.nii.gz", "scan.v2.nrrd", "scan.v2.mha", "scan.v2.mhd"] {
            write_volume(&dir.path().join(name), &v).unwrap_or_else(|e| panic!("{name}: {e}"));
            let back = read_volume(&dir.path().join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(back.data(), v.data(), "{name}");
        }
        assert_eq!(
            std::fs::read(dir.path().join("scan.nii")).unwrap(),
            b"someone else's file",
            "another file was replaced"
        );
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(
            names,
            ["scan.nii", "scan.v2.mha", "scan.v2.mhd", "scan.v2.nii", "scan.v2.nii.gz", "scan.v2.nrrd", "scan.v2.zraw"]
        );
        let wide =
            Volume::new([40_000, 1, 1], [1.0; 3], [0.0; 3], nalgebra::Matrix3::identity(), vec![0.0; 40_000], "wide")
                .unwrap();
        let e = write_volume(&dir.path().join("wide.nii"), &wide).unwrap_err().to_string();
        assert!(e.contains("wide.nii") && e.contains("32767"), "{e}");
        assert!(!dir.path().join("wide.nii").exists());
    }
}
