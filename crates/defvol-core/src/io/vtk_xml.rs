//! VTK XML unstructured grids (`.vtu`), read as VTK, ParaView and meshio write them: data
//! arrays in ascii, inline binary (base64; the header and the data encoded together or apart;
//! compressed by zlib, lz4 or lzma, or not; UInt32 or UInt64 headers) or appended (raw or
//! base64), in either byte order; every piece; other cells than tets counted and skipped.
//! roxmltree parses the XML; the data are decoded here, every size checked against the
//! bytes that are really there before anything is allocated from it.

use std::io::Read;

use base64::Engine;
use nalgebra::Vector3;
use roxmltree::{Document, Node};

use super::error::MAX_DECODED_BYTES;
use super::mesh_file::{MeshFile, PointArray};
use super::solids;

/// What went wrong, in words; the caller adds the file's name.
type Fault = String;

const VTK_TETRA: i64 = 10;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Compressor {
    None,
    Zlib,
    Lz4,
    Lzma,
}

#[derive(Debug, Clone, Copy)]
struct Layout {
    big_endian: bool,
    /// Bytes of a header integer: 4 (UInt32) or 8 (UInt64).
    header: usize,
    compressor: Compressor,
}

/// The appended section: its encoding and the bytes after the `_` marker.
struct Appended<'a> {
    base64: bool,
    bytes: &'a [u8],
}

pub(super) fn parse(bytes: &[u8]) -> Result<MeshFile, Fault> {
    // Appended raw data is not XML: parse what precedes it, and keep the bytes apart.
    let (xml, appended) = match find(bytes, b"<AppendedData") {
        Some(start) => {
            let tag_end = find(&bytes[start..], b">").ok_or("<AppendedData> never closes")? + start;
            let tag = std::str::from_utf8(&bytes[start..tag_end]).map_err(|_| "<AppendedData> is not text")?;
            let base64 = !tag.contains("\"raw\"");
            let marker =
                bytes[tag_end + 1..].iter().position(|b| *b == b'_').ok_or("appended data has no `_` marker")?;
            let data = &bytes[tag_end + 2 + marker..];
            let mut xml = std::str::from_utf8(&bytes[..start])
                .map_err(|_| "the XML before the appended data is not UTF-8")?
                .to_owned();
            xml.push_str("</VTKFile>");
            (xml, Some(Appended { base64, bytes: data }))
        }
        None => (
            std::str::from_utf8(bytes).map_err(|_| "not UTF-8 text (binary data outside <AppendedData>?)")?.to_owned(),
            None,
        ),
    };
    let doc = Document::parse(&xml).map_err(|e| format!("not well-formed XML: {e}"))?;
    let root = doc.root_element();
    if root.tag_name().name() != "VTKFile" {
        return Err(format!("the root element is <{}>, not <VTKFile>", root.tag_name().name()));
    }
    match root.attribute("type") {
        Some("UnstructuredGrid") => {}
        other => {
            return Err(format!("VTKFile type {}: only UnstructuredGrid holds tetrahedra", other.unwrap_or("missing")))
        }
    }
    let layout = Layout {
        big_endian: match root.attribute("byte_order") {
            None | Some("LittleEndian") => false,
            Some("BigEndian") => true,
            Some(other) => return Err(format!("byte_order `{other}` is neither LittleEndian nor BigEndian")),
        },
        header: match root.attribute("header_type") {
            None | Some("UInt32") => 4,
            Some("UInt64") => 8,
            Some(other) => return Err(format!("header_type `{other}` is neither UInt32 nor UInt64")),
        },
        compressor: match root.attribute("compressor") {
            None | Some("") => Compressor::None,
            Some("vtkZLibDataCompressor") => Compressor::Zlib,
            Some("vtkLZ4DataCompressor") => Compressor::Lz4,
            Some("vtkLZMADataCompressor") => Compressor::Lzma,
            Some(other) => return Err(format!("compressor `{other}` is not zlib, lz4 or lzma")),
        },
    };
    let grid = child(root, "UnstructuredGrid")?;
    let mut mesh = MeshFile::default();
    let pieces: Vec<Node> = grid.children().filter(|n| n.has_tag_name("Piece")).collect();
    if pieces.is_empty() {
        return Err("the grid has no <Piece>".into());
    }
    for piece in pieces {
        read_piece(piece, &layout, appended.as_ref(), &mut mesh)?;
    }
    let unit = grid
        .children()
        .filter(|n| n.has_tag_name("FieldData"))
        .flat_map(|data| data.children())
        .find(|n| n.has_tag_name("DataArray") && n.attribute("Name") == Some(super::vtk::UNIT_ARRAY));
    if let Some(node) = unit {
        mesh.record_unit(&values(node, &layout, appended.as_ref(), Some(1))?);
    }
    Ok(mesh)
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    haystack.windows(needle.len()).position(|w| w == needle)
}

