//! The CPU path (rayon). Reductions sum fixed-size chunks in index order, so a run is
//! bit-for-bit repeatable whatever the thread scheduling (replays depend on it).

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

mod contact;
mod explicit;
mod implicit;
mod recovery;

use crate::amg::{Amg, Csr};
use crate::contact::{Positions, Surface, SurfaceContact, ToolCore, CONTACT_NODES};
use crate::haptic::{LocalModel, LocalQuery, LocalTurning, PendingContact, StiffnessRule};
use crate::kernels::{self, ContactTool, SpringTerms};
use crate::model::MassSpringModel;
use crate::tool::{spread_weights, ContactModel, Tool};
use crate::{Integrator, Preconditioner, Reaction, SolverError, SolverParams, StepReport};
use defvol_core::math::Real;

/// Nodes per parallel chunk; also the unit of the deterministic reductions.
const CHUNK: usize = 1024;

/// A sparse matrix as (row, column, value) entries.
pub type Triplets = Vec<(usize, usize, f64)>;

/// Outcome of one linear solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CgStats {
    pub iterations: u32,
    pub relative_residual: f64,
}

struct Snapshot<T: Real> {
    u: Vec<Vector3<T>>,
    v: Vec<Vector3<T>>,
    history: Vec<Vector3<T>>,
    history_valid: bool,
    proxies: Vec<Proxy>,
}

/// The simulated tool of a coupled tool: a body of the implicit system, pulled by the
/// coupling towards the device and stopped by the contact.
#[derive(Debug, Clone)]
struct Proxy {
    tool: usize,
    /// Simulated tip position and velocity (world).
    x: Vector3<f64>,
    v: Vector3<f64>,
    /// The device's tip at the last step, for its velocity.
    device: Vector3<f64>,
    device_velocity: Vector3<f64>,
    /// With a rotational coupling: the simulated tool's orientation and angular velocity,
    /// the device's at the last step and its angular velocity, and the row of the system
    /// the tool turns on.
    turning: Option<Turning>,
}

/// The rotational state of a simulated tool (`RotationalCoupling`).
#[derive(Debug, Clone)]
struct Turning {
    orientation: nalgebra::UnitQuaternion<f64>,
    omega: Vector3<f64>,
    device: nalgebra::UnitQuaternion<f64>,
    device_omega: Vector3<f64>,
    row: usize,
}

/// The nodes' world positions as the contact queries read them, one node at a time.
struct Displaced<'a, T: Real> {
    rest: &'a [Vector3<f64>],
    u: &'a [Vector3<T>],
}

impl<T: Real> Positions for Displaced<'_, T> {
    fn at(&self, node: u32) -> Vector3<f64> {
        self.rest[node as usize] + self.u[node as usize].map(T::to_f64)
    }
}

/// Rows a contact's terms span: its nodes', its simulated tool's, and the row it turns on.
pub(crate) const TERM_ROWS: usize = CONTACT_NODES + 2;

/// A surface contact as the implicit system uses it: rows (nodes, then the proxy's) with
/// the penetration's gradient on each (∇φ), and h² k.
#[derive(Debug, Clone, Copy)]
struct ContactRows<T: Real> {
    rows: [usize; TERM_ROWS],
    gradients: [Vector3<T>; TERM_ROWS],
    h2k: T,
    /// φ̇ at the step's start, Σ g·v over the rows.
    normal_speed: f64,
}

/// A surface contact's terms in the implicit system, in f64 for both backends: its rows
/// (the nodes', then the simulated tool's; `usize::MAX` where none), the gradient of the
/// penetration φ on each, h² k, and the right-hand side's factor h k (φ + h φ̇).
#[derive(Debug, Clone, Copy)]
pub(crate) struct ContactTerms {
    pub rows: [usize; TERM_ROWS],
    pub gradients: [Vector3<f64>; TERM_ROWS],
    pub h2k: f64,
    pub rhs_scale: f64,
    /// φ̇ at the step's start, Σ g·v over the rows.
    pub normal_speed: f64,
}

/// A contact's friction in the step being solved: one rank-one damper along a tangent of
/// the contact (`terms`, h·damping in `h2k`), braking the tool's sliding on the surface.
#[derive(Debug, Clone, Copy)]
pub(crate) struct FrictionTerm {
    tool: usize,
    /// Where it acts (the contact point) and its tangent.
    at: Vector3<f64>,
    tangent: Vector3<f64>,
    /// The damper's coefficient (N·s/m).
    damping: f64,
    terms: ContactTerms,
}

