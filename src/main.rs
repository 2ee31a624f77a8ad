//! The `defvol` command line.

mod cli;

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};

use defvol::bench;
use defvol::engine::{BackendChoice, Engine};
use defvol::io;
use defvol::scene::{MeshSource, Scene};
use defvol::solver::{Integrator, Preconditioner, StepReport};
use defvol::warp::{DisplacementVolume, Sampling, Scheme, WarpOptions};

#[derive(Parser)]
#[command(name = "defvol", version, about = "Deformable volumes: implicit mass-spring meshes on the CPU and the GPU")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a mesh for N steps with a scripted tool; write the final mesh and a per-step CSV.
    Simulate(SimulateArgs),
    /// Warp a volume through a deformed mesh and/or displacement volumes; with no files,
    /// the phantom through a generated bend and press.
    Warp(WarpArgs),
    /// Run a DPCM surface (phyxels engraved by markers) and write its renderings.
    Dpcm(cli::dpcm::DpcmArgs),
    /// A raycast image of a volume (the phantom when no file is given).
    Render(cli::render::RenderArgs),
    /// The node's pipeline on a scene with its scripted tool path, no DDS: writes
    /// DIR/demo.mcap (a rosbag2 MCAP) and DIR/demo.rrd (a rerun log).
    Demo(cli::session::DemoArgs),
    /// Run the pipeline from the tool poses and wrenches of a recorded bag.
    #[cfg(feature = "mcap")]
    Replay(cli::replay::ReplayArgs),
    /// The ROS 2 node (as `defvol_node`): `defvol node [--record F.mcap] --ros-args -p …`.
    #[cfg(feature = "ros")]
    Node {
        /// The node's options and its ROS arguments, as `defvol_node` takes them.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Measure a stage: run time against error.
    Bench {
        #[command(subcommand)]
        stage: BenchStage,
    },
}

#[derive(clap::Args)]
struct SimulateArgs {
    /// Scene file (YAML); the embedded default scene when absent.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Mesh file replacing the scene's mesh (.vtu, .vtk, .msh, .node/.ele).
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Tet count of a generated lattice mesh.
    #[arg(long)]
    tets: Option<usize>,
    #[arg(long, value_enum)]
    integrator: Option<Integrator>,
    /// Time step (s).
    #[arg(long)]
    dt: Option<f64>,
    #[arg(long)]
    cg_tolerance: Option<f64>,
    #[arg(long, value_enum)]
    preconditioner: Option<Preconditioner>,
    #[arg(long, default_value_t = 100)]
    steps: u64,
    #[arg(long, value_enum, default_value = "auto")]
    backend: BackendChoice,
    /// Let a software adapter (llvmpipe) run the GPU path.
    #[arg(long)]
    allow_software_gpu: bool,
    /// Output folder: final.vtu and steps.csv.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Also warp the scene's volume through the final mesh and write it here (.nii.gz,
    /// .nrrd, .mha…), in the volume's own units.
    #[arg(long)]
    warp_out: Option<PathBuf>,
}

#[derive(clap::Args)]
struct WarpArgs {
    /// Rest mesh (.vtu, .vtk, .msh, .node/.ele), in the volume's physical units.
    #[arg(long, requires = "deformed")]
    rest: Option<PathBuf>,
    /// Deformed mesh: same topology, moved nodes.
    #[arg(long, requires = "rest")]
    deformed: Option<PathBuf>,
    /// Source volume (.nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd); the phantom when absent.
    #[arg(long)]
    volume: Option<PathBuf>,
    /// Output volume (.nii, .nii.gz, .nrrd, .mha, .mhd), in the source's units and conventions.
    #[arg(long)]
    out: PathBuf,
    /// A displacement volume "cx,cy,cz:dx,dy,dz:extent" (repeatable; applied in order).
    #[arg(long)]
    displace: Vec<String>,
    #[arg(long, value_enum, default_value = "spans")]
    scheme: Scheme,
    #[arg(long, value_enum, default_value = "trilinear")]
    sampling: Sampling,
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    background: f32,
    /// Voxels outside the mesh keep the source's value.
    #[arg(long)]
    keep_uncovered: bool,
    /// `auto`: the GPU when a hardware adapter exists and the options allow (spans,
    /// trilinear, no displacement volumes), else the CPU.
    #[arg(long, value_enum, default_value = "auto")]
    backend: BackendChoice,
    #[arg(long)]
    allow_software_gpu: bool,
}

