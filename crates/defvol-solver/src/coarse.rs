//! The multigrid coarse correction on the device: the hierarchy [`Amg`] builds on the CPU,
//! uploaded once and applied by `coarse.wgsl` as a chain of dispatches in one compute pass
//! (restrictions down, the coarsest level's dense inverse, then prolongations and the
//! additive levels' Jacobi terms back up), so a preconditioner application is recorded into
//! the solver's own submission with nothing read back. [`Amg::coarse_correction`] is its
//! CPU twin, in the same order of operations.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};

use crate::amg::{Amg, CsrF32};
use defvol_gpu::gpu::{groups_2d, Binding, GpuContext, GpuError, Kernels};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    rows: u32,
    groups: u32,
    cols: u32,
    omega: f32,
}

const WORKGROUP: u32 = 64;
const CSR_PRODUCT: usize = 0;
const ADD_JACOBI: usize = 1;
const DENSE_PRODUCT: usize = 2;

/// One dispatch of the chain: a kernel over `rows` rows with its buffers bound.
struct Dispatch {
    kernel: usize,
    rows: u32,
    bind_group: wgpu::BindGroup,
}

/// The hierarchy on the device and the chain of dispatches that applies it.
pub struct DeviceCoarseCorrection {
    ctx: Arc<GpuContext>,
    kernels: Kernels<3>,
    /// The fine residual (input) and the fine correction (output), f32, `stride` per node.
    residual: wgpu::Buffer,
    correction: wgpu::Buffer,
    dispatches: Vec<Dispatch>,
    unknowns: usize,
}

/// Builds the chain's dispatches, uploading each operator as it comes.
struct Chain<'a> {
    ctx: &'a GpuContext,
    kernels: &'a Kernels<3>,
    /// Bound where a kernel reads no index arrays.
    unused: wgpu::Buffer,
    dispatches: Vec<Dispatch>,
}

impl Chain<'_> {
    fn upload(&self, what: &'static str, label: &str, data: &[u8]) -> Result<wgpu::Buffer, GpuError> {
        self.ctx.require_binding_size(what, data.len() as u64)?;
        Ok(self.ctx.storage_buffer(label, if data.is_empty() { &[0; 4] } else { data }))
    }

    fn push(&mut self, kernel: usize, rows: usize, cols: usize, omega: f64, buffers: [&wgpu::Buffer; 5]) {
        let rows = rows as u32;
        let params = Params { rows, groups: groups_2d(rows, WORKGROUP).0, cols: cols as u32, omega: omega as f32 };
        let params = wgpu::util::DeviceExt::create_buffer_init(
            &self.ctx.device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("coarse correction params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM,
            },
        );
        let [a, b, c, x, y] = buffers;
        let bind_group = self.ctx.bind_group("coarse correction", &self.kernels.layout, &[&params, a, b, c, x, y]);
        self.dispatches.push(Dispatch { kernel, rows, bind_group });
    }

    /// y = m x.
    fn csr(&mut self, what: &'static str, m: &CsrF32, x: &wgpu::Buffer, y: &wgpu::Buffer) -> Result<(), GpuError> {
        let indptr = self.upload(what, "csr indptr", bytemuck::cast_slice(&m.indptr))?;
        let indices = self.upload(what, "csr indices", bytemuck::cast_slice(&m.indices))?;
        let values = self.upload(what, "csr values", bytemuck::cast_slice(&m.values))?;
        self.push(CSR_PRODUCT, m.rows, 0, 0.0, [&indptr, &indices, &values, x, y]);
        Ok(())
    }

    /// y += ω D⁻¹ x.
    fn jacobi(&mut self, dinv: &[f64], omega: f64, x: &wgpu::Buffer, y: &wgpu::Buffer) -> Result<(), GpuError> {
        let d: Vec<f32> = dinv.iter().map(|&v| v as f32).collect();
        let d = self.upload("a coarse level's diagonal", "jacobi diagonal", bytemuck::cast_slice(&d))?;
        let unused = self.unused.clone();
        self.push(ADD_JACOBI, dinv.len(), 0, omega, [&unused, &unused, &d, x, y]);
        Ok(())
    }

    /// y = m x, m dense.
    fn dense(&mut self, m: &nalgebra::DMatrix<f64>, x: &wgpu::Buffer, y: &wgpu::Buffer) -> Result<(), GpuError> {
        let rows: Vec<f32> = (0..m.nrows()).flat_map(|r| (0..m.ncols()).map(move |c| m[(r, c)] as f32)).collect();
        let m32 = self.upload("the coarsest level's inverse", "coarsest inverse", bytemuck::cast_slice(&rows))?;
        let unused = self.unused.clone();
        self.push(DENSE_PRODUCT, m.nrows(), m.ncols(), 0.0, [&unused, &unused, &m32, x, y]);
        Ok(())
    }
}

