//! The CPU path (rayon). Reductions sum fixed-size chunks in index order, so a run is
//! bit-for-bit repeatable whatever the thread scheduling (replays depend on it).

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::amg::{Amg, Csr};
use super::contact::{Surface, SurfaceContact, ToolCore};
use super::kernels::{self, ContactTool, SpringTerms};
use super::model::MassSpringModel;
use super::tool::{spread_weights, ContactModel, Tool};
use super::{Integrator, Preconditioner, Reaction, SolverError, SolverParams, StepReport};
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
}

/// A surface contact as the implicit system uses it: rows (nodes, then the proxy's) with
/// their coefficients c in ∇φ = Σ c_r n, and h² k.
#[derive(Debug, Clone, Copy)]
struct ContactRows<T: Real> {
    rows: [usize; 4],
    coefficients: [T; 4],
    push: Vector3<T>,
    h2k: T,
}

/// The coupling force on the simulated tool and its stiffness and damping scaled down
/// when the force saturates.
fn coupling_force(tool: &Tool, proxy: &Proxy) -> (Vector3<f64>, f64, f64, bool) {
    let Some(c) = tool.coupling else { return (Vector3::zeros(), 0.0, 0.0, false) };
    let raw = (tool.tip() - proxy.x) * c.stiffness + (proxy.device_velocity - proxy.v) * c.damping;
    let magnitude = raw.norm();
    if magnitude > c.max_force {
        let scale = c.max_force / magnitude;
        (raw * scale, c.stiffness * scale, c.damping * scale, true)
    } else {
        (raw, c.stiffness, c.damping, false)
    }
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

    /// Sets the state (e.g. to restart from a recorded one).
    pub fn set_state(&mut self, x: &[Vector3<f64>], v: &[Vector3<f64>]) {
        self.u = x.iter().zip(&self.rest).map(|(p, r)| (p - r).map(T::of)).collect();
        self.v = v.iter().map(|p| p.map(T::of)).collect();
        self.history_valid = false;
        self.solves = 0;
        self.proxies.clear();
    }

    /// Where tool `index` is in the simulation: the device's pose, or for a coupled tool
    /// the simulated tool's (the device's orientation at the simulated tip).
    pub fn simulated_pose(&self, index: usize) -> Option<nalgebra::Isometry3<f64>> {
        let tool = self.tools.get(index)?;
        let mut pose = tool.world_from_tool;
        if let Some(p) = self.proxies.iter().find(|p| p.tool == index) {
            pose.translation.vector = p.x;
        }
        Some(pose)
    }

    /// The surface contacts at the end of the last step.
    pub fn contacts(&self) -> &[SurfaceContact] {
        &self.contacts
    }

    /// The force each node receives from the surface contacts at the end of the last step
    /// (what the mesh feels of the tools).
    pub fn contact_forces_on_nodes(&self) -> Vec<Vector3<f64>> {
        let mut forces = vec![Vector3::zeros(); self.u.len()];
        add_contact_forces(&self.contacts, &mut forces);
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
    }

    /// Checks every tool; returns those whose contact acts node by node (the kernels').
    fn contact_tools(&self) -> Result<Vec<ContactTool<T>>, SolverError> {
        for (index, tool) in self.tools.iter().enumerate() {
            let c = tool.contact_params();
            if !(c.a.iter().chain(c.b.iter()).all(|v| v.is_finite())) {
                return Err(SolverError::NonFiniteToolInput { index, what: "pose" });
            }
            if let Some(coupling) = &tool.coupling {
                coupling.validate(index)?;
                let why = if tool.contact != ContactModel::Surface {
                    Some("a coupled tool needs surface contact")
                } else if self.params.integrator != super::Integrator::ImplicitEuler {
                    Some("a coupled tool needs the implicit_euler integrator")
                } else {
                    None
                };
                if let Some(why) = why {
                    return Err(SolverError::BadParameter {
                        name: format!("tools[{index}].coupling"),
                        value: coupling.stiffness,
                        why: why.into(),
                    });
                }
            }
        }
        self.tools
            .iter()
            .filter(|tool| tool.contact == ContactModel::Nodes)
            .map(|tool| {
                let c = tool.contact_params();
                Ok(ContactTool {
                    a: c.a.map(T::of),
                    b: c.b.map(T::of),
                    radius: T::of(c.radius),
                    stiffness: T::of(c.stiffness),
                })
            })
            .collect()
    }

    /// Spreads every tool's commanded force over the nodes near its tip.
    fn spread_external_forces(&mut self) -> Result<(), SolverError> {
        self.external.iter_mut().for_each(|f| *f = Vector3::zeros());
        for (index, tool) in self.tools.iter().enumerate() {
            if !tool.applied_force.iter().all(|f| f.is_finite()) {
                return Err(SolverError::NonFiniteToolInput { index, what: "applied force" });
            }
            if tool.applied_force == Vector3::zeros() {
                continue;
            }
            let nodes = self.positions_f64();
            for (i, w) in spread_weights(&nodes, &tool.tip(), tool.spread_radius) {
                self.external[i as usize] += (tool.applied_force * w).map(T::of);
            }
        }
        Ok(())
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
        self.finish_step(saved)
    }

    /// Validates tool inputs and spreads commanded forces; returns the contact tools.
    pub(crate) fn prepare_step(&mut self) -> Result<Vec<ContactTool<T>>, SolverError> {
        let tools = self.contact_tools()?;
        self.spread_external_forces()?;
        self.follow_devices();
        self.active_contacts = self.detect_contacts(true);
        Ok(tools)
    }

    /// One simulated tool per coupled tool (made at the device when it first appears), the
    /// devices' velocities from their last poses, and the solver vectors sized to match.
    fn follow_devices(&mut self) {
        let coupled: Vec<usize> = (0..self.tools.len()).filter(|&i| self.tools[i].coupling.is_some()).collect();
        if !self.proxies.iter().map(|p| p.tool).eq(coupled.iter().copied()) {
            self.proxies = coupled
                .iter()
                .map(|&tool| {
                    let tip = self.tools[tool].tip();
                    Proxy { tool, x: tip, v: Vector3::zeros(), device: tip, device_velocity: Vector3::zeros() }
                })
                .collect();
            let rows = self.u.len() + self.proxies.len();
            self.rhs.resize(rows, Vector3::zeros());
            self.precond.resize(rows, Matrix3::zeros());
            for w in [&mut self.dv, &mut self.dv_previous, &mut self.r, &mut self.z, &mut self.p, &mut self.q] {
                w.resize(rows, Vector3::zeros());
            }
            self.proxy_diag = vec![Matrix3::zeros(); self.proxies.len()];
        }
        let dt = self.params.dt;
        for p in &mut self.proxies {
            let tip = self.tools[p.tool].tip();
            p.device_velocity = (tip - p.device) / dt;
            p.device = tip;
        }
    }

    /// The surface contacts of the surface-contact tools at the current positions; with
    /// `speculative`, those about to begin too (within half the radius or spacing).
    fn detect_contacts(&mut self, speculative: bool) -> Vec<SurfaceContact> {
        let cores: Vec<ToolCore> = (self.tools.iter().enumerate())
            .filter(|(_, tool)| tool.contact == ContactModel::Surface && tool.contact_stiffness > 0.0)
            .map(|(index, tool)| {
                let mut core = tool.contact_params();
                if let Some(p) = self.proxies.iter().find(|p| p.tool == index) {
                    let shift = p.x - core.a;
                    (core.a, core.b) = (core.a + shift, core.b + shift);
                }
                ToolCore { tool: index, core }
            })
            .collect();
        if cores.is_empty() {
            return Vec::new();
        }
        let x = self.positions_f64();
        self.surface.refit(&x);
        let radius = cores.iter().map(|c| c.core.radius).fold(f64::INFINITY, f64::min);
        let margin = if speculative { 0.5 * radius.min(self.surface.spacing()) } else { 0.0 };
        self.surface.detect(&cores, &x, margin)
    }

    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn external_forces(&self) -> &[Vector3<T>] {
        &self.external
    }

    fn snapshot(&self) -> Snapshot<T> {
        Snapshot {
            u: self.u.clone(),
            v: self.v.clone(),
            history: self.history.clone(),
            history_valid: self.history_valid,
            proxies: self.proxies.clone(),
        }
    }

    /// Takes a state computed elsewhere (the GPU) as this step's result, with the same
    /// reporting and divergence check as a CPU step.
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn accept_step(
        &mut self,
        u: Vec<Vector3<T>>,
        v: Vec<Vector3<T>>,
        cg: CgStats,
    ) -> Result<StepReport, SolverError> {
        let saved = self.snapshot();
        self.u = u;
        self.v = v;
        self.last_cg = cg;
        self.finish_step(saved)
    }

    fn finish_step(&mut self, saved: Snapshot<T>) -> Result<StepReport, SolverError> {
        self.step += 1;
        self.time += self.params.dt;
        self.contacts = self.detect_contacts(false);
        let report = self.report();
        if let Some(reason) = self.divergence(&report) {
            let failed = (self.step, self.time);
            self.u = saved.u;
            self.v = saved.v;
            self.history = saved.history;
            self.history_valid = saved.history_valid;
            self.proxies = saved.proxies;
            self.step -= 1;
            self.time -= self.params.dt;
            return Err(SolverError::Diverged { step: failed.0, time: failed.1, reason });
        }
        Ok(report)
    }

    fn divergence(&self, report: &StepReport) -> Option<String> {
        if !self.u.iter().chain(self.v.iter()).all(|p| p.iter().all(|c| c.is_finite())) {
            return Some("non-finite positions or velocities".into());
        }
        let internal = report.kinetic_energy + self.spring_energy();
        if internal > self.divergence_energy {
            return Some(format!(
                "energy grew to {internal:.3e} J, beyond {:.3e} J (every spring stretched by its own length)",
                self.divergence_energy
            ));
        }
        if report.max_displacement > self.divergence_distance {
            return Some(format!("a node moved {:.3e} m, twice the mesh's size", report.max_displacement));
        }
        None
    }

    /// Forces on every node at the current (x, v); `v_eval` overrides the velocities.
    fn forces(&self, tools: &[ContactTool<T>], v_eval: &[Vector3<T>]) -> Vec<Vector3<T>> {
        let g = Vector3::from(self.params.gravity).map(T::of);
        let h = T::of(self.params.dt);
        let spring_forces: Vec<Vector3<T>> = (0..self.springs.len())
            .into_par_iter()
            .with_min_len(CHUNK)
            .map(|e| {
                let [a, b] = self.springs[e];
                let (a, b) = (a as usize, b as usize);
                let d = self.rest_edge[e] + self.u[b] - self.u[a];
                kernels::spring_force(
                    &d,
                    &v_eval[a],
                    &v_eval[b],
                    self.rest_length[e],
                    self.stiffness[e],
                    self.damping[e],
                )
            })
            .collect();
        let terms: Vec<SpringTerms<T>> = spring_forces
            .into_iter()
            .map(|force| SpringTerms { force, kv: Vector3::zeros(), block: Matrix3::zeros() })
            .collect();
        let mut forces = (0..self.u.len())
            .into_par_iter()
            .with_min_len(CHUNK)
            .map(|i| {
                let adj = &self.adjacency[self.offsets[i] as usize..self.offsets[i + 1] as usize];
                kernels::node_terms(
                    i,
                    adj,
                    &self.springs,
                    &terms,
                    self.mass[i],
                    self.fixed[i],
                    &self.world(i),
                    &v_eval[i],
                    &self.external[i],
                    &g,
                    tools,
                    h,
                )
                .force
            })
            .collect::<Vec<_>>();
        // Explicit updates hold fixed nodes whatever their force.
        add_contact_forces(&self.active_contacts, &mut forces);
        forces
    }

    fn explicit_euler(&mut self, tools: &[ContactTool<T>]) {
        let h = T::of(self.params.dt);
        let f = self.forces(tools, &self.v);
        let (mass, fixed) = (&self.mass, &self.fixed);
        self.u.par_iter_mut().zip(self.v.par_iter_mut()).enumerate().for_each(|(i, (x, v))| {
            if fixed[i] {
                *v = Vector3::zeros();
                return;
            }
            *x += *v * h;
            *v += f[i] * (h / mass[i]);
        });
    }

    /// Position (Störmer) Verlet. The velocity (for damping and reports) is the half-step
    /// difference plus half a step of acceleration: second order, like the positions.
    fn verlet(&mut self, tools: &[ContactTool<T>]) {
        let h = T::of(self.params.dt);
        if !self.history_valid {
            self.history = self.u.iter().zip(&self.v).map(|(u, v)| u - v * h).collect();
            self.history_valid = true;
        }
        let f = self.forces(tools, &self.v);
        let (mass, fixed) = (&self.mass, &self.fixed);
        let two = T::of(2.0);
        (self.u.par_iter_mut(), self.v.par_iter_mut(), self.history.par_iter_mut())
            .into_par_iter()
            .enumerate()
            .for_each(|(i, (x, v, prev))| {
                if fixed[i] {
                    *v = Vector3::zeros();
                    *prev = *x;
                    return;
                }
                let accel = f[i] / mass[i];
                let next = *x * two - *prev + accel * (h * h);
                *v = (next - *x) / h + accel * (h * T::of(0.5));
                *prev = *x;
                *x = next;
            });
    }

    /// Velocity Verlet; the damping force at the new positions uses the predicted velocity.
    fn velocity_verlet(&mut self, tools: &[ContactTool<T>]) {
        let h = T::of(self.params.dt);
        let half = T::of(0.5);
        if !self.history_valid {
            let f = self.forces(tools, &self.v);
            self.history = f.iter().zip(&self.mass).map(|(f, m)| f / *m).collect();
            self.history_valid = true;
        }
        let fixed = &self.fixed;
        let accel = &self.history;
        self.u.par_iter_mut().zip(self.v.par_iter()).enumerate().for_each(|(i, (x, v))| {
            if !fixed[i] {
                *x += v * h + accel[i] * (half * h * h);
            }
        });
        let predicted: Vec<Vector3<T>> = self.v.iter().zip(accel).map(|(v, a)| v + a * h).collect();
        let f = self.forces(tools, &predicted);
        let mass = &self.mass;
        self.v.par_iter_mut().zip(self.history.par_iter_mut()).enumerate().for_each(|(i, (v, a))| {
            let a_new = f[i] / mass[i];
            *v = if fixed[i] { Vector3::zeros() } else { *v + (*a + a_new) * (half * h) };
            *a = a_new;
        });
    }

    /// Assembles A Δv = b at the current state (spring pass, then node gather).
    pub(crate) fn assemble(&mut self, tools: &[ContactTool<T>]) {
        let h = T::of(self.params.dt);
        let g = Vector3::from(self.params.gravity).map(T::of);
        let (u, v, rest_edge) = (&self.u, &self.v, &self.rest_edge);
        let (springs, rest, k, d) = (&self.springs, &self.rest_length, &self.stiffness, &self.damping);
        self.terms.par_iter_mut().with_min_len(CHUNK).enumerate().for_each(|(e, t)| {
            let [a, b] = springs[e];
            let (a, b) = (a as usize, b as usize);
            let edge = rest_edge[e] + u[b] - u[a];
            *t = kernels::spring_terms(&edge, &v[a], &v[b], rest[e], k[e], d[e], h);
        });
        let x: Vec<Vector3<T>> = (0..u.len()).map(|i| self.world(i)).collect();
        let terms = &self.terms;
        let (offsets, adjacency, mass, fixed, external) =
            (&self.offsets, &self.adjacency, &self.mass, &self.fixed, &self.external);
        (self.rhs.par_iter_mut(), self.diag.par_iter_mut(), self.precond.par_iter_mut())
            .into_par_iter()
            .with_min_len(CHUNK)
            .enumerate()
            .for_each(|(i, (rhs, diag, precond))| {
                let adj = &adjacency[offsets[i] as usize..offsets[i + 1] as usize];
                let t = kernels::node_terms(
                    i,
                    adj,
                    springs,
                    terms,
                    mass[i],
                    fixed[i],
                    &x[i],
                    &v[i],
                    &external[i],
                    &g,
                    tools,
                    h,
                );
                *rhs = t.rhs;
                *diag = t.diag;
                *precond = t.precond;
            });
        self.assemble_tools();
    }

    /// The simulated tools' rows and the surface contacts' terms (few: sequential, so the
    /// sums keep their order). A contact of depth φ along n has energy ½kφ², ∇φ = Σ_r c_r n
    /// over its rows (c = -w on the face's nodes, +1 on a simulated tool), hence
    /// b_r += -c_r h k (φ + h φ̇) n with φ̇ = n·Σ c v, and A += h² k (c cᵀ) ⊗ n nᵀ.
    fn assemble_tools(&mut self) {
        let n = self.u.len();
        let h = self.params.dt;
        for (k, proxy) in self.proxies.iter().enumerate() {
            let tool = &self.tools[proxy.tool];
            let Some(coupling) = tool.coupling else { continue };
            let (force, stiffness, damping, _) = coupling_force(tool, proxy);
            let diag = Matrix3::identity() * (coupling.mass + h * damping + h * h * stiffness);
            self.proxy_diag[k] = diag.map(T::of);
            self.rhs[n + k] = ((force - proxy.v * (h * stiffness)) * h).map(T::of);
            self.precond[n + k] = diag.try_inverse().unwrap_or_else(Matrix3::zeros).map(T::of);
        }
        self.contact_rows.clear();
        self.rows_before_contacts.clear();
        self.add_contacts();
    }

    /// Adds the contacts' terms to the assembled rows, keeping each touched row as it was.
    fn add_contacts(&mut self) {
        let n = self.u.len();
        let h = self.params.dt;
        let mut blocks: Vec<(usize, Matrix3<f64>)> = Vec::new();
        for c in &self.active_contacts {
            let proxy = self.proxies.iter().position(|p| p.tool == c.tool);
            let mut rows = [usize::MAX; 4];
            let mut coefficients = [0.0; 4];
            for k in 0..3 {
                if c.weights[k] > 0.0 && !self.fixed[c.nodes[k] as usize] {
                    rows[k] = c.nodes[k] as usize;
                    coefficients[k] = -c.weights[k];
                }
            }
            if let Some(k) = proxy {
                rows[3] = n + k;
                coefficients[3] = 1.0;
            }
            let mut normal_speed = 0.0;
            for k in 0..3 {
                normal_speed -= c.weights[k] * c.push.dot(&self.v[c.nodes[k] as usize].map(T::to_f64));
            }
            if let Some(k) = proxy {
                normal_speed += c.push.dot(&self.proxies[k].v);
            }
            let g = h * c.stiffness * (c.depth + h * normal_speed);
            let nn = c.push * c.push.transpose() * (h * h * c.stiffness);
            for r in 0..4 {
                if rows[r] != usize::MAX {
                    if !self.rows_before_contacts.iter().any(|(row, _, _)| *row == rows[r]) {
                        self.rows_before_contacts.push((rows[r], self.rhs[rows[r]], self.precond[rows[r]]));
                    }
                    self.rhs[rows[r]] -= (c.push * (coefficients[r] * g)).map(T::of);
                    blocks.push((rows[r], nn * (coefficients[r] * coefficients[r])));
                }
            }
            self.contact_rows.push(ContactRows {
                rows,
                coefficients: coefficients.map(T::of),
                push: c.push.map(T::of),
                h2k: T::of(h * h * c.stiffness),
            });
        }
        // Block Jacobi sees each touched row's diagonal block with its contact part.
        blocks.sort_by_key(|(row, _)| *row);
        for group in blocks.chunk_by(|a, b| a.0 == b.0) {
            let row = group[0].0;
            let base = if row < n { self.diag[row] } else { self.proxy_diag[row - n] };
            let sum = group.iter().fold(base.map(T::to_f64), |s, (_, b)| s + b);
            self.precond[row] = sum.try_inverse().unwrap_or_else(Matrix3::zeros).map(T::of);
        }
    }

    /// Backward Euler evaluates the contact at the step's end, linearised: a contact whose
    /// end penetration φ + h φ̇ comes out ≤ 0 would pull the surface, so it leaves the active
    /// set and the step is solved again from the rows as they were (a few rounds at most).
    fn release_separating_contacts(&mut self) -> bool {
        let n = self.u.len();
        let h = T::of(self.params.dt);
        let keep: Vec<bool> = (self.active_contacts.iter().zip(&self.contact_rows))
            .map(|(c, rows)| {
                let mut rate = T::zero();
                for r in 0..4 {
                    let row = rows.rows[r];
                    if row == usize::MAX {
                        continue;
                    }
                    let v = if row < n { self.v[row] } else { self.proxies[row - n].v.map(T::of) };
                    rate += rows.coefficients[r] * rows.push.dot(&(v + self.dv[row]));
                }
                T::of(c.depth) + h * rate > T::zero()
            })
            .collect();
        if keep.iter().all(|k| *k) {
            return false;
        }
        for (row, rhs, precond) in self.rows_before_contacts.drain(..) {
            self.rhs[row] = rhs;
            self.precond[row] = precond;
        }
        let mut k = keep.iter();
        self.active_contacts.retain(|_| k.next().copied().unwrap_or(false));
        self.contact_rows.clear();
        self.add_contacts();
        true
    }

    /// out += the surface contacts' part of A p (rank one per contact).
    fn contact_product(&self, p: &[Vector3<T>], out: &mut [Vector3<T>]) {
        for c in &self.contact_rows {
            let mut y = T::zero();
            for r in 0..4 {
                if c.rows[r] != usize::MAX {
                    y += c.coefficients[r] * c.push.dot(&p[c.rows[r]]);
                }
            }
            let s = c.h2k * y;
            for r in 0..4 {
                if c.rows[r] != usize::MAX {
                    out[c.rows[r]] += c.push * (c.coefficients[r] * s);
                }
            }
        }
    }

    fn implicit_euler(&mut self, tools: &[ContactTool<T>]) {
        self.assemble(tools);
        // Start CG from Δv extrapolated linearly from the last two steps: the motion is
        // smooth in time, so this guess is closer than the last Δv alone.
        let last = self.dv.clone();
        if self.solves >= 2 {
            let two = T::of(2.0);
            self.dv
                .par_iter_mut()
                .zip(self.dv_previous.par_iter())
                .with_min_len(CHUNK)
                .for_each(|(dv, prev)| *dv = *dv * two - prev);
        }
        if self.multigrid && self.amg.as_ref().is_none_or(|a| a.stale) {
            self.build_amg();
        }
        self.last_cg = self.solve();
        if self.params.preconditioner == Preconditioner::Auto && self.last_cg.iterations > super::AUTO_AMG_ABOVE {
            self.multigrid = true;
        }
        if let Some(state) = &mut self.amg {
            if state.iterations_at_build == 0 {
                state.iterations_at_build = self.last_cg.iterations.max(1);
            } else if self.last_cg.iterations > 2 * state.iterations_at_build + 4 {
                state.stale = true;
            }
        }
        for _ in 0..4 {
            if !self.release_separating_contacts() {
                break;
            }
            let first = self.last_cg.iterations;
            self.last_cg = self.solve();
            self.last_cg.iterations += first;
        }
        self.dv_previous = last;
        self.solves += 1;
        let h = T::of(self.params.dt);
        let (dv, fixed) = (&self.dv, &self.fixed);
        self.u.par_iter_mut().zip(self.v.par_iter_mut()).enumerate().for_each(|(i, (x, v))| {
            if fixed[i] {
                *v = Vector3::zeros();
                return;
            }
            *v += dv[i];
            *x += *v * h;
        });
        let n = self.u.len();
        for (k, proxy) in self.proxies.iter_mut().enumerate() {
            proxy.v += self.dv[n + k].map(T::to_f64);
            proxy.x += proxy.v * self.params.dt;
        }
    }

    fn spmv_into(&self, p: &[Vector3<T>], out: &mut [Vector3<T>]) {
        let n = self.u.len();
        out[..n].par_iter_mut().with_min_len(CHUNK).enumerate().for_each(|(i, q)| {
            let adj = &self.adjacency[self.offsets[i] as usize..self.offsets[i + 1] as usize];
            *q = kernels::spmv_row(i, adj, &self.terms, &self.diag[i], self.fixed[i], p);
        });
        for (k, diag) in self.proxy_diag.iter().enumerate() {
            out[n + k] = diag * p[n + k];
        }
        self.contact_product(p, out);
    }

    /// Preconditioned CG on the assembled system, warm-started from the previous Δv.
    /// Fixed nodes are filtered out (their rows of r, z and p stay zero).
    pub(crate) fn solve(&mut self) -> CgStats {
        let tol = T::of(self.params.cg_tolerance);
        for (dv, &fixed) in self.dv.iter_mut().zip(&self.fixed) {
            if fixed {
                *dv = Vector3::zeros();
            }
        }
        let b_norm2 = dot(&self.rhs, &self.rhs);
        if b_norm2 == T::zero() {
            self.dv.iter_mut().for_each(|v| *v = Vector3::zeros());
            return CgStats { iterations: 0, relative_residual: 0.0 };
        }
        let mut q = std::mem::take(&mut self.q);
        self.spmv_into(&self.dv, &mut q);
        let (rhs, precond) = (&self.rhs, &self.precond);
        (self.r.par_iter_mut(), self.z.par_iter_mut(), q.par_iter())
            .into_par_iter()
            .with_min_len(CHUNK)
            .enumerate()
            .for_each(|(i, (r, z, q))| {
                *r = rhs[i] - q;
                *z = precond[i] * *r;
            });
        if self.amg.is_some() {
            self.z = self.apply_amg(&self.r);
        }
        self.p.clone_from(&self.z);
        let mut rz = dot(&self.r, &self.z);
        let mut rr = dot(&self.r, &self.r);
        let target = tol * tol * b_norm2;
        let mut iterations = 0;
        while rr > target && iterations < self.params.cg_max_iterations {
            // q = A p and p·q in one pass.
            self.spmv_into(&self.p, &mut q);
            let pq = dot(&self.p, &q);
            if pq <= T::zero() {
                break; // cannot happen for SPD A; guards against round-off at convergence
            }
            let alpha = rz / pq;
            // x, r, z updates and both dots in one pass.
            let partials: Vec<(T, T)> = (
                self.dv.par_chunks_mut(CHUNK),
                self.r.par_chunks_mut(CHUNK),
                self.z.par_chunks_mut(CHUNK),
                self.p.par_chunks(CHUNK),
                q.par_chunks(CHUNK),
                precond.par_chunks(CHUNK),
            )
                .into_par_iter()
                .map(|(dv, r, z, p, q, m)| {
                    let (mut rz, mut rr) = (T::zero(), T::zero());
                    for k in 0..dv.len() {
                        dv[k] += p[k] * alpha;
                        r[k] -= q[k] * alpha;
                        z[k] = m[k] * r[k];
                        rz += r[k].dot(&z[k]);
                        rr += r[k].dot(&r[k]);
                    }
                    (rz, rr)
                })
                .collect();
            let (mut rz_new, rr_new) = partials.iter().fold((T::zero(), T::zero()), |(a, b), (c, d)| (a + *c, b + *d));
            if self.amg.is_some() && rr_new > target {
                self.z = self.apply_amg(&self.r);
                rz_new = dot(&self.r, &self.z);
            }
            let beta = rz_new / rz;
            rz = rz_new;
            rr = rr_new;
            self.p.par_iter_mut().zip(self.z.par_iter()).with_min_len(CHUNK).for_each(|(p, z)| *p = z + *p * beta);
            iterations += 1;
        }
        self.q = q;
        CgStats { iterations, relative_residual: (rr / b_norm2).sqrt().to_f64() }
    }

    /// Assembled A as f64 triplets; fixed nodes keep an identity row and no couplings.
    /// With `tools`, the simulated tools' rows and the contacts' terms too (the whole
    /// system); without, the mesh's springs alone (what the multigrid hierarchy is built on).
    fn system_triplets(&self, tools: bool) -> Vec<(usize, usize, f64)> {
        let mut triplets = Vec::with_capacity(self.adjacency.len() * 9 + self.u.len() * 9);
        for i in 0..self.u.len() {
            if self.fixed[i] {
                for c in 0..3 {
                    triplets.push((3 * i + c, 3 * i + c, 1.0));
                }
                continue;
            }
            for r in 0..3 {
                for c in 0..3 {
                    triplets.push((3 * i + r, 3 * i + c, self.diag[i][(r, c)].to_f64()));
                }
            }
            for &[j, e] in &self.adjacency[self.offsets[i] as usize..self.offsets[i + 1] as usize] {
                if self.fixed[j as usize] {
                    continue;
                }
                for r in 0..3 {
                    for c in 0..3 {
                        triplets.push((3 * i + r, 3 * j as usize + c, -self.terms[e as usize].block[(r, c)].to_f64()));
                    }
                }
            }
        }
        if tools {
            let n = self.u.len();
            for (k, d) in self.proxy_diag.iter().enumerate() {
                for r in 0..3 {
                    for c in 0..3 {
                        triplets.push((3 * (n + k) + r, 3 * (n + k) + c, d[(r, c)].to_f64()));
                    }
                }
            }
            for c in &self.contact_rows {
                let nn = c.push.map(T::to_f64) * c.push.map(T::to_f64).transpose() * c.h2k.to_f64();
                for (a, &ra) in c.rows.iter().enumerate().filter(|(_, r)| **r != usize::MAX) {
                    for (b, &rb) in c.rows.iter().enumerate().filter(|(_, r)| **r != usize::MAX) {
                        let block = nn * (c.coefficients[a] * c.coefficients[b]).to_f64();
                        for r in 0..3 {
                            for col in 0..3 {
                                triplets.push((3 * ra + r, 3 * rb + col, block[(r, col)]));
                            }
                        }
                    }
                }
            }
        }
        triplets
    }

    /// (Re)builds the multigrid hierarchy from the assembled matrix of this step.
    fn build_amg(&mut self) {
        let started = std::time::Instant::now();
        let n = self.u.len();
        let a = Csr::from_triplets(3 * n, 3 * n, self.system_triplets(false));
        let neighbours: Vec<Vec<u32>> = (0..n)
            .map(|i| {
                self.adjacency[self.offsets[i] as usize..self.offsets[i + 1] as usize]
                    .iter()
                    .map(|[j, _]| *j)
                    .filter(|j| !self.fixed[*j as usize])
                    .collect()
            })
            .collect();
        let positions = self.positions_f64();
        self.amg = Amg::new(&a, &positions, &self.fixed, &neighbours).map(|mut amg| {
            amg.fine_omega = self.block_jacobi_omega();
            tracing::debug!(
                "AMG hierarchy in {:.0} ms: fine {} unknowns, coarse levels {:?}, prolongator nonzeros per level: {:?}",
                started.elapsed().as_secs_f64() * 1e3,
                3 * n,
                amg.coarse_sizes,
                amg.nonzeros()
            );
            AmgState { amg, iterations_at_build: 0, stale: false }
        });
    }

    /// Damping 4/(3 λmax) of the fine block-Jacobi smoother, λmax of D⁻¹A by power iteration.
    fn block_jacobi_omega(&self) -> f64 {
        let n = self.rhs.len();
        let mut x: Vec<Vector3<T>> = (0..n)
            .map(|i| {
                if self.fixed.get(i).copied().unwrap_or(false) {
                    Vector3::zeros()
                } else {
                    Vector3::repeat(T::one() + T::of(((i * 7919) % 13) as f64 / 13.0))
                }
            })
            .collect();
        let mut y = vec![Vector3::zeros(); n];
        let mut lambda = 1.0;
        for _ in 0..12 {
            self.spmv_into(&x, &mut y);
            for (yi, m) in y.iter_mut().zip(&self.precond) {
                *yi = m * *yi;
            }
            let (yn, xn) = (dot(&y, &y).to_f64().sqrt(), dot(&x, &x).to_f64().sqrt());
            if yn == 0.0 || xn == 0.0 {
                break;
            }
            lambda = yn / xn;
            let inv = T::of(1.0 / yn);
            for (xi, yi) in x.iter_mut().zip(&y) {
                *xi = yi * inv;
            }
        }
        4.0 / (3.0 * lambda)
    }

    /// z = M⁻¹ r: one symmetric V-cycle, the fine level on the current block operator.
    fn apply_amg(&self, r: &[Vector3<T>]) -> Vec<Vector3<T>> {
        let Some(state) = &self.amg else { return r.to_vec() };
        let omega = T::of(state.amg.fine_omega);
        let n = r.len();
        let mut z: Vec<Vector3<T>> =
            r.par_iter().zip(self.precond.par_iter()).with_min_len(CHUNK).map(|(r, m)| m * r * omega).collect();
        let mut az = vec![Vector3::zeros(); n];
        self.spmv_into(&z, &mut az);
        let residual: Vec<f64> = r[..self.u.len()]
            .iter()
            .zip(&az)
            .flat_map(|(r, a)| {
                let d = r - a;
                [d.x.to_f64(), d.y.to_f64(), d.z.to_f64()]
            })
            .collect();
        let e = state.amg.coarse_correction(&residual);
        z[..self.u.len()]
            .par_iter_mut()
            .with_min_len(CHUNK)
            .enumerate()
            .for_each(|(i, zi)| *zi += Vector3::new(T::of(e[3 * i]), T::of(e[3 * i + 1]), T::of(e[3 * i + 2])));
        self.spmv_into(&z, &mut az);
        z.par_iter_mut()
            .zip(az.par_iter())
            .with_min_len(CHUNK)
            .enumerate()
            .for_each(|(i, (zi, a))| *zi += self.precond[i] * (r[i] - a) * omega);
        z
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
            }
            reactions.push(Reaction { force: force.into(), torque: torque.into(), coupling_saturated });
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

    /// The assembled system as f64 triplets (row, col, value), for checks against direct solvers.
    pub fn assembled_system(&mut self) -> Result<(Triplets, Vec<f64>), SolverError> {
        let tools = self.prepare_step()?;
        self.assemble(&tools);
        let rhs = self.rhs.iter().flat_map(|v| [v.x.to_f64(), v.y.to_f64(), v.z.to_f64()]).collect();
        Ok((self.system_triplets(true), rhs))
    }

    /// Prepares the preconditioner in use for the assembled system (tests).
    pub fn prepare_preconditioner(&mut self) {
        if self.multigrid {
            self.build_amg();
        } else {
            self.amg = None;
        }
    }

    /// Solves the currently assembled system from a zero start and returns Δv (for tests).
    pub fn solve_assembled(&mut self) -> (Vec<Vector3<f64>>, CgStats) {
        self.dv.iter_mut().for_each(|v| *v = Vector3::zeros());
        let stats = self.solve();
        (self.dv.iter().map(|v| v.map(T::to_f64)).collect(), stats)
    }
}

/// Adds each penetrating contact's force to its feature's nodes, by their weights.
fn add_contact_forces<T: Real>(contacts: &[SurfaceContact], forces: &mut [Vector3<T>]) {
    for c in contacts.iter().filter(|c| c.depth > 0.0) {
        for k in 0..3 {
            forces[c.nodes[k] as usize] += (c.force() * c.weights[k]).map(T::of);
        }
    }
}

/// Deterministic parallel dot product of two vector fields.
fn dot<T: Real>(a: &[Vector3<T>], b: &[Vector3<T>]) -> T {
    let partials: Vec<T> = a
        .par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(a, b)| a.iter().zip(b).fold(T::zero(), |s, (x, y)| s + x.dot(y)))
        .collect();
    partials.into_iter().fold(T::zero(), |s, x| s + x)
}

/// Deterministic parallel sum of `f(0..n)` in f64.
fn chunked_sum(n: usize, f: impl Fn(usize) -> f64 + Sync) -> f64 {
    let partials: Vec<f64> =
        (0..n.div_ceil(CHUNK)).into_par_iter().map(|c| (c * CHUNK..((c + 1) * CHUNK).min(n)).map(&f).sum()).collect();
    partials.into_iter().sum()
}
