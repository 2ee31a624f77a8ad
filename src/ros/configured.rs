//! A configured node's part: the pipeline with the topics, services, force loop, shared
//! volumes and recording it feeds. An always-active node makes it at start; a managed one
//! at `configure`, and frees it at `cleanup`.

use std::sync::Arc;
use std::time::Duration;

use ros2_client::{Node, Publisher, Server};

use super::error::NodeError;
use super::feedback_thread::{Command, Event, FeedbackIo, FeedbackThread, ToolSubscriptions};
use super::socket_buffers;
use super::wire::{answer, Topics};
use crate::msgs::{
    DeformedMesh, DiagnosticArray, Image, LoadSceneRequest, Marker, Message, Time, TriggerRequest, TriggerResponse,
    WarpedVolumeInfo, WrenchStamped,
};
use crate::pipeline::{Demand, Outputs, Pipeline};
use crate::record::Qos;
use crate::scene::{check_scene_size, named_file, AllowedDirs, Expect, Scene, SceneChange};
use crate::session::{topics, RecordOptions, Session};

struct Publishers {
    mesh: (String, Publisher<DeformedMesh>),
    marker: (String, Publisher<Marker>),
    raycast: (String, Publisher<Image>),
    dpcm_height: (String, Publisher<Image>),
    dpcm_image: (String, Publisher<Image>),
    warped_info: (String, Publisher<WarpedVolumeInfo>),
    diagnostics: (String, Publisher<DiagnosticArray>),
}

struct Services {
    reset: Server<TriggerRequest, TriggerResponse>,
    pause: Server<TriggerRequest, TriggerResponse>,
    resume: Server<TriggerRequest, TriggerResponse>,
    load: Server<LoadSceneRequest, TriggerResponse>,
}

/// The pipeline and everything it feeds.
pub(super) struct Configured {
    pub pipeline: Pipeline,
    publishers: Publishers,
    services: Services,
    pub feedback: FeedbackThread,
    session: Session,
    #[cfg(feature = "shm")]
    shm: Option<Arc<crate::shm::WarpedVolumePublisher>>,
}

impl Configured {
    /// The pipeline's topics, services and force loop on `node`, its shared volumes and its
    /// recording; a managed node's start `active` = false, publishing nothing.
    pub fn wire(
        mut pipeline: Pipeline,
        node: &mut Node,
        topics: &Topics<'_>,
        record: &RecordOptions,
        active: bool,
    ) -> Result<Self, NodeError> {
        let publishers = Publishers {
            mesh: topics.publisher(node, topics::DEFORMED_MESH, Qos::Latched)?,
            marker: topics.publisher(node, topics::SURFACE_MARKER, Qos::Latched)?,
            raycast: topics.publisher(node, topics::RAYCAST_IMAGE, Qos::SensorData)?,
            dpcm_height: topics.publisher(node, topics::DPCM_HEIGHT, Qos::SensorData)?,
            dpcm_image: topics.publisher(node, topics::DPCM_IMAGE, Qos::SensorData)?,
            warped_info: topics.publisher(node, topics::WARPED_VOLUME_INFO, Qos::Latched)?,
            diagnostics: topics.publisher(node, topics::DIAGNOSTICS, Qos::Reliable)?,
        };
        let io = FeedbackIo {
            tools: subscribe_tools(topics, node, &pipeline)?,
            feedback: feedback_publishers(topics, node, &pipeline)?,
        };
        let period = Duration::from_secs_f64(pipeline.scene().solver.dt);
        let feedback = FeedbackThread::spawn(pipeline.detach_feedback(), io, period, active)?;
        if !active {
            pipeline.pause();
        }
        let services = Services {
            reset: topics.server(node, "reset", "std_srvs", "Trigger")?,
            pause: topics.server(node, "pause", "std_srvs", "Trigger")?,
            resume: topics.server(node, "resume", "std_srvs", "Trigger")?,
            load: topics.server(node, "load_scene", "defvol_interfaces", "LoadScene")?,
        };
        #[cfg(feature = "shm")]
        let shm = shm_publisher(&mut pipeline);
        let session = Session::open(topics.names, record, &pipeline)?;
        socket_buffers::warn_if_too_small(&pipeline.message_bytes());
        Ok(Self {
            pipeline,
            publishers,
            services,
            feedback,
            session,
            #[cfg(feature = "shm")]
            shm,
        })
    }

    /// A managed node's activation (the simulation runs on, outputs flow) or deactivation
    /// (it holds its state, outputs stop).
    pub fn set_active(&mut self, active: bool) {
        if active {
            self.pipeline.resume();
            self.feedback.send(Command::Activate);
        } else {
            self.pipeline.pause();
            self.feedback.send(Command::Deactivate);
        }
    }

    /// Records the feedback thread's inputs and feedback, off its path, when `active`; the
    /// inputs' count.
    pub fn record_events(&mut self, active: bool) -> usize {
        let mut inputs = 0;
        while let Ok(event) = self.feedback.events.try_recv() {
            match event {
                Event::Failed(e) => tracing::error!("step failed: {e}; paused (call reset or load_scene)"),
                // An inactive node records nothing.
                _ if !active => {}
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
            }
        }
        inputs
    }

