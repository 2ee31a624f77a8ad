//! Tetrahedral meshes: nodes, tets and the topology every stage derives from them
//! (unique edges for springs, face neighbours for ray walking, the boundary surface).

pub mod generate;
mod quality;

pub use quality::{quality, Distribution, Quality, SLIVER_DEG};

use std::collections::HashMap;

use nalgebra::Vector3;

/// A problem found while checking a mesh; `source` names the file (or generator).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MeshError {
    #[error("{file}: mesh has no tetrahedra")]
    Empty { file: String },
    #[error("{file}: node {node} has a non-finite coordinate {coords:?}")]
    NonFiniteNode { file: String, node: usize, coords: [f64; 3] },
    #[error("{file}: tet {tet} references node {node}, but the mesh has {nodes} nodes")]
    IndexOutOfRange { file: String, tet: usize, node: u32, nodes: usize },
    #[error("{file}: tet {tet} repeats node {node}")]
    RepeatedNode { file: String, tet: usize, node: u32 },
    #[error("{file}: tet {tet} is degenerate (volume {volume:e}, quality {quality:e} below {min_quality:e})")]
    Degenerate { file: String, tet: usize, volume: f64, quality: f64, min_quality: f64 },
    #[error("{file}: tet {tet} is inverted (signed volume {volume:e}) while {positive} other tets are positive")]
    Inverted { file: String, tet: usize, volume: f64, positive: usize },
    #[error("{file}: face {face:?} is shared by {count} tets (at most 2 allowed), e.g. tet {tet}")]
    NonManifoldFace { file: String, face: [u32; 3], count: usize, tet: usize },
    #[error("{file}: {what} has {got} entries, expected {expected} (one per node)")]
    ScalarCount { file: String, what: String, got: usize, expected: usize },
}

/// Below this ratio of |volume| to (longest edge)^3 a tet is degenerate. A regular tet has
/// ratio 0.118; a sliver of 1e-6 would make the spring and barycentric maths meaningless.
pub const MIN_TET_QUALITY: f64 = 1e-6;

/// A validated tetrahedral mesh with its derived topology.
///
/// Tets are stored positively oriented: `det[x1-x0, x2-x0, x3-x0] > 0`.
#[derive(Debug, Clone)]
pub struct TetMesh {
    nodes: Vec<Vector3<f64>>,
    tets: Vec<[u32; 4]>,
    scalars: Option<Vec<f32>>,
    edges: Vec<[u32; 2]>,
    neighbours: Vec<[i32; 4]>,
    boundary: Vec<[u32; 3]>,
}

/// Tets turned inside out by a deformation ([`TetMesh::inverted`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Inversion {
    /// How many tets have a signed volume of zero or less.
    pub count: usize,
    /// The worst: its index and its signed volume over its rest volume.
    pub worst: Option<(usize, f64)>,
}

/// Face of a tet opposite vertex k, ordered so that its normal points out of the tet.
pub const TET_FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]];

