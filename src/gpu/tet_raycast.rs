//! The tetrahedral-mesh raycaster on the GPU: `shaders/tet_raycast.wgsl`. After each
//! deformation step only the node positions go up and the `geometry` kernel refreshes the
//! face planes and gradients on the GPU (seed 000, section 5.2); a frame bins the boundary
//! faces into tiles on the CPU ([`bin_boundary`], a few thousand faces) and runs `render`,
//! one invocation per pixel. Topology, links and tables are the CPU raycaster's, uploaded
//! once.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use nalgebra::Vector3;
use wgpu::util::DeviceExt;

use super::raycast::GpuRenderError;
use super::{GpuContext, Kernels};
use crate::render::camera::{Camera, Projection};
use crate::render::raycast::MAX_TOOLS;
use crate::render::tet_raycast::{bin_boundary, TetGeometry, TetRaycaster};
use crate::render::{RenderError, Rendered};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    cam: [[f32; 4]; 4],
    image: [u32; 4],
    proj: [f32; 4],
    table: [f32; 4],
    scales: [f32; 4],
    lut: [f32; 4],
    background: [f32; 4],
    counts: [u32; 4],
    tools: [[f32; 4]; 3 * MAX_TOOLS],
}

pub struct GpuTetRaycaster {
    ctx: Arc<GpuContext>,
    base: Params,
    layout: wgpu::BindGroupLayout,
    geometry_pipeline: wgpu::ComputePipeline,
    render_pipeline: wgpu::ComputePipeline,
    tets: Vec<[u32; 4]>,
    boundary: Vec<u32>,
    scalars: Vec<f32>,
    anchor: Vector3<f64>,
    positions: Vec<Vector3<f64>>,
    geometry: wgpu::Buffer,
    links: wgpu::Buffer,
    tables: wgpu::Buffer,
    nodes: wgpu::Buffer,
    tet_buffer: wgpu::Buffer,
    /// Stand in for the per-frame tiles and output while the geometry kernel runs.
    placeholders: [wgpu::Buffer; 2],
}

impl GpuTetRaycaster {
    /// Uploads the prepared mesh, links and tables, and computes the geometry of the
    /// prepared raycaster's current positions.
    pub fn new(ctx: Arc<GpuContext>, prepared: &TetRaycaster) -> Result<Self, GpuRenderError> {
        let tets = prepared.tets().to_vec();
        let limit = ctx.device.limits().max_storage_buffer_binding_size;
        let bytes = (tets.len() * std::mem::size_of::<TetGeometry>()) as u64;
        if bytes > limit {
            return Err(GpuRenderError::TooLarge { needed_mib: bytes.div_ceil(1 << 20), limit_mib: limit >> 20 });
        }
        use super::Binding::{Read, ReadWrite, Uniform};
        let Kernels { layout, pipelines: [geometry_pipeline, render_pipeline] } =
            ctx.kernels("tet_raycast.wgsl", concat!(include_str!("../../shaders/camera_tools.wgsl"), include_str!("../../shaders/tet_raycast.wgsl")), &[Uniform, ReadWrite, Read, Read, Read, ReadWrite, Read, Read], ["geometry", "render"]);
        let params = prepared.params();
        let table = &prepared.table;
        let lut_start = table.entries.len();
        let tables: Vec<[f32; 4]> = table.entries.iter().chain(&prepared.tables.lut).copied().collect();
        let tet_ids: Vec<[u32; 4]> = tets.clone();
        let geometry = ctx.storage_buffer("tet geometry", &vec![0u8; bytes.max(80) as usize]);
        let links = ctx.storage_buffer("tet links", bytemuck::cast_slice(&prepared.links));
        let tables_buffer = ctx.storage_buffer("tet tables", bytemuck::cast_slice(&tables));
        let nodes = ctx.storage_buffer("tet nodes", &vec![0u8; (prepared.scalars().len() * 16).max(16)]);
        let tet_buffer = ctx.storage_buffer("tet ids", bytemuck::cast_slice(&tet_ids));
        let placeholders = [ctx.storage_buffer("tet tiles placeholder", &[0u8; 16]), ctx.storage_buffer("tet out placeholder", &[0u8; 16])];
        let a = prepared.anchor;
        let mut tools = [[0.0f32; 4]; 3 * MAX_TOOLS];
        for (k, t) in params.tools.iter().enumerate() {
            let anchored = |v: [f64; 3], w: f64| [(v[0] - a.x) as f32, (v[1] - a.y) as f32, (v[2] - a.z) as f32, w as f32];
            tools[3 * k] = anchored(t.tip, t.radius);
            tools[3 * k + 1] = anchored(t.tail, 0.0);
            tools[3 * k + 2] = [t.color[0] as f32, t.color[1] as f32, t.color[2] as f32, 0.0];
        }
        let base = Params {
            cam: [[0.0; 4]; 4],
            image: [0, 0, 0, u32::from(params.preintegrated)],
            proj: [0.0, 0.0, 0.0, params.step as f32],
            table: [table.lo, table.hi, table.max_len, prepared.tolerance],
            scales: [table.level_scale, table.length_scale, prepared.visible.0, prepared.visible.1],
            lut: [prepared.tables.lo, prepared.tables.hi, params.early_termination as f32, params.ambient as f32],
            background: params.background.map(|c| c as f32),
            counts: [tets.len() as u32, params.tools.len() as u32, lut_start as u32, 0],
            tools,
        };
        let mut raycaster = Self {
            ctx,
            base,
            layout,
            geometry_pipeline,
            render_pipeline,
            tets,
            boundary: prepared.boundary.clone(),
            scalars: prepared.scalars().to_vec(),
            anchor: a,
            positions: Vec::new(),
            geometry,
            links,
            tables: tables_buffer,
            nodes,
            tet_buffer,
            placeholders,
        };
        raycaster.update(&prepared.positions)?;
        Ok(raycaster)
    }

