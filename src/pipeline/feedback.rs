//! The solver and the tools' inputs, apart from the slow stages: poses and wrenches in, one
//! step, each tool's reaction out. The node runs it on a thread of its own at the solver's
//! rate, so that the warp, the raycaster, the DPCM surface, recording and the other topics
//! never delay the force loop; lockstep runs (the demo, replays, tests) step it inside
//! [`super::Pipeline::tick`].

use std::time::Instant;

use nalgebra::{Isometry3, Vector3};

use super::error::PipelineError;
use super::inputs::{Checker, InputCounters, InputLimits, Rejection};
use super::outputs;
use crate::backend::RunsOn;
use crate::msgs::{PoseStamped, Time, WrenchStamped};
use crate::scene::{Scene, ToolPath};
use crate::solver::{LocalModel, SolverEngine, StepReport, Tool};

/// Mesh kinetic energy (J) under which, with no tool touching or pushing, the solver sleeps.
const SLEEP_ENERGY: f64 = 1e-9;
/// Steps the mesh must stay that quiet first.
pub(super) const SLEEP_AFTER: u32 = 20;
/// Below this many nodes a step runs on one thread: handing a few microseconds of work to
/// another core costs more than it saves (see docs/perf/journal.md#one-thread-for-small-steps).
const SERIAL_BELOW_NODES: usize = 2500;

#[derive(Clone)]
pub(super) struct ToolState {
    pub pose_topic: String,
    pub wrench_topic: String,
    pub feedback_topic: String,
    pub last_pose: Option<Time>,
    pub last_wrench: Option<Time>,
    /// The tool as the stages see it (the solver holds a copy).
    pub tool: Tool,
    /// The demo's scripted motion, if any.
    pub path: Option<ToolPath>,
}

/// One step's results, for the slow stages.
#[derive(Debug, Clone)]
pub struct Stepped {
    pub report: StepReport,
    /// Node positions after the step, world units.
    pub positions: Vec<Vector3<f64>>,
    /// Each tool's reaction, in the scene's order, stamped with the stamp of the tool's
    /// latest pose the step used (the step's own stamp before any pose): a device knows
    /// which command a force answers, and the round trip is measured from it.
    pub feedback: Vec<WrenchStamped>,
    /// Milliseconds the step took.
    pub solver_ms: f64,
}

/// What the slow stages follow of a loop running on another thread.
#[derive(Debug, Clone)]
pub struct LoopState {
    /// The latest step since the state was last taken, if any.
    pub stepped: Option<Stepped>,
    pub tools: Vec<Tool>,
    pub counters: InputCounters,
    pub paused: bool,
    pub asleep: bool,
    pub saturated_steps: Vec<u64>,
}

/// The solver and its tools.
pub struct FeedbackLoop {
    /// `None` when the scene disables the solver, or in the copy a detached loop leaves.
    engine: Option<SolverEngine>,
    engine_name: String,
    /// `None` without a solver; kept by a follower.
    engine_backend: Option<RunsOn>,
    nodes: usize,
    tools: Vec<ToolState>,
    frame_id: String,
    limits: InputLimits,
    counters: InputCounters,
    paused: bool,
    quiet_steps: u32,
    asleep: bool,
    last_report: Option<StepReport>,
    solver_ms: f64,
    /// Steps in which each tool's coupling held its device back with its largest force.
    saturated_steps: Vec<u64>,
    /// The coupled tools' local models from the last step, each with the stamp of the
    /// last pose it answered.
    local: Vec<(LocalModel, Option<Time>)>,
    /// Tools whose device's first pose came since the last step: their simulated tools start
    /// there, not where the tool waited.
    to_seat: Vec<bool>,
    /// Topics whose zero stamps were taken as the time they came (said once each).
    zero_stamped: std::collections::BTreeSet<String>,
}

