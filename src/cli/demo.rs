//! `defvol demo`: the node's pipeline without DDS, driven by the scene's scripted tool path
//! (`replay.rs` drives it from a recorded bag).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};

use defvol::msgs::{Header, Pose, PoseStamped, Time};
use defvol::pipeline::inputs::InputLimits;
use defvol::pipeline::{Demand, FrameMode, Pipeline};
use defvol::scene::{BackendArgs, Scene};
use defvol::session::{qualified, RecordOptions, Session, TopicNames};

#[derive(clap::Args)]
pub struct DemoArgs {
    /// Simulated seconds.
    #[arg(long, default_value_t = 2.0)]
    seconds: f64,
    /// Folder for demo.mcap and demo.rrd.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Scene file (YAML); the embedded default scene when absent.
    #[arg(long)]
    scene: Option<PathBuf>,
    #[command(flatten)]
    backend: BackendArgs,
    /// Leave out the rerun log (demo.rrd).
    #[arg(long)]
    no_rerun: bool,
}

pub(super) fn load_scene(path: &Option<PathBuf>) -> Result<Scene> {
    Ok(match path {
        Some(path) => Scene::from_file(path)?,
        None => Scene::default_scene()?,
    })
}

pub(super) fn progress(len: u64) -> ProgressBar {
    let bar = ProgressBar::new(len);
    if let Ok(style) = ProgressStyle::with_template("{bar:40} {pos}/{len} steps {elapsed_precise} (eta {eta}) {msg}") {
        bar.set_style(style);
    }
    bar
}

/// Inputs are judged against the bag's own clock: no message is stale in a replay.
pub(super) fn replay_limits() -> InputLimits {
    InputLimits { max_age: None, ..Default::default() }
}

pub fn run(args: DemoArgs) -> Result<()> {
    if !(args.seconds.is_finite() && args.seconds > 0.0) {
        bail!("--seconds {} must be positive", args.seconds);
    }
    let scene = load_scene(&args.scene)?;
    let backend = scene.backend(&args.backend)?;
    let mut pipeline =
        Pipeline::new(scene, &backend, replay_limits(), FrameMode::Lockstep).context("starting the pipeline")?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    if !cfg!(feature = "mcap") {
        tracing::warn!("defvol was built without the `mcap` feature: no demo.mcap");
    }
    let records = RecordOptions {
        mcap: cfg!(feature = "mcap").then(|| args.out.join("demo.mcap")),
        rerun_file: (!args.no_rerun).then(|| args.out.join("demo.rrd")),
        rerun_connect: None,
        ..Default::default()
    };
    let mut session = Session::open(&TopicNames::under("/"), &records, &pipeline)?;
    let dt_ns = (pipeline.scene().solver.dt * 1e9).round() as u64;
    let steps = (args.seconds * 1e9 / dt_ns as f64).round().max(1.0) as u64;
    let topics = pipeline.tool_topics();
    let tools = pipeline.scene().tools.clone();
    let bar = progress(steps);
    let mut outcome = Ok(());
    for k in 1..=steps {
        let stamp = Time::from_nanos(k * dt_ns);
        // The scripted path goes in as tool_pose messages, as a tracker would send it, so
        // the bag replays to the same run.
        for (tool, (pose_topic, _)) in tools.iter().zip(&topics) {
            let Some(path) = &tool.path else { continue };
            let p = path.position(stamp.as_secs());
            let world_from_tool = nalgebra::Isometry3::translation(p.x, p.y, p.z);
            let msg = PoseStamped {
                header: Header { stamp, frame_id: pipeline.scene().frame_id.clone() },
                pose: Pose::from_isometry(&world_from_tool),
            };
            if let Err(rejection) = pipeline.apply_pose(pose_topic, &msg, stamp) {
                tracing::warn!("{rejection}");
            }
            session.record_pose(&qualified("/", pose_topic), &msg, pipeline.tool_on(pose_topic));
        }
        match pipeline.tick(stamp, &Demand::ALL) {
            Ok(out) => session.record_outputs(&out, &pipeline, stamp),
            Err(e) => {
                outcome = Err(e);
                break;
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    // What was recorded up to an error stays: the bag is closed properly either way.
    session.finish()?;
    outcome.context("the pipeline stopped")?;
    let r = pipeline.last_report();
    tracing::info!(
        "demo: {steps} steps ({} s simulated) on {}; max displacement {:.3e} m; reaction {} N",
        args.seconds,
        pipeline.backend_name(),
        r.map_or(0.0, |r| r.max_displacement),
        r.map_or_else(|| "none".to_owned(), |r| defvol::logging::vector(r.reaction(0).force, 3))
    );
    Ok(())
}
