//! The solver on the GPU: `solver.wgsl` beside this file, run through wgpu. A host-side
//! [`Simulation<f32>`] mirrors the state: it validates tool inputs, spreads commanded forces,
//! and checks and reports each step exactly as the CPU path does, so both paths report alike.
//!
//! CG runs `cg_check_interval` iterations per submission; the reductions and the stopping
//! test stay on the GPU (a `done` flag makes the remaining kernels of a batch return at
//! once), so the host reads back one small struct per batch instead of syncing every
//! iteration. A solve queues as many batches as the last one of its kind needed, in one
//! submission with its start, and checks once; where that falls short, the next batch is
//! queued before the host waits for each check, so the GPU never idles on it (a batch
//! queued after convergence returns at once). A step's positions and velocities come back
//! in one read.
//!
//! Surface contacts and coupled tools: the mirror finds the contacts each step (the BVH is
//! on the host) and gives their terms (`ContactTerms`) and the simulated tools' rows, which
//! are uploaded; the system then carries them as the CPU's does (rows after the nodes' for
//! the simulated tools, rank-one contact terms gathered per touched row), and a contact that
//! separates at the step's end is released and the step solved again, by the CPU's rule.

use std::collections::BTreeMap;

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use nalgebra::Vector3;

use super::coarse::DeviceCoarseCorrection;
use super::cpu::{CgStats, ContactTerms, TERM_ROWS};
use super::kernels::ContactTool;
use super::{
    Integrator, LocalModel, MassSpringModel, Preconditioner, Simulation, SolverError, SolverParams, StepReport, Tool,
};
use defvol_gpu::gpu::{Binding, GpuContext, GpuError, Kernels};

