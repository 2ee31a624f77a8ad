//! The ROS 2 node: tool poses and wrenches in, the pipeline's outputs out, parameters and
//! services served, the session recorded. All computing is in [`crate::pipeline`]; this
//! file only moves messages.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use ros2_client::{Node, NodeName};
use serde_yaml_ng::Value;

use super::args::{self, RosArgs};
use super::configured::Configured;
use super::dds::{self, Discovery};
use super::error::{ros_err, NodeError};
use super::lifecycle::{Outcome, Work};
use super::managed::Managed;
use super::parameters::{ParameterServices, Parameters};
pub use super::wire::qos;
use super::wire::Topics;
use crate::msgs::{
    ChangeStateRequest, ChangeStateResponse, DeformedMesh, DiagnosticArray, GetAvailableStatesResponse,
    GetAvailableTransitionsResponse, GetStateResponse, Image, LoadSceneRequest, Marker, PoseStamped, TransitionEvent,
    TriggerRequest, TriggerResponse, WarpedVolumeInfo, WrenchStamped,
};
use crate::pipeline::inputs::InputLimits;
use crate::pipeline::{Demand, FrameMode, Pipeline};
use crate::record::BagOptions;
use crate::scene::{AllowedDirs, BackendArgs, Scene, ALLOWED_DIRS_PARAMETER};
use crate::session::{RecordOptions, Session, TopicNames};

macro_rules! ros_messages {
    ($($ty:ty),*) => {
        $(impl ros2_client::Message for $ty {})*
    };
}
ros_messages!(
    PoseStamped,
    WrenchStamped,
    DeformedMesh,
    Marker,
    Image,
    WarpedVolumeInfo,
    DiagnosticArray,
    TriggerRequest,
    TriggerResponse,
    LoadSceneRequest,
    TransitionEvent,
    ChangeStateRequest,
    ChangeStateResponse,
    GetStateResponse,
    GetAvailableStatesResponse,
    GetAvailableTransitionsResponse
);

/// How the node runs, beside its scene.
#[derive(Debug, Clone)]
pub struct NodeSettings {
    pub ros: RosArgs,
    pub record: RecordOptions,
    /// The command line's backend, over the scene's `backend` parameter.
    pub backend: BackendArgs,
    pub open_discovery: bool,
    /// A managed (lifecycle) node: it comes up unconfigured and publishes only while active.
    pub managed: bool,
    /// Stop after this long (tests, benchmarks); run until Ctrl-C when `None`.
    pub run_for: Option<Duration>,
    /// Stops the node when set (benchmarks and tests that run it in-process); without it
    /// Ctrl-C does.
    pub stop: Option<Arc<AtomicBool>>,
}

/// Runs the node until Ctrl-C (or `run_for`); the recording is closed properly either way.
pub fn run(settings: NodeSettings) -> Result<(), NodeError> {
    let names = TopicNames { namespace: settings.ros.namespace.clone(), remaps: settings.ros.remaps.clone() };
    let topics = Topics { names: &names };
    let mut node = DefvolNode::open(&settings, &topics)?;
    let stop = stop_flag(&settings);
    let started = Instant::now();
    let mut next_tick = Instant::now();
    let mut demand = Demand::NONE;
    let mut ticks: u64 = 0;
    while !stop.load(Ordering::SeqCst) && settings.run_for.is_none_or(|limit| started.elapsed() < limit) {
        let inputs = node.tick(&settings, &topics, &mut demand, ticks)?;
        ticks += 1;
        // Real time: one tick per solver step; with nothing to step and nothing coming in
        // (asleep, or a managed node not active), poll gently.
        let period = node.period();
        next_tick += if node.idle() && inputs == 0 { period.max(Duration::from_millis(20)) } else { period };
        let now = Instant::now();
        if next_tick > now {
            std::thread::sleep(next_tick - now);
        } else if now - next_tick > period * 5 {
            next_tick = now;
        }
    }
    node.close()
}

