//! The scenes the project ships, on both backends (the GPU the software adapter in the
//! suite): the embedded default scene through its scripted press against the CPU, step by
//! step as the demo and the node run it (scripted poses in, a solver step and the force
//! loop's local models, outputs out).

use defvol::backend::Backend;
use defvol::msgs::{Header, Pose, PoseStamped, Time};
use defvol::pipeline::inputs::InputLimits;
use defvol::pipeline::{Demand, FrameMode, Pipeline};
use defvol::scene::{Scene, Stages};
use nalgebra::Vector3;

/// What a run looked like at one step.
#[derive(Debug, Clone)]
struct Sample {
    step: u64,
    positions: Vec<Vector3<f64>>,
    reaction: Vector3<f64>,
    cg_iterations: u32,
    max_displacement: f64,
}

/// `steps` steps of `scene` on `backend` from t = `start` (s), each tool with a scripted path
/// fed its pose as the demo feeds it; a sample every `every` steps, and the error that
/// stopped the run, if any.
fn run(scene: Scene, backend: &Backend, start: f64, steps: u64, every: u64) -> (Vec<Sample>, Option<String>) {
    let limits = InputLimits { max_age: None, ..Default::default() };
    let mut pipeline = Pipeline::new(scene, backend, limits, FrameMode::Lockstep).unwrap();
    let dt = pipeline.scene().solver.dt;
    let (tools, topics) = (pipeline.scene().tools.clone(), pipeline.tool_topics());
    let mut samples = Vec::new();
    for k in 1..=steps {
        let stamp = Time::from_secs(start + k as f64 * dt);
        for (tool, (pose_topic, _)) in tools.iter().zip(&topics) {
            let Some(path) = &tool.path else { continue };
            let p = path.position(stamp.as_secs());
            let msg = PoseStamped {
                header: Header { stamp, frame_id: pipeline.scene().frame_id.clone() },
                pose: Pose::from_isometry(&nalgebra::Isometry3::translation(p.x, p.y, p.z)),
            };
            pipeline.apply_pose(pose_topic, &msg, stamp).unwrap();
        }
        if let Err(e) = pipeline.tick(stamp, &Demand::ALL) {
            return (samples, Some(format!("{e:#}")));
        }
        let report = pipeline.last_report().unwrap();
        if k % every == 0 {
            samples.push(Sample {
                step: report.step,
                positions: pipeline.positions().to_vec(),
                reaction: Vector3::from(report.reaction(0).force),
                cg_iterations: report.cg_iterations,
                max_displacement: report.max_displacement,
            });
        }
    }
    (samples, None)
}

/// The default scene with the solver alone (what the press is about; the other stages
/// read its nodes and are checked on both backends by their own tests).
fn default_solver_scene() -> Scene {
    let mut scene = Scene::default_scene().unwrap();
    scene.stages = Stages { solver: true, warp: false, dpcm: false, raycast: false };
    scene
}

/// The embedded default scene on the GPU through the scripted press and past it (90 steps:
/// the probe touches the organ at 0.46 s and holds 4 mm into it from 0.5 s), its local
/// models solved after each step as the force loop solves them: at every 10th step the
/// GPU's nodes within 2 % of the largest displacement of the CPU's, the probe's reaction
/// within 5 % of the CPU's largest, and CG's iterations within 20 % of the CPU's.
#[cfg(feature = "gpu")]
#[test]
fn default_scene_on_the_gpu_follows_the_cpu_through_the_press() {
    let Some(ctx) = defvol::gpu::test_context() else { return };
    let (cpu, cpu_error) = run(default_solver_scene(), &Backend::cpu(), 0.0, 90, 10);
    let (gpu, gpu_error) = run(default_solver_scene(), &Backend::gpu(ctx), 0.0, 90, 10);
    assert_eq!((&cpu_error, &gpu_error), (&None, &None), "both runs complete");
    let moved = cpu.iter().map(|s| s.max_displacement).fold(0.0, f64::max);
    let pressed = cpu.iter().map(|s| s.reaction.norm()).fold(0.0, f64::max);
    assert!(moved > 2e-3 && pressed > 3.0, "the probe pressed: {moved} m, {pressed} N");
    let gaps: Vec<(f64, f64)> = (cpu.iter().zip(&gpu))
        .map(|(c, g)| {
            let node_gap = c.positions.iter().zip(&g.positions).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
            eprintln!(
                "step {}: nodes {:.2e} m apart, reactions {:.3?} / {:.3?} N, CG {} / {} its",
                c.step, node_gap, c.reaction, g.reaction, c.cg_iterations, g.cg_iterations
            );
            (node_gap, (c.reaction - g.reaction).norm())
        })
        .collect();
    for ((c, g), (node_gap, force_gap)) in cpu.iter().zip(&gpu).zip(gaps) {
        let its = f64::from(c.cg_iterations.abs_diff(g.cg_iterations));
        assert!(node_gap <= 0.02 * moved, "step {}: nodes {node_gap} m apart (largest move {moved} m)", c.step);
        assert!(force_gap <= 0.05 * pressed, "step {}: reactions {} / {} N", c.step, c.reaction, g.reaction);
        assert!(
            its <= 0.2 * f64::from(c.cg_iterations),
            "step {}: CG its {} / {}",
            c.step,
            c.cg_iterations,
            g.cg_iterations
        );
    }
}

