//! Hexahedra, wedges and pyramids as tets. Each quad face is cut along its diagonal through
//! its smallest node index, and each cell is coned from its smallest node over the faces
//! that do not hold it: the faces at that node are cut through it, so the cone meets every
//! face as cut, and two cells sharing a face cut it alike (a conforming mesh, without
//! new nodes). Dompierre, Labbé, Vallet and Camarero, 1999, *How to subdivide pyramids,
//! prisms and hexahedra into tetrahedra* (8th International Meshing Roundtable) give the
//! rule; coning from the smallest node gives six tets a hexahedron, three a wedge, two a
//! pyramid, for every convex cell.

/// A linear volume cell other than a tet, with its faces in VTK's (and Gmsh's) node order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Solid {
    Hexahedron,
    Wedge,
    Pyramid,
}

impl Solid {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::Hexahedron => "hexahedron",
            Self::Wedge => "wedge",
            Self::Pyramid => "pyramid",
        }
    }

    pub(crate) fn nodes(self) -> usize {
        match self {
            Self::Hexahedron => 8,
            Self::Wedge => 6,
            Self::Pyramid => 5,
        }
    }

    /// Its faces as cycles of its local nodes.
    fn faces(self) -> &'static [&'static [usize]] {
        match self {
            Self::Hexahedron => {
                &[&[0, 1, 2, 3], &[4, 5, 6, 7], &[0, 1, 5, 4], &[1, 2, 6, 5], &[2, 3, 7, 6], &[3, 0, 4, 7]]
            }
            Self::Wedge => &[&[0, 1, 2], &[3, 4, 5], &[0, 1, 4, 3], &[1, 2, 5, 4], &[2, 0, 3, 5]],
            Self::Pyramid => &[&[0, 1, 2, 3], &[0, 1, 4], &[1, 2, 4], &[2, 3, 4], &[3, 0, 4]],
        }
    }
}

/// The tets of a cell whose nodes (mesh indices) are `nodes`, in no particular orientation.
/// A node listed twice is an error naming it.
pub(crate) fn split(solid: Solid, nodes: &[u32]) -> Result<Vec<[u32; 4]>, String> {
    if nodes.len() != solid.nodes() {
        return Err(format!("a {} with {} nodes (it has {})", solid.name(), nodes.len(), solid.nodes()));
    }
    for (i, node) in nodes.iter().enumerate() {
        if nodes[..i].contains(node) {
            return Err(format!("a {} with node {node} twice", solid.name()));
        }
    }
    let apex = (0..nodes.len()).min_by_key(|&i| nodes[i]).unwrap_or(0);
    let mut tets = Vec::new();
    for face in solid.faces().iter().filter(|f| !f.contains(&apex)) {
        let corners: Vec<u32> = face.iter().map(|&i| nodes[i]).collect();
        for [a, b, c] in triangles(&corners) {
            tets.push([nodes[apex], a, b, c]);
        }
    }
    Ok(tets)
}

/// A face's triangles: itself, or a quad cut along the diagonal through its smallest node.
fn triangles(corners: &[u32]) -> Vec<[u32; 3]> {
    match corners {
        [a, b, c] => vec![[*a, *b, *c]],
        _ => {
            let m = (0..4).min_by_key(|&i| corners[i]).unwrap_or(0);
            let at = |k: usize| corners[(m + k) % 4];
            vec![[at(0), at(1), at(2)], [at(0), at(2), at(3)]]
        }
    }
}

/// A VTK cell type that is a solid here, and the order to take its nodes in (a voxel is a
/// hexahedron listed x, y, z fastest).
pub(crate) fn of_vtk(ty: i64) -> Option<(Solid, &'static [usize])> {
    match ty {
        11 => Some((Solid::Hexahedron, &[0, 1, 3, 2, 4, 5, 7, 6])),
        12 => Some((Solid::Hexahedron, &[0, 1, 2, 3, 4, 5, 6, 7])),
        13 => Some((Solid::Wedge, &[0, 1, 2, 3, 4, 5])),
        14 => Some((Solid::Pyramid, &[0, 1, 2, 3, 4])),
        _ => None,
    }
}

/// A VTK solid's nodes in its own order, checked: their count, and each an index below
/// `nodes` (mesh indices).
pub(crate) fn vtk_nodes(solid: Solid, order: &[usize], vertices: &[u32]) -> Result<Vec<u32>, String> {
    if vertices.len() != solid.nodes() {
        return Err(format!("a {} with {} vertices (it has {})", solid.name(), vertices.len(), solid.nodes()));
    }
    Ok(order.iter().map(|&i| vertices[i]).collect())
}