fn child<'a, 'i>(node: Node<'a, 'i>, name: &str) -> Result<Node<'a, 'i>, Fault> {
    node.children()
        .find(|n| n.has_tag_name(name))
        .ok_or_else(|| format!("<{}> has no <{name}>", node.tag_name().name()))
}

fn count_attribute(node: Node, name: &str) -> Result<usize, Fault> {
    let text = node.attribute(name).ok_or_else(|| format!("<{}> has no {name}", node.tag_name().name()))?;
    text.trim().parse().map_err(|_| format!("{name}=\"{text}\" is not a count"))
}

fn read_piece(piece: Node, layout: &Layout, appended: Option<&Appended>, mesh: &mut MeshFile) -> Result<(), Fault> {
    let points = count_attribute(piece, "NumberOfPoints")?;
    let cells = count_attribute(piece, "NumberOfCells")?;
    let first_node = mesh.nodes.len();
    let coords = child(child(piece, "Points")?, "DataArray")?;
    let coords = values(coords, layout, appended, points.checked_mul(3))?;
    if Some(coords.len()) != points.checked_mul(3) {
        return Err(format!("{} point coordinates for {points} points", coords.len()));
    }
    mesh.nodes.extend(coords.chunks_exact(3).map(|c| Vector3::new(c[0], c[1], c[2])));
    let cell_node = child(piece, "Cells")?;
    let array = |name: &str| -> Result<Node, Fault> {
        cell_node
            .children()
            .find(|n| n.has_tag_name("DataArray") && n.attribute("Name") == Some(name))
            .ok_or_else(|| format!("<Cells> has no {name} array"))
    };
    let types = values(array("types")?, layout, appended, Some(cells))?;
    let offsets = values(array("offsets")?, layout, appended, Some(cells))?;
    if types.len() != cells || offsets.len() != cells {
        return Err(format!("{} cell types and {} offsets for {cells} cells", types.len(), offsets.len()));
    }
    let total = offsets.last().map_or(0.0, |v| *v);
    let total = index(total, usize::MAX).map_err(|_| format!("the last cell offset {total} is not a count"))?;
    let connectivity = values(array("connectivity")?, layout, appended, Some(total))?;
    let mut start = 0usize;
    for (cell, (ty, end)) in types.iter().zip(&offsets).enumerate() {
        let end = index(*end, connectivity.len()).map_err(|e| format!("cell {cell}: offset {e}"))?;
        if end < start {
            return Err(format!("cell {cell}: offset {end} goes back before {start}"));
        }
        let vertices = &connectivity[start..end];
        start = end;
        if let Some((solid, order)) = solids::of_vtk(*ty as i64) {
            let mut global = Vec::with_capacity(vertices.len());
            for &v in vertices {
                let local = index(v, points.saturating_sub(1))
                    .map_err(|e| format!("cell {cell}: vertex {e} (the piece has {points} points)"))?;
                global.push(
                    u32::try_from(first_node + local).map_err(|_| format!("cell {cell}: vertex index beyond u32"))?,
                );
            }
            let nodes = solids::vtk_nodes(solid, order, &global).map_err(|why| format!("cell {cell}: {why}"))?;
            mesh.push_solid(solid, &nodes).map_err(|why| format!("cell {cell}: {why}"))?;
            continue;
        }
        if *ty as i64 != VTK_TETRA {
            *mesh.skipped.entry(cell_type_name(*ty as i64)).or_insert(0) += 1;
            continue;
        }
        let [a, b, c, d] = vertices[..] else {
            return Err(format!("cell {cell} is a tetra with {} vertices", vertices.len()));
        };
        let mut tet = [0u32; 4];
        for (slot, v) in tet.iter_mut().zip([a, b, c, d]) {
            let local = index(v, points.saturating_sub(1))
                .map_err(|e| format!("cell {cell}: vertex {e} (the piece has {points} points)"))?;
            *slot = u32::try_from(first_node + local).map_err(|_| format!("cell {cell}: vertex index beyond u32"))?;
        }
        mesh.tets.push(tet);
    }
    if let Some(data) = piece.children().find(|n| n.has_tag_name("PointData")) {
        let active = data.attribute("Scalars");
        for node in data.children().filter(|n| n.has_tag_name("DataArray")) {
            let name = node.attribute("Name").unwrap_or("").to_owned();
            let components = node
                .attribute("NumberOfComponents")
                .map_or(Ok(1), |c| c.trim().parse::<usize>())
                .map_err(|_| format!("array `{name}`: NumberOfComponents is not a count"))?;
            let expected = points.checked_mul(components.max(1));
            let raw = values(node, layout, appended, expected).map_err(|e| format!("point array `{name}`: {e}"))?;
            if Some(raw.len()) != expected {
                return Err(format!(
                    "point array `{name}`: {} values for {points} points of {components} components",
                    raw.len()
                ));
            }
            let values = raw.iter().map(|v| *v as f32).collect();
            mesh.push_array(
                first_node,
                PointArray { active_scalars: active == Some(name.as_str()), name, components, values },
            );
        }
    }
    Ok(())
}

