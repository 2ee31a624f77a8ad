//! What `defvol info` says of a mesh: element quality and boundary topology, computed from
//! the nodes and tets as read, so a mesh the solver would refuse is described, not refused.

use std::collections::HashMap;

use nalgebra::Vector3;

use super::{bounds, dihedral_angles, non_manifold_edges, non_manifold_vertices, root, signed_volume, TET_FACES};

/// The smallest dihedral angle under which a tet is called a sliver (degrees).
pub const SLIVER_DEG: f64 = 5.0;

/// The smallest value, the 1st percentile and the median of a per-tet measure.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Distribution {
    pub min: f64,
    pub p1: f64,
    pub median: f64,
}

impl Distribution {
    fn of(mut values: Vec<f64>) -> Option<Self> {
        values.retain(|v| v.is_finite());
        values.sort_by(f64::total_cmp);
        let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
        (!values.is_empty()).then(|| Self { min: values[0], p1: at(0.01), median: at(0.5) })
    }
}

/// A mesh's element quality and boundary topology.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Quality {
    pub nodes: usize,
    pub tets: usize,
    /// Tets naming a node twice or a node past the nodes: left out of everything below.
    pub broken_tets: usize,
    /// Tets of zero volume.
    pub flat_tets: usize,
    /// Tets oriented against the rest (against the majority: a file of the other handedness
    /// has none).
    pub inverted_tets: usize,
    /// Each tet's smallest dihedral angle (degrees).
    pub min_dihedral_deg: Option<Distribution>,
    /// The largest dihedral angle of any tet (degrees).
    pub max_dihedral_deg: Option<f64>,
    /// Each tet's radius ratio, 3 r_in / r_circ: 1 for a regular tet, 0 for a flat one.
    pub radius_ratio: Option<Distribution>,
    /// Tets whose smallest dihedral angle is under [`SLIVER_DEG`].
    pub slivers: usize,
    pub boundary_triangles: usize,
    /// Pieces of the boundary joined through shared edges: one per closed surface.
    pub boundary_components: usize,
    pub non_manifold_edges: usize,
    pub non_manifold_vertices: usize,
    /// Interior faces held by more than two tets (overlapping elements).
    pub overfull_faces: usize,
    pub bounds: [[f64; 3]; 2],
}

/// The quality of the mesh of `nodes` and `tets`, whatever they hold.
pub fn quality(nodes: &[Vector3<f64>], tets: &[[u32; 4]]) -> Quality {
    let whole =
        |t: &&[u32; 4]| t.iter().all(|&n| (n as usize) < nodes.len()) && (0..4).all(|a| !t[..a].contains(&t[a]));
    let good: Vec<[u32; 4]> = tets.iter().filter(whole).copied().collect();
    let volumes: Vec<f64> = good.iter().map(|t| signed_volume(nodes, t)).collect();
    let positive = volumes.iter().filter(|v| **v > 0.0).count();
    let negative = volumes.iter().filter(|v| **v < 0.0).count();
    let solid: Vec<&[u32; 4]> = good.iter().zip(&volumes).filter(|(_, v)| **v != 0.0).map(|(t, _)| t).collect();
    let extremes: Vec<(f64, f64)> = (solid.iter())
        .map(|t| {
            let angles = dihedral_angles(nodes, t);
            (min_of(angles).to_degrees(), max_of(angles).to_degrees())
        })
        .collect();
    let min_dihedral: Vec<f64> = extremes.iter().map(|(min, _)| *min).collect();
    let max_dihedral = extremes.iter().map(|(_, max)| *max).reduce(f64::max);
    let (boundary, overfull_faces) = boundary(&good);
    let (lo, hi) = bounds(nodes);
    Quality {
        nodes: nodes.len(),
        tets: tets.len(),
        broken_tets: tets.len() - good.len(),
        flat_tets: good.len() - positive - negative,
        inverted_tets: positive.min(negative),
        slivers: min_dihedral.iter().filter(|a| **a < SLIVER_DEG).count(),
        min_dihedral_deg: Distribution::of(min_dihedral),
        max_dihedral_deg: max_dihedral,
        radius_ratio: Distribution::of(solid.iter().map(|t| radius_ratio(nodes, t)).collect()),
        boundary_triangles: boundary.len(),
        boundary_components: components(&boundary),
        non_manifold_edges: non_manifold_edges(&boundary).len(),
        non_manifold_vertices: non_manifold_vertices(&boundary).len(),
        overfull_faces,
        bounds: [[lo.x, lo.y, lo.z], [hi.x, hi.y, hi.z]],
    }
}

