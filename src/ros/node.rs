//! The ROS 2 node: tool poses and wrenches in, the pipeline's outputs out, parameters and
//! services served, the session recorded. All computing is in [`crate::pipeline`]; this
//! file only moves messages.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use ros2_client::{
    MessageTypeName, Name, Node, NodeName, Publisher, QosProfile, Server, ServiceMapping, ServiceTypeName, Subscription,
};
use serde_yaml_ng::Value;

use super::args::{self, RosArgs};
use super::dds::{self, Discovery};
use super::error::{ros_err, NodeError};
use super::feedback_thread::{Command, Event, FeedbackIo, FeedbackThread, ToolSubscriptions};
use super::parameters::{ParameterServices, Parameters};
use crate::msgs::{
    DeformedMesh, DiagnosticArray, Image, LoadSceneRequest, Marker, Message, PoseStamped, Time, TriggerRequest,
    TriggerResponse, WarpedVolumeInfo, WrenchStamped,
};
use crate::pipeline::inputs::InputLimits;
use crate::pipeline::{Demand, FrameMode, Outputs, Pipeline};
use crate::record::Qos;
use crate::scene::BackendArgs;
use crate::scene::Scene;
use crate::session::{topics, RecordOptions, Session, TopicNames};

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
    LoadSceneRequest
);

/// How the node runs, beside its scene.
#[derive(Debug, Clone)]
pub struct NodeSettings {
    pub ros: RosArgs,
    pub record: RecordOptions,
    /// The command line's backend, over the scene's `backend` parameter.
    pub backend: BackendArgs,
    pub open_discovery: bool,
    /// Stop after this long (tests, benchmarks); run until Ctrl-C when `None`.
    pub run_for: Option<Duration>,
    /// Stops the node when set (benchmarks and tests that run it in-process); without it
    /// Ctrl-C does.
    pub stop: Option<Arc<AtomicBool>>,
}

fn type_name<T: Message>() -> MessageTypeName {
    let mut parts = T::NAME.split('/');
    let (package, name) = (parts.next().unwrap_or_default(), parts.next_back().unwrap_or_default());
    MessageTypeName::new(package, name)
}

/// The QoS profiles of the node's topics (inputs: sensor data, so that both reliable and
/// best-effort publishers connect; reliable writers never wait on a slow reader).
pub fn qos(kind: Qos) -> QosProfile {
    use ros2_client::qos::{Durability, History, Reliability, WhenFull};
    let base = QosProfile::subscription_default();
    match kind {
        Qos::SensorData => base.history(History::KeepLast { depth: 5 }),
        Qos::Reliable => base
            .reliability(Reliability::Reliable { when_full: WhenFull::Fail })
            .history(History::KeepLast { depth: 10 }),
        Qos::Latched => base
            .reliability(Reliability::Reliable { when_full: WhenFull::Fail })
            .durability(Durability::TransientLocal)
            .history(History::KeepLast { depth: 1 }),
    }
}

struct Topics<'a> {
    names: &'a TopicNames,
}

