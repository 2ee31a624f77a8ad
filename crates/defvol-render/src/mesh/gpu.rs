//! The tetrahedral-mesh raycaster on the GPU: `tet_raycast.wgsl` (after
//! `camera_tools.wgsl`) and `tet_bins.wgsl` beside this file. The node positions live on
//! the device ([`DeviceNodes`]): placed from the host ([`GpuTetRaycaster::update`]) or from
//! another stage's device buffer (the solver's displacements, through
//! [`GpuTetRaycaster::nodes`]), after which the `geometry` kernel refreshes the face planes
//! and gradients (seed 000, section 5.2). A frame bins the boundary faces into tiles on the
//! device (`tet_bins.wgsl`, the twin of `bin_boundary`) and runs `render`, one invocation
//! per pixel: nothing of the mesh goes through the host. Topology, links and tables are the
//! CPU raycaster's, uploaded once.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use nalgebra::{Matrix3, Vector3};
use wgpu::util::DeviceExt;

use super::cpu::{TetRaycaster, TILE};
use super::geometry::TetGeometry;
use super::look::{SourceLook, TetMap, EDGE_TOLERANCE};
use crate::camera::Camera;
use crate::volume::gpu::{camera_block, GpuRenderError};
use crate::volume::{Shading, ToolPicture, MAX_TOOLS};
use crate::{RenderError, Rendered};
use defvol_core::volume::Sampling;
use defvol_gpu::gpu::{self, DeviceNodes, GpuContext, Kernels};

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
    src_dims: [u32; 4],
    src_at: [u32; 4],
    src_tf: [f32; 4],
    src_light: [f32; 4],
    tools: [[f32; 4]; 3 * MAX_TOOLS],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct BinParams {
    cam: [[f32; 4]; 4],
    proj: [f32; 4],
    image: [u32; 4],
    counts: [u32; 4],
}

const WORKGROUP: u32 = 64;

/// Tile-list entries to start with per boundary face: a face spans about one tile at the
/// images these meshes are seen at; the list grows when a frame needs more.
const ENTRIES_PER_FACE: usize = 4;

pub struct GpuTetRaycaster {
    ctx: Arc<GpuContext>,
    base: Params,
    kernels: Kernels<2>,
    bin_kernels: Kernels<3>,
    tet_count: u32,
    boundary_count: u32,
    anchor: Vector3<f64>,
    /// Positions at creation (the rest the displacements are taken from), and the scale of
    /// the displacements to the mesh's units.
    rest: Vec<Vector3<f64>>,
    to_file: f64,
    nodes: Arc<DeviceNodes>,
    geometry: wgpu::Buffer,
    links: wgpu::Buffer,
    tables: wgpu::Buffer,
    tets: wgpu::Buffer,
    boundary: wgpu::Buffer,
    /// Showing the source: the tets' maps, the nodes' rest index, the source's samples and
    /// the tets' visibility (placeholders for node scalars).
    source: [wgpu::Buffer; 4],
    /// Tile starts then faces, and how many faces it can hold.
    tiles: wgpu::Buffer,
    capacity: usize,
}

