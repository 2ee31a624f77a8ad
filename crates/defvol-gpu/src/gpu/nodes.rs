//! Node positions kept on the device, in a consumer's own frame: `nodes = base + A · u`, with
//! `u` a displacement buffer another stage wrote (`vec4<f32>` per node: the solver's
//! displacements from rest) and `base`, `A` the consumer's rest positions and linear map
//! (its units, its anchor, its index space). The warp and the mesh raycaster read the
//! solver's result this way without a read-back; a CPU solver's result goes up through
//! [`DeviceNodes::place_host`] to the same buffer. `nodes.wgsl` is the kernel, [`place`] its
//! CPU twin.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use nalgebra::{Matrix3, Vector3};

use super::{Binding, GpuContext, GpuError, Kernels};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    a: [[f32; 4]; 3],
    count: [u32; 4],
}

const WORKGROUP: u32 = 64;

/// The kernel's arithmetic for one node, in f32.
pub fn place(base: [f32; 4], a: &Matrix3<f32>, u: [f32; 3]) -> [f32; 4] {
    let moved = a * Vector3::from(u);
    [base[0] + moved.x, base[1] + moved.y, base[2] + moved.z, base[3]]
}

pub struct DeviceNodes {
    ctx: Arc<GpuContext>,
    kernels: Kernels<1>,
    params: wgpu::Buffer,
    base: wgpu::Buffer,
    nodes: wgpu::Buffer,
    /// The base and map in f64, for positions placed from the host.
    host_base: Vec<[f64; 4]>,
    a: Matrix3<f64>,
}

impl DeviceNodes {
    /// Nodes at `base` (xyz: rest position in the consumer's frame; w: a value carried
    /// along), moved by `a` times each displacement.
    pub fn new(ctx: Arc<GpuContext>, base: Vec<[f64; 4]>, a: Matrix3<f64>) -> Result<Self, GpuError> {
        let bytes = base.len() as u64 * 16;
        ctx.require_binding_size("the mesh's nodes", bytes)?;
        let kernels = ctx.kernels(
            "nodes.wgsl",
            include_str!("nodes.wgsl"),
            &[Binding::Uniform, Binding::Read, Binding::Read, Binding::ReadWrite],
            ["place"],
        );
        let base32: Vec<[f32; 4]> = base.iter().map(|b| b.map(|v| v as f32)).collect();
        let count = base.len() as u32;
        let groups = count.div_ceil(WORKGROUP).max(1);
        let row = |r: usize| [a[(r, 0)] as f32, a[(r, 1)] as f32, a[(r, 2)] as f32, 0.0];
        let params = Params { a: [row(0), row(1), row(2)], count: [count, groups.min(super::MAX_GROUPS), 0, 0] };
        let params = wgpu::util::DeviceExt::create_buffer_init(
            &ctx.device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("nodes params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM,
            },
        );
        let base_buffer = ctx.storage_buffer("nodes base", bytemuck::cast_slice(&base32));
        let nodes = ctx.storage_buffer("nodes", bytemuck::cast_slice(&base32));
        Ok(Self { ctx, kernels, params, base: base_buffer, nodes, host_base: base, a })
    }

    /// The positions (`vec4<f32>` per node).
    pub fn buffer(&self) -> &wgpu::Buffer {
        &self.nodes
    }

    pub fn len(&self) -> usize {
        self.host_base.len()
    }

    pub fn is_empty(&self) -> bool {
        self.host_base.is_empty()
    }

    /// Places the nodes from a device buffer of displacements (queued; nothing is read back).
    pub fn place_from(&self, displacements: &wgpu::Buffer) -> Result<(), GpuError> {
        let needed = self.len() as u64 * 16;
        if displacements.size() < needed {
            return Err(GpuError::Readback(format!(
                "a displacement buffer of {} bytes for {} nodes",
                displacements.size(),
                self.len()
            )));
        }
        let bind_group =
            self.ctx.bind_group("nodes", &self.kernels.layout, &[&self.params, &self.base, displacements, &self.nodes]);
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("nodes") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("nodes"),
                timestamp_writes: self.ctx.pass_timestamps(),
            });
            pass.set_pipeline(&self.kernels.pipelines[0]);
            pass.set_bind_group(0, &bind_group, &[]);
            let (x, y) = super::groups_2d(self.len() as u32, WORKGROUP);
            pass.dispatch_workgroups(x, y, 1);
        }
        self.ctx.submit(encoder.finish());
        Ok(())
    }

    /// Places the nodes from displacements on the host (a CPU solver's), in f64, then up.
    pub fn place_host(&self, displacements: &[Vector3<f64>]) -> Result<(), GpuError> {
        if displacements.len() != self.len() {
            return Err(GpuError::Readback(format!("{} displacements for {} nodes", displacements.len(), self.len())));
        }
        let nodes: Vec<[f32; 4]> = self
            .host_base
            .iter()
            .zip(displacements)
            .map(|(b, u)| {
                let p = Vector3::new(b[0], b[1], b[2]) + self.a * u;
                [p.x as f32, p.y as f32, p.z as f32, b[3] as f32]
            })
            .collect();
        self.ctx.queue.write_buffer(&self.nodes, 0, bytemuck::cast_slice(&nodes));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placed_nodes_match_the_cpu_twin() {
        let Some(ctx) = super::super::test_context() else { return };
        let count = 70_001;
        let base: Vec<[f64; 4]> =
            (0..count).map(|i| [i as f64 * 0.25, -(i as f64).sqrt(), 3.0 + (i % 7) as f64, (i % 11) as f64]).collect();
        let a = Matrix3::new(1000.0, 0.0, 0.0, 0.0, 0.0, 1000.0, 0.0, -1000.0, 0.0) * 0.5;
        let u: Vec<[f32; 4]> =
            (0..count).map(|i| [1e-3 * (i % 13) as f32, -2e-4 * (i % 5) as f32, 5e-4, 0.0]).collect();
        let nodes = DeviceNodes::new(ctx.clone(), base.clone(), a).unwrap();
        let displacements = ctx.storage_buffer("test displacements", bytemuck::cast_slice(&u));
        nodes.place_from(&displacements).unwrap();
        let bytes = ctx.read_back(nodes.buffer(), count as u64 * 16).unwrap();
        let got: &[[f32; 4]] = bytemuck::cast_slice(&bytes);
        let a32 = a.cast::<f32>();
        for i in (0..count).step_by(97).chain([count - 1]) {
            let want = place(base[i].map(|v| v as f32), &a32, [u[i][0], u[i][1], u[i][2]]);
            for c in 0..4 {
                assert!(
                    (got[i][c] - want[c]).abs() <= 1e-6 * want[c].abs().max(1.0),
                    "node {i}: {:?} on the GPU, {want:?} on the CPU",
                    got[i]
                );
            }
        }
        // From the host, in f64: the same positions within f32 rounding.
        let host: Vec<Vector3<f64>> =
            u.iter().map(|u| Vector3::new(f64::from(u[0]), f64::from(u[1]), f64::from(u[2]))).collect();
        nodes.place_host(&host).unwrap();
        let bytes = ctx.read_back(nodes.buffer(), count as u64 * 16).unwrap();
        let again: &[[f32; 4]] = bytemuck::cast_slice(&bytes);
        for i in (0..count).step_by(97) {
            for c in 0..4 {
                assert!(
                    (again[i][c] - got[i][c]).abs() <= 1e-5 * got[i][c].abs().max(1.0),
                    "node {i}: {:?} from the host, {:?} on the device",
                    again[i],
                    got[i]
                );
            }
        }
    }
}
