//! The order the raycaster keeps a mesh's tets in: along a Morton (Z-order) curve of their
//! centroids, so that the tets a ray crosses one after another lie near each other in
//! memory whatever order the mesh's file listed them in (a shuffled mesh's frame ran
//! slower; see docs/perf/journal.md#tets-in-morton-order).

use defvol_core::mesh::{bounds, TetMesh};
use nalgebra::Vector3;
use rayon::prelude::*;

/// Bits of a centroid's cell per axis: three axes fill 63 bits of the code, and cells a
/// two-millionth of the mesh's extent leave no two tets of a real mesh sharing one.
const BITS: u32 = 21;

/// The mesh's tets in Morton order of their centroids: new index → the mesh's index (tets
/// sharing a code keep the mesh's order).
pub(crate) fn spatial_order(mesh: &TetMesh) -> Vec<usize> {
    let nodes = mesh.nodes();
    let centroids: Vec<Vector3<f64>> =
        mesh.tets().iter().map(|tet| tet.iter().map(|&i| nodes[i as usize]).sum::<Vector3<f64>>() / 4.0).collect();
    let (lo, hi) = bounds(&centroids);
    let top = f64::from((1u32 << BITS) - 1);
    let scale = (hi - lo).map(|e| if e > 0.0 { top / e } else { 0.0 });
    let mut keyed: Vec<(u64, usize)> = centroids
        .iter()
        .enumerate()
        .map(|(t, c)| (morton(std::array::from_fn(|a| ((c[a] - lo[a]) * scale[a]).clamp(0.0, top) as u32)), t))
        .collect();
    keyed.par_sort_unstable();
    keyed.into_iter().map(|(_, t)| t).collect()
}

/// `neighbours` (per tet and face, the tet across it or -1) with the tets renumbered by
/// `order` (new index → old index): row n is tet `order[n]`'s, naming new indices.
pub(crate) fn renumbered_neighbours(neighbours: &[[i32; 4]], order: &[usize]) -> Vec<[i32; 4]> {
    let mut new_of_old = vec![0i32; order.len()];
    for (new, &old) in order.iter().enumerate() {
        // A mesh's tet count fits i32: its neighbours are stored as i32.
        new_of_old[old] = new as i32;
    }
    order.iter().map(|&old| neighbours[old].map(|m| usize::try_from(m).map_or(-1, |m| new_of_old[m]))).collect()
}

/// The Morton code of a cell: its coordinates' bits interleaved, x lowest.
fn morton(cell: [u32; 3]) -> u64 {
    spread(cell[0]) | spread(cell[1]) << 1 | spread(cell[2]) << 2
}

/// The low [`BITS`] bits of `v`, each moved to three times its place.
fn spread(v: u32) -> u64 {
    let mut x = u64::from(v) & ((1 << BITS) - 1);
    x = (x | x << 32) & 0x001f_0000_0000_ffff;
    x = (x | x << 16) & 0x001f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    x = (x | x << 2) & 0x1249_2492_4924_9249;
    x
}

#[cfg(test)]
mod tests {
    use super::*;
    use defvol_core::mesh::generate::{lattice, CellSplit};
    use defvol_core::mesh::TET_FACES;
    use nalgebra::Vector3;

    /// Bit i of axis a lands at bit 3i + a, against a bit-by-bit loop, over random cells
    /// and the corners of the range.
    #[test]
    fn morton_codes_interleave_the_axes_bits() {
        let naive = |cell: [u32; 3]| {
            (0..BITS).fold(0u64, |code, i| {
                (0..3).fold(code, |code, a| code | u64::from(cell[a] >> i & 1) << (3 * i + a as u32))
            })
        };
        let mut rng = fastrand::Rng::with_seed(38);
        let top = (1 << BITS) - 1;
        let mut cells = vec![[0, 0, 0], [top; 3], [top, 0, 0], [0, top, 0], [0, 0, top]];
        cells.extend((0..10_000).map(|_| [0; 3].map(|_: u32| rng.u32(0..=top))));
        for cell in cells {
            assert_eq!(morton(cell), naive(cell), "{cell:?}");
        }
    }

    /// A lattice with its tets shuffled, renumbered: every face neighbour still shares
    /// exactly that face's nodes, and neighbours sit near each other in the new order
    /// where the shuffle had scattered them.
    #[test]
    fn a_shuffled_meshs_neighbours_are_renumbered_near_each_other() {
        let ordered = lattice(Vector3::zeros(), Vector3::new(30.0, 20.0, 24.0), [15, 10, 12], CellSplit::Five).unwrap();
        let mut tets = ordered.tets().to_vec();
        fastrand::Rng::with_seed(7).shuffle(&mut tets);
        let mesh = TetMesh::new(ordered.nodes().to_vec(), tets, None, "shuffled lattice").unwrap();
        let order = spatial_order(&mesh);
        let mut seen = order.clone();
        seen.sort_unstable();
        assert!(seen.iter().enumerate().all(|(i, &t)| i == t), "not a permutation");
        let neighbours = renumbered_neighbours(mesh.neighbours(), &order);
        let tets: Vec<[u32; 4]> = order.iter().map(|&t| mesh.tets()[t]).collect();
        let gap = |neighbours: &[[i32; 4]]| {
            let mut gaps: Vec<usize> = (0..neighbours.len())
                .flat_map(|n| neighbours[n].iter().filter(|&&m| m >= 0).map(move |&m| n.abs_diff(m as usize)))
                .collect();
            gaps.sort_unstable();
            gaps[gaps.len() / 2]
        };
        let mut faces = 0;
        for (n, row) in neighbours.iter().enumerate() {
            for (k, &m) in row.iter().enumerate() {
                let Ok(m) = usize::try_from(m) else { continue };
                let face = TET_FACES[k].map(|v| tets[n][v]);
                let shared = face.iter().filter(|v| tets[m].contains(v)).count();
                assert_eq!(shared, 3, "tet {n} face {k}: neighbour {m} shares {shared} of {face:?}");
                assert!(neighbours[m].contains(&(n as i32)), "tet {m} does not name {n} back");
                faces += 1;
            }
        }
        assert_eq!(faces, mesh.neighbours().iter().flatten().filter(|&&m| m >= 0).count());
        let (before, after) = (gap(mesh.neighbours()), gap(&neighbours));
        assert!(before > tets.len() / 5, "the shuffle left neighbours {before} apart (median)");
        assert!(after < tets.len() / 100, "renumbered neighbours {after} apart (median) of {} tets", tets.len());
    }
}
