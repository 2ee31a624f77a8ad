//! The solver on the GPU: `solver.wgsl` beside this file, run through wgpu. A host-side
//! [`Simulation<f32>`] mirrors the state: it validates tool inputs, spreads commanded forces,
//! and checks and reports each step exactly as the CPU path does, so both paths report alike.
//!
//! CG runs `cg_check_interval` iterations per submission; the reductions and the stopping
//! test stay on the GPU (a `done` flag makes the remaining kernels of a batch return at
//! once), so the host reads back one small struct per batch instead of syncing every iteration.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use nalgebra::Vector3;

use super::cpu::CgStats;
use super::kernels::ContactTool;
use super::{Integrator, MassSpringModel, Simulation, SolverError, SolverParams, StepReport, Tool};
use defvol_gpu::gpu::{Binding, GpuContext, GpuError, Kernels};

/// Storage buffers the solver shader binds at once.
const STORAGE_BUFFERS: u32 = 25;
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
    #[error(
        "tool {0} touches the boundary surface or follows its device through a coupling; \
         the GPU kernels push nodes only (contact: nodes, no coupling)"
    )]
    SurfaceContact(usize),
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
}

/// The entry points of `solver.wgsl`; the discriminant indexes the pipelines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kernel {
    SpringTerms,
    SpringForces,
    SpringForcesPredicted,
    NodeTerms,
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
}

impl Kernel {
    const ALL: [Kernel; 19] = [
        Kernel::SpringTerms,
        Kernel::SpringForces,
        Kernel::SpringForcesPredicted,
        Kernel::NodeTerms,
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
    ];

    fn entry_point(self) -> &'static str {
        match self {
            Kernel::SpringTerms => "spring_terms",
            Kernel::SpringForces => "spring_forces",
            Kernel::SpringForcesPredicted => "spring_forces_predicted",
            Kernel::NodeTerms => "node_terms",
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
        }
    }
}

/// Read-only bindings of the shader (the rest are read-write storage, 0 is the uniform).
const READ_ONLY: [u32; 8] = [1, 2, 3, 4, 5, 8, 24, 25];

struct Buffers {
    params: wgpu::Buffer,
    /// Displacements from rest.
    x: wgpu::Buffer,
    v: wgpu::Buffer,
    external: wgpu::Buffer,
    dv: wgpu::Buffer,
    p: wgpu::Buffer,
    scalars: wgpu::Buffer,
    aux: wgpu::Buffer,
}

pub struct GpuSimulation {
    ctx: Arc<GpuContext>,
    mirror: Simulation<f32>,
    nodes: u32,
    springs: u32,
    pipelines: [wgpu::ComputePipeline; Kernel::ALL.len()],
    bind_group: wgpu::BindGroup,
    buffers: Buffers,
    history_valid: bool,
}

fn vec4s(v: &[Vector3<f32>]) -> Vec<[f32; 4]> {
    v.iter().map(|p| [p.x, p.y, p.z, 0.0]).collect()
}

