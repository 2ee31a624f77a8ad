//! The slow stages, warp and raycast (tens to hundreds of milliseconds a frame), run by a
//! worker beside the solver. Live (`Background`) the solver never waits for them: a frame
//! starts when the last one is done and its results come out in a later tick. Replays and
//! the demo run them in `Lockstep`, inside the tick, so a bag always gives the same frames.

use std::sync::mpsc::{self, Receiver, SyncSender, TryRecvError};
use std::sync::Arc;
use std::time::Instant;

use nalgebra::Vector3;

use super::{outputs, PipelineError};
use crate::msgs::{Image, Time};
use crate::render::camera::Camera;
use crate::render::raycast::{RaycastParams, ToolPicture, VolumeRaycaster};
use crate::render::tet_raycast::TetRaycaster;
use crate::render::transfer::Tables;
use crate::volume::{Grid, Volume};
use crate::warp::{IncrementalWarp, WarpStats};

/// Whether frames run inside the tick or beside it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameMode {
    /// Inside the tick: deterministic (demo, replay, tests).
    Lockstep,
    /// On a worker thread with its own threads: the solver keeps its rate (the node).
    Background,
}

/// The latest warped volume, shared with whoever publishes it.
#[derive(Debug, Clone)]
pub struct WarpedVolume {
    pub grid: Grid,
    pub data: Arc<Vec<f32>>,
    pub sequence: u64,
    pub stats: WarpStats,
}

/// What the camera's frames are made from.
pub(super) enum Picture {
    /// The volume as the warp deforms it; the tables are built once, over the source's range
    /// (the warped volume stays within it).
    Volume { tables: Arc<Tables>, params: RaycastParams },
    /// The deformed mesh raycast directly (`camera.shows: mesh`).
    Mesh(Box<TetRaycaster>),
}

pub(super) struct RaycastSetup {
    pub camera: Camera,
    pub picture: Picture,
}

/// What the worker owns: the incremental warp and the camera.
pub(super) struct FrameWorker {
    pub warp: Option<(IncrementalWarp, f64)>,
    pub raycast: Option<RaycastSetup>,
    pub volume: Arc<Volume>,
    pub sequence: u64,
}

struct FrameJob {
    stamp: Time,
    /// Deformed positions in the volume's units, when the warp or a mesh picture is due.
    positions: Option<Vec<Vector3<f64>>>,
    warp: bool,
    /// The tools as the picture shows them, when a frame is due.
    render: Option<Vec<ToolPicture>>,
    /// Copy the warped samples out for publishing.
    share: bool,
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
    fn run(&mut self, job: FrameJob) -> Result<FrameDone, PipelineError> {
        let mut done = FrameDone::default();
        if let (true, Some(deformed), Some((warp, tolerance))) = (job.warp, &job.positions, &mut self.warp) {
            let start = Instant::now();
            let stats = warp.update(deformed, *tolerance)?;
            self.sequence += 1;
            done.warp_ms = Some(start.elapsed().as_secs_f64() * 1e3);
            if job.share {
                done.warped = Some(WarpedVolume { grid: warp.grid().clone(), data: Arc::new(warp.data().to_vec()), sequence: self.sequence, stats });
            }
        }
        if let (Some(tools), Some(r)) = (job.render, &mut self.raycast) {
            let start = Instant::now();
            let rendered = match &mut r.picture {
                Picture::Mesh(mesh) => {
                    if let Some(deformed) = &job.positions {
                        mesh.update(deformed)?;
                    }
                    mesh.set_tools(tools)?;
                    mesh.render(&r.camera)?
                }
                Picture::Volume { tables, params } => {
                    params.tools = tools;
                    let warped;
                    let volume = match &self.warp {
                        Some((w, _)) => {
                            warped = Volume::from_grid(w.grid(), w.data().to_vec(), "warped volume")?;
                            &warped
                        }
                        None => &*self.volume,
                    };
                    VolumeRaycaster::with_tables(volume, tables.clone(), params)?.render(&r.camera)?
                }
            };
            done.raycast_ms = Some(start.elapsed().as_secs_f64() * 1e3);
            done.image = Some(outputs::rgba_image(rendered.rgba, rendered.width, rendered.height, job.stamp, "raycast_camera"));
        }
        Ok(done)
    }
}

enum Runner {
    Inline(Box<FrameWorker>),
    Thread { jobs: SyncSender<FrameJob>, results: Receiver<Result<FrameDone, PipelineError>>, in_flight: bool },
}

/// The warp and raycast stages and when they are due.
pub(super) struct Frames {
    runner: Runner,
    has_warp: bool,
    has_raycast: bool,
    /// The picture is the deformed mesh: it needs positions, not the warp.
    renders_mesh: bool,
    warp_period: f64,
    raycast_period: f64,
    last_warp: f64,
    last_raycast: f64,
    /// The mesh moved since the last warp; something moved since the last picture.
    pub warp_stale: bool,
    pub raycast_stale: bool,
    pub latest: Option<WarpedVolume>,
}

impl Frames {
    pub fn new(worker: FrameWorker, mode: FrameMode, warp_rate: f64, raycast_rate: f64) -> Result<Self, PipelineError> {
        let (has_warp, has_raycast) = (worker.warp.is_some(), worker.raycast.is_some());
        let renders_mesh = worker.raycast.as_ref().is_some_and(|r| matches!(r.picture, Picture::Mesh(_)));
        let runner = match mode {
            FrameMode::Lockstep => Runner::Inline(Box::new(worker)),
            FrameMode::Background => {
                // Its own threads: the solver's parallel loops never queue behind a frame.
                let threads = (std::thread::available_parallelism().map_or(2, usize::from) / 2).max(1);
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).thread_name(|i| format!("defvol-frames-{i}")).build().map_err(|e| PipelineError::Invalid(format!("frame worker threads: {e}")))?;
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
            warp_period: 1.0 / warp_rate,
            raycast_period: 1.0 / raycast_rate,
            last_warp: f64::NEG_INFINITY,
            last_raycast: f64::NEG_INFINITY,
            warp_stale: true,
            raycast_stale: true,
            latest: None,
        })
    }

    /// Collects a finished frame, and starts the next when one is due and wanted. Returns
    /// what finished (in lockstep, the frame just run).
    pub fn tick(&mut self, clock: f64, stamp: Time, want_warp: bool, want_image: bool, positions: impl FnOnce() -> Vec<Vector3<f64>>, tools: impl FnOnce() -> Vec<ToolPicture>) -> Result<FrameDone, PipelineError> {
        let mut done = FrameDone::default();
        if let Runner::Thread { results, in_flight, .. } = &mut self.runner {
            match results.try_recv() {
                Ok(result) => {
                    *in_flight = false;
                    done = result?;
                }
                Err(TryRecvError::Empty) => {}
                Err(TryRecvError::Disconnected) => return Err(PipelineError::Invalid("the frame worker stopped".into())),
            }
            if *in_flight {
                return Ok(self.keep(done));
            }
        }
        let due = |last: f64, period: f64| clock - last >= period - 1e-9;
        let render = self.has_raycast && want_image && self.raycast_stale && due(self.last_raycast, self.raycast_period);
        // A picture of the volume shows the current deformation: it brings a stale warp
        // along. A picture of the mesh needs only the positions.
        let warp = self.has_warp && self.warp_stale && ((want_warp && due(self.last_warp, self.warp_period)) || (render && !self.renders_mesh));
        if !(warp || render) {
            return Ok(self.keep(done));
        }
        let job = FrameJob { stamp, positions: (warp || (render && self.renders_mesh)).then(positions), warp, render: render.then(tools), share: want_warp };
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
