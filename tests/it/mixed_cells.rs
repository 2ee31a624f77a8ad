//! Hexahedra, wedges and pyramids read as tets: a block of three unit cubes in a row, the
//! first a 2x2x2 grid of hexahedra, the second of wedges (each cube cut in two), the third
//! of pyramids (each cube coned from its centre), its nodes numbered at random so the split
//! meets every kind of face numbering. The split must conform (every interior triangle shared
//! by exactly two tets, every boundary triangle on the block's surface), keep the volume to
//! 1e-12, and read the same from legacy VTK and Gmsh 2.2, written here by hand.

use std::collections::HashMap;
use std::path::Path;

use defvol::io;
use nalgebra::Vector3;

/// Nodes and cells (VTK type, nodes) of the block.
struct Block {
    nodes: Vec<Vector3<f64>>,
    cells: Vec<(u8, Vec<usize>)>,
}

/// The block with its nodes numbered by a shuffle drawn from `seed`.
fn block(seed: u64) -> Block {
    const N: usize = 2;
    let lattice = |i: usize, j: usize, k: usize| i + (3 * N + 1) * (j + (N + 1) * k);
    let mut nodes: Vec<Vector3<f64>> = Vec::new();
    for k in 0..=N {
        for j in 0..=N {
            for i in 0..=3 * N {
                nodes.push(Vector3::new(i as f64, j as f64, k as f64) / N as f64);
            }
        }
    }
    let mut cells = Vec::new();
    for k in 0..N {
        for j in 0..N {
            for i in 0..3 * N {
                let c = |di: usize, dj: usize, dk: usize| lattice(i + di, j + dj, k + dk);
                let hex =
                    [c(0, 0, 0), c(1, 0, 0), c(1, 1, 0), c(0, 1, 0), c(0, 0, 1), c(1, 0, 1), c(1, 1, 1), c(0, 1, 1)];
                match i / N {
                    0 => cells.push((12, hex.to_vec())),
                    1 => {
                        // Cut by the plane through the cube's diagonal in x-y: two wedges along z.
                        cells.push((13, vec![hex[0], hex[1], hex[2], hex[4], hex[5], hex[6]]));
                        cells.push((13, vec![hex[0], hex[2], hex[3], hex[4], hex[6], hex[7]]));
                    }
                    _ => {
                        let centre = nodes.len();
                        nodes.push(Vector3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5) / N as f64);
                        let faces =
                            [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]];
                        for f in faces {
                            cells.push((14, vec![hex[f[0]], hex[f[1]], hex[f[2]], hex[f[3]], centre]));
                        }
                    }
                }
            }
        }
    }
    // A random numbering (Fisher-Yates by xorshift).
    let mut order: Vec<usize> = (0..nodes.len()).collect();
    let mut state = seed;
    for i in (1..order.len()).rev() {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        order.swap(i, (state % (i as u64 + 1)) as usize);
    }
    let mut renamed = vec![Vector3::zeros(); nodes.len()];
    for (old, &new) in order.iter().enumerate() {
        renamed[new] = nodes[old];
    }
    let cells = cells.into_iter().map(|(ty, c)| (ty, c.into_iter().map(|n| order[n]).collect())).collect();
    Block { nodes: renamed, cells }
}

fn legacy_vtk(b: &Block) -> String {
    let mut s = format!(
        "# vtk DataFile Version 3.0\nblock\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS {} double\n",
        b.nodes.len()
    );
    for p in &b.nodes {
        s += &format!("{} {} {}\n", p.x, p.y, p.z);
    }
    let size: usize = b.cells.iter().map(|(_, c)| c.len() + 1).sum();
    s += &format!("CELLS {} {size}\n", b.cells.len());
    for (_, c) in &b.cells {
        s += &format!("{} {}\n", c.len(), c.iter().map(|n| n.to_string()).collect::<Vec<_>>().join(" "));
    }
    s += &format!("CELL_TYPES {}\n", b.cells.len());
    for (ty, _) in &b.cells {
        s += &format!("{ty}\n");
    }
    s
}

fn gmsh_22(b: &Block) -> String {
    let mut s = format!("$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n{}\n", b.nodes.len());
    for (i, p) in b.nodes.iter().enumerate() {
        s += &format!("{} {} {} {}\n", i + 1, p.x, p.y, p.z);
    }
    s += &format!("$EndNodes\n$Elements\n{}\n", b.cells.len());
    for (e, (ty, c)) in b.cells.iter().enumerate() {
        let gmsh_type = match ty {
            12 => 5,
            13 => 6,
            _ => 7,
        };
        let nodes: Vec<String> = c.iter().map(|n| (n + 1).to_string()).collect();
        s += &format!("{} {gmsh_type} 2 1 1 {}\n", e + 1, nodes.join(" "));
    }
    s + "$EndElements\n"
}

fn volume(p: &[Vector3<f64>; 4]) -> f64 {
    (p[1] - p[0]).cross(&(p[2] - p[0])).dot(&(p[3] - p[0])) / 6.0
}

