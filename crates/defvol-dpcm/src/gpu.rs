//! The DPCM step on the GPU: `dpcm.wgsl` beside this file, one invocation per phyxel, markers binned
//! on the CPU (the same [`MarkerBins`] as the CPU path) and gathered per tile.
//!
//! Z(n+1), Z(n) and Z(n-1) live in three buffers that rotate, so a step uploads only the
//! markers and reads nothing back.

use std::collections::HashMap;
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};

use crate::kernels::{Coeffs, KernelMarker, TILE};
use crate::{to_kernel_markers, DpcmConfig, DpcmError, Marker, MarkerBins, StepStats, Surface};
use defvol_gpu::gpu::{GpuContext, GpuError, Kernels};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GpuDpcmError {
    #[error(transparent)]
    Dpcm(#[from] DpcmError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
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
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
    bind_groups: Vec<wgpu::BindGroup>,
    bins: MarkerBins,
    marker_heights: HashMap<u32, f32>,
    phyxels: usize,
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
        use defvol_gpu::gpu::Binding::{Read, ReadWrite, Uniform};
        let Kernels { layout, pipelines: [pipeline] } = ctx.kernels(
            "dpcm.wgsl",
            include_str!("dpcm.wgsl"),
            &[Uniform, Read, Read, ReadWrite, ReadWrite, Read, Read, Read, Read, Read],
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
            layout,
            pipeline,
            bind_groups: Vec::new(),
            bins: MarkerBins::default(),
            marker_heights: HashMap::new(),
            phyxels,
        };
        gpu.rebuild_bind_groups();
        Ok(gpu)
    }

    /// One bind group per rotation of the three height buffers.
    fn rebuild_bind_groups(&mut self) {
        self.bind_groups = (0..3)
            .map(|r| {
                let (z, out, zp) = (&self.heights[r], &self.heights[(r + 1) % 3], &self.heights[(r + 2) % 3]);
                self.ctx.bind_group(
                    "dpcm",
                    &self.layout,
                    &[
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
                    ],
                )
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
    pub fn step(&mut self, markers: &[Marker]) -> StepStats {
        let (kernel_markers, mut stats) = to_kernel_markers(&self.config, &mut self.marker_heights, markers);
        stats.markers_off_grid = self.bins.build(kernel_markers, self.config.width, self.config.height);
        stats.markers_applied -= stats.markers_off_grid;
        let bins = std::mem::take(&mut self.bins);
        self.upload(|s| &mut s.markers, "dpcm markers", &bins.markers);
        self.upload(|s| &mut s.offsets, "dpcm tile offsets", &bins.offsets);
        self.upload(|s| &mut s.indices, "dpcm tile indices", &bins.indices);
        self.bins = bins;
        let mut encoder =
            self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("dpcm step") });
        {
            let mut pass = encoder
                .begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("dpcm step"), timestamp_writes: None });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &self.bind_groups[self.current], &[]);
            pass.dispatch_workgroups(
                self.config.width.div_ceil(TILE) as u32,
                self.config.height.div_ceil(TILE) as u32,
                1,
            );
        }
        self.ctx.submit(encoder.finish());
        self.current = (self.current + 1) % 3;
        stats
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
                let b = gpu.step(&markers);
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
            gpu.step(&[]);
        }
        assert!(gpu.read_heights().unwrap().iter().all(|&z| z == 0.0037_f32));
    }

    /// Today's round trips, the baseline batching is measured against: a step is one
    /// submission and nothing comes back until asked.
    #[test]
    fn a_gpu_step_is_one_submission_and_reading_the_heights_one_read_back() {
        let Some(ctx) = defvol_gpu::gpu::test_context() else { return };
        let mut c = DpcmConfig::preset("water").unwrap();
        (c.width, c.height) = (48, 40);
        c.script = Script { markers: 3, pattern: Pattern::Wander, speed: 0.15, depth: 0.0015, leave_after: None };
        let mut gpu = GpuSurface::new(ctx.clone(), &c).unwrap();
        let start = ctx.counters();
        for step in 0..10 {
            gpu.step(&c.script.markers_at(&c, step as f64 * c.dt));
        }
        let counted = ctx.counters().since(&start);
        assert_eq!((counted.submissions, counted.readbacks), (10, 0));
        gpu.read_heights().unwrap();
        let counted = ctx.counters().since(&start);
        assert_eq!((counted.readbacks, counted.bytes_read_back), (1, 48 * 40 * 4));
    }
}