impl GpuTetRaycaster {
    /// Uploads the prepared mesh, links and tables, and the positions it was prepared at
    /// (its rest: displacements are taken from there). Displacements placed from a device
    /// buffer are in the units of whoever moves the mesh; `to_file` scales them to the
    /// mesh's (1 when they are the mesh's own).
    pub fn new(ctx: Arc<GpuContext>, prepared: &TetRaycaster, to_file: f64) -> Result<Self, GpuRenderError> {
        let tets = prepared.tets();
        ctx.require_binding_size("the mesh's tet geometry", (tets.len() * std::mem::size_of::<TetGeometry>()) as u64)?;
        if !(to_file.is_finite() && to_file > 0.0) {
            return Err(RenderError::Parameter(format!("unit scale {to_file} must be finite and > 0")).into());
        }
        ctx.require_storage_buffers("the mesh raycaster", 11)?;
        use defvol_gpu::gpu::Binding::{Read, ReadWrite, Uniform};
        let kernels = ctx.kernels(
            "tet_raycast.wgsl",
            concat!(
                include_str!("../camera_tools.wgsl"),
                include_str!("../grid_gradient.wgsl"),
                include_str!("tet_raycast.wgsl")
            ),
            &[Uniform, ReadWrite, Read, Read, Read, ReadWrite, Read, Read, ReadWrite, Read, Read, Read],
            ["geometry", "render"],
        );
        let bin_kernels = ctx.kernels(
            "tet_bins.wgsl",
            include_str!("tet_bins.wgsl"),
            &[Uniform, Read, Read, Read, ReadWrite, ReadWrite],
            ["count_tiles", "scan_tiles", "fill_tiles"],
        );
        let params = prepared.params();
        let table = &prepared.table;
        let (tables, lut_start, lut_range, source, source_block) = match &prepared.source {
            None => {
                let tables: Vec<[f32; 4]> = table.entries.iter().chain(&prepared.tables.lut).copied().collect();
                let placeholders = ["tet maps", "tet rest index", "tet source", "tet visibility"].map(|label| {
                    ctx.zeroed_buffer(&format!("{label} placeholder"), std::mem::size_of::<TetMap>() as u64)
                });
                let lut_range = (prepared.tables.lo, prepared.tables.hi);
                (tables, table.entries.len(), lut_range, placeholders, SourceBlock::default())
            }
            Some(look) => source_buffers(&ctx, look, tets.len())?,
        };
        let anchor = prepared.anchor;
        let base_nodes: Vec<[f64; 4]> = prepared
            .positions
            .iter()
            .zip(prepared.scalars())
            .map(|(p, s)| [p.x - anchor.x, p.y - anchor.y, p.z - anchor.z, f64::from(*s)])
            .collect();
        let nodes = Arc::new(DeviceNodes::new(ctx.clone(), base_nodes, Matrix3::identity() * to_file)?);
        let geometry = ctx.zeroed_buffer("tet geometry", (tets.len() * std::mem::size_of::<TetGeometry>()) as u64);
        let links = ctx.storage_buffer("tet links", bytemuck::cast_slice(&prepared.links));
        let tables_buffer = ctx.storage_buffer("tet tables", bytemuck::cast_slice(&tables));
        let tet_buffer = ctx.storage_buffer("tet ids", bytemuck::cast_slice(tets));
        let boundary = ctx.storage_buffer("tet boundary", bytemuck::cast_slice(&prepared.boundary));
        let mut tools = [[0.0f32; 4]; 3 * MAX_TOOLS];
        fill_tools(&mut tools, &params.tools, anchor);
        let base = Params {
            cam: [[0.0; 4]; 4],
            image: [0, 0, 0, u32::from(params.preintegrated)],
            proj: [0.0, 0.0, 0.0, params.step as f32],
            table: [table.lo, table.hi, table.max_len, prepared.tolerance],
            scales: [table.level_scale, table.length_scale, prepared.visible.0, prepared.visible.1],
            lut: [lut_range.0, lut_range.1, params.early_termination as f32, params.ambient as f32],
            background: params.background.map(|c| c as f32),
            counts: [tets.len() as u32, params.tools.len() as u32, lut_start as u32, 0],
            src_dims: source_block.dims,
            src_at: source_block.at,
            src_tf: source_block.tf,
            src_light: source_block.light,
            tools,
        };
        let capacity = (prepared.boundary.len() * ENTRIES_PER_FACE).max(1024);
        let raycaster = Self {
            tiles: ctx.zeroed_buffer("tet tiles", 4),
            ctx,
            base,
            kernels,
            bin_kernels,
            tet_count: tets.len() as u32,
            boundary_count: prepared.boundary.len() as u32,
            anchor,
            rest: prepared.positions.clone(),
            to_file,
            nodes,
            geometry,
            links,
            tables: tables_buffer,
            tets: tet_buffer,
            boundary,
            source,
            capacity,
        };
        raycaster.refresh();
        Ok(raycaster)
    }

