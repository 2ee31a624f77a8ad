//! Tools against the mesh: contact pushes the surface out (between nodes too), the reaction
//! balances it, a commanded force moves the mesh by what its stiffness predicts, and a
//! coupled tool renders stiff contact passively.

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

/// What the springs pull on the fixed nodes with at `positions`: at rest (no damping force),
/// the load the supports carry, which balances every external force the mesh received. It
/// is computed from the positions alone, not from the contact list the reaction sums.
fn support_load(model: &MassSpringModel, positions: &[Vector3<f64>]) -> Vector3<f64> {
    let mut load = Vector3::zeros();
    for (e, [a, b]) in model.springs.iter().enumerate() {
        let (a, b) = (*a as usize, *b as usize);
        let edge = positions[b] - positions[a];
        let on_a = model.stiffness[e] * (edge.norm() - model.rest_length[e]) * edge.normalize();
        if model.fixed[a] {
            load += on_a;
        }
        if model.fixed[b] {
            load -= on_a;
        }
    }
    load
}

/// The rest stiffness matrix of the free nodes (k n nᵀ per spring), dense: the linear
/// prediction of a small load's displacement.
fn free_stiffness(model: &MassSpringModel) -> (nalgebra::DMatrix<f64>, Vec<Option<usize>>) {
    let mut index = vec![None; model.rest.len()];
    let mut free = 0;
    for (i, slot) in index.iter_mut().enumerate() {
        if !model.fixed[i] {
            *slot = Some(free);
            free += 1;
        }
    }
    let mut k = nalgebra::DMatrix::zeros(3 * free, 3 * free);
    for (e, [a, b]) in model.springs.iter().enumerate() {
        let n = (model.rest[*b as usize] - model.rest[*a as usize]).normalize();
        let block = model.stiffness[e] * n * n.transpose();
        let (ia, ib) = (index[*a as usize], index[*b as usize]);
        for (p, q, sign) in [(ia, ia, 1.0), (ib, ib, 1.0), (ia, ib, -1.0), (ib, ia, -1.0)] {
            if let (Some(p), Some(q)) = (p, q) {
                let mut view = k.fixed_view_mut::<3, 3>(3 * p, 3 * q);
                view += block * sign;
            }
        }
    }
    (k, index)
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
    // Pushed down, at rest, the tool feels the tissue push it up (+z), as hard as the
    // supports hold the block down.
    let felt = Vector3::from(report.reaction(0).force);
    assert!(felt.z > 0.05, "{report:?}");
    assert!(report.kinetic_energy < 1e-12, "settled: {report:?}");
    let support = support_load(&model, &sim.positions_f64());
    assert!((felt + support).norm() < 1e-4 * felt.norm(), "felt {felt} N, the supports carry {support} N");
    assert!(report.reaction(0).force[0].abs() < 1e-6 * report.reaction(0).force[2] + 1e-9, "symmetric: {report:?}");
    // No node remains inside the sphere by more than the penalty depth F/k_c of one node.
    let worst_depth =
        sim.positions_f64().iter().map(|p| 0.02 - (p - Vector3::new(0.0, 0.0, 0.012)).norm()).fold(f64::MIN, f64::max);
    assert!(worst_depth > 0.0 && worst_depth < 0.1 * 0.02, "depth {worst_depth}");
}

#[test]
fn commanded_force_displaces_the_surface_as_its_stiffness_predicts_and_the_supports_carry_it() {
    let model = block();
    let mut tool = Tool::new(ToolShape::Sphere { radius: 0.001 }, 0.0);
    tool.world_from_tool = Isometry3::translation(0.0, 0.0, 0.0);
    tool.spread_radius = 0.03;
    // Small enough for the linear prediction: a fraction of a millimetre.
    tool.applied_force = Vector3::new(0.0, 0.0, -0.05);
    let params = SolverParams { gravity: [0.0; 3], dt: 0.01, cg_tolerance: 1e-10, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool.clone()]).unwrap();
    let mut report = sim.step().unwrap();
    for _ in 0..2000 {
        report = sim.step().unwrap();
        if report.kinetic_energy < 1e-20 {
            break;
        }
    }
    assert!(report.kinetic_energy < 1e-20, "settled: {report:?}");
    // K u = f on the free nodes, f spread as the tool spreads it over the rest positions.
    let (k, index) = free_stiffness(&model);
    let mut f = nalgebra::DVector::zeros(k.nrows());
    for (node, w) in defvol::solver::tool::spread_weights(&model.rest, &Vector3::zeros(), tool.spread_radius) {
        if let Some(i) = index[node as usize] {
            f.fixed_rows_mut::<3>(3 * i).copy_from(&(tool.applied_force * w));
        }
    }
    let predicted = k.lu().solve(&f).unwrap();
    let moved: Vec<Vector3<f64>> = sim.positions_f64().iter().zip(&model.rest).map(|(p, r)| p - r).collect();
    let centre = model.rest.iter().position(|r| r.norm() < 1e-9).unwrap();
    let (got, want) = (moved[centre].z, predicted[3 * index[centre].unwrap() + 2]);
    assert!(want < -1e-5 && (got - want).abs() < 0.02 * want.abs(), "top centre moved {got} m, K predicts {want} m");
    // The supports carry the commanded force, and the tool feels it back.
    let support = support_load(&model, &sim.positions_f64());
    assert!((support - tool.applied_force).norm() < 1e-3 * 0.05, "the supports carry {support} N");
    let felt = Vector3::from(report.reaction(0).force);
    assert!((felt + support).norm() < 1e-3 * 0.05, "felt {felt} N against {support} N carried");
}

