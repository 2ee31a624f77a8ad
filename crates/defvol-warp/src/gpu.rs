//! The grid warp on the GPU: `warp.wgsl` beside this file, the `Spans` scheme with trilinear
//! or tricubic (Catmull-Rom) sampling, after the displacement volumes. The source volume,
//! the rest mesh and the output grid go up once; a warp then takes the deformed nodes where
//! they are ([`GpuWarp::place_from`]: another stage's device buffer; [`GpuWarp::place_host`]:
//! from the host), computes every tet's maps on the device (`tet_maps`, the twin of
//! `tet_map`) and rasterises them into an output buffer that stays on the device, for the
//! volume raycaster to read and for one read-back, with its counts, straight into its
//! destination ([`GpuWarp::read_into`]). The rows of all tets' boxes are one flat range (a
//! prefix sum of their counts on the device, dispatched indirectly), an invocation a row,
//! so a tet a hundred times bigger than the rest does not leave the GPU waiting on it; the
//! background is written afterwards, only where no tet wrote. (One workgroup a tet, the
//! first kernel, was slow where tets are large and was removed, see
//! docs/perf/journal.md#the-gpu-warp-a-row-an-invocation: `WarpOptions::path` chooses
//! among the CPU's loops only.)
//!
//! Differences from the CPU path: maps and spans are computed in f32 on box-local
//! coordinates, so voxels within ~1e-5 (in barycentric terms) of a tet face may be decided
//! differently; a voxel on a face shared by two tets takes whichever tet wrote last.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use nalgebra::{Matrix3, Vector3};

