//! The node's work without ROS: tool inputs in, a solver step, then the stages whose
//! outputs someone wants (the deformed mesh, the warped volume, the DPCM surface, raycast
//! images, diagnostics), as messages. The node, `demo` and `replay` all drive this.

mod diagnostics;
mod error;
mod feedback;
mod frames;
pub mod inputs;
mod outputs;

pub use error::PipelineError;
pub mod priority;
pub use feedback::{run_step, FeedbackLoop, LoopState, StepInput, StepOutput, Stepped};
pub use frames::{FrameMode, VolumeSink, WarpedVolume, WriteVolume};

use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Point3, Vector3};

use crate::backend::{Backend, RunsOn};
use crate::dpcm::engine::DpcmEngine;
use crate::dpcm::markers::Calibration;
use crate::dpcm::DpcmConfig;
use crate::mesh::TetMesh;
use crate::msgs::{DeformedMesh, DiagnosticArray, Image, Marker, PoseStamped, Time, WrenchStamped};
use crate::render::camera::{Camera, Projection};
use crate::render::engine::{MeshRenderer, VolumeRenderer};
use crate::render::mesh::source::SourceSampling;
use crate::render::mesh::{TetRaycastParams, TetRaycaster};
use crate::render::transfer::TransferFunction;
use crate::render::volume::{RaycastParams, ToolPicture, VolumeRaycaster};
use crate::scene::{CameraShows, LoadedScene, Scene, SceneChange};
use crate::solver::{SolverEngine, StepReport};
use crate::volume::{Grid, Volume};
use crate::warp::engine::WarpEngine;
use crate::warp::WarpOptions;
use inputs::{InputCounters, InputLimits, Rejection};

/// Which outputs have a consumer (a subscriber or a recorder): the rest are not computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Demand {
    pub deformed_mesh: bool,
    pub surface_marker: bool,
    pub tool_feedback: bool,
    pub warped_volume: bool,
    pub dpcm_height: bool,
    pub dpcm_image: bool,
    pub raycast: bool,
    pub diagnostics: bool,
}

impl Demand {
    pub const ALL: Demand = Demand {
        deformed_mesh: true,
        surface_marker: true,
        tool_feedback: true,
        warped_volume: true,
        dpcm_height: true,
        dpcm_image: true,
        raycast: true,
        diagnostics: true,
    };
    pub const NONE: Demand = Demand {
        deformed_mesh: false,
        surface_marker: false,
        tool_feedback: false,
        warped_volume: false,
        dpcm_height: false,
        dpcm_image: false,
        raycast: false,
        diagnostics: false,
    };
}

/// What one tick produced; `None` where the output was not wanted or nothing changed.
#[derive(Debug, Clone, Default)]
pub struct Outputs {
    /// Whether the solver stepped (it sleeps while the mesh rests untouched).
    pub stepped: bool,
    /// The reaction on each tool, in the scene's order (topics: [`Pipeline::feedback_topics`]).
    pub tool_feedback: Vec<WrenchStamped>,
    pub deformed_mesh: Option<DeformedMesh>,
    pub surface_marker: Option<Marker>,
    /// A new warped volume is in [`Pipeline::warped_volume`].
    pub warped_volume: bool,
    pub dpcm_height: Option<Image>,
    pub dpcm_image: Option<Image>,
    pub raycast: Option<Image>,
    pub diagnostics: Option<DiagnosticArray>,
}

/// Milliseconds the last run of each stage took.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    pub solver: f64,
    pub warp: f64,
    pub dpcm: f64,
    pub raycast: f64,
}

struct DpcmStage {
    engine: DpcmEngine,
    config: DpcmConfig,
    calibration: Calibration,
    steps_per_tick: usize,
    /// DPCM steps per GPU submission.
    batch: usize,
    last_image_time: f64,
    /// No marker in reach and the surface at rest: steps are skipped, and the last images
    /// repeat once a second for subscribers that join late.
    asleep: bool,
    last_displacement: Vec<f32>,
    last_heights: Vec<f32>,
}

/// Seconds of simulated time between surface markers.
const MARKER_PERIOD: f64 = 0.1;

pub struct Pipeline {
    scene: Scene,
    volume: Arc<Volume>,
    mesh: TetMesh,
    /// The solver and the tools' inputs; in the node, a follower of the loop on its own thread.
    feedback: FeedbackLoop,
    /// A step of the detached loop the next tick makes outputs of.
    followed: Option<Stepped>,
    /// The detached GPU solver's displacements, which the GPU stages read where they are.
    #[cfg(feature = "gpu")]
    device_displacements: Option<wgpu::Buffer>,
    /// The run's backend, chosen once: every stage is built on it, and a reloaded scene
    /// keeps it.
    backend: Backend,
    /// Where warped volumes are published (the node's shared memory), when set.
    sink: Option<Arc<dyn VolumeSink>>,
    limits: InputLimits,
    /// Warp and raycast, when the scene has either.
    frames: Option<frames::Frames>,
    /// The warped volume's grid (known before the first warp: the publisher needs it).
    warp_grid: Option<Grid>,
    mode: FrameMode,
    dpcm: Option<DpcmStage>,
    last_diagnostics: f64,
    /// Each tool's saturated coupling steps at the last `diagnostics`.
    saturated_at_diagnostics: Vec<u64>,
    last_marker: f64,
    times: StageTimes,
    /// Positions after the last step, world units.
    positions: Vec<Vector3<f64>>,
    /// Why the simulation last restarted from rest on a change of its scene.
    last_reset: Option<String>,
}

/// Refuses stage choices that cannot run together.
fn check_stages(scene: &Scene) -> Result<(), PipelineError> {
    if !scene.stages.solver && scene.stages.warp {
        return Err(PipelineError::Invalid(
            "the warp stage follows the solver's mesh: enable stages.solver too".into(),
        ));
    }
    Ok(())
}

impl Pipeline {
    /// Loads the scene and initialises the stages it enables (and only those).
    pub fn new(scene: Scene, backend: &Backend, limits: InputLimits, mode: FrameMode) -> Result<Self, PipelineError> {
        check_stages(&scene)?;
        let mut pipeline = Self::build(scene.load()?, backend, limits, mode)?;
        pipeline.init_stages()?;
        Ok(pipeline)
    }

    /// The scene on the volume already read, the rest as [`Pipeline::new`] builds it.
    fn on_volume(&self, scene: Scene) -> Result<Self, PipelineError> {
        check_stages(&scene)?;
        let mut pipeline =
            Self::build(scene.load_on(self.volume.clone())?, &self.backend, self.limits.clone(), self.mode)?;
        pipeline.init_stages()?;
        Ok(pipeline)
    }

    fn build(
        loaded: LoadedScene,
        backend: &Backend,
        limits: InputLimits,
        mode: FrameMode,
    ) -> Result<Self, PipelineError> {
        let LoadedScene { scene, volume, mesh, model } = loaded;
        let engine = match scene.stages.solver {
            true => {
                let engine = SolverEngine::new(
                    backend,
                    &model,
                    scene.solver.clone(),
                    scene.tools.iter().map(crate::scene::ToolConfig::tool).collect(),
                )?;
                tracing::info!("solver: {} ({} nodes, {} tets)", engine.name(), mesh.nodes().len(), mesh.tets().len());
                Some(engine)
            }
            false => None,
        };
        let positions = engine.as_ref().map_or_else(|| mesh.nodes().to_vec(), SolverEngine::positions);
        let feedback = FeedbackLoop::new(&scene, engine, mesh.nodes().len(), limits.with_scene(&scene.inputs));
        let pipeline = Self {
            scene,
            volume,
            mesh,
            feedback,
            followed: None,
            #[cfg(feature = "gpu")]
            device_displacements: None,
            backend: backend.clone(),
            sink: None,
            limits,
            frames: None,
            warp_grid: None,
            mode,
            dpcm: None,
            last_diagnostics: f64::NEG_INFINITY,
            saturated_at_diagnostics: Vec::new(),
            last_marker: f64::NEG_INFINITY,
            times: StageTimes::default(),
            positions,
            last_reset: None,
        };
        Ok(pipeline)
    }

    fn init_stages(&mut self) -> Result<(), PipelineError> {
        self.init_frames()?;
        self.init_dpcm()
    }