impl TetMesh {
    /// Validates `nodes`/`tets` and derives edges, neighbours and the boundary.
    ///
    /// A mesh whose tets are *all* negatively oriented follows the other handedness
    /// convention (some writers do): it is flipped consistently instead of rejected.
    pub fn new(
        nodes: Vec<Vector3<f64>>,
        mut tets: Vec<[u32; 4]>,
        scalars: Option<Vec<f32>>,
        source: &str,
    ) -> Result<Self, MeshError> {
        let source_name = || source.to_owned();
        if tets.is_empty() {
            return Err(MeshError::Empty { file: source_name() });
        }
        if let Some((node, p)) = nodes.iter().enumerate().find(|(_, p)| !p.iter().all(|c| c.is_finite())) {
            return Err(MeshError::NonFiniteNode { file: source_name(), node, coords: [p.x, p.y, p.z] });
        }
        for (tet, t) in tets.iter().enumerate() {
            for (a, &node) in t.iter().enumerate() {
                if node as usize >= nodes.len() {
                    return Err(MeshError::IndexOutOfRange { file: source_name(), tet, node, nodes: nodes.len() });
                }
                if t[..a].contains(&node) {
                    return Err(MeshError::RepeatedNode { file: source_name(), tet, node });
                }
            }
        }
        if let Some(s) = &scalars {
            if s.len() != nodes.len() {
                return Err(MeshError::ScalarCount {
                    file: source_name(),
                    what: "per-node scalar".into(),
                    got: s.len(),
                    expected: nodes.len(),
                });
            }
        }
        let volumes: Vec<f64> = tets.iter().map(|t| signed_volume(&nodes, t)).collect();
        let positive = volumes.iter().filter(|v| **v > 0.0).count();
        if positive == 0 {
            for t in &mut tets {
                t.swap(1, 2);
            }
        } else if let Some((tet, &volume)) = volumes.iter().enumerate().find(|(_, v)| **v < 0.0) {
            return Err(MeshError::Inverted { file: source_name(), tet, volume, positive });
        }
        for (tet, t) in tets.iter().enumerate() {
            let quality = tet_quality(&nodes, t);
            if quality < MIN_TET_QUALITY {
                return Err(MeshError::Degenerate {
                    file: source_name(),
                    tet,
                    volume: signed_volume(&nodes, t),
                    quality,
                    min_quality: MIN_TET_QUALITY,
                });
            }
        }
        let edges = unique_edges(&tets);
        let (neighbours, boundary) = face_topology(&tets, source)?;
        Ok(Self { nodes, tets, scalars, edges, neighbours, boundary })
    }

    pub fn nodes(&self) -> &[Vector3<f64>] {
        &self.nodes
    }
    pub fn tets(&self) -> &[[u32; 4]] {
        &self.tets
    }
    /// Unique tet edges, `a < b`, sorted: the springs of the mass-spring model.
    pub fn edges(&self) -> &[[u32; 2]] {
        &self.edges
    }
    /// `neighbours[t][k]`: the tet across the face opposite vertex k, or -1 on the boundary.
    pub fn neighbours(&self) -> &[[i32; 4]] {
        &self.neighbours
    }
    /// Boundary triangles, outward-oriented.
    pub fn boundary(&self) -> &[[u32; 3]] {
        &self.boundary
    }

    /// The tets turned inside out at `positions` (the mesh deformed; one per node): how
    /// many, and the worst, as its signed volume over its rest volume.
    pub fn inverted(&self, positions: &[Vector3<f64>]) -> Inversion {
        let mut inversion = Inversion::default();
        if positions.len() != self.nodes.len() {
            return inversion;
        }
        for (tet, t) in self.tets.iter().enumerate() {
            let ratio = signed_volume(positions, t) / signed_volume(&self.nodes, t);
            if ratio <= 0.0 {
                inversion.count += 1;
                if inversion.worst.is_none_or(|(_, worst)| ratio < worst) {
                    inversion.worst = Some((tet, ratio));
                }
            }
        }
        inversion
    }

    /// Boundary edges held by other than two boundary triangles (bodies touching along an
    /// edge, as meshes cut from segmentations have), sorted.
    pub fn non_manifold_edges(&self) -> Vec<[u32; 2]> {
        non_manifold_edges(&self.boundary)
    }

    /// Boundary nodes where bodies touch at a point, sorted ([`non_manifold_vertices`]).
    pub fn non_manifold_vertices(&self) -> Vec<u32> {
        non_manifold_vertices(&self.boundary)
    }
    pub fn scalars(&self) -> Option<&[f32]> {
        self.scalars.as_deref()
    }

    /// Replaces the per-node scalar (e.g. intensities sampled from a volume).
    pub fn set_scalars(&mut self, scalars: Vec<f32>) -> Result<(), MeshError> {
        if scalars.len() != self.nodes.len() {
            return Err(MeshError::ScalarCount {
                file: "set_scalars".into(),
                what: "per-node scalar".into(),
                got: scalars.len(),
                expected: self.nodes.len(),
            });
        }
        self.scalars = Some(scalars);
        Ok(())
    }

    /// Same topology, other node positions (a deformed state); not re-validated,
    /// since deformed states may legitimately contain inverted tets.
    pub fn with_nodes(&self, nodes: Vec<Vector3<f64>>) -> Option<Self> {
        (nodes.len() == self.nodes.len()).then(|| Self { nodes, ..self.clone() })
    }

