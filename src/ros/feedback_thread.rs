//! The force loop's own thread: it waits on the tool subscriptions and answers each pose
//! of a coupled tool at once from the tool's local model (multirate: `solver/haptic.rs`),
//! whatever the mesh's size; the solver steps on a thread of its own, as soon as a pose
//! comes (never more than half a step early: the average rate stays 1/dt) or when a step
//! is due, and each step refreshes the local models. A tool without one (not coupled, or
//! the solver on the GPU) gets each step's feedback as the step ends. The node's main
//! thread, with the warp, the raycaster, DPCM, recording and the other topics, only
//! follows it: it gets the accepted inputs and the feedback to record, and the latest
//! state for the slow stages, and never holds it up.
//!
//! The solver's thread runs inside a rayon pool of its own, sized by
//! [`FeedbackLoop::threads`]: its parallel loops start from a pool worker, so a small step
//! never hands work to another thread.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use mio::{Events, Interest, Poll, Token, Waker};
use ros2_client::{Publisher, Subscription};

use super::error::NodeError;
use crate::msgs::{PoseStamped, Time, WrenchStamped};
use crate::pipeline::inputs::InputLimits;
use crate::pipeline::{priority, run_step, FeedbackLoop, LoopState, StepInput, StepOutput};
use crate::solver::SolverEngine;

/// A tool's input subscriptions.
pub(super) struct ToolSubscriptions {
    pub pose_topic: String,
    pub wrench_topic: String,
    pub pose: Subscription<PoseStamped>,
    pub wrench: Subscription<WrenchStamped>,
}

/// What the loop reads and writes on DDS: each tool's inputs and feedback publisher.
pub(super) struct FeedbackIo {
    pub tools: Vec<ToolSubscriptions>,
    pub feedback: Vec<(String, Publisher<WrenchStamped>)>,
}

/// Told to the loop by the main thread.
pub(super) enum Command {
    Pause,
    Resume,
    /// A managed node's activation: the loop steps and publishes again.
    Activate,
    /// A managed node's deactivation: the loop holds its state and publishes nothing (as
    /// an rclcpp `LifecyclePublisher` drops what an inactive node publishes).
    Deactivate,
    /// New checks of the inputs (`frame_id`, `inputs.*` changed), the simulation running on.
    Checks {
        frame_id: String,
        limits: InputLimits,
    },
    /// A new loop (after a reset or a new scene), with new topics when they changed.
    Replace {
        feedback: Box<FeedbackLoop>,
        io: Option<FeedbackIo>,
    },
}

/// Sent to the main thread: what it records, and the loop's failures.
pub(super) enum Event {
    /// An accepted pose, with the tool's name index and the pose as applied.
    Pose {
        topic: String,
        msg: PoseStamped,
        tool: Option<(usize, nalgebra::Isometry3<f64>)>,
    },
    Wrench {
        topic: String,
        msg: WrenchStamped,
    },
    /// The feedback of one step, as published, at `stamp`.
    Feedback {
        stamp: Time,
        msgs: Vec<WrenchStamped>,
    },
    /// Tool `index`'s answer to one pose, as published at `stamp`.
    LocalFeedback {
        stamp: Time,
        index: usize,
        msg: WrenchStamped,
    },
    /// A step failed: the loop paused itself.
    Failed(String),
}

const WAKER: Token = Token(usize::MAX);
/// How long the loop waits when nothing is due (asleep or paused) before it looks again.
const IDLE_WAIT: Duration = Duration::from_millis(50);

/// The running loop, as the main thread holds it.
pub(super) struct FeedbackThread {
    commands: mpsc::Sender<Command>,
    pub events: mpsc::Receiver<Event>,
    /// The latest state, tagged with the generation of the loop that made it.
    latest: Arc<Mutex<Option<(u64, LoopState)>>>,
    /// Loops replaced so far: a state from an older one is dropped.
    generation: u64,
    waker: Arc<Waker>,
    stop: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
}