/// A slab whose boundary spacing is 15-17 mm, fixed at the bottom, top at z = 0.
fn coarse_slab() -> (defvol::mesh::TetMesh, MassSpringModel) {
    let mesh =
        generate::lattice(Vector3::new(0.0, 0.0, -0.06), Vector3::new(0.1, 0.1, 0.0), [6, 6, 4], CellSplit::Five)
            .unwrap();
    let fixed = FixedNodes::Plane { normal: [0.0, 0.0, 1.0], offset: -0.06 }.select(mesh.nodes()).unwrap();
    let model =
        MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 300.0, damping: 2.0 }, 1000.0, &fixed, None)
            .unwrap();
    (mesh, model)
}

/// The settled state of a tool held at `world_from_tool`, continuing `sim`; it must come to
/// rest (kinetic energy under 1e-14 J) within 600 steps.
fn settle(sim: &mut Simulation<f64>, world_from_tool: Isometry3<f64>) -> defvol::solver::StepReport {
    sim.tool_mut(0).unwrap().world_from_tool = world_from_tool;
    let mut report = sim.step().unwrap();
    for _ in 0..600 {
        report = sim.step().unwrap();
        if report.kinetic_energy < 1e-14 {
            return report;
        }
    }
    panic!("the tool held at {world_from_tool} never settled: {report:?}")
}

/// The top face nearest (x, y) of the coarse slab: its nodes and its centroid.
fn top_face_near(mesh: &defvol::mesh::TetMesh, x: f64, y: f64) -> ([u32; 3], Vector3<f64>) {
    let centroid = |f: &[u32; 3]| f.iter().map(|&i| mesh.nodes()[i as usize]).sum::<Vector3<f64>>() / 3.0;
    let target = Vector3::new(x, y, 0.0);
    let face = (mesh.boundary().iter())
        .filter(|f| f.iter().all(|&i| mesh.nodes()[i as usize].z.abs() < 1e-12))
        .min_by(|a, b| (centroid(a) - target).norm().total_cmp(&(centroid(b) - target).norm()))
        .copied()
        .unwrap();
    (face, centroid(&face))
}