    /// New node positions (a deformation step): uploaded, planes and gradients recomputed
    /// by the `geometry` kernel.
    pub fn update(&mut self, positions: &[Vector3<f64>]) -> Result<(), GpuRenderError> {
        if positions.len() != self.scalars.len() || positions.iter().any(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(RenderError::Parameter(format!("{} positions for {} nodes (all must be finite)", positions.len(), self.scalars.len())).into());
        }
        let nodes: Vec<[f32; 4]> = positions.iter().zip(&self.scalars).map(|(p, s)| {
            let q = p - self.anchor;
            [q.x as f32, q.y as f32, q.z as f32, *s]
        }).collect();
        self.ctx.queue.write_buffer(&self.nodes, 0, bytemuck::cast_slice(&nodes));
        self.positions = positions.to_vec();
        let params = self.uniform(&self.base);
        let bind_group = self.ctx.bind_group("tet geometry", &self.layout, &[&params, &self.geometry, &self.links, &self.placeholders[0], &self.tables, &self.placeholders[1], &self.nodes, &self.tet_buffer]);
        let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("tet geometry") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("tet geometry"), timestamp_writes: None });
            pass.set_pipeline(&self.geometry_pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(self.tets.len().div_ceil(64) as u32, 1, 1);
        }
        self.ctx.queue.submit([encoder.finish()]);
        Ok(())
    }

    fn uniform(&self, params: &Params) -> wgpu::Buffer {
        self.ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some("tet raycast params"), contents: bytemuck::bytes_of(params), usage: wgpu::BufferUsages::UNIFORM })
    }

    /// One frame seen by `camera`, read back.
    pub fn render(&self, camera: &Camera) -> Result<Rendered, GpuRenderError> {
        camera.validate()?;
        let (w, h) = (camera.width, camera.height);
        let bins = bin_boundary(&self.tets, &self.boundary, &self.positions, camera);
        let tile_count = bins.tiles[0] * bins.tiles[1];
        let tiles: Vec<u32> = bins.start.iter().chain(&bins.faces).copied().collect();
        let r = camera.world_from_camera.rotation.to_rotation_matrix().into_inner();
        let t = camera.world_from_camera.translation.vector - self.anchor;
        let col = |c: usize| [r[(0, c)] as f32, r[(1, c)] as f32, r[(2, c)] as f32, 0.0];
        let proj = match camera.projection {
            Projection::Perspective { fov_y_deg } => [1.0, (fov_y_deg.to_radians() / 2.0).tan() as f32, (w as f64 / h as f64) as f32, self.base.proj[3]],
            Projection::Orthographic { height } => [0.0, height as f32, (w as f64 / h as f64) as f32, self.base.proj[3]],
        };
        let params = Params {
            cam: [col(0), col(1), col(2), [t.x as f32, t.y as f32, t.z as f32, 0.0]],
            image: [w as u32, h as u32, bins.tiles[0] as u32, self.base.image[3]],
            proj,
            counts: [self.base.counts[0], self.base.counts[1], self.base.counts[2], tile_count as u32],
            ..self.base
        };
        let uniform = self.uniform(&params);
        let tile_buffer = self.ctx.storage_buffer("tet tiles", bytemuck::cast_slice(&tiles));
        let out = self.ctx.storage_buffer("tet raycast out", &vec![0u8; w * h * 8]);
        let bind_group = self.ctx.bind_group("tet raycast", &self.layout, &[&uniform, &self.geometry, &self.links, &tile_buffer, &self.tables, &out, &self.nodes, &self.tet_buffer]);
        let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("tet raycast") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("tet raycast"), timestamp_writes: None });
            pass.set_pipeline(&self.render_pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(w.div_ceil(8) as u32, h.div_ceil(8) as u32, 1);
        }
        self.ctx.queue.submit([encoder.finish()]);
        let bytes = self.ctx.read_back(&out, (w * h * 8) as u64)?;
        let (rgba, depth) = bytes.split_at(w * h * 4);
        let depth = bytemuck::pod_collect_to_vec::<u8, f32>(depth).into_iter().map(|d| if d >= 1e30 { f32::INFINITY } else { d }).collect();
        Ok(Rendered { width: w, height: h, rgba: rgba.to_vec(), depth })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::{self, CellSplit};
    use crate::render::raycast::ToolPicture;
    use crate::render::tet_raycast::TetRaycastParams;
    use crate::render::transfer::TransferFunction;
    use nalgebra::Point3;

    fn compare(cpu: &Rendered, gpu: &Rendered, what: &str) {
        let diffs: Vec<i32> = cpu.rgba.iter().zip(&gpu.rgba).map(|(a, b)| (i32::from(*a) - i32::from(*b)).abs()).collect();
        let mean = diffs.iter().sum::<i32>() as f64 / diffs.len() as f64;
        let off = diffs.iter().filter(|d| **d > 2).count() as f64 / diffs.len() as f64;
        assert!(mean < 0.3 && off < 0.01, "{what}: mean |diff| {mean:.3} levels, {:.2} % of channels off by > 2", off * 100.0);
        let depth_ok = cpu.depth.iter().zip(&gpu.depth).filter(|(a, b)| a.is_infinite() == b.is_infinite() && (a.is_infinite() || (*a - *b).abs() < 0.1)).count();
        assert!(depth_ok as f64 >= 0.98 * cpu.depth.len() as f64, "{what}: depth agrees on {depth_ok} of {} pixels", cpu.depth.len());
    }

    #[test]
    fn gpu_frames_match_the_cpu_tet_raycaster() {
        let Some(ctx) = crate::gpu::test_context() else { return };
        let volume = crate::volume::phantom::phantom([64, 40, 31], 4.0).unwrap();
        let (lo, hi) = volume.bounds();
        let mesh = generate::lattice_for_box(lo, hi, 6000, CellSplit::Five).unwrap();
        let outside = volume.range().0;
        let scalars: Vec<f32> = mesh.nodes().iter().map(|p| volume.sample_world(*p).unwrap_or(outside)).collect();
        let centre = Point3::from((lo + hi) / 2.0);
        let outside_view = Camera::look_at(centre + Vector3::new(-150.0, -380.0, 120.0), centre, Vector3::z(), Projection::Perspective { fov_y_deg: 40.0 }, 64, 48).unwrap();
        // The eye in the organ, looking along it.
        let inside_view = Camera::look_at(centre + Vector3::new(-60.0, 0.0, 0.0), centre, Vector3::z(), Projection::Perspective { fov_y_deg: 60.0 }, 48, 48).unwrap();
        let tf = TransferFunction::preset("ct_soft_tissue").unwrap();
        let probe = ToolPicture { tip: [centre.x, centre.y - 30.0, centre.z], tail: [centre.x, centre.y - 160.0, centre.z + 60.0], radius: 8.0, color: [0.3, 0.9, 0.3] };
        // A bend (nodes moved by a smooth field) is the deformation step.
        let bent: Vec<Vector3<f64>> = mesh.nodes().iter().map(|p| p + Vector3::new(0.0, 0.0, 12.0 * ((p.x - centre.x) / 60.0).sin())).collect();
        let cases = [
            ("pre-integrated", TetRaycastParams::default(), &outside_view),
            ("point-sampled", TetRaycastParams { preintegrated: false, step: 1.0, ..Default::default() }, &outside_view),
            ("tool", TetRaycastParams { tools: vec![probe], ..Default::default() }, &outside_view),
            ("inside", TetRaycastParams::default(), &inside_view),
        ];
        for (what, params, camera) in cases {
            let mut cpu = TetRaycaster::new(&mesh, &scalars, &tf, &params).unwrap();
            let mut gpu = GpuTetRaycaster::new(ctx.clone(), &cpu).unwrap();
            let cpu_image = cpu.render(camera).unwrap();
            let lit = cpu_image.rgba.chunks_exact(4).filter(|p| p[0] > 10).count();
            assert!(lit > cpu_image.rgba.len() / 4 / 20, "{what}: the CPU image is nearly empty ({lit} pixels)");
            compare(&cpu_image, &gpu.render(camera).unwrap(), what);
            cpu.update(&bent).unwrap();
            gpu.update(&bent).unwrap();
            compare(&cpu.render(camera).unwrap(), &gpu.render(camera).unwrap(), &format!("{what}, bent"));
        }
    }
}