/// Set by SIGINT, SIGTERM or SIGHUP (what Ctrl-C, docker, systemd and `ros2 launch` send),
/// or the caller's own flag. The first signal shuts down as Ctrl-C does (the recording
/// finalised); a second exits at once.
fn stop_flag(settings: &NodeSettings) -> Arc<AtomicBool> {
    if let Some(stop) = &settings.stop {
        return stop.clone();
    }
    let stop = Arc::new(AtomicBool::new(false));
    let stop_flag = stop.clone();
    let handler = move || {
        if stop_flag.swap(true, Ordering::SeqCst) {
            tracing::warn!("a second stop signal: exiting now, without closing the recording");
            std::process::exit(130);
        }
        tracing::info!("stop signal (SIGINT, SIGTERM or SIGHUP): shutting down; a second one exits at once");
    };
    if let Err(e) = ctrlc::set_handler(handler) {
        tracing::warn!("no stop-signal handler ({e}): a signal ends the node without closing the recording");
    }
    stop
}

/// The node's DDS side, alive from start to exit: the participant, the node, its parameters.
struct RosNode {
    /// Kept past the node: its participant must outlive every entity the node made.
    context: ros2_client::Context,
    /// Says when the spinner thread has let go of the node.
    spinner_stopped: std::sync::mpsc::Receiver<()>,
    node: Node,
    parameters: Parameters,
    parameter_services: ParameterServices,
}

impl RosNode {
    /// The participant (loopback-only unless opened) and the node with `declared` parameters.
    fn open(
        settings: &NodeSettings,
        declared: BTreeMap<String, Value>,
        allowed: AllowedDirs,
    ) -> Result<Self, NodeError> {
        let (domain, discovery) = dds::settings(|name| std::env::var(name).ok(), settings.open_discovery)?;
        let context = dds::context(domain, discovery)?;
        tracing::info!(
            "DDS domain {domain}, discovery {}",
            if discovery == Discovery::Localhost { "on 127.0.0.1 only" } else { "open to the subnet" }
        );
        let node_name = NodeName::new(&settings.ros.namespace, &settings.ros.node_name)
            .map_err(|e| NodeError::Ros(format!("node name: {e:?}")))?;
        // Served by `ParameterServices`, which describe each parameter fully.
        let options = ros2_client::NodeOptions::new().enable_rosout(true).start_parameter_services(false);
        let (options, parameters) = Parameters::declare(options, declared, allowed);
        let mut node = context.new_node(node_name, options).map_err(|e| NodeError::Ros(format!("node: {e:?}")))?;
        let parameter_services = ParameterServices::create(&mut node)?;
        let spinner = node.spinner().map_err(ros_err("spinner"))?;
        let (spinner_done, spinner_stopped) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            if let Err(e) = futures::executor::block_on(spinner.spin()) {
                tracing::error!("ROS 2 spinner stopped: {e:?}");
            }
            let _ = spinner_done.send(());
        });
        Ok(Self { context, spinner_stopped, node, parameters, parameter_services })
    }

    /// Servers before the node that made them, and the node (with its rosout) before the
    /// participant: an entity dropped after the participant has no one to remove it and
    /// DDS logs an error for each at shutdown.
    fn close(self) {
        let Self { context, spinner_stopped, node, parameters, parameter_services } = self;
        drop(parameter_services);
        drop(parameters);
        drop(node);
        // Dropping the node stops its spinner.
        let _ = spinner_stopped.recv_timeout(Duration::from_secs(2));
        drop(context);
    }
}

/// The running node: its DDS side, the lifecycle when managed, and the configured part.
struct DefvolNode {
    ros: RosNode,
    managed: Option<Managed>,
    configured: Option<Configured>,
    /// Configures so far: a managed node configured again records to a new file.
    configures: u32,
    /// Where files named over the wire must lie.
    allowed: AllowedDirs,
}