impl Topics<'_> {
    /// The fully qualified name of a relative topic, remaps applied.
    fn resolve(&self, topic: &str) -> String {
        self.names.resolve(topic)
    }

    fn publisher<T: Message + ros2_client::Message>(
        &self,
        node: &mut Node,
        topic: &str,
        kind: Qos,
    ) -> Result<(String, Publisher<T>), NodeError> {
        let full = self.resolve(topic);
        let name = Name::parse(&full).map_err(|e| NodeError::Ros(format!("topic {full}: {e:?}")))?;
        let t = node.create_topic(&name, type_name::<T>(), &qos(kind)).map_err(ros_err(&full))?;
        let publisher = node.create_publisher(&t, Some(qos(kind))).map_err(ros_err(&full))?;
        Ok((full, publisher))
    }

    fn subscription<T: Message + ros2_client::Message + 'static>(
        &self,
        node: &mut Node,
        topic: &str,
    ) -> Result<(String, Subscription<T>), NodeError> {
        let full = self.resolve(topic);
        let name = Name::parse(&full).map_err(|e| NodeError::Ros(format!("topic {full}: {e:?}")))?;
        let t = node.create_topic(&name, type_name::<T>(), &qos(Qos::SensorData)).map_err(ros_err(&full))?;
        // Sensor-data QoS, but a deep queue: 1 kHz trackers send several poses per tick, and
        // every one is checked and recorded.
        let deep = qos(Qos::SensorData).history(ros2_client::qos::History::KeepLast { depth: 64 });
        let subscription = node.create_subscription(&t, Some(deep)).map_err(ros_err(&full))?;
        Ok((full, subscription))
    }

    fn server<Req: ros2_client::Message + Clone + 'static, Resp: ros2_client::Message + 'static>(
        &self,
        node: &mut Node,
        service: &str,
        package: &str,
        ty: &str,
    ) -> Result<Server<Req, Resp>, NodeError> {
        let full = self.resolve(service);
        let name = Name::parse(&full).map_err(|e| NodeError::Ros(format!("service {full}: {e:?}")))?;
        let q = qos(Qos::Reliable);
        node.create_server(ServiceMapping::Enhanced, &name, &ServiceTypeName::new(package, ty), q.clone(), q)
            .map_err(ros_err(&full))
    }
}

struct Publishers {
    mesh: (String, Publisher<DeformedMesh>),
    marker: (String, Publisher<Marker>),
    raycast: (String, Publisher<Image>),
    dpcm_height: (String, Publisher<Image>),
    dpcm_image: (String, Publisher<Image>),
    warped_info: (String, Publisher<WarpedVolumeInfo>),
    diagnostics: (String, Publisher<DiagnosticArray>),
}

/// Runs the node until Ctrl-C (or `run_for`); the recording is closed properly either way.
pub fn run(settings: NodeSettings) -> Result<(), NodeError> {
    let names = TopicNames { namespace: settings.ros.namespace.clone(), remaps: settings.ros.remaps.clone() };
    let topics = Topics { names: &names };
    let mut node = DefvolNode::open(&settings, &topics)?;
    let stop = stop_flag(&settings);
    let period = Duration::from_secs_f64(node.pipeline.scene().solver.dt);
    let started = Instant::now();
    let mut next_tick = Instant::now();
    let mut demand = Demand::NONE;
    let mut ticks: u64 = 0;
    while !stop.load(Ordering::SeqCst) && settings.run_for.is_none_or(|limit| started.elapsed() < limit) {
        let inputs = node.record_events();
        if let Some(state) = node.feedback.latest() {
            node.pipeline.follow(state);
        }
        if node.serve() {
            node.rewire(&topics)?;
        }
        // Who listens decides what runs (checked at 10 Hz: discovery changes slowly).
        if ticks.is_multiple_of(10) {
            demand = node.demand();
        }
        ticks += 1;
        node.publish(&demand);
        // Real time: one tick per solver step; asleep with nothing coming in, poll gently.
        next_tick += if node.pipeline.asleep() && inputs == 0 { period.max(Duration::from_millis(20)) } else { period };
        let now = Instant::now();
        if next_tick > now {
            std::thread::sleep(next_tick - now);
        } else if now - next_tick > period * 5 {
            next_tick = now;
        }
    }
    node.close()
}

/// Set by Ctrl-C, or the caller's own flag.
fn stop_flag(settings: &NodeSettings) -> Arc<AtomicBool> {
    if let Some(stop) = &settings.stop {
        return stop.clone();
    }
    let stop = Arc::new(AtomicBool::new(false));
    let stop_flag = stop.clone();
    if let Err(e) = ctrlc::set_handler(move || stop_flag.store(true, Ordering::SeqCst)) {
        tracing::warn!("no Ctrl-C handler ({e}); stop the node with SIGTERM");
    }
    stop
}

struct Services {
    reset: Server<TriggerRequest, TriggerResponse>,
    pause: Server<TriggerRequest, TriggerResponse>,
    resume: Server<TriggerRequest, TriggerResponse>,
    load: Server<LoadSceneRequest, TriggerResponse>,
}

