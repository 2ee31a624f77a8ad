//! The volume raycaster on the GPU: `raycast.wgsl` beside this file (after
//! `camera_tools.wgsl`), one invocation per pixel. The transfer-function tables are the CPU
//! raycaster's, uploaded once; the volume is either uploaded once ([`GpuVolumeRaycaster::new`])
//! or a device buffer another stage rewrites, the GPU warp's output
//! ([`GpuVolumeRaycaster::on_device`]), read where it is. The macro cells of empty-space
//! skipping are computed on the device (`macro_cells`, the twin of `MacroCells::new`)
//! whenever the volume changed. A frame uploads only the camera and the tools. Rays are set
//! up in f32 (the CPU in f64), so pixels may differ by a level where a ray grazes a surface.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use wgpu::util::DeviceExt;

use crate::camera::{Camera, Projection};
use crate::transfer::Tables;
use crate::volume::{
    check_params, gradient_scale, IndexSpace, Mode, RaycastParams, Shading, ToolPicture, VolumeRaycaster, MAX_TOOLS,
};
use crate::{RenderError, Rendered};
use defvol_core::volume::Grid;
use defvol_gpu::gpu::{self, GpuContext, GpuError, Kernels};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GpuRenderError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
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

/// Side of the macro cells (raycast.rs's `CELL`).
const CELL: usize = 8;
const CELL_WORKGROUP: u32 = 64;

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

/// The camera's part of the uniform block.
pub(crate) fn camera_block(camera: &Camera, anchor: nalgebra::Vector3<f64>, step: f32) -> ([[f32; 4]; 4], [f32; 4]) {
    let (w, h) = (camera.width, camera.height);
    let r = camera.world_from_camera.rotation.to_rotation_matrix().into_inner();
    let t = camera.world_from_camera.translation.vector - anchor;
    let col = |c: usize| [r[(0, c)] as f32, r[(1, c)] as f32, r[(2, c)] as f32, 0.0];
    let proj = match camera.projection {
        Projection::Perspective { fov_y_deg } => {
            [1.0, (fov_y_deg.to_radians() / 2.0).tan() as f32, (w as f64 / h as f64) as f32, step]
        }
        Projection::Orthographic { height } => [0.0, height as f32, (w as f64 / h as f64) as f32, step],
    };
    ([col(0), col(1), col(2), [t.x as f32, t.y as f32, t.z as f32, 0.0]], proj)
}

pub struct GpuVolumeRaycaster {
    ctx: Arc<GpuContext>,
    base: Params,
    kernels: Kernels<2>,
    volume: wgpu::Buffer,
    lut: wgpu::Buffer,
    pre: wgpu::Buffer,
    cells: wgpu::Buffer,
    cell_groups: (u32, u32),
}

impl GpuVolumeRaycaster {
    /// Uploads the prepared raycaster's volume and tables.
    pub fn new(ctx: Arc<GpuContext>, prepared: &VolumeRaycaster) -> Result<Self, GpuRenderError> {
        let volume = prepared.volume;
        ctx.require_binding_size("the volume", volume.len() as u64 * 4)?;
        let buffer = ctx.storage_buffer("raycast volume", bytemuck::cast_slice(volume.data()));
        Self::build(ctx, buffer, &volume.grid(), &prepared.tables, &prepared.params, prepared.gradient_scale)
    }

    /// A raycaster over `volume`, a device buffer of samples on `grid` that another stage
    /// rewrites (the GPU warp's output): after each rewrite, [`Self::volume_changed`].
    /// `range` is the scalar range the tables and the shading scale are set for.
    pub fn on_device(
        ctx: Arc<GpuContext>,
        volume: wgpu::Buffer,
        grid: &Grid,
        range: (f32, f32),
        tables: &Tables,
        params: &RaycastParams,
    ) -> Result<Self, GpuRenderError> {
        check_params(tables, params)?;
        if volume.size() < grid.len() as u64 * 4 {
            return Err(RenderError::Parameter(format!(
                "a device volume of {} bytes for a {:?} grid",
                volume.size(),
                grid.dims
            ))
            .into());
        }
        let scale = gradient_scale(params, grid, range);
        Self::build(ctx, volume, grid, tables, params, scale)
    }