/// Every triangle of the tets shared by two tets, or by one on the block's surface.
fn assert_conforming(mesh: &defvol::mesh::TetMesh, what: &str) {
    let mut faces: HashMap<[u32; 3], usize> = HashMap::new();
    for t in mesh.tets() {
        for skip in 0..4 {
            let mut f: Vec<u32> = (0..4).filter(|&i| i != skip).map(|i| t[i]).collect();
            f.sort_unstable();
            *faces.entry([f[0], f[1], f[2]]).or_insert(0) += 1;
        }
    }
    let on_surface = |f: &[u32; 3]| {
        let p = f.map(|n| mesh.nodes()[n as usize]);
        (0..3).any(|a| {
            let high = if a == 0 { 3.0 } else { 1.0 };
            p.iter().all(|q| q[a].abs() < 1e-12) || p.iter().all(|q| (q[a] - high).abs() < 1e-12)
        })
    };
    for (face, count) in &faces {
        match count {
            1 => assert!(on_surface(face), "{what}: triangle {face:?} has one tet but is inside the block"),
            2 => assert!(!on_surface(face), "{what}: triangle {face:?} on the surface has two tets"),
            n => panic!("{what}: triangle {face:?} has {n} tets"),
        }
    }
}

#[test]
fn hexahedra_wedges_and_pyramids_split_into_a_conforming_mesh_of_the_same_volume() {
    let dir = tempfile::tempdir().unwrap();
    for seed in [1u64, 2, 3, 0x9E37_79B9] {
        let b = block(seed);
        let (hexes, wedges, pyramids) = (8, 16, 48);
        for (name, text) in [("block.vtk", legacy_vtk(&b)), ("block.msh", gmsh_22(&b))] {
            let path = dir.path().join(name);
            std::fs::write(&path, text).unwrap();
            let read = io::read_mesh_with_metadata(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
            let mesh = &read.mesh;
            let split: Vec<(&str, usize)> = read.split.iter().map(|(k, n)| (*k, *n)).collect();
            assert_eq!(split, [("hexahedron", hexes), ("pyramid", pyramids), ("wedge", wedges)], "{name}");
            assert_eq!(mesh.tets().len(), 6 * hexes + 3 * wedges + 2 * pyramids, "{name}");
            let volumes: Vec<f64> = mesh.tets().iter().map(|t| volume(&t.map(|n| mesh.nodes()[n as usize]))).collect();
            assert!(volumes.iter().all(|v| *v > 1e-3), "{name} seed {seed}: a flat or inverted tet");
            let total: f64 = volumes.iter().sum();
            assert!((total - 3.0).abs() < 1e-12, "{name} seed {seed}: volume {total}");
            assert_conforming(mesh, &format!("{name} seed {seed}"));
        }
    }
}

#[test]
fn a_solid_with_a_repeated_node_is_refused_by_name() {
    let b = block(5);
    let mut bad = b.cells.clone();
    bad[0].1[5] = bad[0].1[2];
    let text = legacy_vtk(&Block { nodes: b.nodes.clone(), cells: bad });
    let error =
        io::parse_mesh(Path::new("bad.vtk"), text.as_bytes(), io::MeshFormat::VtkLegacy).unwrap_err().to_string();
    assert!(error.contains("bad.vtk") && error.contains("cell 0: a hexahedron with node"), "{error}");
    // Element 1, a hexahedron: its last node made its first.
    let mut lines: Vec<String> = gmsh_22(&b).lines().map(str::to_owned).collect();
    let at = lines.iter().position(|l| l.starts_with("1 5 2 1 1 ")).unwrap();
    let mut words: Vec<String> = lines[at].split(' ').map(str::to_owned).collect();
    let last = words.len() - 1;
    words[last] = words[5].clone();
    lines[at] = words.join(" ");
    let error = io::parse_mesh(Path::new("bad.msh"), lines.join("\n").as_bytes(), io::MeshFormat::Gmsh)
        .unwrap_err()
        .to_string();
    assert!(error.contains("bad.msh") && error.contains("element 1: a hexahedron with node"), "{error}");
}

/// The block of hexahedra, wedges and pyramids, 3 cm long, simulates 100 steps under
/// gravity held by its lowest layer on both backends, and they agree.
#[test]
fn the_mixed_block_simulates_on_both_backends() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("block.vtk"), legacy_vtk(&block(7))).unwrap();
    let mut finals = Vec::new();
    for (out, backend) in [("cpu", &["--backend", "cpu"][..]), ("gpu", &["--backend", "gpu", "--allow-software-gpu"])] {
        let status = std::process::Command::new(env!("CARGO_BIN_EXE_defvol"))
            .args(["simulate", "--mesh", "block.vtk", "--mesh-scale", "0.01", "--fix", "lowest", "--steps", "100"])
            .args(backend)
            .args(["--out", out])
            .current_dir(dir.path())
            .output()
            .unwrap();
        assert!(status.status.success(), "{out}: {}", String::from_utf8_lossy(&status.stderr));
        finals.push(io::read_mesh(&dir.path().join(out).join("final.vtu")).unwrap().nodes().to_vec());
    }
    let rest = io::read_mesh(&dir.path().join("cpu/rest.vtu")).unwrap();
    let sag = finals[0].iter().zip(rest.nodes()).map(|(p, r)| (p - r).norm()).fold(0.0, f64::max);
    let apart = finals[0].iter().zip(&finals[1]).map(|(p, q)| (p - q).norm()).fold(0.0, f64::max);
    // A few grams on springs of 1000 N/m: about a micrometre.
    assert!(sag > 1e-7 && sag.is_finite(), "the block sagged {sag} m");
    assert!(apart < 0.01 * sag, "cpu and gpu {apart} m apart of a {sag} m sag");
}