/// A 2 mm probe, its contact stiffness, pressed straight down to `depth` below the rest
/// surface at (x, y) and held there: the settled reaction (+z).
fn settled_press(x: f64, y: f64, depth: f64, contact_stiffness: f64) -> f64 {
    let (_, model) = coarse_slab();
    let radius = 0.001;
    let tool = Tool::new(ToolShape::Sphere { radius }, contact_stiffness);
    let params = SolverParams { gravity: [0.0; 3], dt: 0.01, cg_tolerance: 1e-10, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    let report = settle(&mut sim, Isometry3::translation(x, y, radius - depth));
    let held = sim.contacts().iter().all(|c| c.push.z < 0.0 && c.depth < radius);
    assert!(held && !sim.contacts().is_empty(), "held on the surface at ({x}, {y}): {:?}", sim.contacts());
    report.reaction(0).force[2]
}

/// A probe far thinner than the spacing pressed on a node and between nodes (a face's
/// centroid) is held by the surface and felt as the mesh's stiffness at the contact point
/// predicts: the probe's depth over the compliance there (wᵀ K⁻¹ w for barycentric weights
/// w on the free nodes, vertical) plus the penalty's (1/k_c), in series. The mesh is
/// stiffer under a face's three nodes than under one node, by as much as K says.
#[test]
fn thin_probe_is_felt_on_and_between_nodes_as_the_mesh_stiffness_there_predicts() {
    let (mesh, model) = coarse_slab();
    let (k, index) = free_stiffness(&model);
    let compliance = k.try_inverse().unwrap();
    let vertical = |weights: &[(u32, f64)]| {
        let mut sum = 0.0;
        for &(a, wa) in weights {
            for &(b, wb) in weights {
                sum += wa * wb * compliance[(3 * index[a as usize].unwrap() + 2, 3 * index[b as usize].unwrap() + 2)];
            }
        }
        sum
    };
    let node = mesh.nodes().iter().position(|p| (p - Vector3::new(0.05, 0.05, 0.0)).norm() < 1e-9).unwrap() as u32;
    let (face, centroid) = top_face_near(&mesh, 0.05, 0.05);
    let (depth, contact_stiffness) = (0.0005, 20_000.0);
    let cases = [
        ("on a node", 0.05, 0.05, vec![(node, 1.0)]),
        ("between nodes", centroid.x, centroid.y, face.iter().map(|&i| (i, 1.0 / 3.0)).collect()),
    ];
    for (place, x, y, weights) in cases {
        let felt = settled_press(x, y, depth, contact_stiffness);
        let predicted = depth / (1.0 / contact_stiffness + vertical(&weights));
        assert!((felt - predicted).abs() < 0.03 * predicted, "{place}: felt {felt} N, K predicts {predicted} N");
    }
}

/// The tool feels exactly what the mesh received: at rest, the reaction of a thin probe
/// pressed between nodes balances the load the springs put on the supports.
#[test]
fn thin_probe_settles_with_reaction_equal_to_the_support_load() {
    let (_, model) = coarse_slab();
    let tool = Tool::new(ToolShape::Sphere { radius: 0.001 }, 20_000.0);
    let params = SolverParams { gravity: [0.0; 3], dt: 0.01, cg_tolerance: 1e-10, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    let report = settle(&mut sim, Isometry3::translation(0.043, 0.058, -0.004));
    let felt = Vector3::from(report.reaction(0).force);
    let support = support_load(&model, &sim.positions_f64());
    assert!(felt.z > 0.5, "{felt}");
    assert!((felt + support).norm() < 1e-3 * felt.norm(), "felt {felt} N, the supports carry {support} N");
}

/// A needle lying on the surface, pressed in and dragged across faces and edges: the
/// surface follows without jumps (no node moves more between two steps than a bound set by
/// the drag speed) and the needle stays in contact throughout.
#[test]
fn needle_dragged_across_the_surface_deforms_it_continuously() {
    let (_, model) = coarse_slab();
    let radius = 0.0008;
    // Shaft along world +x: the tool's +z turned onto +x.
    let lying = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2);
    let tool = Tool::new(ToolShape::Capsule { radius, length: 0.04 }, 2000.0);
    let dt = 0.005;
    let params = SolverParams { gravity: [0.0; 3], dt, cg_tolerance: 1e-9, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    let depth = 0.003;
    let at = |y: f64| Isometry3::from_parts(nalgebra::Translation3::new(0.03, y, radius - depth), lying);
    settle(&mut sim, at(0.02));
    let speed = 0.02; // m/s: 0.1 mm a step
    let mut previous = sim.positions_f64();
    let mut reactions = Vec::new();
    let mut worst = 0.0f64;
    for k in 1..=500 {
        sim.tool_mut(0).unwrap().world_from_tool = at(0.02 + speed * dt * k as f64);
        let report = sim.step().unwrap();
        let now = sim.positions_f64();
        worst = worst.max(now.iter().zip(&previous).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max));
        previous = now;
        reactions.push(report.reaction(0).force[2]);
    }
    // 50 mm of drag crosses three rows of cells (and their diagonals).
    let step = speed * dt;
    assert!(worst < 3.0 * step, "a node jumped {worst} m in one step (the needle moves {step} m)");
    let low = reactions.iter().copied().fold(f64::INFINITY, f64::min);
    let high = reactions.iter().copied().fold(0.0, f64::max);
    assert!(low > 0.0, "the needle lost the surface");
    let largest_change = reactions.windows(2).map(|w| (w[1] - w[0]).abs()).fold(0.0, f64::max);
    assert!(largest_change < 0.15 * high, "the reaction jumped by {largest_change} N (range {low}..{high} N)");
}

/// A needle pressed across the slab's top edge, the edge halfway between two of its
/// samples (farther from each than its radius), is held there as the capsule itself would
/// be: it settles, the mesh receives what the needle feels (the supports' load), and that is
/// k_c times how deep the capsule's core reaches into the deformed surface.
#[test]
fn a_needle_across_the_slabs_edge_between_its_samples_is_held_as_a_capsule() {
    use defvol::solver::contact::{segment_triangle_nearest, Surface};
    let (mesh, model) = coarse_slab();
    let (radius, length, stiffness) = (0.0008, 0.04, 20_000.0);
    let spacing = Surface::new(mesh.boundary(), mesh.nodes()).spacing();
    let gap = length / (2.0 * length / spacing).ceil();
    assert!(0.5 * gap > 2.0 * radius, "the edge lies beyond every sample's reach");
    // Tilted 30° down past the edge (x = 0.1, z = 0); the core passes 0.5 mm inside it.
    let tilt = std::f64::consts::FRAC_PI_6;
    let (along, out) = (Vector3::new(tilt.cos(), 0.0, -tilt.sin()), Vector3::new(tilt.sin(), 0.0, tilt.cos()));
    let turn = nalgebra::UnitQuaternion::rotation_between(&Vector3::z(), &along).unwrap();
    let tip = Vector3::new(0.1, 0.05, 0.0) + out * (radius - 0.0005) - along * (2.5 * gap);
    let params = SolverParams { gravity: [0.0; 3], dt: 0.01, cg_tolerance: 1e-10, ..Default::default() };
    let tool = Tool::new(ToolShape::Capsule { radius, length }, stiffness);
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    let report = settle(&mut sim, Isometry3::from_parts(tip.into(), turn));
    let felt = Vector3::from(report.reaction(0).force);
    let x = sim.positions_f64();
    let support = support_load(&model, &x);
    assert!(felt.dot(&out) > 0.05, "the needle is pushed back out over the edge: {felt} N");
    assert!((felt + support).norm() < 1e-3 * felt.norm(), "felt {felt} N, the supports carry {support} N");
    let reach = (mesh.boundary().iter())
        .map(|f| {
            let [a, b, c] = f.map(|i| x[i as usize]);
            segment_triangle_nearest(&tip, &(tip + along * length), &a, &b, &c).1
        })
        .fold(f64::INFINITY, f64::min);
    let depth = radius - reach;
    assert!((felt.norm() - stiffness * depth).abs() < 0.02 * felt.norm(), "felt {felt} N at depth {depth} m");
}

/// The simulated tool follows its device through the virtual coupling, and over a stiff
/// press and release the system never holds more energy than the device put in.
#[test]
fn coupled_stiff_press_and_release_is_passive() {
    let (_, model) = coarse_slab();
    let radius = 0.002;
    let mut tool = Tool::new(ToolShape::Sphere { radius }, 50_000.0);
    tool.coupling = Some(defvol::solver::Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 50.0 });
    let dt = 0.001;
    let params = SolverParams { gravity: [0.0; 3], dt, cg_tolerance: 1e-10, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    let device = |t: f64| {
        // 2 mm above, down to 8 mm into the surface over 0.3 s, held, back up, held.
        let z = if t < 0.3 {
            0.002 + radius - 0.01 * t / 0.3
        } else if t < 0.5 {
            radius - 0.008
        } else if t < 0.8 {
            radius - 0.008 + 0.01 * (t - 0.5) / 0.3
        } else {
            0.002 + radius
        };
        Vector3::new(0.043, 0.058, z)
    };
    sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, device(0.0).z);
    let first = sim.step().unwrap();
    let start = first.kinetic_energy + first.potential_energy;
    let mut work = 0.0;
    let mut pull = -Vector3::from(first.reaction(0).force);
    let mut deepest = 0.0f64;
    for k in 1..1200 {
        let (before, after) = (device((k - 1) as f64 * dt), device(k as f64 * dt));
        sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(after.x, after.y, after.z);
        let report = sim.step().unwrap();
        let pull_now = -Vector3::from(report.reaction(0).force);
        work += 0.5 * (pull + pull_now).dot(&(after - before));
        pull = pull_now;
        let energy = report.kinetic_energy + report.potential_energy;
        assert!(energy - start <= work + 1e-9, "step {k}: energy {energy} J, start {start} J + work in {work} J");
        deepest = deepest.max(pull.z.abs());
    }
    assert!(deepest > 1.0, "the press was felt: {deepest} N");
    // Released: the tool follows the device back out and nothing touches.
    let tip = sim.simulated_pose(0).unwrap().translation.vector;
    assert!((tip - device(1.2)).norm() < 1e-4, "the simulated tool is back at the device: {tip}");
}