    fn build(
        ctx: Arc<GpuContext>,
        volume: wgpu::Buffer,
        grid: &Grid,
        tables: &Tables,
        params: &RaycastParams,
        gradient_scale: f32,
    ) -> Result<Self, GpuRenderError> {
        use defvol_gpu::gpu::Binding::{Read, ReadWrite, Uniform};
        let kernels = ctx.kernels(
            "raycast.wgsl",
            concat!(
                include_str!("../camera_tools.wgsl"),
                include_str!("../grid_gradient.wgsl"),
                include_str!("raycast.wgsl")
            ),
            &[Uniform, Read, Read, Read, ReadWrite, ReadWrite, ReadWrite],
            ["render", "macro_cells"],
        );
        let pre: &[[f32; 4]] = if tables.preintegrated.is_empty() { &[[0.0; 4]] } else { &tables.preintegrated };
        let skipping = params.empty_space_skipping && params.mode == Mode::Composite;
        let cell_dims = grid.dims.map(|n| n.div_ceil(CELL));
        let cell_count = (cell_dims[0] * cell_dims[1] * cell_dims[2]) as u32;
        let cell_groups = gpu::groups_2d(cell_count, CELL_WORKGROUP);
        let lut = ctx.storage_buffer(
            "raycast lut",
            bytemuck::cast_slice(&tables.lut.iter().chain(&tables.stepped).copied().collect::<Vec<_>>()),
        );
        let pre = ctx.storage_buffer("raycast preintegrated", bytemuck::cast_slice(pre));
        let cells = ctx.zeroed_buffer("raycast cells", u64::from(cell_count) * 4);
        let space = IndexSpace::of(grid);
        let m = space.index_from_world;
        let col = |c: usize| [m[(0, c)] as f32, m[(1, c)] as f32, m[(2, c)] as f32, 0.0];
        let o = space.origin;
        let d = grid.dims;
        let mode = match params.mode {
            Mode::Composite => 0,
            Mode::Mip => 1,
            Mode::Iso => 2,
        };
        let flags = u32::from(!tables.preintegrated.is_empty()) | (u32::from(skipping) << 1);
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
            misc: [params.ambient as f32, params.early_termination as f32, params.iso_value as f32, gradient_scale],
            background: params.background.map(|c| c as f32),
            shading: [shading, params.tools.len() as u32, cell_groups.0, 0],
            tools: tool_block(&params.tools),
        };
        let raycaster = Self { ctx, base, kernels, volume, lut, pre, cells, cell_groups };
        raycaster.volume_changed();
        Ok(raycaster)
    }

    /// The tools drawn into the next frames.
    pub fn set_tools(&mut self, tools: &[ToolPicture]) -> Result<(), GpuRenderError> {
        if tools.len() > MAX_TOOLS {
            return Err(
                RenderError::Parameter(format!("{} tools; a picture draws up to {MAX_TOOLS}", tools.len())).into()
            );
        }
        for tool in tools {
            tool.validate()?;
        }
        self.base.shading[1] = tools.len() as u32;
        self.base.tools = tool_block(tools);
        Ok(())
    }

    /// Recomputes the macro cells from the volume as it is now on the device (queued).
    pub fn volume_changed(&self) {
        if self.base.image[3] & 2 == 0 {
            return;
        }
        let uniform = self.uniform(&self.base);
        let (rgba, depth) = (
            self.ctx.zeroed_buffer("raycast rgba placeholder", 4),
            self.ctx.zeroed_buffer("raycast depth placeholder", 4),
        );
        let bind_group = self.bind_group(&uniform, &rgba, &depth);
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("macro cells") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("macro cells"),
                timestamp_writes: self.ctx.pass_timestamps(),
            });
            pass.set_pipeline(&self.kernels.pipelines[1]);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(self.cell_groups.0, self.cell_groups.1, 1);
        }
        self.ctx.submit(encoder.finish());
    }

    /// The visible flag of every macro cell (tests).
    pub fn read_cells(&self) -> Result<Vec<bool>, GpuRenderError> {
        let c = self.base.cells;
        let bytes = self.ctx.read_back(&self.cells, u64::from(c[0] * c[1] * c[2]) * 4)?;
        Ok(bytemuck::cast_slice::<u8, u32>(&bytes).iter().map(|v| *v != 0).collect())
    }

    fn uniform(&self, params: &Params) -> wgpu::Buffer {
        self.ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("raycast params"),
            contents: bytemuck::bytes_of(params),
            usage: wgpu::BufferUsages::UNIFORM,
        })
    }

    fn bind_group(&self, uniform: &wgpu::Buffer, rgba: &wgpu::Buffer, depth: &wgpu::Buffer) -> wgpu::BindGroup {
        self.ctx.bind_group(
            "raycast",
            &self.kernels.layout,
            &[uniform, &self.volume, &self.lut, &self.pre, &self.cells, rgba, depth],
        )
    }

    /// One frame seen by `camera`, read back.
    pub fn render(&self, camera: &Camera) -> Result<Rendered, GpuRenderError> {
        camera.validate()?;
        let (w, h) = (camera.width, camera.height);
        let (cam, proj) = camera_block(camera, nalgebra::Vector3::zeros(), self.base.proj[3]);
        let params =
            Params { cam, image: [w as u32, h as u32, self.base.image[2], self.base.image[3]], proj, ..self.base };
        let uniform = self.uniform(&params);
        let out_rgba = self.ctx.zeroed_buffer("raycast rgba", (w * h * 4) as u64);
        let out_depth = self.ctx.zeroed_buffer("raycast depth", (w * h * 4) as u64);
        let bind_group = self.bind_group(&uniform, &out_rgba, &out_depth);
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("raycast") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("raycast"),
                timestamp_writes: self.ctx.pass_timestamps(),
            });
            pass.set_pipeline(&self.kernels.pipelines[0]);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(w.div_ceil(8) as u32, h.div_ceil(8) as u32, 1);
        }
        self.ctx.submit(encoder.finish());
        let rgba = self.ctx.read_back(&out_rgba, (w * h * 4) as u64)?;
        let depth_bytes = self.ctx.read_back(&out_depth, (w * h * 4) as u64)?;
        let depth = bytemuck::cast_slice::<u8, f32>(&depth_bytes)
            .iter()
            .map(|&d| if d >= 1e30 { f32::INFINITY } else { d })
            .collect();
        Ok(Rendered { width: w, height: h, rgba, depth })
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::transfer::TransferFunction;
    use crate::volume::RaycastParams;
    use nalgebra::{Point3, Vector3};

    #[test]
    fn gpu_frames_match_the_cpu_raycaster() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let volume = defvol_core::volume::phantom::phantom([96, 60, 46], 8.0 / 3.0).unwrap();
        let (lo, hi) = volume.bounds();
        let centre = Point3::from((lo + hi) / 2.0);
        let camera = Camera::look_at(
            centre + Vector3::new(-150.0, -380.0, 120.0),
            centre,
            Vector3::z(),
            Projection::Perspective { fov_y_deg: 40.0 },
            64,
            48,
        )
        .unwrap();
        let soft = TransferFunction::preset("ct_soft_tissue").unwrap();
        let bone = TransferFunction::preset("ct_bone").unwrap();
        let cases = [
            (&soft, RaycastParams { shading: Shading::None, ..Default::default() }),
            (
                &soft,
                RaycastParams { shading: Shading::Gradient, preintegrated: false, step: 1.5, ..Default::default() },
            ),
            (
                &soft,
                RaycastParams {
                    shading: Shading::ForwardDifference,
                    empty_space_skipping: false,
                    ..Default::default()
                },
            ),
            (&bone, RaycastParams { mode: Mode::Iso, iso_value: 300.0, step: 0.5, ..Default::default() }),
            (&bone, RaycastParams { mode: Mode::Mip, ..Default::default() }),
            (
                &soft,
                RaycastParams {
                    tools: vec![ToolPicture {
                        tip: [centre.x, centre.y - 40.0, centre.z],
                        tail: [centre.x, centre.y - 160.0, centre.z + 60.0],
                        radius: 12.0,
                        color: [0.3, 0.9, 0.3],
                    }],
                    ..Default::default()
                },
            ),
        ];
        for (tf, params) in cases {
            let prepared = VolumeRaycaster::new(&volume, tf, &params).unwrap();
            let cpu = prepared.render(&camera).unwrap();
            let lit = cpu.rgba.chunks_exact(4).filter(|p| p[0] > 10).count();
            assert!(lit > cpu.rgba.len() / 4 / 50, "{:?}: the CPU image is nearly empty ({lit} pixels)", params.mode);
            let gpu = GpuVolumeRaycaster::new(ctx.clone(), &prepared).unwrap().render(&camera).unwrap();
            compare(&cpu, &gpu, &format!("{:?} {:?}", params.mode, params.shading), 0.5 * params.step as f32 + 0.01);
        }
    }

    pub(crate) fn compare(cpu: &Rendered, gpu: &Rendered, what: &str, depth_tolerance: f32) {
        let diffs: Vec<i32> =
            cpu.rgba.iter().zip(&gpu.rgba).map(|(a, b)| (i32::from(*a) - i32::from(*b)).abs()).collect();
        let mean = diffs.iter().sum::<i32>() as f64 / diffs.len() as f64;
        let off = diffs.iter().filter(|d| **d > 2).count() as f64 / diffs.len() as f64;
        assert!(
            mean < 0.3 && off < 0.01,
            "{what}: mean |diff| {mean:.3} levels, {:.2} % of channels off by > 2",
            off * 100.0
        );
        let depth_ok = cpu
            .depth
            .iter()
            .zip(&gpu.depth)
            .filter(|(a, b)| {
                a.is_infinite() == b.is_infinite() && (a.is_infinite() || (*a - *b).abs() < depth_tolerance)
            })
            .count();
        assert!(
            depth_ok as f64 >= 0.98 * cpu.depth.len() as f64,
            "{what}: depth agrees on {depth_ok} of {} pixels",
            cpu.depth.len()
        );
    }

    /// Macro cells computed on the device from a device volume: every cell the CPU finds
    /// visible is visible, nearly none more; and a raycaster reading a device buffer that
    /// another stage rewrote shows the new contents.
    #[test]
    fn device_macro_cells_cover_the_cpu_ones_and_follow_the_volume() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let volume = defvol_core::volume::phantom::phantom([80, 50, 40], 3.2).unwrap();
        let soft = TransferFunction::preset("ct_soft_tissue").unwrap();
        let params = RaycastParams { shading: Shading::None, ..Default::default() };
        let prepared = VolumeRaycaster::new(&volume, &soft, &params).unwrap();
        let cpu_cells = &prepared.cells.as_ref().unwrap().visible;
        let buffer = ctx.storage_buffer("a stage's volume", bytemuck::cast_slice(volume.data()));
        let gpu = GpuVolumeRaycaster::on_device(
            ctx.clone(),
            buffer.clone(),
            &volume.grid(),
            volume.range(),
            &prepared.tables,
            &params,
        )
        .unwrap();
        let gpu_cells = gpu.read_cells().unwrap();
        assert_eq!(gpu_cells.len(), cpu_cells.len());
        let missed = cpu_cells.iter().zip(&gpu_cells).filter(|(c, g)| **c && !**g).count();
        let extra = cpu_cells.iter().zip(&gpu_cells).filter(|(c, g)| !**c && **g).count();
        assert_eq!(missed, 0, "visible cells the device skips");
        assert!(extra <= cpu_cells.len() / 50, "{extra} cells of {} visible on the device only", cpu_cells.len());
        assert!(cpu_cells.iter().any(|v| !v) && cpu_cells.iter().any(|v| *v), "the phantom has empty and full cells");
        // The stage rewrites its buffer (a flipped copy of the volume): the next frame shows it.
        let (lo, hi) = volume.bounds();
        let centre = Point3::from((lo + hi) / 2.0);
        let camera = Camera::look_at(
            centre + Vector3::new(0.0, -400.0, 50.0),
            centre,
            Vector3::z(),
            Projection::Perspective { fov_y_deg: 40.0 },
            48,
            40,
        )
        .unwrap();
        let [nx, ny, nz] = volume.dims();
        let flipped: Vec<f32> = (0..nx * ny * nz)
            .map(|v| {
                let (i, j, k) = (v % nx, (v / nx) % ny, v / (nx * ny));
                volume.data()[i + nx * (j + ny * (nz - 1 - k))]
            })
            .collect();
        ctx.queue.write_buffer(&buffer, 0, bytemuck::cast_slice(&flipped));
        gpu.volume_changed();
        let flipped_volume = defvol_core::volume::Volume::from_grid(&volume.grid(), flipped, "flipped").unwrap();
        let cpu = VolumeRaycaster::with_tables(&flipped_volume, prepared.tables.clone(), &params)
            .unwrap()
            .render(&camera)
            .unwrap();
        compare(&cpu, &gpu.render(&camera).unwrap(), "a rewritten device volume", 0.51);
    }
}
