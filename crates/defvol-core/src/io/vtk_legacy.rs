//! Legacy VTK unstructured grids (`.vtk`, versions 2.0 to 5.1, ASCII and BINARY): CELLS as
//! counts (before 5.1) or as OFFSETS and CONNECTIVITY (5.1, as VTK 9 and meshio write them);
//! point data as SCALARS (the active scalars) or FIELD arrays; METADATA blocks skipped. Every
//! count is checked against the bytes that are there before anything is allocated from it.

use nalgebra::Vector3;

use super::mesh_file::{MeshFile, PointArray};
use super::solids;

type Fault = String;

const VTK_TETRA: usize = 10;

struct Cursor<'a> {
    bytes: &'a [u8],
    position: usize,
    binary: bool,
}

impl<'a> Cursor<'a> {
    fn skip_space(&mut self) {
        while self.bytes.get(self.position).is_some_and(|b| b.is_ascii_whitespace()) {
            self.position += 1;
        }
    }

    /// The next whitespace-separated word, or `None` at the end.
    fn word(&mut self) -> Option<&'a str> {
        self.skip_space();
        let start = self.position;
        while self.bytes.get(self.position).is_some_and(|b| !b.is_ascii_whitespace()) {
            self.position += 1;
        }
        (self.position > start).then(|| std::str::from_utf8(&self.bytes[start..self.position]).unwrap_or("\u{fffd}"))
    }

    fn expect_word(&mut self, what: &str) -> Result<&'a str, Fault> {
        self.word().ok_or_else(|| format!("the file ends where {what} should be"))
    }

    fn count(&mut self, what: &str) -> Result<usize, Fault> {
        let w = self.expect_word(what)?;
        w.parse().map_err(|_| format!("{what}: `{}` is not a count", w.chars().take(20).collect::<String>()))
    }

    /// The rest of the current line.
    fn line(&mut self) -> &'a str {
        let start = self.position;
        while self.bytes.get(self.position).is_some_and(|b| *b != b'\n') {
            self.position += 1;
        }
        let line = &self.bytes[start..self.position];
        self.position = (self.position + 1).min(self.bytes.len());
        std::str::from_utf8(line).unwrap_or("").trim()
    }

    /// `n` values of `ty`: words in ASCII files; big-endian bytes after the line in binary ones.
    fn values(&mut self, n: usize, ty: &str) -> Result<Vec<f64>, Fault> {
        let size = match ty {
            "bit" => return Err("bit arrays are not supported".into()),
            "unsigned_char" | "char" => 1,
            "unsigned_short" | "short" => 2,
            "unsigned_int" | "int" | "float" => 4,
            "unsigned_long" | "long" | "double" | "vtktypeint64" | "vtktypeuint64" => 8,
            other => return Err(format!("data type `{other}` is not numeric")),
        };
        if !self.binary {
            // A value takes at least two bytes of text (a digit and a separator).
            if n > (self.bytes.len() - self.position) / 2 + 1 {
                return Err(format!("{n} values announced, the file is shorter"));
            }
            let mut out = Vec::with_capacity(n);
            for _ in 0..n {
                let w = self.expect_word("a value")?;
                out.push(
                    w.parse::<f64>()
                        .map_err(|_| format!("`{}` is not a number", w.chars().take(20).collect::<String>()))?,
                );
            }
            return Ok(out);
        }
        // Binary data start after the keyword line's newline.
        self.line();
        let bytes = n.checked_mul(size).ok_or_else(|| format!("{n} values of {size} bytes overflow"))?;
        let end = self
            .position
            .checked_add(bytes)
            .filter(|e| *e <= self.bytes.len())
            .ok_or_else(|| format!("{n} {ty} values announced, {} bytes left", self.bytes.len() - self.position))?;
        let data = &self.bytes[self.position..end];
        self.position = end;
        Ok(data
            .chunks_exact(size)
            .map(|c| {
                let mut b = [0u8; 8];
                b[..size].copy_from_slice(c);
                b[..size].reverse();
                match ty {
                    "unsigned_char" => f64::from(b[0]),
                    "char" => f64::from(b[0] as i8),
                    "unsigned_short" => f64::from(u16::from_le_bytes([b[0], b[1]])),
                    "short" => f64::from(i16::from_le_bytes([b[0], b[1]])),
                    "unsigned_int" => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    "int" => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    "float" => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    "double" => f64::from_le_bytes(b),
                    "unsigned_long" | "vtktypeuint64" => u64::from_le_bytes(b) as f64,
                    _ => i64::from_le_bytes(b) as f64,
                }
            })
            .collect())
    }
}