/// The height of the deformed top surface (the faces whose rest nodes lie at z = 0) above
/// (x, y): the face whose deformed projection holds the point, interpolated.
fn top_surface_height(mesh: &defvol::mesh::TetMesh, positions: &[Vector3<f64>], x: f64, y: f64) -> f64 {
    let top = mesh.boundary().iter().filter(|f| f.iter().all(|&i| mesh.nodes()[i as usize].z.abs() < 1e-12));
    for face in top {
        let [a, b, c] = face.map(|i| positions[i as usize]);
        let det = (b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y);
        let u = ((x - a.x) * (c.y - a.y) - (c.x - a.x) * (y - a.y)) / det;
        let v = ((b.x - a.x) * (y - a.y) - (x - a.x) * (b.y - a.y)) / det;
        if u >= -1e-12 && v >= -1e-12 && u + v <= 1.0 + 1e-12 {
            return a.z + u * (b.z - a.z) + v * (c.z - a.z);
        }
    }
    panic!("no top face above ({x}, {y})")
}

/// The distance from `p` to the deformed top surface.
fn distance_to_top(mesh: &defvol::mesh::TetMesh, positions: &[Vector3<f64>], p: &Vector3<f64>) -> f64 {
    let top = mesh.boundary().iter().filter(|f| f.iter().all(|&i| mesh.nodes()[i as usize].z.abs() < 1e-12));
    top.map(|face| {
        let [a, b, c] = face.map(|i| positions[i as usize]);
        (p - defvol::solver::contact::closest_on_triangle(p, &a, &b, &c).0).norm()
    })
    .fold(f64::INFINITY, f64::min)
}

/// A device pose that jumps through the organ (a dropped packet, a teleport) to far below
/// it: the coupling pulls with its largest force at most and says so, and the tool is held
/// on the dented surface, never deeper into it than that force pushes a penalty contact.
#[test]
fn a_pose_jumping_through_the_organ_is_held_at_the_surface() {
    let (mesh, model) = coarse_slab();
    let radius = 0.001;
    let contact_stiffness = 20_000.0;
    let mut tool = Tool::new(ToolShape::Sphere { radius }, contact_stiffness);
    let max_force = 5.0;
    tool.coupling = Some(defvol::solver::Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force });
    let params = SolverParams { gravity: [0.0; 3], dt: 0.002, cg_tolerance: 1e-9, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, 0.002);
    sim.step().unwrap();
    // Under the slab's bottom in one message: far more than a spacing (15-17 mm) deep.
    sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, -0.2);
    let (mut saturated, mut deepest, mut last) = (0, f64::NEG_INFINITY, 0.0);
    for _ in 0..500 {
        let report = sim.step().unwrap();
        saturated += usize::from(report.reaction(0).coupling_saturated);
        let tip = sim.simulated_pose(0).unwrap().translation.vector;
        let surface = top_surface_height(&mesh, &sim.positions_f64(), tip.x, tip.y);
        deepest = deepest.max(surface - (tip.z - radius));
        last = radius - distance_to_top(&mesh, &sim.positions_f64(), &tip);
    }
    // Arriving, the tool (accelerated by max_force over the 2 mm it had to fall) dips in as
    // far as the penalty stores its kinetic energy: about a millimetre, never through.
    let fall = 0.002 + radius;
    let arrival = (2.0 * max_force * fall / contact_stiffness).sqrt() + max_force / contact_stiffness;
    assert!(deepest < 1.2 * arrival, "the tip went {deepest} m under the dented surface (arrival bound {arrival} m)");
    // Held, the contact carries max_force, and the sphere overlaps the dented surface by no
    // more than max_force / k_c (less where it rests on several faces at once).
    let carried: Vector3<f64> = sim.contacts().iter().map(|c| c.force()).sum();
    assert!((carried.norm() - max_force).abs() < 0.02 * max_force, "the contact carries {carried} N");
    let held = max_force / contact_stiffness;
    assert!(
        last > 0.0 && last < 1.02 * held,
        "the sphere overlaps the surface by {last} m, the penalty holds {held} m"
    );
    let dent = -top_surface_height(&mesh, &sim.positions_f64(), 0.043, 0.058);
    assert!(dent > 1e-3, "the surface is pressed in under the pull: {dent} m");
    assert!(saturated > 400, "the saturated coupling is reported ({saturated} of 500 steps)");
}

