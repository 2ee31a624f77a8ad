//! The mass-spring model of seed 000 (eqs. 1-5): a spring on every tet edge, masses lumped
//! from tet volume × density, fixed nodes, and optional per-spring material from a volume.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::SolverError;
use defvol_core::mesh::{bounds, TetMesh};

/// One row of a tissue table: springs whose sampled intensity is `intensity` get these values;
/// intensities between rows are interpolated linearly, beyond the ends clamped.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TissueRow {
    pub intensity: f64,
    pub stiffness: f64,
    pub damping: f64,
}

/// Where spring stiffness and damping come from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum Material {
    /// One stiffness (N/m) and damping (N·s/m) for every spring.
    Uniform { stiffness: f64, damping: f64 },
    /// Per spring, from the volume's intensity at the spring's midpoint (a tissue table).
    Table { rows: Vec<TissueRow> },
}

impl Material {
    fn validate(&self) -> Result<(), SolverError> {
        let bad = |what: &str, value: f64| SolverError::BadParameter {
            name: what.to_owned(),
            value,
            why: "must be finite and >= 0".into(),
        };
        match self {
            Material::Uniform { stiffness, damping } => {
                if !(stiffness.is_finite() && *stiffness >= 0.0) {
                    return Err(bad("stiffness", *stiffness));
                }
                if !(damping.is_finite() && *damping >= 0.0) {
                    return Err(bad("damping", *damping));
                }
            }
            Material::Table { rows } => {
                if rows.is_empty() {
                    return Err(SolverError::BadParameter {
                        name: "material.rows".into(),
                        value: 0.0,
                        why: "a tissue table needs at least one row".into(),
                    });
                }
                for w in rows.windows(2) {
                    if w[1].intensity <= w[0].intensity {
                        return Err(SolverError::BadParameter {
                            name: "material.rows.intensity".into(),
                            value: w[1].intensity,
                            why: "intensities must increase from row to row".into(),
                        });
                    }
                }
                for r in rows {
                    Material::Uniform { stiffness: r.stiffness, damping: r.damping }.validate()?;
                }
            }
        }
        Ok(())
    }

    fn lookup(rows: &[TissueRow], intensity: f64) -> (f64, f64) {
        let Some(first) = rows.first() else { return (0.0, 0.0) };
        if intensity <= first.intensity {
            return (first.stiffness, first.damping);
        }
        for w in rows.windows(2) {
            if intensity <= w[1].intensity {
                let t = (intensity - w[0].intensity) / (w[1].intensity - w[0].intensity);
                return (
                    w[0].stiffness + t * (w[1].stiffness - w[0].stiffness),
                    w[0].damping + t * (w[1].damping - w[0].damping),
                );
            }
        }
        rows.last().map_or((0.0, 0.0), |r| (r.stiffness, r.damping))
    }
}

/// Which nodes are held in place (velocity zero).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum FixedNodes {
    Indices {
        nodes: Vec<u32>,
    },
    /// Nodes inside the axis-aligned box [min, max] (world units).
    Box {
        min: [f64; 3],
        max: [f64; 3],
    },
    /// Nodes with `normal · x <= offset` (a clamp plane; the side the normal points away from).
    Plane {
        normal: [f64; 3],
        offset: f64,
    },
    /// The mesh's lowest layer: nodes within `fraction` of its height above its lowest z
    /// (what holds a user's organ on the table when the scene names nothing).
    Lowest {
        #[serde(default = "FixedNodes::lowest_fraction")]
        fraction: f64,
    },
}

impl FixedNodes {
    /// The lowest 2 % of the mesh's height: the layer an organ rests on, on a mesh of
    /// fifty layers or fewer.
    pub const LOWEST_FRACTION: f64 = 0.02;

    fn lowest_fraction() -> f64 {
        Self::LOWEST_FRACTION
    }

