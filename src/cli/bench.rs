//! `defvol bench <stage>`: run time against error, as a table or JSON lines (the
//! conventions' format).

use anyhow::{bail, Context, Result};

use defvol::backend::{Backend, BackendChoice};
use defvol::bench;

use super::choices::{self, CliBackend, CliPhysics, CliPreconditioner, CliSampling, CliScheme, CliTopology};

#[derive(clap::Subcommand)]
pub enum BenchStage {
    /// The node's pipeline: pose-in to feedback-out latency at 1 kHz, recording overhead,
    /// pose-in to warped-volume-received through iceoryx2, on each backend; warped-volume
    /// delivery through iceoryx2 beside DDS (DDS rows need a private network namespace:
    /// `tests/netns-run defvol bench node`).
    Node {
        #[arg(long, value_delimiter = ',', default_value = "5000,600")]
        tets: Vec<usize>,
        #[arg(long, default_value_t = 1000)]
        steps: usize,
        #[arg(long, default_value_t = 200)]
        settle: usize,
        #[arg(long, value_delimiter = ',', default_value = "1,64")]
        volume_mib: Vec<usize>,
        #[command(flatten)]
        backends: BenchBackends,
        /// Warped volumes timed from pose to subscriber, per backend.
        #[arg(long, default_value_t = 30)]
        volume_frames: usize,
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
        /// Lattice meshes (tets) bending the phantom: the source seen through the bent mesh
        /// beside warp + volume raycast of the same bend; none when given without values.
        #[arg(long, value_delimiter = ',', num_args = 0.., default_value = "5000")]
        source_meshes: Vec<usize>,
        /// Write each volume case's work (volume, camera, transfer function, f64 reference)
        /// into this folder for the peers in benches/peers/.
        #[arg(long)]
        export: Option<std::path::PathBuf>,
        #[command(flatten)]
        gpu: GpuRows,
        #[arg(long)]
        json: bool,
    },
    /// DPCM steps per second on the seed's 1100 x 1100 grid, 1 to 300 markers; error over dt.
    Dpcm {
        #[arg(long, value_delimiter = ',', default_value = "1100,1100")]
        size: Vec<usize>,
        #[arg(long, value_delimiter = ',', default_value = "1,20,50,100,300")]
        markers: Vec<usize>,
        #[arg(long, value_enum, value_delimiter = ',', default_value = "eight,four")]
        topologies: Vec<CliTopology>,
        #[arg(long, value_enum, value_delimiter = ',', default_value = "elastic,plastic")]
        physics: Vec<CliPhysics>,
        #[arg(long, default_value_t = 200)]
        steps: usize,
        /// Time steps of the accuracy sweep.
        #[arg(long, value_delimiter = ',', default_value = "0.001,0.0005,0.00025,0.000125")]
        dts: Vec<f64>,
        /// Skip the accuracy sweep.
        #[arg(long)]
        no_sweep: bool,
        /// GPU steps per submission, a GPU row each.
        #[arg(long, value_delimiter = ',', default_value = "1,10", value_parser = clap::value_parser!(u32).range(1..=4096))]
        batch: Vec<u32>,
        #[command(flatten)]
        gpu: GpuRows,
        #[arg(long)]
        json: bool,
    },
    /// Grid warp of the phantom through lattice meshes (seed 003's cases).
    Warp {
        #[arg(long, value_delimiter = ',', default_value = "40,700,1080,5000")]
        tets: Vec<usize>,
        #[arg(long, value_delimiter = ',', default_value = "upright,rot45,bend")]
        cases: Vec<String>,
        #[arg(long, value_enum, value_delimiter = ',', default_value = "spans,culling,bbox")]
        schemes: Vec<CliScheme>,
        #[arg(long, value_enum, value_delimiter = ',', default_value = "trilinear")]
        samplings: Vec<CliSampling>,
        /// Phantom size (1 mm voxels).
        #[arg(long, value_delimiter = ',', default_value = "256,160,122")]
        dims: Vec<usize>,
        #[arg(long, default_value_t = 5)]
        runs: usize,
        /// Also time an incremental update after a local press.
        #[arg(long)]
        incremental: bool,
        /// Write each case's work (source, mesh, reference) into this folder for the peers
        /// in benches/peers/.
        #[arg(long)]
        export: Option<std::path::PathBuf>,
        #[command(flatten)]
        gpu: GpuRows,
        #[arg(long)]
        json: bool,
    },
    /// Run time against error drawn: `DIR/<stage>.svg` for each stage (log-log, a curve per
    /// scheme and backend, the seeds' published figures beside), `DIR/index.html` showing them
    /// with the machine, build and date, and `DIR/rows.jsonl`; from the stages' benchmarks run
    /// now, or from rows already written (`--from`).
    Report(super::bench_report::ReportArgs),
    /// Implicit Euler (CG tolerance and time step sweeps) and the explicit schemes.
    Solver {
        /// Mesh sizes in tets (default: the seed's Table 1 sizes).
        #[arg(long, value_delimiter = ',')]
        sizes: Option<Vec<usize>>,
        #[arg(long, default_value_t = 20)]
        steps: usize,
        #[command(flatten)]
        backends: BenchBackends,
        #[arg(long, value_delimiter = ',', default_value = "1e-2,1e-3,1e-4,1e-5")]
        tolerances: Vec<f64>,
        #[arg(long, value_delimiter = ',', default_value = "0.01")]
        dts: Vec<f64>,
        /// Time step of the explicit schemes (they diverge at the implicit one).
        #[arg(long, default_value_t = 5e-6)]
        explicit_dt: f64,
        /// Explicit steps per batch: one GPU submission and one read-back where the solver
        /// can batch them (no surface contact, no commanded force).
        #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=100_000))]
        explicit_batch: u32,
        #[arg(long, value_enum, value_delimiter = ',', default_value = "amg,block-jacobi")]
        preconditioners: Vec<CliPreconditioner>,
        /// One JSON object per line instead of the table.
        #[arg(long)]
        json: bool,
    },
}