/// A coupled thin tool pulled at the organ from 5 cm above with the coupling's largest
/// force, at a 10 ms step, comes faster than the usual contact margin reaches (up to 25 mm a
/// step); the margin covers its travel, so it meets the surface within the step and stays
/// within a spacing (15-17 mm) of the dented surface, where its samples find the faces and
/// hold it, never reported through and held back by the surface to the end. (Before the
/// margin covered the travel it arrived 29 mm deep; the 2-6 mm it still bobs is the soft
/// contact with its centre past the surface, not yet at rest.)
#[test]
fn a_tool_pulled_fast_at_the_surface_is_stopped_not_passed_between_steps() {
    let (mesh, model) = coarse_slab();
    let (radius, contact_stiffness, max_force) = (0.001, 20_000.0, 5.0);
    let mut tool = Tool::new(ToolShape::Sphere { radius }, contact_stiffness);
    tool.coupling = Some(defvol::solver::Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force });
    let params = SolverParams { gravity: [0.0; 3], dt: 0.01, cg_tolerance: 1e-9, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, 0.05);
    sim.step().unwrap();
    sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, -0.2);
    let (mut deepest, mut held) = (f64::NEG_INFINITY, 0);
    for _ in 0..200 {
        let reaction = sim.step().unwrap().reaction(0);
        assert!(!reaction.passed_through, "{reaction:?}");
        held += usize::from(reaction.coupling_saturated && reaction.force[2] > 0.0);
        let tip = sim.simulated_pose(0).unwrap().translation.vector;
        let surface = top_surface_height(&mesh, &sim.positions_f64(), tip.x, tip.y);
        deepest = deepest.max(surface - (tip.z - radius));
    }
    assert!(deepest < 0.015, "the tip went {deepest} m under the dented surface, past a spacing");
    assert!(held > 190, "held back by the surface ({held} of 200 steps)");
}

/// Coulomb's law at a coupled probe pressed into the slab and pulled sideways: pulled
/// below the static limit it sticks (slides slower than `stick_speed`, the regularised
/// friction's creep; frictionless it would slide off), its friction balancing the pull and
/// the push within the static limit; dragged at 20 mm/s it
/// slides, braked by the kinetic coefficient times the contact's normal force.
#[test]
fn friction_holds_below_the_static_limit_and_brakes_sliding_at_the_kinetic_one() {
    let (_, model) = coarse_slab();
    let radius = 0.002;
    let (mu_static, mu_kinetic, stick_speed) = (0.5, 0.3, 1e-4);
    let mut tool = Tool::new(ToolShape::Sphere { radius }, 20_000.0);
    tool.coupling = Some(defvol::solver::Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 50.0 });
    tool.friction =
        Some(defvol::solver::Friction { static_coefficient: mu_static, kinetic_coefficient: mu_kinetic, stick_speed });
    let params = SolverParams { gravity: [0.0; 3], dt: 1e-3, cg_tolerance: 1e-9, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    let mut run = |x: f64, steps: usize| {
        sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(x, 0.058, radius - 0.003);
        let reports: Vec<_> = (0..steps).map(|_| sim.step().unwrap()).collect();
        let at = sim.simulated_pose(0).unwrap().translation.vector;
        let contact: Vector3<f64> = sim.contacts().iter().map(|c| c.force()).sum();
        (reports, at, contact)
    };
    let (pressed, _, _) = run(0.043, 400);
    let normal = pressed[399].reaction(0).force[2];
    assert!(normal > 1.0, "pressed in: {normal} N");
    // A third of the static limit sideways: it sticks, and static friction carries the pull.
    let offset = mu_static * normal / 3.0 / 2000.0;
    let (_, before, _) = run(0.043 + offset, 300);
    let (held, after, contact) = run(0.043 + offset, 100);
    let reaction = held[99].reaction(0);
    let (pull, friction) = (-Vector3::from(reaction.force), Vector3::from(reaction.friction));
    // At rest the tool's forces balance: the pull, the contact's push and the friction.
    let balance = pull - contact + friction;
    assert!(balance.norm() < 0.01 * pull.norm(), "pull {pull} N, push {} N, friction {friction} N", -contact);
    assert!(friction.norm() < mu_static * contact.norm(), "within the static limit: {friction} N, normal {contact} N");
    let creep = (after.x - before.x).abs() / 0.1;
    assert!(creep < stick_speed, "sticking, it creeps at {creep} m/s");
    // Dragged: it slides, braked by μ_k N, now and then sticking a moment (stick-slip, as
    // μ_s > μ_k makes it where the surface under it stiffens), never held past μ_s N.
    let mut ratios = Vec::new();
    for k in 1..=600 {
        let (slid, _, contact) = run(0.043 + offset + 0.02 * k as f64 * 1e-3, 1);
        let friction = Vector3::from(slid[0].reaction(0).friction);
        if k > 200 {
            ratios.push(friction.norm() / contact.norm());
            assert!(friction.x < 0.0, "step {k}: friction {friction} N brakes the +x slide");
        }
    }
    assert!(ratios.iter().all(|r| *r < 1.01 * mu_static), "held past μ_s N: {ratios:?}");
    ratios.sort_by(f64::total_cmp);
    let median = ratios[ratios.len() / 2];
    assert!((median - mu_kinetic).abs() < 0.01 * mu_kinetic, "braked by {median} N per N of contact, μ_k {mu_kinetic}");
}