/// `m` with its columns read from a vector of `stride` floats per node (xyz first): the
/// restriction reading the solver's `vec4` rows.
fn strided_columns(m: &CsrF32, stride: usize) -> CsrF32 {
    let mut out = m.clone();
    for c in &mut out.indices {
        *c = (stride * (*c as usize / 3) + *c as usize % 3) as u32;
    }
    out
}

/// `m` with its rows written to a vector of `stride` floats per node (xyz first, the rest
/// empty rows, so 0): the prolongation writing the solver's `vec4` rows.
fn strided_rows(m: &CsrF32, stride: usize) -> CsrF32 {
    let nodes = m.rows / 3;
    let mut indptr = Vec::with_capacity(nodes * stride + 1);
    indptr.push(0);
    for node in 0..nodes {
        for k in 0..stride {
            let end = if k < 3 { m.indptr[3 * node + k + 1] } else { m.indptr[3 * node + 3] };
            indptr.push(end);
        }
    }
    CsrF32 { rows: nodes * stride, indptr, indices: m.indices.clone(), values: m.values.clone() }
}

impl DeviceCoarseCorrection {
    /// Uploads `amg`'s operators; an error names the first one past the adapter's limits.
    pub fn new(ctx: Arc<GpuContext>, amg: &Amg) -> Result<Self, GpuError> {
        let unknowns = amg.p.rows;
        let vector = |label: &str| ctx.zeroed_buffer(label, unknowns.max(1) as u64 * 4);
        let (residual, correction) = (vector("amg residual"), vector("amg correction"));
        Self::on(ctx, amg, residual, correction, 3)
    }

    /// As [`Self::new`], reading the residual from and writing the correction to the given
    /// buffers of `stride` floats per node (4: the solver's `vec4` rows; the 4th left 0).
    pub fn on(
        ctx: Arc<GpuContext>,
        amg: &Amg,
        residual: wgpu::Buffer,
        correction: wgpu::Buffer,
        stride: usize,
    ) -> Result<Self, GpuError> {
        ctx.require_storage_buffers("the multigrid coarse correction", 5)?;
        let kernels = ctx.kernels(
            "coarse.wgsl",
            include_str!("coarse.wgsl"),
            &[Binding::Uniform, Binding::Read, Binding::Read, Binding::Read, Binding::Read, Binding::ReadWrite],
            ["csr_product", "add_jacobi", "dense_product"],
        );
        let vector = |label: &str, len: usize| ctx.zeroed_buffer(label, len.max(1) as u64 * 4);
        let unknowns = amg.p.rows / 3 * stride;
        // Level k's right-hand side b[k] and solution x[k]; k = 0 is the first coarse level.
        let sizes: Vec<usize> = std::iter::once(amg.r.rows).chain(amg.levels.iter().map(|l| l.r.rows)).collect();
        let b: Vec<wgpu::Buffer> = sizes.iter().map(|&n| vector("amg level rhs", n)).collect();
        let x: Vec<wgpu::Buffer> = sizes.iter().map(|&n| vector("amg level solution", n)).collect();
        let mut chain = Chain { ctx: &ctx, kernels: &kernels, unused: vector("unused", 1), dispatches: Vec::new() };
        chain.csr("the first restriction", &strided_columns(&amg.r, stride), &residual, &b[0])?;
        for (k, level) in amg.levels.iter().enumerate() {
            chain.csr("a coarse restriction", &level.r, &b[k], &b[k + 1])?;
        }
        let last = sizes.len() - 1;
        chain.dense(&amg.coarsest_inverse(), &b[last], &x[last])?;
        for (k, level) in amg.levels.iter().enumerate().rev() {
            chain.csr("a coarse prolongation", &level.p, &x[k + 1], &x[k])?;
            chain.jacobi(&level.dinv, level.omega, &b[k], &x[k])?;
        }
        chain.csr("the fine prolongation", &strided_rows(&amg.p, stride), &x[0], &correction)?;
        let dispatches = chain.dispatches;
        Ok(Self { ctx, kernels, residual, correction, dispatches, unknowns })
    }

    /// The fine residual the chain reads (f32 per unknown, node-major xyz).
    pub fn residual(&self) -> &wgpu::Buffer {
        &self.residual
    }