    /// Warp and raycast, as the scene asks.
    fn init_frames(&mut self) -> Result<(), PipelineError> {
        let stages = self.scene.stages;
        self.frames = None;
        self.warp_grid = None;
        let to_file = 1.0 / self.scene.file_to_world;
        let mut rest = self.mesh.clone();
        rest.map_nodes(|p| p * to_file);
        let rest = Arc::new(rest);
        let warp = match stages.warp {
            false => None,
            true => {
                let config = &self.scene.warp;
                if !(config.rate_hz.is_finite()
                    && config.rate_hz > 0.0
                    && config.tolerance.is_finite()
                    && config.tolerance >= 0.0)
                {
                    return Err(PipelineError::Invalid(format!(
                        "warp: rate_hz {} must be > 0 and tolerance {} >= 0",
                        config.rate_hz, config.tolerance
                    )));
                }
                let options =
                    WarpOptions { background: self.volume.range().0, keep_uncovered: true, ..Default::default() };
                let start = Instant::now();
                let engine = WarpEngine::new(
                    &self.backend,
                    self.volume.clone(),
                    rest.clone(),
                    self.volume.grid(),
                    options,
                    to_file,
                    config.tolerance * to_file,
                )?;
                self.times.warp = start.elapsed().as_secs_f64() * 1e3;
                self.warp_grid = Some(engine.grid().clone());
                tracing::info!("warp: {} ({} voxels)", engine.runs_on(), crate::logging::dims(engine.grid().dims));
                Some(frames::WarpSetup { engine, host: None })
            }
        };
        let raycast = match stages.raycast {
            false => None,
            true => {
                let c = &self.scene.camera;
                if !(c.rate_hz.is_finite() && c.rate_hz > 0.0) {
                    return Err(PipelineError::Invalid(format!("camera: rate_hz {} must be > 0", c.rate_hz)));
                }
                let point = |p: [f64; 3]| Point3::from(Vector3::from(p) * to_file);
                let camera = Camera::look_at(
                    point(c.eye),
                    point(c.target),
                    Vector3::from(c.up),
                    Projection::Perspective { fov_y_deg: c.fov_y_deg },
                    c.width,
                    c.height,
                )?;
                let tf = TransferFunction::preset(&c.transfer_function)?;
                // Prepared once here, so that a bad parameter fails at start, not mid-run.
                let picture = match c.shows {
                    CameraShows::Volume => frames::Picture::Volume(self.volume_picture(warp.as_ref(), &tf)?),
                    CameraShows::Mesh => {
                        let outside = self.volume.range().0;
                        let scalars: Vec<f32> =
                            rest.nodes().iter().map(|p| self.volume.sample_world(*p).unwrap_or(outside)).collect();
                        let prepared = TetRaycaster::new(
                            &rest,
                            &scalars,
                            &tf,
                            &TetRaycastParams { step: c.step, ..Default::default() },
                        )?;
                        frames::Picture::Mesh(MeshRenderer::new(&self.backend, prepared, to_file)?)
                    }
                    CameraShows::Source => {
                        let params = RaycastParams { step: c.step, ..Default::default() };
                        let prepared = TetRaycaster::with_source(
                            &rest,
                            self.volume.clone(),
                            &tf,
                            &params,
                            &SourceSampling::default(),
                        )?;
                        frames::Picture::Mesh(MeshRenderer::new(&self.backend, prepared, to_file)?)
                    }
                };
                Some(frames::RaycastSetup { camera, picture })
            }
        };
        if warp.is_some() || raycast.is_some() {
            let worker = frames::FrameWorker {
                warp,
                raycast,
                source: self.volume.clone(),
                rest,
                to_file,
                warped_since_picture: false,
            };
            let frames = frames::Frames::new(worker, self.mode, self.scene.warp.rate_hz, self.scene.camera.rate_hz)?;
            if let Some(backend) = frames.raycast_backend {
                tracing::info!("raycast: {backend}");
            }
            self.frames = Some(frames);
        }
        Ok(())
    }

    /// The DPCM surface, as the scene asks.
    fn init_dpcm(&mut self) -> Result<(), PipelineError> {
        self.dpcm = None;
        if self.scene.stages.dpcm {
            let c = &self.scene.dpcm;
            let mut config = if c.preset.ends_with(".yaml") || c.preset.ends_with(".yml") {
                DpcmConfig::load(std::path::Path::new(&c.preset))?
            } else {
                DpcmConfig::preset(&c.preset)?
            };
            if let Some([w, h]) = c.size {
                (config.width, config.height) = (w, h);
            }
            if let Some(spacing) = c.spacing {
                config.spacing = spacing;
            }
            let engine = DpcmEngine::new(&config, &self.backend)?;
            let steps_per_tick = (self.scene.solver.dt / config.dt).round().max(1.0) as usize;
            let batch = c.batch.unwrap_or(steps_per_tick);
            if batch == 0 {
                return Err(PipelineError::Invalid("dpcm: batch must be at least 1 step".into()));
            }
            let origin = nalgebra::Isometry3::translation(c.origin[0], c.origin[1], c.origin[2]);
            let calibration = Calibration::new(origin, config.spacing);
            tracing::info!(
                "DPCM: {} {}x{}, {} steps per solver step, {} per GPU submission",
                engine.name(),
                config.width,
                config.height,
                steps_per_tick,
                batch
            );
            self.dpcm = Some(DpcmStage {
                engine,
                config,
                calibration,
                steps_per_tick,
                batch,
                last_image_time: f64::NEG_INFINITY,
                asleep: false,
                last_heights: Vec::new(),
                last_displacement: Vec::new(),
            });
        }
        Ok(())
    }

    /// The camera's volume picture: on the GPU it reads the GPU warp's output where it is;
    /// a warp on the CPU (or none) is raycast on the CPU, or its source uploaded once.
    fn volume_picture(
        &self,
        warp: Option<&frames::WarpSetup>,
        tf: &TransferFunction,
    ) -> Result<VolumeRenderer, PipelineError> {
        let c = &self.scene.camera;
        // The shading scale of the source, so that every frame of the warp shades alike.
        let (lo, hi) = self.volume.range();
        let min_spacing = self.volume.spacing().iter().copied().fold(f64::INFINITY, f64::min);
        let params = RaycastParams {
            step: c.step,
            gradient_scale: Some((f64::from(hi - lo) / (4.0 * min_spacing)).max(1e-12)),
            ..Default::default()
        };
        let tables = Arc::new(VolumeRaycaster::tables_for(self.volume.range(), tf, &params)?);
        match warp.map(|w| w.engine.runs_on()) {
            #[cfg(feature = "gpu")]
            Some(RunsOn::Gpu) => {
                let on_device = warp.and_then(|w| w.engine.device_output()).zip(self.backend.context());
                if let Some((samples, ctx)) = on_device {
                    return Ok(VolumeRenderer::on_device(
                        ctx.clone(),
                        samples.clone(),
                        &self.volume,
                        &tables,
                        &params,
                    )?);
                }
                Ok(VolumeRenderer::new(&Backend::cpu(), &self.volume, tables, &params)?)
            }
            Some(_) => Ok(VolumeRenderer::new(&Backend::cpu(), &self.volume, tables, &params)?),
            None => Ok(VolumeRenderer::new(&self.backend, &self.volume, tables, &params)?),
        }
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }
    pub fn mesh(&self) -> &TetMesh {
        &self.mesh
    }
    pub fn positions(&self) -> &[Vector3<f64>] {
        &self.positions
    }
    /// The bytes one message of each large output carries (its arrays), by output name:
    /// what a subscriber's socket must take in one burst.
    pub fn message_bytes(&self) -> Vec<(&'static str, usize)> {
        let (nodes, faces) = (self.mesh.nodes().len(), self.mesh.boundary().len());
        let mut sizes = vec![("deformed_mesh", nodes * 16 + faces * 12)];
        if self.frames.as_ref().is_some_and(|f| f.raycast_backend.is_some()) {
            sizes.push(("raycast/image", self.scene.camera.width * self.scene.camera.height * 4));
        }
        if let Some(d) = &self.dpcm {
            let phyxels = d.config.width * d.config.height;
            sizes.extend([("dpcm/height", phyxels * 4), ("dpcm/image", phyxels * 3)]);
        }
        sizes
    }