impl FeedbackLoop {
    pub(super) fn new(scene: &Scene, engine: Option<SolverEngine>, nodes: usize, limits: InputLimits) -> Self {
        let tools: Vec<ToolState> = (scene.tools.iter().enumerate())
            .map(|(i, config)| {
                let mut tool = config.tool();
                if let Some(p) = config.path.as_ref().map(|path| path.position(0.0)) {
                    tool.world_from_tool = Isometry3::translation(p.x, p.y, p.z);
                }
                ToolState {
                    pose_topic: config.pose_topic(i),
                    wrench_topic: config.wrench_topic(i),
                    feedback_topic: config.feedback_topic(i),
                    last_pose: None,
                    last_wrench: None,
                    tool,
                    path: config.path.clone(),
                }
            })
            .collect();
        Self {
            engine_name: engine.as_ref().map_or_else(|| "off".into(), SolverEngine::name),
            engine_backend: engine.as_ref().map(SolverEngine::runs_on),
            engine,
            nodes,
            saturated_steps: vec![0; tools.len()],
            tools,
            frame_id: scene.frame_id.clone(),
            limits,
            counters: InputCounters::default(),
            paused: false,
            quiet_steps: 0,
            asleep: false,
            last_report: None,
            solver_ms: 0.0,
            local: Vec::new(),
            to_seat: Vec::new(),
            zero_stamped: Default::default(),
        }
    }

    /// Checks the inputs against `frame_id` and `limits` from now on.
    pub fn set_checks(&mut self, frame_id: &str, limits: InputLimits) {
        frame_id.clone_into(&mut self.frame_id);
        self.limits = limits;
    }

    /// `stamp`, or `now` for a zero stamp (what `ros2 topic pub` and unsynced devices send),
    /// saying so once per topic.
    fn stamp_or_now(&mut self, topic: &str, stamp: Time, now: Time) -> Time {
        if stamp != Time::default() {
            return stamp;
        }
        if self.zero_stamped.insert(topic.to_owned()) {
            tracing::warn!("{topic}: a zero stamp, taken as the time it came (said once for this topic)");
        }
        now
    }

    /// Hands the solver to a loop of its own; this one keeps the tools and follows it.
    pub(super) fn detach(&mut self) -> FeedbackLoop {
        let follower = FeedbackLoop {
            engine: None,
            engine_name: self.engine_name.clone(),
            engine_backend: self.engine_backend,
            nodes: self.nodes,
            tools: self.tools.clone(),
            frame_id: self.frame_id.clone(),
            limits: self.limits.clone(),
            counters: self.counters.clone(),
            paused: self.paused,
            quiet_steps: self.quiet_steps,
            asleep: self.asleep,
            last_report: self.last_report.clone(),
            solver_ms: self.solver_ms,
            saturated_steps: self.saturated_steps.clone(),
            local: self.local.clone(),
            to_seat: self.to_seat.clone(),
            zero_stamped: self.zero_stamped.clone(),
        };
        std::mem::replace(self, follower)
    }

    /// Takes what a detached loop reports; true when a tool moved.
    pub(super) fn follow(&mut self, state: &LoopState) -> bool {
        let mut moved = false;
        for (mine, theirs) in self.tools.iter_mut().zip(&state.tools) {
            moved |= mine.tool.world_from_tool != theirs.world_from_tool;
            mine.tool.clone_from(theirs);
        }
        self.counters.clone_from(&state.counters);
        (self.paused, self.asleep) = (state.paused, state.asleep);
        self.saturated_steps.clone_from(&state.saturated_steps);
        if let Some(s) = &state.stepped {
            self.last_report = Some(s.report.clone());
            self.solver_ms = s.solver_ms;
        }
        moved
    }

    /// What a follower needs, without a step.
    pub fn state(&self) -> LoopState {
        LoopState {
            stepped: None,
            tools: self.tools.iter().map(|t| t.tool.clone()).collect(),
            counters: self.counters.clone(),
            paused: self.paused,
            asleep: self.asleep,
            saturated_steps: self.saturated_steps.clone(),
        }
    }

    /// Threads a step is worth: one below 2,500 nodes, where handing work to another core
    /// costs more than it saves; the node runs the solver on a pool of that many, so that a
    /// small step never hands work across threads. With a coupled tool one core is left to
    /// the force loop, which answers its poses while the solver works (see
    /// docs/perf/journal.md#a-core-for-the-force-loop).
    pub fn threads(&self) -> usize {
        let cores = std::thread::available_parallelism().map_or(1, usize::from);
        let coupled = self.tools.iter().any(|t| t.tool.coupling.is_some());
        match self.nodes < SERIAL_BELOW_NODES {
            true => 1,
            false if coupled => cores.saturating_sub(1).max(1),
            false => cores,
        }
    }