fn parse_displacement(text: &str) -> Result<DisplacementVolume> {
    let parts: Vec<&str> = text.split(':').collect();
    let vec3 = |s: &str| -> Result<[f64; 3]> {
        let v: Vec<f64> = s.split(',').map(|c| c.trim().parse::<f64>()).collect::<Result<_, _>>().with_context(|| format!("`{s}` is not three numbers"))?;
        let [x, y, z] = v[..] else { bail!("`{s}` is not three numbers") };
        Ok([x, y, z])
    };
    let [centre, displacement, extent] = parts[..] else { bail!("--displace `{text}`: expected cx,cy,cz:dx,dy,dz:extent") };
    Ok(DisplacementVolume { centre: vec3(centre)?, displacement: vec3(displacement)?, extent: extent.trim().parse().with_context(|| format!("--displace `{text}`: bad extent"))? })
}

fn warp_command(args: WarpArgs) -> Result<()> {
    let source = match &args.volume {
        Some(path) => io::read_volume(path)?,
        None => defvol::volume::phantom::phantom(defvol::volume::phantom::DEFAULT_DIMS, 1.0)?,
    };
    let displacements = args.displace.iter().map(|d| parse_displacement(d)).collect::<Result<Vec<_>>>()?;
    let options = WarpOptions { scheme: args.scheme, sampling: args.sampling, background: args.background, keep_uncovered: args.keep_uncovered, displacements, ..Default::default() };
    let started = std::time::Instant::now();
    let result = match (&args.rest, &args.deformed) {
        (Some(rest_path), Some(deformed_path)) => {
            let rest = io::read_mesh(rest_path)?;
            let deformed = io::read_mesh(deformed_path)?;
            if deformed.tets() != rest.tets() {
                bail!("{}: the deformed mesh's tets differ from the rest mesh's ({} vs {} tets, or other node order)", deformed_path.display(), deformed.tets().len(), rest.tets().len());
            }
            let grid = defvol::warp::default_grid(&source, deformed.nodes());
            warp_on_backend(&args, &source, &rest, deformed.nodes(), &grid, &options)?
        }
        _ if args.volume.is_some() && args.rest.is_none() && !options.displacements.is_empty() => defvol::warp::displace(&source, &source.grid(), &options)?,
        _ => {
            // The phantom through a generated deformation: a bend plus a local press.
            let (lo, hi) = source.bounds();
            let rest = defvol::mesh::generate::lattice_for_box(lo, hi, 700, defvol::mesh::generate::CellSplit::Five)?;
            let (centre, half) = ((lo + hi) / 2.0, (hi - lo) / 2.0);
            let bent = bench::WarpCase::Bend.deform(rest.nodes(), centre, half);
            let grid = defvol::warp::default_grid(&source, &bent);
            warp_on_backend(&args, &source, &rest, &bent, &grid, &options)?
        }
    };
    tracing::info!("warped to {:?} in {:.1} ms", result.dims(), started.elapsed().as_secs_f64() * 1e3);
    io::write_volume(&args.out, &result)?;
    tracing::info!("wrote {}", args.out.display());
    Ok(())
}

/// The GPU path when asked for and possible, else the CPU path (with a log line saying why).
fn warp_on_backend(
    args: &WarpArgs,
    source: &defvol::volume::Volume,
    rest: &defvol::mesh::TetMesh,
    deformed: &[nalgebra::Vector3<f64>],
    grid: &defvol::volume::Grid,
    options: &WarpOptions,
) -> Result<defvol::volume::Volume> {
    #[cfg(not(feature = "gpu"))]
    let _ = args.backend;
    #[cfg(feature = "gpu")]
    if matches!(args.backend, BackendChoice::Auto | BackendChoice::Gpu) {
        let choice = defvol::gpu_policy::GpuChoice { allow_software: args.allow_software_gpu, required: args.backend == BackendChoice::Gpu };
        if let Some(ctx) = choice.context() {
            let name = ctx.describe();
            match defvol::gpu::warp::GpuWarper::new(std::sync::Arc::new(ctx), source).and_then(|w| w.warp(rest, deformed, grid, options)) {
                Ok((data, stats)) => {
                    tracing::info!("warped on {name}: {stats:?}");
                    return Ok(defvol::volume::Volume::from_grid(grid, data, "warped volume")?);
                }
                Err(e) => tracing::warn!("GPU warp not used: {e}"),
            }
        }
    }
    let (out, stats) = defvol::warp::warp(source, rest, deformed, grid, options)?;
    tracing::info!("warped on the CPU: {stats:?}");
    Ok(out)
}