impl FeedbackThread {
    /// Starts the loop: `period` is the solver's time step; an inactive loop (a managed
    /// node's, once configured) waits for [`Command::Activate`].
    pub fn spawn(
        mut feedback: FeedbackLoop,
        io: FeedbackIo,
        period: Duration,
        active: bool,
    ) -> Result<Self, NodeError> {
        if !active {
            feedback.pause();
        }
        let failed = |e: &dyn std::fmt::Display| NodeError::Ros(format!("feedback thread: {e}"));
        let poll = Poll::new().map_err(|e| failed(&e))?;
        let waker = Arc::new(Waker::new(poll.registry(), WAKER).map_err(|e| failed(&e))?);
        let stop = Arc::new(AtomicBool::new(false));
        let solver = SolverThread::spawn(feedback.take_engine(), feedback.threads(), waker.clone(), stop.clone())?;
        let (commands, command_rx) = mpsc::channel();
        let (event_tx, events) = mpsc::channel();
        let latest = Arc::new(Mutex::new(None));
        let mut worker = Worker {
            feedback,
            io,
            poll,
            commands: command_rx,
            events: event_tx,
            latest: latest.clone(),
            generation: 0,
            stop: stop.clone(),
            period,
            solver,
            busy: false,
            active,
        };
        let handle = std::thread::Builder::new()
            .name("defvol-feedback".into())
            .spawn(move || {
                priority::into_force_loop("the force loop");
                worker.run()
            })
            .map_err(|e| failed(&e))?;
        Ok(Self { commands, events, latest, generation: 0, waker, stop, handle: Some(handle) })
    }

    pub fn send(&mut self, command: Command) {
        if let Command::Replace { .. } = command {
            self.generation += 1;
        }
        if self.commands.send(command).is_err() {
            tracing::error!("the feedback thread has stopped");
        }
        if let Err(e) = self.waker.wake() {
            tracing::warn!("feedback thread not woken: {e}");
        }
    }

    /// The loop's state since the last call, if it changed (and the loop is the latest).
    pub fn latest(&self) -> Option<LoopState> {
        let (generation, state) = self.latest.lock().ok().and_then(|mut slot| slot.take())?;
        (generation == self.generation).then_some(state)
    }
}

impl Drop for FeedbackThread {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        let _ = self.waker.wake();
        if let Some(handle) = self.handle.take() {
            if handle.join().is_err() {
                tracing::error!("the feedback thread panicked");
            }
        }
    }
}

struct Worker {
    feedback: FeedbackLoop,
    io: FeedbackIo,
    poll: Poll,
    commands: mpsc::Receiver<Command>,
    events: mpsc::Sender<Event>,
    latest: Arc<Mutex<Option<(u64, LoopState)>>>,
    generation: u64,
    stop: Arc<AtomicBool>,
    period: Duration,
    solver: SolverThread,
    /// A step of this generation is on the solver's thread.
    busy: bool,
    /// Publishing (not a deactivated managed node's loop).
    active: bool,
}

/// Sent to the solver's thread.
enum Job {
    Step {
        generation: u64,
        input: StepInput,
    },
    /// The solver of a new loop (after a reset or a new scene).
    Engine(Option<Box<SolverEngine>>),
}

/// The solver on a thread of its own: it takes a step's inputs, steps, and hands back the
/// outcome, waking the force loop.
struct SolverThread {
    jobs: mpsc::Sender<Job>,
    done: mpsc::Receiver<(u64, Result<StepOutput, String>)>,
    handle: Option<JoinHandle<()>>,
}

impl SolverThread {
    fn spawn(
        engine: Option<SolverEngine>,
        threads: usize,
        waker: Arc<Waker>,
        stop: Arc<AtomicBool>,
    ) -> Result<Self, NodeError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("defvol-solver-{i}"))
            .start_handler(|_| priority::into_background("the solver"))
            .build()
            .map_err(|e| NodeError::Ros(format!("solver thread pool: {e}")))?;
        let (jobs, job_rx) = mpsc::channel::<Job>();
        let (done_tx, done) = mpsc::channel();
        let handle = std::thread::Builder::new()
            .name("defvol-solver".into())
            .spawn(move || {
                pool.install(move || {
                    let mut engine = engine;
                    while let Ok(job) = job_rx.recv() {
                        if stop.load(Ordering::SeqCst) {
                            break;
                        }
                        match job {
                            Job::Engine(next) => engine = next.map(|e| *e),
                            Job::Step { generation, input } => {
                                let Some(engine) = engine.as_mut() else { continue };
                                let outcome = run_step(engine, &input).map_err(|e| e.to_string());
                                if done_tx.send((generation, outcome)).is_err() {
                                    break;
                                }
                                let _ = waker.wake();
                            }
                        }
                    }
                })
            })
            .map_err(|e| NodeError::Ros(format!("solver thread: {e}")))?;
        Ok(Self { jobs, done, handle: Some(handle) })
    }
}