    /// Applies `f` to every node (unit conversion, placement), keeping the topology.
    pub fn map_nodes(&mut self, f: impl Fn(&Vector3<f64>) -> Vector3<f64>) {
        for p in &mut self.nodes {
            *p = f(p);
        }
    }

    pub fn tet_volume(&self, t: usize) -> f64 {
        signed_volume(&self.nodes, &self.tets[t])
    }

    /// Axis-aligned bounds (min, max) of the nodes.
    pub fn bounds(&self) -> (Vector3<f64>, Vector3<f64>) {
        bounds(&self.nodes)
    }

    /// The smallest and largest dihedral angle (radians) over every tet: the quality
    /// measure meshers report (a regular tet's are all acos(1/3) = 70.53°; slivers near 0°
    /// or 180° stiffen springs and spoil barycentric maps).
    pub fn dihedral_range(&self) -> (f64, f64) {
        self.tets.iter().map(|t| dihedral_angles(&self.nodes, t)).fold((f64::INFINITY, 0.0), |(lo, hi), angles| {
            angles.iter().fold((lo, hi), |(lo, hi), a| (lo.min(*a), hi.max(*a)))
        })
    }
}

/// A tet's six dihedral angles: π minus the angle between the outward normals of the two
/// faces that meet at each edge.
pub fn dihedral_angles(nodes: &[Vector3<f64>], t: &[u32; 4]) -> [f64; 6] {
    let p = t.map(|i| nodes[i as usize]);
    let normal = |face: [usize; 3]| (p[face[1]] - p[face[0]]).cross(&(p[face[2]] - p[face[0]])).normalize();
    let n = TET_FACES.map(normal);
    let mut angles = [0.0; 6];
    let pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];
    for (k, (i, j)) in pairs.into_iter().enumerate() {
        angles[k] = std::f64::consts::PI - n[i].dot(&n[j]).clamp(-1.0, 1.0).acos();
    }
    angles
}

pub fn bounds(points: &[Vector3<f64>]) -> (Vector3<f64>, Vector3<f64>) {
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    for p in points {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    (lo, hi)
}

pub fn signed_volume(nodes: &[Vector3<f64>], t: &[u32; 4]) -> f64 {
    let p0 = nodes[t[0] as usize];
    let a = nodes[t[1] as usize] - p0;
    let b = nodes[t[2] as usize] - p0;
    let c = nodes[t[3] as usize] - p0;
    a.dot(&b.cross(&c)) / 6.0
}

fn tet_quality(nodes: &[Vector3<f64>], t: &[u32; 4]) -> f64 {
    let mut longest: f64 = 0.0;
    for a in 0..4 {
        for b in a + 1..4 {
            longest = longest.max((nodes[t[a] as usize] - nodes[t[b] as usize]).norm());
        }
    }
    if longest == 0.0 {
        return 0.0;
    }
    signed_volume(nodes, t).abs() / longest.powi(3)
}

fn unique_edges(tets: &[[u32; 4]]) -> Vec<[u32; 2]> {
    let mut edges: Vec<[u32; 2]> = tets
        .iter()
        .flat_map(|t| [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)].map(|(a, b)| [t[a].min(t[b]), t[a].max(t[b])]))
        .collect();
    edges.sort_unstable();
    edges.dedup();
    edges
}

/// Per tet, the neighbour across each face (or -1); and the boundary faces.
type FaceTopology = (Vec<[i32; 4]>, Vec<[u32; 3]>);

fn face_topology(tets: &[[u32; 4]], source: &str) -> Result<FaceTopology, MeshError> {
    let mut owners: HashMap<[u32; 3], (usize, usize, u32)> = HashMap::with_capacity(tets.len() * 2);
    let mut neighbours = vec![[-1i32; 4]; tets.len()];
    for (t, tet) in tets.iter().enumerate() {
        for (k, face) in TET_FACES.iter().enumerate() {
            let mut key = face.map(|i| tet[i]);
            key.sort_unstable();
            let entry = owners.entry(key).or_insert((t, k, 0));
            entry.2 += 1;
            match entry.2 {
                1 => {}
                2 => {
                    let (other, other_k, _) = *entry;
                    neighbours[t][k] = other as i32;
                    neighbours[other][other_k] = t as i32;
                }
                count => {
                    return Err(MeshError::NonManifoldFace {
                        file: source.to_owned(),
                        face: key,
                        count: count as usize,
                        tet: t,
                    })
                }
            }
        }
    }
    let mut boundary = Vec::new();
    for (t, tet) in tets.iter().enumerate() {
        for (k, face) in TET_FACES.iter().enumerate() {
            if neighbours[t][k] < 0 {
                boundary.push(face.map(|i| tet[i]));
            }
        }
    }
    Ok((neighbours, boundary))
}