/// Storage buffers the solver shader binds at once.
const STORAGE_BUFFERS: u32 = 30;
/// Rows a contact's terms span (its nodes', its simulated tool's and the row it turns on).
const CONTACT_ROWS: usize = TERM_ROWS;
/// Tools the GPU kernels take per step.
pub const MAX_TOOLS: usize = 4;
const WORKGROUP: u32 = 256;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GpuSolverError {
    #[error(transparent)]
    Solver(#[from] SolverError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("{0} tools given; the GPU solver takes at most {MAX_TOOLS}")]
    TooManyTools(usize),
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuTool {
    a: [f32; 4],
    b: [f32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuParams {
    gravity_h: [f32; 4],
    counts: [u32; 4],
    cg: [f32; 4],
    tools: [GpuTool; MAX_TOOLS],
    /// Rows (nodes + simulated tools' rows), contacts, touched rows, simulated tools' rows.
    system: [u32; 4],
}

/// `ContactTerm` of the shader: a contact's rows, gradients, and (h²k, h k (φ + h φ̇)).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuContactTerm {
    rows: [[u32; 4]; 5],
    gradients: [[f32; 4]; CONTACT_ROWS],
    scale: [f32; 4],
}

impl GpuContactTerm {
    fn new(terms: &ContactTerms) -> Self {
        let mut rows = [[u32::MAX; 4]; 5];
        let mut gradients = [[0.0; 4]; CONTACT_ROWS];
        for (k, (row, g)) in terms.rows.iter().zip(&terms.gradients).enumerate() {
            if *row != usize::MAX {
                rows[k / 4][k % 4] = *row as u32;
                gradients[k] = [g.x as f32, g.y as f32, g.z as f32, 0.0];
            }
        }
        Self { rows, gradients, scale: [terms.h2k as f32, terms.rhs_scale as f32, 0.0, 0.0] }
    }

    /// The rows and directions b of a compliance solve (at most a contact's rows), for bᵀΔv.
    fn probe(b: &[(usize, Vector3<f64>)]) -> Self {
        let mut term = Self::zeroed();
        term.rows = [[u32::MAX; 4]; 5];
        for (k, (row, g)) in b.iter().take(CONTACT_ROWS).enumerate() {
            term.rows[k / 4][k % 4] = *row as u32;
            term.gradients[k] = [g.x as f32, g.y as f32, g.z as f32, 0.0];
        }
        term
    }
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct CgScalars {
    rz: f32,
    rr: f32,
    bb: f32,
    alpha: f32,
    beta: f32,
    pq: f32,
    iterations: u32,
    done: u32,
    contact_pq: f32,
}

const CG_SCALARS_BYTES: u64 = std::mem::size_of::<CgScalars>() as u64;

/// Displacements and velocities, a row a node.
type State = [Vec<Vector3<f32>>; 2];

/// After a solve: the simulated tools' Δv, and each contact's and friction term's rate at
/// the step's end.
type Outcome = (Vec<Vector3<f64>>, Vec<f64>);

/// What a step leaves for the host: the simulated tools' Δv, the CG's statistics (none
/// for an explicit scheme), and the state.
struct StepOutcome {
    proxy_dv: Vec<Vector3<f64>>,
    cg: CgStats,
    state: State,
}

/// The kinds of CG solve, each learning its own iteration count.
#[derive(Debug, Clone, Copy)]
enum Solve {
    /// A step's system.
    Step,
    /// A local model's compliance along a contact.
    Probe,
}

/// The entry points of `solver.wgsl`; the discriminant indexes the pipelines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kernel {
    SpringTerms,
    SpringForces,
    SpringForcesPredicted,
    NodeTerms,
    CgExtrapolate,
    CgStartSpmv,
    CgInit,
    CgInitReduce,
    CgSpmv,
    CgAlpha,
    CgUpdate,
    CgBeta,
    CgDirection,
    ImplicitUpdate,
    NodeForces,
    ExplicitEulerUpdate,
    VerletUpdate,
    VelocityVerletPositions,
    VelocityVerletVelocities,
    AccelerationFromForce,
    ContactRows,
    ContactDot,
    ContactScatter,
    ContactOutcome,
    ProbeOutcome,
    AmgPresmooth,
    AmgResidual,
    AmgCorrect,
    AmgPostsmooth,
    AmgInitReduce,
}

impl Kernel {
    const ALL: [Kernel; 30] = [
        Kernel::SpringTerms,
        Kernel::SpringForces,
        Kernel::SpringForcesPredicted,
        Kernel::NodeTerms,
        Kernel::CgExtrapolate,
        Kernel::CgStartSpmv,
        Kernel::CgInit,
        Kernel::CgInitReduce,
        Kernel::CgSpmv,
        Kernel::CgAlpha,
        Kernel::CgUpdate,
        Kernel::CgBeta,
        Kernel::CgDirection,
        Kernel::ImplicitUpdate,
        Kernel::NodeForces,
        Kernel::ExplicitEulerUpdate,
        Kernel::VerletUpdate,
        Kernel::VelocityVerletPositions,
        Kernel::VelocityVerletVelocities,
        Kernel::AccelerationFromForce,
        Kernel::ContactRows,
        Kernel::ContactDot,
        Kernel::ContactScatter,
        Kernel::ContactOutcome,
        Kernel::ProbeOutcome,
        Kernel::AmgPresmooth,
        Kernel::AmgResidual,
        Kernel::AmgCorrect,
        Kernel::AmgPostsmooth,
        Kernel::AmgInitReduce,
    ];

    fn entry_point(self) -> &'static str {
        match self {
            Kernel::SpringTerms => "spring_terms",
            Kernel::SpringForces => "spring_forces",
            Kernel::SpringForcesPredicted => "spring_forces_predicted",
            Kernel::NodeTerms => "node_terms",
            Kernel::CgExtrapolate => "cg_extrapolate",
            Kernel::CgStartSpmv => "cg_start_spmv",
            Kernel::CgInit => "cg_init",
            Kernel::CgInitReduce => "cg_init_reduce",
            Kernel::CgSpmv => "cg_spmv",
            Kernel::CgAlpha => "cg_alpha",
            Kernel::CgUpdate => "cg_update",
            Kernel::CgBeta => "cg_beta",
            Kernel::CgDirection => "cg_direction",
            Kernel::ImplicitUpdate => "implicit_update",
            Kernel::NodeForces => "node_forces",
            Kernel::ExplicitEulerUpdate => "explicit_euler_update",
            Kernel::VerletUpdate => "verlet_update",
            Kernel::VelocityVerletPositions => "velocity_verlet_positions",
            Kernel::VelocityVerletVelocities => "velocity_verlet_velocities",
            Kernel::AccelerationFromForce => "acceleration_from_force",
            Kernel::ContactRows => "contact_rows",
            Kernel::ContactDot => "contact_dot",
            Kernel::ContactScatter => "contact_scatter",
            Kernel::ContactOutcome => "contact_outcome",
            Kernel::ProbeOutcome => "probe_outcome",
            Kernel::AmgPresmooth => "amg_presmooth",
            Kernel::AmgResidual => "amg_residual",
            Kernel::AmgCorrect => "amg_correct",
            Kernel::AmgPostsmooth => "amg_postsmooth",
            Kernel::AmgInitReduce => "amg_init_reduce",
        }
    }
}

/// Read-only bindings of the shader (the rest are read-write storage, 0 is the uniform).
const READ_ONLY: [u32; 11] = [1, 2, 3, 4, 5, 8, 24, 25, 26, 27, 28];
/// Bindings of the contacts' buffers, which grow with the contact count.
const CONTACT_BINDINGS: std::ops::Range<usize> = 26..31;

/// The buffers the host writes or reads by name; `bound` holds every binding in order.
struct Buffers {
    params: wgpu::Buffer,
    /// Displacements from rest.
    x: wgpu::Buffer,
    v: wgpu::Buffer,
    external: wgpu::Buffer,
    dv: wgpu::Buffer,
    z: wgpu::Buffer,
    p: wgpu::Buffer,
    q: wgpu::Buffer,
    scalars: wgpu::Buffer,
    aux: wgpu::Buffer,
    force: wgpu::Buffer,
    diag: wgpu::Buffer,
    precond: wgpu::Buffer,
    rhs: wgpu::Buffer,
    /// A compliance probe's right-hand side rows, copied into `rhs` once it is cleared.
    probe_rhs: wgpu::Buffer,
    /// The Δv the last step's solve started from, for the next one's extrapolated start.
    previous_dv: wgpu::Buffer,
    /// The step's Δv while a compliance probe borrows `dv` (put back before the next step).
    held_dv: wgpu::Buffer,
    bound: Vec<wgpu::Buffer>,
    /// Contacts the contact buffers hold.
    contact_capacity: usize,
}

/// The multigrid preconditioner on the device: the coarse cycle over the CPU-built hierarchy,
/// its fine damping, and room for CG's direction while the cycle's products borrow `p`.
struct Multigrid {
    coarse: DeviceCoarseCorrection,
    omega: f32,
    saved_p: wgpu::Buffer,
    /// Iterations of the first solve with it (0 until then), for [`crate::amg::is_stale`].
    iterations_at_build: u32,
}

/// A piece of a CG submission: kernels in one compute pass, a whole-buffer copy, or the
/// coarse cycle's chain.
#[derive(Clone)]
enum Piece<'a> {
    Pass(Vec<(Kernel, u32)>),
    Copy(&'a wgpu::Buffer, &'a wgpu::Buffer),
    Coarse(&'a DeviceCoarseCorrection),
}

pub struct GpuSimulation {
    ctx: Arc<GpuContext>,
    mirror: Simulation<f32>,
    nodes: u32,
    springs: u32,
    pipelines: [wgpu::ComputePipeline; Kernel::ALL.len()],
    layout: wgpu::BindGroupLayout,
    bind_group: wgpu::BindGroup,
    buffers: Buffers,
    history_valid: bool,
    /// Implicit steps solved, for the extrapolated start (from the second on, as on the CPU).
    solves: u64,
    /// Whether a compliance probe holds `dv` since the last step (its Δv in `held_dv`).
    probed: bool,
    /// CG windows the last solve of each [`Solve`] needed: queued before its first check.
    windows_ahead: [std::cell::Cell<u32>; 2],
    /// The `system` counts of the last implicit solve (its rows, contacts and touched rows
    /// stay assembled until the next step).
    system: [u32; 4],
    /// The multigrid preconditioner once in use (`amg` from the first implicit step, `auto`
    /// after a block-Jacobi solve past [`crate::AUTO_AMG_ABOVE`] iterations), and whether
    /// it can be (not where it will not be, or does not fit).
    multigrid: Option<Multigrid>,
    multigrid_possible: bool,
    multigrid_wanted: bool,
}

fn vec4s(v: &[Vector3<f32>]) -> Vec<[f32; 4]> {
    v.iter().map(|p| [p.x, p.y, p.z, 0.0]).collect()
}

fn groups(count: u32) -> u32 {
    count.div_ceil(WORKGROUP).max(1)
}

/// A 3x3 block as the shader's `mat3x3<f32>` stores it: three padded columns.
fn mat3_columns(m: &nalgebra::Matrix3<f64>) -> [f32; 12] {
    let mut out = [0.0; 12];
    for c in 0..3 {
        for r in 0..3 {
            out[4 * c + r] = m[(r, c)] as f32;
        }
    }
    out
}

impl GpuSimulation {
    pub fn new(
        ctx: Arc<GpuContext>,
        model: &MassSpringModel,
        params: SolverParams,
        tools: Vec<Tool>,
    ) -> Result<Self, GpuSolverError> {
        if tools.len() > MAX_TOOLS {
            return Err(GpuSolverError::TooManyTools(tools.len()));
        }
        ctx.require_storage_buffers("the solver", STORAGE_BUFFERS)?;
        let multigrid_wanted = params.preconditioner == Preconditioner::Amg;
        let multigrid_possible =
            params.integrator == Integrator::ImplicitEuler && params.preconditioner != Preconditioner::BlockJacobi;
        let mirror = Simulation::<f32>::new(model, params, tools)?;
        let n = model.node_count();
        let e = model.springs.len();
        // The system's rows: the nodes', then room for a simulated tool per tool and a row
        // for each to turn on.
        let rows = n + 2 * MAX_TOOLS;
        let bindings: Vec<Binding> = (0..=STORAGE_BUFFERS)
            .map(|binding| match binding {
                0 => Binding::Uniform,
                b if READ_ONLY.contains(&b) => Binding::Read,
                _ => Binding::ReadWrite,
            })
            .collect();
        let Kernels { layout, pipelines } =
            ctx.kernels("solver.wgsl", include_str!("solver.wgsl"), &bindings, Kernel::ALL.map(Kernel::entry_point));

        let zeros4 = |count: usize| vec![[0f32; 4]; count.max(1)];
        let mat3 = |count: usize| vec![0f32; 12 * count.max(1)];
        let spring_params: Vec<[f32; 4]> = (0..e)
            .map(|s| [model.rest_length[s] as f32, model.stiffness[s] as f32, model.damping[s] as f32, 0.0])
            .collect();
        // Simulated tools' rows: free, no springs (their adjacency is empty).
        let node_params: Vec<[f32; 4]> = (0..rows)
            .map(|i| match i < n {
                true => [model.mass[i] as f32, if model.fixed[i] { 1.0 } else { 0.0 }, 0.0, 0.0],
                false => [1.0, 0.0, 0.0, 0.0],
            })
            .collect();
        let mut offsets = model.offsets.clone();
        offsets.resize(rows + 1, model.offsets[n]);
        let rest_edge: Vec<[f32; 4]> = model
            .springs
            .iter()
            .map(|[a, b]| {
                let d = model.rest[*b as usize] - model.rest[*a as usize];
                [d.x as f32, d.y as f32, d.z as f32, 0.0]
            })
            .collect();
        let rest_pos: Vec<[f32; 4]> = model.rest.iter().map(|p| [p.x as f32, p.y as f32, p.z as f32, 0.0]).collect();
        let buf = |label: &str, bytes: &[u8]| ctx.storage_buffer(label, bytes);
        let params_buffer = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("params"),
            size: std::mem::size_of::<GpuParams>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut bound = vec![
            params_buffer,
            buf("springs", bytemuck::cast_slice(&model.springs)),
            buf("spring_params", bytemuck::cast_slice(&spring_params)),
            buf("offsets", bytemuck::cast_slice(&offsets)),
            buf("adjacency", bytemuck::cast_slice(&model.adjacency)),
            buf("node_params", bytemuck::cast_slice(&node_params)),
            buf("u", bytemuck::cast_slice(&zeros4(n))),
            buf("v", bytemuck::cast_slice(&zeros4(n))),
            buf("external", bytemuck::cast_slice(&zeros4(n))),
            buf("spring_force", bytemuck::cast_slice(&zeros4(e))),
            buf("spring_kv", bytemuck::cast_slice(&zeros4(e))),
            buf("spring_block", bytemuck::cast_slice(&mat3(e))),
            buf("diag", bytemuck::cast_slice(&mat3(rows))),
            buf("precond", bytemuck::cast_slice(&mat3(rows))),
            buf("rhs", bytemuck::cast_slice(&zeros4(rows))),
            buf("dv", bytemuck::cast_slice(&zeros4(rows))),
            buf("r", bytemuck::cast_slice(&zeros4(rows))),
            buf("z", bytemuck::cast_slice(&zeros4(rows))),
            buf("p", bytemuck::cast_slice(&zeros4(rows))),
            buf("q", bytemuck::cast_slice(&zeros4(rows))),
            buf("partials", bytemuck::cast_slice(&zeros4(groups(rows as u32) as usize))),
            buf("scalars", bytemuck::bytes_of(&CgScalars::zeroed())),
            buf("aux", bytemuck::cast_slice(&zeros4(n))),
            buf("force", bytemuck::cast_slice(&zeros4(n))),
            buf("rest_edge", bytemuck::cast_slice(&rest_edge)),
            buf("rest_pos", bytemuck::cast_slice(&rest_pos)),
        ];
        let contact_capacity = 64;
        bound.extend(contact_buffers(&ctx, contact_capacity));
        let bind_group = ctx.bind_group("solver", &layout, &bound.iter().collect::<Vec<_>>());
        let buffers = Buffers {
            params: bound[0].clone(),
            x: bound[6].clone(),
            v: bound[7].clone(),
            external: bound[8].clone(),
            diag: bound[12].clone(),
            precond: bound[13].clone(),
            rhs: bound[14].clone(),
            dv: bound[15].clone(),
            z: bound[17].clone(),
            p: bound[18].clone(),
            q: bound[19].clone(),
            scalars: bound[21].clone(),
            aux: bound[22].clone(),
            force: bound[23].clone(),
            probe_rhs: ctx.zeroed_buffer("probe_rhs", (CONTACT_ROWS * 16) as u64),
            previous_dv: ctx.zeroed_buffer("previous dv", rows as u64 * 16),
            held_dv: ctx.zeroed_buffer("held dv", rows as u64 * 16),
            bound,
            contact_capacity,
        };
        Ok(Self {
            ctx,
            mirror,
            nodes: n as u32,
            springs: e as u32,
            pipelines,
            layout,
            bind_group,
            buffers,
            history_valid: false,
            solves: 0,
            probed: false,
            windows_ahead: Default::default(),
            system: [n as u32, 0, 0, 0],
            multigrid: None,
            multigrid_possible,
            multigrid_wanted,
        })
    }

    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }
    /// Node displacements from rest (`vec4<f32>` per node, world units), where the other
    /// stages read them.
    pub fn displacements(&self) -> &wgpu::Buffer {
        &self.buffers.x
    }
    /// The host mirror: last accepted state, tools, parameters.
    pub fn mirror(&self) -> &Simulation<f32> {
        &self.mirror
    }
    pub fn tool_mut(&mut self, index: usize) -> Result<&mut Tool, SolverError> {
        self.mirror.tool_mut(index)
    }
    /// Puts coupled tool `index`'s simulated tool at its device, at rest.
    pub fn seat_simulated_tool(&mut self, index: usize) {
        self.mirror.seat_simulated_tool(index);
    }

    fn dispatch(&self, pass: &mut wgpu::ComputePass<'_>, kernel: Kernel, invocations: u32) {
        pass.set_pipeline(&self.pipelines[kernel as usize]);
        pass.dispatch_workgroups(groups(invocations), 1, 1);
    }

    fn run(&self, kernels: &[(Kernel, u32)]) {
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("solver") });
        self.encode(&mut encoder, kernels);
        self.ctx.submit(encoder.finish());
    }

    /// `kernels` in one compute pass of `encoder`.
    fn encode(&self, encoder: &mut wgpu::CommandEncoder, kernels: &[(Kernel, u32)]) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("solver"),
            timestamp_writes: self.ctx.pass_timestamps(),
        });
        pass.set_bind_group(0, &self.bind_group, &[]);
        for (kernel, invocations) in kernels {
            self.dispatch(&mut pass, *kernel, *invocations);
        }
    }

    fn encode_pieces(&self, encoder: &mut wgpu::CommandEncoder, pieces: &[Piece]) {
        for piece in pieces {
            match piece {
                Piece::Pass(kernels) => self.encode(encoder, kernels),
                Piece::Copy(from, to) => self.ctx.copy_buffer(encoder, from, 0, to, 0, from.size()),
                Piece::Coarse(coarse) => {
                    let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("coarse cycle"),
                        timestamp_writes: self.ctx.pass_timestamps(),
                    });
                    coarse.record(&mut pass);
                }
            }
        }
    }

    /// Builds the multigrid hierarchy on the CPU from the step's system (`tools` its contact
    /// tools, after the mirror's `prepare_step`), where and as the CPU path builds it, and
    /// uploads it. Past the adapter's limits: an error under `amg`; under `auto`, block
    /// Jacobi on, saying why.
    fn build_multigrid(&mut self, tools: &[ContactTool<f32>]) -> Result<(), GpuSolverError> {
        if !self.multigrid_possible {
            return Ok(());
        }
        let Some(amg) = self.mirror.multigrid_at_step(tools) else {
            tracing::warn!("no multigrid hierarchy for this mesh (nothing to aggregate): block Jacobi on the GPU");
            self.multigrid_possible = false;
            return Ok(());
        };
        let (aux, force) = (self.buffers.aux.clone(), self.buffers.force.clone());
        match DeviceCoarseCorrection::on(self.ctx.clone(), &amg, aux, force, 4) {
            Ok(coarse) => {
                let saved_p = self.ctx.zeroed_buffer("saved direction", self.buffers.p.size());
                let omega = amg.fine_omega as f32;
                self.multigrid = Some(Multigrid { coarse, omega, saved_p, iterations_at_build: 0 });
                Ok(())
            }
            Err(e) if self.mirror.params().preconditioner == Preconditioner::Auto => {
                tracing::warn!("the multigrid hierarchy does not fit the GPU ({e}): block Jacobi on");
                self.multigrid_possible = false;
                Ok(())
            }
            Err(e) => Err(e.into()),
        }
    }

    /// The preconditioner's rules after a solve of `iterations`: `auto` turns to multigrid
    /// past [`crate::AUTO_AMG_ABOVE`]; a stale hierarchy ([`crate::amg::is_stale`]) is rebuilt
    /// before the next step.
    fn note_iterations(&mut self, iterations: u32) {
        let auto = self.mirror.params().preconditioner == Preconditioner::Auto;
        self.multigrid_wanted |= auto && iterations > crate::AUTO_AMG_ABOVE;
        if let Some(m) = &mut self.multigrid {
            if m.iterations_at_build == 0 {
                m.iterations_at_build = iterations.max(1);
            } else if crate::amg::is_stale(m.iterations_at_build, iterations) {
                self.multigrid = None;
            }
        }
    }

    fn upload_params(&self, tools: &[ContactTool<f32>], system: [u32; 4]) {
        let p = self.mirror.params();
        let mut gpu_tools = [GpuTool::zeroed(); MAX_TOOLS];
        for (slot, t) in gpu_tools.iter_mut().zip(tools) {
            *slot = GpuTool { a: [t.a.x, t.a.y, t.a.z, t.radius], b: [t.b.x, t.b.y, t.b.z, t.stiffness] };
        }
        let params = GpuParams {
            gravity_h: [p.gravity[0] as f32, p.gravity[1] as f32, p.gravity[2] as f32, p.dt as f32],
            counts: [self.nodes, self.springs, tools.len() as u32, 0],
            cg: [
                (p.cg_tolerance * p.cg_tolerance) as f32,
                p.cg_max_iterations as f32,
                self.multigrid.as_ref().map_or(0.0, |m| m.omega),
                0.0,
            ],
            tools: gpu_tools,
            system,
        };
        self.ctx.queue.write_buffer(&self.buffers.params, 0, bytemuck::bytes_of(&params));
        self.ctx.queue.write_buffer(
            &self.buffers.external,
            0,
            bytemuck::cast_slice(&vec4s(&self.mirror.external_forces())),
        );
    }

    /// The step's system beyond the springs, uploaded: the simulated tools' rows and the
    /// active contacts' and their friction's terms, gathered per touched row. Returns the terms and the
    /// counts the shader's `system` takes.
    fn upload_system(&mut self) -> (Vec<ContactTerms>, [u32; 4]) {
        let n = self.nodes as usize;
        let mut tools = 0;
        for k in 0..self.mirror.proxy_count() {
            let rows: Vec<_> = self.mirror.proxy_row(k).into_iter().chain(self.mirror.turning_row(k)).collect();
            for (row, diag, rhs) in rows {
                let inverse = diag.try_inverse().unwrap_or_else(nalgebra::Matrix3::zeros);
                let (row, queue) = (row as u64, &self.ctx.queue);
                queue.write_buffer(&self.buffers.diag, row * 48, bytemuck::cast_slice(&mat3_columns(&diag)));
                queue.write_buffer(&self.buffers.precond, row * 48, bytemuck::cast_slice(&mat3_columns(&inverse)));
                queue.write_buffer(&self.buffers.rhs, row * 16, bytemuck::cast_slice(&vec4s(&[rhs.map(|c| c as f32)])));
                tools += 1;
            }
        }
        let terms = self.mirror.system_terms();
        let mut by_row: BTreeMap<usize, Vec<[u32; 2]>> = BTreeMap::new();
        for (c, t) in terms.iter().enumerate() {
            for (slot, row) in t.rows.iter().enumerate().filter(|(_, row)| **row != usize::MAX) {
                by_row.entry(*row).or_default().push([c as u32, slot as u32]);
            }
        }
        let mut touched: Vec<[u32; 4]> = Vec::with_capacity(by_row.len());
        let mut incidence: Vec<[u32; 2]> = Vec::new();
        for (row, list) in &by_row {
            touched.push([*row as u32, incidence.len() as u32, list.len() as u32, 0]);
            incidence.extend_from_slice(list);
        }
        self.reserve_contacts(terms.len());
        let gpu_terms: Vec<GpuContactTerm> = terms.iter().map(GpuContactTerm::new).collect();
        let [terms_buffer, touched_buffer, incidence_buffer, ..] = &self.buffers.bound[CONTACT_BINDINGS] else {
            unreachable!("five contact bindings")
        };
        for (buffer, bytes) in [
            (terms_buffer, bytemuck::cast_slice::<GpuContactTerm, u8>(&gpu_terms)),
            (touched_buffer, bytemuck::cast_slice(&touched)),
            (incidence_buffer, bytemuck::cast_slice(&incidence)),
        ] {
            if !bytes.is_empty() {
                self.ctx.queue.write_buffer(buffer, 0, bytes);
            }
        }
        let system = [(n + tools) as u32, terms.len() as u32, touched.len() as u32, tools as u32];
        let at = std::mem::offset_of!(GpuParams, system) as u64;
        self.ctx.queue.write_buffer(&self.buffers.params, at, bytemuck::bytes_of(&system));
        (terms, system)
    }

    /// Grows the contacts' buffers to hold `contacts` (and rebinds them).
    fn reserve_contacts(&mut self, contacts: usize) {
        if contacts <= self.buffers.contact_capacity {
            return;
        }
        let capacity = contacts.next_power_of_two();
        let fresh = contact_buffers(&self.ctx, capacity);
        // Keep what the old ones hold (a compliance solve grows them mid-step).
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("grow contacts") });
        for (old, new) in self.buffers.bound[CONTACT_BINDINGS].iter().zip(&fresh) {
            self.ctx.copy_buffer(&mut encoder, old, 0, new, 0, old.size());
        }
        self.ctx.submit(encoder.finish());
        self.buffers.bound.splice(CONTACT_BINDINGS, fresh);
        self.buffers.contact_capacity = capacity;
        self.bind_group = self.ctx.bind_group("solver", &self.layout, &self.buffers.bound.iter().collect::<Vec<_>>());
    }

    /// The simulated tools' rows of Δv and each contact's φ̇ at the step's end (Σ g·(v + Δv):
    /// its start rate plus g·Δv from the GPU), from the `contact_outcome` kernel's rows.
    fn decode_outcome(terms: &[ContactTerms], tools: usize, bytes: &[u8]) -> Result<Outcome, GpuError> {
        let rows: &[[f32; 4]] = bytemuck::try_cast_slice(bytes).map_err(|e| GpuError::Readback(e.to_string()))?;
        let proxy_dv = rows[..tools].iter().map(|r| Vector3::new(r[0], r[1], r[2]).map(f64::from)).collect();
        let end_rates = terms.iter().zip(&rows[tools..]).map(|(t, r)| t.normal_speed + f64::from(r[0])).collect();
        Ok((proxy_dv, end_rates))
    }

    /// Puts the mirror's state back on the GPU: it is the GPU's as last read back, so this
    /// undoes whatever ran since (a diverged batch, a step solved again).
    fn restore_state(&self) {
        let queue = &self.ctx.queue;
        queue.write_buffer(&self.buffers.x, 0, bytemuck::cast_slice(&vec4s(self.mirror.displacements())));
        queue.write_buffer(&self.buffers.v, 0, bytemuck::cast_slice(&vec4s(self.mirror.velocities())));
    }

    /// Runs `kernels`, and reads displacements and velocities back in the same submission.
    fn run_then_read_state(&self, kernels: &[(Kernel, u32)]) -> Result<State, GpuError> {
        let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        self.encode(&mut encoder, kernels);
        let bytes = self.nodes as u64 * 16;
        let pending = self.ctx.submit_and_read(encoder, &[(&self.buffers.x, bytes), (&self.buffers.v, bytes)]);
        let mut both = vec![0u8; 2 * bytes as usize];
        self.ctx.finish_read(pending, &mut both)?;
        Ok(self.decode_state(&both))
    }

    /// Displacements then velocities, as read back (16 bytes a node each).
    fn decode_state(&self, both: &[u8]) -> State {
        let rows: Vec<[f32; 4]> = bytemuck::pod_collect_to_vec(both);
        let vec3 = |p: &[f32; 4]| Vector3::new(p[0], p[1], p[2]);
        let (x, v) = rows.split_at(self.nodes as usize);
        [x.iter().map(vec3).collect(), v.iter().map(vec3).collect()]
    }

    /// The kernels that assemble the system from the current state.
    fn assembly(&self, system: [u32; 4]) -> Vec<(Kernel, u32)> {
        let mut assembly = vec![(Kernel::SpringTerms, self.springs), (Kernel::NodeTerms, self.nodes)];
        if system[2] > 0 {
            assembly.push((Kernel::ContactRows, system[2]));
        }
        assembly
    }

    /// CG's work for `system`: its start, and one window of `cg_check_interval` iterations;
    /// with the multigrid, each preconditioner application between them.
    fn cg_kernels(&self, system: [u32; 4]) -> [Vec<Piece<'_>>; 2] {
        let (rows, touched) = (system[0], system[2]);
        // The contacts' kernels run only when there are contacts.
        let contacts = |kernels: &[(Kernel, u32)]| if touched > 0 { kernels.to_vec() } else { Vec::new() };
        let product = || {
            let mut q = vec![(Kernel::CgStartSpmv, rows)];
            q.extend(contacts(&[(Kernel::ContactDot, 1), (Kernel::ContactScatter, touched)]));
            q
        };
        let mut start = product();
        start.extend([(Kernel::CgInit, rows), (Kernel::CgInitReduce, 1)]);
        let mut iteration = vec![(Kernel::CgSpmv, rows)];
        iteration.extend(contacts(&[(Kernel::ContactDot, 1), (Kernel::ContactScatter, touched)]));
        iteration.extend([(Kernel::CgAlpha, 1), (Kernel::CgUpdate, rows)]);
        let interval = self.mirror.params().cg_check_interval as usize;
        let direction = [(Kernel::CgBeta, 1), (Kernel::CgDirection, rows)];
        let Some(m) = &self.multigrid else {
            iteration.extend(direction);
            return [vec![Piece::Pass(start)], vec![Piece::Pass(iteration.repeat(interval))]];
        };
        // z = M⁻¹ r (solver.wgsl, "multigrid preconditioner"), its products on p.
        let cycle = || {
            let nodes = self.nodes;
            let mut down = vec![(Kernel::AmgPresmooth, rows)];
            down.extend(product());
            down.push((Kernel::AmgResidual, nodes));
            let mut up = vec![(Kernel::AmgCorrect, nodes)];
            up.extend(product());
            up.push((Kernel::AmgPostsmooth, rows));
            [Piece::Pass(down), Piece::Coarse(&m.coarse), Piece::Pass(up)]
        };
        let p = &self.buffers.p;
        let mut first = vec![Piece::Pass(start)];
        first.extend(cycle());
        first.extend([Piece::Pass(vec![(Kernel::AmgInitReduce, 1)]), Piece::Copy(&self.buffers.z, p)]);
        let mut window = Vec::new();
        for _ in 0..interval {
            window.extend([Piece::Pass(iteration.clone()), Piece::Copy(p, &m.saved_p)]);
            window.extend(cycle());
            window.extend([Piece::Copy(&m.saved_p, p), Piece::Pass(direction.to_vec())]);
        }
        [first, window]
    }

    /// `before` (what sets the system up), CG on it from the Δv in its buffer, then `after`
    /// (kernels that do nothing until CG is done): all that, as many windows of
    /// `cg_check_interval` iterations as the last solve of this `kind` needed and the read
    /// of the check with `result_parts` go in one submission, one read-back for the solve
    /// and its result. Where that falls short, a window more and its check are queued
    /// behind each check, and `after` and the result come once CG is done.
    fn cg_then(
        &self,
        system: [u32; 4],
        kind: Solve,
        before: &dyn Fn(&mut wgpu::CommandEncoder),
        after: &[(Kernel, u32)],
        result_parts: &[(&wgpu::Buffer, u64)],
    ) -> Result<(CgStats, Vec<u8>), GpuError> {
        let rows = system[0];
        self.ctx.queue.write_buffer(&self.buffers.scalars, 0, bytemuck::bytes_of(&CgScalars::zeroed()));
        let [start, window] = self.cg_kernels(system);
        let params = self.mirror.params();
        let ahead = self.windows_ahead[kind as usize].get().max(1);
        let encoder = || self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("cg") });
        let mut first = encoder();
        before(&mut first);
        self.ctx.copy_buffer(&mut first, &self.buffers.dv, 0, &self.buffers.p, 0, rows as u64 * 16);
        self.encode_pieces(&mut first, &start);
        for _ in 0..ahead {
            self.encode_pieces(&mut first, &window);
        }
        if !after.is_empty() {
            self.encode(&mut first, after);
        }
        let scalars = (&self.buffers.scalars, CG_SCALARS_BYTES);
        let with_result: Vec<(&wgpu::Buffer, u64)> =
            std::iter::once(scalars).chain(result_parts.iter().copied()).collect();
        let read = |pending, parts: &[(&wgpu::Buffer, u64)]| -> Result<(CgScalars, Vec<u8>), GpuError> {
            let mut bytes = vec![0u8; parts.iter().map(|(_, n)| *n as usize).sum()];
            self.ctx.finish_read(pending, &mut bytes)?;
            let s = bytemuck::pod_read_unaligned(&bytes[..CG_SCALARS_BYTES as usize]);
            Ok((s, bytes.split_off(CG_SCALARS_BYTES as usize)))
        };
        let finished = |s: &CgScalars| s.done != 0 || s.iterations >= params.cg_max_iterations;
        let (mut s, mut result) = read(self.ctx.submit_and_read(first, &with_result), &with_result)?;
        if !finished(&s) {
            // Short of the prediction: the next window runs while the host waits for each check.
            let checked_window = || {
                let mut e = encoder();
                self.encode_pieces(&mut e, &window);
                self.ctx.submit_and_read(e, &[scalars])
            };
            let mut checked = checked_window();
            loop {
                let next = checked_window();
                (s, _) = read(std::mem::replace(&mut checked, next), &[scalars])?;
                if finished(&s) {
                    break;
                }
            }
            let mut last = encoder();
            if !after.is_empty() {
                self.encode(&mut last, after);
            }
            (_, result) = read(self.ctx.submit_and_read(last, &with_result), &with_result)?;
        }
        self.windows_ahead[kind as usize].set(s.iterations.div_ceil(params.cg_check_interval));
        let residual = if s.bb > 0.0 { (s.rr / s.bb).max(0.0).sqrt() as f64 } else { 0.0 };
        Ok((CgStats { iterations: s.iterations, relative_residual: residual }, result))
    }

    /// Implicit Euler: the solve with the contacts' outcome and the update queued behind it,
    /// read back in one (see [`GpuSimulation::solve_and_update`]). Where contacts separate at
    /// the step's end they are released, the update undone and the step solved again
    /// without them (at most four rounds, as on the CPU); the CG statistics of all rounds.
    /// The preconditioner's rules judge the first round alone, as the CPU's do.
    fn implicit_step(&mut self) -> Result<StepOutcome, GpuError> {
        let (mut terms, mut system) = self.upload_system();
        let (mut iterations, mut releases, mut first) = (0, 0, 0);
        loop {
            let (cg, (proxy_dv, end_rates), state) = self.solve_and_update(&terms, system, releases == 0)?;
            if releases == 0 {
                first = cg.iterations;
            }
            iterations += cg.iterations;
            let contacts = self.mirror.active_contacts().len();
            if releases == 4 || !self.mirror.release_contacts(&end_rates[..contacts]) {
                self.mirror.record_friction(&end_rates[contacts..]);
                self.system = system;
                self.solves += 1;
                self.probed = false;
                self.note_iterations(first);
                let cg = CgStats { iterations, relative_residual: cg.relative_residual };
                return Ok(StepOutcome { proxy_dv, cg, state });
            }
            releases += 1;
            self.restore_state();
            (terms, system) = self.upload_system();
        }
    }

    /// The step's start, before its first assembly: the Δv a compliance probe borrowed put
    /// back, and CG's start extrapolated from the last two steps' (from the second step on,
    /// as on the CPU).
    fn encode_start(&self, encoder: &mut wgpu::CommandEncoder, rows: u32) {
        let b = &self.buffers;
        let mut whole =
            |from: &wgpu::Buffer, to: &wgpu::Buffer| self.ctx.copy_buffer(encoder, from, 0, to, 0, from.size());
        if self.probed {
            whole(&b.held_dv, &b.dv);
        }
        let extrapolate = self.solves >= 2;
        if extrapolate {
            whole(&b.previous_dv, &b.q);
        }
        whole(&b.dv, &b.previous_dv);
        if extrapolate {
            self.encode(encoder, &[(Kernel::CgExtrapolate, rows)]);
        }
    }

    /// Assembles and solves (the step's `first` solve from its extrapolated start), with the
    /// contacts' outcome and the update behind the solve (no-ops until CG is done): when the
    /// foretold CG windows were enough, the outcome and the state come back with the check,
    /// one read-back for the step; else in one more.
    fn solve_and_update(
        &self,
        terms: &[ContactTerms],
        system: [u32; 4],
        first: bool,
    ) -> Result<(CgStats, Outcome, State), GpuError> {
        let tools = system[3] as usize;
        let rows = tools + terms.len();
        let mut after = Vec::new();
        let mut parts = Vec::new();
        if rows > 0 {
            after.push((Kernel::ContactOutcome, rows as u32));
            parts.push((&self.buffers.bound[CONTACT_BINDINGS.end - 1], rows as u64 * 16));
        }
        after.push((Kernel::ImplicitUpdate, self.nodes));
        let node_bytes = self.nodes as u64 * 16;
        parts.extend([(&self.buffers.x, node_bytes), (&self.buffers.v, node_bytes)]);
        let assembly = self.assembly(system);
        let before = |e: &mut wgpu::CommandEncoder| {
            if first {
                self.encode_start(e, system[0]);
            }
            self.encode(e, &assembly);
        };
        let (cg, bytes) = self.cg_then(system, Solve::Step, &before, &after, &parts)?;
        let (outcome, state) = bytes.split_at(rows * 16);
        Ok((cg, Self::decode_outcome(terms, tools, outcome)?, self.decode_state(state)))
    }

    /// Each coupled tool's local model for the force loop, from the step just taken, its
    /// contact's stiffness solved on the step's own system on the GPU.
    pub fn local_models(&mut self) -> Result<Vec<LocalModel>, GpuError> {
        let h = self.mirror.params().dt;
        let queries = self.mirror.local_queries();
        let mut models = Vec::with_capacity(queries.len());
        for query in queries {
            let compliance = match query.along() {
                Some(b) => self.compliance_along(b)?,
                None => 0.0,
            };
            models.push(query.finish(compliance, h));
        }
        Ok(models)
    }

    /// bᵀA⁻¹b for the system the last step assembled (its contacts included) and b given on
    /// a few rows: CG from zero, then bᵀΔv by the `probe_outcome` kernel (the twin of
    /// `Simulation::compliance_along`), read with the CG's check when its windows were
    /// foretold. The next step assembles afresh.
    fn compliance_along(&mut self, b: &[(usize, Vector3<f64>)]) -> Result<f64, GpuError> {
        let system = self.system;
        let free: Vec<(usize, Vector3<f64>)> =
            b.iter().filter(|(row, _)| !self.mirror.fixed_row(*row)).copied().collect();
        let contacts = system[1] as usize;
        self.reserve_contacts(contacts + 1);
        let mut rhs: BTreeMap<usize, Vector3<f64>> = BTreeMap::new();
        for (row, v) in free.iter().take(CONTACT_ROWS) {
            *rhs.entry(*row).or_insert_with(Vector3::zeros) += v;
        }
        let values: Vec<Vector3<f32>> = rhs.values().map(|v| v.map(|c| c as f32)).collect();
        self.ctx.queue.write_buffer(&self.buffers.probe_rhs, 0, bytemuck::cast_slice(&vec4s(&values)));
        let probe = GpuContactTerm::probe(&free);
        let at = (contacts * std::mem::size_of::<GpuContactTerm>()) as u64;
        self.ctx.queue.write_buffer(&self.buffers.bound[CONTACT_BINDINGS.start], at, bytemuck::bytes_of(&probe));
        // The writes land before the submission's commands: b's rows go in once rhs and Δv
        // are cleared, in the solve's own submission; the step's Δv is held for the next
        // step's start (the first probe since that step holds it).
        let hold = !self.probed;
        let clear_then_b = |encoder: &mut wgpu::CommandEncoder| {
            if hold {
                let dv = &self.buffers.dv;
                self.ctx.copy_buffer(encoder, dv, 0, &self.buffers.held_dv, 0, dv.size());
            }
            encoder.clear_buffer(&self.buffers.rhs, 0, None);
            encoder.clear_buffer(&self.buffers.dv, 0, None);
            for (k, row) in rhs.keys().enumerate() {
                let (from, to) = (k as u64 * 16, *row as u64 * 16);
                self.ctx.copy_buffer(encoder, &self.buffers.probe_rhs, from, &self.buffers.rhs, to, 16);
            }
        };
        let outcome = [(&self.buffers.bound[CONTACT_BINDINGS.end - 1], 16)];
        let (_, bytes) = self.cg_then(system, Solve::Probe, &clear_then_b, &[(Kernel::ProbeOutcome, 1)], &outcome)?;
        self.probed = true;
        let out: [f32; 4] = bytemuck::pod_read_unaligned(&bytes);
        Ok(f64::from(out[0]))
    }

    /// Advances one step on the GPU; reads positions and velocities back for the report.
    pub fn step(&mut self) -> Result<StepReport, GpuSolverError> {
        self.step_batch(1)
    }

    /// Advances `steps` steps. An explicit scheme whose steps need nothing from the host
    /// (no surface contact, no commanded force) runs them in one submission and reads back
    /// once, the state bit for bit that of as many single steps; otherwise they are taken
    /// one by one. The last step's report; a batch that diverged is undone whole.
    pub fn step_batch(&mut self, steps: u32) -> Result<StepReport, GpuSolverError> {
        if steps == 0 {
            return Err(crate::empty_batch().into());
        }
        let integrator = self.mirror.params().integrator;
        let batched = integrator != Integrator::ImplicitEuler && self.mirror.steps_without_the_host();
        let (per_submission, submissions) = if batched { (steps, 1) } else { (1, steps) };
        let mut report = StepReport::default();
        for _ in 0..submissions {
            report = self.steps_in_one_submission(per_submission)?;
        }
        Ok(report)
    }

    /// `steps` steps (more than one only for an explicit batch) and one read-back.
    fn steps_in_one_submission(&mut self, steps: u32) -> Result<StepReport, GpuSolverError> {
        let tools = self.mirror.prepare_step()?;
        if self.multigrid_wanted && self.multigrid.is_none() {
            self.build_multigrid(&tools)?;
        }
        // The implicit step rewrites `system` with its simulated tools and contacts.
        self.upload_params(&tools, [self.nodes, 0, 0, 0]);
        let StepOutcome { proxy_dv, cg, state: [x, v] } = match self.mirror.params().integrator {
            Integrator::ImplicitEuler => self.implicit_step()?,
            _ => {
                let kernels = self.explicit_kernels().repeat(steps as usize);
                let cg = CgStats { iterations: 0, relative_residual: 0.0 };
                StepOutcome { proxy_dv: Vec::new(), cg, state: self.run_then_read_state(&kernels)? }
            }
        };
        self.history_valid = true;
        match self.mirror.accept_steps(x, v, &proxy_dv, cg, steps) {
            Ok(report) => Ok(report),
            Err(err) => {
                // Put the last stable state back on the GPU too.
                self.restore_state();
                self.history_valid = false;
                Err(err.into())
            }
        }
    }

    /// One explicit step's kernels, the scheme's history set up first where it is not valid
    /// (none for implicit Euler, whose step is [`GpuSimulation::implicit_step`]).
    fn explicit_kernels(&mut self) -> Vec<(Kernel, u32)> {
        let (n, e) = (self.nodes, self.springs);
        match self.mirror.params().integrator {
            Integrator::ImplicitEuler => Vec::new(),
            Integrator::ExplicitEuler => {
                vec![(Kernel::SpringForces, e), (Kernel::NodeForces, n), (Kernel::ExplicitEulerUpdate, n)]
            }
            Integrator::Verlet => {
                if !self.history_valid {
                    let h = self.mirror.params().dt as f32;
                    let prev: Vec<Vector3<f32>> = self
                        .mirror
                        .displacements()
                        .iter()
                        .zip(self.mirror.velocities())
                        .map(|(x, v)| x - v * h)
                        .collect();
                    self.ctx.queue.write_buffer(&self.buffers.aux, 0, bytemuck::cast_slice(&vec4s(&prev)));
                }
                vec![(Kernel::SpringForces, e), (Kernel::NodeForces, n), (Kernel::VerletUpdate, n)]
            }
            Integrator::VelocityVerlet => {
                if !self.history_valid {
                    self.run(&[(Kernel::SpringForces, e), (Kernel::NodeForces, n), (Kernel::AccelerationFromForce, n)]);
                }
                vec![
                    (Kernel::VelocityVerletPositions, n),
                    (Kernel::SpringForcesPredicted, e),
                    (Kernel::NodeForces, n),
                    (Kernel::VelocityVerletVelocities, n),
                ]
            }
        }
    }
}