/// A value as an index at most `max`; the error names the value.
fn index(v: f64, max: usize) -> Result<usize, String> {
    if v.is_finite() && v >= 0.0 && v.fract() == 0.0 && v <= max as f64 {
        Ok(v as usize)
    } else {
        Err(format!("{v} out of range"))
    }
}

/// VTK's names of the cells other than tets that meshes carry.
pub(super) fn cell_type_name(ty: i64) -> &'static str {
    match ty {
        1 => "vertex",
        2 => "poly-vertex",
        3 => "line",
        4 => "poly-line",
        5 => "triangle",
        6 => "triangle strip",
        7 => "polygon",
        8 => "pixel",
        9 => "quad",
        11 => "voxel",
        12 => "hexahedron",
        13 => "wedge",
        14 => "pyramid",
        21 => "quadratic edge",
        22 => "quadratic triangle",
        24 => "quadratic tetra",
        25 => "quadratic hexahedron",
        _ => "other cell",
    }
}

#[derive(Debug, Clone, Copy)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl Scalar {
    fn of(name: &str) -> Result<Self, Fault> {
        Ok(match name {
            "Int8" | "Char" => Self::I8,
            "UInt8" | "UChar" => Self::U8,
            "Int16" | "Short" => Self::I16,
            "UInt16" | "UShort" => Self::U16,
            "Int32" | "Int" => Self::I32,
            "UInt32" | "UInt" => Self::U32,
            "Int64" | "Long" => Self::I64,
            "UInt64" | "ULong" => Self::U64,
            "Float32" | "Float" => Self::F32,
            "Float64" | "Double" => Self::F64,
            other => return Err(format!("data type `{other}` is not numeric")),
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::I64 | Self::U64 | Self::F64 => 8,
        }
    }

    fn decode(self, bytes: &[u8], big_endian: bool) -> f64 {
        let mut b = [0u8; 8];
        b[..bytes.len()].copy_from_slice(bytes);
        if big_endian {
            b[..bytes.len()].reverse();
        }
        match self {
            Self::I8 => f64::from(b[0] as i8),
            Self::U8 => f64::from(b[0]),
            Self::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            Self::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Self::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Self::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Self::I64 => i64::from_le_bytes(b) as f64,
            Self::U64 => u64::from_le_bytes(b) as f64,
            Self::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Self::F64 => f64::from_le_bytes(b),
        }
    }
}