#[derive(Subcommand)]
enum BenchStage {
    /// The node's pipeline: pose-in to feedback-out latency at 1 kHz, recording overhead,
    /// and warped-volume delivery through iceoryx2 beside DDS (DDS rows need a private
    /// network namespace: `tests/netns-run defvol bench node`).
    Node {
        #[arg(long, value_delimiter = ',', default_value = "5000,600")]
        tets: Vec<usize>,
        #[arg(long, default_value_t = 1000)]
        steps: usize,
        #[arg(long, default_value_t = 200)]
        settle: usize,
        #[arg(long, value_delimiter = ',', default_value = "1,64")]
        volume_mib: Vec<usize>,
        #[arg(long, value_enum, default_value = "cpu")]
        backend: BackendChoice,
        #[arg(long)]
        json: bool,
    },
    /// Volume raycasting of the phantom (plain and warped): ms per frame and PSNR against the
    /// f64 ray integral, over steps.
    Render {
        #[arg(long, value_delimiter = ',', default_value = "512,1024")]
        sizes: Vec<usize>,
        #[arg(long, value_delimiter = ',', default_value = "2,1,0.5")]
        steps: Vec<f64>,
        #[arg(long, default_value_t = 5)]
        runs: usize,
        #[arg(long, default_value_t = 0.1)]
        reference_step: f64,
        /// Only the phantom as it is (no warped copy).
        #[arg(long)]
        no_warped: bool,
        /// Lattice meshes (tets) over the phantom for the tetrahedral-mesh raycaster; none
        /// when given without values.
        #[arg(long, value_delimiter = ',', num_args = 0.., default_value = "112000,157000")]
        meshes: Vec<usize>,
        /// Also time the GPU raycasters (volume and mesh), read-back included.
        #[arg(long)]
        gpu: bool,
        /// Let a software adapter (llvmpipe) run the GPU rows.
        #[arg(long)]
        allow_software_gpu: bool,
        #[arg(long)]
        json: bool,
    },
    /// DPCM steps per second on the seed's 1100 x 1100 grid, 1 to 300 markers; error over dt.
    Dpcm {
        #[arg(long, value_delimiter = ',', default_value = "1100,1100")]
        size: Vec<usize>,
        #[arg(long, value_delimiter = ',', default_value = "1,20,50,100,300")]
        markers: Vec<usize>,
        #[arg(long, value_delimiter = ',', default_value = "eight,four")]
        topologies: Vec<defvol::dpcm::Topology>,
        #[arg(long, value_delimiter = ',', default_value = "elastic,plastic")]
        physics: Vec<bench::dpcm::Physics>,
        #[arg(long, default_value_t = 200)]
        steps: usize,
        /// Time steps of the accuracy sweep.
        #[arg(long, value_delimiter = ',', default_value = "0.001,0.0005,0.00025,0.000125")]
        dts: Vec<f64>,
        /// Skip the accuracy sweep.
        #[arg(long)]
        no_sweep: bool,
        /// Also run the GPU path.
        #[arg(long)]
        gpu: bool,
        #[arg(long)]
        allow_software_gpu: bool,
        #[arg(long)]
        json: bool,
    },
    /// Grid warp of the phantom through lattice meshes (seed 003's cases).
    Warp {
        #[arg(long, value_delimiter = ',', default_value = "40,700,1080,5000")]
        tets: Vec<usize>,
        #[arg(long, value_delimiter = ',', default_value = "upright,rot45,bend")]
        cases: Vec<String>,
        #[arg(long, value_delimiter = ',', default_value = "spans,culling,bbox")]
        schemes: Vec<Scheme>,
        #[arg(long, value_delimiter = ',', default_value = "trilinear")]
        samplings: Vec<Sampling>,
        /// Phantom size (1 mm voxels).
        #[arg(long, value_delimiter = ',', default_value = "256,160,122")]
        dims: Vec<usize>,
        #[arg(long, default_value_t = 5)]
        runs: usize,
        /// Also time an incremental update after a local press.
        #[arg(long)]
        incremental: bool,
        /// Also run the GPU path.
        #[arg(long)]
        gpu: bool,
        /// Let a software adapter (llvmpipe) run the GPU path.
        #[arg(long)]
        allow_software_gpu: bool,
        #[arg(long)]
        json: bool,
    },
    /// Implicit Euler (CG tolerance and time step sweeps) and the explicit schemes.
    Solver {
        /// Mesh sizes in tets (default: the seed's Table 1 sizes).
        #[arg(long, value_delimiter = ',')]
        sizes: Option<Vec<usize>>,
        #[arg(long, default_value_t = 20)]
        steps: usize,
        #[arg(long, value_delimiter = ',', default_value = "cpu,gpu")]
        backends: Vec<BackendChoice>,
        #[arg(long)]
        allow_software_gpu: bool,
        #[arg(long, value_delimiter = ',', default_value = "1e-2,1e-3,1e-4,1e-5")]
        tolerances: Vec<f64>,
        #[arg(long, value_delimiter = ',', default_value = "0.01")]
        dts: Vec<f64>,
        /// Time step of the explicit schemes (they diverge at the implicit one).
        #[arg(long, default_value_t = 5e-6)]
        explicit_dt: f64,
        #[arg(long, value_delimiter = ',', default_value = "amg,block-jacobi")]
        preconditioners: Vec<Preconditioner>,
        /// One JSON object per line instead of the table.
        #[arg(long)]
        json: bool,
    },
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
}