/// Prints benchmark rows as JSON lines (the conventions' format) or as a table under `header`.
fn row_printer(json: bool, header: &str, table_row: fn(&bench::BenchRow) -> String) -> impl FnMut(&bench::BenchRow) {
    if !json {
        println!("{header}");
    }
    // Each row says when and by which command it was measured, so a report can show both.
    let date = jiff::Timestamp::now().strftime("%Y-%m-%d").to_string();
    let command = std::iter::once("defvol".to_owned()).chain(std::env::args().skip(1)).collect::<Vec<_>>().join(" ");
    move |row| {
        if json {
            let line = serde_json::to_value(row).and_then(|mut value| {
                value["date"] = date.clone().into();
                value["command"] = command.clone().into();
                serde_json::to_string(&value)
            });
            match line {
                Ok(line) => println!("{line}"),
                Err(e) => tracing::error!("cannot encode a benchmark row: {e}"),
            }
        } else {
            println!("{}", table_row(row));
        }
    }
}

/// The backends a benchmark times side by side in one run.
#[derive(clap::Args)]
pub struct BenchBackends {
    /// Backends timed side by side, e.g. `cpu,gpu` (`gpu` with no usable adapter is an
    /// error).
    #[arg(long = "backends", alias = "backend", value_enum, value_delimiter = ',', default_value = "cpu")]
    backends: Vec<CliBackend>,
    /// Let a software adapter (lavapipe, llvmpipe) run the GPU rows: correctness, not speed.
    #[arg(long)]
    allow_software_gpu: bool,
}

/// GPU rows beside a stage's CPU rows.
#[derive(clap::Args)]
pub struct GpuRows {
    /// Also time the GPU path, read-back included (no usable adapter is an error).
    #[arg(long)]
    gpu: bool,
    /// Let a software adapter (lavapipe, llvmpipe) run the GPU rows: correctness, not speed.
    #[arg(long)]
    allow_software_gpu: bool,
}

