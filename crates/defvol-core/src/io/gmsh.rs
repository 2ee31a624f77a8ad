//! Gmsh `.msh` version 1 (ASCII), 2.2 and 4.1 (ASCII and binary), read here (every count checked
//! against the bytes that are there); written as 4.1 ASCII. Linear tets (type 4) become the
//! mesh, hexahedra, prisms and pyramids (types 5-7) are split into tets; the other elements
//! Gmsh writes beside them (points, lines, boundary triangles of the physical groups) are
//! counted and skipped.

use std::collections::HashMap;

use nalgebra::Vector3;

use super::mesh_file::{CellArray, MeshFile};
use super::solids::Solid;

type Fault = String;

const TET4: u32 = 4;

/// Nodes per element of Gmsh's element types (`None`: a type this reader does not know).
fn nodes_per_element(ty: u32) -> Option<usize> {
    Some(match ty {
        1 => 2,
        2 => 3,
        3 => 4,
        4 => 4,
        5 => 8,
        6 => 6,
        7 => 5,
        8 => 3,
        9 => 6,
        10 => 9,
        11 => 10,
        12 => 27,
        13 => 18,
        14 => 14,
        15 => 1,
        16 => 8,
        17 => 20,
        18 => 15,
        19 => 13,
        _ => return None,
    })
}

fn element_name(ty: u32) -> &'static str {
    match ty {
        1 => "line",
        2 => "triangle",
        3 => "quadrangle",
        5 => "hexahedron",
        6 => "prism",
        7 => "pyramid",
        8 => "quadratic line",
        9 => "quadratic triangle",
        11 => "quadratic tetrahedron",
        15 => "point",
        _ => "other element",
    }
}

/// Text and binary reads over the file's bytes.
struct Cursor<'a> {
    bytes: &'a [u8],
    position: usize,
    /// Bytes of a `size_t` in binary files (4.1).
    size_t: usize,
}

impl<'a> Cursor<'a> {
    fn remaining(&self) -> usize {
        self.bytes.len() - self.position
    }

    fn word(&mut self) -> Option<&'a str> {
        while self.bytes.get(self.position).is_some_and(|b| b.is_ascii_whitespace()) {
            self.position += 1;
        }
        let start = self.position;
        while self.bytes.get(self.position).is_some_and(|b| !b.is_ascii_whitespace()) {
            self.position += 1;
        }
        (self.position > start).then(|| std::str::from_utf8(&self.bytes[start..self.position]).unwrap_or("\u{fffd}"))
    }

    fn number<T: std::str::FromStr>(&mut self, what: &str) -> Result<T, Fault> {
        let w = self.word().ok_or_else(|| format!("the file ends where {what} should be"))?;
        w.parse().map_err(|_| format!("{what}: `{}` is not a number", w.chars().take(20).collect::<String>()))
    }

    /// Skips the rest of the line (before binary data).
    fn end_line(&mut self) {
        while self.bytes.get(self.position).is_some_and(|b| *b != b'\n') {
            self.position += 1;
        }
        self.position = (self.position + 1).min(self.bytes.len());
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], Fault> {
        if n > self.remaining() {
            return Err(format!("{n} bytes of binary data announced, {} left", self.remaining()));
        }
        let out = &self.bytes[self.position..self.position + n];
        self.position += n;
        Ok(out)
    }

    fn int(&mut self) -> Result<i64, Fault> {
        let b = self.take(4)?;
        Ok(i64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])))
    }

    fn size(&mut self) -> Result<u64, Fault> {
        let b = self.take(self.size_t)?;
        let mut w = [0u8; 8];
        w[..b.len()].copy_from_slice(b);
        Ok(u64::from_le_bytes(w))
    }

    fn double(&mut self) -> Result<f64, Fault> {
        let b = self.take(8)?;
        Ok(f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
    }

    /// Skips to just after the line `$End<section>`.
    fn skip_section(&mut self, section: &str) -> Result<(), Fault> {
        let end = format!("$End{section}");
        let at = self.bytes[self.position..]
            .windows(end.len())
            .position(|w| w == end.as_bytes())
            .ok_or_else(|| format!("${section} never ends"))?;
        self.position += at + end.len();
        Ok(())
    }
}

/// A count from a header that must fit the bytes left, `per` bytes each at least.
fn bounded(count: u64, per: usize, c: &Cursor, what: &str) -> Result<usize, Fault> {
    let count = usize::try_from(count).map_err(|_| format!("{what} {count} is beyond this machine"))?;
    if count.saturating_mul(per) > c.remaining() {
        return Err(format!("{count} {what} announced, the file is too short for them"));
    }
    Ok(count)
}

