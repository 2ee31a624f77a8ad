//! The DPCM step on the GPU: `dpcm.wgsl` beside this file, one invocation per phyxel, markers binned
//! on the CPU (the same [`MarkerBins`] as the CPU path) and gathered per tile.
//!
//! Z(n+1), Z(n) and Z(n-1) live in three buffers that rotate, so a step uploads only the
//! markers and reads nothing back. A batch of steps is one upload of every step's markers
//! and one submission: each dispatch picks its step's tile lists by a dynamic offset.

use std::collections::HashMap;
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};

use crate::kernels::{Coeffs, KernelMarker, TILE};
use crate::{to_kernel_markers, DpcmConfig, DpcmError, Marker, MarkerBins, StepStats, Surface};
use defvol_gpu::gpu::{Blocks, GpuContext, GpuError, Kernels};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GpuDpcmError {
    #[error(transparent)]
    Dpcm(#[from] DpcmError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("a DPCM batch needs at least one step")]
    EmptyBatch,
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    c: Coeffs,
    width: u32,
    height: u32,
    tiles_x: u32,
    flags: u32,
    _pad: [u32; 4],
}

/// Where a dispatch's step starts in the batch's tile offsets (`BatchStep` in the shader).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct BatchStep {
    offsets_base: u32,
    _pad: [u32; 3],
}

/// The markers of a batch's steps in one upload: each step's tile lists follow the last
/// step's, its offsets shifted into the shared index list and its indices into the shared
/// markers.
#[derive(Debug, Default)]
struct BatchBins {
    markers: Vec<KernelMarker>,
    offsets: Vec<u32>,
    indices: Vec<u32>,
}

impl BatchBins {
    fn clear(&mut self) {
        self.markers.clear();
        self.offsets.clear();
        self.indices.clear();
    }

    fn push(&mut self, bins: &MarkerBins) {
        let (marker_base, index_base) = (self.markers.len() as u32, self.indices.len() as u32);
        self.markers.extend_from_slice(&bins.markers);
        self.indices.extend(bins.indices.iter().map(|i| i + marker_base));
        self.offsets.extend(bins.offsets.iter().map(|o| o + index_base));
    }
}

const FLAG_GROUND_TEXTURE: u32 = 1;
const FLAG_REST_PER_PHYXEL: u32 = 2;

pub struct GpuSurface {
    ctx: Arc<GpuContext>,
    config: DpcmConfig,
    params: wgpu::Buffer,
    /// u = Z - rest height buffers; `current` indexes u(n), the next u(n+1), the last u(n-1).
    heights: [wgpu::Buffer; 3],
    current: usize,
    rest: wgpu::Buffer,
    ground: [wgpu::Buffer; 2],
    markers: wgpu::Buffer,
    offsets: wgpu::Buffer,
    indices: wgpu::Buffer,
    /// Step k of a batch reads block k.
    steps: Blocks,
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
    bind_groups: Vec<wgpu::BindGroup>,
    bins: MarkerBins,
    batch: BatchBins,
    marker_heights: HashMap<u32, f32>,
    phyxels: usize,
    tiles: usize,
}

fn storage<T: Pod>(ctx: &GpuContext, label: &str, data: &[T], fallback: T) -> wgpu::Buffer {
    if data.is_empty() {
        ctx.storage_buffer(label, bytemuck::bytes_of(&fallback))
    } else {
        ctx.storage_buffer(label, bytemuck::cast_slice(data))
    }
}

impl GpuSurface {
    /// The GPU twin of `Surface::new(config)`, starting from the same state.
    pub fn new(ctx: Arc<GpuContext>, config: &DpcmConfig) -> Result<Self, GpuDpcmError> {
        let surface = Surface::new(config)?;
        Self::from_surface(ctx, &surface)
    }