/// The friction a step left: on the tool and on the rows of the nodes it brakes (N).
#[derive(Debug, Clone)]
struct FrictionForce {
    tool: usize,
    at: Vector3<f64>,
    on_tool: Vector3<f64>,
    on_nodes: Vec<(usize, Vector3<f64>)>,
}

impl ContactTerms {
    /// The rows the contact touches, with the gradient on each.
    pub(crate) fn touched(&self) -> impl Iterator<Item = (usize, &Vector3<f64>)> {
        self.rows.iter().zip(&self.gradients).filter(|(row, _)| **row != usize::MAX).map(|(row, g)| (*row, g))
    }
}

/// The coupling force on the simulated tool and its stiffness and damping scaled down
/// when the force saturates (`Coupling::pull`).
fn coupling_force(tool: &Tool, proxy: &Proxy) -> (Vector3<f64>, f64, f64, bool) {
    tool.coupling
        .map_or((Vector3::zeros(), 0.0, 0.0, false), |c| c.pull(tool.tip() - proxy.x, proxy.device_velocity - proxy.v))
}

/// The device's orientation relative to the simulated tool's, as axis times angle.
fn turn_error(turning: &Turning) -> Vector3<f64> {
    (turning.device * turning.orientation.inverse()).scaled_axis()
}

/// The rotational coupling's torque on the simulated tool, with its stiffness and damping
/// scaled down when it saturates (`RotationalCoupling::twist`).
fn twisting(tool: &Tool, turning: &Turning) -> (Vector3<f64>, f64, f64, bool) {
    tool.rotational_coupling.map_or((Vector3::zeros(), 0.0, 0.0, false), |r| {
        r.twist(turn_error(turning), turning.device_omega - turning.omega)
    })
}

/// A running mass-spring simulation on the CPU in precision `T`.
pub struct Simulation<T: Real> {
    params: SolverParams,
    springs: Vec<[u32; 2]>,
    rest_length: Vec<T>,
    stiffness: Vec<T>,
    damping: Vec<T>,
    offsets: Vec<u32>,
    adjacency: Vec<[u32; 2]>,
    mass: Vec<T>,
    fixed: Vec<bool>,
    /// Rest positions (f64, for output) and rest edge vectors (per spring, precision T).
    rest: Vec<Vector3<f64>>,
    rest_edge: Vec<Vector3<T>>,
    divergence_energy: f64,
    divergence_distance: f64,
    /// Displacements from rest. Storing them instead of positions keeps f32 resolution
    /// relative to the deformation, not to the body's distance from the origin.
    u: Vec<Vector3<T>>,
    v: Vec<Vector3<T>>,
    /// Previous displacements (position Verlet) or accelerations (velocity Verlet).
    history: Vec<Vector3<T>>,
    history_valid: bool,
    external: Vec<Vector3<T>>,
    tools: Vec<Tool>,
    surface: Surface,
    /// Surface contacts of the step being solved (the active set), and at the end of the last.
    active_contacts: Vec<SurfaceContact>,
    contacts: Vec<SurfaceContact>,
    contact_rows: Vec<ContactRows<T>>,
    /// Rows (rhs, block-Jacobi inverse) as they were before the contacts were added.
    rows_before_contacts: Vec<(usize, Vector3<T>, Matrix3<T>)>,
    proxies: Vec<Proxy>,
    /// Diagonal blocks of the proxies' rows (after the nodes' in every solver vector).
    proxy_diag: Vec<Matrix3<T>>,
    /// Each tool's tip at the last step and its velocity since (friction of uncoupled tools).
    tool_tips: Vec<Option<Vector3<f64>>>,
    tool_velocities: Vec<Vector3<f64>>,
    /// The friction terms of the system being solved, and the forces of the last step's.
    frictions: Vec<FrictionTerm>,
    friction_forces: Vec<FrictionForce>,
    step: u64,
    time: f64,
    // Workspace of the implicit solve.
    terms: Vec<SpringTerms<T>>,
    diag: Vec<Matrix3<T>>,
    precond: Vec<Matrix3<T>>,
    rhs: Vec<Vector3<T>>,
    dv: Vec<Vector3<T>>,
    /// Δv of the step before the last, for the extrapolated CG start.
    dv_previous: Vec<Vector3<T>>,
    solves: u64,
    r: Vec<Vector3<T>>,
    z: Vec<Vector3<T>>,
    p: Vec<Vector3<T>>,
    q: Vec<Vector3<T>>,
    last_cg: CgStats,
    amg: Option<AmgState>,
    /// CG runs with the multigrid preconditioner (from the start with `Amg`; with `Auto`
    /// once block Jacobi needs too many iterations).
    multigrid: bool,
}