    pub fn asleep(&self) -> bool {
        self.feedback.asleep()
    }
    pub fn paused(&self) -> bool {
        self.feedback.paused()
    }
    pub fn counters(&self) -> &InputCounters {
        self.feedback.counters()
    }
    /// The solver's path and device, for logs.
    pub fn backend_name(&self) -> String {
        self.feedback.engine_name().to_owned()
    }
    /// The run's backend.
    pub fn backend(&self) -> &Backend {
        &self.backend
    }
    /// Where each enabled stage runs, as `diagnostics` reports it.
    pub fn stage_backends(&self) -> Vec<(&'static str, RunsOn)> {
        let mut stages = Vec::new();
        if let Some(backend) = self.feedback.engine_backend() {
            stages.push(("solver", backend));
        }
        if let Some(backend) = self.frames.as_ref().and_then(|f| f.warp_backend) {
            stages.push(("warp", backend));
        }
        if let Some(d) = &self.dpcm {
            stages.push(("dpcm", d.engine.runs_on()));
        }
        if let Some(backend) = self.frames.as_ref().and_then(|f| f.raycast_backend) {
            stages.push(("raycast", backend));
        }
        stages
    }
    pub fn last_report(&self) -> Option<&StepReport> {
        self.feedback.last_report()
    }
    pub fn times(&self) -> StageTimes {
        StageTimes { solver: self.feedback.solver_ms(), ..self.times }
    }
    /// The tool on `pose_topic`: its name and `world_from_tool`, as the stages see it.
    pub fn tool_on(&self, pose_topic: &str) -> Option<(&str, nalgebra::Isometry3<f64>)> {
        let (index, pose) = self.feedback.tool_on(pose_topic)?;
        Some((self.scene.tools[index].name.as_str(), pose))
    }

    /// The pose and wrench topics of each tool.
    pub fn tool_topics(&self) -> Vec<(String, String)> {
        self.feedback.tool_topics()
    }

    /// The feedback topic of each tool, in the order of [`Outputs::tool_feedback`].
    pub fn feedback_topics(&self) -> Vec<String> {
        self.feedback.feedback_topics()
    }

    /// Steps in which each tool's coupling held its device back with its largest force.
    pub fn saturated_steps(&self) -> &[u64] {
        self.feedback.saturated_steps()
    }

    /// The latest warped volume (grid in file units, sequence, work), once one is made.
    /// How many take the published volumes now; `None` without a volume sink.
    pub fn volume_subscribers(&self) -> Option<usize> {
        self.sink.as_ref().map(|sink| sink.subscribers())
    }

    pub fn warped_volume(&self) -> Option<&WarpedVolume> {
        self.frames.as_ref().and_then(|f| f.latest.as_ref())
    }

    /// The latest warped volume's samples, when they are kept on the host: in lockstep runs
    /// without a volume sink (the demo, replays, tests). With a sink they are written only
    /// into the memory it lends.
    pub fn warped_samples(&self) -> Option<&[f32]> {
        self.frames.as_ref().and_then(|f| f.host_warped())
    }

    /// Publishes every warped volume someone takes through `sink` (written straight into
    /// the memory it lends); `None` keeps them on the host.
    pub fn set_volume_sink(&mut self, sink: Option<Arc<dyn VolumeSink>>) {
        self.sink = sink;
    }

    /// The grid warped volumes come on, when the scene warps.
    pub fn warped_grid(&self) -> Option<&Grid> {
        self.warp_grid.as_ref()
    }

    /// Pauses the solver (here: a detached loop is told by its owner).
    pub fn pause(&mut self) {
        self.feedback.pause();
    }
    pub fn resume(&mut self) {
        self.feedback.resume();
    }

    /// Back to the rest state: the mesh, the DPCM surface and the tools' input history.
    /// The solver comes back attached: the node detaches it again.
    pub fn reset(&mut self) -> Result<(), PipelineError> {
        // Warp and raycast hold no state of the simulation's: they carry over, and only the
        // simulation and the DPCM surface start again.
        check_stages(&self.scene)?;
        let loaded = self.scene.clone().load_on(self.volume.clone())?;
        let mut replacement = Self::build(loaded, &self.backend, self.limits.clone(), self.mode)?;
        replacement.init_dpcm()?;
        (replacement.frames, replacement.warp_grid) = (self.frames.take(), self.warp_grid.take());
        if let Some(frames) = &mut replacement.frames {
            frames.restart();
        }
        if self.paused() {
            replacement.pause();
        }
        replacement.sink = self.sink.take();
        *self = replacement;
        Ok(())
    }

    /// Applies `scene` doing no more than it needs ([`Scene::change_from`]): the stages after
    /// the solver rebuilt alone and new input checks taken as the simulation runs on; only a
    /// change of the physics rebuilds the simulation from rest, said in the log and in
    /// `diagnostics`. On error the running scene is kept.
    pub fn apply_scene(&mut self, scene: Scene) -> Result<SceneChange, PipelineError> {
        let change = scene.change_from(&self.scene);
        if !change.physics.is_empty() {
            // The volume is read again only when it is another (or scaled otherwise).
            if change.physics.contains(&"volume") || change.physics.contains(&"file_to_world") {
                self.load_scene(scene)?;
            } else {
                let mut replacement = self.on_volume(scene)?;
                replacement.sink = self.sink.take();
                *self = replacement;
            }
            let why = format!("{} changed", change.physics.join(", "));
            tracing::warn!("the simulation restarted from rest: {why}");
            self.last_reset = Some(why);
            return Ok(change);
        }
        let running = std::mem::replace(&mut self.scene, scene);
        if change.outputs {
            if let Err(e) = self.init_stages() {
                self.scene = running;
                self.init_stages()?;
                return Err(e);
            }
        }
        if change.checks {
            self.feedback.set_checks(&self.scene.frame_id, self.limits.with_scene(&self.scene.inputs));
        }
        Ok(change)
    }

    /// The input checks the scene asks for (what [`Pipeline::apply_scene`] gave the loop).
    pub fn input_checks(&self) -> (String, InputLimits) {
        (self.scene.frame_id.clone(), self.limits.with_scene(&self.scene.inputs))
    }

    /// Replaces the scene; on error the running one is kept. The solver comes back
    /// attached: the node detaches it again.
    pub fn load_scene(&mut self, scene: Scene) -> Result<(), PipelineError> {
        let mut replacement = Self::new(scene, &self.backend, self.limits.clone(), self.mode)?;
        replacement.sink = self.sink.take();
        *self = replacement;
        Ok(())
    }

    /// Hands the solver and the tools' inputs to a loop of their own (the node's feedback
    /// thread); from then on [`Pipeline::follow`] brings its steps here.
    pub fn detach_feedback(&mut self) -> FeedbackLoop {
        #[cfg(feature = "gpu")]
        {
            self.device_displacements = self.feedback.engine().and_then(SolverEngine::device_displacements).cloned();
        }
        self.feedback.detach()
    }

    /// Takes the state of the detached loop: its tools, counters and latest step.
    pub fn follow(&mut self, state: LoopState) {
        if self.feedback.follow(&state) {
            self.wake_frames();
        }
        if let Some(stepped) = state.stepped {
            self.followed = Some(stepped);
        }
    }

    /// Applies a tool pose; refused ones are counted and leave the tool where it was.
    pub fn apply_pose(&mut self, topic: &str, msg: &PoseStamped, now: Time) -> Result<(), Rejection> {
        if self.feedback.apply_pose(topic, msg, now)? {
            self.wake_frames();
        }
        Ok(())
    }

    /// Applies a commanded tool force.
    pub fn apply_wrench(&mut self, topic: &str, msg: &WrenchStamped, now: Time) -> Result<(), Rejection> {
        self.feedback.apply_wrench(topic, msg, now)
    }

    /// Moves scripted tools along their paths (the demo); tools without a path stay.
    pub fn follow_scripts(&mut self, t: f64) {
        if self.feedback.follow_scripts(t) {
            self.wake_frames();
        }
    }

    fn wake_frames(&mut self) {
        if let Some(f) = &mut self.frames {
            f.raycast_stale = true;
        }
    }