impl From<&StepReport> for CsvRow {
    fn from(r: &StepReport) -> Self {
        Self {
            step: r.step,
            time: r.time,
            cg_iterations: r.cg_iterations,
            residual: r.residual,
            kinetic_energy: r.kinetic_energy,
            potential_energy: r.potential_energy,
            max_displacement: r.max_displacement,
            reaction_fx: r.reaction_force[0],
            reaction_fy: r.reaction_force[1],
            reaction_fz: r.reaction_force[2],
        }
    }
}

fn simulate(args: SimulateArgs) -> Result<()> {
    let mut scene = match &args.scene {
        Some(path) => Scene::from_file(path)?,
        None => Scene::default_scene()?,
    };
    if let Some(path) = &args.mesh {
        scene.mesh = MeshSource::File { path: path.clone() };
    }
    if let Some(tets) = args.tets {
        match &mut scene.mesh {
            MeshSource::VolumeLattice { target_tets, .. } | MeshSource::Lattice { target_tets, .. } => *target_tets = tets,
            _ => bail!("--tets applies to generated lattice meshes only"),
        }
    }
    if let Some(i) = args.integrator {
        scene.solver.integrator = i;
    }
    if let Some(dt) = args.dt {
        scene.solver.dt = dt;
    }
    if let Some(tol) = args.cg_tolerance {
        scene.solver.cg_tolerance = tol;
    }
    if let Some(p) = args.preconditioner {
        scene.solver.preconditioner = p;
    }
    let loaded = scene.load().context("loading the scene")?;
    tracing::info!("mesh: {} nodes, {} tets, {} springs", loaded.mesh.nodes().len(), loaded.mesh.tets().len(), loaded.model.springs.len());
    let mut engine = Engine::new(args.backend, args.allow_software_gpu, &loaded.model, loaded.scene.solver.clone(), loaded.tools_at(0.0))?;
    tracing::info!("backend: {}", engine.name());
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let csv_path = args.out.join("steps.csv");
    let mut csv = csv::Writer::from_path(&csv_path).with_context(|| format!("creating {}", csv_path.display()))?;
    let dt = loaded.scene.solver.dt;
    let mut outcome = Ok(());
    for step in 0..args.steps {
        let t = (step + 1) as f64 * dt;
        for (index, tool) in loaded.tools_at(t).into_iter().enumerate() {
            engine.tool_mut(index)?.world_from_tool = tool.world_from_tool;
        }
        match engine.step() {
            Ok(report) => {
                csv.serialize(CsvRow::from(&report))?;
                if report.step % 10 == 0 || report.step == args.steps {
                    tracing::info!(
                        "step {:>5} t={:.3}s CG {:>4} its residual {:.1e} max displacement {:.3e} m reaction {:?}",
                        report.step,
                        report.time,
                        report.cg_iterations,
                        report.residual,
                        report.max_displacement,
                        report.reaction_force.map(|f| (f * 1e3).round() / 1e3)
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
    let mesh_path = args.out.join("final.vtu");
    io::write_mesh(&mesh_path, &loaded.mesh, Some(&engine.positions()))?;
    tracing::info!("wrote {} and {}", mesh_path.display(), csv_path.display());
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
        tracing::info!("wrote the warped volume {} ({:?} voxels, {} inside the mesh)", path.display(), warped.dims(), stats.inside);
    }
    outcome.context("simulation stopped")?;
    Ok(())
}

/// Prints benchmark rows as JSON lines (the conventions' format) or as a table under `header`.
fn row_printer(json: bool, header: &str, table_row: fn(&bench::BenchRow) -> String) -> impl FnMut(&bench::BenchRow) {
    if !json {
        println!("{header}");
    }
    move |row| {
        if json {
            match serde_json::to_string(row) {
                Ok(line) => println!("{line}"),
                Err(e) => tracing::error!("cannot encode a benchmark row: {e}"),
            }
        } else {
            println!("{}", table_row(row));
        }
    }
}

fn main() -> Result<()> {
    tracing_subscriber::fmt().with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info,rustdds=error,ros2_client=warn".into())).with_target(false).init();
    match Cli::parse().command {
        Command::Simulate(args) => simulate(args),
        Command::Warp(args) => warp_command(args),
        Command::Dpcm(args) => cli::dpcm::run(args),
        Command::Render(args) => cli::render::run(args),
        Command::Demo(args) => cli::session::demo(args),
        #[cfg(feature = "mcap")]
        Command::Replay(args) => cli::replay::replay(args),
        #[cfg(feature = "ros")]
        Command::Node { args } => {
            let settings = defvol::ros::node::settings_from_args(&args)?;
            defvol::ros::node::run(settings)?;
            Ok(())
        }
        Command::Bench { stage: BenchStage::Node { tets, steps, settle, volume_mib, backend, json } } => {
            let opts = bench::node::NodeBenchOptions { tets, steps, settle, volume_mib, backend };
            bench::node::run(&opts, row_printer(json, bench::node::TABLE_HEADER, bench::node::table_row))?;
            Ok(())
        }
        Command::Bench { stage: BenchStage::Render { sizes, steps, runs, reference_step, no_warped, meshes, gpu, allow_software_gpu, json } } => {
            let gpu = gpu.then_some(defvol::gpu_policy::GpuChoice { allow_software: allow_software_gpu, required: true });
            let opts = bench::render::RenderBenchOptions { sizes, steps, runs, reference_step, warped: !no_warped, meshes, gpu };
            bench::render::run(&opts, row_printer(json, bench::render::TABLE_HEADER, bench::render::table_row))?;
            Ok(())
        }
        Command::Bench { stage: BenchStage::Dpcm { size, markers, topologies, physics, steps, dts, no_sweep, gpu, allow_software_gpu, json } } => {
            let [w, h] = size[..] else { bail!("--size takes two sizes") };
            let gpu = gpu.then_some(defvol::gpu_policy::GpuChoice { allow_software: allow_software_gpu, required: true });
            let dts = if no_sweep { Vec::new() } else { dts };
            let opts = bench::dpcm::DpcmBenchOptions { size: [w, h], markers, topologies, physics, steps, dts, gpu };
            bench::dpcm::run(&opts, row_printer(json, bench::dpcm::TABLE_HEADER, bench::dpcm::table_row))?;
            Ok(())
        }
        Command::Bench { stage: BenchStage::Warp { tets, cases, schemes, samplings, dims, runs, incremental, gpu, allow_software_gpu, json } } => {
            let cases = cases
                .iter()
                .map(|c| bench::WarpCase::ALL.into_iter().find(|k| k.name() == c).with_context(|| format!("unknown warp case `{c}` (upright, rot45, bend)")))
                .collect::<Result<Vec<_>>>()?;
            let [x, y, z] = dims[..] else { bail!("--dims takes three sizes") };
            let gpu = gpu.then_some(defvol::gpu_policy::GpuChoice { allow_software: allow_software_gpu, required: true });
            let opts = bench::WarpBenchOptions { tets, cases, schemes, samplings, dims: [x, y, z], runs, incremental, gpu };
            bench::warp(&opts, row_printer(json, bench::WARP_TABLE_HEADER, bench::warp_table_row))?;
            Ok(())
        }
        Command::Bench { stage: BenchStage::Solver { sizes, steps, backends, allow_software_gpu, tolerances, dts, explicit_dt, preconditioners, json } } => {
            let opts = bench::SolverBenchOptions { sizes: sizes.unwrap_or(bench::SEED_SIZES.to_vec()), steps, backends, allow_software_gpu, tolerances, dts, explicit_dt, preconditioners };
            bench::solver(&opts, row_printer(json, bench::TABLE_HEADER, bench::table_row))?;
            Ok(())
        }
    }
}