fn min_of(angles: [f64; 6]) -> f64 {
    angles.into_iter().fold(f64::INFINITY, f64::min)
}

fn max_of(angles: [f64; 6]) -> f64 {
    angles.into_iter().fold(f64::NEG_INFINITY, f64::max)
}

/// 3 r_in / r_circ: r_in = 3V / (the faces' area), r_circ = |a²(b×c) + b²(c×a) + c²(a×b)| / 12V
/// for the edges a, b, c from one corner.
fn radius_ratio(nodes: &[Vector3<f64>], t: &[u32; 4]) -> f64 {
    let p = t.map(|i| nodes[i as usize]);
    let (a, b, c) = (p[1] - p[0], p[2] - p[0], p[3] - p[0]);
    let volume = a.dot(&b.cross(&c)).abs() / 6.0;
    let area: f64 = TET_FACES.iter().map(|f| (p[f[1]] - p[f[0]]).cross(&(p[f[2]] - p[f[0]])).norm() / 2.0).sum();
    let circumradius =
        (a.norm_squared() * b.cross(&c) + b.norm_squared() * c.cross(&a) + c.norm_squared() * a.cross(&b)).norm()
            / (12.0 * volume);
    3.0 * (3.0 * volume / area) / circumradius
}

/// The faces held by one tet (each as its tet orders it), and how many faces more than two
/// tets hold.
fn boundary(tets: &[[u32; 4]]) -> (Vec<[u32; 3]>, usize) {
    let mut faces: HashMap<[u32; 3], (usize, [u32; 3])> = HashMap::with_capacity(tets.len() * 2);
    for t in tets {
        for face in TET_FACES {
            let tri = face.map(|i| t[i]);
            let mut key = tri;
            key.sort_unstable();
            faces.entry(key).and_modify(|(n, _)| *n += 1).or_insert((1, tri));
        }
    }
    let overfull = faces.values().filter(|(n, _)| *n > 2).count();
    let mut boundary: Vec<[u32; 3]> = faces.into_values().filter(|(n, _)| *n == 1).map(|(_, tri)| tri).collect();
    boundary.sort_unstable();
    (boundary, overfull)
}

/// Pieces of a set of triangles joined through shared edges.
fn components(triangles: &[[u32; 3]]) -> usize {
    let mut forest: Vec<usize> = (0..triangles.len()).collect();
    let mut first_on_edge: HashMap<[u32; 2], usize> = HashMap::new();
    for (f, tri) in triangles.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            match first_on_edge.get(&[a.min(b), a.max(b)]) {
                Some(&g) => {
                    let (rf, rg) = (root(&forest, f), root(&forest, g));
                    forest[rf] = rg;
                }
                None => {
                    first_on_edge.insert([a.min(b), a.max(b)], f);
                }
            }
        }
    }
    (0..triangles.len()).filter(|&f| root(&forest, f) == f).count()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A regular tet: every dihedral angle acos(1/3), radius ratio 1. A unit cube's corner
    /// tet: smallest dihedral acos(1/√3) (between a slanted face and an axis face), radius
    /// ratio 3 r_in / r_circ with r_in = (1/2) / (3/2 + √3/2) and r_circ = √3/2.
    #[test]
    fn a_regular_and_a_corner_tet_have_their_analytic_quality() {
        let regular = [[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]].map(Vector3::from);
        let q = quality(&regular, &[[0, 1, 2, 3]]);
        let tetrahedral = (1.0f64 / 3.0).acos().to_degrees();
        assert!((q.min_dihedral_deg.unwrap().min - tetrahedral).abs() < 1e-9, "{q:?}");
        assert!((q.radius_ratio.unwrap().median - 1.0).abs() < 1e-12, "{q:?}");
        assert_eq!((q.boundary_triangles, q.boundary_components, q.slivers), (4, 1, 0));
        let corner = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(Vector3::from);
        let q = quality(&corner, &[[0, 1, 2, 3]]);
        let expected = 3.0 * (0.5 / (1.5 + 3f64.sqrt() / 2.0)) / (3f64.sqrt() / 2.0);
        assert!((q.radius_ratio.unwrap().min - expected).abs() < 1e-12, "{q:?} against {expected}");
        let smallest = (1.0 / 3f64.sqrt()).acos().to_degrees();
        assert!((q.min_dihedral_deg.unwrap().min - smallest).abs() < 1e-9, "{q:?}");
        assert!((q.max_dihedral_deg.unwrap() - 90.0).abs() < 1e-9, "{q:?}");
    }
}