    /// One solver step (unless paused or asleep, or the solver runs detached: then the step
    /// [`Pipeline::follow`] brought), then every wanted output that changed. `stamp` stamps
    /// the outputs.
    pub fn tick(&mut self, stamp: Time, demand: &Demand) -> Result<Outputs, PipelineError> {
        let mut out = Outputs::default();
        let stepped = match self.followed.take() {
            Some(stepped) => Some(stepped),
            None => self.feedback.step(stamp)?,
        };
        if let Some(stepped) = stepped {
            self.positions = stepped.positions;
            out.stepped = true;
            if demand.tool_feedback {
                out.tool_feedback = stepped.feedback;
            }
            if let Some(f) = &mut self.frames {
                (f.warp_stale, f.raycast_stale) = (true, true);
            }
        } else if demand.tool_feedback {
            // Asleep, the devices still get a force every tick.
            out.tool_feedback = self.feedback.resting_feedback(stamp).unwrap_or_default();
        }
        // Output rates run on the stamps' clock (bag time in replays, wall time live), which
        // goes on while the solver sleeps.
        let clock = stamp.as_secs();
        if out.stepped && demand.deformed_mesh {
            out.deformed_mesh = Some(outputs::deformed_mesh(
                &self.mesh,
                &self.positions,
                self.last_report().map_or(0, |r| r.step),
                stamp,
                &self.scene.frame_id,
            ));
        }
        // The marker repeats every triangle corner (hundreds of kB): 10 Hz is what a viewer needs.
        if out.stepped && demand.surface_marker && clock - self.last_marker >= MARKER_PERIOD - 1e-9 {
            self.last_marker = clock;
            out.surface_marker =
                Some(outputs::surface_marker(&self.mesh, &self.positions, stamp, &self.scene.frame_id));
        }
        let to_file = 1.0 / self.scene.file_to_world;
        if let Some(frames) = &mut self.frames {
            let (positions, rest, tools, scene) =
                (&self.positions, self.mesh.nodes(), self.feedback.tool_states(), &self.scene);
            let host = || -> Vec<Vector3<f64>> { positions.iter().zip(rest).map(|(p, r)| p - r).collect() };
            let deformation = frames::Deformation {
                host: &host,
                #[cfg(feature = "gpu")]
                device: self
                    .feedback
                    .engine()
                    .and_then(SolverEngine::device_displacements)
                    .or(self.device_displacements.as_ref()),
            };
            let done = frames.tick(
                clock,
                stamp,
                demand.warped_volume,
                demand.raycast,
                &deformation,
                self.sink.as_ref(),
                || {
                    tools
                        .iter()
                        .zip(&scene.tools)
                        .take(crate::render::volume::MAX_TOOLS)
                        .map(|(t, c)| {
                            let (a, b) = t.tool.segment();
                            ToolPicture {
                                tip: (a * to_file).into(),
                                tail: (b * to_file).into(),
                                radius: c.shape.radius() * to_file,
                                color: [0.75, 0.78, 0.82],
                            }
                        })
                        .collect()
                },
            )?;
            out.warped_volume = done.warped.is_some();
            out.raycast = done.image;
            self.times.warp = done.warp_ms.unwrap_or(self.times.warp);
            self.times.raycast = done.raycast_ms.unwrap_or(self.times.raycast);
        }
        if demand.dpcm_height || demand.dpcm_image {
            let (height, image) = self.run_dpcm(clock, stamp, demand)?;
            (out.dpcm_height, out.dpcm_image) = (height, image);
        }
        if demand.diagnostics && clock - self.last_diagnostics >= 1.0 - 1e-9 {
            self.last_diagnostics = clock;
            let since: Vec<u64> = (self.saturated_steps().iter().enumerate())
                .map(|(i, now)| now - self.saturated_at_diagnostics.get(i).copied().unwrap_or(0))
                .collect();
            out.diagnostics = Some(self.diagnostics(stamp, &since));
            self.saturated_at_diagnostics = self.saturated_steps().to_vec();
        }
        Ok(out)
    }

    fn run_dpcm(
        &mut self,
        clock: f64,
        stamp: Time,
        demand: &Demand,
    ) -> Result<(Option<Image>, Option<Image>), PipelineError> {
        let Some(d) = &mut self.dpcm else { return Ok((None, None)) };
        if self.feedback.paused() {
            return Ok((None, None));
        }
        // Markers out of reach of the grid are left out (their footprint misses it).
        let reach = d.config.marker.threshold / d.config.spacing;
        let markers: Vec<_> = (self.feedback.tool_states().iter().enumerate())
            .map(|(i, t)| d.calibration.marker(i as u32, Point3::from(t.tool.tip())))
            .filter(|m| {
                m.col >= -reach
                    && m.row >= -reach
                    && m.col <= d.config.width as f64 + reach
                    && m.row <= d.config.height as f64 + reach
                    && m.height.abs() <= d.config.marker.threshold
            })
            .collect();
        if !markers.is_empty() {
            d.asleep = false;
        }
        let period = if d.asleep { 1.0 } else { 1.0 / self.scene.dpcm.rate_hz };
        if !d.asleep {
            let start = Instant::now();
            d.engine.step_many(&markers, d.steps_per_tick, d.batch)?;
            self.times.dpcm = start.elapsed().as_secs_f64() * 1e3;
        }
        if clock - d.last_image_time < period - 1e-9 {
            return Ok((None, None));
        }
        d.last_image_time = clock;
        let (heights, displacement) = if d.asleep {
            (d.last_heights.clone(), d.last_displacement.clone())
        } else {
            d.engine.heights_and_displacement()?
        };
        // At rest when nothing touches it and no phyxel moved a nanometre since the last image.
        let settled = d.last_heights.len() == heights.len()
            && heights.iter().zip(&d.last_heights).all(|(a, b)| (a - b).abs() < 1e-9);
        d.asleep = markers.is_empty() && settled;
        d.last_heights.clone_from(&heights);
        d.last_displacement.clone_from(&displacement);
        let (w, h) = (d.config.width, d.config.height);
        let height = demand.dpcm_height.then(|| outputs::float_image(&heights, w, h, stamp, "dpcm"));
        let image = demand.dpcm_image.then(|| {
            let picture = crate::dpcm::render::colour_map(&displacement, w, h, &d.config.render);
            outputs::rgb_image(picture.rgb, w, h, stamp, "dpcm")
        });
        Ok((height, image))
    }
}

#[cfg(test)]
mod tests {
    use super::feedback::SLEEP_AFTER;
    use super::*;
    use crate::msgs::{Header, Pose};

    /// The default scene, small: 600 tets, solver only unless `stages` says more.
    fn scene(stages: crate::scene::Stages) -> Scene {
        let mut scene = Scene::default_scene().unwrap();
        if let crate::scene::MeshSource::VolumeLattice { target_tets, .. } = &mut scene.mesh {
            *target_tets = 600;
        }
        scene.stages = stages;
        (scene.camera.width, scene.camera.height, scene.camera.step) = (32, 24, 4.0);
        scene.dpcm.size = Some([32, 32]);
        scene
    }

    fn pipeline(scene: Scene) -> Pipeline {
        Pipeline::new(scene, &Backend::cpu(), InputLimits { max_age: None, ..Default::default() }, FrameMode::Lockstep)
            .unwrap()
    }