impl DefvolNode {
    /// An always-active node loads the scene and makes its entities at once; a managed one
    /// waits, unconfigured, for `configure`.
    fn open(settings: &NodeSettings, topics: &Topics<'_>) -> Result<Self, NodeError> {
        let scene = args::scene_from_parameters(&settings.ros.parameters)?;
        let pipeline = if settings.managed { None } else { Some(load(scene.clone(), settings)?) };
        let allowed = allowed_dirs(&settings.ros.parameters)?;
        let mut declared = declared_parameters(pipeline.as_ref().map_or(&scene, Pipeline::scene), settings);
        let dirs = allowed.dirs().iter().map(|dir| Value::String(dir.display().to_string())).collect();
        declared.insert(ALLOWED_DIRS_PARAMETER.into(), Value::Sequence(dirs));
        let mut ros = RosNode::open(settings, declared, allowed.clone())?;
        let managed = if settings.managed { Some(Managed::create(&mut ros.node)?) } else { None };
        let (record, number) = unused_record(&settings.record, 0);
        let configured = pipeline.map(|p| Configured::wire(p, &mut ros.node, topics, &record, true)).transpose()?;
        match &configured {
            Some(c) => {
                let poses: Vec<String> =
                    c.pipeline.tool_topics().iter().map(|(pose, _)| topics.resolve(pose)).collect();
                tracing::info!("node {} up: tools on {}", ros.node.fully_qualified_name(), poses.join(", "));
            }
            None => tracing::info!(
                "node {} up, unconfigured: a managed node, brought up through ~/change_state",
                ros.node.fully_qualified_name()
            ),
        }
        let configures = if configured.is_some() { number + 1 } else { 0 };
        Ok(Self { ros, managed, configured, configures, allowed })
    }

    fn active(&self) -> bool {
        self.configured.is_some() && self.managed.as_ref().is_none_or(Managed::is_active)
    }

    /// The solver's step when configured.
    fn period(&self) -> Duration {
        self.configured
            .as_ref()
            .map_or(Duration::from_millis(20), |c| Duration::from_secs_f64(c.pipeline.scene().solver.dt))
    }

    fn idle(&self) -> bool {
        !self.active() || self.configured.as_ref().is_some_and(|c| c.pipeline.asleep())
    }

    /// One pass: parameter and lifecycle requests, the configured part's services, then
    /// (active) a tick of the pipeline, published and recorded; the inputs' count.
    fn tick(
        &mut self,
        settings: &NodeSettings,
        topics: &Topics<'_>,
        demand: &mut Demand,
        ticks: u64,
    ) -> Result<usize, NodeError> {
        self.ros.parameter_services.serve(&self.ros.node, &self.ros.parameters);
        if let Some(managed) = self.managed.as_mut() {
            let (ros, configured, configures) = (&mut self.ros, &mut self.configured, &mut self.configures);
            managed.serve(|work| transition(work, settings, topics, ros, configured, configures));
        }
        let active = self.active();
        let Some(c) = self.configured.as_mut() else {
            self.ros.parameters.absorb();
            self.ros.parameter_services.settle(&BTreeMap::new());
            return Ok(0);
        };
        let inputs = c.record_events(active);
        if let Some(state) = c.feedback.latest() {
            c.pipeline.follow(state);
        }
        let served = c.serve(&self.allowed);
        let (changed, refused) = self.ros.parameters.apply(&mut c.pipeline, &self.ros.node);
        self.ros.parameter_services.settle(&refused);
        if !changed.physics.is_empty() || served {
            c.rewire(&mut self.ros.node, topics)?;
        } else {
            c.take_change(&changed);
        }
        if active {
            // Who listens decides what runs (checked at 10 Hz: discovery changes slowly).
            if ticks.is_multiple_of(10) {
                *demand = c.demand(&self.ros.node);
            }
            c.publish(demand);
        }
        Ok(inputs)
    }

    /// The force loop stops first, then every entity goes, then the recording is closed.
    fn close(self) -> Result<(), NodeError> {
        let Self { ros, managed, configured, .. } = self;
        let session = configured.map(Configured::release);
        drop(managed);
        ros.close();
        if let Some(session) = session {
            session.finish()?;
        }
        Ok(())
    }
}

/// The recording's files, numbered from `n` past any that exist, saying so when renamed.
fn unused_record(record: &RecordOptions, n: u32) -> (RecordOptions, u32) {
    let (unused, number) = record.unused_from(n);
    if number > 0 {
        if let (Some(asked), Some(used)) = (&record.mcap, &unused.mcap) {
            tracing::warn!("{} exists: recording to {} instead", asked.display(), used.display());
        }
    }
    (unused, number)
}

