//! The force loop's local model against the full solve: identical in free space, within a
//! stated bound while pressing, refreshed slower than it answers; never above the
//! coupling's saturation.

use defvol::mesh::generate::{self, CellSplit};
use defvol::solver::{
    Coupling, FixedNodes, Friction, MassSpringModel, Material, RotationalCoupling, Simulation, SolverParams, Tool,
    ToolShape,
};
use nalgebra::{Isometry3, UnitQuaternion, Vector3};

/// A slab whose boundary spacing is 15-17 mm, fixed at the bottom, top at z = 0.
fn coarse_slab() -> MassSpringModel {
    let mesh =
        generate::lattice(Vector3::new(0.0, 0.0, -0.06), Vector3::new(0.1, 0.1, 0.0), [6, 6, 4], CellSplit::Five)
            .unwrap();
    let fixed = FixedNodes::Plane { normal: [0.0, 0.0, 1.0], offset: -0.06 }.select(mesh.nodes()).unwrap();
    MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 300.0, damping: 2.0 }, 1000.0, &fixed, None).unwrap()
}

const COUPLING: Coupling = Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 5.0 };

/// A coupled 2 mm probe over the slab, stepping every `dt`, with `friction`.
fn coupled_probe(dt: f64, friction: Option<Friction>) -> Simulation<f64> {
    let mut tool = Tool::new(ToolShape::Sphere { radius: 0.001 }, 20_000.0);
    (tool.coupling, tool.friction) = (Some(COUPLING), friction);
    let params = SolverParams { gravity: [0.0; 3], dt, cg_tolerance: 1e-10, ..Default::default() };
    Simulation::<f64>::new(&coarse_slab(), params, vec![tool]).unwrap()
}

/// The device's path: down from 2 mm above the surface to `bottom` over 0.3 s, then held,
/// and from then on sideways at `drag` (m/s).
fn device_at(t: f64, bottom: f64, drag: f64) -> Vector3<f64> {
    let x = 0.043 + drag * (t - 0.3).max(0.0);
    Vector3::new(x, 0.058, 0.003 + (bottom - 0.003) * (t / 0.3).min(1.0))
}

/// `local_against_full_on` for the frictionless probe pressing down to `bottom`, 500 poses.
fn local_against_full(every: usize, bottom: f64) -> (f64, f64) {
    local_against_full_on(coupled_probe(1e-3, None), every, bottom, 0.0, 500)
}

/// Answers each 1 ms pose from a local model refreshed by a full solve every `every` poses,
/// beside the full solve of every pose, over `poses`: the largest difference between the
/// two forces (N), and the largest force of the full solve (N).
fn local_against_full_on(mut full: Simulation<f64>, every: usize, bottom: f64, drag: f64, poses: usize) -> (f64, f64) {
    let dt = 1e-3;
    full.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, 0.003);
    full.step().unwrap();
    let mut model = full.local_models().remove(0);
    let (mut worst, mut largest) = (0.0f64, 0.0f64);
    for k in 1..=poses {
        let device = device_at(k as f64 * dt, bottom, drag);
        let answer = model.answer(&Isometry3::translation(device.x, device.y, device.z), dt);
        full.tool_mut(0).unwrap().world_from_tool = Isometry3::from_parts(device.into(), Default::default());
        let felt = Vector3::from(full.step().unwrap().reaction(0).force);
        worst = worst.max((answer.force - felt).norm());
        largest = largest.max(felt.norm());
        if k % every == 0 {
            model = full.local_models().remove(0);
        }
    }
    (worst, largest)
}

/// Above the surface the simulated tool's row does not touch the mesh's: the local model is
/// the full solve's own step for it, and the two agree to rounding, never refreshed.
#[test]
fn local_model_in_free_space_is_the_full_solve() {
    let (worst, largest) = local_against_full(usize::MAX, 0.0015);
    assert!(largest > 0.01, "the device pulled the tool: {largest} N");
    assert!(worst < 1e-9 * largest, "the local model departs by {worst} N (forces up to {largest} N)");
}

/// Pressing 3 mm into the slab, a local model refreshed by every solve answers within 1 %
/// of the largest force, and one refreshed every 5 ms (answering four poses between) within
/// 6 %: the bound of the departure. The largest departures come as the tool first touches,
/// where the mesh under it starts to move away faster than the one-step compliance says
/// (measured: 0.26 % every solve, 0.85 % every 2 ms, 4.8 % every 5 ms, 9.3 % every 10 ms).
#[test]
fn local_model_follows_the_full_solve_while_pressing_within_a_bound() {
    for (every, bound) in [(1, 0.01), (5, 0.06)] {
        let (worst, largest) = local_against_full(every, -0.003);
        assert!(largest > 1.0, "the probe pressed: {largest} N");
        assert!(
            worst < bound * largest,
            "refreshed every {every} ms, the local model departs by {worst} N (forces up to {largest} N)"
        );
    }
}