    /// A camera change rebuilds the picture alone: the simulation runs on from its step and
    /// positions, the next image has the new size; a camera that cannot be built is refused
    /// and the running one kept; a change of the solver's system restarts the simulation from
    /// rest and `diagnostics` say why; `reset` brings the organ back to rest under the same
    /// camera.
    #[test]
    fn a_parameter_rebuilds_only_what_it_touches() {
        let stages = crate::scene::Stages { solver: true, warp: false, dpcm: false, raycast: true };
        let mut p = pipeline(scene(stages));
        for i in 1..=5 {
            p.tick(Time::from_secs(0.01 * f64::from(i)), &Demand::ALL).unwrap();
        }
        let (step, positions) = (p.last_report().unwrap().step, p.positions().to_vec());
        let mut wider = p.scene().clone();
        wider.camera.width = 48;
        let change = p.apply_scene(wider).unwrap();
        assert_eq!(change, SceneChange { physics: vec![], checks: false, outputs: true, warp: false });
        assert_eq!((p.last_report().unwrap().step, p.positions()), (step, &positions[..]));
        let out = p.tick(Time::from_secs(0.06), &Demand::ALL).unwrap();
        assert_eq!((out.raycast.unwrap().width, p.last_report().unwrap().step), (48, step + 1));
        let mut blind = p.scene().clone();
        blind.camera.target = blind.camera.eye;
        assert!(p.apply_scene(blind).is_err());
        assert_eq!(p.scene().camera.width, 48, "the running camera is kept");
        assert!(p.tick(Time::from_secs(0.07), &Demand::ALL).unwrap().raycast.is_some());
        let mut stiffer = p.scene().clone();
        stiffer.solver.dt = 0.005;
        stiffer.frame_id = "map".into();
        let change = p.apply_scene(stiffer).unwrap();
        assert_eq!((change.physics, change.checks), (vec!["solver"], true));
        assert!(p.last_report().is_none(), "restarted from rest");
        let diagnostics = p.diagnostics(Time::from_secs(0.0), &[0]);
        let solver = diagnostics.status.iter().find(|s| s.name == "defvol: solver").unwrap();
        let reset = solver.values.iter().find(|v| v.key == "last_reset").unwrap();
        assert_eq!(reset.value, "restarted from rest: solver changed");
        // `reset` keeps the frames and the volume: the organ is at rest, the camera as it was.
        for i in 1..=3 {
            p.tick(Time::from_secs(0.005 * f64::from(i)), &Demand::ALL).unwrap();
        }
        assert_ne!(p.positions(), p.mesh().nodes());
        p.reset().unwrap();
        assert_eq!((p.positions(), p.scene().camera.width), (p.mesh().nodes(), 48));
        let out = p.tick(Time::from_secs(0.02), &Demand::ALL).unwrap();
        assert_eq!(out.raycast.unwrap().width, 48);
    }

    /// A zero stamp (what `ros2 topic pub` sends) is taken as the time the pose came: the
    /// staleness limit that refuses a pose stamped 5 s ago lets it through, and it moves the
    /// tool; later poses are ordered after that time.
    #[test]
    fn a_zero_stamped_pose_is_taken_as_the_time_it_came() {
        let stages = crate::scene::Stages { solver: true, warp: false, dpcm: false, raycast: false };
        let mut s = scene(stages);
        s.tools[0].path = None;
        let now = Time::from_secs(1.0e9);
        let limits = InputLimits::default();
        let mut p = Pipeline::new(s.clone(), &Backend::cpu(), limits.clone(), FrameMode::Lockstep).unwrap();
        let stale = p.apply_pose("tool_pose", &pose(1.0e9 - 5.0, 0.05), now);
        assert!(matches!(stale, Err(Rejection::Stale { .. })), "{stale:?}");
        let mut p = Pipeline::new(s, &Backend::cpu(), limits, FrameMode::Lockstep).unwrap();
        p.apply_pose("tool_pose", &pose(0.0, 0.05), now).unwrap();
        assert_eq!(p.tool_on("tool_pose").unwrap().1.translation.z, 0.05);
        let earlier = p.apply_pose("tool_pose", &pose(1.0e9 - 0.1, 0.04), now);
        assert!(matches!(earlier, Err(Rejection::OutOfOrder { .. })), "{earlier:?}");
    }

    /// `inputs.max_age` sets how old a stamp may be, 0 accepting any (a device whose clock
    /// is not this host's); replay's unchecked ages stay unchecked whatever the scene says.
    #[test]
    fn the_scene_sets_how_old_an_input_may_be() {
        let stages = crate::scene::Stages { solver: true, warp: false, dpcm: false, raycast: false };
        let now = Time::from_secs(1.0e9);
        let age_of = |max_age: f64, limits: InputLimits, age: f64| {
            let mut s = scene(stages);
            (s.tools[0].path, s.inputs.max_age) = (None, max_age);
            let mut p = Pipeline::new(s, &Backend::cpu(), limits, FrameMode::Lockstep).unwrap();
            p.apply_pose("tool_pose", &pose(1.0e9 - age, 0.05), now)
        };
        let live = InputLimits::default();
        assert!(matches!(age_of(0.5, live.clone(), 1.0), Err(Rejection::Stale { .. })));
        assert!(age_of(2.0, live.clone(), 1.0).is_ok());
        assert!(matches!(age_of(2.0, live.clone(), 3.0), Err(Rejection::Stale { .. })));
        assert!(age_of(0.0, live, 1.0e6).is_ok(), "0: any age");
        assert!(age_of(0.5, InputLimits { max_age: None, ..Default::default() }, 1.0e6).is_ok());
        let mut s = scene(stages);
        s.inputs.max_age = -1.0;
        assert!(s.load().err().unwrap().to_string().contains("inputs.max_age = -1.0 is outside [0, 3600]"));
    }

    fn pose(t: f64, z: f64) -> PoseStamped {
        let mut msg = PoseStamped {
            header: Header { stamp: Time::from_secs(t), frame_id: "world".into() },
            pose: Pose::default(),
        };
        msg.pose.position.z = z;
        msg
    }

    #[test]
    fn disabled_stages_are_never_initialised_and_unwanted_outputs_not_computed() {
        let mut p = pipeline(scene(crate::scene::Stages::default()));
        assert!(p.frames.is_none() && p.dpcm.is_none() && p.warped_grid().is_none());
        let out = p.tick(Time::from_secs(0.01), &Demand::NONE).unwrap();
        assert!(out.stepped, "the solver runs whoever listens: feedback is its product");
        assert!(
            out.tool_feedback.is_empty()
                && out.deformed_mesh.is_none()
                && out.surface_marker.is_none()
                && out.diagnostics.is_none()
        );
        let out = p.tick(Time::from_secs(0.02), &Demand::ALL).unwrap();
        let (mesh, feedback) = (out.deformed_mesh.unwrap(), &out.tool_feedback[0]);
        assert_eq!(mesh.positions.len(), 3 * p.mesh().nodes().len());
        assert_eq!(mesh.triangles.len(), 3 * p.mesh().boundary().len());
        let report = p.last_report().unwrap();
        assert_eq!((mesh.step, feedback.wrench.force.z), (report.step, report.reaction(0).force[2]));
        assert!(
            out.raycast.is_none() && out.dpcm_height.is_none() && !out.warped_volume,
            "disabled stages give nothing"
        );
    }

    #[test]
    fn the_solver_sleeps_at_rest_and_wakes_when_a_tool_moves() {
        let mut s = scene(crate::scene::Stages::default());
        s.solver.gravity = [0.0; 3];
        s.tools[0].path = None;
        let mut p = pipeline(s);
        // The probe starts far above: nothing touches, nothing moves.
        p.apply_pose("tool_pose", &pose(0.0, 0.5), Time::from_secs(0.0)).unwrap();
        let stepped: Vec<bool> =
            (1..=40).map(|k| p.tick(Time::from_secs(k as f64 * 0.01), &Demand::ALL).unwrap().stepped).collect();
        assert_eq!(
            stepped.iter().filter(|s| **s).count(),
            SLEEP_AFTER as usize,
            "asleep after {SLEEP_AFTER} quiet steps"
        );
        assert!(p.asleep());
        // Asleep, a device holding still gets its (zero) force at every tick, stamped with
        // its pose, and the solver does not step.
        p.apply_pose("tool_pose", &pose(0.405, 0.5), Time::from_secs(0.405)).unwrap();
        let out = p.tick(Time::from_secs(0.41), &Demand::ALL).unwrap();
        assert!(!out.stepped && p.asleep());
        let [answer] = &out.tool_feedback[..] else { panic!("one answer: {:?}", out.tool_feedback) };
        assert_eq!(answer.header.stamp, Time::from_secs(0.405));
        assert_eq!((answer.wrench.force.x, answer.wrench.force.y, answer.wrench.force.z), (0.0, 0.0, 0.0));
        // Pressing 5 mm into the top node nearest the centre wakes it, and it stays awake
        // while the tool touches.
        let top = p
            .mesh()
            .nodes()
            .iter()
            .filter(|n| n.z > 0.06)
            .min_by(|a, b| (a.x.hypot(a.y)).total_cmp(&b.x.hypot(b.y)))
            .copied()
            .unwrap();
        let radius = p.scene().tools[0].shape.radius();
        let mut press = pose(0.5, top.z + radius - 0.005);
        (press.pose.position.x, press.pose.position.y) = (top.x, top.y);
        p.apply_pose("tool_pose", &press, Time::from_secs(0.5)).unwrap();
        for k in 0..50 {
            let stepped = p.tick(Time::from_secs(0.5 + k as f64 * 0.01), &Demand::ALL).unwrap().stepped;
            assert!(stepped, "step {k} after the press: {:?}", p.last_report());
        }
        assert!(p.last_report().unwrap().reaction(0).force[2] > 0.5);
        // A refused pose leaves the tool where it was and is counted.
        assert!(p.apply_pose("tool_pose", &pose(1.0, f64::NAN), Time::from_secs(1.0)).is_err());
        assert!(p.apply_pose("elsewhere", &pose(1.0, 0.0), Time::from_secs(1.0)).is_err());
        assert_eq!(p.counters().total_rejected(), 2);
        assert_eq!(p.tool_on("tool_pose").unwrap().1.translation.z, top.z + radius - 0.005);
    }

