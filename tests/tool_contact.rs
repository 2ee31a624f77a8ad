//! Tools against the mesh: contact pushes nodes out, the reaction balances it, and a
//! commanded force moves the mesh by what its stiffness predicts.

use defvol::mesh::generate::{self, CellSplit};
use defvol::solver::{FixedNodes, MassSpringModel, Material, Simulation, SolverParams, Tool, ToolShape};
use nalgebra::{Isometry3, Vector3};

fn block() -> MassSpringModel {
    let mesh =
        generate::lattice(Vector3::new(-0.05, -0.05, -0.05), Vector3::new(0.05, 0.05, 0.0), [6, 6, 3], CellSplit::Five)
            .unwrap();
    let fixed = FixedNodes::Plane { normal: [0.0, 0.0, 1.0], offset: -0.05 }.select(mesh.nodes()).unwrap();
    MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 500.0, damping: 1.0 }, 1000.0, &fixed, None).unwrap()
}

#[test]
fn pressing_sphere_settles_with_reaction_equal_to_the_support_load() {
    let model = block();
    let mut tool = Tool::new(ToolShape::Sphere { radius: 0.02 }, 3000.0);
    tool.world_from_tool = Isometry3::translation(0.0, 0.0, 0.012);
    let params = SolverParams { gravity: [0.0; 3], dt: 0.01, cg_tolerance: 1e-8, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    let mut report = sim.step().unwrap();
    for _ in 0..400 {
        report = sim.step().unwrap();
    }
    // Pushed down, at rest, the tool feels the tissue push it up (+z).
    assert!(report.reaction(0).force[2] > 0.05, "{report:?}");
    assert!(report.kinetic_energy < 1e-9, "settled: {report:?}");
    assert!(report.reaction(0).force[0].abs() < 1e-6 * report.reaction(0).force[2] + 1e-9, "symmetric: {report:?}");
    // No node remains inside the sphere by more than the penalty depth F/k_c of one node.
    let worst_depth =
        sim.positions_f64().iter().map(|p| 0.02 - (p - Vector3::new(0.0, 0.0, 0.012)).norm()).fold(f64::MIN, f64::max);
    assert!(worst_depth > 0.0 && worst_depth < 0.1 * 0.02, "depth {worst_depth}");
}

#[test]
fn commanded_force_displaces_the_surface_and_is_felt_back() {
    let model = block();
    let mut tool = Tool::new(ToolShape::Sphere { radius: 0.001 }, 0.0);
    tool.world_from_tool = Isometry3::translation(0.0, 0.0, 0.0);
    tool.spread_radius = 0.03;
    tool.applied_force = Vector3::new(0.0, 0.0, -1.0);
    let params = SolverParams { gravity: [0.0; 3], ..Default::default() };
    let mut sim = Simulation::<f32>::new(&model, params, vec![tool]).unwrap();
    let mut report = sim.step().unwrap();
    for _ in 0..300 {
        report = sim.step().unwrap();
    }
    let top_centre = sim
        .positions_f64()
        .iter()
        .zip(&model.rest)
        .filter(|(_, r)| r.x.abs() < 1e-9 && r.y.abs() < 1e-9 && r.z.abs() < 1e-9)
        .map(|(p, _)| p.z)
        .next()
        .unwrap();
    assert!(top_centre < -1e-4, "pushed down: {top_centre}");
    assert!((report.reaction(0).force[2] - 1.0).abs() < 1e-9, "{report:?}");
}