/// A multigrid hierarchy built at some step, reused while it keeps CG fast.
struct AmgState {
    amg: Amg,
    /// Iterations of the first solve with this hierarchy; a rebuild follows when a solve
    /// needs twice as many.
    iterations_at_build: u32,
    stale: bool,
}

impl<T: Real> Simulation<T> {
    pub fn new(model: &MassSpringModel, params: SolverParams, tools: Vec<Tool>) -> Result<Self, SolverError> {
        params.validate()?;
        let n = model.node_count();
        let conv = |v: &[f64]| v.iter().map(|x| T::of(*x)).collect::<Vec<T>>();
        let rest_edge =
            model.springs.iter().map(|[a, b]| (model.rest[*b as usize] - model.rest[*a as usize]).map(T::of)).collect();
        let (lo, hi) = defvol_core::mesh::bounds(&model.rest);
        let multigrid = params.preconditioner == Preconditioner::Amg;
        Ok(Self {
            params,
            springs: model.springs.clone(),
            rest_length: conv(&model.rest_length),
            stiffness: conv(&model.stiffness),
            damping: conv(&model.damping),
            offsets: model.offsets.clone(),
            adjacency: model.adjacency.clone(),
            mass: conv(&model.mass),
            fixed: model.fixed.clone(),
            divergence_energy: model.divergence_energy(),
            divergence_distance: 2.0 * (hi - lo).norm(),
            u: vec![Vector3::zeros(); n],
            v: vec![Vector3::zeros(); n],
            history: vec![Vector3::zeros(); n],
            history_valid: false,
            external: vec![Vector3::zeros(); n],
            tools,
            surface: Surface::new(&model.boundary, &model.rest),
            active_contacts: Vec::new(),
            contacts: Vec::new(),
            contact_rows: Vec::new(),
            rows_before_contacts: Vec::new(),
            proxies: Vec::new(),
            proxy_diag: Vec::new(),
            tool_tips: Vec::new(),
            tool_velocities: Vec::new(),
            frictions: Vec::new(),
            friction_forces: Vec::new(),
            step: 0,
            time: 0.0,
            terms: vec![
                SpringTerms { force: Vector3::zeros(), kv: Vector3::zeros(), block: Matrix3::zeros() };
                model.springs.len()
            ],
            diag: vec![Matrix3::zeros(); n],
            precond: vec![Matrix3::zeros(); n],
            rhs: vec![Vector3::zeros(); n],
            dv: vec![Vector3::zeros(); n],
            dv_previous: vec![Vector3::zeros(); n],
            solves: 0,
            r: vec![Vector3::zeros(); n],
            z: vec![Vector3::zeros(); n],
            p: vec![Vector3::zeros(); n],
            q: vec![Vector3::zeros(); n],
            last_cg: CgStats { iterations: 0, relative_residual: 0.0 },
            amg: None,
            multigrid,
            rest: model.rest.clone(),
            rest_edge,
        })
    }

    pub fn params(&self) -> &SolverParams {
        &self.params
    }

    /// Displacements from the rest shape.
    pub fn displacements(&self) -> &[Vector3<T>] {
        &self.u
    }

    pub fn velocities(&self) -> &[Vector3<T>] {
        &self.v
    }

    pub fn time(&self) -> f64 {
        self.time
    }

    pub fn step_index(&self) -> u64 {
        self.step
    }

    pub fn tools(&self) -> &[Tool] {
        &self.tools
    }

    pub fn last_cg(&self) -> CgStats {
        self.last_cg
    }

    /// Positions in f64 (rest + displacement, for output and comparisons).
    pub fn positions_f64(&self) -> Vec<Vector3<f64>> {
        self.rest.iter().zip(&self.u).map(|(r, u)| r + u.map(T::to_f64)).collect()
    }

    /// World position of node i in precision T (contact tests).
    fn world(&self, i: usize) -> Vector3<T> {
        self.rest[i].map(T::of) + self.u[i]
    }

    /// Mutable access to a tool (pose, applied force) between steps.
    pub fn tool_mut(&mut self, index: usize) -> Result<&mut Tool, SolverError> {
        let count = self.tools.len();
        self.tools.get_mut(index).ok_or(SolverError::NoSuchTool { index, count })
    }