pub(super) fn parse(bytes: &[u8]) -> Result<MeshFile, Fault> {
    let mut c = Cursor { bytes, position: 0, size_t: 8 };
    match c.word() {
        Some("$MeshFormat") => {}
        Some("$NOD") => return parse_v1(&mut c),
        Some(first) => {
            let first: String = first.chars().take(30).collect();
            return Err(format!(
                "not a Gmsh file: it starts with `{first}`, where version 1 starts with `$NOD` and 2.2 and 4.1 with `$MeshFormat`"
            ));
        }
        None => return Err("the file is empty".into()),
    }
    let version: String = c.number("the version")?;
    let binary = c.number::<u32>("the file type")? == 1;
    let data_size: usize = c.number("the data size")?;
    if data_size != 4 && data_size != 8 {
        return Err(format!("data size {data_size}: only 4 or 8 bytes"));
    }
    c.size_t = data_size;
    if binary {
        c.end_line();
        if c.int()? != 1 {
            return Err("a binary file in the other byte order".into());
        }
    }
    let v4 = match version.as_str() {
        "4.1" => true,
        v if v.starts_with("2.") => false,
        other => return Err(format!("version {other}: only 1, 2.2 and 4.1 are read")),
    };
    let mut mesh = MeshFile::default();
    let mut index_of_tag: HashMap<u64, u32> = HashMap::new();
    while let Some(word) = c.word() {
        match word {
            "$EndMeshFormat" => {}
            "$Nodes" if v4 => read_nodes_v4(&mut c, binary, &mut mesh, &mut index_of_tag)?,
            "$Nodes" => read_nodes_v2(&mut c, binary, &mut mesh, &mut index_of_tag)?,
            "$Elements" if v4 => read_elements_v4(&mut c, binary, &mut mesh, &index_of_tag)?,
            "$Elements" => read_elements_v2(&mut c, binary, &mut mesh, &index_of_tag)?,
            section if section.starts_with('$') && !section.starts_with("$End") => c.skip_section(&section[1..])?,
            other => {
                return Err(format!("unexpected `{}` between sections", other.chars().take(30).collect::<String>()))
            }
        }
    }
    Ok(mesh)
}

/// Gmsh's first format (no `$MeshFormat`; ASCII only): `$NOD` count, `tag x y z` lines,
/// `$ENDNOD`; `$ELM` count, `tag type physical elementary nodes node…` lines, `$ENDELM`.
/// The two region numbers become the cell arrays meshio names `gmsh:physical` and
/// `gmsh:geometrical`.
fn parse_v1(c: &mut Cursor) -> Result<MeshFile, Fault> {
    let mut mesh = MeshFile::default();
    let mut index_of_tag: HashMap<u64, u32> = HashMap::new();
    let count: u64 = c.number("the node count after $NOD")?;
    for _ in 0..bounded(count, 8, c, "nodes")? {
        let tag: u64 = c.number("a node tag")?;
        let p = Vector3::new(c.number("x")?, c.number("y")?, c.number("z")?);
        add_node(&mut mesh, &mut index_of_tag, tag, p)?;
    }
    expect(c, "$ENDNOD", "after the last node")?;
    expect(c, "$ELM", "after $ENDNOD")?;
    let count: u64 = c.number("the element count after $ELM")?;
    let (mut physical, mut elementary) = (Vec::new(), Vec::new());
    let mut nodes = Vec::new();
    for _ in 0..bounded(count, 10, c, "elements")? {
        let tag: u64 = c.number("an element tag")?;
        let ty: u32 = c.number("an element type")?;
        let regions: [f32; 2] = [c.number("a physical region")?, c.number("an elementary region")?];
        let listed: usize = c.number("an element's node count")?;
        let per = nodes_per_element(ty).ok_or_else(|| format!("element {tag}: type {ty} is not known"))?;
        if listed != per {
            return Err(format!("element {tag}: {listed} nodes listed where type {ty} has {per}"));
        }
        nodes.clear();
        for _ in 0..per {
            nodes.push(c.number("a node tag")?);
        }
        let added = add_element(&mut mesh, &index_of_tag, tag, ty, &nodes)?;
        physical.extend(std::iter::repeat_n(regions[0], added));
        elementary.extend(std::iter::repeat_n(regions[1], added));
    }
    expect(c, "$ENDELM", "after the last element")?;
    mesh.cell_arrays.push(CellArray { name: "gmsh:physical".into(), values: physical });
    mesh.cell_arrays.push(CellArray { name: "gmsh:geometrical".into(), values: elementary });
    Ok(mesh)
}

fn expect(c: &mut Cursor, word: &str, place: &str) -> Result<(), Fault> {
    match c.word() {
        Some(found) if found == word => Ok(()),
        Some(_) => Err(format!("`{word}` expected {place}, found other text")),
        None => Err(format!("the file ends where `{word}` should be, {place}")),
    }
}