/// Text replacements in a scene file: (what it says, what it says instead).
type Edits = Vec<(&'static str, &'static str)>;

/// The shipped default scene with `edits` made to its text (the variants its comments
/// document), the probe starting its path at `start`.
fn shipped_variant(edits: &[(&str, &str)]) -> Scene {
    let text = edits.iter().fold(defvol::scene::DEFAULT_SCENE.to_owned(), |text, (from, to)| {
        assert!(text.contains(from), "the default scene documents `{from}`");
        text.replace(from, to)
    });
    Scene::parse(&text, "default_scene.yaml (variant)").unwrap()
}

/// `scene` on the CPU and on the GPU from `start` for `steps` steps, every stage it enables
/// running: both complete, the probe touches the organ, and at every step the GPU's nodes and
/// reaction follow the CPU's (2 % of the largest move, 5 % of the largest reaction).
#[cfg(feature = "gpu")]
fn both_backends_agree(name: &str, scene: Scene, start: f64, steps: u64) {
    let Some(ctx) = defvol::gpu::test_context() else { return };
    let (cpu, cpu_error) = run(scene.clone(), &Backend::cpu(), start, steps, 1);
    let (gpu, gpu_error) = run(scene, &Backend::gpu(ctx), start, steps, 1);
    assert_eq!((&cpu_error, &gpu_error), (&None, &None), "{name}: both runs complete");
    let moved = cpu.iter().map(|s| s.max_displacement).fold(0.0, f64::max);
    let pressed = cpu.iter().map(|s| s.reaction.norm()).fold(0.0, f64::max);
    let touching = cpu.iter().filter(|s| s.reaction.norm() > 0.05).count();
    assert!(touching >= 3, "{name}: the probe touched for {touching} of {steps} steps");
    for (c, g) in cpu.iter().zip(&gpu) {
        let node_gap = c.positions.iter().zip(&g.positions).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
        let force_gap = (c.reaction - g.reaction).norm();
        assert!(node_gap <= 0.02 * moved, "{name}, step {}: nodes {node_gap} m apart (largest move {moved} m)", c.step);
        assert!(
            force_gap <= 0.05 * pressed,
            "{name}, step {}: reactions {} / {} N (largest {pressed} N)",
            c.step,
            c.reaction,
            g.reaction
        );
    }
}

/// The probe starts its scripted path 3 mm above the organ (t = 0.43 s of its 0.5 s path),
/// so that a dozen steps reach well past the first contact.
const JUST_ABOVE: f64 = 0.43;

#[cfg(feature = "gpu")]
#[test]
fn the_default_scene_with_every_stage_runs_past_contact_on_both_backends() {
    both_backends_agree("default scene", Scene::default_scene().unwrap(), JUST_ABOVE, 12);
}

/// The variants the default scene's comments document: friction and the rotational
/// coupling turned on, contact on the nodes (for a tool wider than the mesh spacing, no
/// coupling: here a 40 mm ball, touching from 0.23 s), each preconditioner, the mesh shown.
#[cfg(feature = "gpu")]
#[test]
fn the_documented_variants_of_the_default_scene_run_past_contact_on_both_backends() {
    let solver_only = ("stages: { solver: true, warp: true, dpcm: true, raycast: true }", "stages: { solver: true }");
    let wide_ball_on_nodes = vec![
        ("contact: surface", "contact: nodes"),
        ("coupling: { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 10.0 }", ""),
        ("radius: 0.002 }", "radius: 0.02 }"),
        solver_only,
    ];
    let variants: [(&str, Edits, f64); 5] = [
        (
            "friction and rotational coupling",
            vec![("# rotational_coupling:", "rotational_coupling:"), ("# friction:", "friction:"), solver_only],
            JUST_ABOVE,
        ),
        ("contact on the nodes", wide_ball_on_nodes, 0.2),
        ("multigrid", vec![("preconditioner: auto ", "preconditioner: amg "), solver_only], JUST_ABOVE),
        ("block Jacobi", vec![("preconditioner: auto ", "preconditioner: block_jacobi "), solver_only], JUST_ABOVE),
        ("the mesh shown", vec![("shows: volume ", "shows: mesh ")], JUST_ABOVE),
    ];
    for (name, edits, start) in variants {
        both_backends_agree(name, shipped_variant(&edits), start, 12);
    }
}

/// The node benchmark's scenes (`defvol bench node`, its default sizes): the default
/// scene's solver alone at 1 kHz on about 5,000 and 600 tets.
#[cfg(feature = "gpu")]
#[test]
fn the_benchmarks_haptic_scenes_run_past_contact_on_both_backends() {
    for tets in [5000, 600] {
        let scene = defvol::bench::node::haptic_scene(tets).unwrap();
        both_backends_agree(&format!("haptic bench scene, {tets} tets"), scene, 0.455, 25);
    }
}