/// The values of a `<DataArray>`, whatever its format; `expected`: how many it should
/// hold, when known (the decoded bytes may not exceed that many elements).
fn values(
    node: Node,
    layout: &Layout,
    appended: Option<&Appended>,
    expected: Option<usize>,
) -> Result<Vec<f64>, Fault> {
    let scalar = Scalar::of(node.attribute("type").ok_or("a DataArray without a type")?)?;
    let limit =
        expected.and_then(|n| n.checked_mul(scalar.size())).map_or(MAX_DECODED_BYTES, |b| b.min(MAX_DECODED_BYTES));
    let bytes = match node.attribute("format").unwrap_or("ascii") {
        "ascii" => {
            let text = node.text().unwrap_or("");
            return text
                .split_ascii_whitespace()
                .take(expected.map_or(usize::MAX, |n| n.saturating_add(1)))
                .map(|t| {
                    t.parse::<f64>()
                        .map_err(|_| format!("`{}` is not a number", t.chars().take(20).collect::<String>()))
                })
                .collect();
        }
        "binary" => {
            let text: Vec<u8> = node.text().unwrap_or("").bytes().filter(|b| !b.is_ascii_whitespace()).collect();
            let mut source = Base64Groups::new(&text);
            block(&mut source, layout, limit)?
        }
        "appended" => {
            let appended = appended.ok_or("an appended DataArray but no <AppendedData>")?;
            let offset: usize = node
                .attribute("offset")
                .ok_or("an appended DataArray without an offset")?
                .trim()
                .parse()
                .map_err(|_| "a DataArray offset is not a count")?;
            let data = appended
                .bytes
                .get(offset..)
                .ok_or_else(|| format!("offset {offset} is past the {} appended bytes", appended.bytes.len()))?;
            if appended.base64 {
                let mut source = Base64Groups::new(data);
                block(&mut source, layout, limit)?
            } else {
                let mut source = RawBytes { bytes: data, position: 0 };
                block(&mut source, layout, limit)?
            }
        }
        other => return Err(format!("DataArray format `{other}` is not ascii, binary or appended")),
    };
    if bytes.len() % scalar.size() != 0 {
        return Err(format!("{} data bytes are not whole values of {} bytes", bytes.len(), scalar.size()));
    }
    Ok(bytes.chunks_exact(scalar.size()).map(|c| scalar.decode(c, layout.big_endian)).collect())
}

/// Where a block's bytes come from: raw appended bytes, or base64 decoded four characters
/// at a time (so that header and data encoded apart, each padded, decode as one stream).
trait Source {
    fn take(&mut self, n: usize) -> Result<Vec<u8>, Fault>;
}

struct RawBytes<'a> {
    bytes: &'a [u8],
    position: usize,
}

impl Source for RawBytes<'_> {
    fn take(&mut self, n: usize) -> Result<Vec<u8>, Fault> {
        let end = self
            .position
            .checked_add(n)
            .filter(|e| *e <= self.bytes.len())
            .ok_or_else(|| format!("{n} bytes wanted, {} left", self.bytes.len() - self.position))?;
        let out = self.bytes[self.position..end].to_vec();
        self.position = end;
        Ok(out)
    }
}

struct Base64Groups<'a> {
    text: &'a [u8],
    position: usize,
    /// Bytes of the last group decoded but not yet taken (header and data encoded together
    /// share a group).
    pending: Vec<u8>,
}

impl<'a> Base64Groups<'a> {
    fn new(text: &'a [u8]) -> Self {
        Self { text, position: 0, pending: Vec::new() }
    }
}

