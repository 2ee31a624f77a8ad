//! Mass-spring dynamics on tetrahedral meshes (seed 000, sections 3-4): explicit Euler,
//! Verlet, velocity Verlet, and implicit Euler in the Baraff-Witkin form solved by
//! preconditioned conjugate gradient. [`cpu::Simulation`] is the CPU path (f32, or f64 as the
//! reference); `gpu.rs` (feature `gpu`) runs the same kernels in WGSL (`solver.wgsl`).

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

pub mod amg;
#[cfg(feature = "gpu")]
pub mod coarse;
pub mod contact;
pub mod cpu;
pub mod engine;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod haptic;
pub mod kernels;
pub mod model;
pub mod tool;

use serde::{Deserialize, Serialize};

pub use cpu::Simulation;
pub use engine::{SolverEngine, SolverEngineError};
pub use haptic::{LocalAnswer, LocalContact, LocalModel, LocalTurning};
pub use model::{FixedNodes, MassSpringModel, Material, TissueRow};
pub use tool::{ContactModel, Coupling, Friction, RotationalCoupling, Tool, ToolShape};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SolverError {
    #[error("parameter `{name}` = {value} cannot work: {why}")]
    BadParameter { name: String, value: f64, why: String },
    #[error("simulation diverged at step {step} (t = {time:.4} s): {reason}; the last stable state was kept")]
    Diverged { step: u64, time: f64, reason: String },
    #[error(
        "the mesh fell freely, {distance:.3} m by step {step} (t = {time:.4} s): no node is held (the scene's \
         `fixed` selects none; `fixed: {{kind: lowest}}` rests it on its lowest layer); the last state \
         before was kept"
    )]
    FellFreely { step: u64, time: f64, distance: f64 },
    #[error("tool {index} does not exist ({count} tools)")]
    NoSuchTool { index: usize, count: usize },
    #[error("tool {index}: {what} is not finite")]
    NonFiniteToolInput { index: usize, what: &'static str },
}

/// Time integration scheme.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Integrator {
    ExplicitEuler,
    Verlet,
    VelocityVerlet,
    ImplicitEuler,
}

impl Integrator {
    pub const ALL: [Integrator; 4] =
        [Integrator::ExplicitEuler, Integrator::Verlet, Integrator::VelocityVerlet, Integrator::ImplicitEuler];
    pub fn name(self) -> &'static str {
        match self {
            Integrator::ExplicitEuler => "explicit_euler",
            Integrator::Verlet => "verlet",
            Integrator::VelocityVerlet => "velocity_verlet",
            Integrator::ImplicitEuler => "implicit_euler",
        }
    }
}

/// Preconditioner of the implicit step's CG.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preconditioner {
    /// Inverse 3x3 diagonal blocks: cheap, on both backends; iterations grow with resolution.
    BlockJacobi,
    /// Smoothed-aggregation multigrid: few iterations, independent of resolution (on the
    /// GPU, the CPU-built hierarchy's V-cycle on the device, `coarse.rs`).
    Amg,
    /// Block Jacobi while CG converges within [`AUTO_AMG_ABOVE`] iterations, multigrid from
    /// the step after one that needed more. A V-cycle costs about six Jacobi iterations
    /// here, so small or mass-dominated systems (haptic rates, 1 ms steps) run Jacobi and
    /// stiff or large ones multigrid.
    Auto,
}

/// Block-Jacobi CG iterations beyond which `Preconditioner::Auto` turns to multigrid: about
/// where a step costs the same with either (see docs/perf/journal.md#when-auto-turns-to-multigrid).
pub const AUTO_AMG_ABOVE: u32 = 40;

/// Time stepping and linear-solver settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SolverParams {
    pub integrator: Integrator,
    /// Time step h (s).
    pub dt: f64,
    /// Gravity (m/s²), world frame.
    pub gravity: [f64; 3],
    /// CG stops when |r| <= tolerance · |b| ...
    pub cg_tolerance: f64,
    /// ... or after this many iterations.
    pub cg_max_iterations: u32,
    /// GPU only: iterations recorded between two residual read-backs.
    pub cg_check_interval: u32,
    pub preconditioner: Preconditioner,
}

impl Default for SolverParams {
    fn default() -> Self {
        Self {
            integrator: Integrator::ImplicitEuler,
            dt: 0.01,
            gravity: [0.0, 0.0, -9.81],
            cg_tolerance: 1e-4,
            cg_max_iterations: 1000,
            cg_check_interval: 16,
            preconditioner: Preconditioner::Auto,
        }
    }
}

impl SolverParams {
    pub fn validate(&self) -> Result<(), SolverError> {
        let bad = |name: &str, value: f64, why: &str| {
            Err(SolverError::BadParameter { name: name.into(), value, why: why.into() })
        };
        if !(self.dt.is_finite() && self.dt > 0.0) {
            return bad("dt", self.dt, "the time step must be positive and finite");
        }
        if let Some(g) = self.gravity.iter().find(|g| !g.is_finite()) {
            return bad("gravity", *g, "gravity must be finite");
        }
        if !(self.cg_tolerance.is_finite() && self.cg_tolerance > 0.0 && self.cg_tolerance < 1.0) {
            return bad("cg_tolerance", self.cg_tolerance, "a relative residual in (0, 1)");
        }
        if self.cg_max_iterations == 0 {
            return bad("cg_max_iterations", 0.0, "at least one iteration");
        }
        if self.cg_check_interval == 0 {
            return bad("cg_check_interval", 0.0, "at least one iteration between checks");
        }
        Ok(())
    }
}

/// The refusal of a batch of no steps.
pub(crate) fn empty_batch() -> SolverError {
    SolverError::BadParameter { name: "batch".into(), value: 0.0, why: "a batch is at least one step".into() }
}

/// What one step did: the CSV row of `defvol simulate` and the node's diagnostics.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct StepReport {
    pub step: u64,
    pub time: f64,
    pub cg_iterations: u32,
    /// Relative residual |r|/|b| of the last solve (0 for explicit schemes).
    pub residual: f64,
    pub kinetic_energy: f64,
    /// Spring + contact + gravity potential (gravity relative to the rest shape).
    pub potential_energy: f64,
    pub max_displacement: f64,
    /// The reaction on each tool, in the scene's order: what its haptic device renders.
    pub reactions: Vec<Reaction>,
}

impl StepReport {
    /// The reaction on tool `index` (none for a tool that does not exist).
    pub fn reaction(&self, index: usize) -> Reaction {
        self.reactions.get(index).copied().unwrap_or_default()
    }
}

/// What the mesh does to one tool: the force (N) and the torque about the tool's tip (N·m),
/// world frame. It includes the tool's own commanded force, pushed back. For a coupled
/// tool the force is the coupling's pull on the device, which is what a haptic device renders.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Reaction {
    pub force: [f64; 3],
    pub torque: [f64; 3],
    /// The surface's friction on the tool (N, world), part of `force` for a tool without a
    /// coupling (a coupled tool's device feels the coupling, which carries it).
    pub friction: [f64; 3],
    /// The coupling held the device back with its largest force this step (the device's
    /// pose ran away from the tool: a dropped packet, a teleport through the organ).
    pub coupling_saturated: bool,
    /// A surface-contact tool's tip lies inside the body with no contact holding it: it went
    /// through the surface (a teleport, or a step too long), and nothing pushes back.
    pub passed_through: bool,
}