    /// Where the solver runs, `None` when the scene disables it.
    pub fn engine_backend(&self) -> Option<RunsOn> {
        self.engine_backend
    }
    /// The solver itself (on a GPU, the warp reads its displacements where they are).
    #[cfg(feature = "gpu")]
    pub(super) fn engine(&self) -> Option<&SolverEngine> {
        self.engine.as_ref()
    }
    /// The solver's path and device, for logs.
    pub fn engine_name(&self) -> &str {
        &self.engine_name
    }
    pub(super) fn tool_states(&self) -> &[ToolState] {
        &self.tools
    }
    pub fn asleep(&self) -> bool {
        self.asleep
    }
    pub fn paused(&self) -> bool {
        self.paused
    }
    pub fn pause(&mut self) {
        self.paused = true;
    }
    pub fn resume(&mut self) {
        self.paused = false;
    }
    pub fn counters(&self) -> &InputCounters {
        &self.counters
    }
    pub fn last_report(&self) -> Option<&StepReport> {
        self.last_report.as_ref()
    }
    pub fn solver_ms(&self) -> f64 {
        self.solver_ms
    }
    pub fn saturated_steps(&self) -> &[u64] {
        &self.saturated_steps
    }

    /// The tool on `pose_topic`: its name (index) and `world_from_tool`.
    pub fn tool_on(&self, pose_topic: &str) -> Option<(usize, Isometry3<f64>)> {
        let index = self.tools.iter().position(|t| t.pose_topic == pose_topic)?;
        Some((index, self.tools[index].tool.world_from_tool))
    }

    /// The pose and wrench topics of each tool.
    pub fn tool_topics(&self) -> Vec<(String, String)> {
        self.tools.iter().map(|t| (t.pose_topic.clone(), t.wrench_topic.clone())).collect()
    }

    /// The feedback topic of each tool, in the order of [`Stepped::feedback`].
    pub fn feedback_topics(&self) -> Vec<String> {
        self.tools.iter().map(|t| t.feedback_topic.clone()).collect()
    }

    /// Applies a tool pose; refused ones are counted and leave the tool where it was.
    /// Returns whether the tool moved.
    pub fn apply_pose(&mut self, topic: &str, msg: &PoseStamped, now: Time) -> Result<bool, Rejection> {
        let stamp = self.stamp_or_now(topic, msg.header.stamp, now);
        let outcome = self.pose_outcome(topic, msg, stamp, now);
        self.counters.record(&outcome.as_ref().map(drop).map_err(Clone::clone));
        outcome
    }

    fn pose_outcome(&mut self, topic: &str, msg: &PoseStamped, stamp: Time, now: Time) -> Result<bool, Rejection> {
        let Some(index) = self.tools.iter().position(|t| t.pose_topic == topic) else {
            return Err(Rejection::UnknownTopic { topic: topic.into() });
        };
        let checker = Checker { limits: &self.limits, world_frame: &self.frame_id, now };
        let world_from_tool = checker.pose(topic, msg, stamp, self.tools[index].last_pose)?;
        let state = &mut self.tools[index];
        if state.last_pose.is_none() && state.path.is_none() {
            self.to_seat.resize(self.tools.len(), false);
            self.to_seat[index] = true;
            self.local.retain(|(model, _)| model.tool != index);
        }
        let state = &mut self.tools[index];
        state.last_pose = Some(stamp);
        let moved = state.tool.world_from_tool != world_from_tool;
        if moved {
            state.tool.world_from_tool = world_from_tool;
            self.wake();
        }
        Ok(moved)
    }

    /// Applies a commanded tool force.
    pub fn apply_wrench(&mut self, topic: &str, msg: &WrenchStamped, now: Time) -> Result<(), Rejection> {
        let stamp = self.stamp_or_now(topic, msg.header.stamp, now);
        let outcome = self.wrench_outcome(topic, msg, stamp, now);
        self.counters.record(&outcome);
        outcome
    }