    /// The device positions: another stage places them
    /// ([`DeviceNodes::place_from`]), then [`Self::refresh`].
    pub fn nodes(&self) -> &Arc<DeviceNodes> {
        &self.nodes
    }

    /// New node positions from the host (a deformation step, the mesh's units): placed,
    /// planes and gradients recomputed by the `geometry` kernel.
    pub fn update(&mut self, positions: &[Vector3<f64>]) -> Result<(), GpuRenderError> {
        if positions.len() != self.rest.len() || positions.iter().any(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(RenderError::Parameter(format!(
                "{} positions for {} nodes (all must be finite)",
                positions.len(),
                self.rest.len()
            ))
            .into());
        }
        let displacements: Vec<Vector3<f64>> =
            positions.iter().zip(&self.rest).map(|(p, r)| (p - r) / self.to_file).collect();
        self.nodes.place_host(&displacements)?;
        self.refresh();
        Ok(())
    }

    /// Recomputes the planes and gradients from the positions on the device (queued).
    pub fn refresh(&self) {
        let params = self.uniform(&self.base);
        let placeholders =
            [self.ctx.zeroed_buffer("tet tiles placeholder", 16), self.ctx.zeroed_buffer("tet out placeholder", 16)];
        let bind_group = self.ctx.bind_group(
            "tet geometry",
            &self.kernels.layout,
            &[
                &params,
                &self.geometry,
                &self.links,
                &placeholders[0],
                &self.tables,
                &placeholders[1],
                self.nodes.buffer(),
                &self.tets,
                &self.source[0],
                &self.source[1],
                &self.source[2],
                &self.source[3],
            ],
        );
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("tet geometry") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tet geometry"),
                timestamp_writes: self.ctx.pass_timestamps(),
            });
            pass.set_pipeline(&self.kernels.pipelines[0]);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(self.tet_count.div_ceil(WORKGROUP).max(1), 1, 1);
        }
        self.ctx.submit(encoder.finish());
    }

    /// The tools drawn into the next frames (up to [`MAX_TOOLS`]).
    pub fn set_tools(&mut self, tools: &[ToolPicture]) -> Result<(), GpuRenderError> {
        if tools.len() > MAX_TOOLS {
            return Err(
                RenderError::Parameter(format!("{} tools; a picture draws up to {MAX_TOOLS}", tools.len())).into()
            );
        }
        for tool in tools {
            tool.validate()?;
        }
        fill_tools(&mut self.base.tools, tools, self.anchor);
        self.base.counts[1] = tools.len() as u32;
        Ok(())
    }

    fn uniform<T: Pod>(&self, params: &T) -> wgpu::Buffer {
        self.ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("tet raycast params"),
            contents: bytemuck::bytes_of(params),
            usage: wgpu::BufferUsages::UNIFORM,
        })
    }

    /// One frame seen by `camera`, read back. The tile lists grow (and the frame is cast
    /// again) when this view needs more entries than they hold.
    pub fn render(&mut self, camera: &Camera) -> Result<Rendered, GpuRenderError> {
        camera.validate()?;
        let (w, h) = (camera.width, camera.height);
        let tiles = [w.div_ceil(TILE), h.div_ceil(TILE)];
        let tile_count = tiles[0] * tiles[1];
        let (cam, proj) = camera_block(camera, self.anchor, self.base.proj[3]);
        loop {
            let needed = ((tile_count + 1 + self.capacity) * 4) as u64;
            if self.tiles.size() < needed {
                self.ctx.require_binding_size("the mesh raycaster's tile lists", needed)?;
                self.tiles = self.ctx.zeroed_buffer("tet tiles", needed);
            }
            let face_groups = gpu::groups_2d(self.boundary_count, WORKGROUP);
            let bin_params = BinParams {
                cam,
                proj,
                image: [w as u32, h as u32, tiles[0] as u32, tiles[1] as u32],
                counts: [self.boundary_count, tile_count as u32, self.capacity as u32, face_groups.0],
            };
            let bin_uniform = self.uniform(&bin_params);
            let cursor = self.ctx.zeroed_buffer("tet tile cursors", (tile_count * 4) as u64);
            let bin_group = self.ctx.bind_group(
                "tet bins",
                &self.bin_kernels.layout,
                &[&bin_uniform, self.nodes.buffer(), &self.tets, &self.boundary, &cursor, &self.tiles],
            );
            let params = Params {
                cam,
                image: [w as u32, h as u32, tiles[0] as u32, self.base.image[3]],
                proj,
                counts: [self.base.counts[0], self.base.counts[1], self.base.counts[2], tile_count as u32],
                ..self.base
            };
            let uniform = self.uniform(&params);
            // The picture, then the tile lists' total (to know they held every entry).
            let image_bytes = (w * h * 8) as u64;
            let out = self.ctx.zeroed_buffer("tet raycast out", image_bytes + 4);
            let bind_group = self.ctx.bind_group(
                "tet raycast",
                &self.kernels.layout,
                &[
                    &uniform,
                    &self.geometry,
                    &self.links,
                    &self.tiles,
                    &self.tables,
                    &out,
                    self.nodes.buffer(),
                    &self.tets,
                    &self.source[0],
                    &self.source[1],
                    &self.source[2],
                    &self.source[3],
                ],
            );
            let mut encoder =
                self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("tet raycast") });
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("tet raycast"),
                    timestamp_writes: self.ctx.pass_timestamps(),
                });
                pass.set_bind_group(0, &bin_group, &[]);
                pass.set_pipeline(&self.bin_kernels.pipelines[0]);
                pass.dispatch_workgroups(face_groups.0, face_groups.1, 1);
                pass.set_pipeline(&self.bin_kernels.pipelines[1]);
                pass.dispatch_workgroups(1, 1, 1);
                pass.set_pipeline(&self.bin_kernels.pipelines[2]);
                pass.dispatch_workgroups(face_groups.0, face_groups.1, 1);
                pass.set_bind_group(0, &bind_group, &[]);
                pass.set_pipeline(&self.kernels.pipelines[1]);
                pass.dispatch_workgroups(w.div_ceil(8) as u32, h.div_ceil(8) as u32, 1);
            }
            self.ctx.copy_buffer(&mut encoder, &self.tiles, (tile_count * 4) as u64, &out, image_bytes, 4);
            self.ctx.submit(encoder.finish());
            let bytes = self.ctx.read_back(&out, image_bytes + 4)?;
            let (image, total) = bytes.split_at(image_bytes as usize);
            let total = u32::from_le_bytes([total[0], total[1], total[2], total[3]]) as usize;
            if total > self.capacity {
                self.capacity = total + total / 4;
                continue;
            }
            let (rgba, depth) = image.split_at(w * h * 4);
            let depth = bytemuck::pod_collect_to_vec::<u8, f32>(depth)
                .into_iter()
                .map(|d| if d >= 1e30 { f32::INFINITY } else { d })
                .collect();
            return Ok(Rendered { width: w, height: h, rgba: rgba.to_vec(), depth });
        }
    }
}