    /// Poses at 10 kHz into a 1 kHz loop: each step uses the latest pose and answers it
    /// once; the nine before it are coalesced, neither queued for later steps nor refused.
    #[test]
    fn a_pose_stream_faster_than_the_loop_is_coalesced_not_queued() {
        let mut s = scene(crate::scene::Stages::default());
        s.tools[0].path = None;
        s.solver.dt = 1e-3;
        let mut p = pipeline(s);
        for step in 1..=5u32 {
            for k in 0..10u32 {
                let t = f64::from(10 * (step - 1) + k) * 1e-4;
                p.apply_pose("tool_pose", &pose(t, 0.2 - t), Time::from_secs(t)).unwrap();
            }
            let stamp = Time::from_secs(f64::from(step) * 1e-3);
            let out = p.tick(stamp, &Demand::ALL).unwrap();
            let latest = Time::from_secs(f64::from(10 * step - 1) * 1e-4);
            let [answer] = &out.tool_feedback[..] else { panic!("one answer a step: {:?}", out.tool_feedback) };
            assert!(out.stepped && answer.header.stamp == latest, "step {step} answers the latest pose");
            let at = p.tool_on("tool_pose").unwrap().1.translation.z;
            assert!((at - (0.2 - f64::from(10 * step - 1) * 1e-4)).abs() < 1e-12, "step {step} uses it");
        }
        assert_eq!(p.counters().total_rejected(), 0, "none refused");
    }

    /// The node's arrangement: the loop detached and stepped on its own, the pipeline
    /// following its states, against the same run in lockstep.
    #[test]
    fn a_detached_loop_followed_gives_the_lockstep_run_and_echoes_each_pose_stamp() {
        let mut s = scene(crate::scene::Stages::default());
        s.tools[0].path = None;
        let mut lockstep = pipeline(s.clone());
        let mut follower = pipeline(s);
        let mut detached = follower.detach_feedback();
        for k in 1..=40 {
            let stamp = Time::from_secs(k as f64 * 0.01);
            let msg = pose(k as f64 * 0.01 - 0.005, 0.1 - 0.001 * k as f64);
            lockstep.apply_pose("tool_pose", &msg, stamp).unwrap();
            let expected = lockstep.tick(stamp, &Demand::ALL).unwrap();
            detached.apply_pose("tool_pose", &msg, stamp).unwrap();
            let mut stepped = detached.step(stamp).unwrap().unwrap();
            let feedback = std::mem::take(&mut stepped.feedback);
            follower.follow(LoopState { stepped: Some(stepped), ..detached.state() });
            let got = follower.tick(stamp, &Demand::ALL).unwrap();
            assert_eq!(feedback, expected.tool_feedback, "step {k}");
            assert_eq!(feedback[0].header.stamp, msg.header.stamp, "the feedback answers pose {k}");
            assert!(got.tool_feedback.is_empty(), "the loop published it");
            assert_eq!(got.deformed_mesh, expected.deformed_mesh, "step {k}");
        }
        assert!(lockstep.last_report().unwrap().reaction(0).force[2] > 0.1, "the probe pressed the mesh");
        assert_eq!(follower.last_report(), lockstep.last_report());
        assert_eq!(follower.counters(), lockstep.counters());
        assert_eq!(follower.tool_on("tool_pose"), lockstep.tool_on("tool_pose"));
    }