use crate::{Sampling, WarpError, WarpOptions, WarpStats};
use defvol_core::mesh::TetMesh;
use defvol_core::volume::{Grid, Volume};
use defvol_gpu::gpu::{self, DeviceNodes, GpuContext, GpuError, Kernels};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GpuWarpError {
    #[error(transparent)]
    Warp(#[from] WarpError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("the GPU warp does {0}; use the CPU path")]
    Unsupported(&'static str),
    #[error("the deformed tets' boxes hold more than 2^32 rows of voxels (a runaway deformation?)")]
    TooManyRows,
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    out_dims: [u32; 4],
    src_dims: [u32; 4],
    background: [f32; 4],
    identity: [[f32; 4]; 3],
    groups: [u32; 4],
    scan: [u32; 4],
}

const WORKGROUP: u32 = 64;
/// The CPU path's tolerances (INSIDE_TOLERANCE, SAMPLE_TOLERANCE) are below f32 round-off
/// on voxel-local coordinates; these are above it, so boundary voxels of a mesh built on the
/// lattice (exact ties) are kept here as they are on the CPU.
const GPU_INSIDE_TOLERANCE: f32 = 1e-5;
const GPU_SAMPLE_TOLERANCE: f32 = 1e-4;
/// Storage buffers `warp.wgsl` binds.
const STORAGE_BUFFERS: u32 = 9;
/// Tets a workgroup of `scan_rows` sums.
const SCAN_BLOCK: u32 = 256;
/// Bytes of `stats` before its coverage bits: voxels written, tets skipped, rows
/// overflowed, one unused.
const STATS_HEADER: u64 = 16;

/// A warp of one source volume through one mesh onto one grid, kept on the device.
pub struct GpuWarp {
    ctx: Arc<GpuContext>,
    grid: Grid,
    tet_count: u32,
    nodes: Arc<DeviceNodes>,
    out: wgpu::Buffer,
    stats: wgpu::Buffer,
    rows: wgpu::Buffer,
    /// `warp_rows`' dispatch, copied out of `rows` (a buffer bound for writing cannot be
    /// read as the dispatch that binds it).
    dispatch: wgpu::Buffer,
    kernels: Kernels<5>,
    bind_group: wgpu::BindGroup,
    groups: Groups,
    /// The last warp's work, once read back with its volume (a later `stats` then costs no
    /// round trip).
    read: std::sync::Mutex<Option<WarpStats>>,
}

/// The direct dispatches' grids.
struct Groups {
    fill: (u32, u32),
    maps: (u32, u32),
    scan: (u32, u32),
}

impl GpuWarp {
    /// Uploads `source` and the `rest` mesh (in the source's units) for warps onto `grid`.
    /// Deformed nodes come as displacements from rest in the units of whoever moves them
    /// (the solver: world units); `to_file` scales those to the source's units.
    pub fn new(
        ctx: Arc<GpuContext>,
        source: &Volume,
        rest: &TetMesh,
        grid: Grid,
        options: &WarpOptions,
        to_file: f64,
    ) -> Result<Self, GpuWarpError> {
        if !(to_file.is_finite() && to_file > 0.0) {
            return Err(GpuWarpError::Unsupported("positive, finite unit scales only"));
        }
        ctx.require_storage_buffers("the warp", STORAGE_BUFFERS)?;
        ctx.require_binding_size("the source volume", source.len() as u64 * 4)?;
        ctx.require_binding_size("the output grid", (grid.len() as u64).saturating_mul(4))?;
        ctx.require_binding_size("the tet maps", rest.tets().len() as u64 * 144)?;
        let stats_bytes = STATS_HEADER + grid.len().div_ceil(32) as u64 * 4;
        ctx.require_binding_size("the coverage marks", stats_bytes)?;
        let source_grid = source.grid();
        // Deformed nodes in output index space: the rest nodes there, moved by the
        // displacement's image under the grid's linear map.
        let base = rest.nodes().iter().map(|p| {
            let q = grid.index_from_world(*p);
            [q.x, q.y, q.z, 0.0]
        });
        let linear = Matrix3::from_diagonal(&Vector3::from(grid.spacing).map(|s| 1.0 / s))
            * grid.direction.transpose()
            * to_file;
        let nodes = Arc::new(DeviceNodes::new(ctx.clone(), base.collect(), linear)?);
        let rest_src = source_grid.indices_f32(rest.nodes());
        let (m, c) = grid.index_map_to(&source_grid);
        let identity = [0, 1, 2].map(|r| [c[r] as f32, m[(r, 0)] as f32, m[(r, 1)] as f32, m[(r, 2)] as f32]);
        let tet_count = rest.tets().len() as u32;
        let blocks = tet_count.div_ceil(SCAN_BLOCK);
        let groups = Groups {
            fill: gpu::groups_2d(grid.len() as u32, WORKGROUP),
            maps: gpu::groups_2d(tet_count, WORKGROUP),
            scan: gpu::groups_2d(blocks, 1),
        };
        let d = |dims: [usize; 3], w: u32| [dims[0] as u32, dims[1] as u32, dims[2] as u32, w];
        let params = Params {
            out_dims: d(grid.dims, tet_count),
            src_dims: d(source.dims(), options.displacements.len() as u32),
            background: [
                options.background,
                GPU_INSIDE_TOLERANCE,
                GPU_SAMPLE_TOLERANCE,
                if options.keep_uncovered { 1.0 } else { 0.0 },
            ],
            identity,
            groups: [groups.fill.0, groups.maps.0, 0, u32::from(options.sampling == Sampling::Tricubic)],
            scan: [groups.scan.0, blocks, 0, 0],
        };
        use defvol_gpu::gpu::Binding::{Read, ReadWrite, Uniform};
        let kernels = ctx.kernels(
            "warp.wgsl",
            include_str!("warp.wgsl"),
            &[Uniform, ReadWrite, Read, ReadWrite, Read, Read, Read, ReadWrite, Read, ReadWrite],
            ["fill", "tet_maps", "scan_rows", "scan_blocks", "warp_rows"],
        );
        let params = wgpu::util::DeviceExt::create_buffer_init(
            &ctx.device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("warp params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM,
            },
        );
        let maps_buffer = ctx.zeroed_buffer("warp maps", u64::from(tet_count) * 144);
        let source_buffer = ctx.storage_buffer("warp source", bytemuck::cast_slice(source.data()));
        let out = ctx.zeroed_buffer("warp out", grid.len() as u64 * 4);
        let rest_buffer = ctx.storage_buffer("warp rest nodes", bytemuck::cast_slice(&rest_src));
        let tets = ctx.storage_buffer("warp tets", bytemuck::cast_slice(rest.tets()));
        let stats = ctx.zeroed_buffer("warp stats", stats_bytes);
        let rows = ctx.zeroed_buffer("warp rows", 4 * (4 + u64::from(tet_count) + u64::from(blocks)));
        let dispatch = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("warp dispatch"),
            size: 12,
            usage: wgpu::BufferUsages::INDIRECT | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let pushes =
            ctx.storage_buffer("warp displacement volumes", bytemuck::cast_slice(&pushes(&source_grid, options)?));
        let bind_group = ctx.bind_group(
            "warp",
            &kernels.layout,
            &[&params, &maps_buffer, &source_buffer, &out, nodes.buffer(), &rest_buffer, &tets, &stats, &pushes, &rows],
        );
        Ok(Self {
            ctx,
            grid,
            tet_count,
            nodes,
            out,
            stats,
            rows,
            dispatch,
            kernels,
            bind_group,
            groups,
            read: Default::default(),
        })
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The deformed nodes on the device, for another stage to place
    /// ([`DeviceNodes::place_from`]) before [`Self::run`].
    pub fn nodes(&self) -> &Arc<DeviceNodes> {
        &self.nodes
    }

    /// The warped samples on the device (x fastest), after [`Self::run`].
    pub fn output(&self) -> &wgpu::Buffer {
        &self.out
    }

    /// Deformed nodes from a device buffer of displacements from rest (`vec4<f32>` per
    /// node, e.g. the GPU solver's): nothing goes through the host.
    pub fn place_from(&self, displacements: &wgpu::Buffer) -> Result<(), GpuWarpError> {
        Ok(self.nodes.place_from(displacements)?)
    }

    /// Deformed nodes from displacements on the host (same units as for `place_from`).
    pub fn place_host(&self, displacements: &[Vector3<f64>]) -> Result<(), GpuWarpError> {
        if let Some(node) = displacements.iter().position(|u| !u.iter().all(|c| c.is_finite())) {
            return Err(WarpError::NonFiniteNode { node }.into());
        }
        if displacements.len() != self.nodes.len() {
            return Err(WarpError::NodeCount { got: displacements.len(), expected: self.nodes.len() }.into());
        }
        Ok(self.nodes.place_host(displacements)?)
    }

    /// Queues one warp of the placed nodes: tet maps, their rows counted and summed, the
    /// rows' spans, then the background (or source) where no tet wrote.
    pub fn run(&self) {
        let [fill, tet_maps, scan_rows, scan_blocks, warp_rows] = &self.kernels.pipelines;
        let g = &self.groups;
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("warp") });
        encoder.clear_buffer(&self.stats, 0, None);
        self.pass(&mut encoder, &[(tet_maps, g.maps), (scan_rows, g.scan), (scan_blocks, (1, 1))]);
        encoder.copy_buffer_to_buffer(&self.rows, 0, &self.dispatch, 0, 12);
        let mut pass = self.begin_pass(&mut encoder);
        pass.set_pipeline(warp_rows);
        pass.dispatch_workgroups_indirect(&self.dispatch, 0);
        pass.set_pipeline(fill);
        pass.dispatch_workgroups(g.fill.0, g.fill.1, 1);
        drop(pass);
        self.ctx.submit(encoder.finish());
        *self.read_stats() = None;
    }

    fn read_stats(&self) -> std::sync::MutexGuard<'_, Option<WarpStats>> {
        self.read.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn begin_pass<'e>(&self, encoder: &'e mut wgpu::CommandEncoder) -> wgpu::ComputePass<'e> {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("warp"),
            timestamp_writes: self.ctx.pass_timestamps(),
        });
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass
    }

    /// One compute pass of direct dispatches.
    fn pass(&self, encoder: &mut wgpu::CommandEncoder, dispatches: &[(&wgpu::ComputePipeline, (u32, u32))]) {
        let mut pass = self.begin_pass(encoder);
        for (pipeline, (x, y)) in dispatches {
            pass.set_pipeline(pipeline);
            pass.dispatch_workgroups(*x, *y, 1);
        }
    }

    /// The last warp's work: as read with its volume, else a small read-back.
    pub fn stats(&self) -> Result<WarpStats, GpuWarpError> {
        if let Some(stats) = *self.read_stats() {
            return Ok(stats);
        }
        let mut counts = [0u8; STATS_HEADER as usize];
        self.ctx.read_back_into(&self.stats, &mut counts)?;
        let stats = self.work(counts)?;
        *self.read_stats() = Some(stats);
        Ok(stats)
    }

    /// Reads the last warp back into `out` (one staging copy straight into it: a
    /// shared-memory sample, say) and returns its work, read in the same round trip.
    pub fn read_into(&self, out: &mut [f32]) -> Result<WarpStats, GpuWarpError> {
        if out.len() != self.grid.len() {
            return Err(WarpError::BufferSize { got: out.len(), expected: self.grid.len() }.into());
        }
        let pending = self.ctx.read_back_later(&[(&self.out, self.grid.len() as u64 * 4), (&self.stats, STATS_HEADER)]);
        let mut counts = [0u8; STATS_HEADER as usize];
        self.ctx.finish_read_parts(pending, &mut [bytemuck::cast_slice_mut(out), &mut counts])?;
        let stats = self.work(counts)?;
        *self.read_stats() = Some(stats);
        Ok(stats)
    }

    fn work(&self, counts: [u8; STATS_HEADER as usize]) -> Result<WarpStats, GpuWarpError> {
        let [inside, skipped, overflowed, _]: [u32; 4] = bytemuck::pod_read_unaligned(&counts);
        if overflowed != 0 {
            return Err(GpuWarpError::TooManyRows);
        }
        Ok(WarpStats {
            voxels: self.grid.len() as u64,
            candidates: 0,
            inside: u64::from(inside),
            skipped_tets: u64::from(skipped),
        })
    }

    /// Warps to `deformed` (positions in the source's units, `to_file` = 1) and reads the
    /// samples back: the one-shot path of `defvol warp`.
    pub fn warp(&self, rest: &TetMesh, deformed: &[Vector3<f64>]) -> Result<(Vec<f32>, WarpStats), GpuWarpError> {
        let mut out = vec![0f32; self.grid.len()];
        let stats = self.warp_into(rest, deformed, &mut out)?;
        Ok((out, stats))
    }

    /// As [`GpuWarp::warp`], read back into `out` (the grid's length), which a caller keeps
    /// from step to step: the benches, as the node keeps its shared-memory samples.
    pub fn warp_into(
        &self,
        rest: &TetMesh,
        deformed: &[Vector3<f64>],
        out: &mut [f32],
    ) -> Result<WarpStats, GpuWarpError> {
        if deformed.len() != rest.nodes().len() {
            return Err(WarpError::NodeCount { got: deformed.len(), expected: rest.nodes().len() }.into());
        }
        let displacements: Vec<Vector3<f64>> = deformed.iter().zip(rest.nodes()).map(|(p, r)| p - r).collect();
        self.place_host(&displacements)?;
        self.run();
        self.read_into(out)
    }

    /// Tets in the mesh.
    pub fn tet_count(&self) -> usize {
        self.tet_count as usize
    }
}

