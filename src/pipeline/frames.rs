//! The slow stages, warp and raycast (milliseconds to hundreds of milliseconds a frame), run
//! by a worker beside the solver. Live (`Background`) the solver never waits for them: a
//! frame starts when the last one is done and its results come out in a later tick. Replays
//! and the demo run them in `Lockstep`, inside the tick, so a bag always gives the same
//! frames.
//!
//! On the GPU the deformed nodes never leave the device: when a frame starts, the solver's
//! displacement buffer is placed (a kernel, no read-back) into the warp's and the mesh
//! raycaster's own node buffers; the warp's output stays on the device for the volume
//! raycaster; only the picture and the published volume come back, once, straight into
//! their destinations. A published volume is written into memory the [`VolumeSink`] lends.

use std::sync::mpsc::{self, Receiver, SyncSender, TryRecvError};
use std::sync::Arc;
use std::time::Instant;

use nalgebra::Vector3;

use super::error::PipelineError;
use super::outputs;
use crate::backend::RunsOn;
use crate::mesh::TetMesh;
use crate::msgs::{Image, Time};
use crate::render::camera::Camera;
use crate::render::engine::{MeshRenderer, Shown, VolumeRenderer};
use crate::render::volume::ToolPicture;
use crate::volume::{Grid, Volume};
use crate::warp::engine::WarpEngine;
use crate::warp::WarpStats;

/// Whether frames run inside the tick or beside it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameMode {
    /// Inside the tick: deterministic (demo, replay, tests).
    Lockstep,
    /// On a worker thread with its own threads: the solver keeps its rate (the node).
    Background,
}

/// Writes one volume into memory a [`VolumeSink`] lends, told the sequence of the earlier
/// volume of the run that memory still holds (if the sink knows one).
pub type WriteVolume<'a> = dyn FnMut(&mut [f32], Option<u64>) -> Result<(), String> + 'a;

/// Where warped volumes are published (the node's iceoryx2 service). The warp writes each
/// volume straight into memory the sink lends, so it is never copied on its way out.
pub trait VolumeSink: Send + Sync {
    /// Whether anyone takes the volumes (else the warp is not published).
    fn has_subscribers(&self) -> bool;

    /// How many take them now, for diagnostics (0 or 1 where the sink cannot count them).
    fn subscribers(&self) -> usize {
        usize::from(self.has_subscribers())
    }

    /// Lends memory for one volume of `volume.grid` to `write`, which is told the sequence
    /// of the earlier volume of this run the memory still holds (if the sink knows one),
    /// then publishes it. An error from `write` is returned and nothing is published.
    fn publish(&self, volume: &WarpedVolume, write: &mut WriteVolume<'_>) -> Result<(), String>;
}

/// The latest warped volume: its geometry (file units), sequence and stamp, and the work.
#[derive(Debug, Clone, PartialEq)]
pub struct WarpedVolume {
    pub grid: Grid,
    pub sequence: u64,
    pub stamp: Time,
    pub stats: WarpStats,
    /// Whether it went out through the volume sink.
    pub published: bool,
}

/// What the camera's frames are made from.
pub(super) enum Picture {
    /// The volume as the warp deforms it (the source as it is when the warp is off).
    Volume(VolumeRenderer),
    /// The deformed mesh raycast directly (`camera.shows: mesh`).
    Mesh(MeshRenderer),
}

pub(super) struct RaycastSetup {
    pub camera: Camera,
    pub picture: Picture,
}

/// The warp and the host copy of its output, when one is kept (the CPU volume picture reads
/// it; without a sink it is where the volume lives), with the warp it holds.
pub(super) struct WarpSetup {
    pub engine: WarpEngine,
    pub host: Option<(Volume, Option<u64>)>,
}

/// What the worker owns.
pub(super) struct FrameWorker {
    pub warp: Option<WarpSetup>,
    pub raycast: Option<RaycastSetup>,
    pub source: Arc<Volume>,
    /// The rest mesh in the volume's units, and the scale from the solver's units.
    pub rest: Arc<TetMesh>,
    pub to_file: f64,
    /// The volume picture has not seen the latest warp yet.
    pub warped_since_picture: bool,
}

struct FrameJob {
    stamp: Time,
    /// Displacements from rest (solver units) for the stages that read them on the host;
    /// the GPU stages had theirs placed on the device when the job was made.
    displacements: Option<Vec<Vector3<f64>>>,
    warp: bool,
    /// The tools as the picture shows them, when a frame is due.
    render: Option<Vec<ToolPicture>>,
    /// Where the warped volume goes out, when someone takes it.
    sink: Option<Arc<dyn VolumeSink>>,
    /// Keep the warped volume on the host (no sink in this run).
    keep_host: bool,
}

/// What a frame produced.
#[derive(Debug, Default)]
pub(super) struct FrameDone {
    pub warped: Option<WarpedVolume>,
    pub image: Option<Image>,
    pub warp_ms: Option<f64>,
    pub raycast_ms: Option<f64>,
}

impl FrameWorker {
    fn picture_reads_host(&self) -> bool {
        matches!(&self.raycast, Some(RaycastSetup { picture: Picture::Volume(VolumeRenderer::Cpu { .. }), .. }))
    }