    /// Puts coupled tool `index`'s simulated tool where its device is, at rest: for a
    /// device whose first pose arrives after the simulation started (the tool had been
    /// waiting at its configured pose, maybe inside the organ).
    pub fn seat_simulated_tool(&mut self, index: usize) {
        let Some(pose) = self.tools.get(index).map(|t| t.world_from_tool) else { return };
        if let Some(proxy) = self.proxies.iter_mut().find(|p| p.tool == index) {
            let tip = pose.translation.vector;
            (proxy.x, proxy.v, proxy.device, proxy.device_velocity) = (tip, Vector3::zeros(), tip, Vector3::zeros());
            if let Some(turning) = &mut proxy.turning {
                (turning.orientation, turning.device) = (pose.rotation, pose.rotation);
                (turning.omega, turning.device_omega) = (Vector3::zeros(), Vector3::zeros());
            }
        }
    }

    /// Sets the state (e.g. to restart from a recorded one).
    pub fn set_state(&mut self, x: &[Vector3<f64>], v: &[Vector3<f64>]) {
        self.u = x.iter().zip(&self.rest).map(|(p, r)| (p - r).map(T::of)).collect();
        self.v = v.iter().map(|p| p.map(T::of)).collect();
        self.history_valid = false;
        self.solves = 0;
        self.proxies.clear();
        self.tool_tips.clear();
        self.surface.moved(f64::INFINITY);
    }

    /// Where tool `index` is in the simulation: the device's pose, or for a coupled tool
    /// the simulated tool's (the device's orientation at the simulated tip).
    pub fn simulated_pose(&self, index: usize) -> Option<nalgebra::Isometry3<f64>> {
        let tool = self.tools.get(index)?;
        let mut pose = tool.world_from_tool;
        if let Some(p) = self.proxies.iter().find(|p| p.tool == index) {
            pose.translation.vector = p.x;
            if let Some(turning) = &p.turning {
                pose.rotation = turning.orientation;
            }
        }
        Some(pose)
    }

    /// The surface contacts at the end of the last step (those that push: not the rows
    /// that only carry a multi-plane hold's stiffness into the step).
    pub fn contacts(&self) -> &[SurfaceContact] {
        &self.contacts
    }

    /// The force each node receives from the surface contacts at the end of the last step
    /// (what the mesh feels of the tools).
    pub fn contact_forces_on_nodes(&self) -> Vec<Vector3<f64>> {
        let mut forces = vec![Vector3::zeros(); self.u.len()];
        add_contact_forces(&self.contacts, &mut forces);
        for (node, force) in self.friction_forces.iter().flat_map(|f| &f.on_nodes) {
            forces[*node] += force;
        }
        forces
    }

    /// Back to the rest shape at t = 0.
    pub fn reset(&mut self) {
        self.u.iter_mut().for_each(|u| *u = Vector3::zeros());
        self.v.iter_mut().for_each(|v| *v = Vector3::zeros());
        self.dv.iter_mut().for_each(|v| *v = Vector3::zeros());
        self.solves = 0;
        self.history_valid = false;
        self.step = 0;
        self.time = 0.0;
        self.proxies.clear();
        self.tool_tips.clear();
        self.surface.moved(f64::INFINITY);
    }

    /// Advances one step with the configured integrator.
    pub fn step(&mut self) -> Result<StepReport, SolverError> {
        let tools = self.prepare_step()?;
        let saved = self.snapshot();
        match self.params.integrator {
            Integrator::ExplicitEuler => self.explicit_euler(&tools),
            Integrator::Verlet => self.verlet(&tools),
            Integrator::VelocityVerlet => self.velocity_verlet(&tools),
            Integrator::ImplicitEuler => self.implicit_euler(&tools),
        }
        self.finish_steps(saved, 1)
    }

    /// Validates tool inputs and spreads commanded forces; returns the contact tools.
    pub(crate) fn prepare_step(&mut self) -> Result<Vec<ContactTool<T>>, SolverError> {
        let tools = self.contact_tools()?;
        self.spread_external_forces()?;
        self.follow_devices();
        self.active_contacts = self.detect_contacts(true);
        Ok(tools)
    }

    fn spring_energy(&self) -> f64 {
        let (springs, u, rest, k) = (&self.springs, &self.u, &self.rest_length, &self.stiffness);
        chunked_sum(springs.len(), |e| {
            let [a, b] = springs[e];
            let stretch = (self.rest_edge[e] + u[b as usize] - u[a as usize]).norm().to_f64() - rest[e].to_f64();
            0.5 * k[e].to_f64() * stretch * stretch
        })
    }