/// The contacts' buffers (bindings 26-30) for `capacity` contacts.
fn contact_buffers(ctx: &GpuContext, capacity: usize) -> [wgpu::Buffer; 5] {
    let per_contact = |bytes: usize| (bytes * capacity) as u64;
    [
        ctx.zeroed_buffer("contact_terms", per_contact(std::mem::size_of::<GpuContactTerm>())),
        ctx.zeroed_buffer("touched", per_contact(CONTACT_ROWS * 16)),
        ctx.zeroed_buffer("incidence", per_contact(CONTACT_ROWS * 8)),
        ctx.zeroed_buffer("contact_y", per_contact(16)),
        ctx.zeroed_buffer("outcome", ((2 * MAX_TOOLS + capacity) * 16) as u64),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Coupling, FixedNodes, Friction, Material, RotationalCoupling, ToolShape};
    use defvol_core::mesh::generate::{self, CellSplit};
    use nalgebra::Isometry3;

    fn cantilever() -> MassSpringModel {
        let mesh =
            generate::lattice(Vector3::zeros(), Vector3::new(0.12, 0.03, 0.03), [8, 2, 2], CellSplit::Five).unwrap();
        let fixed = FixedNodes::Plane { normal: [1.0, 0.0, 0.0], offset: 0.0 }.select(mesh.nodes()).unwrap();
        MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 800.0, damping: 0.5 }, 1000.0, &fixed, None)
            .unwrap()
    }

    /// A slab fixed at the bottom, top at z = 0, boundary spacing 15-17 mm.
    fn slab() -> MassSpringModel {
        let mesh =
            generate::lattice(Vector3::new(0.0, 0.0, -0.06), Vector3::new(0.1, 0.1, 0.0), [6, 6, 4], CellSplit::Five)
                .unwrap();
        let fixed = FixedNodes::Plane { normal: [0.0, 0.0, 1.0], offset: -0.06 }.select(mesh.nodes()).unwrap();
        MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 300.0, damping: 2.0 }, 1000.0, &fixed, None)
            .unwrap()
    }

    /// Steps a 2 mm tool on surface contact down from 3 mm above the slab to 3 mm into it
    /// (over `steps / 2` steps, then held) and 10 mm sideways on the CPU and the GPU (both
    /// f32): the largest node and reaction differences over the run, relative to the largest
    /// displacement and force, and the largest force (N).
    fn surface_contact_run(
        params: SolverParams,
        coupling: Option<Coupling>,
        friction: Option<Friction>,
        steps: usize,
    ) -> (f64, f64, f64) {
        let ctx = defvol_gpu::gpu::test_context().expect("checked by the caller");
        let mut tool = Tool::new(ToolShape::Sphere { radius: 0.001 }, 20_000.0);
        (tool.coupling, tool.friction) = (coupling, friction);
        let model = slab();
        let mut cpu = Simulation::<f32>::new(&model, params.clone(), vec![tool.clone()]).unwrap();
        let mut gpu = GpuSimulation::new(ctx, &model, params, vec![tool]).unwrap();
        let (mut node_gap, mut force_gap, mut largest, mut moved) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        let (mut touched, mut rubbed) = (0, 0.0f64);
        for k in 0..steps {
            let z = 0.003 - 0.006 * (2.0 * k as f64 / steps as f64).min(1.0);
            let pose = Isometry3::translation(0.043 + 0.01 * k as f64 / steps as f64, 0.058, z);
            cpu.tool_mut(0).unwrap().world_from_tool = pose;
            gpu.tool_mut(0).unwrap().world_from_tool = pose;
            let (rc, rg) = (cpu.step().unwrap(), gpu.step().unwrap());
            let (fc, fg) = (Vector3::from(rc.reaction(0).force), Vector3::from(rg.reaction(0).force));
            let (tc, tg) = (Vector3::from(rc.reaction(0).friction), Vector3::from(rg.reaction(0).friction));
            force_gap = force_gap.max((fc - fg).norm()).max((tc - tg).norm());
            largest = largest.max(fc.norm());
            rubbed = rubbed.max(tc.norm());
            moved = moved.max(rc.max_displacement);
            touched += usize::from(!cpu.contacts().is_empty());
            let worst = (cpu.displacements().iter().zip(gpu.mirror().displacements()))
                .map(|(a, b)| f64::from((a - b).norm()))
                .fold(0.0, f64::max);
            node_gap = node_gap.max(worst);
            let (pc, pg) = (cpu.simulated_pose(0).unwrap(), gpu.mirror().simulated_pose(0).unwrap());
            node_gap = node_gap.max((pc.translation.vector - pg.translation.vector).norm());
        }
        assert!(touched > steps / 3 && moved > 5e-4, "the tool pressed: {touched} steps in contact, moved {moved} m");
        assert_eq!(rubbed > 0.1, friction.is_some(), "friction felt: {rubbed} N");
        (node_gap / moved, force_gap / largest, largest)
    }

    /// A coupled tool on surface contact with friction (simulated tool's row, contact and
    /// friction terms, releases): the GPU's nodes, simulated tool and felt force follow the
    /// CPU's.
    #[test]
    fn gpu_matches_cpu_with_a_coupled_tool_on_surface_contact() {
        if defvol_gpu::gpu::test_context().is_none() {
            return;
        }
        let coupling = Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 5.0 };
        let params = SolverParams { gravity: [0.0; 3], dt: 1e-3, cg_tolerance: 1e-6, ..Default::default() };
        let friction = Friction { static_coefficient: 0.5, kinetic_coefficient: 0.3, stick_speed: 1e-4 };
        let (nodes, force, largest) = surface_contact_run(params, Some(coupling), Some(friction), 300);
        assert!(largest > 1.0, "the coupling pulled the tool in: {largest} N");
        // lavapipe: 3e-7 / 2e-7; hardware FMA rounding differs more.
        assert!(nodes <= 1e-4 && force <= 1e-4, "GPU departs from CPU: nodes {nodes:e}, force {force:e} (relative)");
    }

    /// A wide tool on surface contact pressing many boundary nodes at once (an 80 mm sphere
    /// 10 mm into a 5 mm lattice: 69 contacts): more contacts than the contact buffers
    /// first hold, so they grow mid-run (rebinding), and the GPU still follows the CPU
    /// (lavapipe: 1e-8 m of 1e-2 m).
    #[test]
    fn gpu_matches_cpu_when_the_contacts_outgrow_their_buffers() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let mesh =
            generate::lattice(Vector3::new(0.0, 0.0, -0.02), Vector3::new(0.1, 0.1, 0.0), [20, 20, 4], CellSplit::Five)
                .unwrap();
        let fixed = FixedNodes::Plane { normal: [0.0, 0.0, 1.0], offset: -0.02 }.select(mesh.nodes()).unwrap();
        let model =
            MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 300.0, damping: 2.0 }, 1000.0, &fixed, None)
                .unwrap();
        let radius = 0.04;
        let tool = Tool::new(ToolShape::Sphere { radius }, 5000.0);
        let params = SolverParams { gravity: [0.0; 3], dt: 1e-3, cg_tolerance: 1e-6, ..Default::default() };
        let mut cpu = Simulation::<f32>::new(&model, params.clone(), vec![tool.clone()]).unwrap();
        let mut gpu = GpuSimulation::new(ctx, &model, params, vec![tool]).unwrap();
        let mut most = 0;
        for k in 0..110 {
            let pose = Isometry3::translation(0.05, 0.05, radius + 0.001 - 0.0001 * k as f64);
            cpu.tool_mut(0).unwrap().world_from_tool = pose;
            gpu.tool_mut(0).unwrap().world_from_tool = pose;
            cpu.step().unwrap();
            gpu.step().unwrap();
            most = most.max(gpu.mirror().contacts().len());
        }
        assert!(most > 64, "{most} contacts at most: the buffers grew past their first 64");
        let scale = cpu.displacements().iter().map(|u| f64::from(u.norm())).fold(0.0, f64::max);
        let worst = (cpu.displacements().iter().zip(gpu.mirror().displacements()))
            .map(|(a, b)| f64::from((a - b).norm()))
            .fold(0.0, f64::max);
        assert!(scale > 1e-4 && worst <= 1e-4 * scale, "GPU departs by {worst:e} m of {scale:e} m");
    }

    /// A needle with a rotational coupling, tilted into the slab at its far end (the row it
    /// turns on, contacts' gradients on it): the GPU's simulated pose, nodes and felt
    /// torque follow the CPU's.
    #[test]
    fn gpu_matches_cpu_with_a_turning_needle() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let mut tool = Tool::new(ToolShape::Capsule { radius: 0.001, length: 0.04 }, 20_000.0);
        tool.coupling = Some(Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 50.0 });
        tool.rotational_coupling =
            Some(RotationalCoupling { stiffness: 2.0, damping: 0.02, inertia: 1e-5, max_torque: 5.0 });
        let params = SolverParams { gravity: [0.0; 3], dt: 1e-3, cg_tolerance: 1e-6, ..Default::default() };
        let model = slab();
        let mut cpu = Simulation::<f32>::new(&model, params.clone(), vec![tool.clone()]).unwrap();
        let mut gpu = GpuSimulation::new(ctx, &model, params, vec![tool]).unwrap();
        let tilt = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2 + 0.1);
        let (mut turned, mut worst, mut torque_gap, mut largest) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for k in 0..200 {
            let z = 0.02 - 0.017 * (k as f64 / 100.0).min(1.0);
            let pose = Isometry3::from_parts(nalgebra::Translation3::new(0.03, 0.058, z), tilt);
            cpu.tool_mut(0).unwrap().world_from_tool = pose;
            gpu.tool_mut(0).unwrap().world_from_tool = pose;
            let (rc, rg) = (cpu.step().unwrap(), gpu.step().unwrap());
            let (tc, tg) = (Vector3::from(rc.reaction(0).torque), Vector3::from(rg.reaction(0).torque));
            torque_gap = torque_gap.max((tc - tg).norm());
            largest = largest.max(tc.norm());
            let (pc, pg) = (cpu.simulated_pose(0).unwrap(), gpu.mirror().simulated_pose(0).unwrap());
            turned = turned.max(pc.rotation.angle_to(&tilt));
            worst = worst.max(pc.rotation.angle_to(&pg.rotation));
            worst = worst.max((pc.translation.vector - pg.translation.vector).norm() / 0.04);
        }
        assert!(turned > 0.01 && largest > 1e-3, "the needle turned {turned} rad under {largest} N·m");
        // lavapipe: poses 7e-9 apart (the needle turned 0.015 rad), torques 7e-8 of 0.047 N·m.
        assert!(worst < 1e-4 * turned, "poses differ by {worst:e} (rad, or per needle length)");
        assert!(torque_gap < 1e-3 * largest, "torques differ by {torque_gap:e} N·m of {largest:e}");
    }

    /// The force loop's local models from the GPU (the contact's stiffness solved on the
    /// GPU's system) match the CPU's, about to touch and pressing.
    #[test]
    fn gpu_local_models_match_the_cpu_ones() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let mut tool = Tool::new(ToolShape::Sphere { radius: 0.001 }, 20_000.0);
        tool.coupling = Some(Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 5.0 });
        let params = SolverParams { gravity: [0.0; 3], dt: 1e-3, cg_tolerance: 1e-6, ..Default::default() };
        let model = slab();
        let mut cpu = Simulation::<f32>::new(&model, params.clone(), vec![tool.clone()]).unwrap();
        let mut gpu = GpuSimulation::new(ctx, &model, params, vec![tool]).unwrap();
        let (mut ahead, mut pressed, mut worst) = (0, 0, 0.0f64);
        for k in 0..150 {
            let pose = Isometry3::translation(0.043, 0.058, 0.003 - 0.006 * (k as f64 / 100.0).min(1.0));
            cpu.tool_mut(0).unwrap().world_from_tool = pose;
            gpu.tool_mut(0).unwrap().world_from_tool = pose;
            cpu.step().unwrap();
            gpu.step().unwrap();
            let (mc, mg) = (cpu.local_models().remove(0), gpu.local_models().unwrap().remove(0));
            assert!((mc.position - mg.position).norm() < 1e-6, "step {k}: {mc:?} / {mg:?}");
            match (mc.contact, mg.contact) {
                (None, None) => {}
                (Some(c), Some(g)) => {
                    if c.depth > 0.0 {
                        pressed += 1
                    } else {
                        ahead += 1
                    }
                    worst = worst.max((c.stiffness - g.stiffness).abs() / c.stiffness);
                    worst = worst.max((c.normal - g.normal).norm());
                    assert!((c.depth - g.depth).abs() < 1e-6, "step {k}: depth {} / {}", c.depth, g.depth);
                }
                (c, g) => panic!("step {k}: a contact on one side only: {c:?} / {g:?}"),
            }
        }
        assert!(ahead > 3 && pressed > 30, "{ahead} steps about to touch, {pressed} pressing");
        // lavapipe: 3e-6 (CG tolerance 1e-6 on both sides).
        assert!(worst <= 1e-4, "stiffness or normal departs by {worst:e} (relative)");
    }

    /// A thin tool on surface contact without a coupling, implicit and explicit: the GPU
    /// follows the CPU.
    #[test]
    fn gpu_matches_cpu_with_a_thin_tool_on_surface_contact() {
        if defvol_gpu::gpu::test_context().is_none() {
            return;
        }
        for (integrator, dt, steps) in [(Integrator::ImplicitEuler, 1e-3, 200), (Integrator::ExplicitEuler, 1e-4, 1000)]
        {
            let params = SolverParams { integrator, gravity: [0.0; 3], dt, cg_tolerance: 1e-6, ..Default::default() };
            let (nodes, force, _) = surface_contact_run(params, None, None, steps);
            // lavapipe: 2e-7 / 2e-6.
            assert!(
                nodes <= 1e-4 && force <= 1e-4,
                "{integrator:?}: GPU departs from CPU: nodes {nodes:e}, force {force:e} (relative)"
            );
        }
    }

    /// 256 nodes fill one workgroup, so a coupled tool's row opens a second: CG's reductions
    /// count it (they once stopped at the nodes' workgroups, and CG stalled, then diverged
    /// once the contact coupled that row), and the GPU takes the CPU's iterations and path
    /// through a press, its local model solved after each step as the force loop does.
    #[test]
    fn a_simulated_tools_row_in_a_workgroup_of_its_own_is_counted() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let (lo, hi) = (Vector3::new(0.0, 0.0, -0.03), Vector3::new(0.15, 0.03, 0.0));
        let mesh = generate::lattice(lo, hi, [15, 3, 3], CellSplit::Five).unwrap();
        assert_eq!(mesh.nodes().len() as u32, WORKGROUP);
        let fixed = FixedNodes::Plane { normal: [0.0, 0.0, 1.0], offset: -0.03 }.select(mesh.nodes()).unwrap();
        let material = Material::Uniform { stiffness: 300.0, damping: 2.0 };
        let model = MassSpringModel::new(&mesh, &material, 1000.0, &fixed, None).unwrap();
        let mut tool = Tool::new(ToolShape::Sphere { radius: 0.002 }, 20_000.0);
        tool.coupling = Some(Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 10.0 });
        let params = SolverParams { preconditioner: Preconditioner::BlockJacobi, ..Default::default() };
        let mut cpu = Simulation::<f32>::new(&model, params.clone(), vec![tool.clone()]).unwrap();
        let mut gpu = GpuSimulation::new(ctx, &model, params, vec![tool]).unwrap();
        let (mut pressed, mut moved) = (0.0f64, 0.0f64);
        for k in 0..40 {
            let pose = Isometry3::translation(0.075, 0.015, 0.004 - 0.008 * (k as f64 / 20.0).min(1.0));
            cpu.tool_mut(0).unwrap().world_from_tool = pose;
            gpu.tool_mut(0).unwrap().world_from_tool = pose;
            let (rc, rg) = (cpu.step().unwrap(), gpu.step().unwrap());
            let (cpu_local, gpu_local) = (cpu.local_models(), gpu.local_models().unwrap());
            assert_eq!(cpu_local.len(), gpu_local.len());
            let (its_c, its_g) = (rc.cg_iterations, rg.cg_iterations);
            assert!(its_c.abs_diff(its_g) <= its_c / 5 + 2, "step {k}: CG its {its_c} / {its_g}");
            let (fc, fg) = (Vector3::from(rc.reaction(0).force), Vector3::from(rg.reaction(0).force));
            pressed = pressed.max(fc.norm());
            moved = moved.max(rc.max_displacement);
            assert!((fc - fg).norm() <= 1e-3 * pressed.max(1.0), "step {k}: reactions {fc} / {fg} N");
            let gap = (cpu.displacements().iter().zip(gpu.mirror().displacements()))
                .map(|(a, b)| f64::from((a - b).norm()))
                .fold(0.0, f64::max);
            assert!(gap <= 1e-3 * moved.max(1e-4), "step {k}: nodes {gap} m apart");
        }
        assert!(pressed > 1.0 && moved > 1e-3, "the tool pressed: {pressed} N, {moved} m");
    }

    /// Every integrator, with a tool pressing in: GPU and CPU (f32) agree after 100 steps.
    #[test]
    fn gpu_matches_cpu_for_every_integrator() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let model = cantilever();
        for integrator in Integrator::ALL {
            let dt = if integrator == Integrator::ImplicitEuler { 0.005 } else { 2e-4 };
            let params =
                SolverParams { integrator, dt, cg_tolerance: 1e-6, cg_check_interval: 4, ..Default::default() };
            let mut tool = Tool::new(ToolShape::Sphere { radius: 0.01 }, 500.0);
            tool.contact = crate::ContactModel::Nodes;
            tool.world_from_tool = Isometry3::translation(0.1, 0.015, 0.038);
            tool.applied_force = Vector3::new(0.0, 0.0, -0.05);
            let mut cpu = Simulation::<f32>::new(&model, params.clone(), vec![tool.clone()]).unwrap();
            let mut gpu = GpuSimulation::new(ctx.clone(), &model, params, vec![tool]).unwrap();
            let (mut rc, mut rg) = (StepReport::default(), StepReport::default());
            for _ in 0..100 {
                rc = cpu.step().unwrap();
                rg = gpu.step().unwrap();
            }
            let scale = rc.max_displacement;
            assert!(scale > 1e-4, "{integrator:?} moved: {scale}");
            let worst = cpu
                .displacements()
                .iter()
                .zip(gpu.mirror().displacements())
                .map(|(a, b)| (a - b).norm() as f64)
                .fold(0.0, f64::max);
            // lavapipe: 0 (explicit) to 4e-7 (implicit, CG to 1e-6); hardware FMA rounding differs more.
            assert!(
                worst <= 2e-5 * scale,
                "{integrator:?}: GPU differs from CPU by {worst:e} m (max displacement {scale:e} m)"
            );
            if integrator == Integrator::ImplicitEuler {
                assert!(rg.cg_iterations > 0 && rg.residual <= 1e-5, "{rg:?}");
                let (fc, fg) = (rc.reaction(0).force[2], rg.reaction(0).force[2]);
                assert!((fc - fg).abs() <= 1e-2 * fc.abs().max(1e-3), "reaction {fc} on the CPU, {fg} on the GPU");
            }
        }
    }

    /// The multigrid preconditioner on the GPU, over implicit steps of a cantilever sagging
    /// under gravity (3,321 nodes): the CPU multigrid's iterations within 20 %, its solution
    /// within the CG tolerance, and far fewer iterations than block Jacobi on the GPU
    /// (lavapipe: CPU 15, 14, 15, 13; GPU 15, 14, 15, 14; GPU block Jacobi 126-162).
    #[test]
    fn gpu_multigrid_takes_the_cpu_multigrids_iterations_and_solution() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let model = crate::model::clamped_cantilever([40, 8, 8]);
        let params = SolverParams {
            integrator: Integrator::ImplicitEuler,
            dt: 0.01,
            cg_tolerance: 1e-4,
            cg_check_interval: 4,
            preconditioner: Preconditioner::Amg,
            ..Default::default()
        };
        let jacobi_params = SolverParams { preconditioner: Preconditioner::BlockJacobi, ..params.clone() };
        let mut cpu = Simulation::<f32>::new(&model, params.clone(), Vec::new()).unwrap();
        let mut gpu = GpuSimulation::new(ctx.clone(), &model, params, Vec::new()).unwrap();
        let mut jacobi = GpuSimulation::new(ctx, &model, jacobi_params, Vec::new()).unwrap();
        let mut iterations = Vec::new();
        for _ in 0..4 {
            let (c, g, j) = (cpu.step().unwrap(), gpu.step().unwrap(), jacobi.step().unwrap());
            iterations.push([c.cg_iterations, g.cg_iterations, j.cg_iterations]);
            let (c, g) = (f64::from(c.cg_iterations), f64::from(g.cg_iterations));
            assert!((g - c).abs() <= 0.2 * c + 1.0, "iterations cpu / gpu / gpu jacobi: {iterations:?}");
            assert!(f64::from(j.cg_iterations) > 2.0 * g, "{iterations:?}");
        }
        let scale = cpu.displacements().iter().map(|u| u.norm()).fold(0.0f32, f32::max);
        let worst = cpu
            .displacements()
            .iter()
            .zip(gpu.mirror().displacements())
            .map(|(a, b)| (a - b).norm())
            .fold(0.0f32, f32::max);
        assert!(scale > 1e-4 && worst <= 1e-3 * scale, "{worst:e} against {scale:e}; iterations {iterations:?}");
    }

    /// An implicit step (no contacts) queues as many CG windows as the last step needed,
    /// and the update behind them: when that was enough, its one read-back is the check
    /// with the state; when it fell short by k windows, the check after each (and one
    /// queued behind the last) and the state come back apart.
    #[test]
    fn an_implicit_step_is_one_read_back_when_the_last_step_foretold_its_cg_windows() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let params = SolverParams {
            integrator: Integrator::ImplicitEuler,
            dt: 0.005,
            cg_tolerance: 1e-6,
            cg_check_interval: 4,
            ..Default::default()
        };
        let mut gpu = GpuSimulation::new(ctx.clone(), &cantilever(), params, Vec::new()).unwrap();
        let (mut foretold, mut hits) = (1, 0);
        for _ in 0..8 {
            let start = ctx.counters();
            let report = gpu.step().unwrap();
            let counted = ctx.counters().since(&start);
            let needed = u64::from(report.cg_iterations.div_ceil(4));
            assert!(needed > 1, "{report:?}");
            let expected = if needed <= foretold { 1 } else { needed - foretold + 3 };
            assert_eq!(counted.readbacks, expected, "{report:?}, {foretold} windows foretold");
            hits += usize::from(needed <= foretold);
            foretold = needed;
        }
        assert!(hits >= 4, "the last step foretold {hits} of 8");
    }

    /// A coupled tool held 2 mm into the slab on surface contact: the contacts' outcome
    /// (for the release rule and the simulated tool) and the state come back with the CG
    /// check, so a step in contact is one submission and one read-back when the last step
    /// foretold its CG windows, as a step without contacts is; the local model's probe
    /// likewise (b set up in the solve's own submission), and short of its windows each
    /// check still rides in the submission of the window it checks.
    #[test]
    fn a_step_in_contact_and_its_probe_are_one_submission_and_read_back_when_their_cg_windows_were_foretold() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let params = SolverParams {
            gravity: [0.0; 3],
            dt: 1e-3,
            cg_tolerance: 1e-6,
            cg_check_interval: 4,
            ..Default::default()
        };
        let mut tool = Tool::new(ToolShape::Sphere { radius: 0.002 }, 20_000.0);
        tool.coupling = Some(Coupling { stiffness: 2000.0, damping: 5.0, mass: 0.02, max_force: 5.0 });
        let mut gpu = GpuSimulation::new(ctx.clone(), &slab(), params, vec![tool]).unwrap();
        let (mut foretold, mut hits, mut probes_in_one) = (0, 0, 0);
        for k in 0..80 {
            let z = 0.003 - 0.005 * (k as f64 / 40.0).min(1.0);
            gpu.tool_mut(0).unwrap().world_from_tool = Isometry3::translation(0.05, 0.05, z);
            let start = ctx.counters();
            let report = gpu.step().unwrap();
            let stepped = ctx.counters();
            let models = gpu.local_models().unwrap();
            let (step, probe) = (stepped.since(&start), ctx.counters().since(&stepped));
            let needed = u64::from(report.cg_iterations.div_ceil(4));
            if k >= 40 {
                assert!(!gpu.mirror().contacts().is_empty() && needed > 1, "step {k}: {report:?}");
                assert!(models.len() == 1 && models[0].contact.is_some(), "step {k}: {models:?}");
                // Short by w windows: the first check, w + 1 windows with theirs, the result.
                let expected = if needed <= foretold { (1, 1) } else { (needed - foretold + 3, needed - foretold + 3) };
                assert_eq!((step.submissions, step.readbacks), expected, "step {k}: {report:?}, {foretold} foretold");
                assert!(probe.readbacks >= 1 && probe.submissions == probe.readbacks, "step {k}: {probe:?}");
                hits += usize::from(needed <= foretold);
                probes_in_one += usize::from((probe.submissions, probe.readbacks) == (1, 1));
            }
            foretold = needed.max(1);
        }
        assert!(hits >= 20 && probes_in_one >= 20, "foretold: {hits} steps, {probes_in_one} probes of 40");
    }

    /// Explicit steps batched, a tool dented into the nodes and gravity: after the first
    /// batch (which sets a scheme's history up), a batch is one submission and one
    /// read-back, and every scheme reaches the state and the report of as many single
    /// steps, bit for bit. A commanded force (spread by where the nodes are) steps one by
    /// one, to the same bits.
    #[test]
    fn an_explicit_batch_is_one_submission_and_read_back_and_steps_as_single_steps_bit_for_bit() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let model = cantilever();
        let explicit = [Integrator::ExplicitEuler, Integrator::Verlet, Integrator::VelocityVerlet];
        for (integrator, force) in explicit.map(|i| (i, 0.0)).into_iter().chain([(Integrator::Verlet, -0.05)]) {
            let params = SolverParams { integrator, dt: 2e-4, ..Default::default() };
            let mut tool = Tool::new(ToolShape::Sphere { radius: 0.01 }, 500.0);
            tool.contact = crate::ContactModel::Nodes;
            tool.world_from_tool = Isometry3::translation(0.1, 0.015, 0.038);
            tool.applied_force = Vector3::new(0.0, 0.0, force);
            let mut single = GpuSimulation::new(ctx.clone(), &model, params.clone(), vec![tool.clone()]).unwrap();
            let mut batched = GpuSimulation::new(ctx.clone(), &model, params, vec![tool]).unwrap();
            let mut expected = StepReport::default();
            for _ in 0..60 {
                expected = single.step().unwrap();
            }
            batched.step_batch(13).unwrap();
            let start = ctx.counters();
            let report = batched.step_batch(47).unwrap();
            let counted = ctx.counters().since(&start);
            let one_by_one = if force == 0.0 { 1 } else { 47 };
            assert_eq!((counted.submissions, counted.readbacks), (one_by_one, one_by_one), "{integrator:?} {force}");
            assert!(expected.max_displacement > 1e-6, "{integrator:?} moved {}", expected.max_displacement);
            assert_eq!(report, expected, "{integrator:?}");
            let bits = |s: &GpuSimulation| -> Vec<u32> {
                let (x, v) = (s.mirror().displacements(), s.mirror().velocities());
                x.iter().chain(v).flat_map(|p| p.iter().map(|c| c.to_bits()).collect::<Vec<_>>()).collect()
            };
            assert_eq!(bits(&batched), bits(&single), "{integrator:?}");
        }
    }
}
