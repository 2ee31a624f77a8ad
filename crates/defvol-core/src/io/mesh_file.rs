//! A mesh as its file holds it, before it becomes a [`TetMesh`]: what every mesh parser
//! fills in.

use std::collections::BTreeMap;
use std::path::Path;

use nalgebra::Vector3;

use super::error::IoError;
use super::solids::{self, Solid};
use crate::mesh::TetMesh;

/// A named point array of a mesh file: `components` values per node.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PointArray {
    pub name: String,
    pub components: usize,
    pub values: Vec<f32>,
    /// Tagged as the active scalars (legacy SCALARS, XML `Scalars="…"`).
    pub active_scalars: bool,
}

/// A named array of one value per tet (Gmsh's physical and elementary regions).
#[derive(Debug, Clone, PartialEq)]
pub struct CellArray {
    pub name: String,
    pub values: Vec<f32>,
}

/// A mesh as its file holds it: nodes, tets, point arrays, and the other cells skipped.
#[derive(Debug, Clone, Default)]
pub(crate) struct MeshFile {
    pub nodes: Vec<Vector3<f64>>,
    pub tets: Vec<[u32; 4]>,
    pub arrays: Vec<PointArray>,
    /// Arrays of one value per tet.
    pub cell_arrays: Vec<CellArray>,
    /// Cells other than linear tets, by kind.
    pub skipped: BTreeMap<&'static str, usize>,
    /// Hexahedra, wedges and pyramids split into tets, by kind.
    pub split: BTreeMap<&'static str, usize>,
    /// The tets those splits made, to be oriented once the nodes are all read.
    pub split_tets: Vec<usize>,
    /// The length unit the file records (field data `metres_per_unit`), when it does.
    pub metres_per_unit: Option<f64>,
}

impl MeshFile {
    /// Adds a piece's array whose nodes start at `first_node`: appended to the earlier
    /// pieces' array of that name, or new for the first piece.
    pub(crate) fn push_array(&mut self, first_node: usize, array: PointArray) {
        match self.arrays.iter_mut().find(|a| a.name == array.name && a.components == array.components) {
            Some(existing) if existing.values.len() == first_node * existing.components => {
                existing.values.extend(array.values)
            }
            Some(_) => {}
            None if first_node == 0 => self.arrays.push(array),
            None => {}
        }
    }

    /// The mesh's own scalars: the first one-component array tagged as the active scalars.
    pub(crate) fn scalars(&self) -> Option<Vec<f32>> {
        self.arrays.iter().find(|a| a.active_scalars && a.components == 1).map(|a| a.values.clone())
    }

    /// Keeps a recorded unit only when it is a length a mesh can have: finite and above zero.
    pub(crate) fn record_unit(&mut self, values: &[f64]) {
        if let [unit] = values {
            self.metres_per_unit = Some(*unit).filter(|u| u.is_finite() && *u > 0.0);
        }
    }

    /// Adds a hexahedron, wedge or pyramid (`nodes` in VTK's order, mesh indices) as tets;
    /// returns how many.
    pub(crate) fn push_solid(&mut self, solid: Solid, nodes: &[u32]) -> Result<usize, String> {
        let tets = solids::split(solid, nodes)?;
        let count = tets.len();
        for tet in tets {
            self.split_tets.push(self.tets.len());
            self.tets.push(tet);
        }
        *self.split.entry(solid.name()).or_insert(0) += 1;
        Ok(count)
    }

    /// Turns each tet a split made to a positive volume (an index past the nodes is left for
    /// [`TetMesh::new`] to refuse).
    fn orient_split_tets(&mut self) {
        for &t in &self.split_tets {
            let tet = &mut self.tets[t];
            let Some(p) = tet.iter().map(|&n| self.nodes.get(n as usize)).collect::<Option<Vec<_>>>() else {
                continue;
            };
            if (p[1] - p[0]).cross(&(p[2] - p[0])).dot(&(p[3] - p[0])) < 0.0 {
                tet.swap(2, 3);
            }
        }
    }

    pub(crate) fn into_mesh(self, path: &Path) -> Result<MeshRead, IoError> {
        let raw = self.into_raw(path);
        let mesh = TetMesh::new(raw.nodes, raw.tets, raw.scalars, &path.display().to_string())?;
        Ok(MeshRead {
            mesh,
            skipped: raw.skipped,
            split: raw.split,
            metres_per_unit: raw.metres_per_unit,
            cell_arrays: raw.cell_arrays,
            unused_nodes: raw.unused_nodes,
        })
    }