    fn report(&self) -> StepReport {
        let g = Vector3::from(self.params.gravity);
        let mut kinetic =
            chunked_sum(self.u.len(), |i| 0.5 * self.mass[i].to_f64() * self.v[i].norm_squared().to_f64());
        let gravity = chunked_sum(self.u.len(), |i| -self.mass[i].to_f64() * g.dot(&self.u[i].map(T::to_f64)));
        let mut contact_energy = 0.0;
        let mut reactions = Vec::with_capacity(self.tools.len());
        for (index, tool) in self.tools.iter().enumerate() {
            // The mesh pushes back the tool's own commanded force, and every contact force.
            let mut force = -tool.applied_force;
            let mut torque = Vector3::zeros();
            let mut friction = Vector3::zeros();
            let tip = self.simulated_pose(index).map_or_else(|| tool.tip(), |pose| pose.translation.vector);
            match tool.contact {
                ContactModel::Nodes => {
                    let c = tool.contact_params();
                    let (a, b) = (c.a.map(T::of), c.b.map(T::of));
                    let (radius, stiffness) = (T::of(c.radius), T::of(c.stiffness));
                    for i in 0..self.u.len() {
                        let p = &self.world(i);
                        if let Some((f, _)) = kernels::contact(p, &a, &b, radius, stiffness) {
                            let f = f.map(T::to_f64);
                            contact_energy += 0.5 * f.norm_squared() / c.stiffness;
                            force -= f;
                            torque -= (p.map(T::to_f64) - tip).cross(&f);
                        }
                    }
                }
                ContactModel::Surface => {
                    for c in self.contacts.iter().filter(|c| c.tool == index) {
                        contact_energy += 0.5 * c.stiffness * c.depth * c.depth;
                        force -= c.force();
                        torque -= (c.at - tip).cross(&c.force());
                    }
                    for f in self.friction_forces.iter().filter(|f| f.tool == index) {
                        friction += f.on_tool;
                        force += f.on_tool;
                        torque += (f.at - tip).cross(&f.on_tool);
                    }
                }
            }
            let mut coupling_saturated = false;
            if let (Some(proxy), Some(coupling)) = (self.proxies.iter().find(|p| p.tool == index), tool.coupling) {
                // The device feels the coupling, not the contact: they agree once it settles.
                let (pull, _, _, saturated) = coupling_force(tool, proxy);
                force = -pull - tool.applied_force;
                coupling_saturated = saturated;
                kinetic += 0.5 * coupling.mass * proxy.v.norm_squared();
                contact_energy += 0.5 * coupling.stiffness * (tool.tip() - proxy.x).norm_squared();
                if let (Some(turning), Some(rotational)) = (&proxy.turning, tool.rotational_coupling) {
                    // The device feels the torque that holds the tool's orientation.
                    let (twist, _, _, saturated) = twisting(tool, turning);
                    torque = -twist;
                    coupling_saturated |= saturated;
                    kinetic += 0.5 * rotational.inertia * turning.omega.norm_squared();
                    contact_energy += 0.5 * rotational.stiffness * turn_error(turning).norm_squared();
                }
            }
            reactions.push(Reaction {
                force: force.into(),
                torque: torque.into(),
                friction: friction.into(),
                coupling_saturated,
                passed_through: self.passed_through(index),
            });
        }
        let max_displacement = self.u.iter().map(|u| u.norm().to_f64()).fold(0.0, f64::max);
        StepReport {
            step: self.step,
            time: self.time,
            cg_iterations: self.last_cg.iterations,
            residual: self.last_cg.relative_residual,
            kinetic_energy: kinetic,
            potential_energy: self.spring_energy() + gravity + contact_energy,
            max_displacement,
            reactions,
        }
    }
}

/// Adds each penetrating contact's force to its feature's nodes, by their weights.
fn add_contact_forces<T: Real>(contacts: &[SurfaceContact], forces: &mut [Vector3<T>]) {
    for c in contacts.iter().filter(|c| c.depth > 0.0) {
        for (node, force) in c.node_forces() {
            forces[node as usize] += force.map(T::of);
        }
    }
}

/// Deterministic parallel sum of `f(0..n)` in f64.
fn chunked_sum(n: usize, f: impl Fn(usize) -> f64 + Sync) -> f64 {
    let partials: Vec<f64> =
        (0..n.div_ceil(CHUNK)).into_par_iter().map(|c| (c * CHUNK..((c + 1) * CHUNK).min(n)).map(&f).sum()).collect();
    partials.into_iter().sum()
}