impl Drop for SolverThread {
    fn drop(&mut self) {
        // Closing the job channel ends the thread once its step is done.
        let (closed, _) = mpsc::channel();
        drop(std::mem::replace(&mut self.jobs, closed));
        if let Some(handle) = self.handle.take() {
            if handle.join().is_err() {
                tracing::error!("the solver thread panicked");
            }
        }
    }
}

impl Worker {
    fn run(&mut self) {
        self.register(true);
        let mut events = Events::with_capacity(64);
        let mut next_step = Instant::now();
        while !self.stop.load(Ordering::SeqCst) {
            let idle = self.feedback.paused() || self.feedback.asleep() || self.busy;
            let wait = if idle { IDLE_WAIT } else { next_step.saturating_duration_since(Instant::now()) };
            if let Err(e) = self.poll.poll(&mut events, Some(wait)) {
                if e.kind() != std::io::ErrorKind::Interrupted {
                    tracing::error!("feedback thread: waiting on the tool topics failed: {e}");
                    std::thread::sleep(self.period);
                }
            }
            let (posed, changed) = self.take_inputs();
            let commanded = self.take_commands();
            if commanded {
                next_step = Instant::now();
            }
            let stepped = self.take_step();
            let now = Instant::now();
            // A step goes as soon as a pose comes, at most half a step early, so that the
            // feedback follows the device's own clock at 1/dt on average.
            let due = now >= next_step || (posed && now + self.period / 2 >= next_step);
            if due && !self.busy {
                if let Some(input) = self.feedback.step_input(Time::now()) {
                    self.busy = self.solver.jobs.send(Job::Step { generation: self.generation, input }).is_ok();
                    next_step += self.period;
                    // Behind by more than a few steps (a stall, or waking from sleep): start afresh.
                    if next_step + self.period * 5 < now {
                        next_step = now + self.period;
                    }
                } else {
                    next_step = now;
                    // Asleep, each pose still gets its answer: the rest state's force.
                    if let Some(msgs) = posed.then(|| self.feedback.resting_feedback(Time::now())).flatten() {
                        self.send_unanswered(msgs);
                    }
                }
            }
            if stepped.is_some() || changed || commanded {
                self.publish_state(stepped);
            }
        }
    }

    /// The step the solver's thread finished, if any: its feedback goes to each tool not
    /// answered from a local model.
    fn take_step(&mut self) -> Option<crate::pipeline::Stepped> {
        let mut latest = None;
        while let Ok((generation, outcome)) = self.solver.done.try_recv() {
            if generation != self.generation {
                continue; // a step of a loop since replaced
            }
            self.busy = false;
            match outcome {
                Ok(output) => latest = Some(self.feedback.finish_step(output)),
                Err(e) => {
                    self.feedback.pause();
                    let _ = self.events.send(Event::Failed(e));
                }
            }
        }
        let mut stepped = latest?;
        self.send_unanswered(std::mem::take(&mut stepped.feedback));
        Some(stepped)
    }

    /// Publishes the feedback of each tool not answered from a local model (those got
    /// their answer as their pose came) and not waiting for its device's first pose.
    fn send_unanswered(&self, msgs: Vec<WrenchStamped>) {
        let elsewhere = |index: usize| self.feedback.answers_locally(index) || self.feedback.awaits_first_pose(index);
        if (0..msgs.len()).any(elsewhere) {
            for (index, msg) in msgs.into_iter().enumerate().filter(|(index, _)| !elsewhere(*index)) {
                self.send_one(index, msg);
            }
        } else {
            self.send_feedback(msgs);
        }
    }

    /// Publishes one tool's feedback and hands it to the node to record.
    fn send_one(&self, index: usize, msg: WrenchStamped) {
        if !self.active {
            return;
        }
        if let Some((topic, publisher)) = self.io.feedback.get(index) {
            if let Err(e) = publisher.publish(msg.clone()) {
                tracing::debug!("{topic}: not sent ({e:?})");
            }
        }
        let _ = self.events.send(Event::LocalFeedback { stamp: Time::now(), index, msg });
    }

    /// Publishes each tool's feedback and hands it to the node to record.
    fn send_feedback(&self, msgs: Vec<WrenchStamped>) {
        if !self.active {
            return;
        }
        for (publisher, msg) in self.io.feedback.iter().zip(&msgs) {
            if let Err(e) = publisher.1.publish(msg.clone()) {
                tracing::debug!("{}: not sent ({e:?})", publisher.0);
            }
        }
        let _ = self.events.send(Event::Feedback { stamp: Time::now(), msgs });
    }