/// The running node: the pipeline, its ROS 2 entities, the feedback thread and the session.
struct DefvolNode {
    pipeline: Pipeline,
    /// Kept past the node: its participant must outlive every entity the node made.
    context: ros2_client::Context,
    /// Says when the spinner thread has let go of the node's parameter services.
    spinner_stopped: std::sync::mpsc::Receiver<()>,
    node: Node,
    publishers: Publishers,
    services: Services,
    parameters: Parameters,
    parameter_services: ParameterServices,
    feedback: FeedbackThread,
    session: Session,
    #[cfg(feature = "shm")]
    shm: Option<Arc<crate::shm::WarpedVolumePublisher>>,
}

impl DefvolNode {
    /// The scene from the parameters, the pipeline on the run's backend, the DDS node with
    /// its parameters, topics and services, the feedback thread and the recording.
    fn open(settings: &NodeSettings, topics: &Topics<'_>) -> Result<Self, NodeError> {
        let scene = args::scene_from_parameters(&settings.ros.parameters)?;
        // Chosen once per run: a reloaded scene keeps it.
        let backend = scene.backend(&settings.backend)?;
        let mut pipeline = Pipeline::new(scene, &backend, InputLimits::default(), FrameMode::Background)?;

        let (domain, discovery) = dds::settings(|name| std::env::var(name).ok(), settings.open_discovery)?;
        let context = dds::context(domain, discovery)?;
        tracing::info!(
            "DDS domain {domain}, discovery {}",
            if discovery == Discovery::Localhost { "on 127.0.0.1 only" } else { "open to the subnet" }
        );
        let node_name = NodeName::new(&settings.ros.namespace, &settings.ros.node_name)
            .map_err(|e| NodeError::Ros(format!("node name: {e:?}")))?;

        // Every scene field is a declared parameter; a change is checked, then reloads the scene.
        let mut declared = args::scene_parameters(pipeline.scene());
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
        // Served by `ParameterServices`, which describe each parameter fully.
        let options = ros2_client::NodeOptions::new().enable_rosout(true).start_parameter_services(false);
        let (options, parameters) = Parameters::declare(options, declared);
        let mut node = context.new_node(node_name, options).map_err(|e| NodeError::Ros(format!("node: {e:?}")))?;
        let parameter_services = ParameterServices::create(&mut node)?;
        let spinner = node.spinner().map_err(ros_err("spinner"))?;
        let (spinner_done, spinner_stopped) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            if let Err(e) = futures::executor::block_on(spinner.spin()) {
                tracing::error!("ROS 2 spinner stopped: {e:?}");
            }
            // spin() consumed the spinner: its parameter services are dropped by now.
            let _ = spinner_done.send(());
        });

        let publishers = Publishers {
            mesh: topics.publisher(&mut node, topics::DEFORMED_MESH, Qos::Reliable)?,
            marker: topics.publisher(&mut node, topics::SURFACE_MARKER, Qos::Reliable)?,
            raycast: topics.publisher(&mut node, topics::RAYCAST_IMAGE, Qos::SensorData)?,
            dpcm_height: topics.publisher(&mut node, topics::DPCM_HEIGHT, Qos::SensorData)?,
            dpcm_image: topics.publisher(&mut node, topics::DPCM_IMAGE, Qos::SensorData)?,
            warped_info: topics.publisher(&mut node, topics::WARPED_VOLUME_INFO, Qos::Latched)?,
            diagnostics: topics.publisher(&mut node, topics::DIAGNOSTICS, Qos::Reliable)?,
        };
        let io = FeedbackIo {
            tools: subscribe_tools(topics, &mut node, &pipeline)?,
            feedback: feedback_publishers(topics, &mut node, &pipeline)?,
        };
        let period = Duration::from_secs_f64(pipeline.scene().solver.dt);
        let feedback = FeedbackThread::spawn(pipeline.detach_feedback(), io, period)?;
        let services = Services {
            reset: topics.server(&mut node, "reset", "std_srvs", "Trigger")?,
            pause: topics.server(&mut node, "pause", "std_srvs", "Trigger")?,
            resume: topics.server(&mut node, "resume", "std_srvs", "Trigger")?,
            load: topics.server(&mut node, "load_scene", "defvol", "LoadScene")?,
        };

        #[cfg(feature = "shm")]
        let shm = shm_publisher(&mut pipeline);
        let session = Session::open(topics.names, &settings.record, &pipeline)?;
        let poses: Vec<String> = pipeline.tool_topics().iter().map(|(pose, _)| topics.resolve(pose)).collect();
        tracing::info!("node {} up: tools on {}", node.fully_qualified_name(), poses.join(", "));
        Ok(Self {
            pipeline,
            context,
            spinner_stopped,
            node,
            publishers,
            services,
            parameters,
            parameter_services,
            feedback,
            session,
            #[cfg(feature = "shm")]
            shm,
        })
    }

    /// Records the feedback thread's inputs and feedback, off its path; the inputs' count.
    fn record_events(&mut self) -> usize {
        let mut inputs = 0;
        while let Ok(event) = self.feedback.events.try_recv() {
            match event {
                Event::Pose { topic, msg, tool } => {
                    inputs += 1;
                    let tool = tool.and_then(|(index, pose)| {
                        self.pipeline.scene().tools.get(index).map(|t| (t.name.as_str(), pose))
                    });
                    self.session.record_pose(&topic, &msg, tool);
                }
                Event::Wrench { topic, msg } => {
                    inputs += 1;
                    self.session.record_wrench(&topic, &msg);
                }
                Event::Feedback { stamp, msgs } => {
                    let out = Outputs { tool_feedback: msgs, ..Default::default() };
                    self.session.record_outputs(&out, &self.pipeline, stamp);
                }
                Event::LocalFeedback { stamp, index, msg } => {
                    if let Some(topic) = self.pipeline.feedback_topics().get(index) {
                        self.session.record_feedback(topic, &msg, stamp);
                    }
                }
                Event::Failed(e) => tracing::error!("step failed: {e}; paused (call reset or load_scene)"),
            }
        }
        inputs
    }

    /// Answers the services and applies parameter changes; true when the scene was reloaded.
    fn serve(&mut self) -> bool {
        let pipeline = &mut self.pipeline;
        let mut was_reset = false;
        serve(&self.services.reset, |_| {
            let outcome = pipeline.reset();
            was_reset = outcome.is_ok();
            result(outcome.map(|()| "reset to the rest state".into()).map_err(|e| e.to_string()))
        });
        if was_reset {
            self.feedback.send(Command::Replace { feedback: Box::new(pipeline.detach_feedback()), io: None });
        }
        let mut told = Vec::new();
        serve(&self.services.pause, |_| {
            pipeline.pause();
            told.push(Command::Pause);
            result(Ok("paused".into()))
        });
        serve(&self.services.resume, |_| {
            pipeline.resume();
            told.push(Command::Resume);
            result(Ok("running".into()))
        });
        for command in told {
            self.feedback.send(command);
        }
        let mut reloaded = false;
        serve(&self.services.load, |request| {
            let loaded =
                scene_of(&request.scene).and_then(|scene| pipeline.load_scene(scene).map_err(|e| e.to_string()));
            reloaded = loaded.is_ok();
            result(loaded.map(|()| "scene loaded".into()).map_err(|e| format!("kept the running scene: {e}")))
        });
        self.parameter_services.serve(&self.node, &self.parameters);
        let changed = self.parameters.apply(pipeline);
        reloaded || changed
    }

    /// After a reload: the new scene's tool topics, a new feedback loop, a new volume sink.
    fn rewire(&mut self, topics: &Topics<'_>) -> Result<(), NodeError> {
        let io = FeedbackIo {
            tools: subscribe_tools(topics, &mut self.node, &self.pipeline)?,
            feedback: feedback_publishers(topics, &mut self.node, &self.pipeline)?,
        };
        self.feedback.send(Command::Replace { feedback: Box::new(self.pipeline.detach_feedback()), io: Some(io) });
        #[cfg(feature = "shm")]
        {
            // The old publisher goes first: the service allows one.
            self.pipeline.set_volume_sink(None);
            drop(self.shm.take());
            self.shm = shm_publisher(&mut self.pipeline);
        }
        Ok(())
    }

    /// The outputs someone listens to (a subscriber or the recording).
    fn demand(&self) -> Demand {
        let recorded = self.session.recording();
        #[cfg(feature = "shm")]
        let shm_listens = self.shm.as_ref().is_some_and(|s| crate::pipeline::VolumeSink::has_subscribers(s.as_ref()));
        #[cfg(not(feature = "shm"))]
        let shm_listens = false;
        let (node, p) = (&self.node, &self.publishers);
        Demand {
            // Published by the feedback thread.
            tool_feedback: false,
            deformed_mesh: recorded || listened(node, &p.mesh),
            surface_marker: recorded || listened(node, &p.marker),
            raycast: recorded || listened(node, &p.raycast),
            dpcm_height: recorded || listened(node, &p.dpcm_height),
            dpcm_image: recorded || listened(node, &p.dpcm_image),
            warped_volume: recorded || shm_listens || listened(node, &p.warped_info),
            diagnostics: true,
        }
    }

    /// One tick of the pipeline, its outputs recorded and published.
    fn publish(&mut self, demand: &Demand) {
        let stamp = Time::now();
        match self.pipeline.tick(stamp, demand) {
            Ok(out) => {
                self.session.record_outputs(&out, &self.pipeline, stamp);
                let info = out.warped_volume.then(|| crate::session::warped_info(&self.pipeline, stamp)).flatten();
                let p = &self.publishers;
                publish(&p.mesh, out.deformed_mesh);
                publish(&p.marker, out.surface_marker);
                publish(&p.raycast, out.raycast);
                publish(&p.dpcm_height, out.dpcm_height);
                publish(&p.dpcm_image, out.dpcm_image);
                publish(&p.warped_info, info);
                publish(&p.diagnostics, out.diagnostics);
            }
            // A failed step (a diverging solver, say) is reported; the node stays up and
            // can be reset or given another scene.
            Err(e) => {
                tracing::error!("step failed: {e}; pausing (call reset or load_scene)");
                self.pipeline.pause();
                self.feedback.send(Command::Pause);
            }
        }
    }

    /// The feedback thread stops first; dropping the node stops its spinner; the
    /// recording is closed.
    fn close(self) -> Result<(), NodeError> {
        let Self {
            feedback,
            context,
            spinner_stopped,
            node,
            session,
            publishers,
            services,
            parameters,
            parameter_services,
            ..
        } = self;
        drop(feedback);
        // Writers and servers go before the node that made them, and the node (with its own
        // parameter services and rosout) before the participant: an entity dropped after the
        // participant has no one to remove it and DDS logs an error for each at shutdown.
        drop(publishers);
        drop(services);
        drop(parameter_services);
        drop(parameters);
        drop(node);
        // Dropping the node stops its spinner, whose thread then drops the parameter services.
        let _ = spinner_stopped.recv_timeout(std::time::Duration::from_secs(2));
        drop(context);
        session.finish()?;
        Ok(())
    }
}