fn add_node(mesh: &mut MeshFile, index_of_tag: &mut HashMap<u64, u32>, tag: u64, p: Vector3<f64>) -> Result<(), Fault> {
    let index = u32::try_from(mesh.nodes.len()).map_err(|_| "more nodes than u32 indices")?;
    if index_of_tag.insert(tag, index).is_some() {
        return Err(format!("node tag {tag} appears twice"));
    }
    mesh.nodes.push(p);
    Ok(())
}

fn add_element(
    mesh: &mut MeshFile,
    index_of_tag: &HashMap<u64, u32>,
    tag: u64,
    ty: u32,
    nodes: &[u64],
) -> Result<usize, Fault> {
    let solid = match ty {
        TET4 => None,
        5 => Some(Solid::Hexahedron),
        6 => Some(Solid::Wedge),
        7 => Some(Solid::Pyramid),
        _ => {
            *mesh.skipped.entry(element_name(ty)).or_insert(0) += 1;
            return Ok(0);
        }
    };
    let mut indices = Vec::with_capacity(nodes.len());
    for node in nodes {
        indices.push(*index_of_tag.get(node).ok_or_else(|| format!("element {tag} references unknown node {node}"))?);
    }
    match solid {
        Some(solid) => mesh.push_solid(solid, &indices).map_err(|why| format!("element {tag}: {why}")),
        None => {
            mesh.tets.push([indices[0], indices[1], indices[2], indices[3]]);
            Ok(1)
        }
    }
}

fn read_nodes_v2(c: &mut Cursor, binary: bool, mesh: &mut MeshFile, tags: &mut HashMap<u64, u32>) -> Result<(), Fault> {
    let count: u64 = c.number("the node count")?;
    let count = bounded(count, if binary { 28 } else { 8 }, c, "nodes")?;
    if binary {
        c.end_line();
    }
    for _ in 0..count {
        let (tag, p) = if binary {
            let tag = c.int()?;
            (tag, Vector3::new(c.double()?, c.double()?, c.double()?))
        } else {
            (c.number("a node tag")?, Vector3::new(c.number("x")?, c.number("y")?, c.number("z")?))
        };
        let tag = u64::try_from(tag).map_err(|_| format!("node tag {tag} is negative"))?;
        add_node(mesh, tags, tag, p)?;
    }
    c.skip_section("Nodes")
}

fn read_elements_v2(c: &mut Cursor, binary: bool, mesh: &mut MeshFile, tags: &HashMap<u64, u32>) -> Result<(), Fault> {
    let count: u64 = c.number("the element count")?;
    let count = bounded(count, if binary { 12 } else { 8 }, c, "elements")?;
    if binary {
        c.end_line();
        // Blocks of one type: (type, elements in the block, tags per element), then each
        // element as its number, its tags and its nodes.
        let mut read = 0usize;
        while read < count {
            let ty = u32::try_from(c.int()?).map_err(|_| "a negative element type")?;
            let in_block = usize::try_from(c.int()?).map_err(|_| "a negative block size")?;
            let ntags = usize::try_from(c.int()?).map_err(|_| "a negative tag count")?;
            let per = nodes_per_element(ty).ok_or_else(|| format!("element type {ty} is not known"))?;
            let ints = (1 + ntags).checked_add(per).ok_or("an element's size overflows")?;
            bounded(in_block as u64, ints.saturating_mul(4), c, "elements in a block")?;
            if in_block == 0 || in_block > count - read {
                return Err(format!("an element block of {in_block} where {} are left", count - read));
            }
            for _ in 0..in_block {
                let tag = c.int()?;
                for _ in 0..ntags {
                    c.int()?;
                }
                let mut nodes = Vec::with_capacity(per);
                for _ in 0..per {
                    nodes.push(u64::try_from(c.int()?).map_err(|_| "a negative node tag")?);
                }
                add_element(mesh, tags, tag.max(0) as u64, ty, &nodes)?;
            }
            read += in_block;
        }
    } else {
        for _ in 0..count {
            let tag: u64 = c.number("an element tag")?;
            let ty: u32 = c.number("an element type")?;
            let ntags: usize = c.number("a tag count")?;
            let per = nodes_per_element(ty).ok_or_else(|| format!("element {tag}: type {ty} is not known"))?;
            bounded(ntags as u64, 2, c, "element tags")?;
            for _ in 0..ntags {
                c.number::<i64>("an element tag")?;
            }
            let mut nodes = Vec::with_capacity(per);
            for _ in 0..per {
                nodes.push(c.number("a node tag")?);
            }
            add_element(mesh, tags, tag, ty, &nodes)?;
        }
    }
    c.skip_section("Elements")
}