impl GpuRows {
    /// The GPU for `--gpu` rows: asked for explicitly, so no usable adapter is an error.
    fn backend(&self) -> Result<Option<Backend>> {
        Ok(match self.gpu {
            true => Some(Backend::choose(BackendChoice::Gpu, self.allow_software_gpu)?),
            false => None,
        })
    }
}

pub fn run(stage: BenchStage) -> Result<()> {
    match stage {
        BenchStage::Report(args) => super::bench_report::run(&args)?,
        BenchStage::Node { tets, steps, settle, volume_mib, backends, volume_frames, json } => {
            let opts = bench::node::NodeBenchOptions {
                tets,
                steps,
                settle,
                volume_mib,
                backends: choices::all(&backends.backends),
                allow_software_gpu: backends.allow_software_gpu,
                volume_frames,
            };
            bench::node::run(&opts, row_printer(json, bench::node::TABLE_HEADER, bench::node::table_row))?;
        }
        BenchStage::Render {
            sizes,
            steps,
            runs,
            reference_step,
            no_warped,
            meshes,
            source_meshes,
            export,
            gpu,
            json,
        } => {
            let opts = bench::render::RenderBenchOptions {
                sizes,
                steps,
                runs,
                reference_step,
                warped: !no_warped,
                meshes,
                source_meshes,
                gpu: gpu.backend()?,
                export,
            };
            bench::render::run(&opts, row_printer(json, bench::render::TABLE_HEADER, bench::render::table_row))?;
        }
        BenchStage::Dpcm { size, markers, topologies, physics, steps, dts, no_sweep, batch, gpu, json } => {
            let [w, h] = size[..] else { bail!("--size takes two sizes") };
            let dts = if no_sweep { Vec::new() } else { dts };
            let opts = bench::dpcm::DpcmBenchOptions {
                size: [w, h],
                markers,
                topologies: choices::all(&topologies),
                physics: choices::all(&physics),
                steps,
                dts,
                gpu: gpu.backend()?,
                batches: batch.into_iter().map(|b| b as usize).collect(),
            };
            bench::dpcm::run(&opts, row_printer(json, bench::dpcm::TABLE_HEADER, bench::dpcm::table_row))?;
        }
        BenchStage::Warp { tets, cases, schemes, samplings, dims, runs, incremental, export, gpu, json } => {
            let cases = cases
                .iter()
                .map(|c| {
                    bench::WarpCase::ALL
                        .into_iter()
                        .find(|k| k.name() == c)
                        .with_context(|| format!("unknown warp case `{c}` (upright, rot45, bend)"))
                })
                .collect::<Result<Vec<_>>>()?;
            let [x, y, z] = dims[..] else { bail!("--dims takes three sizes") };
            let opts = bench::WarpBenchOptions {
                tets,
                cases,
                schemes: choices::all(&schemes),
                samplings: choices::all(&samplings),
                dims: [x, y, z],
                runs,
                incremental,
                gpu: gpu.backend()?,
                export,
            };
            bench::warp(&opts, row_printer(json, bench::WARP_TABLE_HEADER, bench::warp_table_row))?;
        }
        BenchStage::Solver {
            sizes,
            steps,
            backends,
            tolerances,
            dts,
            explicit_dt,
            explicit_batch,
            preconditioners,
            json,
        } => {
            let opts = bench::SolverBenchOptions {
                sizes: sizes.unwrap_or(bench::SEED_SIZES.to_vec()),
                steps,
                backends: choices::all(&backends.backends),
                allow_software_gpu: backends.allow_software_gpu,
                tolerances,
                dts,
                explicit_dt,
                explicit_batch,
                preconditioners: choices::all(&preconditioners),
            };
            bench::solver(&opts, row_printer(json, bench::TABLE_HEADER, bench::table_row))?;
        }
    }
    Ok(())
}