/// The displacement volumes in the source's index space, 4 vec4 each as `warp.wgsl` reads
/// them (one zero block where there are none: a binding is never empty).
fn pushes(source: &Grid, options: &WarpOptions) -> Result<Vec<[f32; 4]>, WarpError> {
    let compiled = crate::bspline::compile_all(&options.displacements)
        .map_err(|(index, why)| WarpError::BadDisplacement { index, why })?;
    let m = source.direction * Matrix3::from_diagonal(&Vector3::from(source.spacing));
    let mut blocks = Vec::with_capacity(4 * compiled.len().max(1));
    for (index, volume) in compiled.iter().enumerate() {
        let (rows, d) = volume
            .in_space(&m, &Vector3::from(source.origin))
            .ok_or_else(|| WarpError::BadDisplacement { index, why: "the source grid is singular".into() })?;
        blocks.extend(rows.map(|r| r.map(|v| v as f32)));
        blocks.push([d.x as f32, d.y as f32, d.z as f32, 0.0]);
    }
    if blocks.is_empty() {
        blocks.resize(4, [0.0; 4]);
    }
    Ok(blocks)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate as warp;
    use defvol_core::mesh::generate::{self, CellSplit};
    use defvol_core::volume::phantom;
    use nalgebra::Rotation3;

    /// GPU and CPU warps of the phantom through an upright, a rotated and bent mesh, with
    /// the uncovered voxels kept, and with two displacement volumes on top, sampled trilinear
    /// and tricubic: the same inside decisions and values.
    #[test]
    fn gpu_warp_matches_cpu() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let source = phantom::phantom([64, 40, 31], 4.0).unwrap();
        let (lo, hi) = source.bounds();
        let mesh = generate::lattice_for_box(lo, hi, 700, CellSplit::Five).unwrap();
        let centre = (lo + hi) / 2.0;
        let rot = Rotation3::from_euler_angles(0.6, 0.5, 0.0);
        let bent: Vec<Vector3<f64>> = mesh
            .nodes()
            .iter()
            .map(|p| centre + rot * (p - centre) + Vector3::new(0.0, 0.0, 1e-3 * (p.x - centre.x).powi(2)))
            .collect();
        // Upright: the mesh boundary lies on voxel planes, every boundary voxel an exact tie.
        // Two pushes (mm, the phantom's units) across the bent mesh, the second overlapping the first.
        let pushes = vec![
            warp::DisplacementVolume { centre: centre.into(), displacement: [0.0, 6.0, 3.0], extent: 30.0 },
            warp::DisplacementVolume {
                centre: (centre + Vector3::new(10.0, 0.0, 0.0)).into(),
                displacement: [-4.0, 0.0, 0.0],
                extent: 20.0,
            },
        ];
        let cases = [
            (mesh.nodes().to_vec(), false, Vec::new()),
            (bent.clone(), false, Vec::new()),
            (bent.clone(), true, Vec::new()),
            (bent, true, pushes),
        ];
        for ((deformed, keep_uncovered, displacements), sampling) in
            cases.iter().flat_map(|case| [Sampling::Trilinear, Sampling::Tricubic].map(|s| (case.clone(), s)))
        {
            let grid = warp::default_grid(&source, &deformed);
            let options =
                WarpOptions { background: -2000.0, keep_uncovered, sampling, displacements, ..Default::default() };
            let (cpu, stats) = warp::warp_samples::<f32>(&source, &mesh, &deformed, &grid, &options).unwrap();
            let gpu = GpuWarp::new(ctx.clone(), &source, &mesh, grid, &options, 1.0).unwrap();
            let (gpu_out, gpu_stats) = gpu.warp(&mesh, &deformed).unwrap();
            let (vmin, vmax) = source.range();
            // A voxel decided differently (a tie on a face) takes another value: count those
            // apart from the round-off of the rest.
            let off: Vec<f32> =
                cpu.iter().zip(&gpu_out).map(|(a, b)| (a - b).abs()).filter(|d| *d > 2e-5 * (vmax - vmin)).collect();
            assert!(stats.inside > 20_000, "{stats:?}");
            // Measured on lavapipe: 0 of 73,719 decided differently, values within 6e-6 of the range.
            assert!(
                (off.len() as f64) <= 1e-4 * stats.inside as f64,
                "{} voxels differ (keep_uncovered {keep_uncovered}, {sampling:?}, {} pushes) of {} inside",
                off.len(),
                options.displacements.len(),
                stats.inside
            );
            // Shared faces are written by both their tets: the GPU counts every write.
            assert!(
                gpu_stats.inside >= stats.inside && gpu_stats.inside <= stats.inside + stats.inside / 5,
                "{gpu_stats:?} against {stats:?}"
            );
            assert_eq!(gpu_stats.skipped_tets, stats.skipped_tets);
        }
    }

    /// Tets of every size in one warp, more of them than one workgroup's prefix sum spans
    /// (75k tets, so the blocks' sum takes chunks): a lattice of voxel-sized tets, many
    /// covering no voxel centre, around a node pulled ten voxels out (its tets a hundred
    /// times the others' boxes, some inverted and skipped), warped as on the CPU.
    #[test]
    fn tets_of_every_size_in_many_scan_blocks_warp_as_on_the_cpu() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let source = phantom::phantom([48, 36, 28], 4.0).unwrap();
        let (lo, hi) = source.bounds();
        let mesh = generate::lattice_for_box(lo, hi, 75_000, CellSplit::Five).unwrap();
        assert!(mesh.tets().len() > 65_536, "{} tets", mesh.tets().len());
        let centre = (lo + hi) / 2.0;
        let pulled = (0..mesh.nodes().len())
            .min_by(|&a, &b| (mesh.nodes()[a] - centre).norm().total_cmp(&(mesh.nodes()[b] - centre).norm()))
            .unwrap();
        let mut deformed = mesh.nodes().to_vec();
        deformed[pulled] += Vector3::new(40.0, 10.0, -5.0);
        let grid = warp::default_grid(&source, &deformed);
        let options = WarpOptions { background: -2000.0, ..Default::default() };
        let (cpu, stats) = warp::warp_samples::<f32>(&source, &mesh, &deformed, &grid, &options).unwrap();
        let (gpu, gpu_stats) =
            GpuWarp::new(ctx, &source, &mesh, grid, &options, 1.0).unwrap().warp(&mesh, &deformed).unwrap();
        let (vmin, vmax) = source.range();
        let off = cpu.iter().zip(&gpu).filter(|(a, b)| (*a - *b).abs() > 2e-5 * (vmax - vmin)).count();
        assert!(stats.skipped_tets > 0 && stats.inside > 30_000, "{stats:?}");
        assert!((off as f64) <= 1e-3 * stats.inside as f64, "{off} voxels differ of {} inside", stats.inside);
        assert_eq!(gpu_stats.skipped_tets, stats.skipped_tets);
    }

    /// Tets whose boxes hold more than 2^32 rows (1100 tets, each over a 1x2048x2048 grid)
    /// are refused by name, nothing written in their place.
    #[test]
    fn rows_past_u32_are_refused_by_name() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let source = phantom::phantom([16, 16, 16], 1.0).unwrap();
        let corners = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(Vector3::from);
        let tets: Vec<[u32; 4]> = (0..1100u32).map(|t| [0, 1, 2, 3].map(|k| 4 * t + k)).collect();
        let rest: Vec<Vector3<f64>> = (0..1100).flat_map(|_| corners.map(|c| c * 4.0 + Vector3::repeat(2.0))).collect();
        let mesh = TetMesh::new(rest, tets, None, "1100 tets").unwrap();
        let huge: Vec<Vector3<f64>> =
            (0..1100).flat_map(|_| corners.map(|c| c * 20_000.0 - Vector3::repeat(5_000.0))).collect();
        let grid = Grid { dims: [1, 2048, 2048], spacing: [1.0; 3], origin: [0.0; 3], direction: Matrix3::identity() };
        let gpu = GpuWarp::new(ctx, &source, &mesh, grid, &WarpOptions::default(), 1.0).unwrap();
        let err = gpu.warp(&mesh, &huge).unwrap_err();
        assert!(matches!(err, GpuWarpError::TooManyRows), "{err}");
        assert!(err.to_string().contains("more than 2^32 rows"), "{err}");
    }

    /// An output grid past what one GPU buffer may hold is refused before anything is
    /// allocated, naming the grid, its size and the adapter's limit.
    #[test]
    fn an_output_grid_over_the_buffer_limit_is_refused_naming_the_limit() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let limits = ctx.device.limits();
        let limit = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
        let source = phantom::phantom([16, 16, 16], 1.0).unwrap();
        let (lo, hi) = source.bounds();
        let mesh = generate::lattice_for_box(lo, hi, 40, CellSplit::Five).unwrap();
        // One slice of 1024x1024 voxels (4 MiB) more than the limit holds.
        let slices = (limit / 4).div_ceil(1 << 20) as usize + 1;
        let grid =
            Grid { dims: [1024, 1024, slices], spacing: [1.0; 3], origin: [0.0; 3], direction: Matrix3::identity() };
        let err = GpuWarp::new(ctx.clone(), &source, &mesh, grid, &WarpOptions::default(), 1.0).err().unwrap();
        let GpuWarpError::Gpu(GpuError::BufferTooLarge { what, needed_mib, limit_mib, .. }) = &err else {
            panic!("{err}")
        };
        assert_eq!((*what, *needed_mib, *limit_mib), ("the output grid", 4 * slices as u64, limit >> 20), "{err}");
        assert!(err.to_string().contains(&format!("allows {} MiB", limit >> 20)), "{err}");
        // A runaway deformation's default grid, whose bytes no 64 bits count: refused alike.
        let mut thrown = mesh.nodes().to_vec();
        thrown[0] = Vector3::repeat(1e30);
        let runaway = crate::cpu::default_grid(&source, &thrown);
        assert_eq!(runaway.len(), usize::MAX);
        let err = GpuWarp::new(ctx, &source, &mesh, runaway, &WarpOptions::default(), 1.0).err().unwrap();
        let GpuWarpError::Gpu(GpuError::BufferTooLarge { what, needed_mib, .. }) = &err else { panic!("{err}") };
        assert_eq!((*what, *needed_mib), ("the output grid", u64::MAX.div_ceil(1 << 20)), "{err}");
    }

    /// A read-back of a warp is one round trip, its work counted in it (asking for the
    /// work again costs none): the samples and the counts equal those of the same warp run
    /// again and read apart.
    #[test]
    fn a_warp_reads_back_with_its_work_in_one_round_trip() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let source = phantom::phantom([40, 30, 20], 4.0).unwrap();
        let (lo, hi) = source.bounds();
        let mesh = generate::lattice_for_box(lo, hi, 300, CellSplit::Five).unwrap();
        let grid = warp::default_grid(&source, mesh.nodes());
        let gpu = GpuWarp::new(ctx.clone(), &source, &mesh, grid.clone(), &WarpOptions::default(), 1.0).unwrap();
        gpu.place_host(&vec![Vector3::zeros(); mesh.nodes().len()]).unwrap();
        gpu.run();
        let mut out = vec![f32::NAN; grid.len()];
        let before = ctx.counters();
        let stats = gpu.read_into(&mut out).unwrap();
        let cost = ctx.counters().since(&before);
        assert_eq!((cost.submissions, cost.readbacks, cost.bytes_read_back), (1, 1, grid.len() as u64 * 4 + 16));
        let before = ctx.counters();
        assert_eq!(stats, gpu.stats().unwrap());
        assert_eq!(ctx.counters().since(&before).readbacks, 0);
        gpu.run();
        let before = ctx.counters();
        assert_eq!(stats, gpu.stats().unwrap());
        assert_eq!(ctx.counters().since(&before).readbacks, 1, "the run again is read apart");
        assert!(stats.inside >= grid.len() as u64, "{stats:?}: the lattice covers its own grid");
        let apart = ctx.read_back(gpu.output(), grid.len() as u64 * 4).unwrap();
        assert_eq!(bytemuck::cast_slice::<f32, u8>(&out), apart.as_slice());
    }

    /// The deformed nodes read from a device buffer of displacements in other units (metres
    /// over a millimetre volume) give the warp the host's positions give.
    #[test]
    fn displacements_on_the_device_warp_as_host_positions_do() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let source = phantom::phantom([48, 30, 24], 5.0).unwrap();
        let (lo, hi) = source.bounds();
        let mesh = generate::lattice_for_box(lo, hi, 400, CellSplit::Five).unwrap();
        let centre = (lo + hi) / 2.0;
        let moved: Vec<Vector3<f64>> = mesh
            .nodes()
            .iter()
            .map(|p| p + Vector3::new(0.0, 0.0, -8.0 * (-(p - centre).norm_squared() / 3000.0).exp()))
            .collect();
        let options = WarpOptions { background: -1000.0, keep_uncovered: true, ..Default::default() };
        let grid = source.grid();
        let metres: Vec<[f32; 4]> = moved
            .iter()
            .zip(mesh.nodes())
            .map(|(p, r)| {
                let u = (p - r) * 1e-3;
                [u.x as f32, u.y as f32, u.z as f32, 0.0]
            })
            .collect();
        let on_device = GpuWarp::new(ctx.clone(), &source, &mesh, grid.clone(), &options, 1e3).unwrap();
        on_device.place_from(&ctx.storage_buffer("displacements", bytemuck::cast_slice(&metres))).unwrap();
        on_device.run();
        let mut from_device = vec![0f32; grid.len()];
        on_device.read_into(&mut from_device).unwrap();
        let from_host =
            GpuWarp::new(ctx, &source, &mesh, grid.clone(), &options, 1.0).unwrap().warp(&mesh, &moved).unwrap().0;
        let (cpu, _) = warp::warp_samples::<f32>(&source, &mesh, &moved, &grid, &options).unwrap();
        let (vmin, vmax) = source.range();
        let off =
            |a: &[f32], b: &[f32]| a.iter().zip(b).filter(|(x, y)| (*x - *y).abs() > 1e-4 * (vmax - vmin)).count();
        assert!(
            off(&from_device, &from_host) <= grid.len() / 10_000,
            "{} voxels differ between device and host placement",
            off(&from_device, &from_host)
        );
        assert!(
            off(&from_device, &cpu) <= grid.len() / 10_000,
            "{} voxels differ from the CPU warp",
            off(&from_device, &cpu)
        );
    }
}
