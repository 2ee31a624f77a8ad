//! `defvol simulate`: the solver alone on a scene, with its scripted tools; the final mesh,
//! a CSV of every step, and optionally the volume warped through the final mesh.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};

use defvol::io;
use defvol::mesh::Inversion;
use defvol::scene::{BackendArgs, MeshSource, Scene};
use defvol::solver::FixedNodes;
use defvol::solver::{SolverEngine, StepReport};
use defvol::warp::WarpOptions;

use super::choices::{CliIntegrator, CliPreconditioner};

#[derive(clap::Args)]
pub struct SimulateArgs {
    /// Scene file (YAML); the embedded default scene when absent.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Mesh file replacing the scene's mesh (.vtu, .vtk, .msh, .node/.ele).
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Metres per unit of the `--mesh` file (0.001 for millimetres). Default: the unit the
    /// file records (defvol's own files do), else the scene's `file_to_world`.
    #[arg(long, requires = "mesh", value_parser = super::checks::mesh_scale)]
    mesh_scale: Option<f64>,
    /// Tet count of a generated lattice mesh.
    #[arg(long)]
    tets: Option<usize>,
    #[arg(long, value_enum)]
    integrator: Option<CliIntegrator>,
    /// Time step (s).
    #[arg(long)]
    dt: Option<f64>,
    #[arg(long)]
    cg_tolerance: Option<f64>,
    #[arg(long, value_enum)]
    preconditioner: Option<CliPreconditioner>,
    #[arg(long, default_value_t = 100)]
    steps: u64,
    /// Which nodes are held (world metres): `lowest[:FRACTION]` (the nodes within FRACTION of
    /// the mesh's height above its lowest point, 0.02 by default), `plane:NX,NY,NZ,OFFSET`,
    /// `box:X0,Y0,Z0,X1,Y1,Z1`, `nodes:I,J,…` or `none`. Default: the scene's, or `lowest`
    /// for a `--mesh` without a `--scene`.
    #[arg(long, value_parser = parse_fix)]
    fix: Option<Fix>,
    #[command(flatten)]
    backend: BackendArgs,
    /// The f64 reference path (CPU) instead of the f32 one.
    #[arg(long, conflicts_with = "backend")]
    f64: bool,
    /// Output folder: rest.vtu, final.vtu and steps.csv.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Also warp the scene's volume through the final mesh and write it here (.nii.gz,
    /// .nrrd, .mha…), in the volume's own units.
    #[arg(long)]
    warp_out: Option<PathBuf>,
}

/// `--fix`: a rule for the held nodes, or none held.
#[derive(Debug, Clone)]
struct Fix(Option<FixedNodes>);

fn parse_fix(text: &str) -> Result<Fix, String> {
    let (kind, values) = text.split_once(':').unwrap_or((text, ""));
    let numbers = || -> Result<Vec<f64>, String> {
        values.split(',').map(|v| v.trim().parse::<f64>().map_err(|e| format!("`{v}` in `{text}`: {e}"))).collect()
    };
    let count = |n: usize, v: Vec<f64>| match v.len() == n {
        true => Ok(v),
        false => Err(format!("`{text}`: {kind} takes {n} numbers, got {}", v.len())),
    };
    let rule = match kind {
        "none" => None,
        "lowest" if values.is_empty() => Some(FixedNodes::Lowest { fraction: FixedNodes::LOWEST_FRACTION }),
        "lowest" => Some(FixedNodes::Lowest { fraction: count(1, numbers()?)?[0] }),
        "plane" => {
            let v = count(4, numbers()?)?;
            Some(FixedNodes::Plane { normal: [v[0], v[1], v[2]], offset: v[3] })
        }
        "box" => {
            let v = count(6, numbers()?)?;
            Some(FixedNodes::Box { min: [v[0], v[1], v[2]], max: [v[3], v[4], v[5]] })
        }
        "nodes" => {
            let nodes = values.split(',').map(|v| v.trim().parse::<u32>().map_err(|e| format!("`{v}`: {e}")));
            Some(FixedNodes::Indices { nodes: nodes.collect::<Result<_, _>>()? })
        }
        other => return Err(format!("`{other}` is not a rule (lowest, plane, box, nodes or none)")),
    };
    Ok(Fix(rule))
}

#[derive(serde::Serialize)]
struct CsvRow {
    step: u64,
    time: f64,
    cg_iterations: u32,
    residual: f64,
    kinetic_energy: f64,
    potential_energy: f64,
    max_displacement: f64,
    reaction_fx: f64,
    reaction_fy: f64,
    reaction_fz: f64,
    /// Tets turned inside out after the step.
    inverted_tets: usize,
}

impl CsvRow {
    fn new(r: &StepReport, inverted_tets: usize) -> Self {
        let f = r.reaction(0).force;
        Self {
            step: r.step,
            time: r.time,
            cg_iterations: r.cg_iterations,
            residual: r.residual,
            kinetic_energy: r.kinetic_energy,
            potential_energy: r.potential_energy,
            max_displacement: r.max_displacement,
            reaction_fx: f[0],
            reaction_fy: f[1],
            reaction_fz: f[2],
            inverted_tets,
        }
    }
}