fn groups(count: u32) -> u32 {
    count.div_ceil(WORKGROUP).max(1)
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
        check_tools(&tools)?;
        ctx.require_storage_buffers("the solver", STORAGE_BUFFERS)?;
        let mirror = Simulation::<f32>::new(model, params, tools)?;
        let n = model.node_count();
        let e = model.springs.len();
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
        let springs: Vec<[u32; 2]> = model.springs.clone();
        let spring_params: Vec<[f32; 4]> = (0..e)
            .map(|s| [model.rest_length[s] as f32, model.stiffness[s] as f32, model.damping[s] as f32, 0.0])
            .collect();
        let node_params: Vec<[f32; 4]> =
            (0..n).map(|i| [model.mass[i] as f32, if model.fixed[i] { 1.0 } else { 0.0 }, 0.0, 0.0]).collect();
        let adjacency: Vec<[u32; 2]> = model.adjacency.clone();
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
        let b = Buffers {
            params: ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("params"),
                size: std::mem::size_of::<GpuParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            x: buf("u", bytemuck::cast_slice(&zeros4(n))),
            v: buf("v", bytemuck::cast_slice(&zeros4(n))),
            external: buf("external", bytemuck::cast_slice(&zeros4(n))),
            dv: buf("dv", bytemuck::cast_slice(&zeros4(n))),
            p: buf("p", bytemuck::cast_slice(&zeros4(n))),
            scalars: buf("scalars", bytemuck::bytes_of(&CgScalars::zeroed())),
            aux: buf("aux", bytemuck::cast_slice(&zeros4(n))),
        };
        let others = [
            buf("springs", bytemuck::cast_slice(&springs)),
            buf("spring_params", bytemuck::cast_slice(&spring_params)),
            buf("offsets", bytemuck::cast_slice(&model.offsets)),
            buf("adjacency", bytemuck::cast_slice(&adjacency)),
            buf("node_params", bytemuck::cast_slice(&node_params)),
            buf("spring_force", bytemuck::cast_slice(&zeros4(e))),
            buf("spring_kv", bytemuck::cast_slice(&zeros4(e))),
            buf("spring_block", bytemuck::cast_slice(&mat3(e))),
            buf("diag", bytemuck::cast_slice(&mat3(n))),
            buf("precond", bytemuck::cast_slice(&mat3(n))),
            buf("rhs", bytemuck::cast_slice(&zeros4(n))),
            buf("r", bytemuck::cast_slice(&zeros4(n))),
            buf("z", bytemuck::cast_slice(&zeros4(n))),
            buf("q", bytemuck::cast_slice(&zeros4(n))),
            buf("partials", bytemuck::cast_slice(&zeros4(groups(n as u32) as usize))),
            buf("force", bytemuck::cast_slice(&zeros4(n))),
            buf("rest_edge", bytemuck::cast_slice(&rest_edge)),
            buf("rest_pos", bytemuck::cast_slice(&rest_pos)),
        ];
        let [springs_b, spring_params_b, offsets_b, adjacency_b, node_params_b, spring_force_b, spring_kv_b, spring_block_b, diag_b, precond_b, rhs_b, r_b, z_b, q_b, partials_b, force_b, rest_edge_b, rest_pos_b] =
            &others;
        let order: [&wgpu::Buffer; 26] = [
            &b.params,
            springs_b,
            spring_params_b,
            offsets_b,
            adjacency_b,
            node_params_b,
            &b.x,
            &b.v,
            &b.external,
            spring_force_b,
            spring_kv_b,
            spring_block_b,
            diag_b,
            precond_b,
            rhs_b,
            &b.dv,
            r_b,
            z_b,
            &b.p,
            q_b,
            partials_b,
            &b.scalars,
            &b.aux,
            force_b,
            rest_edge_b,
            rest_pos_b,
        ];
        let bind_group = ctx.bind_group("solver", &layout, &order);
        Ok(Self {
            ctx,
            mirror,
            nodes: n as u32,
            springs: e as u32,
            pipelines,
            bind_group,
            buffers: b,
            history_valid: false,
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

    fn dispatch(&self, pass: &mut wgpu::ComputePass<'_>, kernel: Kernel, invocations: u32) {
        pass.set_pipeline(&self.pipelines[kernel as usize]);
        pass.dispatch_workgroups(groups(invocations), 1, 1);
    }

    fn run(&self, kernels: &[(Kernel, u32)]) {
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("solver") });
        {
            let mut pass = encoder
                .begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("solver"), timestamp_writes: None });
            pass.set_bind_group(0, &self.bind_group, &[]);
            for (kernel, invocations) in kernels {
                self.dispatch(&mut pass, *kernel, *invocations);
            }
        }
        self.ctx.queue.submit([encoder.finish()]);
    }

    fn upload_params(&self, tools: &[ContactTool<f32>]) {
        let p = self.mirror.params();
        let mut gpu_tools = [GpuTool::zeroed(); MAX_TOOLS];
        for (slot, t) in gpu_tools.iter_mut().zip(tools) {
            *slot = GpuTool { a: [t.a.x, t.a.y, t.a.z, t.radius], b: [t.b.x, t.b.y, t.b.z, t.stiffness] };
        }
        let params = GpuParams {
            gravity_h: [p.gravity[0] as f32, p.gravity[1] as f32, p.gravity[2] as f32, p.dt as f32],
            counts: [self.nodes, self.springs, tools.len() as u32, groups(self.nodes)],
            cg: [(p.cg_tolerance * p.cg_tolerance) as f32, p.cg_max_iterations as f32, 0.0, 0.0],
            tools: gpu_tools,
        };
        self.ctx.queue.write_buffer(&self.buffers.params, 0, bytemuck::bytes_of(&params));
        self.ctx.queue.write_buffer(
            &self.buffers.external,
            0,
            bytemuck::cast_slice(&vec4s(self.mirror.external_forces())),
        );
    }

    fn read_vec(&self, buffer: &wgpu::Buffer) -> Result<Vec<Vector3<f32>>, GpuError> {
        let bytes = self.ctx.read_back(buffer, self.nodes as u64 * 16)?;
        let v: &[[f32; 4]] = bytemuck::try_cast_slice(&bytes).map_err(|e| GpuError::Readback(e.to_string()))?;
        Ok(v.iter().map(|p| Vector3::new(p[0], p[1], p[2])).collect())
    }

    fn solve(&self) -> Result<CgStats, GpuError> {
        let (n, q) = (self.nodes, &self.ctx.queue);
        q.write_buffer(&self.buffers.scalars, 0, bytemuck::bytes_of(&CgScalars::zeroed()));
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("cg start") });
        encoder.copy_buffer_to_buffer(&self.buffers.dv, 0, &self.buffers.p, 0, n as u64 * 16);
        self.ctx.queue.submit([encoder.finish()]);
        self.run(&[
            (Kernel::SpringTerms, self.springs),
            (Kernel::NodeTerms, n),
            (Kernel::CgStartSpmv, n),
            (Kernel::CgInit, n),
            (Kernel::CgInitReduce, 1),
        ]);
        let params = self.mirror.params();
        let batch: Vec<(Kernel, u32)> = (0..params.cg_check_interval)
            .flat_map(|_| {
                [
                    (Kernel::CgSpmv, n),
                    (Kernel::CgAlpha, 1),
                    (Kernel::CgUpdate, n),
                    (Kernel::CgBeta, 1),
                    (Kernel::CgDirection, n),
                ]
            })
            .collect();
        loop {
            let bytes = self.ctx.read_back(&self.buffers.scalars, std::mem::size_of::<CgScalars>() as u64)?;
            let s: CgScalars = bytemuck::pod_read_unaligned(&bytes);
            if s.done != 0 || s.iterations >= params.cg_max_iterations {
                let residual = if s.bb > 0.0 { (s.rr / s.bb).max(0.0).sqrt() as f64 } else { 0.0 };
                return Ok(CgStats { iterations: s.iterations, relative_residual: residual });
            }
            self.run(&batch);
        }
    }

    /// Advances one step on the GPU; reads positions and velocities back for the report.
    pub fn step(&mut self) -> Result<StepReport, GpuSolverError> {
        check_tools(self.mirror.tools())?;
        let tools = self.mirror.prepare_step()?;
        self.upload_params(&tools);
        let (n, e) = (self.nodes, self.springs);
        let integrator = self.mirror.params().integrator;
        let mut cg = CgStats { iterations: 0, relative_residual: 0.0 };
        match integrator {
            Integrator::ImplicitEuler => {
                cg = self.solve()?;
                self.run(&[(Kernel::ImplicitUpdate, n)]);
            }
            Integrator::ExplicitEuler => {
                self.run(&[(Kernel::SpringForces, e), (Kernel::NodeForces, n), (Kernel::ExplicitEulerUpdate, n)])
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
                self.run(&[(Kernel::SpringForces, e), (Kernel::NodeForces, n), (Kernel::VerletUpdate, n)]);
            }
            Integrator::VelocityVerlet => {
                if !self.history_valid {
                    self.run(&[(Kernel::SpringForces, e), (Kernel::NodeForces, n), (Kernel::AccelerationFromForce, n)]);
                }
                self.run(&[
                    (Kernel::VelocityVerletPositions, n),
                    (Kernel::SpringForcesPredicted, e),
                    (Kernel::NodeForces, n),
                    (Kernel::VelocityVerletVelocities, n),
                ]);
            }
        }
        self.history_valid = true;
        let x = self.read_vec(&self.buffers.x)?;
        let v = self.read_vec(&self.buffers.v)?;
        match self.mirror.accept_step(x, v, cg) {
            Ok(report) => Ok(report),
            Err(err) => {
                // Put the last stable state back on the GPU too.
                self.ctx.queue.write_buffer(
                    &self.buffers.x,
                    0,
                    bytemuck::cast_slice(&vec4s(self.mirror.displacements())),
                );
                self.ctx.queue.write_buffer(&self.buffers.v, 0, bytemuck::cast_slice(&vec4s(self.mirror.velocities())));
                self.history_valid = false;
                Err(err.into())
            }
        }
    }
}

/// The GPU kernels push nodes one by one: surface contact and couplings run on the CPU.
fn check_tools(tools: &[Tool]) -> Result<(), GpuSolverError> {
    match tools.iter().position(|t| t.contact != super::ContactModel::Nodes || t.coupling.is_some()) {
        Some(index) => Err(GpuSolverError::SurfaceContact(index)),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{FixedNodes, Material, ToolShape};
    use defvol_core::mesh::generate;
    use nalgebra::Isometry3;

    fn cantilever() -> MassSpringModel {
        let mesh =
            generate::lattice(Vector3::zeros(), Vector3::new(0.12, 0.03, 0.03), [8, 2, 2], generate::CellSplit::Five)
                .unwrap();
        let fixed = FixedNodes::Plane { normal: [1.0, 0.0, 0.0], offset: 0.0 }.select(mesh.nodes()).unwrap();
        MassSpringModel::new(&mesh, &Material::Uniform { stiffness: 800.0, damping: 0.5 }, 1000.0, &fixed, None)
            .unwrap()
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
}