fn as_index(v: f64, limit: usize, what: &str) -> Result<usize, Fault> {
    if v.is_finite() && v >= 0.0 && v.fract() == 0.0 && v < limit as f64 {
        Ok(v as usize)
    } else {
        Err(format!("{what} {v} is out of range (below {limit})"))
    }
}

pub(super) fn parse(bytes: &[u8]) -> Result<MeshFile, Fault> {
    let mut c = Cursor { bytes, position: 0, binary: false };
    let magic = c.line();
    if !magic.starts_with("# vtk DataFile Version") {
        return Err("missing the `# vtk DataFile Version` line".into());
    }
    let _title = c.line();
    c.binary = match c.line().to_ascii_uppercase().as_str() {
        "ASCII" => false,
        "BINARY" => true,
        other => return Err(format!("format `{other}` is neither ASCII nor BINARY")),
    };
    let mut mesh = MeshFile::default();
    let mut points = 0usize;
    let mut cell_types: Vec<usize> = Vec::new();
    let mut cells: Vec<Vec<usize>> = Vec::new();
    let mut point_data = false;
    while let Some(keyword) = c.word() {
        match keyword.to_ascii_uppercase().as_str() {
            "DATASET" => {
                let kind = c.expect_word("the dataset type")?;
                if !kind.eq_ignore_ascii_case("UNSTRUCTURED_GRID") {
                    return Err(format!("DATASET {kind}: only UNSTRUCTURED_GRID holds tetrahedra"));
                }
            }
            "POINTS" => {
                points = c.count("the point count")?;
                let ty = c.expect_word("the point type")?;
                let n = points.checked_mul(3).ok_or("the point count overflows")?;
                let coords = c.values(n, ty)?;
                mesh.nodes = coords.chunks_exact(3).map(|v| Vector3::new(v[0], v[1], v[2])).collect();
            }
            "CELLS" => {
                let first = c.count("the cell count")?;
                let second = c.count("the cell list size")?;
                cells = read_cells(&mut c, first, second, points)?;
            }
            "CELL_TYPES" => {
                let n = c.count("the cell type count")?;
                cell_types = c
                    .values(n, "int")?
                    .into_iter()
                    .map(|t| as_index(t, 1 << 16, "cell type"))
                    .collect::<Result<_, _>>()?;
            }
            "POINT_DATA" => {
                let n = c.count("the point data count")?;
                if n != points {
                    return Err(format!("POINT_DATA {n} for {points} points"));
                }
                point_data = true;
            }
            "CELL_DATA" => {
                // Cell data are not kept: the arrays that follow are skipped.
                c.count("the cell data count")?;
                point_data = false;
            }
            "SCALARS" => {
                let name = c.expect_word("the array name")?.to_owned();
                let ty = c.expect_word("the array type")?;
                // An optional component count, then LOOKUP_TABLE.
                let mut components = 1;
                let mut next = c.expect_word("LOOKUP_TABLE")?;
                if let Ok(k) = next.parse::<usize>() {
                    components = k.clamp(1, 4);
                    next = c.expect_word("LOOKUP_TABLE")?;
                }
                if !next.eq_ignore_ascii_case("LOOKUP_TABLE") {
                    return Err(format!("SCALARS {name}: expected LOOKUP_TABLE, found `{next}`"));
                }
                c.expect_word("the lookup table name")?;
                let rows = array_rows(point_data, points, &cells);
                let values = c.values(rows.checked_mul(components).ok_or("the array size overflows")?, ty)?;
                if point_data {
                    mesh.arrays.push(PointArray {
                        name,
                        components,
                        values: values.iter().map(|v| *v as f32).collect(),
                        active_scalars: true,
                    });
                }
            }
            "VECTORS" | "NORMALS" => {
                let name = c.expect_word("the array name")?.to_owned();
                let ty = c.expect_word("the array type")?;
                let rows = array_rows(point_data, points, &cells);
                let values = c.values(rows.checked_mul(3).ok_or("the array size overflows")?, ty)?;
                if point_data {
                    mesh.arrays.push(PointArray {
                        name,
                        components: 3,
                        values: values.iter().map(|v| *v as f32).collect(),
                        active_scalars: false,
                    });
                }
            }
            "FIELD" => {
                c.expect_word("the field name")?;
                let arrays = c.count("the field's array count")?;
                for _ in 0..arrays {
                    let name = c.expect_word("the array name")?.to_owned();
                    if name.eq_ignore_ascii_case("METADATA") {
                        skip_metadata(&mut c);
                        continue;
                    }
                    let components = c.count("the array's component count")?;
                    let tuples = c.count("the array's tuple count")?;
                    let ty = c.expect_word("the array type")?;
                    let values = c.values(components.checked_mul(tuples).ok_or("the array size overflows")?, ty)?;
                    if !point_data && name == super::vtk::UNIT_ARRAY {
                        mesh.record_unit(&values);
                    } else if point_data && tuples == points {
                        mesh.arrays.push(PointArray {
                            name,
                            components,
                            values: values.iter().map(|v| *v as f32).collect(),
                            active_scalars: false,
                        });
                    }
                }
            }
            "METADATA" => skip_metadata(&mut c),
            "LOOKUP_TABLE" => {
                c.expect_word("the table name")?;
                let n = c.count("the table size")?;
                c.values(
                    n.checked_mul(4).ok_or("the table size overflows")?,
                    if c.binary { "unsigned_char" } else { "float" },
                )?;
            }
            other => return Err(format!("unknown keyword `{}`", other.chars().take(30).collect::<String>())),
        }
    }
    if cells.len() != cell_types.len() {
        return Err(format!("{} cells but {} cell types", cells.len(), cell_types.len()));
    }
    for (cell, (vertices, ty)) in cells.iter().zip(&cell_types).enumerate() {
        if let Some((solid, order)) = solids::of_vtk(*ty as i64) {
            let global: Vec<u32> = vertices.iter().map(|&v| u32::try_from(v).unwrap_or(u32::MAX)).collect();
            let nodes = solids::vtk_nodes(solid, order, &global).map_err(|why| format!("cell {cell}: {why}"))?;
            mesh.push_solid(solid, &nodes).map_err(|why| format!("cell {cell}: {why}"))?;
            continue;
        }
        if *ty != VTK_TETRA {
            *mesh.skipped.entry(super::vtk_xml::cell_type_name(*ty as i64)).or_insert(0) += 1;
            continue;
        }
        let [a, b, c, d] = vertices[..] else {
            return Err(format!("cell {cell} is a tetra with {} vertices", vertices.len()));
        };
        mesh.tets.push([a, b, c, d].map(|v| v as u32));
    }
    Ok(mesh)
}

