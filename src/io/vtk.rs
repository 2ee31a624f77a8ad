//! VTK unstructured grids (`.vtu` XML, `.vtk` legacy) through vtkio.

use std::path::Path;

use nalgebra::Vector3;
use vtkio::model::{
    Attribute, Attributes, ByteOrder, CellType, Cells, DataArray, DataSet, ElementType, UnstructuredGridPiece, Version,
    VertexNumbers,
};
use vtkio::Vtk;

use super::{malformed, IoError};

pub(super) type MeshParts = (Vec<Vector3<f64>>, Vec<[u32; 4]>, Option<Vec<f32>>);

pub(super) fn read(path: &Path) -> Result<MeshParts, IoError> {
    let (nodes, tets, point_data) = read_with_point_data(path)?;
    // The mesh's own scalars: the first array tagged as scalars.
    let scalars = point_data.into_iter().find_map(|a| if a.tagged_scalars { a.values } else { None });
    Ok((nodes, tets, scalars))
}

/// The named one-component point array; an error lists the arrays the file has.
pub(super) fn read_point_array(path: &Path, name: &str) -> Result<Vec<f32>, IoError> {
    let (_, _, point_data) = read_with_point_data(path)?;
    let names: Vec<&str> = point_data.iter().filter(|a| a.values.is_some()).map(|a| a.name.as_str()).collect();
    let message = format!("no one-component point array `{name}`; it has {names:?}");
    point_data.into_iter().find(|a| a.name == name).and_then(|a| a.values).ok_or_else(|| malformed(path, message))
}

/// A point array: its values when it has one numeric component.
struct PointArray {
    name: String,
    values: Option<Vec<f32>>,
    /// Tagged as scalars (legacy SCALARS, XML Scalars="…"), not just a generic array.
    tagged_scalars: bool,
}

/// Nodes, tets and the point arrays of a file.
type MeshWithArrays = (Vec<Vector3<f64>>, Vec<[u32; 4]>, Vec<PointArray>);

fn read_with_point_data(path: &Path) -> Result<MeshWithArrays, IoError> {
    if !path.exists() {
        return Err(IoError::Io {
            path: path.to_owned(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "file not found"),
        });
    }
    let vtk = Vtk::import(path).map_err(|e| malformed(path, format!("not a readable VTK file: {e}")))?;
    let DataSet::UnstructuredGrid { pieces, .. } = vtk.data else {
        return Err(malformed(path, "not an unstructured grid"));
    };
    let Some(piece) = pieces.into_iter().next() else {
        return Err(malformed(path, "unstructured grid has no pieces"));
    };
    let piece =
        piece.into_loaded_piece_data(None).map_err(|e| malformed(path, format!("cannot load the grid: {e}")))?;
    let Some(coords) = piece.points.cast_into::<f64>() else {
        return Err(malformed(path, "points are not numeric"));
    };
    if coords.len() % 3 != 0 {
        return Err(malformed(path, format!("{} point coordinates is not a multiple of 3", coords.len())));
    }
    let nodes: Vec<Vector3<f64>> = coords.chunks_exact(3).map(|c| Vector3::new(c[0], c[1], c[2])).collect();
    let types = piece.cells.types;
    let (connectivity, offsets) = piece.cells.cell_verts.into_xml();
    let mut tets = Vec::new();
    let mut start = 0usize;
    for (cell, (&end, ty)) in offsets.iter().zip(&types).enumerate() {
        let verts = &connectivity[start..end as usize];
        start = end as usize;
        match ty {
            CellType::Tetra => {
                let Ok(t) = <[u64; 4]>::try_from(verts) else {
                    return Err(malformed(path, format!("cell {cell} is a tetra with {} vertices", verts.len())));
                };
                let idx = t.map(|v| u32::try_from(v).unwrap_or(u32::MAX));
                tets.push(idx);
            }
            CellType::Vertex
            | CellType::PolyVertex
            | CellType::Line
            | CellType::PolyLine
            | CellType::Triangle
            | CellType::TriangleStrip
            | CellType::Polygon
            | CellType::Pixel
            | CellType::Quad => {}
            other => {
                return Err(malformed(
                    path,
                    format!("cell {cell} has type {other:?}; only linear tetrahedra are supported"),
                ))
            }
        }
    }
    let point_data = piece
        .data
        .point
        .into_iter()
        .map(|a| match a {
            Attribute::DataArray(DataArray { name, elem: ElementType::Scalars { num_comp: 1, .. }, data }) => {
                PointArray { name, values: data.cast_into::<f32>(), tagged_scalars: true }
            }
            Attribute::DataArray(DataArray { name, elem: ElementType::Generic(1), data }) => {
                PointArray { name, values: data.cast_into::<f32>(), tagged_scalars: false }
            }
            Attribute::DataArray(DataArray { name, .. }) | Attribute::Field { name, .. } => {
                PointArray { name, values: None, tagged_scalars: false }
            }
        })
        .collect();
    Ok((nodes, tets, point_data))
}

pub(super) fn write(
    path: &Path,
    nodes: &[Vector3<f64>],
    tets: &[[u32; 4]],
    scalars: Option<&[f32]>,
) -> Result<(), IoError> {
    let points: Vec<f64> = nodes.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
    write_cells(path, points, tets, CellType::Tetra, scalars, "defvol tetrahedral mesh")
}

/// A triangle surface (a height field, a boundary) as an unstructured grid of triangles.
pub(super) fn write_triangles(
    path: &Path,
    nodes: &[[f32; 3]],
    triangles: &[[u32; 3]],
    scalars: Option<&[f32]>,
) -> Result<(), IoError> {
    let points: Vec<f64> = nodes.iter().flat_map(|p| p.map(f64::from)).collect();
    write_cells(path, points, triangles, CellType::Triangle, scalars, "defvol surface")
}

fn write_cells<const N: usize>(
    path: &Path,
    points: Vec<f64>,
    cells: &[[u32; N]],
    cell_type: CellType,
    scalars: Option<&[f32]>,
    title: &str,
) -> Result<(), IoError> {
    let xml = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("vtu"));
    let cell_verts = if xml {
        VertexNumbers::XML {
            connectivity: cells.iter().flat_map(|c| c.map(u64::from)).collect(),
            offsets: (1..=cells.len() as u64).map(|c| N as u64 * c).collect(),
        }
    } else {
        VertexNumbers::Legacy {
            num_cells: cells.len() as u32,
            vertices: cells.iter().flat_map(|c| std::iter::once(N as u32).chain(c.iter().copied())).collect(),
        }
    };
    let mut data = Attributes::new();
    if let Some(s) = scalars {
        data.point.push(Attribute::DataArray(DataArray::scalars("scalar", 1).with_data(s.to_vec())));
    }
    let piece = UnstructuredGridPiece {
        points: points.into(),
        cells: Cells { cell_verts, types: vec![cell_type; cells.len()] },
        data,
    };
    let vtk = Vtk {
        version: if xml { Version::new((1, 0)) } else { Version::new((4, 2)) },
        title: title.into(),
        // Legacy binary VTK is big-endian by specification.
        byte_order: if xml { ByteOrder::LittleEndian } else { ByteOrder::BigEndian },
        file_path: None,
        data: DataSet::inline(piece),
    };
    vtk.export(path).map_err(|e| malformed(path, format!("cannot write VTK: {e}")))
}