    fn run(&mut self, job: FrameJob) -> Result<FrameDone, PipelineError> {
        let mut done = FrameDone::default();
        let picture_reads_host = self.picture_reads_host();
        if let (true, Some(w)) = (job.warp, &mut self.warp) {
            let start = Instant::now();
            let host_positions = if w.engine.runs_on() == RunsOn::Cpu { job.displacements.as_deref() } else { None };
            let sequence = w.engine.advance(host_positions)?;
            let mut published = false;
            let mut written: Option<WarpStats> = None;
            let meta = WarpedVolume {
                grid: w.engine.grid().clone(),
                sequence,
                stamp: job.stamp,
                stats: WarpStats::default(),
                published: false,
            };
            if let Some(sink) = &job.sink {
                let engine = &w.engine;
                sink.publish(&meta, &mut |samples, holds| {
                    written = Some(engine.write_into(samples, holds).map_err(|e| e.to_string())?);
                    Ok(())
                })
                .map_err(|e| PipelineError::Invalid(format!("publishing the warped volume: {e}")))?;
                published = true;
            }
            if job.keep_host || picture_reads_host {
                if w.host.is_none() {
                    w.host = Some((Volume::from_grid(&meta.grid, vec![0.0; meta.grid.len()], "warped volume")?, None));
                }
                if let Some((volume, holds)) = &mut w.host {
                    let stats = w.engine.write_into(volume.data_mut(), *holds)?;
                    written.get_or_insert(stats);
                    *holds = Some(sequence);
                }
            } else {
                w.host = None;
            }
            let mut stats = w.engine.stats()?;
            if let Some(written) = written {
                stats.candidates = written.candidates;
                stats.inside = stats.inside.max(written.inside);
            }
            self.warped_since_picture = true;
            done.warp_ms = Some(start.elapsed().as_secs_f64() * 1e3);
            done.warped = Some(WarpedVolume { stats, published, ..meta });
        }
        if let (Some(tools), Some(r)) = (job.render, &mut self.raycast) {
            let start = Instant::now();
            let rendered = match &mut r.picture {
                Picture::Mesh(mesh) => {
                    match (mesh.runs_on(), &job.displacements) {
                        (RunsOn::Cpu, Some(u)) => {
                            let positions: Vec<Vector3<f64>> =
                                self.rest.nodes().iter().zip(u).map(|(r, u)| r + u * self.to_file).collect();
                            mesh.update(&positions)?;
                        }
                        (RunsOn::Cpu, None) => {}
                        _ => mesh.refresh(),
                    }
                    mesh.render(&tools, &r.camera)?
                }
                Picture::Volume(volume) => {
                    let shown = match &self.warp {
                        Some(WarpSetup { host: Some((warped, _)), .. }) if volume.runs_on() == RunsOn::Cpu => {
                            Shown::Host(warped)
                        }
                        Some(_) if volume.runs_on() == RunsOn::Gpu => {
                            if self.warped_since_picture {
                                volume.volume_changed();
                            }
                            Shown::Device
                        }
                        _ => Shown::Host(&self.source),
                    };
                    self.warped_since_picture = false;
                    volume.render(shown, &tools, &r.camera)?
                }
            };
            done.raycast_ms = Some(start.elapsed().as_secs_f64() * 1e3);
            done.image =
                Some(outputs::rgba_image(rendered.rgba, rendered.width, rendered.height, job.stamp, "raycast_camera"));
        }
        Ok(done)
    }
}

enum Runner {
    Inline(Box<FrameWorker>),
    Thread { jobs: SyncSender<FrameJob>, results: Receiver<Result<FrameDone, PipelineError>>, in_flight: bool },
}

/// The deformed mesh as a frame takes it: the displacements from rest on the host (solver
/// units, computed only when a stage needs them there) and, with the solver on the GPU,
/// its displacement buffer.
pub(super) struct Deformation<'a> {
    pub host: &'a dyn Fn() -> Vec<Vector3<f64>>,
    #[cfg(feature = "gpu")]
    pub device: Option<&'a wgpu::Buffer>,
}