/// A coupled needle with a rotational coupling, held by its device tilted down so its far
/// end presses into the slab: the contacts along it turn the simulated needle about its tip
/// until the coupling's torque balances theirs, and the device feels that torque. At rest:
/// the torque felt is Σ (at - tip) × (each contact's force on the needle), within 1 %
/// (measured: 0.030 N·m, to 1e-8), the force felt is the contacts' sum, and the needle has
/// turned up away from the device.
#[test]
fn a_needle_pressed_at_its_far_end_turns_and_its_torque_is_felt() {
    let (_, model) = coarse_slab();
    let (radius, length) = (0.001, 0.04);
    let mut tool = Tool::new(ToolShape::Capsule { radius, length }, 20_000.0);
    tool.coupling = Some(defvol::solver::Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 50.0 });
    tool.rotational_coupling =
        Some(defvol::solver::RotationalCoupling { stiffness: 2.0, damping: 0.02, inertia: 1e-5, max_torque: 5.0 });
    let params = SolverParams { gravity: [0.0; 3], dt: 1e-3, cg_tolerance: 1e-10, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    // The shaft (the tool's +z) along +x tilted 0.1 rad down: the far end 4 mm lower.
    let tilt = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2 + 0.1);
    let device = Isometry3::from_parts(nalgebra::Translation3::new(0.03, 0.058, 0.002 + radius), tilt);
    sim.tool_mut(0).unwrap().world_from_tool =
        Isometry3::from_parts(nalgebra::Translation3::new(0.03, 0.058, 0.05), tilt);
    sim.step().unwrap();
    let report = settle(&mut sim, device);
    let pose = sim.simulated_pose(0).unwrap();
    let tip = pose.translation.vector;
    let (mut force, mut torque) = (Vector3::zeros(), Vector3::zeros());
    for c in sim.contacts() {
        force -= c.force();
        torque -= (c.at - tip).cross(&c.force());
    }
    let reaction = report.reaction(0);
    let (felt_force, felt_torque) = (Vector3::from(reaction.force), Vector3::from(reaction.torque));
    assert!(torque.norm() > 1e-3, "the contacts turn the needle: {torque} N·m");
    assert!((felt_torque - torque).norm() < 0.01 * torque.norm(), "felt {felt_torque} N·m, contacts {torque} N·m");
    assert!((felt_force - force).norm() < 0.01 * force.norm(), "felt {felt_force} N, contacts {force} N");
    let (shaft, commanded) = (pose.rotation * Vector3::z(), device.rotation * Vector3::z());
    assert!(shaft.z > commanded.z + 0.01, "the far end turned up: shaft {shaft}, device {commanded}");
}

/// A rotational coupling without the translational one it turns is refused by name.
#[test]
fn a_rotational_coupling_without_a_coupling_is_refused_by_name() {
    let (_, model) = coarse_slab();
    let mut tool = Tool::new(ToolShape::Capsule { radius: 0.001, length: 0.04 }, 20_000.0);
    tool.rotational_coupling =
        Some(defvol::solver::RotationalCoupling { stiffness: 2.0, damping: 0.02, inertia: 1e-5, max_torque: 5.0 });
    let mut sim = Simulation::<f64>::new(&model, SolverParams::default(), vec![tool]).unwrap();
    let e = sim.step().unwrap_err().to_string();
    assert!(e.contains("tools[0].rotational_coupling") && e.contains("coupling too"), "{e}");
}

/// An uncoupled thin tool put deeper than a spacing into the body meets no face: nothing
/// holds it, and the step says it went through, rather than passing silently. Above the
/// surface, or held by it, it did not.
#[test]
fn a_thin_tool_put_through_the_surface_is_reported_not_passed_silently() {
    let (_, model) = coarse_slab();
    let radius = 0.001;
    let tool = Tool::new(ToolShape::Sphere { radius }, 20_000.0);
    let params = SolverParams { gravity: [0.0; 3], dt: 0.002, cg_tolerance: 1e-9, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    let mut at = |z: f64| {
        sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, z);
        sim.step().unwrap().reaction(0)
    };
    let above = at(0.01);
    assert!(!above.passed_through && above.force == [0.0; 3], "{above:?}");
    let pressing = at(radius - 0.002);
    assert!(!pressing.passed_through && pressing.force[2] > 0.0, "held by the surface: {pressing:?}");
    // 40 mm deep, more than two spacings: no face within reach.
    let inside = at(-0.04);
    assert!(inside.passed_through && inside.force == [0.0; 3], "{inside:?}");
    // Beside the slab, level with its inside: outside the body.
    sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.2, 0.058, -0.04);
    assert!(!sim.step().unwrap().reaction(0).passed_through);
}