    fn wrench_outcome(&mut self, topic: &str, msg: &WrenchStamped, stamp: Time, now: Time) -> Result<(), Rejection> {
        let Some(index) = self.tools.iter().position(|t| t.wrench_topic == topic) else {
            return Err(Rejection::UnknownTopic { topic: topic.into() });
        };
        let checker = Checker { limits: &self.limits, world_frame: &self.frame_id, now };
        let force = checker.wrench(topic, msg, stamp, self.tools[index].last_wrench)?;
        let state = &mut self.tools[index];
        state.last_wrench = Some(stamp);
        if state.tool.applied_force != force {
            state.tool.applied_force = force;
            self.wake();
        }
        Ok(())
    }

    /// Moves scripted tools along their paths (the demo); true when one moved.
    pub(super) fn follow_scripts(&mut self, t: f64) -> bool {
        let mut moved = false;
        for state in &mut self.tools {
            let Some(p) = state.path.as_ref().map(|path| path.position(t)) else { continue };
            let iso = Isometry3::translation(p.x, p.y, p.z);
            moved |= state.tool.world_from_tool != iso;
            state.tool.world_from_tool = iso;
        }
        if moved {
            self.wake();
        }
        moved
    }

    fn wake(&mut self) {
        self.asleep = false;
        self.quiet_steps = 0;
    }

    /// While the solver sleeps: each tool's last reaction (the mesh at rest and untouched)
    /// stamped with its latest pose, so that a device streaming poses gets an answer to each
    /// at a fixed rate. None while awake or paused, or before the first step.
    pub fn resting_feedback(&self, stamp: Time) -> Option<Vec<WrenchStamped>> {
        if !self.asleep || self.paused {
            return None;
        }
        let report = self.last_report.as_ref()?;
        let feedback = (self.tools.iter().enumerate())
            .map(|(index, t)| outputs::feedback(report, index, t.last_pose.unwrap_or(stamp), &self.frame_id));
        Some(feedback.collect())
    }

    /// One solver step, unless there is no solver here, or it is paused or asleep.
    pub fn step(&mut self, stamp: Time) -> Result<Option<Stepped>, PipelineError> {
        let Some(input) = self.step_input(stamp) else { return Ok(None) };
        let Some(engine) = self.engine.as_mut() else { return Ok(None) };
        let output = run_step(engine, &input)?;
        Ok(Some(self.finish_step(output)))
    }

    /// What a step needs, unless it is paused or asleep: the force loop's thread hands it to
    /// the solver's own thread, so that poses are answered while the solver works.
    pub fn step_input(&mut self, stamp: Time) -> Option<StepInput> {
        if self.paused || self.asleep {
            return None;
        }
        let tools = (self.tools.iter().enumerate())
            .map(|(index, t)| ToolInput {
                pose: t.tool.world_from_tool,
                force: t.tool.applied_force,
                last_pose: t.last_pose,
                // A tool that waits for its device's first pose touches nothing yet.
                contact_stiffness: if self.awaits_first_pose(index) { 0.0 } else { t.tool.contact_stiffness },
            })
            .collect();
        Some(StepInput { tools, seat: std::mem::take(&mut self.to_seat), stamp })
    }

    /// Gives the solver away (to a thread of its own); this loop then only takes its steps.
    pub fn take_engine(&mut self) -> Option<SolverEngine> {
        self.engine.take()
    }

    /// Takes a step's outcome: the sleep rule, the counters, each tool's feedback stamped
    /// with the pose the step used, and the local models the loop answers poses from until
    /// the next step.
    pub fn finish_step(&mut self, output: StepOutput) -> Stepped {
        let StepOutput { report, positions, local, solver_ms, input } = output;
        self.solver_ms = solver_ms;
        let touching = report.reactions.iter().any(|r| r.force.iter().any(|f| *f != 0.0))
            || self.tools.iter().any(|t| t.tool.applied_force != Vector3::zeros());
        self.quiet_steps = if report.kinetic_energy < SLEEP_ENERGY && !touching { self.quiet_steps + 1 } else { 0 };
        self.asleep = self.quiet_steps >= SLEEP_AFTER;
        for (count, reaction) in self.saturated_steps.iter_mut().zip(&report.reactions) {
            *count += u64::from(reaction.coupling_saturated);
        }
        for (index, reaction) in report.reactions.iter().enumerate() {
            let before = self.last_report.as_ref().is_some_and(|r| r.reaction(index).passed_through);
            if reaction.passed_through && !before {
                tracing::warn!(
                    "{}: the tool went through the surface (its tip is inside the body and no contact holds it: a \
                     teleport, or a pose step too long); a coupling holds a tool at the surface",
                    self.tools[index].pose_topic
                );
            }
        }
        let feedback = (input.tools.iter().enumerate())
            .map(|(index, t)| outputs::feedback(&report, index, t.last_pose.unwrap_or(input.stamp), &self.frame_id))
            .collect();
        // A model from before its device's first pose came would answer from where the tool
        // waited: the next step, which seats it, brings one.
        self.local = (local.into_iter())
            .filter(|model| !self.to_seat.get(model.tool).copied().unwrap_or(false))
            .map(|model| {
                let answered = input.tools.get(model.tool).and_then(|t| t.last_pose);
                (model, answered)
            })
            .collect();
        self.last_report = Some(report.clone());
        Stepped { report, positions, feedback, solver_ms }
    }