    /// Answers the services (a scene to load confined to `allowed`); true when one
    /// reloaded the scene.
    pub fn serve(&mut self, allowed: &AllowedDirs) -> bool {
        let pipeline = &mut self.pipeline;
        let mut was_reset = false;
        answer(&self.services.reset, |_| {
            let outcome = pipeline.reset();
            was_reset = outcome.is_ok();
            result(outcome.map(|()| "reset to the rest state".into()).map_err(|e| e.to_string()))
        });
        if was_reset {
            self.feedback.send(Command::Replace { feedback: Box::new(pipeline.detach_feedback()), io: None });
        }
        let mut told = Vec::new();
        answer(&self.services.pause, |_| {
            pipeline.pause();
            told.push(Command::Pause);
            result(Ok("paused".into()))
        });
        answer(&self.services.resume, |_| {
            pipeline.resume();
            told.push(Command::Resume);
            result(Ok("running".into()))
        });
        for command in told {
            self.feedback.send(command);
        }
        let mut reloaded = false;
        answer(&self.services.load, |request| {
            let loaded = scene_of(&request.scene, allowed, pipeline.scene())
                .and_then(|scene| pipeline.load_scene(scene).map_err(|e| e.to_string()));
            reloaded = loaded.is_ok();
            result(loaded.map(|()| "scene loaded".into()).map_err(|e| format!("kept the running scene: {e}")))
        });
        reloaded
    }

    /// After a reload: the new scene's tool topics, a new feedback loop, a new volume sink.
    pub fn rewire(&mut self, node: &mut Node, topics: &Topics<'_>) -> Result<(), NodeError> {
        socket_buffers::warn_if_too_small(&self.pipeline.message_bytes());
        let io = FeedbackIo {
            tools: subscribe_tools(topics, node, &self.pipeline)?,
            feedback: feedback_publishers(topics, node, &self.pipeline)?,
        };
        self.feedback.send(Command::Replace { feedback: Box::new(self.pipeline.detach_feedback()), io: Some(io) });
        #[cfg(feature = "shm")]
        self.reshare();
        Ok(())
    }

    /// After a change that left the simulation running: the force loop's new input checks,
    /// and the outputs' buffers and shared volumes when the stages were rebuilt.
    pub fn take_change(&mut self, change: &SceneChange) {
        if change.checks {
            let (frame_id, limits) = self.pipeline.input_checks();
            self.feedback.send(Command::Checks { frame_id, limits });
        }
        if change.outputs {
            socket_buffers::warn_if_too_small(&self.pipeline.message_bytes());
        }
        #[cfg(feature = "shm")]
        if change.warp {
            self.reshare();
        }
    }

    /// A new shared-volume publisher for the warp as it now is (none without one).
    #[cfg(feature = "shm")]
    fn reshare(&mut self) {
        // The old publisher goes first: the service allows one.
        self.pipeline.set_volume_sink(None);
        drop(self.shm.take());
        self.shm = shm_publisher(&mut self.pipeline);
    }

    /// The outputs someone listens to (a subscriber or the recording).
    pub fn demand(&self, node: &Node) -> Demand {
        let recorded = self.session.recording();
        #[cfg(feature = "shm")]
        let shm_listens = self.shm.as_ref().is_some_and(|s| crate::pipeline::VolumeSink::has_subscribers(s.as_ref()));
        #[cfg(not(feature = "shm"))]
        let shm_listens = false;
        let p = &self.publishers;
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
    pub fn publish(&mut self, demand: &Demand) {
        let stamp = Time::now();
        match self.pipeline.tick(stamp, demand) {
            Ok(mut out) => {
                self.session.record_outputs(&out, &self.pipeline, stamp);
                if let Some(diagnostics) = out.diagnostics.as_mut() {
                    self.session.report_failure(diagnostics);
                }
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

    /// Stops the force loop and drops every entity; the recording is handed back, to be
    /// finished once the node's own entities are gone too.
    pub fn release(self) -> Session {
        let Self { feedback, publishers, services, session, .. } = self;
        drop(feedback);
        drop(publishers);
        drop(services);
        session
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

fn publish<T: Message + std::fmt::Debug>(publisher: &(String, Publisher<T>), msg: Option<T>) {
    let Some(msg) = msg else { return };
    if let Err(e) = publisher.1.publish(msg) {
        tracing::debug!("{}: not sent ({e:?})", publisher.0);
    }
}

/// A scene from a `load_scene` request: a file path inside the `allowed` directories, or
/// YAML text (several lines, or one with `{` or `: `) whose files are either the `running`
/// scene's or inside them. Which one a request is never depends on what exists.
fn scene_of(text: &str, allowed: &AllowedDirs, running: &Scene) -> Result<Scene, String> {
    check_scene_size(text.len()).map_err(|why| format!("load_scene request: {why}"))?;
    let line = text.trim();
    if !line.contains('\n') && !line.starts_with('{') && !line.contains(": ") {
        let path = allowed.admit(std::path::Path::new(text.trim()), Expect::File)?;
        return Scene::from_file(&path).map_err(|e| e.to_string());
    }
    let scene = Scene::parse(text, "load_scene request").map_err(|e| e.to_string())?;
    let known = running.named_files();
    for (parameter, path) in scene.named_files() {
        if !known.contains(&(parameter, path.clone())) {
            let expect = named_file(parameter, &path).unwrap_or(Expect::File);
            allowed.admit(std::path::Path::new(&path), expect).map_err(|why| format!("{parameter}: {why}"))?;
        }
    }
    Ok(scene)
}
