//! Mesh and volume files, chosen by extension. Maintained crates do the formats where one
//! exists (vtkio: VTK; mshio: Gmsh 4.1; nifti: NIfTI-1); Gmsh 2.2, TetGen, NRRD and
//! MetaImage are small text-header formats read and written here.

mod gmsh;
mod metaimage;
mod nifti_io;
mod nrrd;
mod tetgen;
mod vtk;

use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use crate::mesh::{MeshError, TetMesh};
use crate::volume::{Volume, VolumeError};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum IoError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: unsupported file type (expected one of {expected})")]
    UnsupportedExtension { path: PathBuf, expected: &'static str },
    #[error("{path}: {message}")]
    Malformed { path: PathBuf, message: String },
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

fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(String::new, |n| n.to_string_lossy().to_lowercase())
}

const MESH_TYPES: &str = ".vtu, .vtk, .msh, .node/.ele";
const VOLUME_TYPES: &str = ".nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd";

/// A named one-component point array of a VTK mesh (`.vtu`/`.vtk`): node values to render
/// when the file holds several (dose, temperature, a segmentation's labels).
pub fn read_mesh_point_array(path: &Path, name: &str) -> Result<Vec<f32>, IoError> {
    let file = file_name(path);
    if !(file.ends_with(".vtu") || file.ends_with(".vtk")) {
        return Err(IoError::UnsupportedExtension {
            path: path.to_owned(),
            expected: ".vtu, .vtk (named point arrays)",
        });
    }
    vtk::read_point_array(path, name)
}

/// Reads a tetrahedral mesh (VTK `.vtu`/`.vtk`, Gmsh `.msh` 4.1 or 2.2, TetGen `.node`/`.ele`).
pub fn read_mesh(path: &Path) -> Result<TetMesh, IoError> {
    let name = file_name(path);
    let (nodes, tets, scalars) = if name.ends_with(".vtu") || name.ends_with(".vtk") {
        vtk::read(path)?
    } else if name.ends_with(".msh") {
        gmsh::read(path)?
    } else if name.ends_with(".node") || name.ends_with(".ele") {
        tetgen::read(path)?
    } else {
        return Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: MESH_TYPES });
    };
    Ok(TetMesh::new(nodes, tets, scalars, &path.display().to_string())?)
}

/// Writes `mesh` with node positions `positions` (the deformed state, or the mesh's own).
pub fn write_mesh(path: &Path, mesh: &TetMesh, positions: Option<&[Vector3<f64>]>) -> Result<(), IoError> {
    let nodes = positions.unwrap_or(mesh.nodes());
    if nodes.len() != mesh.nodes().len() {
        return Err(malformed(path, format!("{} positions for a mesh of {} nodes", nodes.len(), mesh.nodes().len())));
    }
    let name = file_name(path);
    if name.ends_with(".vtu") || name.ends_with(".vtk") {
        vtk::write(path, nodes, mesh.tets(), mesh.scalars())
    } else if name.ends_with(".msh") {
        gmsh::write(path, nodes, mesh.tets())
    } else if name.ends_with(".node") || name.ends_with(".ele") {
        tetgen::write(path, nodes, mesh.tets())
    } else {
        Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: MESH_TYPES })
    }
}

/// Writes a triangle surface with per-vertex scalars (`.vtu` or legacy `.vtk`).
pub fn write_triangles(
    path: &Path,
    nodes: &[[f32; 3]],
    triangles: &[[u32; 3]],
    scalars: Option<&[f32]>,
) -> Result<(), IoError> {
    let name = file_name(path);
    if name.ends_with(".vtu") || name.ends_with(".vtk") {
        vtk::write_triangles(path, nodes, triangles, scalars)
    } else {
        Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: ".vtu, .vtk" })
    }
}

