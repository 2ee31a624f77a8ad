//! The CPU path (rayon). Reductions sum fixed-size chunks in index order, so a run is
//! bit-for-bit repeatable whatever the thread scheduling (replays depend on it).

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::amg::{Amg, Csr};
use super::kernels::{self, ContactTool, SpringTerms};
use super::model::MassSpringModel;
use super::tool::{spread_weights, Tool};
use super::{Integrator, Preconditioner, Reaction, SolverError, SolverParams, StepReport};
use crate::math::Real;

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
        let (lo, hi) = crate::mesh::bounds(&model.rest);
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
    }

    fn contact_tools(&self) -> Result<Vec<ContactTool<T>>, SolverError> {
        self.tools
            .iter()
            .enumerate()
            .map(|(index, tool)| {
                let c = tool.contact_params();
                if !(c.a.iter().chain(c.b.iter()).all(|v| v.is_finite())) {
                    return Err(SolverError::NonFiniteToolInput { index, what: "pose" });
                }
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
        self.finish_step(&tools, saved)
    }

    /// Validates tool inputs and spreads commanded forces; returns the contact tools.
    pub(crate) fn prepare_step(&mut self) -> Result<Vec<ContactTool<T>>, SolverError> {
        let tools = self.contact_tools()?;
        self.spread_external_forces()?;
        Ok(tools)
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
        }
    }

    /// Takes a state computed elsewhere (the GPU) as this step's result, with the same
    /// reporting and divergence check as a CPU step.
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn accept_step(
        &mut self,
        tools: &[ContactTool<T>],
        u: Vec<Vector3<T>>,
        v: Vec<Vector3<T>>,
        cg: CgStats,
    ) -> Result<StepReport, SolverError> {
        let saved = self.snapshot();
        self.u = u;
        self.v = v;
        self.last_cg = cg;
        self.finish_step(tools, saved)
    }

    fn finish_step(&mut self, tools: &[ContactTool<T>], saved: Snapshot<T>) -> Result<StepReport, SolverError> {
        self.step += 1;
        self.time += self.params.dt;
        let report = self.report(tools);
        if let Some(reason) = self.divergence(&report) {
            let failed = (self.step, self.time);
            self.u = saved.u;
            self.v = saved.v;
            self.history = saved.history;
            self.history_valid = saved.history_valid;
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
        (0..self.u.len())
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
            .collect()
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
        if self.params.preconditioner == Preconditioner::Amg && self.amg.as_ref().is_none_or(|a| a.stale) {
            self.build_amg();
        }
        self.last_cg = self.solve();
        if let Some(state) = &mut self.amg {
            if state.iterations_at_build == 0 {
                state.iterations_at_build = self.last_cg.iterations.max(1);
            } else if self.last_cg.iterations > 2 * state.iterations_at_build + 4 {
                state.stale = true;
            }
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
    }

    fn spmv_into(&self, p: &[Vector3<T>], out: &mut [Vector3<T>]) {
        out.par_iter_mut().with_min_len(CHUNK).enumerate().for_each(|(i, q)| {
            let adj = &self.adjacency[self.offsets[i] as usize..self.offsets[i + 1] as usize];
            *q = kernels::spmv_row(i, adj, &self.terms, &self.diag[i], self.fixed[i], p);
        });
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
    fn system_triplets(&self) -> Vec<(usize, usize, f64)> {
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
        triplets
    }

    /// (Re)builds the multigrid hierarchy from the assembled matrix of this step.
    fn build_amg(&mut self) {
        let started = std::time::Instant::now();
        let n = self.u.len();
        let a = Csr::from_triplets(3 * n, 3 * n, self.system_triplets());
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
        let n = self.u.len();
        let mut x: Vec<Vector3<T>> = (0..n)
            .map(|i| {
                if self.fixed[i] {
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
        let residual: Vec<f64> = r
            .iter()
            .zip(&az)
            .flat_map(|(r, a)| {
                let d = r - a;
                [d.x.to_f64(), d.y.to_f64(), d.z.to_f64()]
            })
            .collect();
        let e = state.amg.coarse_correction(&residual);
        z.par_iter_mut()
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

    fn report(&self, tools: &[ContactTool<T>]) -> StepReport {
        let g = Vector3::from(self.params.gravity);
        let kinetic = chunked_sum(self.u.len(), |i| 0.5 * self.mass[i].to_f64() * self.v[i].norm_squared().to_f64());
        let gravity = chunked_sum(self.u.len(), |i| -self.mass[i].to_f64() * g.dot(&self.u[i].map(T::to_f64)));
        let mut contact_energy = 0.0;
        let mut reactions = Vec::with_capacity(tools.len());
        for (tool, commanded) in tools.iter().zip(&self.tools) {
            // The mesh pushes back the tool's own commanded force, and every contact force.
            let mut force = -commanded.applied_force;
            let mut torque = Vector3::zeros();
            for i in 0..self.u.len() {
                let p = &self.world(i);
                if let Some((f, _)) = kernels::contact(p, &tool.a, &tool.b, tool.radius, tool.stiffness) {
                    let f = f.map(T::to_f64);
                    contact_energy += 0.5 * f.norm_squared() / tool.stiffness.to_f64();
                    force -= f;
                    torque -= (p.map(T::to_f64) - tool.a.map(T::to_f64)).cross(&f);
                }
            }
            reactions.push(Reaction { force: force.into(), torque: torque.into() });
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
        let tools = self.contact_tools()?;
        self.spread_external_forces()?;
        self.assemble(&tools);
        let rhs = self.rhs.iter().flat_map(|v| [v.x.to_f64(), v.y.to_f64(), v.z.to_f64()]).collect();
        Ok((self.system_triplets(), rhs))
    }

    /// Prepares the configured preconditioner for the assembled system (tests).
    pub fn prepare_preconditioner(&mut self) {
        if self.params.preconditioner == Preconditioner::Amg {
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
