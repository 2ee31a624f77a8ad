//! TetGen `.node` / `.ele` pairs (either file names the pair). Indices may start at 0 or 1,
//! as TetGen writes whichever its input used: the first node's index decides. Node
//! attributes come along as point arrays (`attribute0`, …); boundary markers are skipped.
//! Every count is checked against the lines that are there before anything is allocated.

use std::path::Path;

use nalgebra::Vector3;

use super::mesh_file::{MeshFile, PointArray};

type Fault = String;

fn data_lines(text: &str) -> Vec<(usize, Vec<&str>)> {
    text.lines()
        .enumerate()
        .map(|(n, l)| (n + 1, l.split('#').next().unwrap_or("").split_whitespace().collect::<Vec<_>>()))
        .filter(|(_, w)| !w.is_empty())
        .collect()
}

fn parse_word<T: std::str::FromStr>(file: &str, line: usize, word: Option<&&str>, what: &str) -> Result<T, Fault> {
    word.and_then(|w| w.parse().ok()).ok_or_else(|| format!("{file} line {line}: expected {what}"))
}

pub(super) fn parse(node_bytes: &[u8], ele_bytes: &[u8]) -> Result<MeshFile, Fault> {
    let (mut mesh, first_index) = parse_nodes(node_bytes)?;
    parse_elements(&mut mesh, first_index, ele_bytes)?;
    Ok(mesh)
}

/// The `.node` file: the nodes, their attributes, and the first node's index.
pub(super) fn parse_nodes(node_bytes: &[u8]) -> Result<(MeshFile, i64), Fault> {
    let node_text = std::str::from_utf8(node_bytes).map_err(|_| ".node: not text")?;
    let lines = data_lines(node_text);
    let Some((line, header)) = lines.first() else { return Err(".node: empty".into()) };
    let count: usize = parse_word(".node", *line, header.first(), "the node count")?;
    let dim: usize = parse_word(".node", *line, header.get(1), "the dimension")?;
    if dim != 3 {
        return Err(format!(".node line {line}: dimension {dim}, only 3 is supported"));
    }
    let attributes: usize = header
        .get(2)
        .map_or(Ok(0), |w| w.parse())
        .map_err(|_| format!(".node line {line}: expected the attribute count"))?;
    if count != lines.len() - 1 {
        return Err(format!(
            ".node: the header announces {count} nodes, the file has {} lines of them",
            lines.len() - 1
        ));
    }
    // The attributes a node line can hold: no more columns than its words.
    let widest = lines.get(1).map_or(0, |(_, w)| w.len().saturating_sub(4));
    if attributes > widest {
        return Err(format!(".node line {line}: {attributes} attributes announced, the node lines hold {widest}"));
    }
    let mut mesh = MeshFile { nodes: Vec::with_capacity(count), ..Default::default() };
    let mut values = vec![Vec::with_capacity(count); attributes];
    let mut first_index = 0;
    for (k, (line, w)) in lines[1..].iter().enumerate() {
        let index: i64 = parse_word(".node", *line, w.first(), "a node index")?;
        if k == 0 {
            first_index = index;
        } else if Some(index) != first_index.checked_add(k as i64) {
            return Err(format!(".node line {line}: node {index} out of order (the first is {first_index})"));
        }
        let c = |a: usize| parse_word::<f64>(".node", *line, w.get(a), "3 coordinates");
        mesh.nodes.push(Vector3::new(c(1)?, c(2)?, c(3)?));
        for (a, column) in values.iter_mut().enumerate() {
            column.push(parse_word::<f32>(".node", *line, w.get(4 + a), "the node's attributes")?);
        }
    }
    mesh.arrays = values
        .into_iter()
        .enumerate()
        .map(|(a, values)| PointArray { name: format!("attribute{a}"), components: 1, values, active_scalars: false })
        .collect();
    Ok((mesh, first_index))
}

/// The `.ele` file's tets, indices relative to the first node's.
pub(super) fn parse_elements(mesh: &mut MeshFile, first_index: i64, ele_bytes: &[u8]) -> Result<(), Fault> {
    let ele_text = std::str::from_utf8(ele_bytes).map_err(|_| ".ele: not text")?;
    let lines = data_lines(ele_text);
    let Some((line, header)) = lines.first() else { return Err(".ele: empty".into()) };
    let count: usize = parse_word(".ele", *line, header.first(), "the tet count")?;
    let per: usize = parse_word(".ele", *line, header.get(1), "nodes per tet")?;
    if per != 4 {
        return Err(format!(".ele line {line}: {per} nodes per tet, only linear (4) tets are supported"));
    }
    if count != lines.len() - 1 {
        return Err(format!(".ele: the header announces {count} tets, the file has {} lines of them", lines.len() - 1));
    }
    mesh.tets.reserve(count);
    for (line, w) in &lines[1..] {
        let mut t = [0u32; 4];
        for (a, slot) in t.iter_mut().enumerate() {
            let raw: i64 = parse_word(".ele", *line, w.get(a + 1), "4 node indices")?;
            *slot = raw.checked_sub(first_index).and_then(|i| u32::try_from(i).ok()).ok_or_else(|| {
                format!(".ele line {line}: node index {raw} outside the nodes (the first is {first_index})")
            })?;
        }
        mesh.tets.push(t);
    }
    Ok(())
}

pub(super) fn write(path: &Path, nodes: &[Vector3<f64>], tets: &[[u32; 4]]) -> Result<(), super::error::IoError> {
    use std::fmt::Write;
    let mut node_text = format!("{} 3 0 0\n", nodes.len());
    for (i, p) in nodes.iter().enumerate() {
        let _ = writeln!(node_text, "{i} {:e} {:e} {:e}", p.x, p.y, p.z);
    }
    let mut ele_text = format!("{} 4 0\n", tets.len());
    for (i, t) in tets.iter().enumerate() {
        let _ = writeln!(ele_text, "{i} {} {} {} {}", t[0], t[1], t[2], t[3]);
    }
    let node_path = path.with_extension("node");
    let ele_path = path.with_extension("ele");
    super::files::write_atomically(&ele_path, ele_text.as_bytes())?;
    super::files::write_atomically(&node_path, node_text.as_bytes())
}