/// Reads a scalar volume (NIfTI-1 `.nii[.gz]`, NRRD `.nrrd`/`.nhdr`, MetaImage `.mha`/`.mhd`).
pub fn read_volume(path: &Path) -> Result<Volume, IoError> {
    let name = file_name(path);
    if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        nifti_io::read(path)
    } else if name.ends_with(".nrrd") || name.ends_with(".nhdr") {
        nrrd::read(path)
    } else if name.ends_with(".mha") || name.ends_with(".mhd") {
        metaimage::read(path)
    } else {
        Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: VOLUME_TYPES })
    }
}

/// Writes a volume as f32 samples in the format the extension names.
pub fn write_volume(path: &Path, volume: &Volume) -> Result<(), IoError> {
    let name = file_name(path);
    if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        nifti_io::write(path, volume)
    } else if name.ends_with(".nrrd") {
        nrrd::write(path, volume)
    } else if name.ends_with(".mha") || name.ends_with(".mhd") {
        metaimage::write(path, volume)
    } else {
        Err(IoError::UnsupportedExtension { path: path.to_owned(), expected: ".nii, .nii.gz, .nrrd, .mha, .mhd" })
    }
}

/// Sample element types found in volume files; all become f32.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SampleType {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    F32,
    F64,
}

impl SampleType {
    pub(crate) fn size(self) -> usize {
        match self {
            SampleType::U8 | SampleType::I8 => 1,
            SampleType::U16 | SampleType::I16 => 2,
            SampleType::U32 | SampleType::I32 | SampleType::F32 => 4,
            SampleType::F64 => 8,
        }
    }

    /// Decodes raw bytes (little- or big-endian) into f32 samples.
    pub(crate) fn decode(self, bytes: &[u8], big_endian: bool) -> Vec<f32> {
        let n = self.size();
        bytes
            .chunks_exact(n)
            .map(|c| {
                let mut b = [0u8; 8];
                b[..n].copy_from_slice(c);
                if big_endian {
                    b[..n].reverse();
                }
                match self {
                    SampleType::U8 => b[0] as f32,
                    SampleType::I8 => b[0] as i8 as f32,
                    SampleType::U16 => u16::from_le_bytes([b[0], b[1]]) as f32,
                    SampleType::I16 => i16::from_le_bytes([b[0], b[1]]) as f32,
                    SampleType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
                    SampleType::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
                    SampleType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                    SampleType::F64 => f64::from_le_bytes(b) as f32,
                }
            })
            .collect()
    }
}

/// Reads `expected` bytes of samples from a possibly gzip/zlib-compressed payload.
pub(crate) fn decompress(
    path: &Path,
    payload: &[u8],
    compression: Compression,
    expected: usize,
) -> Result<Vec<u8>, IoError> {
    use std::io::Read;
    let mut out = Vec::with_capacity(expected);
    let result = match compression {
        Compression::None => {
            out.extend_from_slice(payload);
            Ok(())
        }
        Compression::Gzip => flate2::read::MultiGzDecoder::new(payload).read_to_end(&mut out).map(|_| ()),
        Compression::Zlib => flate2::read::ZlibDecoder::new(payload).read_to_end(&mut out).map(|_| ()),
    };
    result.map_err(|e| malformed(path, format!("cannot decompress the sample data: {e}")))?;
    if out.len() < expected {
        return Err(malformed(path, format!("sample data holds {} bytes, {} needed", out.len(), expected)));
    }
    out.truncate(expected);
    Ok(out)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Compression {
    None,
    Gzip,
    Zlib,
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
            write_mesh(&path, &mesh, None).unwrap();
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
            write_mesh(&path, &mesh, None).unwrap();
            assert_eq!(read_mesh_point_array(&path, "scalar").unwrap(), values, "{name}");
            let err = read_mesh_point_array(&path, "dose").unwrap_err().to_string();
            assert!(err.contains("`dose`") && err.contains("\"scalar\"") && err.contains(name), "{err}");
        }
        let msh = dir.path().join("m.msh");
        assert!(matches!(read_mesh_point_array(&msh, "scalar"), Err(IoError::UnsupportedExtension { .. })));
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
}