    /// Uploads a CPU surface's state (heights, rest points, textures).
    pub fn from_surface(ctx: Arc<GpuContext>, surface: &Surface) -> Result<Self, GpuDpcmError> {
        let config = surface.config().clone();
        let phyxels = config.width * config.height;
        ctx.require_binding_size("the DPCM grid", phyxels as u64 * 4)?;
        use defvol_gpu::gpu::Binding::{DynamicUniform, Read, ReadWrite, Uniform};
        let Kernels { layout, pipelines: [pipeline] } = ctx.kernels(
            "dpcm.wgsl",
            include_str!("dpcm.wgsl"),
            &[Uniform, Read, Read, ReadWrite, ReadWrite, Read, Read, Read, Read, Read, DynamicUniform],
            ["step"],
        );
        let device = &ctx.device;
        let coeffs = *surface.coeffs();
        let rest = surface.rest_deviations();
        let per_phyxel_rest = !rest.is_empty();
        let ground: Vec<(f32, f32)> = (0..phyxels).map(|i| surface.ground_coeffs(i)).collect();
        let textured = ground.iter().any(|g| *g != (coeffs.ground_a, coeffs.ground_b));
        let flags =
            if textured { FLAG_GROUND_TEXTURE } else { 0 } | if per_phyxel_rest { FLAG_REST_PER_PHYXEL } else { 0 };
        let tiles_x = config.width.div_ceil(TILE);
        let block = uniform_block(&config, coeffs, tiles_x, flags);
        let params = wgpu::util::DeviceExt::create_buffer_init(
            device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("dpcm params"),
                contents: bytemuck::bytes_of(&block),
                usage: wgpu::BufferUsages::UNIFORM,
            },
        );
        let heights = [
            ctx.storage_buffer("dpcm u(n)", bytemuck::cast_slice(surface.deviations())),
            ctx.storage_buffer("dpcm u(n+1)", bytemuck::cast_slice(surface.deviations())),
            ctx.storage_buffer("dpcm u(n-1)", bytemuck::cast_slice(surface.previous_deviations())),
        ];
        let rest = storage(&ctx, "dpcm rest", rest, 0.0f32);
        let (ga, gb): (Vec<f32>, Vec<f32>) =
            if textured { ground.iter().copied().unzip() } else { (Vec::new(), Vec::new()) };
        let ground = [storage(&ctx, "dpcm ground a", &ga, 0.0f32), storage(&ctx, "dpcm ground b", &gb, 0.0f32)];
        let tiles = tiles_x * config.height.div_ceil(TILE);
        let markers = storage(&ctx, "dpcm markers", &[], KernelMarker::zeroed());
        let offsets = storage(&ctx, "dpcm tile offsets", &vec![0u32; tiles + 1], 0u32);
        let indices = storage(&ctx, "dpcm tile indices", &[], 0u32);
        let steps = batch_steps(&ctx, tiles, 1)?;
        let mut gpu = Self {
            ctx,
            config,
            params,
            heights,
            current: 0,
            rest,
            ground,
            markers,
            offsets,
            indices,
            steps,
            layout,
            pipeline,
            bind_groups: Vec::new(),
            bins: MarkerBins::default(),
            batch: BatchBins::default(),
            marker_heights: HashMap::new(),
            phyxels,
            tiles,
        };
        gpu.rebuild_bind_groups();
        Ok(gpu)
    }

    /// One bind group per rotation of the three height buffers.
    fn rebuild_bind_groups(&mut self) {
        self.bind_groups = (0..3)
            .map(|r| {
                let (z, out, zp) = (&self.heights[r], &self.heights[(r + 1) % 3], &self.heights[(r + 2) % 3]);
                let buffers = [
                    &self.params,
                    z,
                    zp,
                    out,
                    &self.rest,
                    &self.ground[0],
                    &self.ground[1],
                    &self.markers,
                    &self.offsets,
                    &self.indices,
                ];
                let mut resources: Vec<_> = buffers.iter().map(|b| b.as_entire_binding()).collect();
                resources.push(self.steps.binding());
                self.ctx.bind_group_of("dpcm", &self.layout, resources)
            })
            .collect();
    }

    /// Writes `data` to `buffer`, growing it (and the bind groups) when it is too small.
    fn upload<T: Pod>(&mut self, which: fn(&mut Self) -> &mut wgpu::Buffer, label: &str, data: &[T]) {
        if data.is_empty() {
            return;
        }
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let too_small = which(self).size() < bytes.len() as u64;
        if too_small {
            let grown = self.ctx.storage_buffer(label, &vec![0u8; bytes.len().next_power_of_two()]);
            *which(self) = grown;
            self.rebuild_bind_groups();
        }
        let ctx = self.ctx.clone();
        ctx.queue.write_buffer(which(self), 0, bytes);
    }

    /// One step under `markers` (queued; nothing is read back).
    pub fn step(&mut self, markers: &[Marker]) -> Result<StepStats, GpuDpcmError> {
        let stats = self.step_batch(&[markers])?;
        Ok(stats[0])
    }

    /// `batch.len()` steps, step k under `batch[k]`, in one submission with every step's
    /// markers uploaded at once (queued; nothing is read back). The same state as as many
    /// single steps, bit for bit. Refused, naming the limit, when the batch's marker lists
    /// outgrow what the adapter binds.
    pub fn step_batch<M: AsRef<[Marker]>>(&mut self, batch: &[M]) -> Result<Vec<StepStats>, GpuDpcmError> {
        if batch.is_empty() {
            return Err(GpuDpcmError::EmptyBatch);
        }
        let stats = self.bin_batch(batch)?;
        if self.steps.len() < batch.len() {
            self.steps = batch_steps(&self.ctx, self.tiles, batch.len().next_power_of_two())?;
            self.rebuild_bind_groups();
        }
        let bins = std::mem::take(&mut self.batch);
        self.upload(|s| &mut s.markers, "dpcm markers", &bins.markers);
        self.upload(|s| &mut s.offsets, "dpcm tile offsets", &bins.offsets);
        self.upload(|s| &mut s.indices, "dpcm tile indices", &bins.indices);
        self.batch = bins;
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("dpcm batch") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("dpcm batch"),
                timestamp_writes: self.ctx.pass_timestamps(),
            });
            pass.set_pipeline(&self.pipeline);
            for k in 0..batch.len() {
                pass.set_bind_group(0, &self.bind_groups[self.current], &[self.steps.offset(k)]);
                pass.dispatch_workgroups(
                    self.config.width.div_ceil(TILE) as u32,
                    self.config.height.div_ceil(TILE) as u32,
                    1,
                );
                self.current = (self.current + 1) % 3;
            }
        }
        self.ctx.submit(encoder.finish());
        Ok(stats)
    }

    /// Bins each step's markers into the batch's lists, checking they fit one binding.
    fn bin_batch<M: AsRef<[Marker]>>(&mut self, batch: &[M]) -> Result<Vec<StepStats>, GpuDpcmError> {
        self.batch.clear();
        let mut all = Vec::with_capacity(batch.len());
        for markers in batch {
            let (kernel_markers, mut stats) =
                to_kernel_markers(&self.config, &mut self.marker_heights, markers.as_ref());
            stats.markers_off_grid = self.bins.build(kernel_markers, self.config.width, self.config.height);
            stats.markers_applied -= stats.markers_off_grid;
            self.batch.push(&self.bins);
            all.push(stats);
        }
        let bytes = |n: usize, each: usize| (n * each) as u64;
        self.ctx.require_binding_size("a DPCM batch's tile offsets", bytes(self.batch.offsets.len(), 4))?;
        self.ctx.require_binding_size("a DPCM batch's tile lists", bytes(self.batch.indices.len(), 4))?;
        let marker_bytes = std::mem::size_of::<KernelMarker>();
        self.ctx.require_binding_size("a DPCM batch's markers", bytes(self.batch.markers.len(), marker_bytes))?;
        Ok(all)
    }

    /// u(n) = Z(n) - rest height, read back.
    pub fn read_deviations(&self) -> Result<Vec<f32>, GpuError> {
        let bytes = self.ctx.read_back(&self.heights[self.current], self.phyxels as u64 * 4)?;
        Ok(bytemuck::cast_slice(&bytes).to_vec())
    }

    /// Z(n), read back.
    pub fn read_heights(&self) -> Result<Vec<f32>, GpuError> {
        let rest_height = self.config.rest_height as f32;
        Ok(self.read_deviations()?.into_iter().map(|u| u + rest_height).collect())
    }
}