/// The source's part of the uniform block.
#[derive(Default)]
struct SourceBlock {
    dims: [u32; 4],
    at: [u32; 4],
    tf: [f32; 4],
    light: [f32; 4],
}

/// What showing the source needs on the device: tables (the full-step lut and the
/// pre-integrated table after the 1D lut), where the lut starts and its range, the
/// buffers and the uniform block's part. Tricubic sampling and displacement volumes run on
/// the CPU path only.
#[allow(clippy::type_complexity)]
fn source_buffers(
    ctx: &Arc<GpuContext>,
    look: &SourceLook,
    tets: usize,
) -> Result<(Vec<[f32; 4]>, usize, (f32, f32), [wgpu::Buffer; 4], SourceBlock), GpuRenderError> {
    if look.sampling != Sampling::Trilinear || !look.displacements.is_empty() {
        return Err(RenderError::Parameter(
            "the GPU shows the source with trilinear sampling and no displacement volumes (tricubic sampling and displacement volumes run on the CPU)".into(),
        )
        .into());
    }
    let volume = &look.volume;
    ctx.require_binding_size("the source volume", (volume.data().len() * 4) as u64)?;
    ctx.require_binding_size("the tets' maps", (tets * std::mem::size_of::<TetMap>()) as u64)?;
    let t = &look.tables;
    let tables: Vec<[f32; 4]> = t.lut.iter().chain(&t.stepped).chain(&t.preintegrated).copied().collect();
    ctx.require_binding_size("the source's tables", (tables.len() * 16) as u64)?;
    let buffers = [
        ctx.zeroed_buffer("tet maps", (tets.max(1) * std::mem::size_of::<TetMap>()) as u64),
        ctx.storage_buffer("tet rest index", bytemuck::cast_slice(&look.rest_index)),
        ctx.storage_buffer("tet source", bytemuck::cast_slice(volume.data())),
        ctx.storage_buffer("tet visibility", bytemuck::cast_slice(&look.visible)),
    ];
    let params = &look.params;
    let shading = match params.shading {
        Shading::None => 0,
        Shading::Gradient => 4,
        Shading::ForwardDifference => 8,
    };
    let dims = volume.dims().map(|n| n as u32);
    let light = params.light.map_or([0.0; 4], |l| {
        let l = Vector3::from(l).normalize();
        [l.x as f32, l.y as f32, l.z as f32, 1.0]
    });
    let block = SourceBlock {
        dims: [dims[0], dims[1], dims[2], 1 | if params.preintegrated { 2 } else { 0 } | shading],
        at: [t.lut.len() as u32, (t.lut.len() + t.stepped.len()) as u32, 0, 0],
        tf: [t.pre_lo, t.pre_hi, look.gradient_scale, EDGE_TOLERANCE],
        light,
    };
    Ok((tables, 0, (t.lo, t.hi), buffers, block))
}