/// The folders files named over the wire must lie in: `files.allowed_dirs` as given (a list
/// or one path), else the defaults; logged, so that a refusal is no surprise.
fn allowed_dirs(parameters: &BTreeMap<String, Value>) -> Result<AllowedDirs, NodeError> {
    let given: Option<Vec<std::path::PathBuf>> = match parameters.get(ALLOWED_DIRS_PARAMETER) {
        None => None,
        Some(Value::String(dir)) => Some(vec![dir.into()]),
        Some(Value::Sequence(dirs)) => Some(
            dirs.iter()
                .map(|dir| dir.as_str().map(std::path::PathBuf::from))
                .collect::<Option<_>>()
                .ok_or_else(|| NodeError::Refused(format!("`{ALLOWED_DIRS_PARAMETER}`: a list of folders")))?,
        ),
        Some(_) => return Err(NodeError::Refused(format!("`{ALLOWED_DIRS_PARAMETER}`: a list of folders"))),
    };
    let scene_file = parameters.get("scene_file").and_then(Value::as_str).filter(|s| !s.is_empty());
    let allowed =
        AllowedDirs::new(given.unwrap_or_else(|| AllowedDirs::default_dirs(scene_file.map(std::path::Path::new))));
    let dirs: Vec<String> = allowed.dirs().iter().map(|dir| dir.display().to_string()).collect();
    tracing::info!("files named over the wire: only inside {}", dirs.join(", "));
    Ok(allowed)
}

/// The pipeline of `scene` on the run's backend (the command line's over the scene's).
fn load(scene: Scene, settings: &NodeSettings) -> Result<Pipeline, NodeError> {
    let backend = scene.backend(&settings.backend)?;
    Ok(Pipeline::new(scene, &backend, InputLimits::default(), FrameMode::Background)?)
}

/// A managed node's transition callbacks (rclcpp's `on_configure`, `on_activate`, …):
/// configure loads the scene the parameters describe and makes the entities, activate and
/// deactivate start and stop the outputs, cleanup and shutdown free it all and close the
/// recording. A scene that does not load fails configure and changes nothing.
fn transition(
    work: Work,
    settings: &NodeSettings,
    topics: &Topics<'_>,
    ros: &mut RosNode,
    configured: &mut Option<Configured>,
    configures: &mut u32,
) -> Outcome {
    match work {
        Work::Configure => {
            let loaded = ros.parameters.scene().and_then(|scene| load(scene, settings).map_err(|e| e.to_string()));
            let pipeline = match loaded {
                Ok(pipeline) => pipeline,
                Err(e) => return Outcome::Failure(format!("configure: {e}")),
            };
            let (record, number) = unused_record(&settings.record, *configures);
            match Configured::wire(pipeline, &mut ros.node, topics, &record, false) {
                Ok(c) => {
                    *configured = Some(c);
                    *configures = number + 1;
                    Outcome::Success
                }
                Err(e) => Outcome::Error(format!("configure: {e}")),
            }
        }
        Work::Activate | Work::Deactivate => {
            if let Some(c) = configured {
                c.set_active(work == Work::Activate);
            }
            Outcome::Success
        }
        Work::Cleanup | Work::Shutdown | Work::ErrorProcessing => {
            let finished = configured.take().map(Configured::release).map(Session::finish);
            match finished {
                Some(Err(e)) => Outcome::Error(format!("closing the recording: {e}")),
                Some(Ok(())) | None => Outcome::Success,
            }
        }
    }
}

/// Every scene field of `scene`, the command line's values over them, and the node's own.
fn declared_parameters(scene: &Scene, settings: &NodeSettings) -> BTreeMap<String, Value> {
    let mut declared = crate::scene::descriptors::flat(scene);
    for (name, value) in &settings.ros.parameters {
        let value = match (declared.get(name), value) {
            // `-p solver.dt:=1` means 1.0: a real number of the scene stays a double.
            (Some(Value::Number(scene)), Value::Number(given)) if scene.is_f64() && !given.is_f64() => {
                given.as_f64().map_or_else(|| value.clone(), Value::from)
            }
            _ => value.clone(),
        };
        declared.insert(name.clone(), value);
    }
    // The command line's choices are the ones in force.
    if let Some(choice) = settings.backend.backend {
        declared.insert("backend".into(), Value::String(choice.name().into()));
    }
    if settings.backend.allow_software_gpu {
        declared.insert("allow_software_gpu".into(), Value::Bool(true));
    }
    declared.extend(node_parameters(settings));
    declared
}