/// The warped-volume publisher, handed to the pipeline as its volume sink (the warp writes
/// into its samples). Without one (no room in /dev/shm, the service taken by another node)
/// the node runs on, saying why once: `warped_volume/info` still comes.
#[cfg(feature = "shm")]
fn shm_publisher(pipeline: &mut Pipeline) -> Option<Arc<crate::shm::WarpedVolumePublisher>> {
    let grid = pipeline.warped_grid()?;
    let service = pipeline.scene().warp.service.clone();
    match crate::shm::WarpedVolumePublisher::new(&service, grid) {
        Ok(publisher) => {
            let publisher = Arc::new(publisher);
            pipeline.set_volume_sink(Some(publisher.clone()));
            Some(publisher)
        }
        Err(e) => {
            tracing::error!("{e}; warped volumes are not shared (another node on `{service}`? give each its own `-p warp.service:=…`)");
            None
        }
    }
}

/// The node's own parameters as they stand (`ros2 param list` shows them; each is
/// read-only: the command line and the start decide them).
fn node_parameters(settings: &NodeSettings) -> BTreeMap<String, Value> {
    let path =
        |p: &Option<std::path::PathBuf>| Value::String(p.as_ref().map(|p| p.display().to_string()).unwrap_or_default());
    let scene_file = settings.ros.parameters.get("scene_file").cloned().unwrap_or_else(|| Value::String(String::new()));
    BTreeMap::from([
        ("scene_file".to_owned(), scene_file),
        ("record".to_owned(), path(&settings.record.mcap)),
        ("rerun".to_owned(), path(&settings.record.rerun_file)),
        ("dds.open_discovery".to_owned(), Value::Bool(settings.open_discovery)),
    ])
}