    #[test]
    fn a_teleported_coupled_tool_is_held_back_and_diagnostics_say_so() {
        let mut s = scene(crate::scene::Stages::default());
        s.tools[0].path = None;
        s.tools[0].contact = crate::solver::ContactModel::Surface;
        s.tools[0].coupling =
            Some(crate::solver::Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 5.0 });
        let mut p = pipeline(s);
        let status = |out: &Outputs| {
            let d = out.diagnostics.clone().unwrap();
            d.status.into_iter().find(|s| s.name == "defvol: solver").unwrap()
        };
        p.apply_pose("tool_pose", &pose(0.0, 0.2), Time::from_secs(0.0)).unwrap();
        let first = status(&p.tick(Time::from_secs(0.01), &Demand::ALL).unwrap());
        assert_eq!(first.level, crate::msgs::DiagnosticStatus::OK, "{first:?}");
        // The device jumps through the organ to 0.2 m below it in one message.
        p.apply_pose("tool_pose", &pose(0.02, -0.2), Time::from_secs(0.02)).unwrap();
        let mut last = None;
        for k in 2..=101 {
            let out = p.tick(Time::from_secs(k as f64 * 0.01), &Demand::ALL).unwrap();
            let force = p.last_report().unwrap().reaction(0).force;
            assert!(Vector3::from(force).norm() <= 5.0 + 1e-9, "step {k}: {force:?}");
            if out.diagnostics.is_some() {
                last = Some(status(&out));
            }
        }
        let last = last.unwrap();
        assert_eq!(last.level, crate::msgs::DiagnosticStatus::WARN, "{last:?}");
        assert!(last.message.contains("coupling saturated") && last.message.contains("probe"), "{}", last.message);
        let held = last.values.iter().find(|v| v.key == "coupling_saturated_steps.probe").unwrap();
        assert_eq!(held.value, p.saturated_steps()[0].to_string());
        assert!(p.saturated_steps()[0] >= 90, "held back every step since the jump: {:?}", p.saturated_steps());
    }

    #[test]
    fn warp_and_raycast_run_only_when_something_changed() {
        let stages = crate::scene::Stages { solver: true, warp: true, dpcm: true, raycast: true };
        let mut p = pipeline(scene(stages));
        let first = p.tick(Time::from_secs(0.01), &Demand::ALL).unwrap();
        assert!(first.warped_volume && first.raycast.is_some());
        let warped = p.warped_volume().unwrap();
        assert_eq!((p.warped_samples().unwrap().len(), warped.sequence), (256 * 160 * 122, 1));
        // Within the rate limit nothing is redone.
        let next = p.tick(Time::from_secs(0.02), &Demand::ALL).unwrap();
        assert!(!next.warped_volume && next.raycast.is_none());
        // Paused: no step; the motion of step 2 is warped once when due, then nothing more.
        p.pause();
        let mut paused_warps = 0;
        for k in 3..30 {
            let out = p.tick(Time::from_secs(k as f64 * 0.01), &Demand::ALL).unwrap();
            assert!(!out.stepped);
            paused_warps += usize::from(out.warped_volume);
        }
        assert_eq!(paused_warps, 1);
        p.resume();
        let mut warps = 0;
        for k in 30..60 {
            warps += usize::from(p.tick(Time::from_secs(k as f64 * 0.01), &Demand::ALL).unwrap().warped_volume);
        }
        assert_eq!(warps, 3, "10 Hz of simulated time over 0.3 s");
        // Reset brings the rest state back.
        p.reset().unwrap();
        assert!(p.last_report().is_none() && p.positions() == p.mesh().nodes());
    }

    #[test]
    fn a_source_camera_needs_no_warp_and_shows_what_warp_then_raycast_shows() {
        let stages = crate::scene::Stages { solver: true, warp: false, dpcm: false, raycast: true };
        let mut s = scene(stages);
        s.camera.shows = CameraShows::Source;
        s.tools[0].path = None;
        let mut warped = s.clone();
        (warped.stages.warp, warped.camera.shows) = (true, CameraShows::Volume);
        let mut through_mesh = pipeline(s);
        let mut warp_then_raycast = pipeline(warped);
        assert!(through_mesh.warped_grid().is_none(), "the warp is not built for a source picture");
        let (mut a, mut b) = (None, None);
        for k in 1..=20 {
            let stamp = Time::from_secs(k as f64 * 0.01);
            for p in [&mut through_mesh, &mut warp_then_raycast] {
                p.apply_pose("tool_pose", &pose(k as f64 * 0.01, 5.0), stamp).unwrap();
            }
            a = through_mesh.tick(stamp, &Demand::ALL).unwrap().raycast.or(a);
            b = warp_then_raycast.tick(stamp, &Demand::ALL).unwrap().raycast.or(b);
        }
        assert!(through_mesh.last_report().unwrap().max_displacement > 1e-4, "gravity moved the organ");
        let (a, b) = (a.unwrap(), b.unwrap());
        assert!(a.data.iter().filter(|v| **v > 10).count() > a.data.len() / 20, "the picture shows the organ");
        let mean = a.data.iter().zip(&b.data).map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs()).sum::<f64>()
            / a.data.len() as f64;
        assert!(mean < 2.0, "the source through the mesh and the warped volume differ by {mean:.2} levels");
    }

    #[test]
    fn a_mesh_camera_needs_no_warp_and_shows_the_current_deformation() {
        let stages = crate::scene::Stages { solver: true, warp: false, dpcm: false, raycast: true };
        let mut s = scene(stages);
        s.camera.shows = CameraShows::Mesh;
        // The probe out of the picture (the reference draws no tools), gravity deforming.
        s.tools[0].path = None;
        let mut p = pipeline(s.clone());
        p.apply_pose("tool_pose", &pose(0.0, 5.0), Time::from_secs(0.0)).unwrap();
        assert!(p.warped_grid().is_none(), "the warp is not built for a mesh picture");
        let mut image = None;
        for k in 1..=20 {
            image = p.tick(Time::from_secs(k as f64 * 0.01), &Demand::ALL).unwrap().raycast.or(image);
        }
        let image = image.unwrap();
        // Paused, the next frame shows the positions the f64 reference is given.
        p.pause();
        let frame =
            (21..40).find_map(|k| p.tick(Time::from_secs(k as f64 * 0.01), &Demand::ALL).unwrap().raycast).unwrap();
        assert_eq!(frame.data.len(), image.data.len());
        let to_file = 1.0 / s.file_to_world;
        let mut rest = p.mesh().clone();
        rest.map_nodes(|q| q * to_file);
        let deformed: Vec<Vector3<f64>> = p.positions().iter().map(|q| q * to_file).collect();
        let outside = p.volume.range().0;
        let scalars: Vec<f32> = rest.nodes().iter().map(|q| p.volume.sample_world(*q).unwrap_or(outside)).collect();
        let c = &s.camera;
        let point = |q: [f64; 3]| Point3::from(Vector3::from(q) * to_file);
        let camera = Camera::look_at(
            point(c.eye),
            point(c.target),
            Vector3::from(c.up),
            Projection::Perspective { fov_y_deg: c.fov_y_deg },
            c.width,
            c.height,
        )
        .unwrap();
        let tf = TransferFunction::preset(&c.transfer_function).unwrap();
        let reference = crate::render::mesh::reference(
            &rest,
            &deformed,
            &scalars,
            &camera,
            &tf,
            &TetRaycastParams { step: 0.25, ..Default::default() },
        )
        .unwrap();
        let rendered =
            crate::render::Rendered { width: c.width, height: c.height, rgba: frame.data.clone(), depth: Vec::new() };
        assert!(reference.iter().filter(|q| q[0] > 0.05).count() > c.width * c.height / 10, "the organ is out of view");
        let (mean, max) = rendered.errors(&reference);
        assert!(mean < 0.5 && max < 8.0, "against the f64 reference: mean {mean:.2}, max {max:.1} levels");
        // The organ has sagged visibly: the same reference at rest is further off.
        let at_rest = crate::render::mesh::reference(
            &rest,
            rest.nodes(),
            &scalars,
            &camera,
            &tf,
            &TetRaycastParams { step: 0.25, ..Default::default() },
        )
        .unwrap();
        let (rest_mean, _) = rendered.errors(&at_rest);
        assert!(
            rest_mean > 2.0 * mean,
            "mean error {rest_mean:.2} levels against the rest pose, {mean:.2} against the deformed one"
        );
    }

    #[test]
    fn background_frames_never_hold_the_solver_up() {
        let stages = crate::scene::Stages { solver: true, warp: true, dpcm: false, raycast: true };
        let mut p = Pipeline::new(
            scene(stages),
            &Backend::cpu(),
            InputLimits { max_age: None, ..Default::default() },
            FrameMode::Background,
        )
        .unwrap();
        let first = p.tick(Time::from_secs(0.01), &Demand::ALL).unwrap();
        assert!(
            first.stepped && first.raycast.is_none() && !first.warped_volume,
            "the frame is in flight, not waited for"
        );
        let start = std::time::Instant::now();
        let mut steps_meanwhile = 0;
        let image = loop {
            let out = p.tick(Time::from_secs(0.01), &Demand::ALL).unwrap();
            if let Some(image) = out.raycast {
                assert!(out.warped_volume, "the warp came along with the picture");
                break image;
            }
            steps_meanwhile += usize::from(out.stepped);
            assert!(start.elapsed() < std::time::Duration::from_secs(60), "no frame came back");
        };
        assert!(steps_meanwhile >= 1, "the solver stepped while the frame was made");
        assert_eq!((image.width, image.height), (32, 24));
        assert_eq!(p.warped_volume().unwrap().sequence, 1);
    }

    /// A sink lending three buffers in turn, as shared memory does: each keeps what it was
    /// last written, and the sink says which volume that was.
    #[derive(Default)]
    struct Lender {
        buffers: std::sync::Mutex<Vec<(Vec<f32>, Option<u64>)>>,
        published: std::sync::Mutex<Vec<(u64, usize)>>,
    }

    impl VolumeSink for Lender {
        fn has_subscribers(&self) -> bool {
            true
        }
        fn publish(&self, volume: &WarpedVolume, write: &mut WriteVolume<'_>) -> Result<(), String> {
            let mut buffers = self.buffers.lock().unwrap();
            if buffers.is_empty() {
                // Fresh memory holds anything: NaN shows any sample left unwritten.
                *buffers = (0..3).map(|_| (vec![f32::NAN; volume.grid.len()], None)).collect();
            }
            let mut published = self.published.lock().unwrap();
            let slot = published.len() % 3;
            let (buffer, holds) = &mut buffers[slot];
            write(buffer, *holds)?;
            *holds = Some(volume.sequence);
            published.push((volume.sequence, slot));
            Ok(())
        }
    }

    /// With a sink, the warp writes each published volume into the memory the sink lends
    /// and nowhere else (no host copy is kept), and what lands there is the full warp of the
    /// mesh at that moment, in buffers that held older volumes too.
    #[test]
    fn published_volumes_are_written_only_into_the_lent_memory() {
        let stages = crate::scene::Stages { solver: true, warp: true, dpcm: false, raycast: false };
        let mut s = scene(stages);
        s.tools[0].path = None;
        // Every motion reaches the warp, so the volume is the full warp of the mesh as it is.
        s.warp.tolerance = 0.0;
        let mut p = pipeline(s.clone());
        let lender = Arc::new(Lender::default());
        p.set_volume_sink(Some(lender.clone()));
        let top = p
            .mesh()
            .nodes()
            .iter()
            .filter(|n| n.z > 0.06)
            .min_by(|a, b| (a.x.hypot(a.y)).total_cmp(&b.x.hypot(b.y)))
            .copied()
            .unwrap();
        let to_file = 1.0 / s.file_to_world;
        let mut rest = p.mesh().clone();
        rest.map_nodes(|q| q * to_file);
        let options = WarpOptions { background: p.volume.range().0, keep_uncovered: true, ..Default::default() };
        let mut checked = 0;
        for k in 1..=60 {
            // The probe presses deeper, a node under it: the mesh moves every step.
            let radius = s.tools[0].shape.radius();
            let mut press = pose(k as f64 * 0.01, top.z + radius - 0.0004 * k as f64);
            (press.pose.position.x, press.pose.position.y) = (top.x, top.y);
            p.apply_pose("tool_pose", &press, Time::from_secs(k as f64 * 0.01)).unwrap();
            let demand = Demand { warped_volume: true, ..Demand::NONE };
            let out = p.tick(Time::from_secs(k as f64 * 0.01), &demand).unwrap();
            assert!(p.warped_samples().is_none(), "no host copy is kept beside the lent memory");
            if !out.warped_volume {
                continue;
            }
            let published = lender.published.lock().unwrap();
            let (sequence, slot) = *published.last().unwrap();
            assert_eq!(sequence, p.warped_volume().unwrap().sequence);
            let deformed: Vec<Vector3<f64>> = p.positions().iter().map(|q| q * to_file).collect();
            let (full, _) = crate::warp::warp(&p.volume, &rest, &deformed, p.warped_grid().unwrap(), &options).unwrap();
            let buffers = lender.buffers.lock().unwrap();
            assert!(
                buffers[slot].0.iter().zip(full.data()).all(|(a, b)| a.to_bits() == b.to_bits()),
                "volume {sequence} differs from the full warp"
            );
            checked += 1;
        }
        assert!(checked >= 5, "{checked} volumes published");
        // Diagnostics say who takes the volumes and that the latest went out.
        let report = p.diagnostics(Time::from_secs(1.0), &[]);
        let warp = report.status.iter().find(|s| s.name == "defvol: warp").unwrap();
        let value = |key: &str| warp.values.iter().find(|v| v.key == key).map(|v| v.value.as_str());
        assert_eq!((value("shared_subscribers"), value("shared_published")), (Some("1"), Some("true")));
        let solver = report.status.iter().find(|s| s.name == "defvol: solver").unwrap();
        assert!(solver.values.iter().any(|v| v.key == "inverted_tets" && v.value == "0"), "{solver:?}");
        assert!(
            lender.published.lock().unwrap().iter().skip(3).count() >= 2,
            "buffers came back holding older volumes"
        );
    }

    /// Two tools, each on its own feedback topic with its own reaction.
    #[test]
    fn every_tool_feels_its_own_reaction() {
        let mut s = scene(crate::scene::Stages::default());
        s.solver.gravity = [0.0; 3];
        s.tools[0].path = None;
        let mut needle = s.tools[0].clone();
        needle.name = "needle".into();
        s.tools.push(needle);
        let mut p = pipeline(s);
        assert_eq!(p.feedback_topics(), ["tool_feedback", "needle/tool_feedback"]);
        let top = p
            .mesh()
            .nodes()
            .iter()
            .filter(|n| n.z > 0.06)
            .min_by(|a, b| (a.x.hypot(a.y)).total_cmp(&b.x.hypot(b.y)))
            .copied()
            .unwrap();
        let mut away = pose(0.0, 1.0);
        away.pose.position.x = 0.5;
        p.apply_pose("tool_pose", &away, Time::from_secs(0.0)).unwrap();
        let radius = p.scene().tools[1].shape.radius();
        let mut press = pose(0.0, top.z + radius - 0.005);
        (press.pose.position.x, press.pose.position.y) = (top.x, top.y);
        p.apply_pose("needle/tool_pose", &press, Time::from_secs(0.0)).unwrap();
        let mut out = Outputs::default();
        for k in 1..=40 {
            out = p.tick(Time::from_secs(k as f64 * 0.01), &Demand::ALL).unwrap();
        }
        assert_eq!(out.tool_feedback.len(), 2);
        let report = p.last_report().unwrap();
        for (index, msg) in out.tool_feedback.iter().enumerate() {
            let f = report.reaction(index).force;
            assert_eq!([msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z], f);
        }
        assert!(out.tool_feedback[1].wrench.force.z > 0.5, "the needle presses: {:?}", out.tool_feedback[1]);
        assert_eq!(out.tool_feedback[0].wrench.force.z, 0.0, "the probe is far away");
    }

    /// The node's pipeline on the GPU (every stage) against the same pipeline on the CPU
    /// after a scripted press: the deformed mesh, the warped volume, the raycast image (of
    /// the warped volume, of the mesh, and of the source through the mesh, with no warp
    /// stage) and the DPCM height agree.
    #[cfg(feature = "gpu")]
    #[test]
    fn the_gpu_pipeline_matches_the_cpu_pipeline() {
        let Some(ctx) = crate::gpu::test_context() else { return };
        for shows in [CameraShows::Volume, CameraShows::Mesh, CameraShows::Source] {
            let stages =
                crate::scene::Stages { solver: true, warp: shows == CameraShows::Volume, dpcm: true, raycast: true };
            let mut s = scene(stages);
            s.tools[0].path = None;
            s.camera.shows = shows;
            // Both solvers block Jacobi, converged tightly: the same steps within round-off.
            s.solver.preconditioner = crate::solver::Preconditioner::BlockJacobi;
            s.solver.cg_tolerance = 1e-6;
            // The 32x32 surface at the organ's top (6 cm), which the probe comes down through.
            s.dpcm.origin = [-0.016, -0.016, 0.061];
            let limits = InputLimits { max_age: None, ..Default::default() };
            let mut cpu = Pipeline::new(s.clone(), &Backend::cpu(), limits.clone(), FrameMode::Lockstep).unwrap();
            let mut gpu = Pipeline::new(s, &Backend::gpu(ctx.clone()), limits, FrameMode::Lockstep).unwrap();
            assert!(gpu.stage_backends().iter().all(|(_, b)| *b == RunsOn::Gpu), "{:?}", gpu.stage_backends());
            let top = cpu
                .mesh()
                .nodes()
                .iter()
                .filter(|n| n.z > 0.06)
                .min_by(|a, b| (a.x.hypot(a.y)).total_cmp(&b.x.hypot(b.y)))
                .copied()
                .unwrap();
            let (mut image, mut gpu_image) = (None, None);
            let (mut height, mut gpu_height) = (None, None);
            for k in 1..=30 {
                let stamp = Time::from_secs(k as f64 * 0.01);
                let radius = cpu.scene().tools[0].shape.radius();
                let mut press = pose(k as f64 * 0.01, top.z + radius - 0.0005 * k as f64);
                (press.pose.position.x, press.pose.position.y) = (top.x, top.y);
                for p in [&mut cpu, &mut gpu] {
                    p.apply_pose("tool_pose", &press, stamp).unwrap();
                }
                let a = cpu.tick(stamp, &Demand::ALL).unwrap();
                let b = gpu.tick(stamp, &Demand::ALL).unwrap();
                assert_eq!(
                    (a.raycast.is_some(), a.warped_volume),
                    (b.raycast.is_some(), b.warped_volume),
                    "tick {k}: the same outputs come out"
                );
                image = a.raycast.or(image);
                gpu_image = b.raycast.or(gpu_image);
                height = a.dpcm_height.or(height);
                gpu_height = b.dpcm_height.or(gpu_height);
            }
            let scale = cpu.last_report().unwrap().max_displacement;
            assert!(scale > 1e-3, "the press moved the mesh {scale} m");
            let worst = cpu.positions().iter().zip(gpu.positions()).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
            assert!(worst <= 1e-3 * scale, "{shows:?}: the deformed meshes differ by {worst:e} m of {scale:e} m");
            if shows == CameraShows::Volume {
                let (a, b) = (cpu.warped_samples().unwrap(), gpu.warped_samples().unwrap());
                let (lo, hi) = cpu.volume.range();
                let off = a.iter().zip(b).filter(|(x, y)| (*x - *y).abs() > 1e-3 * (hi - lo)).count();
                assert!(off <= a.len() / 1000, "{off} of {} warped voxels differ", a.len());
            }
            let (a, b) = (image.unwrap(), gpu_image.unwrap());
            let mean = a.data.iter().zip(&b.data).map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs()).sum::<f64>()
                / a.data.len() as f64;
            assert!(
                a.data.iter().filter(|v| **v > 10).count() > a.data.len() / 20,
                "{shows:?}: the picture shows the organ"
            );
            assert!(mean < 1.0, "{shows:?}: the raycast images differ by {mean:.2} levels on average");
            let decode = |m: &Image| {
                m.data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect::<Vec<f32>>()
            };
            let (a, b) = (decode(&height.unwrap()), decode(&gpu_height.unwrap()));
            let peak = a.iter().fold(0.0f32, |m, z| m.max((z - a[0]).abs()));
            let worst = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
            assert!(peak > 1e-5, "the probe engraved the surface ({peak})");
            assert!(worst <= 1e-3 * peak.max(1e-6), "DPCM heights differ by {worst:e} of a peak {peak:e}");
        }
    }
}