/// How the recording splits and flushes: the options, else the `record.*` parameters.
fn bag_options(cli: &NodeCli, parameters: &BTreeMap<String, Value>) -> Result<BagOptions, NodeError> {
    let number = |name: &str| parameters.get(name).and_then(Value::as_f64).filter(|v| *v > 0.0);
    let seconds = |given: Option<f64>, name: &str| -> Result<Option<Duration>, NodeError> {
        match given.or_else(|| number(name)) {
            Some(s) if s.is_finite() && s > 0.0 => Ok(Some(Duration::from_secs_f64(s))),
            Some(s) => Err(NodeError::Ros(format!("`{name}` = {s}: a positive number of seconds"))),
            None => Ok(None),
        }
    };
    let defaults = BagOptions::default();
    Ok(BagOptions {
        max_duration: seconds(cli.max_bag_duration, "record.max_bag_duration")?,
        max_bytes: cli.max_bag_size.or_else(|| number("record.max_bag_size").map(|b| b as u64)).filter(|b| *b > 0),
        flush_interval: seconds(cli.flush_interval, "record.flush_interval")?.unwrap_or(defaults.flush_interval),
    })
}

/// The node's own parameters as they stand (`ros2 param list` shows them; each is
/// read-only: the command line and the start decide them).
fn node_parameters(settings: &NodeSettings) -> BTreeMap<String, Value> {
    let path =
        |p: &Option<std::path::PathBuf>| Value::String(p.as_ref().map(|p| p.display().to_string()).unwrap_or_default());
    let scene_file = settings.ros.parameters.get("scene_file").cloned().unwrap_or_else(|| Value::String(String::new()));
    let bag = &settings.record.bag;
    BTreeMap::from([
        ("scene_file".to_owned(), scene_file),
        ("record".to_owned(), path(&settings.record.mcap)),
        ("rerun".to_owned(), path(&settings.record.rerun_file)),
        ("dds.open_discovery".to_owned(), Value::Bool(settings.open_discovery)),
        ("lifecycle.managed".to_owned(), Value::Bool(settings.managed)),
        ("record.max_bag_duration".to_owned(), Value::from(bag.max_duration.map_or(0.0, |d| d.as_secs_f64()))),
        (
            "record.max_bag_size".to_owned(),
            Value::from(bag.max_bytes.map_or(0, |b| i64::try_from(b).unwrap_or(i64::MAX))),
        ),
        ("record.flush_interval".to_owned(), Value::from(bag.flush_interval.as_secs_f64())),
    ])
}

/// The node's own options, outside `--ros-args` (each also a node parameter).
#[derive(Debug, clap::Parser)]
#[command(
    name = "defvol_node",
    about = "The defvol ROS 2 node: tool poses in; deformed meshes, warped volumes, DPCM surfaces and raycast images out",
    after_help = "ROS arguments follow the options: --ros-args [-p NAME:=VALUE]... [-r FROM:=TO]... \
                  [--params-file FILE] [-r __ns:=/NAMESPACE] [-r __node:=NAME]. Every scene field is a \
                  parameter (`-p solver.dt:=0.005`, `-p scene_file:=organ.yaml`); `ros2 param list` shows them."
)]
struct NodeCli {
    /// Record every input and output topic: to this MCAP file (`x.mcap`), or to a rosbag2
    /// bag directory (`DIR/DIR_0.mcap`, … and `metadata.yaml`) for any other path.
    #[arg(long)]
    record: Option<std::path::PathBuf>,
    /// Start a new split of the bag directory once one spans this many seconds.
    #[arg(long, value_name = "SECONDS")]
    max_bag_duration: Option<f64>,
    /// Start a new split of the bag directory once one holds this many bytes.
    #[arg(long, value_name = "BYTES")]
    max_bag_size: Option<u64>,
    /// Write the open chunk out at least this often, in seconds (what a crash may lose).
    #[arg(long, value_name = "SECONDS")]
    flush_interval: Option<f64>,
    /// Log the session to this rerun file (.rrd).
    #[arg(long)]
    rerun: Option<std::path::PathBuf>,
    /// Stream the session to a running rerun viewer (e.g. rerun+http://127.0.0.1:9876/proxy).
    #[arg(long)]
    rerun_connect: Option<String>,
    #[command(flatten)]
    backend: BackendArgs,
    /// Let DDS discovery reach other hosts (as ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET does).
    #[arg(long)]
    open_discovery: bool,
    /// A managed (lifecycle) node, as rclcpp's LifecycleNode: it comes up unconfigured and is
    /// configured, activated, deactivated, cleaned up and shut down through ~/change_state.
    #[arg(long)]
    managed: bool,
    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long)]
    seconds: Option<f64>,
}