/// With friction, pressed 3 mm in and dragged sideways at 20 mm/s: the local model carries
/// the contact's friction (its damper on the sliding velocity), so refreshed by every solve
/// it answers within 3 % of the largest force while the tool sticks and slides (measured
/// 2.1 %; without the friction in the local model, 11.9 %).
#[test]
fn local_model_with_friction_follows_the_full_solve_while_sliding() {
    let friction = Friction { static_coefficient: 0.5, kinetic_coefficient: 0.3, stick_speed: 1e-4 };
    let (worst, largest) = local_against_full_on(coupled_probe(1e-3, Some(friction)), 1, -0.003, 0.02, 900);
    assert!(largest > 1.0, "the probe pressed: {largest} N");
    assert!(worst < 0.03 * largest, "the local model departs by {worst} N (forces up to {largest} N)");
}

/// A coupled needle turning with its device (a rotational coupling), refreshed every
/// `every` poses: the largest torque difference between the local model's answers and the
/// full solve's (N·m), and the largest torque (N·m). The device comes down tilted 0.1 rad
/// so the needle's far end ends `depth` into the slab, then turns about z at 1 rad/s.
fn turning_needle_against_full(every: usize, depth: f64) -> (f64, f64) {
    let mut tool = Tool::new(ToolShape::Capsule { radius: 0.001, length: 0.04 }, 20_000.0);
    tool.coupling = Some(COUPLING);
    tool.rotational_coupling =
        Some(RotationalCoupling { stiffness: 2.0, damping: 0.02, inertia: 1e-5, max_torque: 5.0 });
    let params = SolverParams { gravity: [0.0; 3], dt: 1e-3, cg_tolerance: 1e-10, ..Default::default() };
    let mut full = Simulation::<f64>::new(&coarse_slab(), params, vec![tool]).unwrap();
    let tilt = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2 + 0.1);
    // The far end is 0.04 sin 0.1 = 4 mm below the tip.
    let device = |t: f64| {
        let z = 0.02 + (0.001 + 0.004 - depth - 0.02) * (t / 0.3).min(1.0);
        let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), (t - 0.3).max(0.0));
        Isometry3::from_parts(nalgebra::Translation3::new(0.03, 0.058, z), turn * tilt)
    };
    full.tool_mut(0).unwrap().world_from_tool = device(0.0);
    full.step().unwrap();
    let mut model = full.local_models().remove(0);
    let (mut worst, mut largest) = (0.0f64, 0.0f64);
    for k in 1..=500 {
        let pose = device(k as f64 * 1e-3);
        let answer = model.answer(&pose, 1e-3);
        full.tool_mut(0).unwrap().world_from_tool = pose;
        let felt = Vector3::from(full.step().unwrap().reaction(0).torque);
        worst = worst.max((answer.torque - felt).norm());
        largest = largest.max(felt.norm());
        if k % every == 0 {
            model = full.local_models().remove(0);
        }
    }
    (worst, largest)
}

/// Turning in free space the local model's torque is the full solve's own, never
/// refreshed (1e-9); with the far end pressed 2 mm in, refreshed every solve, it answers
/// within 5 % of the largest torque (measured 2.8 %, as the needle first touches: the
/// contact plane's row spans the tool's turning through its lever; holding the contacts'
/// torque instead gave 16.7 %, and before, no torque at all).
#[test]
fn local_model_turns_with_the_device_and_feels_its_torque() {
    let (worst, largest) = turning_needle_against_full(usize::MAX, -0.005);
    assert!(largest > 1e-3, "the coupling turned the needle: {largest} N·m");
    assert!(worst < 1e-9 * largest, "free: the local torque departs by {worst} N·m of {largest} N·m");
    let (worst, largest) = turning_needle_against_full(1, 0.002);
    assert!(largest > 1e-2, "pressed: {largest} N·m");
    assert!(worst < 0.05 * largest, "pressed: the local torque departs by {worst} N·m of {largest} N·m");
}

/// A device pose far through the organ: the local model pulls with the coupling's largest
/// force at most, and says it saturated.
#[test]
fn local_model_never_pulls_harder_than_the_coupling_saturates() {
    let mut full = coupled_probe(1e-3, None);
    full.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.043, 0.058, 0.001);
    full.step().unwrap();
    let mut model = full.local_models().remove(0);
    for k in 0..200 {
        let answer = model.answer(&Isometry3::translation(0.043, 0.058, -0.2), 1e-3);
        assert!(answer.force.norm() <= COUPLING.max_force * (1.0 + 1e-12), "pose {k}: {} N", answer.force.norm());
        assert!(answer.saturated, "pose {k} is reported saturated");
    }
}