/// One `tool_feedback` publisher per tool (`<tool>/tool_feedback` after the first).
fn feedback_publishers(
    topics: &Topics<'_>,
    node: &mut Node,
    pipeline: &Pipeline,
) -> Result<Vec<(String, Publisher<WrenchStamped>)>, NodeError> {
    pipeline.feedback_topics().iter().map(|topic| topics.publisher(node, topic, Qos::SensorData)).collect()
}

fn subscribe_tools(
    topics: &Topics<'_>,
    node: &mut Node,
    pipeline: &Pipeline,
) -> Result<Vec<ToolSubscriptions>, NodeError> {
    pipeline
        .tool_topics()
        .into_iter()
        .map(|(pose_topic, wrench_topic)| {
            let (_, pose) = topics.subscription(node, &pose_topic)?;
            let (_, wrench) = topics.subscription(node, &wrench_topic)?;
            Ok(ToolSubscriptions { pose_topic, wrench_topic, pose, wrench })
        })
        .collect()
}

fn listened<T: serde::Serialize>(node: &Node, publisher: &(String, Publisher<T>)) -> bool {
    node.subscription_count(&publisher.0) > 0
}

fn result(outcome: Result<String, String>) -> TriggerResponse {
    match outcome {
        Ok(message) => TriggerResponse { success: true, message },
        Err(message) => {
            tracing::error!("{message}");
            TriggerResponse { success: false, message }
        }
    }
}