/// The node from a command line (`defvol_node …`, `defvol node …`): `--help` prints the
/// node's options and returns; otherwise the node runs until Ctrl-C or `--seconds`.
pub fn run_from_args(args: &[String]) -> Result<(), NodeError> {
    match settings_from_args(args) {
        Err(NodeError::Help(text)) => {
            print!("{text}");
            Ok(())
        }
        settings => run(settings?),
    }
}

/// Every command-line parameter against its descriptor, then the scene they make together,
/// before anything is built: a refusal in rclcpp's words (as its `declare_parameter` throws
/// at start-up), not after the pipeline was made.
fn refuse_bad_parameters(parameters: &BTreeMap<String, Value>) -> Result<(), NodeError> {
    for (name, value) in parameters {
        if let Some(reason) = crate::scene::descriptors::describe(name).and_then(|d| d.refuses(name, value, false)) {
            return Err(NodeError::Refused(format!("parameter '{name}' could not be set: {reason}")));
        }
    }
    args::check_scene(parameters)
        .map(|_| ())
        .map_err(|reason| NodeError::Refused(format!("the parameters make no scene: {reason}")))
}

/// Settings from a command line: the node's options, then `--ros-args …`; node
/// parameters (`-p record:=…`, `-p backend:=cpu`) fill what the options leave unset.
pub fn settings_from_args(args: &[String]) -> Result<NodeSettings, NodeError> {
    use clap::Parser as _;
    let ros = RosArgs::parse(args, "defvol")?;
    let mut argv = vec!["defvol_node".to_owned()];
    argv.extend(ros.rest.iter().cloned());
    let cli = NodeCli::try_parse_from(argv).map_err(|e| match e.kind() {
        clap::error::ErrorKind::DisplayHelp | clap::error::ErrorKind::DisplayVersion => NodeError::Help(e.to_string()),
        _ => NodeError::Ros(e.to_string()),
    })?;
    let text = |name: &str| match ros.parameters.get(name) {
        Some(Value::String(s)) if !s.is_empty() => Some(s.clone()),
        _ => None,
    };
    let flag = |name: &str| ros.parameters.get(name).and_then(Value::as_bool).unwrap_or(false);
    let run_for = match cli.seconds {
        Some(s) if s.is_finite() && s > 0.0 => Some(Duration::from_secs_f64(s)),
        Some(s) => return Err(NodeError::Ros(format!("--seconds {s} must be positive"))),
        None => None,
    };
    refuse_bad_parameters(&ros.parameters)?;
    let bag = bag_options(&cli, &ros.parameters)?;
    Ok(NodeSettings {
        record: RecordOptions {
            mcap: cli.record.or_else(|| text("record").map(Into::into)),
            rerun_file: cli.rerun.or_else(|| text("rerun").map(Into::into)),
            rerun_connect: cli.rerun_connect,
            bag,
        },
        backend: cli.backend,
        open_discovery: cli.open_discovery || flag("dds.open_discovery"),
        managed: cli.managed || flag("lifecycle.managed"),
        run_for,
        stop: None,
        ros,
    })
}