    /// The fine correction the chain writes: P (cycle) R residual.
    pub fn correction(&self) -> &wgpu::Buffer {
        &self.correction
    }

    /// Dispatches in the chain (each reads what the one before wrote).
    pub fn len(&self) -> usize {
        self.dispatches.len()
    }

    pub fn is_empty(&self) -> bool {
        self.dispatches.is_empty()
    }

    /// Records the chain into `pass`.
    pub fn record(&self, pass: &mut wgpu::ComputePass) {
        for d in &self.dispatches {
            pass.set_pipeline(&self.kernels.pipelines[d.kernel]);
            pass.set_bind_group(0, &d.bind_group, &[]);
            let (x, y) = groups_2d(d.rows, WORKGROUP);
            pass.dispatch_workgroups(x, y, 1);
        }
    }

    /// The correction of a residual from the host: one upload, one submission, one read-back.
    pub fn apply(&self, residual: &[f32]) -> Result<Vec<f32>, GpuError> {
        if residual.len() != self.unknowns {
            return Err(GpuError::Readback(format!(
                "{} residual values for {} unknowns",
                residual.len(),
                self.unknowns
            )));
        }
        self.ctx.queue.write_buffer(&self.residual, 0, bytemuck::cast_slice(residual));
        let mut encoder = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("coarse correction") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("coarse correction"),
                timestamp_writes: self.ctx.pass_timestamps(),
            });
            self.record(&mut pass);
        }
        let bytes = self.unknowns as u64 * 4;
        let pending = self.ctx.submit_and_read(encoder, &[(&self.correction, bytes)]);
        let mut out = vec![0f32; self.unknowns];
        self.ctx.finish_read(pending, bytemuck::cast_slice_mut(&mut out))?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Integrator, Preconditioner, Simulation, SolverParams};

    /// The CPU's own hierarchy for a cantilever's implicit system (1,422 unknowns on the first
    /// coarse level, a dense coarsest of 42): on the device it corrects the system's right-hand
    /// side and a rough residual as the CPU cycle does, to f32 rounding (1e-5 of the largest
    /// value; measured 5e-7).
    #[test]
    fn the_device_coarse_correction_is_the_cpu_cycles() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let model = crate::model::clamped_cantilever([40, 8, 8]);
        let params = SolverParams {
            integrator: Integrator::ImplicitEuler,
            preconditioner: Preconditioner::Amg,
            ..SolverParams::default()
        };
        let mut sim = Simulation::<f32>::new(&model, params, Vec::new()).unwrap();
        let (_, rhs) = sim.assembled_system().unwrap();
        sim.prepare_preconditioner();
        let amg = sim.multigrid().expect("a hierarchy");
        assert!(!amg.levels.is_empty(), "coarse sizes {:?}", amg.coarse_sizes);
        let device = DeviceCoarseCorrection::new(ctx.clone(), amg).unwrap();
        assert_eq!(device.len(), 3 * amg.levels.len() + 3);
        // The same chain on the solver's vec4 rows: the 4th value ignored on the way in, 0 out.
        let nodes = amg.p.rows / 3;
        let strided = DeviceCoarseCorrection::on(
            ctx.clone(),
            amg,
            ctx.zeroed_buffer("vec4 residual", nodes as u64 * 16),
            ctx.zeroed_buffer("vec4 correction", nodes as u64 * 16),
            4,
        )
        .unwrap();
        let rough: Vec<f64> = (0..rhs.len()).map(|i| ((i * 7919) % 101) as f64 / 50.0 - 1.0).collect();
        for residual in [rhs, rough] {
            let want = amg.coarse_correction(&residual);
            let got = device.apply(&residual.iter().map(|&v| v as f32).collect::<Vec<_>>()).unwrap();
            let rows: Vec<f32> =
                residual.chunks(3).flat_map(|r| [r[0] as f32, r[1] as f32, r[2] as f32, 7.0]).collect();
            let got4 = strided.apply(&rows).unwrap();
            for (node, (four, three)) in got4.chunks(4).zip(got.chunks(3)).enumerate() {
                assert_eq!((&four[..3], four[3]), (three, 0.0), "node {node}");
            }
            let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let worst = got.iter().zip(&want).map(|(g, w)| (f64::from(*g) - w).abs()).fold(0.0, f64::max);
            assert!(scale > 0.0 && worst <= 1e-5 * scale, "worst {worst:e} against {scale:e}");
        }
    }
}