/// The isotropic Young's modulus and Poisson's ratio of a lattice of cubes of side `h`
/// split five ways, every edge and face diagonal a spring of stiffness `k`, from the energy
/// of a uniform strain: C11 = 2k/h, C12 = C44 = k/(2h) (cubic, central forces), made
/// isotropic by the Hill average of the Voigt and Reuss shear moduli.
fn lattice_modulus(k: f64, h: f64) -> (f64, f64) {
    let (c11, c12, c44) = (2.0 * k / h, 0.5 * k / h, 0.5 * k / h);
    let bulk = (c11 + 2.0 * c12) / 3.0;
    let voigt = (c11 - c12 + 3.0 * c44) / 5.0;
    let reuss = 5.0 / (4.0 / (c11 - c12) + 3.0 / c44);
    let shear = 0.5 * (voigt + reuss);
    let young = 9.0 * bulk * shear / (3.0 * bulk + shear);
    let poisson = (3.0 * bulk - 2.0 * shear) / (2.0 * (3.0 * bulk + shear));
    (young, poisson)
}

/// The force pressing a rigid frictionless sphere of radius `r` to depth `d` into an
/// elastic layer of thickness `t` bonded to a rigid base: Hertz's half-space law
/// F = 4/3 E/(1-ν²) √r d^1.5 times the thickness correction of Dimitriadis et al.
/// (Biophys. J. 82, 2002, bonded case), a series in χ = √(r d)/t.
fn hertz_on_a_bonded_layer(young: f64, poisson: f64, r: f64, d: f64, t: f64) -> f64 {
    use std::f64::consts::PI;
    let nu = poisson;
    let alpha = -(1.2876 - 1.4678 * nu + 1.3442 * nu * nu) / (1.0 - nu);
    let beta = (0.6387 - 1.0277 * nu + 1.5164 * nu * nu) / (1.0 - nu);
    let chi = (r * d).sqrt() / t;
    let correction = 1.0 - 2.0 * alpha / PI * chi + 4.0 * alpha * alpha / (PI * PI) * chi.powi(2)
        - 8.0 / PI.powi(3) * (alpha.powi(3) + 4.0 * PI * PI * beta / 15.0) * chi.powi(3)
        + 16.0 * alpha / PI.powi(4) * (alpha.powi(3) + 3.0 * PI * PI * beta / 5.0) * chi.powi(4);
    4.0 / 3.0 * young / (1.0 - nu * nu) * r.sqrt() * d.powf(1.5) * correction
}

/// A rigid sphere pressed into a block bonded to a rigid base follows Hertz's elastic law
/// with the lattice's own modulus and the layer's thickness correction, within 5 % at two
/// depths (it comes within 2-3 %; the contact spans about two cells).
#[test]
fn sphere_pressed_into_a_block_follows_hertz_with_the_mesh_modulus() {
    let (cells, side, thickness) = (16, 0.1, 0.05);
    let h = side / cells as f64;
    let mesh = generate::lattice(
        Vector3::new(-side / 2.0, -side / 2.0, -thickness),
        Vector3::new(side / 2.0, side / 2.0, 0.0),
        [cells, cells, 8],
        CellSplit::Five,
    )
    .unwrap();
    let fixed = FixedNodes::Plane { normal: [0.0, 0.0, 1.0], offset: -thickness }.select(mesh.nodes()).unwrap();
    let spring = 100.0;
    let model =
        MassSpringModel::new(&mesh, &Material::Uniform { stiffness: spring, damping: 5.0 }, 1000.0, &fixed, None)
            .unwrap();
    let radius = 0.04;
    let tool = Tool::new(ToolShape::Sphere { radius }, 1e5);
    let params = SolverParams { gravity: [0.0; 3], dt: 0.02, cg_tolerance: 1e-9, ..Default::default() };
    let mut sim = Simulation::<f64>::new(&model, params, vec![tool]).unwrap();
    let (young, poisson) = lattice_modulus(spring, h);
    for d in [0.0015, 0.003] {
        let felt = settle(&mut sim, Isometry3::translation(0.0, 0.0, radius - d)).reaction(0).force[2];
        let law = hertz_on_a_bonded_layer(young, poisson, radius, d, thickness);
        assert!((felt - law).abs() < 0.05 * law, "at {d} m: {felt} N, Hertz on the layer says {law} N");
    }
}

/// A coupled thin tool whose surface contact is too soft for its coupling is said so, and
/// truly: pulled through the organ with the coupling's largest force, its centre ends inside
/// the body; stiff enough, it is not said, and the centre stays out.
#[test]
fn a_contact_too_soft_for_its_coupling_is_said_so_and_the_centre_goes_in() {
    let (mesh, model) = coarse_slab();
    let radius = 0.001;
    let coupling = defvol::solver::Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 5.0 };
    for (contact_stiffness, soft) in [(2_000.0, true), (20_000.0, false)] {
        let config = defvol::scene::ToolConfig {
            name: "probe".into(),
            shape: ToolShape::Sphere { radius },
            contact_stiffness,
            spread_radius: 0.01,
            contact: defvol::solver::ContactModel::Surface,
            coupling: Some(coupling),
            friction: None,
            rotational_coupling: None,
            path: None,
            pose_topic: None,
            wrench_topic: None,
            feedback_topic: None,
        };
        let said = config.too_soft_for_its_coupling();
        assert_eq!(said.is_some(), soft, "k_c {contact_stiffness}: {said:?}");
        let params = SolverParams { gravity: [0.0; 3], dt: 0.002, cg_tolerance: 1e-9, ..Default::default() };
        let mut sim = Simulation::<f64>::new(&model, params, vec![config.tool()]).unwrap();
        sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, 0.002);
        sim.step().unwrap();
        sim.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, -0.2);
        for _ in 0..300 {
            sim.step().unwrap();
        }
        let tip = sim.simulated_pose(0).unwrap().translation.vector;
        let inside = tip.z < top_surface_height(&mesh, &sim.positions_f64(), tip.x, tip.y);
        assert_eq!(inside, soft, "k_c {contact_stiffness}: the centre at {tip}");
    }
}