fn read_nodes_v4(c: &mut Cursor, binary: bool, mesh: &mut MeshFile, tags: &mut HashMap<u64, u32>) -> Result<(), Fault> {
    let (blocks, total) = if binary {
        c.end_line();
        let b = c.size()?;
        let t = c.size()?;
        c.size()?;
        c.size()?;
        (b, t)
    } else {
        let b: u64 = c.number("the entity block count")?;
        let t: u64 = c.number("the node count")?;
        c.number::<u64>("the smallest node tag")?;
        c.number::<u64>("the largest node tag")?;
        (b, t)
    };
    let blocks = bounded(blocks, 4, c, "node blocks")?;
    bounded(total, if binary { 32 } else { 8 }, c, "nodes")?;
    for _ in 0..blocks {
        let (parametric, in_block) = block_header(c, binary, "the parametric flag", "the nodes in a block")?;
        if parametric != 0 {
            return Err("parametric node coordinates are not supported".into());
        }
        let in_block = bounded(in_block, if binary { c.size_t + 24 } else { 8 }, c, "nodes in a block")?;
        let mut block_tags = Vec::with_capacity(in_block);
        for _ in 0..in_block {
            block_tags.push(if binary { c.size()? } else { c.number("a node tag")? });
        }
        for tag in block_tags {
            let p = if binary {
                Vector3::new(c.double()?, c.double()?, c.double()?)
            } else {
                Vector3::new(c.number("x")?, c.number("y")?, c.number("z")?)
            };
            add_node(mesh, tags, tag, p)?;
        }
    }
    c.skip_section("Nodes")
}

/// A 4.1 entity block's header: entity dimension and tag (skipped), then the field that
/// differs between node and element blocks, and the block's count.
fn block_header(c: &mut Cursor, binary: bool, field: &str, count: &str) -> Result<(i64, u64), Fault> {
    if binary {
        c.int()?;
        c.int()?;
        let value = c.int()?;
        Ok((value, c.size()?))
    } else {
        c.number::<i64>("an entity dimension")?;
        c.number::<i64>("an entity tag")?;
        let value: i64 = c.number(field)?;
        Ok((value, c.number(count)?))
    }
}

fn read_elements_v4(c: &mut Cursor, binary: bool, mesh: &mut MeshFile, tags: &HashMap<u64, u32>) -> Result<(), Fault> {
    let blocks = if binary {
        c.end_line();
        let b = c.size()?;
        for _ in 0..3 {
            c.size()?;
        }
        b
    } else {
        let b: u64 = c.number("the entity block count")?;
        for what in ["the element count", "the smallest element tag", "the largest element tag"] {
            c.number::<u64>(what)?;
        }
        b
    };
    let blocks = bounded(blocks, 4, c, "element blocks")?;
    for _ in 0..blocks {
        let (ty, in_block) = block_header(c, binary, "an element type", "the elements in a block")?;
        let ty = u32::try_from(ty).map_err(|_| format!("element type {ty} is negative"))?;
        let per = nodes_per_element(ty).ok_or_else(|| format!("element type {ty} is not known"))?;
        let in_block =
            bounded(in_block, if binary { (per + 1) * c.size_t } else { 2 * (per + 1) }, c, "elements in a block")?;
        let mut nodes = Vec::with_capacity(per);
        for _ in 0..in_block {
            let tag = if binary { c.size()? } else { c.number("an element tag")? };
            nodes.clear();
            for _ in 0..per {
                nodes.push(if binary { c.size()? } else { c.number("a node tag")? });
            }
            add_element(mesh, tags, tag, ty, &nodes)?;
        }
    }
    c.skip_section("Elements")
}

/// A tet mesh as Gmsh 4.1 ASCII bytes (one volume entity; tags from 1).
pub(super) fn write(nodes: &[Vector3<f64>], tets: &[[u32; 4]]) -> Vec<u8> {
    use std::fmt::Write;
    let (n, m) = (nodes.len(), tets.len());
    let mut s = String::with_capacity(64 * (n + m));
    let _ = write!(s, "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 {n} 1 {n}\n3 1 0 {n}\n");
    for i in 1..=n {
        let _ = writeln!(s, "{i}");
    }
    for p in nodes {
        let _ = writeln!(s, "{:e} {:e} {:e}", p.x, p.y, p.z);
    }
    let _ = write!(s, "$EndNodes\n$Elements\n1 {m} 1 {m}\n3 1 4 {m}\n");
    for (e, t) in tets.iter().enumerate() {
        let _ = writeln!(s, "{} {} {} {} {}", e + 1, t[0] + 1, t[1] + 1, t[2] + 1, t[3] + 1);
    }
    s.push_str("$EndElements\n");
    s.into_bytes()
}
