//! TetGen `.node` / `.ele` pairs (either file names the pair). Indices may start at 0 or 1,
//! as TetGen writes whichever its input used: the first node's index decides.

use std::path::Path;

use nalgebra::Vector3;

use super::vtk::MeshParts;
use super::{io_error, malformed, IoError};

fn data_lines(text: &str) -> impl Iterator<Item = (usize, Vec<&str>)> {
    text.lines()
        .enumerate()
        .map(|(n, l)| (n + 1, l.split('#').next().unwrap_or("").split_whitespace().collect::<Vec<_>>()))
        .filter(|(_, w)| !w.is_empty())
}

fn parse<T: std::str::FromStr>(path: &Path, line: usize, word: Option<&&str>, what: &str) -> Result<T, IoError> {
    word.and_then(|w| w.parse().ok()).ok_or_else(|| malformed(path, format!("line {line}: expected {what}")))
}

pub(super) fn read(path: &Path) -> Result<MeshParts, IoError> {
    let node_path = path.with_extension("node");
    let ele_path = path.with_extension("ele");
    let node_text = std::fs::read_to_string(&node_path).map_err(io_error(&node_path))?;
    let mut lines = data_lines(&node_text);
    let Some((line, header)) = lines.next() else { return Err(malformed(&node_path, "empty .node file")) };
    let count: usize = parse(&node_path, line, header.first(), "the node count")?;
    let dim: usize = parse(&node_path, line, header.get(1), "the dimension")?;
    if dim != 3 {
        return Err(malformed(&node_path, format!("line {line}: dimension {dim}, only 3 is supported")));
    }
    let mut nodes = Vec::with_capacity(count);
    let mut first_index = 0;
    for (k, (line, w)) in lines.by_ref().take(count).enumerate() {
        let index: i64 = parse(&node_path, line, w.first(), "a node index")?;
        if k == 0 {
            first_index = index;
        }
        let c = |a: usize| parse::<f64>(&node_path, line, w.get(a), "3 coordinates");
        nodes.push(Vector3::new(c(1)?, c(2)?, c(3)?));
    }
    if nodes.len() != count {
        return Err(malformed(&node_path, format!("header announces {count} nodes, file has {}", nodes.len())));
    }
    let ele_text = std::fs::read_to_string(&ele_path).map_err(io_error(&ele_path))?;
    let mut lines = data_lines(&ele_text);
    let Some((line, header)) = lines.next() else { return Err(malformed(&ele_path, "empty .ele file")) };
    let count: usize = parse(&ele_path, line, header.first(), "the tet count")?;
    let per: usize = parse(&ele_path, line, header.get(1), "nodes per tet")?;
    if per != 4 {
        return Err(malformed(
            &ele_path,
            format!("line {line}: {per} nodes per tet, only linear (4) tets are supported"),
        ));
    }
    let mut tets = Vec::with_capacity(count);
    for (line, w) in lines.take(count) {
        let mut t = [0u32; 4];
        for (a, slot) in t.iter_mut().enumerate() {
            let raw: i64 = parse(&ele_path, line, w.get(a + 1), "4 node indices")?;
            *slot = u32::try_from(raw - first_index).map_err(|_| {
                malformed(&ele_path, format!("line {line}: node index {raw} below the first node {first_index}"))
            })?;
        }
        tets.push(t);
    }
    if tets.len() != count {
        return Err(malformed(&ele_path, format!("header announces {count} tets, file has {}", tets.len())));
    }
    Ok((nodes, tets, None))
}

pub(super) fn write(path: &Path, nodes: &[Vector3<f64>], tets: &[[u32; 4]]) -> Result<(), IoError> {
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
    std::fs::write(&node_path, node_text).map_err(io_error(&node_path))?;
    std::fs::write(&ele_path, ele_text).map_err(io_error(&ele_path))
}
