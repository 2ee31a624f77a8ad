//! Gmsh `.msh`: version 4.1 (ASCII or binary) through mshio; version 2.2 ASCII read here.
//! Files are written as 4.1 ASCII. Only linear tets (type 4) become elements; points,
//! lines and triangles (physical groups, boundaries) are skipped.

use std::collections::HashMap;
use std::path::Path;

use nalgebra::Vector3;

use super::vtk::MeshParts;
use super::{io_error, malformed, IoError};

const TET4: i64 = 4;

pub(super) fn read(path: &Path) -> Result<MeshParts, IoError> {
    let bytes = std::fs::read(path).map_err(io_error(path))?;
    let head = String::from_utf8_lossy(&bytes[..bytes.len().min(64)]).into_owned();
    let version = head.lines().nth(1).and_then(|l| l.split_whitespace().next()).unwrap_or("").to_owned();
    if version.starts_with("2.") {
        return read_v2(path, &bytes);
    }
    let msh = mshio::parse_msh_bytes(&bytes).map_err(|e| {
        malformed(path, format!("not a readable Gmsh 4.1 file: {e:?}").chars().take(300).collect::<String>())
    })?;
    let Some(node_data) = msh.data.nodes else { return Err(malformed(path, "no $Nodes section")) };
    let mut index_of_tag: HashMap<u64, u32> = HashMap::new();
    let mut nodes = Vec::new();
    let mut next_tag = node_data.min_node_tag;
    for block in &node_data.node_blocks {
        let tags: Vec<u64> = match &block.node_tags {
            Some(map) => {
                let mut by_index = vec![0u64; block.nodes.len()];
                for (&tag, &i) in map {
                    if let Some(slot) = by_index.get_mut(i) {
                        *slot = tag;
                    }
                }
                by_index
            }
            None => (0..block.nodes.len() as u64).map(|k| next_tag + k).collect(),
        };
        for (tag, n) in tags.iter().zip(&block.nodes) {
            index_of_tag.insert(*tag, nodes.len() as u32);
            nodes.push(Vector3::new(n.x, n.y, n.z));
            next_tag = next_tag.max(tag + 1);
        }
    }
    let Some(elements) = msh.data.elements else { return Err(malformed(path, "no $Elements section")) };
    let mut tets = Vec::new();
    for block in &elements.element_blocks {
        if block.element_type as i64 != TET4 {
            if block.entity_dim == 3 {
                return Err(malformed(
                    path,
                    format!(
                        "volume elements of type {:?}; only linear tetrahedra (Tet4) are supported",
                        block.element_type
                    ),
                ));
            }
            continue;
        }
        for el in &block.elements {
            let mut t = [0u32; 4];
            for (slot, tag) in t.iter_mut().zip(&el.nodes) {
                *slot = *index_of_tag.get(tag).ok_or_else(|| {
                    malformed(path, format!("element {} references unknown node {tag}", el.element_tag))
                })?;
            }
            tets.push(t);
        }
    }
    Ok((nodes, tets, None))
}

fn read_v2(path: &Path, bytes: &[u8]) -> Result<MeshParts, IoError> {
    let text = std::str::from_utf8(bytes)
        .map_err(|_| malformed(path, "Gmsh 2.2 binary files are not supported; save as ASCII"))?;
    let mut lines = text.lines().enumerate().map(|(n, l)| (n + 1, l.trim()));
    let mut index_of_tag: HashMap<u64, u32> = HashMap::new();
    let mut nodes = Vec::new();
    let mut tets = Vec::new();
    let bad = |line: usize, what: &str| malformed(path, format!("line {line}: {what}"));
    while let Some((_, l)) = lines.next() {
        match l {
            "$MeshFormat" => {
                if let Some((n, fmt)) = lines.next() {
                    if fmt.split_whitespace().nth(1) != Some("0") {
                        return Err(bad(n, "Gmsh 2.2 binary files are not supported; save as ASCII"));
                    }
                }
            }
            "$Nodes" => {
                let (n, count) = lines.next().ok_or_else(|| bad(0, "missing node count"))?;
                let count: usize = count.parse().map_err(|_| bad(n, "expected the node count"))?;
                for _ in 0..count {
                    let (n, l) = lines.next().ok_or_else(|| bad(n, "file ends inside $Nodes"))?;
                    let w: Vec<f64> = l
                        .split_whitespace()
                        .map(str::parse)
                        .collect::<Result<_, _>>()
                        .map_err(|_| bad(n, "expected: tag x y z"))?;
                    let [tag, x, y, z] = w[..] else { return Err(bad(n, "expected: tag x y z")) };
                    index_of_tag.insert(tag as u64, nodes.len() as u32);
                    nodes.push(Vector3::new(x, y, z));
                }
            }
            "$Elements" => {
                let (n, count) = lines.next().ok_or_else(|| bad(0, "missing element count"))?;
                let count: usize = count.parse().map_err(|_| bad(n, "expected the element count"))?;
                for _ in 0..count {
                    let (n, l) = lines.next().ok_or_else(|| bad(n, "file ends inside $Elements"))?;
                    let w: Vec<u64> = l
                        .split_whitespace()
                        .map(str::parse)
                        .collect::<Result<_, _>>()
                        .map_err(|_| bad(n, "expected integers"))?;
                    let (Some(&ty), Some(&ntags)) = (w.get(1), w.get(2)) else {
                        return Err(bad(n, "expected: tag type ntags ..."));
                    };
                    if ty as i64 != TET4 {
                        continue;
                    }
                    let start = 3 + ntags as usize;
                    let Some(ids) = w.get(start..start + 4) else {
                        return Err(bad(n, "tetrahedron with fewer than 4 nodes"));
                    };
                    let mut t = [0u32; 4];
                    for (slot, tag) in t.iter_mut().zip(ids) {
                        *slot = *index_of_tag.get(tag).ok_or_else(|| bad(n, &format!("unknown node {tag}")))?;
                    }
                    tets.push(t);
                }
            }
            _ => {}
        }
    }
    Ok((nodes, tets, None))
}

pub(super) fn write(path: &Path, nodes: &[Vector3<f64>], tets: &[[u32; 4]]) -> Result<(), IoError> {
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
    std::fs::write(path, s).map_err(io_error(path))
}