    /// The file's nodes and tets as read: solids split, unused nodes dropped, nothing refused.
    pub(crate) fn into_raw(mut self, path: &Path) -> RawMesh {
        if !self.skipped.is_empty() {
            let skipped: Vec<String> = self.skipped.iter().map(|(kind, n)| format!("{n} {kind}")).collect();
            tracing::info!("{}: kept {} tets, skipped {}", path.display(), self.tets.len(), skipped.join(", "));
        }
        if !self.split.is_empty() {
            let split: Vec<String> = self.split.iter().map(|(kind, n)| format!("{n} {kind}")).collect();
            let tets = self.split_tets.len();
            tracing::info!("{}: split {} into {tets} tets (conforming)", path.display(), split.join(", "));
            self.orient_split_tets();
        }
        let unused_nodes = self.drop_unused_nodes();
        if unused_nodes > 0 {
            tracing::info!("{}: dropped {unused_nodes} nodes that no tet uses (the rest renumbered)", path.display());
        }
        RawMesh {
            scalars: self.scalars(),
            nodes: self.nodes,
            tets: self.tets,
            skipped: self.skipped,
            split: self.split,
            metres_per_unit: self.metres_per_unit,
            cell_arrays: self.cell_arrays,
            unused_nodes,
        }
    }

    /// Drops the nodes no tet uses (a mesher's or a cut's leftovers, which would carry no
    /// mass), renumbering the tets and the point arrays; returns how many went. An index past
    /// the nodes is left as it is, for [`TetMesh::new`] to refuse.
    pub(crate) fn drop_unused_nodes(&mut self) -> usize {
        let mut used = vec![false; self.nodes.len()];
        for &node in self.tets.iter().flatten() {
            if let Some(u) = used.get_mut(node as usize) {
                *u = true;
            }
        }
        let unused = used.iter().filter(|u| !**u).count();
        if unused == 0 {
            return 0;
        }
        let mut renumbered = vec![0u32; used.len()];
        for (next, (slot, _)) in renumbered.iter_mut().zip(&used).filter(|(_, u)| **u).enumerate() {
            *slot = next as u32;
        }
        for node in self.tets.iter_mut().flatten() {
            if let Some(&index) = renumbered.get(*node as usize) {
                *node = index;
            }
        }
        let mut kept = used.iter();
        self.nodes.retain(|_| *kept.next().unwrap_or(&true));
        for array in self.arrays.iter_mut().filter(|a| a.values.len() == used.len() * a.components) {
            let values = array.values.chunks(array.components).zip(&used).filter(|(_, u)| **u);
            array.values = values.flat_map(|(v, _)| v.iter().copied()).collect();
        }
        unused
    }
}

/// A mesh file's nodes and tets before a [`TetMesh`] checks them (inverted, flat or
/// repeated-node tets, indices past the nodes are all still there): what `defvol info`
/// reports on, and the positions of a deformed copy of a mesh already checked.
#[derive(Debug, Clone)]
pub struct RawMesh {
    pub nodes: Vec<Vector3<f64>>,
    pub tets: Vec<[u32; 4]>,
    /// The active point scalars, where the file tags some.
    pub scalars: Option<Vec<f32>>,
    pub skipped: SkippedCells,
    pub split: SkippedCells,
    pub metres_per_unit: Option<f64>,
    pub cell_arrays: Vec<CellArray>,
    pub unused_nodes: usize,
}

/// A mesh and what its file said beside the tets.
#[derive(Debug, Clone)]
pub struct MeshRead {
    pub mesh: TetMesh,
    /// The cells other than linear tets the file held, by kind: counted, and skipped.
    pub skipped: SkippedCells,
    /// The hexahedra, wedges and pyramids the file held, by kind: split into tets.
    pub split: SkippedCells,
    /// Metres per file unit, when the file records it (defvol's VTK files do).
    pub metres_per_unit: Option<f64>,
    /// Arrays of one value per tet (Gmsh 1's physical and elementary regions).
    pub cell_arrays: Vec<CellArray>,
    /// Nodes no tet used, dropped on reading.
    pub unused_nodes: usize,
}

impl MeshRead {
    /// The mesh in a frame of `target` metres per unit (1 for a metre world, 0.001 for a
    /// millimetre volume), and the factor applied: `chosen` when given, else the unit the
    /// file records, else `fallback` (what the caller assumes of a file that says nothing).
    pub fn into_scaled(self, target: f64, chosen: Option<f64>, fallback: f64) -> (TetMesh, f64) {
        let scale = chosen.or(self.metres_per_unit.map(|unit| unit / target)).unwrap_or(fallback);
        let mut mesh = self.mesh;
        mesh.map_nodes(|p| p * scale);
        (mesh, scale)
    }
}

/// The cells other than linear tets a mesh file held, by kind: counted, and skipped.
pub type SkippedCells = BTreeMap<&'static str, usize>;