    pub fn select(&self, nodes: &[Vector3<f64>]) -> Result<Vec<bool>, SolverError> {
        let mut fixed = vec![false; nodes.len()];
        match self {
            FixedNodes::Indices { nodes: list } => {
                for &i in list {
                    let Some(slot) = fixed.get_mut(i as usize) else {
                        return Err(SolverError::BadParameter {
                            name: "fixed.nodes".into(),
                            value: i as f64,
                            why: format!("node index out of range (mesh has {} nodes)", nodes.len()),
                        });
                    };
                    *slot = true;
                }
            }
            FixedNodes::Box { min, max } => {
                let (lo, hi) = (Vector3::from(*min), Vector3::from(*max));
                for (f, p) in fixed.iter_mut().zip(nodes) {
                    *f = (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]);
                }
            }
            FixedNodes::Plane { normal, offset } => {
                let n = Vector3::from(*normal);
                if !(n.norm() > 0.0 && n.iter().all(|c| c.is_finite())) {
                    return Err(SolverError::BadParameter {
                        name: "fixed.normal".into(),
                        value: n.norm(),
                        why: "plane normal must be a finite non-zero vector".into(),
                    });
                }
                let n = n.normalize();
                let tol = 1e-9 * (1.0 + offset.abs());
                for (f, p) in fixed.iter_mut().zip(nodes) {
                    *f = n.dot(p) <= offset + tol;
                }
            }
            FixedNodes::Lowest { fraction } => {
                if !(fraction.is_finite() && (0.0..=1.0).contains(fraction)) {
                    return Err(SolverError::BadParameter {
                        name: "fixed.fraction".into(),
                        value: *fraction,
                        why: "a fraction of the mesh's height, between 0 and 1".into(),
                    });
                }
                let (lo, hi) = bounds(nodes);
                let top = lo.z + fraction * (hi.z - lo.z) + 1e-9 * (1.0 + lo.z.abs());
                for (f, p) in fixed.iter_mut().zip(nodes) {
                    *f = p.z <= top;
                }
            }
        }
        Ok(fixed)
    }
}

impl std::fmt::Display for FixedNodes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FixedNodes::Indices { nodes } => write!(f, "{} listed nodes", nodes.len()),
            FixedNodes::Box { min, max } => write!(f, "inside the box {min:?} to {max:?}"),
            FixedNodes::Plane { normal, offset } => write!(f, "below the plane {normal:?} · x = {offset}"),
            FixedNodes::Lowest { fraction } => write!(f, "the lowest {}% of the mesh's height", fraction * 100.0),
        }
    }
}

/// The volume intensity at a world point (tissue tables look springs up on it).
pub type IntensityAt<'a> = &'a dyn Fn(&Vector3<f64>) -> Option<f32>;

/// The model in f64, independent of precision and backend; each backend converts once.
#[derive(Debug, Clone)]
pub struct MassSpringModel {
    pub rest: Vec<Vector3<f64>>,
    pub mass: Vec<f64>,
    pub fixed: Vec<bool>,
    pub springs: Vec<[u32; 2]>,
    pub rest_length: Vec<f64>,
    pub stiffness: Vec<f64>,
    pub damping: Vec<f64>,
    /// Node adjacency (CSR): for node i, `adjacency[offsets[i]..offsets[i+1]]` lists
    /// (neighbour, spring) pairs; per-node gathers replace scattered atomics on both backends.
    pub offsets: Vec<u32>,
    pub adjacency: Vec<[u32; 2]>,
    /// Boundary triangles, outward (what tools touch).
    pub boundary: Vec<[u32; 3]>,
}

impl MassSpringModel {
    /// Builds the model; `intensity_at` samples the volume for a tissue-table material.
    pub fn new(
        mesh: &TetMesh,
        material: &Material,
        density: f64,
        fixed: &[bool],
        intensity_at: Option<IntensityAt<'_>>,
    ) -> Result<Self, SolverError> {
        if !(density.is_finite() && density > 0.0) {
            return Err(SolverError::BadParameter {
                name: "density".into(),
                value: density,
                why: "mass must be positive: density > 0".into(),
            });
        }
        material.validate()?;
        let nodes = mesh.nodes();
        if fixed.len() != nodes.len() {
            return Err(SolverError::BadParameter {
                name: "fixed".into(),
                value: fixed.len() as f64,
                why: format!("one flag per node expected ({})", nodes.len()),
            });
        }
        let mut mass = vec![0.0; nodes.len()];
        for t in 0..mesh.tets().len() {
            let m = mesh.tet_volume(t).abs() * density / 4.0;
            for &i in &mesh.tets()[t] {
                mass[i as usize] += m;
            }
        }
        if let Some(i) = mass.iter().position(|m| *m <= 0.0) {
            return Err(SolverError::BadParameter {
                name: "mass".into(),
                value: mass[i],
                why: format!("node {i} belongs to no tet, so it has no mass"),
            });
        }
        let springs = mesh.edges().to_vec();
        let rest_length: Vec<f64> =
            springs.iter().map(|[a, b]| (nodes[*b as usize] - nodes[*a as usize]).norm()).collect();
        let (stiffness, damping): (Vec<f64>, Vec<f64>) = match material {
            Material::Uniform { stiffness, damping } => {
                (vec![*stiffness; springs.len()], vec![*damping; springs.len()])
            }
            Material::Table { rows } => {
                let Some(sample) = intensity_at else {
                    return Err(SolverError::BadParameter {
                        name: "material".into(),
                        value: 0.0,
                        why: "a tissue table needs a volume to sample".into(),
                    });
                };
                springs
                    .iter()
                    .map(|[a, b]| {
                        let mid = (nodes[*a as usize] + nodes[*b as usize]) / 2.0;
                        let intensity = sample(&mid).unwrap_or(rows[0].intensity as f32) as f64;
                        Material::lookup(rows, intensity)
                    })
                    .unzip()
            }
        };
        let mut degree = vec![0u32; nodes.len()];
        for [a, b] in &springs {
            degree[*a as usize] += 1;
            degree[*b as usize] += 1;
        }
        let mut offsets = vec![0u32; nodes.len() + 1];
        for i in 0..nodes.len() {
            offsets[i + 1] = offsets[i] + degree[i];
        }
        let mut cursor = offsets.clone();
        let mut adjacency = vec![[0u32; 2]; offsets[nodes.len()] as usize];
        for (e, [a, b]) in springs.iter().enumerate() {
            adjacency[cursor[*a as usize] as usize] = [*b, e as u32];
            cursor[*a as usize] += 1;
            adjacency[cursor[*b as usize] as usize] = [*a, e as u32];
            cursor[*b as usize] += 1;
        }
        Ok(Self {
            rest: nodes.to_vec(),
            mass,
            fixed: fixed.to_vec(),
            springs,
            rest_length,
            stiffness,
            damping,
            offsets,
            adjacency,
            boundary: mesh.boundary().to_vec(),
        })
    }