/// Rows of an attribute array: one per point (or per cell, for cell data that is skipped).
fn array_rows(point_data: bool, points: usize, cells: &[Vec<usize>]) -> usize {
    if point_data {
        points
    } else {
        cells.len()
    }
}

/// A METADATA block runs to the next blank line.
fn skip_metadata(c: &mut Cursor) {
    c.line();
    while c.position < c.bytes.len() && !c.line().is_empty() {}
}

/// CELLS: counts (`n size`, each cell `k v1 … vk`) before 5.1; from 5.1 `offsets+1 size`
/// then OFFSETS and CONNECTIVITY arrays.
fn read_cells(c: &mut Cursor, first: usize, second: usize, points: usize) -> Result<Vec<Vec<usize>>, Fault> {
    let before = c.position;
    let next = c.word();
    c.position = before;
    if next.is_some_and(|w| w.eq_ignore_ascii_case("OFFSETS")) {
        c.word();
        let ty = c.expect_word("the offset type")?;
        let offsets = c.values(first, ty)?;
        let keyword = c.expect_word("CONNECTIVITY")?;
        if !keyword.eq_ignore_ascii_case("CONNECTIVITY") {
            return Err(format!("expected CONNECTIVITY, found `{keyword}`"));
        }
        let ty = c.expect_word("the connectivity type")?;
        let connectivity = c.values(second, ty)?;
        let mut cells = Vec::with_capacity(first.saturating_sub(1));
        for (k, pair) in offsets.windows(2).enumerate() {
            let start = as_index(pair[0], connectivity.len() + 1, "offset")?;
            let end = as_index(pair[1], connectivity.len() + 1, "offset")?;
            if end < start {
                return Err(format!("cell {k}: offset {end} goes back before {start}"));
            }
            cells.push(
                connectivity[start..end].iter().map(|v| as_index(*v, points, "vertex")).collect::<Result<_, _>>()?,
            );
        }
        return Ok(cells);
    }
    let list = c.values(second, "int")?;
    let mut cells = Vec::new();
    let mut at = 0;
    for k in 0..first {
        let n = as_index(
            *list.get(at).ok_or_else(|| format!("cell {k}: the cell list ends"))?,
            list.len(),
            "vertex count",
        )?;
        let vertices =
            list.get(at + 1..at + 1 + n).ok_or_else(|| format!("cell {k}: {n} vertices past the cell list"))?;
        cells.push(vertices.iter().map(|v| as_index(*v, points, "vertex")).collect::<Result<_, _>>()?);
        at += 1 + n;
    }
    Ok(cells)
}
