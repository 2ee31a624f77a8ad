//! The volume raycaster on the GPU: `shaders/raycast.wgsl`, one invocation per pixel. The
//! transfer-function tables and macro cells are the CPU raycaster's ([`VolumeRaycaster`]),
//! uploaded once; a frame uploads only the camera. Rays are set up in f32 (the CPU in f64),
//! so pixels may differ by a level where a ray grazes a surface.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use wgpu::util::DeviceExt;

use super::{GpuContext, GpuError, Kernels};
use crate::render::camera::{Camera, Projection};
use crate::render::raycast::{Mode, Shading, ToolPicture, VolumeRaycaster, MAX_TOOLS};
use crate::render::{RenderError, Rendered};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GpuRenderError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("the volume needs {needed_mib} MiB in one GPU buffer; the adapter allows {limit_mib} MiB")]
    TooLarge { needed_mib: u64, limit_mib: u64 },
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    cam: [[f32; 4]; 4],
    ifw: [[f32; 4]; 3],
    vol_origin: [f32; 4],
    dims: [u32; 4],
    cells: [u32; 4],
    image: [u32; 4],
    proj: [f32; 4],
    tf: [f32; 4],
    light: [f32; 4],
    misc: [f32; 4],
    background: [f32; 4],
    shading: [u32; 4],
    tools: [[f32; 4]; 12],
}

/// Tip and radius, tail, colour per tool, as the shader's uniform holds them.
fn tool_block(tools: &[ToolPicture]) -> [[f32; 4]; 3 * MAX_TOOLS] {
    let mut block = [[0.0f32; 4]; 3 * MAX_TOOLS];
    for (k, t) in tools.iter().take(MAX_TOOLS).enumerate() {
        let f = |v: [f64; 3], w: f64| [v[0] as f32, v[1] as f32, v[2] as f32, w as f32];
        block[3 * k] = f(t.tip, t.radius);
        block[3 * k + 1] = f(t.tail, 0.0);
        block[3 * k + 2] = f(t.color, 0.0);
    }
    block
}

pub struct GpuVolumeRaycaster {
    ctx: Arc<GpuContext>,
    base: Params,
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
    buffers: [wgpu::Buffer; 4],
}

impl GpuVolumeRaycaster {
    /// Uploads the prepared volume, tables and macro cells.
    pub fn new(ctx: Arc<GpuContext>, prepared: &VolumeRaycaster) -> Result<Self, GpuRenderError> {
        let volume = prepared.volume;
        let limit = ctx.device.limits().max_storage_buffer_binding_size;
        let bytes = volume.len() as u64 * 4;
        if bytes > limit {
            return Err(GpuRenderError::TooLarge { needed_mib: bytes.div_ceil(1 << 20), limit_mib: limit >> 20 });
        }
        use super::Binding::{Read, ReadWrite, Uniform};
        let Kernels { layout, pipelines: [pipeline] } = ctx.kernels("raycast.wgsl", concat!(include_str!("../../shaders/camera_tools.wgsl"), include_str!("../../shaders/raycast.wgsl")), &[Uniform, Read, Read, Read, Read, ReadWrite, ReadWrite], ["render"]);
        let tables = &prepared.tables;
        let pre: &[[f32; 4]] = if tables.preintegrated.is_empty() { &[[0.0; 4]] } else { &tables.preintegrated };
        let (cell_dims, visible): ([usize; 3], Vec<u32>) = match &prepared.cells {
            Some(c) => (c.dims, c.visible.iter().map(|v| u32::from(*v)).collect()),
            None => ([1, 1, 1], vec![1]),
        };
        let buffers = [
            ctx.storage_buffer("raycast volume", bytemuck::cast_slice(volume.data())),
            ctx.storage_buffer("raycast lut", bytemuck::cast_slice(&tables.lut.iter().chain(&tables.stepped).copied().collect::<Vec<_>>())),
            ctx.storage_buffer("raycast preintegrated", bytemuck::cast_slice(pre)),
            ctx.storage_buffer("raycast cells", bytemuck::cast_slice(&visible)),
        ];
        let m = prepared.space.index_from_world;
        let col = |c: usize| [m[(0, c)] as f32, m[(1, c)] as f32, m[(2, c)] as f32, 0.0];
        let o = prepared.space.origin;
        let params = &prepared.params;
        let d = volume.dims();
        let mode = match params.mode {
            Mode::Composite => 0,
            Mode::Mip => 1,
            Mode::Iso => 2,
        };
        let flags = u32::from(!tables.preintegrated.is_empty()) | (u32::from(prepared.cells.is_some()) << 1);
        let shading = match params.shading {
            Shading::None => 0,
            Shading::Gradient => 1,
            Shading::ForwardDifference => 2,
        };
        let light = params.light.map_or([0.0; 4], |l| [l[0] as f32, l[1] as f32, l[2] as f32, 1.0]);
        let base = Params {
            cam: [[0.0; 4]; 4],
            ifw: [col(0), col(1), col(2)],
            vol_origin: [o.x as f32, o.y as f32, o.z as f32, 0.0],
            dims: [d[0] as u32, d[1] as u32, d[2] as u32, 0],
            cells: [cell_dims[0] as u32, cell_dims[1] as u32, cell_dims[2] as u32, 0],
            image: [0, 0, mode, flags],
            proj: [0.0, 0.0, 0.0, params.step as f32],
            tf: [tables.lo, tables.hi, tables.pre_lo, tables.pre_hi],
            light,
            misc: [params.ambient as f32, params.early_termination as f32, params.iso_value as f32, prepared.gradient_scale],
            background: params.background.map(|c| c as f32),
            shading: [shading, params.tools.len() as u32, 0, 0],
            tools: tool_block(&params.tools),
        };
        Ok(Self { ctx, base, layout, pipeline, buffers })
    }