impl Source for Base64Groups<'_> {
    fn take(&mut self, n: usize) -> Result<Vec<u8>, Fault> {
        // Every 4 characters give at most 3 bytes: bound the work by what is there.
        let available = self.pending.len() + (self.text.len() - self.position.min(self.text.len())) / 4 * 3;
        if n > available {
            return Err(format!("{n} bytes wanted, the base64 text holds at most {available}"));
        }
        let mut out = std::mem::take(&mut self.pending);
        while out.len() < n {
            let group = self.text.get(self.position..self.position + 4).ok_or("the base64 text ends inside a value")?;
            self.position += 4;
            let decoded =
                base64::engine::general_purpose::STANDARD.decode(group).map_err(|e| format!("bad base64: {e}"))?;
            out.extend_from_slice(&decoded);
        }
        self.pending = out.split_off(n);
        Ok(out)
    }
}

/// One binary block: the header (a byte count, or the compressed block table), then the data.
fn block(source: &mut dyn Source, layout: &Layout, limit: usize) -> Result<Vec<u8>, Fault> {
    let int = |source: &mut dyn Source| -> Result<usize, Fault> {
        let bytes = source.take(layout.header)?;
        let mut b = [0u8; 8];
        b[..layout.header].copy_from_slice(&bytes);
        if layout.big_endian {
            b[..layout.header].reverse();
        }
        usize::try_from(u64::from_le_bytes(b)).map_err(|_| "a header value beyond this machine's sizes".into())
    };
    if layout.compressor == Compressor::None {
        let size = int(source)?;
        if size > limit {
            return Err(format!("a block of {size} bytes where at most {limit} belong"));
        }
        return source.take(size);
    }
    let blocks = int(source)?;
    let block_size = int(source)?;
    let last_size = int(source)?;
    let total = blocks
        .checked_sub(1)
        .and_then(|n| n.checked_mul(block_size))
        .map_or(0, |full| full.saturating_add(if last_size == 0 { block_size } else { last_size }));
    if blocks > 0 && total > limit {
        return Err(format!("{blocks} compressed blocks of {block_size} bytes where at most {limit} belong"));
    }
    let mut sizes = Vec::new();
    for _ in 0..blocks {
        sizes.push(int(source)?);
    }
    let mut out = Vec::new();
    for (k, compressed) in sizes.iter().enumerate() {
        let expect = if k + 1 == blocks && last_size != 0 { last_size } else { block_size };
        let data = source.take(*compressed)?;
        let decoded = decompress(&data, layout.compressor, expect)?;
        if decoded.len() != expect {
            return Err(format!("block {k} decompresses to {} bytes, not {expect}", decoded.len()));
        }
        out.extend_from_slice(&decoded);
    }
    Ok(out)
}

fn decompress(data: &[u8], compressor: Compressor, expect: usize) -> Result<Vec<u8>, Fault> {
    let mut out = Vec::new();
    let limit = expect as u64 + 1;
    match compressor {
        Compressor::None => out.extend_from_slice(data),
        Compressor::Zlib => {
            flate2::read::ZlibDecoder::new(data).take(limit).read_to_end(&mut out).map_err(|e| format!("zlib: {e}"))?;
        }
        Compressor::Lz4 => {
            // LZ4 expands at most 255-fold: a larger claim is a broken header, not a block.
            if expect > data.len().saturating_mul(255).saturating_add(16) {
                return Err(format!("an lz4 block of {} bytes cannot hold {expect}", data.len()));
            }
            out = lz4_flex::block::decompress(data, expect).map_err(|e| format!("lz4: {e}"))?;
        }
        Compressor::Lzma => {
            let mut limited = Limited { out: Vec::new(), limit: expect };
            lzma_rs::xz_decompress(&mut std::io::BufReader::new(data), &mut limited)
                .map_err(|e| format!("lzma: {e}"))?;
            out = limited.out;
        }
    }
    Ok(out)
}

/// A sink that refuses to grow past `limit` bytes: a stream that claims less than it holds
/// is cut there, not grown into.
struct Limited {
    out: Vec<u8>,
    limit: usize,
}

impl std::io::Write for Limited {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if self.out.len() + buf.len() > self.limit {
            return Err(std::io::Error::other(format!("more than the {} bytes the block holds", self.limit)));
        }
        self.out.extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}