/// The edges of `boundary` (triangles) held by other than two of its triangles, sorted.
pub fn non_manifold_edges(boundary: &[[u32; 3]]) -> Vec<[u32; 2]> {
    let mut edges: Vec<[u32; 2]> =
        boundary_edge_counts(boundary).into_iter().filter(|(_, n)| *n != 2).map(|(e, _)| e).collect();
    edges.sort_unstable();
    edges
}

/// The nodes of `boundary` where bodies touch at a point: their triangles fall into more
/// than one fan (triangles joined through edges of two triangles), and no non-manifold
/// edge ends there. Sorted.
pub fn non_manifold_vertices(boundary: &[[u32; 3]]) -> Vec<u32> {
    let counts = boundary_edge_counts(boundary);
    let mut around: HashMap<u32, Vec<usize>> = HashMap::new();
    for (f, tri) in boundary.iter().enumerate() {
        for &n in tri {
            around.entry(n).or_default().push(f);
        }
    }
    let on_bad_edge: std::collections::HashSet<u32> =
        counts.iter().filter(|(_, c)| **c != 2).flat_map(|(e, _)| *e).collect();
    let mut nodes: Vec<u32> = around
        .into_iter()
        .filter(|(node, faces)| !on_bad_edge.contains(node) && fans(boundary, *node, faces, &counts) > 1)
        .map(|(node, _)| node)
        .collect();
    nodes.sort_unstable();
    nodes
}

/// How many fans the triangles `faces` of `boundary` around `node` form.
fn fans(boundary: &[[u32; 3]], node: u32, faces: &[usize], counts: &HashMap<[u32; 2], usize>) -> usize {
    let mut fan: Vec<usize> = (0..faces.len()).collect();
    for a in 0..faces.len() {
        for b in a + 1..faces.len() {
            let shared: Vec<u32> =
                boundary[faces[a]].iter().filter(|n| boundary[faces[b]].contains(n)).copied().collect();
            if let [p, q] = shared[..] {
                let other = if p == node { q } else { p };
                if counts.get(&[node.min(other), node.max(other)]) == Some(&2) {
                    let (ra, rb) = (root(&fan, a), root(&fan, b));
                    fan[ra] = rb;
                }
            }
        }
    }
    (0..faces.len()).filter(|&i| root(&fan, i) == i).count()
}

/// The root of `i` in a union-find forest.
pub(crate) fn root(forest: &[usize], mut i: usize) -> usize {
    while forest[i] != i {
        i = forest[i];
    }
    i
}