/// One block per step of a batch of up to `capacity` steps: step k's tile offsets start at
/// k (tiles + 1).
fn batch_steps(ctx: &GpuContext, tiles: usize, capacity: usize) -> Result<Blocks, GpuError> {
    let steps: Vec<BatchStep> =
        (0..capacity).map(|k| BatchStep { offsets_base: (k * (tiles + 1)) as u32, _pad: [0; 3] }).collect();
    ctx.blocks("a DPCM batch's steps", &steps)
}

/// The uniform block for `config`.
fn uniform_block(config: &DpcmConfig, coeffs: Coeffs, tiles_x: usize, flags: u32) -> Params {
    Params {
        c: coeffs,
        width: config.width as u32,
        height: config.height as u32,
        tiles_x: tiles_x as u32,
        flags,
        _pad: [0; 4],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Interaction, Topology};
    use crate::{Pattern, Script};

    /// The GPU step against the CPU step, over every topology and ground kind, with
    /// markers moving: same state within f32 round-off (the GPU may fuse multiply-adds).
    #[test]
    fn gpu_steps_match_the_cpu_surface() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let cases = [
            (Topology::Eight, 1.0, Interaction::DampedSpring { stiffness: 0.5, damping: 5e-4 }),
            (Topology::Four, 1.0, Interaction::Plastic { stiffness: 20.0, damping: 0.02, threshold: 3e-4 }),
            (Topology::Diagonal, 1.0, Interaction::Elastic { stiffness: 1.0 }),
            (Topology::Eight, 0.5, Interaction::Plastic { stiffness: 10.0, damping: 0.05, threshold: 2e-4 }),
            (Topology::None, 1.0, Interaction::Plastic { stiffness: 10.0, damping: 0.05, threshold: 2e-4 }),
        ];
        for (topology, probability, ground) in cases {
            let mut c = DpcmConfig::preset("water").unwrap();
            (c.width, c.height) = (83, 61);
            c.links.topology = topology;
            c.links.probability = probability;
            c.links.seed = 11;
            c.ground = ground;
            c.script = Script { markers: 7, pattern: Pattern::Wander, speed: 0.15, depth: 0.0015, leave_after: None };
            let mut cpu = Surface::new(&c).unwrap();
            let mut gpu = GpuSurface::new(ctx.clone(), &c).unwrap();
            let mut peak = 0.0f32;
            for step in 0..400 {
                let markers = c.script.markers_at(&c, step as f64 * c.dt);
                let a = cpu.step(&markers);
                let b = gpu.step(&markers).unwrap();
                assert_eq!(a, b);
                peak = cpu.heights().iter().fold(peak, |m, z| m.max(z.abs()));
            }
            let gpu_heights = gpu.read_heights().unwrap();
            let worst = cpu.heights().iter().zip(&gpu_heights).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(peak > 5e-4, "{topology:?}: markers engraved too little ({peak})");
            assert!(
                worst <= 1e-4 * peak,
                "{topology:?} p={probability}: GPU off the CPU by {worst:e} of a peak {peak:e}"
            );
        }
    }

    #[test]
    fn a_gpu_grid_at_rest_stays_bit_exact() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let mut c = DpcmConfig::preset("fossil").unwrap();
        (c.width, c.height) = (40, 33);
        c.rest_height = 0.0037;
        let mut gpu = GpuSurface::new(ctx, &c).unwrap();
        for _ in 0..20_000 {
            gpu.step(&[]).unwrap();
        }
        assert!(gpu.read_heights().unwrap().iter().all(|&z| z == 0.0037_f32));
    }

    /// A batch of steps, markers moving, is one submission and nothing read back; it leaves
    /// the state bit for bit as the same steps submitted one by one (batches of 1 to 15, the
    /// step buffers growing on the way), with the same marker stats.
    #[test]
    fn a_batch_is_one_submission_and_leaves_the_state_of_its_single_steps_bit_for_bit() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let mut c = DpcmConfig::preset("water").unwrap();
        (c.width, c.height) = (83, 61);
        c.script = Script { markers: 7, pattern: Pattern::Wander, speed: 0.15, depth: 0.0015, leave_after: None };
        let markers: Vec<Vec<Marker>> = (0..40).map(|s| c.script.markers_at(&c, s as f64 * c.dt)).collect();
        let mut single = GpuSurface::new(ctx.clone(), &c).unwrap();
        let single_stats: Vec<StepStats> = markers.iter().map(|m| single.step(m).unwrap()).collect();
        let mut batched = GpuSurface::new(ctx.clone(), &c).unwrap();
        let start = ctx.counters();
        let mut batched_stats = Vec::new();
        let mut first = 0;
        for n in [1, 3, 8, 13, 15] {
            batched_stats.extend(batched.step_batch(&markers[first..first + n]).unwrap());
            first += n;
        }
        let counted = ctx.counters().since(&start);
        assert_eq!((counted.submissions, counted.readbacks), (5, 0));
        assert_eq!(batched_stats, single_stats);
        let b = batched.read_deviations().unwrap();
        let counted = ctx.counters().since(&start);
        assert_eq!((counted.readbacks, counted.bytes_read_back), (1, 83 * 61 * 4));
        let a = single.read_deviations().unwrap();
        assert!(a.iter().fold(0.0f32, |m, u| m.max(u.abs())) > 5e-4, "markers engraved too little");
        assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()), "batched state differs");
    }

    #[test]
    fn an_empty_batch_is_refused() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let c = DpcmConfig::preset("water").unwrap();
        let mut gpu = GpuSurface::new(ctx, &c).unwrap();
        let none: [&[Marker]; 0] = [];
        assert!(matches!(gpu.step_batch(&none), Err(GpuDpcmError::EmptyBatch)));
    }
}
