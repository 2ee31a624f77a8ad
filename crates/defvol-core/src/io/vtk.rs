//! VTK writers: `.vtu` as VTK's own XML writer does by default (inline binary, zlib blocks
//! of 32 KiB under UInt32 headers) and legacy `.vtk` 4.2 BINARY (big-endian, as the format
//! says). ParaView, VTK and meshio read both.

use std::io::Write;

use base64::Engine;

/// VTK cell types the writers use.
pub(super) const TETRA: u8 = 10;
pub(super) const TRIANGLE: u8 = 5;

const BLOCK: usize = 1 << 15;

/// One data array as VTK's zlib-compressed binary: the block table, then the blocks, each
/// base64-encoded apart (as VTK encodes them).
fn compressed(bytes: &[u8]) -> String {
    let blocks: Vec<Vec<u8>> = bytes
        .chunks(BLOCK)
        .map(|chunk| {
            let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
            // Writing into memory cannot fail.
            let _ = z.write_all(chunk);
            z.finish().unwrap_or_default()
        })
        .collect();
    let last = bytes.len() % BLOCK;
    let mut header: Vec<u32> = vec![blocks.len() as u32, BLOCK as u32, last as u32];
    header.extend(blocks.iter().map(|b| b.len() as u32));
    let engine = base64::engine::general_purpose::STANDARD;
    let mut out = engine.encode(bytemuck::cast_slice::<u32, u8>(&header));
    out.push_str(&engine.encode(blocks.concat()));
    out
}

fn data_array(out: &mut String, ty: &str, name: &str, components: usize, bytes: &[u8]) {
    let name = if name.is_empty() { String::new() } else { format!(" Name=\"{name}\"") };
    out.push_str(&format!(
        "        <DataArray type=\"{ty}\"{name} NumberOfComponents=\"{components}\" format=\"binary\">\n          "
    ));
    out.push_str(&compressed(bytes));
    out.push_str("\n        </DataArray>\n");
}

/// The name of the one-value field-data array that records a file's length unit: numeric,
/// because meshio refuses VTK's String arrays.
pub(super) const UNIT_ARRAY: &str = "metres_per_unit";

/// An unstructured grid of one cell type as `.vtu` bytes.
pub(super) fn xml<const N: usize>(
    points: &[[f64; 3]],
    cells: &[[u32; N]],
    cell_type: u8,
    scalars: Option<&[f32]>,
    metres_per_unit: Option<f64>,
) -> Vec<u8> {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt32\" compressor=\"vtkZLibDataCompressor\">\n  <UnstructuredGrid>\n");
    if let Some(unit) = metres_per_unit {
        s.push_str(&format!(
            "    <FieldData>\n      <DataArray type=\"Float64\" Name=\"{UNIT_ARRAY}\" NumberOfTuples=\"1\" format=\"ascii\">{unit:?}</DataArray>\n    </FieldData>\n"
        ));
    }
    s.push_str(&format!("    <Piece NumberOfPoints=\"{}\" NumberOfCells=\"{}\">\n", points.len(), cells.len()));
    if let Some(values) = scalars {
        s.push_str("      <PointData Scalars=\"scalar\">\n");
        data_array(&mut s, "Float32", "scalar", 1, bytemuck::cast_slice(values));
        s.push_str("      </PointData>\n");
    }
    s.push_str("      <Points>\n");
    data_array(&mut s, "Float64", "", 3, bytemuck::cast_slice(points));
    s.push_str("      </Points>\n      <Cells>\n");
    let connectivity: Vec<i64> = cells.iter().flatten().map(|v| i64::from(*v)).collect();
    let offsets: Vec<i64> = (1..=cells.len() as i64).map(|c| c * N as i64).collect();
    data_array(&mut s, "Int64", "connectivity", 1, bytemuck::cast_slice(&connectivity));
    data_array(&mut s, "Int64", "offsets", 1, bytemuck::cast_slice(&offsets));
    data_array(&mut s, "UInt8", "types", 1, &vec![cell_type; cells.len()]);
    s.push_str("      </Cells>\n    </Piece>\n  </UnstructuredGrid>\n</VTKFile>\n");
    s.into_bytes()
}

/// An unstructured grid of one cell type as legacy `.vtk` 4.2 BINARY bytes.
pub(super) fn legacy<const N: usize>(
    points: &[[f64; 3]],
    cells: &[[u32; N]],
    cell_type: u8,
    scalars: Option<&[f32]>,
    metres_per_unit: Option<f64>,
    title: &str,
) -> Vec<u8> {
    let mut out = format!(
        "# vtk DataFile Version 4.2\n{title}\nBINARY\nDATASET UNSTRUCTURED_GRID\nPOINTS {} double\n",
        points.len()
    )
    .into_bytes();
    for v in points.iter().flatten() {
        out.extend_from_slice(&v.to_be_bytes());
    }
    out.extend_from_slice(format!("\nCELLS {} {}\n", cells.len(), cells.len() * (N + 1)).as_bytes());
    for cell in cells {
        out.extend_from_slice(&(N as i32).to_be_bytes());
        for v in cell {
            out.extend_from_slice(&(*v as i32).to_be_bytes());
        }
    }
    out.extend_from_slice(format!("\nCELL_TYPES {}\n", cells.len()).as_bytes());
    for _ in cells {
        out.extend_from_slice(&i32::from(cell_type).to_be_bytes());
    }
    // After the cells, where meshio as well as VTK reads it as the dataset's field data.
    if let Some(unit) = metres_per_unit {
        out.extend_from_slice(format!("\nFIELD FieldData 1\n{UNIT_ARRAY} 1 1 double\n").as_bytes());
        out.extend_from_slice(&unit.to_be_bytes());
    }
    if let Some(values) = scalars {
        out.extend_from_slice(
            format!("\nPOINT_DATA {}\nSCALARS scalar float 1\nLOOKUP_TABLE default\n", points.len()).as_bytes(),
        );
        for v in values {
            out.extend_from_slice(&v.to_be_bytes());
        }
    }
    out.push(b'\n');
    out
}