    pub fn node_count(&self) -> usize {
        self.rest.len()
    }

    /// Energy at which every spring would be stretched by its own length: far beyond any
    /// physical state, so a simulation above it has diverged.
    pub fn divergence_energy(&self) -> f64 {
        self.springs
            .iter()
            .enumerate()
            .map(|(e, _)| 0.5 * self.stiffness[e] * self.rest_length[e].powi(2))
            .sum::<f64>()
            .max(f64::MIN_POSITIVE)
    }
}

/// A cantilever 0.3 x 0.06 x 0.06 m clamped at x = 0 (k = 1000 N/m, damping 0.5, 1000 kg/m³),
/// `cells` lattice cells of five tets each: the multigrid tests' beam.
#[cfg(test)]
pub(crate) fn clamped_cantilever(cells: [usize; 3]) -> MassSpringModel {
    use defvol_core::mesh::generate::{self, CellSplit};
    let mesh = generate::lattice(Vector3::zeros(), Vector3::new(0.3, 0.06, 0.06), cells, CellSplit::Five).unwrap();
    let fixed = FixedNodes::Plane { normal: [1.0, 0.0, 0.0], offset: 0.0 }.select(mesh.nodes()).unwrap();
    MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 1000.0, damping: 0.5 }, 1000.0, &fixed, None).unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;
    use defvol_core::mesh::generate;

    #[test]
    fn lumped_mass_sums_to_body_mass() {
        let mesh = generate::bar(0.1).unwrap();
        let fixed = vec![false; mesh.nodes().len()];
        let m =
            MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 100.0, damping: 0.0 }, 1000.0, &fixed, None)
                .unwrap();
        let total: f64 = m.mass.iter().sum();
        assert!((total - 0.1 * 0.025 * 0.025 * 1000.0).abs() < 1e-12);
        assert_eq!(m.adjacency.len(), 2 * m.springs.len());
    }

    #[test]
    fn tissue_table_interpolates() {
        let rows = vec![
            TissueRow { intensity: 0.0, stiffness: 100.0, damping: 1.0 },
            TissueRow { intensity: 100.0, stiffness: 300.0, damping: 3.0 },
        ];
        assert_eq!(Material::lookup(&rows, 50.0), (200.0, 2.0));
        assert_eq!(Material::lookup(&rows, -10.0), (100.0, 1.0));
        assert_eq!(Material::lookup(&rows, 1e9), (300.0, 3.0));
    }

    #[test]
    fn impossible_parameters_are_errors() {
        let mesh = generate::bar(0.1).unwrap();
        let fixed = vec![false; mesh.nodes().len()];
        let uniform = Material::Uniform { stiffness: 1.0, damping: 0.0 };
        assert!(MassSpringModel::new(&mesh, &uniform, 0.0, &fixed, None).is_err());
        let negative = Material::Uniform { stiffness: -1.0, damping: 0.0 };
        let e = MassSpringModel::new(&mesh, &negative, 1.0, &fixed, None).unwrap_err();
        assert!(e.to_string().contains("stiffness"), "{e}");
        let e = FixedNodes::Indices { nodes: vec![999] }.select(mesh.nodes()).unwrap_err();
        assert!(e.to_string().contains("999"), "{e}");
    }
}
