//! `defvol replay`: the node's pipeline without DDS, driven by the tool inputs of a
//! recorded bag (one `demo` or `node --record` wrote).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

use defvol::backend::BackendChoice;
use defvol::msgs::{self, PoseStamped, Time, WrenchStamped};
use defvol::pipeline::{Demand, FrameMode, Pipeline};
use defvol::record::bag;
use defvol::scene::BackendArgs;
use defvol::session::{qualified, RecordOptions, Session, TopicNames};

use super::demo::{load_scene, progress, replay_limits};

#[derive(clap::Args)]
pub struct ReplayArgs {
    /// A bag (MCAP) holding tool poses and wrenches, e.g. one `demo` or `node --record` wrote.
    bag: PathBuf,
    /// Where the replay's outputs go (MCAP).
    #[arg(long)]
    out: Option<PathBuf>,
    /// A rerun log of the replay.
    #[arg(long)]
    rerun: Option<PathBuf>,
    /// Scene file (YAML); the embedded default scene when absent.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// The node namespace the bag's topics are under.
    #[arg(long, default_value = "/")]
    namespace: String,
    /// Pace the replay at the bag's rate instead of as fast as possible.
    #[arg(long)]
    realtime: bool,
    /// The CPU path is deterministic (the same bag, the same outputs), so it is the default.
    #[command(flatten)]
    backend: BackendArgs,
}

/// A recorded tool input.
enum Input {
    Pose(String, PoseStamped),
    Wrench(String, WrenchStamped),
}

pub fn run(args: ReplayArgs) -> Result<()> {
    let scene = load_scene(&args.scene)?;
    // The bag is read first: a missing or foreign file is refused before anything is built.
    let topics: Vec<(String, String)> =
        scene.tools.iter().enumerate().map(|(i, tool)| (tool.pose_topic(i), tool.wrench_topic(i))).collect();
    let wanted: Vec<(String, usize, bool)> = topics
        .iter()
        .enumerate()
        .flat_map(|(i, (pose, wrench))| {
            [(qualified(&args.namespace, pose), i, true), (qualified(&args.namespace, wrench), i, false)]
        })
        .collect();
    let names: Vec<&str> = wanted.iter().map(|(t, _, _)| t.as_str()).collect();
    let recorded = bag::read_messages(&args.bag, &names)?;
    if recorded.is_empty() {
        let all = bag::read_messages(&args.bag, &[])?;
        let present: std::collections::BTreeSet<&str> = all.iter().map(|m| m.topic.as_str()).collect();
        let present: Vec<&str> = present.into_iter().collect();
        bail!(
            "{}: no tool inputs on {}; the bag's topics are {} (see --namespace)",
            args.bag.display(),
            names.join(", "),
            present.join(", ")
        );
    }
    let mut inputs = Vec::with_capacity(recorded.len());
    let mut undecodable = 0;
    for m in &recorded {
        let Some((_, index, is_pose)) = wanted.iter().find(|(t, _, _)| *t == m.topic) else { continue };
        let (pose_topic, wrench_topic) = &topics[*index];
        let decoded = if *is_pose {
            msgs::decode::<PoseStamped>(&m.data, &m.topic).map(|p| Input::Pose(pose_topic.clone(), p))
        } else {
            msgs::decode::<WrenchStamped>(&m.data, &m.topic).map(|w| Input::Wrench(wrench_topic.clone(), w))
        };
        match decoded {
            Ok(input) => inputs.push((m.log_time_ns, input)),
            Err(e) => {
                undecodable += 1;
                tracing::warn!("skipped: {e}");
            }
        }
    }
    let backend = scene
        .backend(&BackendArgs { backend: Some(args.backend.backend.unwrap_or(BackendChoice::Cpu)), ..args.backend })?;
    let mut pipeline =
        Pipeline::new(scene, &backend, replay_limits(), FrameMode::Lockstep).context("starting the pipeline")?;
    let records = RecordOptions { mcap: args.out.clone(), rerun_file: args.rerun.clone(), ..Default::default() };
    let mut session = Session::open(&TopicNames::under(&args.namespace), &records, &pipeline)?;
    let dt_ns = (pipeline.scene().solver.dt * 1e9).round() as u64;
    let (first, last) = (inputs.first().map_or(0, |i| i.0), inputs.last().map_or(0, |i| i.0));
    let steps = (last - first) / dt_ns + 1;
    let bar = progress(steps);
    let wall_start = Instant::now();
    let mut next = 0;
    let mut outcome = Ok(());
    let demand = if session.recording() { Demand::ALL } else { Demand { deformed_mesh: true, ..Demand::NONE } };
    for k in 0..steps {
        let t_ns = first + k * dt_ns;
        let stamp = Time::from_nanos(t_ns);
        while let Some((_, input)) = inputs.get(next).filter(|(time, _)| *time <= t_ns) {
            // The outputs bag holds the inputs too, so that it replays in turn.
            let refused = match input {
                Input::Pose(topic, msg) => {
                    let outcome = pipeline.apply_pose(topic, msg, stamp);
                    session.record_pose(&qualified(&args.namespace, topic), msg, pipeline.tool_on(topic));
                    outcome.err()
                }
                Input::Wrench(topic, msg) => {
                    session.record_wrench(&qualified(&args.namespace, topic), msg);
                    pipeline.apply_wrench(topic, msg, stamp).err()
                }
            };
            if let Some(rejection) = refused {
                tracing::warn!("{rejection}");
            }
            next += 1;
        }
        if args.realtime {
            let due = Duration::from_nanos(t_ns - first);
            if let Some(wait) = due.checked_sub(wall_start.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        match pipeline.tick(stamp, &demand) {
            Ok(out) => session.record_outputs(&out, &pipeline, stamp),
            Err(e) => {
                outcome = Err(e);
                break;
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    session.finish()?;
    outcome.context("the pipeline stopped")?;
    let counters = pipeline.counters();
    tracing::info!(
        "replayed {} inputs ({} refused, {undecodable} undecodable) over {steps} steps in {:.2} s",
        counters.accepted,
        counters.total_rejected(),
        wall_start.elapsed().as_secs_f64()
    );
    Ok(())
}