/// Two 2 cm blocks of a 2x2x2 lattice, the second at `offset` from the first, the nodes they
/// share merged: touching along an edge or at a node, as meshes cut from a segmentation do.
/// The first is held at its bottom, the second at the face away from the first.
fn touching_blocks(offset: Vector3<f64>) -> MassSpringModel {
    let size = Vector3::repeat(0.02);
    let a = generate::lattice(Vector3::zeros(), size, [2, 2, 2], CellSplit::Five).unwrap();
    let b = generate::lattice(offset, offset + size, [2, 2, 2], CellSplit::Five).unwrap();
    let mut nodes = a.nodes().to_vec();
    let mut tets = a.tets().to_vec();
    let index: Vec<u32> = (b.nodes().iter())
        .map(|p| match nodes.iter().position(|q| (p - q).norm() < 1e-12) {
            Some(shared) => shared as u32,
            None => {
                nodes.push(*p);
                nodes.len() as u32 - 1
            }
        })
        .collect();
    tets.extend(b.tets().iter().map(|t| t.map(|n| index[n as usize])));
    let mesh = defvol::mesh::TetMesh::new(nodes, tets, None, "touching blocks").unwrap();
    let far = if offset.z > 0.0 { offset.z + size.z } else { 0.0 };
    let fixed: Vec<bool> = (mesh.nodes().iter()).map(|p| p.z.abs() < 1e-12 || (p.z - far).abs() < 1e-12).collect();
    // Stiff enough that the probe's largest pull dents it by a tenth of a millimetre.
    MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 30_000.0, damping: 1.0 }, 1000.0, &fixed, None).unwrap()
}

/// How deep `p` lies inside the box from `lo` of side 2 cm (negative: outside).
fn depth_in_block(p: &Vector3<f64>, lo: Vector3<f64>) -> f64 {
    (0..3).map(|a| (p[a] - lo[a]).min(lo[a] + 0.02 - p[a])).fold(f64::INFINITY, f64::min)
}

/// A coupled 1 mm probe dragged across where two blocks touch (through the shared edge, or
/// over the shared node), on both backends: finite forces, the probe held outside both
/// blocks at every step, and the GPU's probe where the CPU's is.
#[test]
fn a_probe_dragged_across_where_two_bodies_touch_is_held_outside_both() {
    let radius = 0.001;
    for (what, offset, z) in [("edge", Vector3::new(0.02, 0.02, 0.0), 0.01), ("node", Vector3::repeat(0.02), 0.02)] {
        let model = touching_blocks(offset);
        let mut tool = Tool::new(ToolShape::Sphere { radius }, 20_000.0);
        tool.coupling = Some(defvol::solver::Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 3.0 });
        tool.world_from_tool = Isometry3::translation(0.026, 0.014, z);
        let params = SolverParams { gravity: [0.0; 3], dt: 0.002, cg_tolerance: 1e-9, ..Default::default() };
        // The device's path: from the open quadrant through the touching edge or node to
        // the other open quadrant, then held there.
        let device = |step: usize| {
            let s = (step as f64 / 150.0).min(1.0);
            Isometry3::translation(0.026 - 0.012 * s, 0.014 + 0.012 * s, z)
        };
        let check = |backend: &str, step: usize, tip: Vector3<f64>, force: [f64; 3]| {
            assert!(force.iter().all(|f| f.is_finite()), "{what} {backend} step {step}: force {force:?}");
            let deepest = depth_in_block(&tip, Vector3::zeros()).max(depth_in_block(&tip, offset));
            assert!(
                deepest < 0.5 * radius,
                "{what} {backend} step {step}: the probe's centre {deepest} m inside a block"
            );
        };
        let mut cpu = Simulation::<f32>::new(&model, params.clone(), vec![tool.clone()]).unwrap();
        let mut tips = Vec::new();
        for step in 0..300 {
            cpu.tool_mut(0).unwrap().world_from_tool = device(step);
            let report = cpu.step().unwrap();
            let tip = cpu.simulated_pose(0).unwrap().translation.vector;
            check("cpu", step, tip, report.reaction(0).force);
            tips.push(tip);
        }
        // Through an edge the two open quadrants meet in a line: the probe cannot pass.
        let pulled = device(300).translation.vector - tips[299];
        assert!(what == "node" || pulled.norm() > 5e-3, "{what}: the probe is {pulled} from the device, not held");
        #[cfg(feature = "gpu")]
        if let Some(ctx) = defvol::gpu::test_context() {
            let mut gpu = defvol::solver::gpu::GpuSimulation::new(ctx, &model, params, vec![tool]).unwrap();
            for (step, cpu_tip) in tips.iter().enumerate() {
                gpu.tool_mut(0).unwrap().world_from_tool = device(step);
                let report = gpu.step().unwrap();
                let tip = gpu.mirror().simulated_pose(0).unwrap().translation.vector;
                check("gpu", step, tip, report.reaction(0).force);
                assert!((tip - cpu_tip).norm() < 2e-4, "{what} step {step}: gpu probe at {tip}, cpu at {cpu_tip}");
            }
        }
    }
}