/// How many boundary triangles hold each boundary edge (`a < b`).
pub(crate) fn boundary_edge_counts(boundary: &[[u32; 3]]) -> HashMap<[u32; 2], usize> {
    let mut count: HashMap<[u32; 2], usize> = HashMap::with_capacity(boundary.len() * 2);
    for tri in boundary {
        for e in 0..3 {
            let (a, b) = (tri[e], tri[(e + 1) % 3]);
            *count.entry([a.min(b), a.max(b)]).or_default() += 1;
        }
    }
    count
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dihedral_angles_of_a_regular_and_a_corner_tet_are_the_analytic_ones() {
        let regular = [[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]].map(Vector3::from);
        let corner = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(Vector3::from);
        let mesh = |nodes: [Vector3<f64>; 4]| TetMesh::new(nodes.to_vec(), vec![[0, 1, 2, 3]], None, "tet").unwrap();
        let (lo, hi) = mesh(regular).dihedral_range();
        let tetrahedral = (1.0f64 / 3.0).acos();
        assert!((lo - tetrahedral).abs() < 1e-12 && (hi - tetrahedral).abs() < 1e-12, "{lo} {hi}");
        // Three right angles along the axes; where the slanted face meets an axis plane,
        // acos(1/√3) = 54.74°.
        let (lo, hi) = mesh(corner).dihedral_range();
        let slanted = (1.0f64 / 3.0f64.sqrt()).acos();
        assert!((lo - slanted).abs() < 1e-12 && (hi - std::f64::consts::FRAC_PI_2).abs() < 1e-12, "{lo} {hi}");
    }

    fn unit_tet() -> (Vec<Vector3<f64>>, Vec<[u32; 4]>) {
        (vec![Vector3::zeros(), Vector3::x(), Vector3::y(), Vector3::z()], vec![[0, 1, 2, 3]])
    }

    #[test]
    fn single_tet_topology() {
        let (n, t) = unit_tet();
        let m = TetMesh::new(n, t, None, "unit").unwrap();
        assert_eq!(m.edges().len(), 6);
        assert_eq!(m.boundary().len(), 4);
        assert!((m.tet_volume(0) - 1.0 / 6.0).abs() < 1e-15);
        // Outward normals: each face normal points away from the opposite vertex.
        for (k, f) in TET_FACES.iter().enumerate() {
            let p = |i: usize| m.nodes()[m.tets()[0][i] as usize];
            let normal = (p(f[1]) - p(f[0])).cross(&(p(f[2]) - p(f[0])));
            assert!(normal.dot(&(p(k) - p(f[0]))) < 0.0, "face {k} points inwards");
        }
    }

    #[test]
    fn all_negative_mesh_is_flipped_not_rejected() {
        let (n, _) = unit_tet();
        let m = TetMesh::new(n, vec![[0, 2, 1, 3]], None, "neg").unwrap();
        assert!(m.tet_volume(0) > 0.0);
    }

    #[test]
    fn errors_name_the_element() {
        let (mut n, t) = unit_tet();
        let e = TetMesh::new(n.clone(), vec![[0, 1, 2, 7]], None, "f.vtu").unwrap_err();
        assert!(matches!(e, MeshError::IndexOutOfRange { tet: 0, node: 7, .. }), "{e}");
        assert!(e.to_string().starts_with("f.vtu: tet 0"));
        n.push(Vector3::new(1.0, 1.0, 1.0));
        let e = TetMesh::new(n.clone(), vec![[0, 1, 2, 3], [1, 2, 3, 4], [0, 2, 1, 4]], None, "m").unwrap_err();
        assert!(matches!(e, MeshError::Inverted { .. }), "{e}");
        let flat = vec![Vector3::zeros(), Vector3::x(), Vector3::y(), Vector3::new(0.3, 0.3, 1e-9)];
        let e = TetMesh::new(flat, t.clone(), None, "m").unwrap_err();
        assert!(matches!(e, MeshError::Degenerate { tet: 0, .. }), "{e}");
        let mut nan = n.clone();
        nan[2].y = f64::NAN;
        let e = TetMesh::new(nan, t, None, "m").unwrap_err();
        assert!(matches!(e, MeshError::NonFiniteNode { node: 2, .. }), "{e}");
    }

    #[test]
    fn tets_sharing_only_an_edge_or_a_node_load_and_say_where() {
        // Two tets glued along the edge (0,1) only; two more touching the first at node 3.
        let n = vec![
            Vector3::zeros(),
            Vector3::x(),
            Vector3::y(),
            Vector3::z(),
            Vector3::new(0.0, -1.0, 0.0),
            Vector3::new(0.0, 0.0, -1.0),
        ];
        let bowtie = TetMesh::new(n.clone(), vec![[0, 1, 2, 3], [0, 1, 4, 5]], None, "bowtie").unwrap();
        assert_eq!((bowtie.non_manifold_edges(), bowtie.non_manifold_vertices()), (vec![[0, 1]], vec![]));
        let mut n = n;
        n.extend([Vector3::new(0.0, 0.0, 2.0), Vector3::new(1.0, 0.0, 2.0), Vector3::new(0.0, 1.0, 2.0)]);
        let touching = TetMesh::new(n, vec![[0, 1, 2, 3], [3, 6, 7, 8]], None, "touching").unwrap();
        assert_eq!((touching.non_manifold_edges(), touching.non_manifold_vertices()), (vec![], vec![3]));
    }
}