    /// Whether tool `index` waits for its device's first pose (it has no scripted path): it
    /// sits where the scene put it, maybe inside the organ, so it touches nothing and its
    /// feedback answers nothing yet.
    pub fn awaits_first_pose(&self, index: usize) -> bool {
        self.tools.get(index).is_some_and(|t| t.last_pose.is_none() && t.path.is_none())
    }

    /// Whether tool `index` is answered from a local model between steps.
    pub fn answers_locally(&self, index: usize) -> bool {
        self.local.iter().any(|(model, _)| model.tool == index)
    }

    /// Tool `index`'s feedback to its latest pose from its local model (multirate: the
    /// full solve refreshes the model, the loop answers every pose at once), advanced by the
    /// time between the poses' stamps (at most `LOCAL_STEP_MAX`). None for a tool without
    /// one (not coupled) or before its first step.
    pub fn answer_locally(&mut self, index: usize) -> Option<WrenchStamped> {
        let state = self.tools.get(index)?;
        let stamp = state.last_pose?;
        let device = state.tool.world_from_tool;
        let (model, answered) = self.local.iter_mut().find(|(model, _)| model.tool == index)?;
        let dt = answered.map_or(0.0, |last| (stamp.as_secs() - last.as_secs()).clamp(0.0, LOCAL_STEP_MAX));
        *answered = Some(stamp);
        let answer = model.answer(&device, dt);
        Some(outputs::local_feedback(&answer, stamp, &self.frame_id))
    }
}

/// The longest time one local answer advances its model (s): a gap in the pose stream (a
/// dropped packet) is not integrated as one long step.
const LOCAL_STEP_MAX: f64 = 0.005;

/// One tool as a step takes it.
#[derive(Debug, Clone)]
struct ToolInput {
    pose: Isometry3<f64>,
    force: Vector3<f64>,
    last_pose: Option<Time>,
    contact_stiffness: f64,
}

/// A step's inputs: each tool, and which tools' simulated tools start at their devices.
#[derive(Debug, Clone)]
pub struct StepInput {
    tools: Vec<ToolInput>,
    seat: Vec<bool>,
    stamp: Time,
}

/// A step's outcome, from wherever the solver ran.
pub struct StepOutput {
    report: StepReport,
    positions: Vec<Vector3<f64>>,
    local: Vec<LocalModel>,
    solver_ms: f64,
    input: StepInput,
}

/// One step of `engine` with `input`'s tools, and the local models after it.
pub fn run_step(engine: &mut SolverEngine, input: &StepInput) -> Result<StepOutput, PipelineError> {
    for (index, input) in input.tools.iter().enumerate() {
        let tool = engine.tool_mut(index)?;
        tool.world_from_tool = input.pose;
        tool.applied_force = input.force;
        tool.contact_stiffness = input.contact_stiffness;
    }
    for (index, _) in input.seat.iter().enumerate().filter(|(_, seat)| **seat) {
        engine.seat_simulated_tool(index);
    }
    let start = Instant::now();
    let report = engine.step()?;
    let local = engine.local_models()?;
    let positions = engine.positions();
    let solver_ms = start.elapsed().as_secs_f64() * 1e3;
    Ok(StepOutput { report, positions, local, solver_ms, input: input.clone() })
}