fn serve<Req: ros2_client::Message + Clone + 'static>(
    server: &Server<Req, TriggerResponse>,
    mut handle: impl FnMut(Req) -> TriggerResponse,
) {
    while let Ok(Some((id, request))) = server.receive_request() {
        if let Err(e) = server.send_response(id, handle(request)) {
            tracing::warn!("service reply not sent: {e:?}");
        }
    }
}

fn publish<T: Message + std::fmt::Debug>(publisher: &(String, Publisher<T>), msg: Option<T>) {
    let Some(msg) = msg else { return };
    if let Err(e) = publisher.1.publish(msg) {
        tracing::debug!("{}: not sent ({e:?})", publisher.0);
    }
}

/// A scene from a `load_scene` request: a file path, or YAML text.
fn scene_of(text: &str) -> Result<Scene, String> {
    let path = std::path::Path::new(text.trim());
    if !text.contains('\n') && path.exists() {
        return Scene::from_file(path).map_err(|e| e.to_string());
    }
    Scene::parse(text, "load_scene request").map_err(|e| e.to_string())
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
    /// Record every input and output topic to this MCAP file (rosbag2's format).
    #[arg(long)]
    record: Option<std::path::PathBuf>,
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
    Ok(NodeSettings {
        record: RecordOptions {
            mcap: cli.record.or_else(|| text("record").map(Into::into)),
            rerun_file: cli.rerun.or_else(|| text("rerun").map(Into::into)),
            rerun_connect: cli.rerun_connect,
        },
        backend: cli.backend,
        open_discovery: cli.open_discovery || flag("dds.open_discovery"),
        run_for,
        stop: None,
        ros,
    })
}