/// The tools in the uniform block: anchored tip and radius, anchored tail, colour.
fn fill_tools(block: &mut [[f32; 4]; 3 * MAX_TOOLS], tools: &[ToolPicture], anchor: Vector3<f64>) {
    *block = [[0.0; 4]; 3 * MAX_TOOLS];
    for (k, t) in tools.iter().take(MAX_TOOLS).enumerate() {
        let anchored = |v: [f64; 3], w: f64| {
            [(v[0] - anchor.x) as f32, (v[1] - anchor.y) as f32, (v[2] - anchor.z) as f32, w as f32]
        };
        block[3 * k] = anchored(t.tip, t.radius);
        block[3 * k + 1] = anchored(t.tail, 0.0);
        block[3 * k + 2] = [t.color[0] as f32, t.color[1] as f32, t.color[2] as f32, 0.0];
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Projection;
    use crate::mesh::TetRaycastParams;
    use crate::transfer::TransferFunction;
    use crate::volume::gpu::tests::compare;
    use defvol_core::mesh::generate::{self, CellSplit};
    use defvol_core::mesh::TetMesh;
    use defvol_core::volume::Volume;
    use nalgebra::Point3;

    /// The coarse phantom, a lattice of about `tets` over it, its centre, and two views:
    /// from outside, and with the eye in the organ looking along it.
    fn phantom_views(tets: usize) -> (Volume, TetMesh, Point3<f64>, Camera, Camera) {
        let volume = defvol_core::volume::phantom::phantom([64, 40, 31], 4.0).unwrap();
        let (lo, hi) = volume.bounds();
        let mesh = generate::lattice_for_box(lo, hi, tets, CellSplit::Five).unwrap();
        let centre = Point3::from((lo + hi) / 2.0);
        let outside_view = Camera::look_at(
            centre + Vector3::new(-150.0, -380.0, 120.0),
            centre,
            Vector3::z(),
            Projection::Perspective { fov_y_deg: 40.0 },
            64,
            48,
        )
        .unwrap();
        let inside_view = Camera::look_at(
            centre + Vector3::new(-60.0, 0.0, 0.0),
            centre,
            Vector3::z(),
            Projection::Perspective { fov_y_deg: 60.0 },
            48,
            48,
        )
        .unwrap();
        (volume, mesh, centre, outside_view, inside_view)
    }

    /// A tool reaching into the organ from the outside view's side.
    fn probe(centre: &Point3<f64>) -> ToolPicture {
        ToolPicture {
            tip: [centre.x, centre.y - 30.0, centre.z],
            tail: [centre.x, centre.y - 160.0, centre.z + 60.0],
            radius: 8.0,
            color: [0.3, 0.9, 0.3],
        }
    }

    /// A bend (nodes moved by a smooth field): the deformation step.
    fn bend(mesh: &TetMesh, centre: &Point3<f64>) -> Vec<Vector3<f64>> {
        mesh.nodes().iter().map(|p| p + Vector3::new(0.0, 0.0, 12.0 * ((p.x - centre.x) / 60.0).sin())).collect()
    }

    #[test]
    fn gpu_frames_match_the_cpu_tet_raycaster() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let (volume, mesh, centre, outside_view, inside_view) = phantom_views(6000);
        let outside = volume.range().0;
        let scalars: Vec<f32> = mesh.nodes().iter().map(|p| volume.sample_world(*p).unwrap_or(outside)).collect();
        let ortho_view = Camera::look_at(
            centre + Vector3::new(0.0, -300.0, 0.0),
            centre,
            Vector3::z(),
            Projection::Orthographic { height: 180.0 },
            56,
            40,
        )
        .unwrap();
        let tf = TransferFunction::preset("ct_soft_tissue").unwrap();
        let probe = probe(&centre);
        let bent = bend(&mesh, &centre);
        let cases = [
            ("pre-integrated", TetRaycastParams::default(), &outside_view),
            (
                "point-sampled",
                TetRaycastParams { preintegrated: false, step: 1.0, ..Default::default() },
                &outside_view,
            ),
            ("tool", TetRaycastParams { tools: vec![probe], ..Default::default() }, &outside_view),
            ("inside", TetRaycastParams::default(), &inside_view),
            ("orthographic", TetRaycastParams::default(), &ortho_view),
        ];
        for (what, params, camera) in cases {
            let mut cpu = TetRaycaster::new(&mesh, &scalars, &tf, &params).unwrap();
            let mut gpu = GpuTetRaycaster::new(ctx.clone(), &cpu, 1.0).unwrap();
            let cpu_image = cpu.render(camera).unwrap();
            let lit = cpu_image.rgba.chunks_exact(4).filter(|p| p[0] > 10).count();
            assert!(lit > cpu_image.rgba.len() / 4 / 20, "{what}: the CPU image is nearly empty ({lit} pixels)");
            compare(&cpu_image, &gpu.render(camera).unwrap(), what, 0.1);
            cpu.update(&bent).unwrap();
            gpu.update(&bent).unwrap();
            compare(&cpu.render(camera).unwrap(), &gpu.render(camera).unwrap(), &format!("{what}, bent"), 0.1);
        }
    }

    #[test]
    fn gpu_frames_of_the_source_through_the_mesh_match_the_cpu() {
        use crate::mesh::source::SourceSampling;
        use crate::volume::{RaycastParams, Shading};
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let (volume, mesh, centre, outside_view, inside_view) = phantom_views(3000);
        let volume = Arc::new(volume);
        let tf = TransferFunction::preset("ct_soft_tissue").unwrap();
        let probe = probe(&centre);
        let bent = bend(&mesh, &centre);
        let step = RaycastParams { step: 2.0, ..Default::default() };
        let cases = [
            ("pre-integrated, gradient", step.clone(), &outside_view),
            (
                "point-sampled, forward difference",
                RaycastParams { preintegrated: false, shading: Shading::ForwardDifference, ..step.clone() },
                &outside_view,
            ),
            ("tool", RaycastParams { tools: vec![probe], ..step.clone() }, &outside_view),
            ("inside", step.clone(), &inside_view),
        ];
        for (what, params, camera) in cases {
            let mut cpu =
                TetRaycaster::with_source(&mesh, volume.clone(), &tf, &params, &SourceSampling::default()).unwrap();
            let mut gpu = GpuTetRaycaster::new(ctx.clone(), &cpu, 1.0).unwrap();
            let cpu_image = cpu.render(camera).unwrap();
            let lit = cpu_image.rgba.chunks_exact(4).filter(|p| p[0] > 10).count();
            assert!(lit > cpu_image.rgba.len() / 4 / 20, "{what}: the CPU image is nearly empty ({lit} pixels)");
            compare(&cpu_image, &gpu.render(camera).unwrap(), what, 0.5);
            cpu.update(&bent).unwrap();
            gpu.update(&bent).unwrap();
            compare(&cpu.render(camera).unwrap(), &gpu.render(camera).unwrap(), &format!("{what}, bent"), 0.5);
        }
        // What the GPU path does not do is refused by name (the CPU does it).
        let tricubic = SourceSampling { sampling: defvol_core::volume::Sampling::Tricubic, ..Default::default() };
        let cpu = TetRaycaster::with_source(&mesh, volume.clone(), &tf, &step, &tricubic).unwrap();
        let e = GpuTetRaycaster::new(ctx.clone(), &cpu, 1.0).err().unwrap().to_string();
        assert!(e.contains("tricubic"), "{e}");
    }

    /// The bend placed from a device buffer of displacements in metres (the solver's units
    /// over a millimetre mesh) renders as the bend placed from the host; tile lists that
    /// start too small grow and give the same frame.
    #[test]
    fn displacements_on_the_device_render_as_host_positions_do() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let volume = defvol_core::volume::phantom::phantom([64, 40, 31], 4.0).unwrap();
        let (lo, hi) = volume.bounds();
        let mesh = generate::lattice_for_box(lo, hi, 3000, CellSplit::Five).unwrap();
        let outside = volume.range().0;
        let scalars: Vec<f32> = mesh.nodes().iter().map(|p| volume.sample_world(*p).unwrap_or(outside)).collect();
        let centre = Point3::from((lo + hi) / 2.0);
        let camera = Camera::look_at(
            centre + Vector3::new(-150.0, -380.0, 120.0),
            centre,
            Vector3::z(),
            Projection::Perspective { fov_y_deg: 40.0 },
            96,
            64,
        )
        .unwrap();
        let tf = TransferFunction::preset("ct_soft_tissue").unwrap();
        let bend = |p: &Vector3<f64>| Vector3::new(0.0, 0.0, 12.0 * ((p.x - centre.x) / 60.0).sin());
        let mut cpu = TetRaycaster::new(&mesh, &scalars, &tf, &TetRaycastParams::default()).unwrap();
        let mut from_host = GpuTetRaycaster::new(ctx.clone(), &cpu, 1e3).unwrap();
        let mut from_device = GpuTetRaycaster::new(ctx.clone(), &cpu, 1e3).unwrap();
        from_device.capacity = 1;
        let bent: Vec<Vector3<f64>> = mesh.nodes().iter().map(|p| p + bend(p)).collect();
        let metres: Vec<[f32; 4]> = mesh
            .nodes()
            .iter()
            .map(|p| {
                let u = bend(p) * 1e-3;
                [u.x as f32, u.y as f32, u.z as f32, 0.0]
            })
            .collect();
        from_device.nodes().place_from(&ctx.storage_buffer("displacements", bytemuck::cast_slice(&metres))).unwrap();
        from_device.refresh();
        from_host.update(&bent).unwrap();
        cpu.update(&bent).unwrap();
        let cpu_image = cpu.render(&camera).unwrap();
        compare(&cpu_image, &from_host.render(&camera).unwrap(), "placed from the host", 0.1);
        compare(&cpu_image, &from_device.render(&camera).unwrap(), "placed from a device buffer", 0.1);
        assert!(from_device.capacity > 1, "the tile lists grew");
    }
}
