//! Generated meshes: lattices embedding a box (the default scene and the seed's Table 1
//! sizes) and meshed primitives. Deterministic, so tests and benchmarks need no files.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::{MeshError, TetMesh};

/// How a hexahedral cell is split into tets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CellSplit {
    /// 5 tets per cell, alternating by cell parity so that face diagonals match.
    Five,
    /// 6 tets per cell around the main diagonal (Kuhn/Freudenthal); identical cells.
    Six,
}

impl CellSplit {
    pub fn tets_per_cell(self) -> usize {
        match self {
            CellSplit::Five => 5,
            CellSplit::Six => 6,
        }
    }
}

/// A lattice of `cells` hexahedra spanning `[lo, hi]`.
pub fn lattice(lo: Vector3<f64>, hi: Vector3<f64>, cells: [usize; 3], split: CellSplit) -> Result<TetMesh, MeshError> {
    let [cx, cy, cz] = cells.map(|c| c.max(1));
    let (nx, ny, nz) = (cx + 1, cy + 1, cz + 1);
    let step = (hi - lo).component_div(&Vector3::new(cx as f64, cy as f64, cz as f64));
    let mut nodes = Vec::with_capacity(nx * ny * nz);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                nodes.push(lo + step.component_mul(&Vector3::new(i as f64, j as f64, k as f64)));
            }
        }
    }
    let id = |i: usize, j: usize, k: usize| (i + nx * (j + ny * k)) as u32;
    let mut tets = Vec::with_capacity(cx * cy * cz * split.tets_per_cell());
    for k in 0..cz {
        for j in 0..cy {
            for i in 0..cx {
                // corner c = (bit0: x, bit1: y, bit2: z)
                let c = |b: usize| id(i + (b & 1), j + ((b >> 1) & 1), k + ((b >> 2) & 1));
                let cell_tets: &[[usize; 4]] = match split {
                    CellSplit::Six => {
                        &[[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]]
                    }
                    // Even cells: central tet on the even corners {0,3,5,6}; odd cells mirror it.
                    CellSplit::Five if (i + j + k) % 2 == 0 => {
                        &[[0, 3, 5, 6], [1, 0, 3, 5], [2, 0, 3, 6], [4, 0, 5, 6], [7, 3, 5, 6]]
                    }
                    CellSplit::Five => &[[1, 2, 4, 7], [0, 1, 2, 4], [3, 1, 2, 7], [5, 1, 4, 7], [6, 2, 4, 7]],
                };
                for t in cell_tets {
                    let mut tet = t.map(c);
                    if super::signed_volume(&nodes, &tet) < 0.0 {
                        tet.swap(1, 2);
                    }
                    tets.push(tet);
                }
            }
        }
    }
    TetMesh::new(nodes, tets, None, "generated lattice")
}

/// Cell counts for a lattice over `extent` with about `target_tets` tets of near-cubic cells.
pub fn cells_for_target(extent: Vector3<f64>, target_tets: usize, split: CellSplit) -> [usize; 3] {
    let cells = (target_tets as f64 / split.tets_per_cell() as f64).max(1.0);
    let edge = (extent.x * extent.y * extent.z / cells).cbrt();
    [extent.x, extent.y, extent.z].map(|e| ((e / edge).round() as usize).max(1))
}

/// A lattice of about `target_tets` tets embedding the box `[lo, hi]`.
pub fn lattice_for_box(
    lo: Vector3<f64>,
    hi: Vector3<f64>,
    target_tets: usize,
    split: CellSplit,
) -> Result<TetMesh, MeshError> {
    lattice(lo, hi, cells_for_target(hi - lo, target_tets, split), split)
}

/// The seed's "Bar": 4x2x2 cells of 5 tets = 80 tets, `length` along x, square section.
pub fn bar(length: f64) -> Result<TetMesh, MeshError> {
    let half = length / 4.0;
    lattice(Vector3::zeros(), Vector3::new(length, half, half), [4, 2, 2], CellSplit::Five)
}

/// An ellipsoid with semi-axes `radii` centred at `centre`: a lattice of the cube mapped
/// onto the ball (a smooth bijection), then scaled, so every boundary node lies on the surface.
pub fn ellipsoid(centre: Vector3<f64>, radii: Vector3<f64>, cells_per_axis: usize) -> Result<TetMesh, MeshError> {
    let n = cells_per_axis.max(2);
    let mut mesh = lattice(Vector3::repeat(-1.0), Vector3::repeat(1.0), [n; 3], CellSplit::Five)?;
    let mut nodes: Vec<Vector3<f64>> = mesh.nodes().to_vec();
    for p in &mut nodes {
        let (x2, y2, z2) = (p.x * p.x, p.y * p.y, p.z * p.z);
        let ball = Vector3::new(
            p.x * (1.0 - y2 / 2.0 - z2 / 2.0 + y2 * z2 / 3.0).sqrt(),
            p.y * (1.0 - z2 / 2.0 - x2 / 2.0 + z2 * x2 / 3.0).sqrt(),
            p.z * (1.0 - x2 / 2.0 - y2 / 2.0 + x2 * y2 / 3.0).sqrt(),
        );
        *p = centre + ball.component_mul(&radii);
    }
    let tets = mesh.tets().to_vec();
    mesh = TetMesh::new(nodes, tets, None, "generated ellipsoid")?;
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattice_volume_and_counts() {
        for split in [CellSplit::Five, CellSplit::Six] {
            let m = lattice(Vector3::zeros(), Vector3::new(2.0, 1.0, 3.0), [4, 3, 5], split).unwrap();
            assert_eq!(m.tets().len(), 60 * split.tets_per_cell());
            assert_eq!(m.nodes().len(), 5 * 4 * 6);
            let vol: f64 = (0..m.tets().len()).map(|t| m.tet_volume(t)).sum();
            assert!((vol - 6.0).abs() < 1e-12, "{split:?}: {vol}");
            // Boundary of a box lattice: 2 triangles per boundary cell face.
            assert_eq!(m.boundary().len(), 2 * 2 * (4 * 3 + 3 * 5 + 4 * 5));
        }
    }

    #[test]
    fn seed_bar_has_80_tets() {
        let m = bar(0.1).unwrap();
        assert_eq!(m.tets().len(), 80);
        assert_eq!(m.nodes().len(), 45);
    }

    #[test]
    fn ellipsoid_volume_converges() {
        let r = Vector3::new(0.05, 0.03, 0.02);
        let m = ellipsoid(Vector3::zeros(), r, 16).unwrap();
        let vol: f64 = (0..m.tets().len()).map(|t| m.tet_volume(t)).sum();
        let exact = 4.0 / 3.0 * std::f64::consts::PI * r.x * r.y * r.z;
        assert!((vol - exact).abs() / exact < 0.02, "{vol} vs {exact}");
        for tri in m.boundary() {
            for &i in tri {
                let p = m.nodes()[i as usize].component_div(&r);
                assert!((p.norm() - 1.0).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn target_sizes_land_near_the_seed_table() {
        let extent = Vector3::new(0.256, 0.160, 0.122);
        for target in [14_000, 35_000, 112_000, 157_000] {
            let cells = cells_for_target(extent, target, CellSplit::Five);
            let tets = cells.iter().product::<usize>() * 5;
            assert!((tets as f64 / target as f64 - 1.0).abs() < 0.15, "{target}: {tets}");
        }
    }
}
