//! `defvol bench node`: what a user of the node feels. The pose-in to feedback-out
//! latency of the pipeline at 1 kHz input, the cost of recording, the pose-in to
//! warped-volume-received latency through iceoryx2, each on every backend asked for, and
//! the delivery time of a volume through iceoryx2 beside DDS for the same bytes.

use std::time::Instant;

use serde_json::json;

use super::{cpu_description, time_stats, BenchRow};
use crate::backend::{Backend, BackendChoice, RunsOn};
use crate::msgs::{Header, Pose, PoseStamped, Time};
use crate::pipeline::inputs::InputLimits;
use crate::pipeline::{Demand, FrameMode, Pipeline, PipelineError};
use crate::scene::Scene;
use crate::session::{RecordOptions, Session, TopicNames};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum NodeBenchError {
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error(transparent)]
    Session(#[from] crate::session::SessionError),
    #[error(transparent)]
    Backend(#[from] crate::backend::BackendError),
    #[error("{0}")]
    Setup(String),
}

pub struct NodeBenchOptions {
    /// Tet counts of the lattice scenes timed.
    pub tets: Vec<usize>,
    /// Steps timed per case (after `settle` untimed ones).
    pub steps: usize,
    pub settle: usize,
    /// Volume bytes sent through shared memory (and DDS).
    pub volume_mib: Vec<usize>,
    /// Each timed in the same run (`gpu` with no usable adapter is an error).
    pub backends: Vec<BackendChoice>,
    pub allow_software_gpu: bool,
    /// Warped volumes timed from pose to subscriber, per backend.
    pub volume_frames: usize,
}

pub const TABLE_HEADER: &str = "case                          backend     p50 ms     p99 ms     max ms  notes";

/// A time in milliseconds, with the digits a sub-microsecond delivery needs.
fn ms(v: f64) -> String {
    match v < 0.01 {
        true => format!("{v:.5}"),
        false => format!("{v:.3}"),
    }
}

/// One row of the table; the rates are in the notes (what was sent and received), not
/// derived from a percentile.
pub fn table_row(row: &BenchRow) -> String {
    let notes = row.params["note"].as_str().unwrap_or_default();
    if row.runs == 0 {
        return format!("{:<29} {:<8} {:>10} {:>10} {:>10}  {notes}", row.case, row.backend, "-", "-", "-");
    }
    let p99 = row.params["p99_ms"].as_f64().map_or("-".into(), ms);
    format!(
        "{:<29} {:<8} {:>10} {:>10} {:>10}  {notes}",
        row.case,
        row.backend,
        ms(row.time_ms.median),
        p99,
        ms(row.time_ms.max)
    )
}

/// The fractions at which a row reports its latency distribution (`quantiles_ms`, drawn as
/// a CDF by `bench report`).
const QUANTILES: [f64; 11] = [0.0, 0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95, 0.99, 0.999, 1.0];

/// (fraction, ms) at each of [`QUANTILES`]; none without samples.
fn quantiles(samples: &[f64]) -> Vec<[f64; 2]> {
    if samples.is_empty() {
        return Vec::new();
    }
    QUANTILES.iter().map(|&p| [p, percentile(samples, p)]).collect()
}

fn percentile(samples: &[f64], p: f64) -> f64 {
    let mut sorted = samples.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted.get(((sorted.len() as f64 - 1.0) * p).round() as usize).copied().unwrap_or(0.0)
}

/// The default scene with the solver alone at 1 kHz, on a lattice of about `tets`.
pub fn haptic_scene(tets: usize) -> Result<Scene, NodeBenchError> {
    let mut scene = Scene::default_scene().map_err(|e| NodeBenchError::Setup(e.to_string()))?;
    scene.stages = crate::scene::Stages { solver: true, warp: false, dpcm: false, raycast: false };
    scene.solver.dt = 1e-3;
    if let crate::scene::MeshSource::VolumeLattice { target_tets, .. } = &mut scene.mesh {
        *target_tets = tets;
    }
    Ok(scene)
}

/// The GPU where any of the pipeline's stages runs there.
fn any_stage_on(pipeline: &Pipeline) -> RunsOn {
    match pipeline.stage_backends().iter().any(|(_, on)| *on == RunsOn::Gpu) {
        true => RunsOn::Gpu,
        false => RunsOn::Cpu,
    }
}

/// Pose in, one solver step, feedback and mesh messages out: `steps` times, recording or
/// not; ms per step and, on a GPU, what a step cost it.
fn pose_to_feedback(
    scene: Scene,
    backend: &Backend,
    opts: &NodeBenchOptions,
    record: Option<&std::path::Path>,
) -> Result<(Vec<f64>, Option<super::GpuCost>, usize), NodeBenchError> {
    let mut pipeline =
        Pipeline::new(scene, backend, InputLimits { max_age: None, ..Default::default() }, FrameMode::Lockstep)?;
    let tets = pipeline.mesh().tets().len();
    let records = RecordOptions { mcap: record.map(Into::into), ..Default::default() };
    let mut session = Session::open(&TopicNames::under("/"), &records, &pipeline)?;
    let demand = Demand { tool_feedback: true, deformed_mesh: true, ..Demand::NONE };
    let mut samples = Vec::with_capacity(opts.steps);
    let mut meter = None;
    for k in 0..opts.settle + opts.steps {
        if k == opts.settle {
            meter = super::GpuMeter::start(backend, any_stage_on(&pipeline));
        }
        let t = (k + 1) as f64 * 1e-3;
        // The probe comes down over the first half second, then holds: contact throughout.
        let z = 0.07 - 0.01 * (t / 0.5).min(1.0);
        let stamp = Time::from_secs(t);
        let mut pose = PoseStamped { header: Header { stamp, frame_id: "world".into() }, pose: Pose::default() };
        pose.pose.position.z = z;
        let start = Instant::now();
        let _ = pipeline.apply_pose("tool_pose", &pose, stamp);
        session.record_pose("/tool_pose", &pose, pipeline.tool_on("tool_pose"));
        let out = pipeline.tick(stamp, &demand)?;
        session.record_outputs(&out, &pipeline, stamp);
        if k >= opts.settle {
            samples.push(start.elapsed().as_secs_f64() * 1e3);
        }
    }
    let cost = meter.and_then(|m| m.finish(opts.steps));
    session.finish()?;
    Ok((samples, cost, tets))
}

pub fn run(opts: &NodeBenchOptions, mut emit: impl FnMut(&BenchRow)) -> Result<(), NodeBenchError> {
    let cpu = cpu_description();
    let dir = tempfile_dir()?;
    let backends =
        opts.backends.iter().map(|b| Backend::choose(*b, opts.allow_software_gpu)).collect::<Result<Vec<_>, _>>()?;
    for backend in &backends {
        let device = match backend.runs_on() {
            RunsOn::Gpu => backend.describe(),
            RunsOn::Cpu => cpu.clone(),
        };
        for &tets in &opts.tets {
            feedback_rows(backend, &device, tets, opts, &dir, &mut emit)?;
        }
        #[cfg(feature = "shm")]
        if opts.volume_frames > 0 {
            emit(&pose_to_volume(backend, &device, opts.volume_frames)?);
        }
    }
    #[cfg(feature = "shm")]
    for &mib in &opts.volume_mib {
        emit(&shm_delivery(mib, &cpu)?);
    }
    #[cfg(feature = "ros")]
    for &mib in &opts.volume_mib {
        emit(&dds_delivery(mib, &cpu)?);
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// Pose to feedback on a lattice of about `tets`: through the node and DDS with the solver
/// alone and with every stage beside it, each plain and recording; outside a private
/// network namespace, in-process (no DDS) and said so.
fn feedback_rows(
    backend: &Backend,
    device: &str,
    tets: usize,
    opts: &NodeBenchOptions,
    dir: &std::path::Path,
    emit: &mut impl FnMut(&BenchRow),
) -> Result<(), NodeBenchError> {
    #[cfg(feature = "ros")]
    if crate::ros::dds::private_network() {
        let n = haptic_scene(tets)?.load().map_err(|e| NodeBenchError::Setup(e.to_string()))?.mesh.tets().len();
        for everything in [false, true] {
            let bag = dir.join(format!("bench_{tets}_{everything}.mcap"));
            let plain = dds::feedback_through_node(tets, everything, None, backend, opts)?;
            let recorded = dds::feedback_through_node(tets, everything, Some(&bag), backend, opts)?;
            let beside = if everything { "all_stages" } else { "solver" };
            for (run, case) in [
                (plain, format!("pose_to_feedback_{n}tets_{beside}")),
                (recorded, format!("recording_{n}tets_{beside}")),
            ] {
                emit(&run.row(case, backend.runs_on().name(), device, n, everything));
            }
            let _ = std::fs::remove_file(&bag);
        }
        return Ok(());
    }
    let name = backend.runs_on().name().to_owned();
    let (plain, plain_cost, n) = pose_to_feedback(haptic_scene(tets)?, backend, opts, None)?;
    let bag = dir.join(format!("bench_{tets}.mcap"));
    let (recorded, recorded_cost, _) = pose_to_feedback(haptic_scene(tets)?, backend, opts, Some(&bag))?;
    let (p50, p99) = (percentile(&plain, 0.5), percentile(&plain, 0.99));
    let overhead = percentile(&recorded, 0.5) / p50 - 1.0;
    let mean = plain.iter().sum::<f64>() / plain.len().max(1) as f64;
    emit(&BenchRow {
        stage: "node",
        case: format!("in_process_step_{n}tets"),
        backend: name.clone(),
        device: device.to_owned(),
        params: json!({"input_hz": 1000, "dt": 1e-3, "p99_ms": p99, "quantiles_ms": quantiles(&plain), "sustained_hz": 1e3 / mean, "note": format!("no DDS (outside a private network namespace); sustains {:.0} Hz", 1e3 / mean)}),
        runs: plain.len(),
        time_ms: time_stats(plain),
        error: None,
        work: json!({"tets": n, "outputs": ["tool_feedback", "deformed_mesh"]}),
        gpu: plain_cost,
    });
    emit(&BenchRow {
        stage: "node",
        case: format!("in_process_recording_{n}tets"),
        backend: name,
        device: device.to_owned(),
        params: json!({"p99_ms": percentile(&recorded, 0.99), "quantiles_ms": quantiles(&recorded), "overhead": overhead, "note": format!("MCAP recording adds {:.1} % to the median step", overhead * 100.0)}),
        runs: recorded.len(),
        time_ms: time_stats(recorded),
        error: None,
        work: json!({"tets": n, "bag_bytes": std::fs::metadata(&bag).map(|m| m.len()).unwrap_or(0)}),
        gpu: recorded_cost,
    });
    let _ = std::fs::remove_file(&bag);
    Ok(())
}

/// The force loop as a device sees it: the node itself on a thread (its feedback thread,
/// DDS, the stages the case enables, recording or not), and a device on a participant of
/// its own publishing a pose every millisecond and taking `tool_feedback`. A feedback
/// echoes the stamp of the pose it answers: the time runs from that stamp to the device
/// holding the first answer to it.
#[cfg(feature = "ros")]
mod dds {
    use std::collections::BTreeMap;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    use std::time::{Duration, Instant};

    use mio::{Events, Interest, Poll, Token};
    use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions};
    use serde_json::json;

    use super::{percentile, quantiles, time_stats, BenchRow, NodeBenchError, NodeBenchOptions};
    use crate::backend::{Backend, BackendChoice, RunsOn};
    use crate::bench::GpuCost;
    use crate::msgs::{DiagnosticArray, Header, Pose, PoseStamped, Time, WrenchStamped};
    use crate::record::Qos;
    use crate::ros::args::RosArgs;
    use crate::ros::dds::{context, settings, Discovery};
    use crate::ros::node::{qos, run, NodeSettings};
    use crate::scene::BackendArgs;
    use crate::session::RecordOptions;

    pub struct FeedbackRun {
        /// Milliseconds from each pose's stamp to the device holding an answer to it or to a
        /// later pose (one coalesced with a later pose is answered by that one's answer).
        latencies: Vec<f64>,
        /// Poses answered by an answer of their own.
        own_answers: usize,
        poses: usize,
        /// Feedback messages the device took, and the seconds it listened.
        feedback: usize,
        seconds: f64,
        /// Solver steps per second behind the answers, and the median step time (ms), from
        /// the node's diagnostics.
        simulation_hz: f64,
        step_ms: f64,
        /// The node's GPU round trips per solver step, from its diagnostics (GPU rows).
        gpu: Option<GpuCost>,
    }

    impl FeedbackRun {
        pub fn row(self, case: String, backend: &str, device: &str, tets: usize, everything: bool) -> BenchRow {
            let rate = self.feedback as f64 / self.seconds.max(1e-9);
            let note = format!(
                "DDS loop, 1 kHz poses, coupled 2 mm tool, surface contact, local model; feedback at {rate:.0} Hz, {} of {} poses answered by their own answer, {} by it or a \
                 later one's, solver at {:.0} steps/s ({:.2} ms a step){}; goal p99 < 1 ms",
                self.own_answers,
                self.poses,
                self.latencies.len(),
                self.simulation_hz,
                self.step_ms,
                if everything { "; warp, raycast and DPCM beside" } else { "" }
            );
            BenchRow {
                stage: "node",
                case,
                backend: backend.into(),
                device: device.into(),
                params: json!({"input_hz": 1000, "dt": 1e-3, "p99_ms": percentile(&self.latencies, 0.99), "quantiles_ms": quantiles(&self.latencies), "sustained_hz": rate, "answered": self.own_answers, "answered_or_superseded": self.latencies.len(), "poses": self.poses, "simulation_hz": self.simulation_hz, "solver_step_ms": self.step_ms, "note": note}),
                runs: self.latencies.len(),
                time_ms: time_stats(self.latencies),
                error: None,
                work: json!({"tets": tets, "stages_beside": everything}),
                gpu: self.gpu,
            }
        }
    }

    pub fn feedback_through_node(
        tets: usize,
        everything: bool,
        record: Option<&std::path::Path>,
        backend: &Backend,
        opts: &NodeBenchOptions,
    ) -> Result<FeedbackRun, NodeBenchError> {
        let setup = |e: &dyn std::fmt::Debug| NodeBenchError::Setup(format!("DDS: {e:?}"));
        let mut parameters = BTreeMap::new();
        parameters.insert("mesh.target_tets".to_owned(), yaml(tets));
        parameters.insert("solver.dt".to_owned(), yaml(1e-3));
        for stage in ["warp", "raycast", "dpcm"] {
            parameters.insert(format!("stages.{stage}"), yaml(everything));
        }
        // The haptic configuration: a coupled 2 mm tool on the boundary surface, answered
        // from its local model, on either backend.
        for (name, value) in HAPTIC_TOOL {
            let value: serde_yaml_ng::Value = serde_yaml_ng::from_str(value).map_err(|e| setup(&e))?;
            parameters.insert(format!("tools.0.{name}"), value);
        }
        let stop = Arc::new(AtomicBool::new(false));
        let node_settings = NodeSettings {
            ros: RosArgs {
                node_name: "defvol".into(),
                namespace: "/".into(),
                parameters,
                remaps: BTreeMap::new(),
                rest: Vec::new(),
            },
            record: RecordOptions { mcap: record.map(Into::into), ..Default::default() },
            backend: BackendArgs {
                backend: Some(match backend.runs_on() {
                    RunsOn::Gpu => BackendChoice::Gpu,
                    RunsOn::Cpu => BackendChoice::Cpu,
                }),
                allow_software_gpu: opts.allow_software_gpu,
            },
            open_discovery: false,
            managed: false,
            run_for: Some(Duration::from_secs(900)),
            stop: Some(stop.clone()),
        };
        let node = std::thread::spawn(move || run(node_settings).map_err(|e| e.to_string()));
        // The device's side plays a haptic device's driver, whose loop runs at raised
        // priority: its own wake-ups are not the node's latency.
        let measured =
            crate::pipeline::priority::at_force_loop_priority("the bench's device", || device_side(opts, &setup));
        stop.store(true, Ordering::SeqCst);
        let ran = node.join().map_err(|_| NodeBenchError::Setup("the node panicked".into()))?;
        ran.map_err(|e| NodeBenchError::Setup(format!("node: {e}")))?;
        measured
    }

    /// The tool of the haptic configuration, as node parameters under `tools.0`.
    const HAPTIC_TOOL: [(&str, &str); 8] = [
        ("shape.kind", "sphere"),
        ("shape.radius", "0.002"),
        ("contact", "surface"),
        ("contact_stiffness", "20000.0"),
        ("coupling.stiffness", "2000.0"),
        ("coupling.damping", "5.0"),
        ("coupling.mass", "0.02"),
        ("coupling.max_force", "10.0"),
    ];

    fn device_side(
        opts: &NodeBenchOptions,
        setup: &dyn Fn(&dyn std::fmt::Debug) -> NodeBenchError,
    ) -> Result<FeedbackRun, NodeBenchError> {
        let (domain, _) = settings(|name| std::env::var(name).ok(), false).map_err(|e| setup(&e))?;
        let ctx = context(domain, Discovery::Localhost).map_err(|e| setup(&e))?;
        let mut device = ctx
            .new_node(NodeName::new("/", "bench_device").map_err(|e| setup(&e))?, NodeOptions::new())
            .map_err(|e| setup(&e))?;
        let q = qos(Qos::SensorData);
        let pose_topic = device
            .create_topic(
                &Name::parse("/tool_pose").map_err(|e| setup(&e))?,
                MessageTypeName::new("geometry_msgs", "PoseStamped"),
                &q,
            )
            .map_err(|e| setup(&e))?;
        let feedback_topic = device
            .create_topic(
                &Name::parse("/tool_feedback").map_err(|e| setup(&e))?,
                MessageTypeName::new("geometry_msgs", "WrenchStamped"),
                &q,
            )
            .map_err(|e| setup(&e))?;
        let diagnostics_topic = device
            .create_topic(
                &Name::parse("/diagnostics").map_err(|e| setup(&e))?,
                MessageTypeName::new("diagnostic_msgs", "DiagnosticArray"),
                &qos(Qos::Reliable),
            )
            .map_err(|e| setup(&e))?;
        let diagnostics = device
            .create_subscription::<DiagnosticArray>(&diagnostics_topic, Some(qos(Qos::Reliable)))
            .map_err(|e| setup(&e))?;
        let mut solver_steps: Vec<(Instant, f64, f64)> = Vec::new();
        let mut round_trips: Vec<(f64, [u64; 3])> = Vec::new();
        let poses = device.create_publisher::<PoseStamped>(&pose_topic, Some(q.clone())).map_err(|e| setup(&e))?;
        let mut feedback =
            device.create_subscription::<WrenchStamped>(&feedback_topic, Some(q)).map_err(|e| setup(&e))?;
        let mut poll = Poll::new().map_err(|e| setup(&e))?;
        mio::event::Source::register(&mut feedback, poll.registry(), Token(0), Interest::READABLE)
            .map_err(|e| setup(&e))?;
        let mut events = Events::with_capacity(16);
        let pose = |stamp: Time, z: f64| {
            let mut msg = PoseStamped { header: Header { stamp, frame_id: "world".into() }, pose: Pose::default() };
            msg.pose.position.z = z;
            msg
        };
        // The node is up, and hears the device, once a feedback echoes one of its poses.
        let deadline = Instant::now() + Duration::from_secs(300);
        let mut sent = std::collections::HashSet::new();
        'wait: loop {
            if Instant::now() > deadline {
                return Err(NodeBenchError::Setup("the node never answered a pose within 300 s".into()));
            }
            let stamp = Time::now();
            sent.insert(stamp.as_nanos());
            let _ = poses.publish(pose(stamp, 0.1));
            let _ = poll.poll(&mut events, Some(Duration::from_millis(10)));
            while let Ok(Some((msg, _))) = feedback.take() {
                if sent.contains(&msg.header.stamp.as_nanos()) {
                    break 'wait;
                }
            }
        }
        let period = Duration::from_millis(1);
        let total = opts.settle + opts.steps;
        let (mut latencies, mut own_answers, mut taken, mut listened) = (Vec::new(), 0, 0, 0.0);
        // The timed poses not yet answered, oldest first.
        let mut waiting: std::collections::VecDeque<Time> = std::collections::VecDeque::new();
        let mut next = Instant::now();
        let mut timed_from = None;
        for k in 0..total {
            if k == opts.settle {
                timed_from = Some(Instant::now());
            }
            // The device comes down over the first half second, then holds: the thin tool's
            // centre 2 mm under the organ's top (at 6 cm), in contact throughout.
            let t = k as f64 * 1e-3;
            let sent = Time::now();
            if k >= opts.settle {
                waiting.push_back(sent);
            }
            let _ = poses.publish(pose(sent, 0.07 - 0.012 * (t / 0.5).min(1.0)));
            next += period;
            loop {
                let wait = next.saturating_duration_since(Instant::now());
                if wait.is_zero() {
                    break;
                }
                let _ = poll.poll(&mut events, Some(wait));
                while let Ok(Some((msg, _))) = diagnostics.take() {
                    if k >= opts.settle {
                        solver_steps.extend(solver_step(&msg).map(|(step, ms)| (Instant::now(), step, ms)));
                        round_trips.extend(solver_step(&msg).zip(gpu_counters(&msg)).map(|((step, _), c)| (step, c)));
                    }
                }
                while let Ok(Some((msg, _))) = feedback.take() {
                    let arrived = Time::now();
                    if k >= opts.settle {
                        taken += 1;
                    }
                    // An answer answers its pose and every earlier one still waiting (coalesced
                    // into it); later answers to the same pose repeat it.
                    own_answers += usize::from(waiting.contains(&msg.header.stamp));
                    while waiting.front().is_some_and(|&stamp| stamp <= msg.header.stamp) {
                        if let Some(stamp) = waiting.pop_front() {
                            latencies.push((arrived.as_secs() - stamp.as_secs()) * 1e3);
                        }
                    }
                }
            }
        }
        if let Some(from) = timed_from {
            listened = from.elapsed().as_secs_f64();
        }
        let simulation_hz = match (solver_steps.first(), solver_steps.last()) {
            (Some(a), Some(b)) if b.0 > a.0 => (b.1 - a.1) / b.0.duration_since(a.0).as_secs_f64(),
            _ => f64::NAN,
        };
        let step_ms = percentile(&solver_steps.iter().map(|s| s.2).collect::<Vec<_>>(), 0.5);
        Ok(FeedbackRun {
            latencies,
            own_answers,
            poses: opts.steps,
            feedback: taken,
            seconds: listened,
            simulation_hz,
            step_ms,
            gpu: per_solver_step(&round_trips),
        })
    }

    /// The GPU's counters in a diagnostics message's backend status (a GPU node's).
    fn gpu_counters(msg: &DiagnosticArray) -> Option<[u64; 3]> {
        let status = msg.status.iter().find(|s| s.name == "defvol: backend")?;
        let value = |key: &str| status.values.iter().find(|kv| kv.key == key)?.value.parse::<u64>().ok();
        Some([value("gpu.submissions")?, value("gpu.readbacks")?, value("gpu.bytes_read_back")?])
    }

    /// The round trips between the first and the last timed diagnostics, per solver step
    /// (every stage's on the node's context; its timestamps are off).
    fn per_solver_step(round_trips: &[(f64, [u64; 3])]) -> Option<GpuCost> {
        let ((first_step, first), (last_step, last)) = (round_trips.first()?, round_trips.last()?);
        let steps = last_step - first_step;
        let per = |k: usize| last[k].saturating_sub(first[k]) as f64 / steps;
        (steps > 0.0).then(|| GpuCost {
            kernel_ms: None,
            copy_ms: None,
            submissions: per(0),
            readbacks: per(1),
            bytes_read_back: per(2),
            timestamps: "off",
        })
    }

    /// The solver's step count and step time in a diagnostics message.
    fn solver_step(msg: &DiagnosticArray) -> Option<(f64, f64)> {
        let status = msg.status.iter().find(|s| s.name == "defvol: solver")?;
        let value = |key: &str| status.values.iter().find(|kv| kv.key == key)?.value.parse::<f64>().ok();
        Some((value("step")?, value("step_ms")?))
    }

    /// A plain value as a YAML parameter.
    fn yaml(value: impl serde::Serialize) -> serde_yaml_ng::Value {
        serde_yaml_ng::to_value(value).unwrap_or(serde_yaml_ng::Value::Null)
    }
}

/// Pose in to warped volume received: a probe pressing the default scene (solver and warp
/// on `backend`, every tick a warp), the volume published through a real iceoryx2 service
/// into the samples it lends, a subscriber on another thread taking each. The time runs
/// from the pose to the subscriber holding the volume.
#[cfg(feature = "shm")]
fn pose_to_volume(backend: &Backend, device: &str, frames: usize) -> Result<BenchRow, NodeBenchError> {
    use crate::shm::{WarpedVolumeHeader, WarpedVolumePublisher};
    use iceoryx2::prelude::*;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    use std::time::Duration;

    let mut scene = Scene::default_scene().map_err(|e| NodeBenchError::Setup(e.to_string()))?;
    scene.stages = crate::scene::Stages { solver: true, warp: true, dpcm: false, raycast: false };
    // Its range's top: a warp every solver step.
    scene.warp.rate_hz = 1e4;
    scene.tools[0].path = None;
    let mut pipeline =
        Pipeline::new(scene, backend, InputLimits { max_age: None, ..Default::default() }, FrameMode::Lockstep)?;
    let grid = pipeline.warped_grid().cloned().ok_or_else(|| NodeBenchError::Setup("no warp stage".into()))?;
    let service = format!("defvol/bench_volume_{}_{}", std::process::id(), backend.runs_on().name());
    let publisher =
        Arc::new(WarpedVolumePublisher::new(&service, &grid).map_err(|e| NodeBenchError::Setup(e.to_string()))?);
    pipeline.set_volume_sink(Some(publisher.clone()));
    let (tx, rx) = std::sync::mpsc::channel::<(u64, Instant)>();
    let (ready_tx, ready_rx) = std::sync::mpsc::channel::<()>();
    let reader_service = service.clone();
    let timed = Arc::new(AtomicBool::new(false));
    let reader_done = timed.clone();
    let reader = std::thread::spawn(move || -> Result<(), String> {
        let node = NodeBuilder::new().create::<ipc::Service>().map_err(|e| format!("{e:?}"))?;
        let name: ServiceName = reader_service.as_str().try_into().map_err(|e| format!("{e:?}"))?;
        let factory = node
            .service_builder(&name)
            .publish_subscribe::<[f32]>()
            .user_header::<WarpedVolumeHeader>()
            .open()
            .map_err(|e| format!("{e:?}"))?;
        let subscriber = factory.subscriber_builder().create().map_err(|e| format!("{e:?}"))?;
        let _ = ready_tx.send(());
        let deadline = Instant::now() + Duration::from_secs(600);
        while Instant::now() < deadline && !reader_done.load(Ordering::Relaxed) {
            match subscriber.receive() {
                Ok(Some(sample)) => {
                    let sequence = sample.user_header().sequence;
                    std::hint::black_box(sample.payload()[sample.payload().len() / 2]);
                    if tx.send((sequence, Instant::now())).is_err() {
                        return Ok(());
                    }
                }
                Ok(None) => std::thread::sleep(Duration::from_micros(50)),
                Err(e) => return Err(format!("{e:?}")),
            }
        }
        Ok(())
    });
    ready_rx
        .recv_timeout(Duration::from_secs(10))
        .map_err(|_| NodeBenchError::Setup(format!("iceoryx2: the subscriber did not open `{service}`")))?;
    let demand = Demand { warped_volume: true, ..Demand::NONE };
    let mut samples = Vec::with_capacity(frames);
    let mut meter = None;
    for k in 0..frames + 2 {
        if k == 2 {
            meter = super::GpuMeter::start(backend, any_stage_on(&pipeline));
        }
        let t = (k + 1) as f64 * 0.01;
        let stamp = Time::from_secs(t);
        // The probe presses in 0.5 mm a frame: every frame moves the mesh.
        let mut pose = PoseStamped { header: Header { stamp, frame_id: "world".into() }, pose: Pose::default() };
        pose.pose.position.z = 0.066 - 0.0005 * k as f64;
        let start = Instant::now();
        let _ = pipeline.apply_pose("tool_pose", &pose, stamp);
        let out = pipeline.tick(stamp, &demand)?;
        let Some(sequence) = out.warped_volume.then(|| pipeline.warped_volume().map(|w| w.sequence)).flatten() else {
            continue;
        };
        let received = loop {
            let (got, at) = rx
                .recv_timeout(Duration::from_secs(60))
                .map_err(|_| NodeBenchError::Setup("the warped volume never arrived".into()))?;
            if got == sequence {
                break at;
            }
        };
        if k >= 2 {
            samples.push((received - start).as_secs_f64() * 1e3);
        }
    }
    let cost = meter.and_then(|m| m.finish(frames));
    // The reader may be idle with nothing left to take: tell it, rather than wait for a send to fail.
    timed.store(true, Ordering::Relaxed);
    drop(rx);
    if let Ok(Err(e)) = reader.join() {
        return Err(NodeBenchError::Setup(format!("iceoryx2 subscriber: {e}")));
    }
    Ok(BenchRow {
        stage: "node",
        case: format!("pose_to_warped_volume_{}tets", pipeline.mesh().tets().len()),
        backend: backend.runs_on().name().into(),
        device: device.into(),
        params: json!({"p99_ms": percentile(&samples, 0.99), "quantiles_ms": quantiles(&samples), "note": format!("pose to subscriber, {:?} voxels through iceoryx2", grid.dims)}),
        runs: samples.len(),
        time_ms: time_stats(samples),
        error: None,
        work: json!({"voxels": grid.len(), "bytes": grid.len() * 4}),
        gpu: cost,
    })
}

fn tempfile_dir() -> Result<std::path::PathBuf, NodeBenchError> {
    let dir = std::env::temp_dir().join(format!("defvol-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| NodeBenchError::Setup(format!("{}: {e}", dir.display())))?;
    Ok(dir)
}

/// Send-to-receive time of `mib` MiB through iceoryx2: from `send()` of a sample already
/// written (the warp writes into the loan) to the subscriber holding it.
#[cfg(feature = "shm")]
fn shm_delivery(mib: usize, cpu: &str) -> Result<BenchRow, NodeBenchError> {
    use crate::shm::WarpedVolumeHeader;
    use iceoryx2::prelude::*;
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    use std::sync::Arc;
    use std::time::Duration;

    let err = |e: &dyn std::fmt::Debug| NodeBenchError::Setup(format!("iceoryx2: {e:?}"));
    let elements = mib * (1 << 20) / 4;
    let name = format!("defvol/bench_{}_{mib}", std::process::id());
    let needed = crate::shm::bytes_needed(elements);
    let node = NodeBuilder::new().create::<ipc::Service>().map_err(|e| err(&e))?;
    let service_name: ServiceName = name.as_str().try_into().map_err(|e| err(&e))?;
    let service = node
        .service_builder(&service_name)
        .publish_subscribe::<[f32]>()
        .user_header::<WarpedVolumeHeader>()
        .enable_safe_overflow(true)
        .subscriber_max_buffer_size(2)
        .max_subscribers(1)
        .open_or_create()
        .map_err(|e| NodeBenchError::Setup(format!("iceoryx2 ({} MiB of /dev/shm needed): {e:?}", needed >> 20)))?;
    let publisher = service
        .publisher_builder()
        .initial_max_slice_len(elements)
        .max_loaned_samples(2)
        .create()
        .map_err(|e| err(&e))?;
    let base = Instant::now();
    let sent_at = Arc::new(AtomicU64::new(0));
    let done = Arc::new(AtomicBool::new(false));
    let (tx, rx) = std::sync::mpsc::channel::<f64>();
    let (sent_at_reader, done_reader, reader_name) = (sent_at.clone(), done.clone(), name.clone());
    // iceoryx2 ports stay on the thread that made them: the subscriber opens its own node.
    let reader = std::thread::spawn(move || -> Result<(), String> {
        let node = NodeBuilder::new().create::<ipc::Service>().map_err(|e| format!("{e:?}"))?;
        let name: ServiceName = reader_name.as_str().try_into().map_err(|e| format!("{e:?}"))?;
        let service = node
            .service_builder(&name)
            .publish_subscribe::<[f32]>()
            .user_header::<WarpedVolumeHeader>()
            .open()
            .map_err(|e| format!("{e:?}"))?;
        let subscriber = service.subscriber_builder().create().map_err(|e| format!("{e:?}"))?;
        let _ = tx.send(-1.0);
        while !done_reader.load(Ordering::Acquire) {
            if let Ok(Some(sample)) = subscriber.receive() {
                let received = base.elapsed().as_nanos() as u64;
                let latency = received.saturating_sub(sent_at_reader.load(Ordering::Acquire)) as f64 * 1e-6;
                std::hint::black_box(sample.payload().len());
                let _ = tx.send(latency);
            }
        }
        Ok(())
    });
    if rx.recv_timeout(Duration::from_secs(10)).is_err() {
        return Err(NodeBenchError::Setup(format!("iceoryx2: the subscriber did not open `{name}`")));
    }
    let data = vec![1.5f32; elements];
    let mut samples = Vec::new();
    for run in 0..12 {
        let sample = publisher.loan_slice_uninit(elements).map_err(|e| err(&e))?;
        let sample = sample.write_from_slice(&data);
        sent_at.store(base.elapsed().as_nanos() as u64, Ordering::Release);
        sample.send().map_err(|e| err(&e))?;
        if let Ok(latency) = rx.recv_timeout(Duration::from_secs(5)) {
            if run >= 2 {
                samples.push(latency);
            }
        }
    }
    done.store(true, Ordering::Release);
    if let Ok(Err(e)) = reader.join() {
        return Err(NodeBenchError::Setup(format!("iceoryx2 subscriber: {e}")));
    }
    Ok(BenchRow {
        stage: "node",
        case: format!("volume_{mib}mib_iceoryx2"),
        backend: "shm".into(),
        device: cpu.into(),
        params: json!({"p99_ms": percentile(&samples, 0.99), "quantiles_ms": quantiles(&samples), "note": "send() to receive(), goal < 0.1 ms"}),
        runs: samples.len(),
        time_ms: time_stats(samples),
        error: None,
        work: json!({"bytes": elements * 4}),
        gpu: None,
    })
}

/// The same bytes as a sensor_msgs/Image over DDS (ros2-client/RustDDS, reliable), between
/// two participants on loopback: publish() to take(). Only inside a private network
/// namespace (run it as `tests/netns-run defvol bench node`).
#[cfg(feature = "ros")]
fn dds_delivery(mib: usize, cpu: &str) -> Result<BenchRow, NodeBenchError> {
    use crate::msgs::Image;
    use crate::record::Qos;
    use crate::ros::dds::{context, Discovery};
    use crate::ros::node::qos;
    use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions};
    use std::time::Duration;

    let row = |samples: Vec<f64>, note: String| BenchRow {
        stage: "node",
        case: format!("volume_{mib}mib_dds"),
        backend: "rustdds".into(),
        device: cpu.into(),
        params: json!({"p99_ms": percentile(&samples, 0.99), "quantiles_ms": quantiles(&samples), "note": note}),
        runs: samples.len(),
        time_ms: time_stats(samples),
        error: None,
        work: json!({"bytes": mib << 20}),
        gpu: None,
    };
    if !crate::ros::dds::private_network() {
        return Ok(row(Vec::new(), "skipped: run inside a private network namespace (tests/netns-run)".into()));
    }
    let setup = |e: &dyn std::fmt::Debug| NodeBenchError::Setup(format!("DDS: {e:?}"));
    let (a, b) = (
        context(23, Discovery::Localhost).map_err(|e| setup(&e))?,
        context(23, Discovery::Localhost).map_err(|e| setup(&e))?,
    );
    let mut sender = a
        .new_node(NodeName::new("/", "bench_sender").map_err(|e| setup(&e))?, NodeOptions::new())
        .map_err(|e| setup(&e))?;
    let mut receiver = b
        .new_node(NodeName::new("/", "bench_receiver").map_err(|e| setup(&e))?, NodeOptions::new())
        .map_err(|e| setup(&e))?;
    let q = qos(Qos::Reliable);
    let name = Name::parse("/bench_volume").map_err(|e| setup(&e))?;
    let ty = || MessageTypeName::new("sensor_msgs", "Image");
    let topic_a = sender.create_topic(&name, ty(), &q).map_err(|e| setup(&e))?;
    let topic_b = receiver.create_topic(&name, ty(), &q).map_err(|e| setup(&e))?;
    let publisher = sender.create_publisher::<Image>(&topic_a, Some(q.clone())).map_err(|e| setup(&e))?;
    let subscription = receiver.create_subscription::<Image>(&topic_b, Some(q)).map_err(|e| setup(&e))?;
    std::thread::sleep(Duration::from_secs(2));
    let image = Image {
        height: 1,
        width: (mib << 20) as u32,
        encoding: "mono8".into(),
        step: (mib << 20) as u32,
        data: vec![3u8; mib << 20],
        ..Default::default()
    };
    let mut samples = Vec::new();
    let mut lost = 0;
    for run in 0..7 {
        let start = Instant::now();
        if publisher.publish(image.clone()).is_err() {
            lost += 1;
            continue;
        }
        let got = loop {
            if let Ok(Some(_)) = subscription.take() {
                break true;
            }
            if start.elapsed() > Duration::from_secs(10) {
                break false;
            }
            std::thread::sleep(Duration::from_micros(50));
        };
        match (got, run) {
            (true, 0) => {}
            (true, _) => samples.push(start.elapsed().as_secs_f64() * 1e3),
            (false, _) => lost += 1,
        }
    }
    let note = if lost > 0 {
        format!("{lost} of 7 not delivered within 10 s")
    } else {
        "publish() to take(), reliable".into()
    };
    Ok(row(samples, note))
}

#[cfg(test)]
mod table_tests {
    use super::*;

    #[test]
    fn sub_microsecond_times_keep_their_digits() {
        assert_eq!(ms(0.00041), "0.00041");
        assert_eq!(ms(1.5), "1.500");
    }
}