/// The warp and raycast stages and when they are due.
pub(super) struct Frames {
    runner: Runner,
    has_warp: bool,
    has_raycast: bool,
    /// The picture is the deformed mesh: it needs positions, not the warp.
    renders_mesh: bool,
    /// Which stages read the deformed nodes on the host (the rest read them on the device).
    warp_on_host: bool,
    mesh_on_host: bool,
    #[cfg(feature = "gpu")]
    warp_nodes: Option<Arc<crate::gpu::DeviceNodes>>,
    #[cfg(feature = "gpu")]
    mesh_nodes: Option<Arc<crate::gpu::DeviceNodes>>,
    warp_period: f64,
    raycast_period: f64,
    last_warp: f64,
    last_raycast: f64,
    /// The mesh moved since the last warp; something moved since the last picture.
    pub warp_stale: bool,
    pub raycast_stale: bool,
    pub latest: Option<WarpedVolume>,
    /// The stage backends, for diagnostics.
    pub warp_backend: Option<RunsOn>,
    pub raycast_backend: Option<RunsOn>,
}

impl Frames {
    pub fn new(worker: FrameWorker, mode: FrameMode, warp_rate: f64, raycast_rate: f64) -> Result<Self, PipelineError> {
        let (has_warp, has_raycast) = (worker.warp.is_some(), worker.raycast.is_some());
        let renders_mesh = worker.raycast.as_ref().is_some_and(|r| matches!(r.picture, Picture::Mesh(_)));
        let warp_backend = worker.warp.as_ref().map(|w| w.engine.runs_on());
        let raycast_backend = worker.raycast.as_ref().map(|r| match &r.picture {
            Picture::Volume(v) => v.runs_on(),
            Picture::Mesh(m) => m.runs_on(),
        });
        #[cfg(feature = "gpu")]
        let warp_nodes = worker.warp.as_ref().and_then(|w| w.engine.device_nodes().cloned());
        #[cfg(feature = "gpu")]
        let mesh_nodes = match &worker.raycast {
            Some(RaycastSetup { picture: Picture::Mesh(m), .. }) => m.device_nodes().cloned(),
            _ => None,
        };
        let runner = match mode {
            FrameMode::Lockstep => Runner::Inline(Box::new(worker)),
            FrameMode::Background => {
                // Its own threads: the solver's parallel loops never queue behind a frame.
                let threads = (std::thread::available_parallelism().map_or(2, usize::from) / 2).max(1);
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .thread_name(|i| format!("defvol-frames-{i}"))
                    .start_handler(|_| super::priority::into_background("the frame worker"))
                    .build()
                    .map_err(|e| PipelineError::Invalid(format!("frame worker threads: {e}")))?;
                let (jobs, job_queue) = mpsc::sync_channel::<FrameJob>(1);
                let (result_queue, results) = mpsc::channel();
                let mut worker = worker;
                std::thread::Builder::new()
                    .name("defvol-frames".into())
                    .spawn(move || {
                        while let Ok(job) = job_queue.recv() {
                            if result_queue.send(pool.install(|| worker.run(job))).is_err() {
                                break;
                            }
                        }
                    })
                    .map_err(|e| PipelineError::Invalid(format!("frame worker: {e}")))?;
                Runner::Thread { jobs, results, in_flight: false }
            }
        };
        Ok(Self {
            runner,
            has_warp,
            has_raycast,
            renders_mesh,
            warp_on_host: warp_backend == Some(RunsOn::Cpu),
            mesh_on_host: renders_mesh && raycast_backend == Some(RunsOn::Cpu),
            #[cfg(feature = "gpu")]
            warp_nodes,
            #[cfg(feature = "gpu")]
            mesh_nodes,
            warp_period: 1.0 / warp_rate,
            raycast_period: 1.0 / raycast_rate,
            last_warp: f64::NEG_INFINITY,
            last_raycast: f64::NEG_INFINITY,
            warp_stale: true,
            raycast_stale: true,
            latest: None,
            warp_backend,
            raycast_backend,
        })
    }