    /// Waits on every tool subscription (`true`) or stops waiting on them.
    fn register(&mut self, on: bool) {
        let registry = self.poll.registry();
        for (i, tool) in self.io.tools.iter_mut().enumerate() {
            let outcome = if on {
                mio::event::Source::register(&mut tool.pose, registry, Token(2 * i), Interest::READABLE).and_then(
                    |()| mio::event::Source::register(&mut tool.wrench, registry, Token(2 * i + 1), Interest::READABLE),
                )
            } else {
                mio::event::Source::deregister(&mut tool.pose, registry)
                    .and_then(|()| mio::event::Source::deregister(&mut tool.wrench, registry))
            };
            // Unregistered, the loop still reads the topic each step; it only reacts later.
            if let Err(e) = outcome {
                tracing::warn!("feedback thread: {}: {e}", tool.pose_topic);
            }
        }
    }

    /// Applies every waiting input; (a pose came, anything came).
    fn take_inputs(&mut self) -> (bool, bool) {
        let (mut posed, mut changed) = (false, false);
        let now = Time::now();
        for tool in &self.io.tools {
            let mut answer = false;
            drain(&tool.pose, |msg| {
                changed = true;
                if self.feedback.apply_pose(&tool.pose_topic, &msg, now).is_ok() {
                    (posed, answer) = (true, true);
                    let pose = self.feedback.tool_on(&tool.pose_topic);
                    let _ = self.events.send(Event::Pose { topic: tool.pose_topic.clone(), msg, tool: pose });
                }
            });
            // The latest pose of a coupled tool is answered now, from its local model.
            let to_answer = self.feedback.tool_on(&tool.pose_topic).map(|(index, _)| index).filter(|_| answer);
            if let Some((index, msg)) = to_answer.and_then(|i| Some((i, self.feedback.answer_locally(i)?))) {
                self.send_one(index, msg);
            }
            drain(&tool.wrench, |msg| {
                changed = true;
                if self.feedback.apply_wrench(&tool.wrench_topic, &msg, now).is_ok() {
                    let _ = self.events.send(Event::Wrench { topic: tool.wrench_topic.clone(), msg });
                }
            });
        }
        (posed, changed)
    }

    /// Obeys the main thread; true when anything was told.
    fn take_commands(&mut self) -> bool {
        let mut any = false;
        while let Ok(command) = self.commands.try_recv() {
            any = true;
            match command {
                Command::Pause => self.feedback.pause(),
                Command::Checks { frame_id, limits } => self.feedback.set_checks(&frame_id, limits),
                Command::Resume => self.feedback.resume(),
                Command::Activate => {
                    self.active = true;
                    self.feedback.resume();
                }
                Command::Deactivate => {
                    self.active = false;
                    self.feedback.pause();
                }
                Command::Replace { mut feedback, io } => {
                    let _ = self.solver.jobs.send(Job::Engine(feedback.take_engine().map(Box::new)));
                    self.feedback = *feedback;
                    if !self.active {
                        self.feedback.pause();
                    }
                    self.generation += 1;
                    self.busy = false;
                    if let Some(io) = io {
                        self.register(false);
                        self.io = io;
                        self.register(true);
                    }
                }
            }
        }
        any
    }

    /// Hands the state to the main thread; a step it has not taken yet is kept unless a
    /// newer one replaces it.
    fn publish_state(&self, stepped: Option<crate::pipeline::Stepped>) {
        let Ok(mut slot) = self.latest.lock() else { return };
        let unread = slot.take().filter(|(generation, _)| *generation == self.generation);
        let stepped = stepped.or_else(|| unread.and_then(|(_, s)| s.stepped));
        *slot = Some((self.generation, LoopState { stepped, ..self.feedback.state() }));
    }
}

/// Takes every waiting sample; undecodable ones are logged and skipped.
pub(super) fn drain<T: serde::de::DeserializeOwned + 'static>(
    subscription: &Subscription<T>,
    mut apply: impl FnMut(T),
) -> usize {
    let mut n = 0;
    loop {
        match subscription.take() {
            Ok(Some((msg, _))) => {
                apply(msg);
                n += 1;
            }
            Ok(None) => return n,
            Err(e) => {
                tracing::warn!("a tool sample could not be read: {e:?}");
                return n;
            }
        }
    }
}