    /// One frame seen by `camera`, read back.
    pub fn render(&self, camera: &Camera) -> Result<Rendered, GpuRenderError> {
        camera.validate()?;
        let (w, h) = (camera.width, camera.height);
        let r = camera.world_from_camera.rotation.to_rotation_matrix().into_inner();
        let t = camera.world_from_camera.translation.vector;
        let col = |c: usize| [r[(0, c)] as f32, r[(1, c)] as f32, r[(2, c)] as f32, 0.0];
        let proj = match camera.projection {
            Projection::Perspective { fov_y_deg } => [1.0, (fov_y_deg.to_radians() / 2.0).tan() as f32, (w as f64 / h as f64) as f32, self.base.proj[3]],
            Projection::Orthographic { height } => [0.0, height as f32, (w as f64 / h as f64) as f32, self.base.proj[3]],
        };
        let params = Params { cam: [col(0), col(1), col(2), [t.x as f32, t.y as f32, t.z as f32, 0.0]], image: [w as u32, h as u32, self.base.image[2], self.base.image[3]], proj, ..self.base };
        let device = &self.ctx.device;
        let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some("raycast params"), contents: bytemuck::bytes_of(&params), usage: wgpu::BufferUsages::UNIFORM });
        let out_rgba = self.ctx.storage_buffer("raycast rgba", &vec![0u8; w * h * 4]);
        let out_depth = self.ctx.storage_buffer("raycast depth", &vec![0u8; w * h * 4]);
        let bind_group = self.ctx.bind_group("raycast", &self.layout, &[&uniform, &self.buffers[0], &self.buffers[1], &self.buffers[2], &self.buffers[3], &out_rgba, &out_depth]);
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("raycast") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("raycast"), timestamp_writes: None });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(w.div_ceil(8) as u32, h.div_ceil(8) as u32, 1);
        }
        self.ctx.queue.submit([encoder.finish()]);
        let rgba = self.ctx.read_back(&out_rgba, (w * h * 4) as u64)?;
        let depth_bytes = self.ctx.read_back(&out_depth, (w * h * 4) as u64)?;
        let depth = bytemuck::cast_slice::<u8, f32>(&depth_bytes).iter().map(|&d| if d >= 1e30 { f32::INFINITY } else { d }).collect();
        Ok(Rendered { width: w, height: h, rgba, depth })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::raycast::RaycastParams;
    use crate::render::transfer::TransferFunction;
    use nalgebra::{Point3, Vector3};

    #[test]
    fn gpu_frames_match_the_cpu_raycaster() {
        let Some(ctx) = crate::gpu::test_context() else { return };
        let volume = crate::volume::phantom::phantom([96, 60, 46], 8.0 / 3.0).unwrap();
        let (lo, hi) = volume.bounds();
        let centre = Point3::from((lo + hi) / 2.0);
        let camera = Camera::look_at(centre + Vector3::new(-150.0, -380.0, 120.0), centre, Vector3::z(), Projection::Perspective { fov_y_deg: 40.0 }, 64, 48).unwrap();
        let soft = TransferFunction::preset("ct_soft_tissue").unwrap();
        let bone = TransferFunction::preset("ct_bone").unwrap();
        let cases = [
            (&soft, RaycastParams { shading: Shading::None, ..Default::default() }),
            (&soft, RaycastParams { shading: Shading::Gradient, preintegrated: false, step: 1.5, ..Default::default() }),
            (&soft, RaycastParams { shading: Shading::ForwardDifference, empty_space_skipping: false, ..Default::default() }),
            (&bone, RaycastParams { mode: Mode::Iso, iso_value: 300.0, step: 0.5, ..Default::default() }),
            (&bone, RaycastParams { mode: Mode::Mip, ..Default::default() }),
            (&soft, RaycastParams { tools: vec![crate::render::raycast::ToolPicture { tip: [centre.x, centre.y - 40.0, centre.z], tail: [centre.x, centre.y - 160.0, centre.z + 60.0], radius: 12.0, color: [0.3, 0.9, 0.3] }], ..Default::default() }),
        ];
        for (tf, params) in cases {
            let prepared = VolumeRaycaster::new(&volume, tf, &params).unwrap();
            let cpu = prepared.render(&camera).unwrap();
            let lit = cpu.rgba.chunks_exact(4).filter(|p| p[0] > 10).count();
            assert!(lit > cpu.rgba.len() / 4 / 50, "{:?}: the CPU image is nearly empty ({lit} pixels)", params.mode);
            let gpu = GpuVolumeRaycaster::new(ctx.clone(), &prepared).unwrap().render(&camera).unwrap();
            let diffs: Vec<i32> = cpu.rgba.iter().zip(&gpu.rgba).map(|(a, b)| (i32::from(*a) - i32::from(*b)).abs()).collect();
            let mean = diffs.iter().sum::<i32>() as f64 / diffs.len() as f64;
            let off = diffs.iter().filter(|d| **d > 2).count() as f64 / diffs.len() as f64;
            assert!(mean < 0.3 && off < 0.01, "{:?} {:?}: mean |diff| {mean:.3} levels, {:.2} % of channels off by > 2", params.mode, params.shading, off * 100.0);
            let depth_ok = cpu.depth.iter().zip(&gpu.depth).filter(|(a, b)| a.is_infinite() == b.is_infinite() && (a.is_infinite() || (*a - *b).abs() < 0.5 * params.step as f32 + 0.01)).count();
            assert!(depth_ok as f64 >= 0.98 * cpu.depth.len() as f64, "{:?}: depth agrees on {depth_ok} of {} pixels", params.mode, cpu.depth.len());
        }
    }
}