    /// The warped volume kept on the host, in lockstep (the worker is not shared then).
    /// After a reset, whose clock starts again at 0: the next warp and picture are due at
    /// once, and show the organ at rest.
    pub fn restart(&mut self) {
        (self.last_warp, self.last_raycast) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
        (self.warp_stale, self.raycast_stale) = (true, true);
    }

    pub fn host_warped(&self) -> Option<&[f32]> {
        match &self.runner {
            Runner::Inline(worker) => worker.warp.as_ref()?.host.as_ref().map(|(v, _)| v.data()),
            Runner::Thread { .. } => None,
        }
    }

    /// Collects a finished frame, and starts the next when one is due and wanted. Returns
    /// what finished (in lockstep, the frame just run).
    #[allow(clippy::too_many_arguments)]
    pub fn tick(
        &mut self,
        clock: f64,
        stamp: Time,
        want_warp: bool,
        want_image: bool,
        deformation: &Deformation<'_>,
        sink: Option<&Arc<dyn VolumeSink>>,
        tools: impl FnOnce() -> Vec<ToolPicture>,
    ) -> Result<FrameDone, PipelineError> {
        let mut done = FrameDone::default();
        if let Runner::Thread { results, in_flight, .. } = &mut self.runner {
            match results.try_recv() {
                Ok(result) => {
                    *in_flight = false;
                    done = result?;
                }
                Err(TryRecvError::Empty) => {}
                Err(TryRecvError::Disconnected) => {
                    return Err(PipelineError::Invalid("the frame worker stopped".into()))
                }
            }
            if *in_flight {
                return Ok(self.keep(done));
            }
        }
        let due = |last: f64, period: f64| clock - last >= period - 1e-9;
        let render =
            self.has_raycast && want_image && self.raycast_stale && due(self.last_raycast, self.raycast_period);
        // A picture of the volume shows the current deformation: it brings a stale warp
        // along. A picture of the mesh needs only the positions.
        let warp = self.has_warp
            && self.warp_stale
            && ((want_warp && due(self.last_warp, self.warp_period)) || (render && !self.renders_mesh));
        if !(warp || render) {
            return Ok(self.keep(done));
        }
        let mesh_moves = render && self.renders_mesh;
        let host_needed = (warp && self.warp_on_host) || (mesh_moves && self.mesh_on_host);
        let displacements = host_needed.then(|| (deformation.host)());
        #[cfg(feature = "gpu")]
        {
            let place = |nodes: &Option<Arc<crate::gpu::DeviceNodes>>, wanted: bool| -> Result<(), PipelineError> {
                let Some(nodes) = nodes.as_ref().filter(|_| wanted) else { return Ok(()) };
                match deformation.device {
                    Some(buffer) => nodes.place_from(buffer),
                    None => nodes.place_host(&displacements.clone().unwrap_or_else(|| (deformation.host)())),
                }
                .map_err(|e| PipelineError::Invalid(format!("placing the deformed nodes on the device: {e}")))
            };
            place(&self.warp_nodes, warp)?;
            place(&self.mesh_nodes, mesh_moves)?;
        }
        let sink = sink.filter(|s| want_warp && s.has_subscribers()).cloned();
        let job = FrameJob {
            stamp,
            displacements,
            warp,
            render: render.then(tools),
            keep_host: sink.is_none() && want_warp,
            sink,
        };
        if warp {
            (self.last_warp, self.warp_stale) = (clock, false);
            self.raycast_stale = true;
        }
        if render {
            (self.last_raycast, self.raycast_stale) = (clock, false);
        }
        match &mut self.runner {
            Runner::Inline(worker) => {
                let now = worker.run(job)?;
                Ok(self.keep(now))
            }
            Runner::Thread { jobs, in_flight, .. } => {
                jobs.send(job).map_err(|_| PipelineError::Invalid("the frame worker stopped".into()))?;
                *in_flight = true;
                Ok(self.keep(done))
            }
        }
    }

    fn keep(&mut self, done: FrameDone) -> FrameDone {
        if let Some(w) = &done.warped {
            self.latest = Some(w.clone());
        }
        done
    }
}