pub fn run(args: SimulateArgs) -> Result<()> {
    if let Some(path) = &args.warp_out {
        io::check_volume_output(path)?;
    }
    let mut scene = match &args.scene {
        Some(path) => Scene::from_file(path)?,
        None => Scene::default_scene()?,
    };
    if let Some(path) = &args.mesh {
        scene.mesh = MeshSource::File { path: path.clone(), scale: args.mesh_scale };
        // The default scene's clamp plane fits its own lattice, not a user's mesh.
        if args.scene.is_none() {
            scene.fixed = Some(FixedNodes::Lowest { fraction: FixedNodes::LOWEST_FRACTION });
        }
    }
    if let Some(Fix(rule)) = &args.fix {
        scene.fixed = rule.clone();
    }
    if let Some(tets) = args.tets {
        match &mut scene.mesh {
            MeshSource::VolumeLattice { target_tets, .. } | MeshSource::Lattice { target_tets, .. } => {
                *target_tets = tets
            }
            _ => bail!("--tets applies to generated lattice meshes only"),
        }
    }
    if let Some(i) = args.integrator {
        scene.solver.integrator = i.into();
    }
    if let Some(dt) = args.dt {
        scene.solver.dt = dt;
    }
    if let Some(tol) = args.cg_tolerance {
        scene.solver.cg_tolerance = tol;
    }
    if let Some(p) = args.preconditioner {
        scene.solver.preconditioner = p.into();
    }
    let backend = scene.backend(&args.backend)?;
    let loaded = scene.load().context("loading the scene")?;
    tracing::info!(
        "mesh: {} nodes, {} tets, {} springs",
        loaded.mesh.nodes().len(),
        loaded.mesh.tets().len(),
        loaded.model.springs.len()
    );
    let held = loaded.model.fixed.iter().filter(|f| **f).count();
    match &loaded.scene.fixed {
        Some(rule) => tracing::info!("fixed {held} of {} nodes: {rule}", loaded.mesh.nodes().len()),
        None => tracing::warn!("no node is fixed: the mesh moves freely under gravity"),
    }
    let mut engine = match args.f64 {
        true => SolverEngine::reference_f64(&loaded.model, loaded.scene.solver.clone(), loaded.tools_at(0.0))?,
        false => SolverEngine::new(&backend, &loaded.model, loaded.scene.solver.clone(), loaded.tools_at(0.0))?,
    };
    tracing::info!("solver: {}", engine.name());
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let csv_path = args.out.join("steps.csv");
    let mut csv = csv::Writer::from_path(&csv_path).with_context(|| format!("creating {}", csv_path.display()))?;
    let dt = loaded.scene.solver.dt;
    let mut outcome = Ok(());
    // The first step that turned tets inside out, and the most any step did.
    let (mut first_inverted, mut most_inverted): (Option<u64>, Inversion) = (None, Inversion::default());
    for step in 0..args.steps {
        let t = (step + 1) as f64 * dt;
        for (index, tool) in loaded.tools_at(t).into_iter().enumerate() {
            engine.tool_mut(index)?.world_from_tool = tool.world_from_tool;
        }
        match engine.step() {
            Ok(report) => {
                let inverted = loaded.mesh.inverted(&engine.positions());
                if inverted.count > 0 && first_inverted.is_none() {
                    first_inverted = Some(report.step);
                    tracing::warn!("step {}: {}", report.step, describe(&inverted));
                }
                if inverted.count > most_inverted.count {
                    most_inverted = inverted;
                }
                csv.serialize(CsvRow::new(&report, inverted.count))?;
                if report.step % 10 == 0 || report.step == args.steps {
                    tracing::info!(
                        "step {:>5} t={:.3}s CG {:>4} its residual {:.1e} max displacement {:.3e} m reaction {} N",
                        report.step,
                        report.time,
                        report.cg_iterations,
                        report.residual,
                        report.max_displacement,
                        defvol::logging::vector(report.reaction(0).force, 3)
                    );
                }
            }
            Err(e) => {
                outcome = Err(e);
                break;
            }
        }
    }
    // Whatever happened, keep what was computed: the CSV so far and the last stable mesh.
    csv.flush()?;
    if let Some(step) = first_inverted {
        let last = loaded.mesh.inverted(&engine.positions());
        tracing::warn!(
            "tets turned inside out from step {step}: at most {} in a step; after the last step {}",
            most_inverted.count,
            if last.count > 0 { describe(&last) } else { "none".to_owned() }
        );
    }
    let (rest_path, mesh_path) = (args.out.join("rest.vtu"), args.out.join("final.vtu"));
    io::write_mesh(&rest_path, &loaded.mesh, None, Some(1.0))?;
    io::write_mesh(&mesh_path, &loaded.mesh, Some(&engine.positions()), Some(1.0))?;
    tracing::info!("wrote {}, {} (metres) and {}", rest_path.display(), mesh_path.display(), csv_path.display());
    if let Some(path) = &args.warp_out {
        // The mesh lives in world units; the volume in its file's units.
        let to_file = 1.0 / loaded.scene.file_to_world;
        let mut rest = loaded.mesh.clone();
        rest.map_nodes(|p| p * to_file);
        let deformed: Vec<_> = engine.positions().iter().map(|p| p * to_file).collect();
        let grid = defvol::warp::default_grid(&loaded.volume, &deformed);
        let options = WarpOptions { background: loaded.volume.range().0, ..Default::default() };
        let (warped, stats) = defvol::warp::warp(&loaded.volume, &rest, &deformed, &grid, &options)?;
        io::write_volume(path, &warped)?;
        tracing::info!(
            "wrote the warped volume {} ({} voxels, {} inside the mesh)",
            path.display(),
            defvol::logging::dims(warped.dims()),
            stats.inside
        );
    }
    outcome.context("simulation stopped")?;
    Ok(())
}

/// "N tets inverted (the worst, tet T, at R of its rest volume)".
fn describe(inversion: &Inversion) -> String {
    let worst = inversion
        .worst
        .map_or(String::new(), |(tet, ratio)| format!(" (the worst, tet {tet}, at {ratio:.3} of its rest volume)"));
    let tets = if inversion.count == 1 { "tet" } else { "tets" };
    format!("{} {tets} inverted{worst}", inversion.count)
}
