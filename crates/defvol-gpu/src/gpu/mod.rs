//! wgpu plumbing shared by every GPU stage: adapter choice, kernels, buffers, read-back,
//! node positions on the device. It knows no stage: each stage's host code and shader live
//! in the stage's own folder and build on this.
//!
//! Adapter policy: a hardware GPU runs the GPU path; a CPU adapter (llvmpipe/lavapipe) only
//! when the caller allows it (tests do). Only Vulkan, Metal and DX12 are asked for: the GL
//! backend lacks what compute needs here. The device is opened with the adapter's own
//! limits; each stage checks the limits it needs ([`GpuContext::require_storage_buffers`],
//! [`GpuContext::require_binding_size`]).

pub mod nodes;
mod staging;
pub mod timing;

pub use nodes::DeviceNodes;
pub use staging::PendingRead;
pub use timing::{GpuTimes, Timestamps};

use staging::StagingPool;
use timing::{SpanKind, Timer};

use std::sync::atomic::{AtomicU64, Ordering};

use wgpu::util::DeviceExt;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GpuError {
    #[error("no GPU adapter found (Vulkan, Metal or DX12){0}")]
    NoAdapter(String),
    #[error("cannot open the GPU device {adapter}: {message}")]
    Device { adapter: String, message: String },
    #[error("the GPU adapter {adapter} allows {got} storage buffers per shader stage; {what} needs {needed}")]
    StorageBuffers { adapter: String, what: &'static str, got: u32, needed: u32 },
    #[error("{what} needs {needed_mib} MiB in one GPU buffer; the adapter {adapter} allows {limit_mib} MiB")]
    BufferTooLarge { adapter: String, what: &'static str, needed_mib: u64, limit_mib: u64 },
    #[error("reading results back from the GPU failed: {0}")]
    Readback(String),
}

/// The most workgroups one dimension of a dispatch may have.
pub const MAX_GROUPS: u32 = 65_535;

/// A dispatch of `count` invocations in workgroups of `workgroup` threads, as (x, y)
/// groups with x at most [`MAX_GROUPS`]; a kernel's linear index is
/// `gid.x + gid.y * x * workgroup`.
pub fn groups_2d(count: u32, workgroup: u32) -> (u32, u32) {
    let groups = count.div_ceil(workgroup).max(1);
    let x = groups.min(MAX_GROUPS);
    (x, groups.div_ceil(x))
}

/// How a kernel binds one buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Binding {
    Uniform,
    /// A uniform block picked per dispatch by a dynamic offset (a [`Blocks`] buffer): the
    /// steps of a batch share one bind group and each reads its own block.
    DynamicUniform,
    Read,
    ReadWrite,
}

/// Uniform blocks of one type in one buffer, each at an offset the device takes as a
/// dynamic offset, so one bind group serves every dispatch of a batch.
pub struct Blocks {
    pub buffer: wgpu::Buffer,
    stride: u64,
    block: u64,
    len: usize,
}

impl Blocks {
    /// The binding of one block (the dynamic offset picks which).
    pub fn binding(&self) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.buffer,
            offset: 0,
            size: wgpu::BufferSize::new(self.block),
        })
    }

    /// The dynamic offset of block `k`.
    pub fn offset(&self, k: usize) -> u32 {
        debug_assert!(k < self.len);
        // Fits: `GpuContext::blocks` refused buffers past u32 offsets.
        (k as u64 * self.stride) as u32
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// A WGSL module's bind-group layout (bindings 0.. of group 0) and its compute pipelines,
/// one per entry point, in the order asked.
pub struct Kernels<const N: usize> {
    pub layout: wgpu::BindGroupLayout,
    pub pipelines: [wgpu::ComputePipeline; N],
}

/// Which adapters may run the GPU path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdapterPolicy {
    /// Hardware GPUs only.
    HardwareOnly,
    /// Hardware first, a software (CPU) adapter if that is all there is.
    AllowSoftware,
}

/// A device and queue with the adapter's description, counting the round trips every
/// stage makes through it.
pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub adapter_info: wgpu::AdapterInfo,
    counters: [AtomicU64; 3],
    /// Timestamp queries, where the adapter offers them.
    timer: Option<Timer>,
    /// Read-backs' staging buffers, kept for the next read.
    staging: StagingPool,
}

/// What the plumbing counted since the context was opened: queue submissions, blocking
/// read-backs, and the bytes those brought back. A stage's cost on a real GPU is mostly
/// these round trips, which a software adapter counts as faithfully as a GPU.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GpuCounters {
    pub submissions: u64,
    pub readbacks: u64,
    pub bytes_read_back: u64,
}

impl GpuCounters {
    /// What happened between `earlier` and `self`.
    pub fn since(&self, earlier: &GpuCounters) -> GpuCounters {
        GpuCounters {
            submissions: self.submissions - earlier.submissions,
            readbacks: self.readbacks - earlier.readbacks,
            bytes_read_back: self.bytes_read_back - earlier.bytes_read_back,
        }
    }
}

impl GpuContext {
    /// Opens the best allowed adapter (see the module's adapter policy).
    pub fn open(policy: AdapterPolicy) -> Result<Self, GpuError> {
        pollster::block_on(Self::new_async(policy, true))
    }

    /// [`GpuContext::open`] without timestamp queries, as on an adapter that has none
    /// (GPU time then reads "unavailable").
    pub fn open_without_timestamps(policy: AdapterPolicy) -> Result<Self, GpuError> {
        pollster::block_on(Self::new_async(policy, false))
    }

    async fn new_async(policy: AdapterPolicy, timestamps: bool) -> Result<Self, GpuError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
        desc.flags = wgpu::InstanceFlags::empty().with_env();
        let instance = wgpu::Instance::new(desc);
        let adapters = instance.enumerate_adapters(desc_backends()).await;
        let rank = |a: &wgpu::Adapter| match a.get_info().device_type {
            wgpu::DeviceType::DiscreteGpu => 0,
            wgpu::DeviceType::IntegratedGpu => 1,
            wgpu::DeviceType::VirtualGpu | wgpu::DeviceType::Other => 2,
            wgpu::DeviceType::Cpu => 3,
        };
        let seen: Vec<String> =
            adapters.iter().map(|a| format!("{} ({:?})", a.get_info().name, a.get_info().device_type)).collect();
        let Some(adapter) = adapters
            .into_iter()
            .filter(|a| policy == AdapterPolicy::AllowSoftware || a.get_info().device_type != wgpu::DeviceType::Cpu)
            .min_by_key(rank)
        else {
            let detail = if seen.is_empty() {
                String::new()
            } else {
                format!("; only software adapters, not allowed: {}", seen.join(", "))
            };
            return Err(GpuError::NoAdapter(detail));
        };
        let info = adapter.get_info();
        let limits = adapter.limits();
        let timestamps = match timestamps {
            true => wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS,
            false => wgpu::Features::empty(),
        };
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("defvol"),
                required_features: adapter.features() & timestamps,
                required_limits: limits,
                experimental_features: wgpu::ExperimentalFeatures::disabled(),
                memory_hints: wgpu::MemoryHints::Performance,
                trace: wgpu::Trace::Off,
            })
            .await
            .map_err(|e| GpuError::Device { adapter: info.name.clone(), message: e.to_string() })?;
        let timer = Timer::new(&device, &queue);
        Ok(Self {
            device,
            queue,
            adapter_info: info,
            counters: Default::default(),
            timer,
            staging: StagingPool::default(),
        })
    }

    /// Whether the adapter is a software one (lavapipe, llvmpipe): its timings say nothing
    /// of a GPU.
    pub fn is_software(&self) -> bool {
        self.adapter_info.device_type == wgpu::DeviceType::Cpu
    }

    /// An error unless a shader stage may bind `needed` storage buffers.
    pub fn require_storage_buffers(&self, what: &'static str, needed: u32) -> Result<(), GpuError> {
        let got = self.device.limits().max_storage_buffers_per_shader_stage;
        if got < needed {
            return Err(GpuError::StorageBuffers { adapter: self.adapter_info.name.clone(), what, got, needed });
        }
        Ok(())
    }

    /// An error unless one storage binding may hold `bytes`.
    pub fn require_binding_size(&self, what: &'static str, bytes: u64) -> Result<(), GpuError> {
        let limits = self.device.limits();
        let limit = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
        if bytes > limit {
            return Err(GpuError::BufferTooLarge {
                adapter: self.adapter_info.name.clone(),
                what,
                needed_mib: bytes.div_ceil(1 << 20),
                limit_mib: limit >> 20,
            });
        }
        Ok(())
    }

    /// "name (type, backend)", for logs and benchmark rows.
    pub fn describe(&self) -> String {
        format!("{} ({:?}, {:?})", self.adapter_info.name, self.adapter_info.device_type, self.adapter_info.backend)
    }

    /// Compiles `wgsl` and builds its layout from `bindings` and a pipeline per entry point.
    pub fn kernels<const N: usize>(
        &self,
        label: &str,
        wgsl: &str,
        bindings: &[Binding],
        entry_points: [&str; N],
    ) -> Kernels<N> {
        let device = &self.device;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(wgsl.into()),
        });
        let entries: Vec<wgpu::BindGroupLayoutEntry> = bindings
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupLayoutEntry {
                binding: i as u32,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: match b {
                        Binding::Uniform | Binding::DynamicUniform => wgpu::BufferBindingType::Uniform,
                        Binding::Read => wgpu::BufferBindingType::Storage { read_only: true },
                        Binding::ReadWrite => wgpu::BufferBindingType::Storage { read_only: false },
                    },
                    has_dynamic_offset: *b == Binding::DynamicUniform,
                    min_binding_size: None,
                },
                count: None,
            })
            .collect();
        let layout =
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor { label: Some(label), entries: &entries });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(label),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipelines = entry_points.map(|entry| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        });
        Kernels { layout, pipelines }
    }

    /// A bind group of `buffers` at bindings 0.. of `layout`.
    pub fn bind_group(
        &self,
        label: &str,
        layout: &wgpu::BindGroupLayout,
        buffers: &[&wgpu::Buffer],
    ) -> wgpu::BindGroup {
        let resources: Vec<wgpu::BindingResource> = buffers.iter().map(|b| b.as_entire_binding()).collect();
        self.bind_group_of(label, layout, resources)
    }

    /// A bind group of `resources` at bindings 0.. of `layout` (a [`Blocks`] binding among
    /// whole buffers).
    pub fn bind_group_of(
        &self,
        label: &str,
        layout: &wgpu::BindGroupLayout,
        resources: Vec<wgpu::BindingResource>,
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = resources
            .into_iter()
            .enumerate()
            .map(|(i, resource)| wgpu::BindGroupEntry { binding: i as u32, resource })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor { label: Some(label), layout, entries: &entries })
    }

    /// `blocks` as uniform blocks a dispatch picks by dynamic offset, each padded to the
    /// device's offset alignment; an error naming the limit when they do not fit one buffer.
    pub fn blocks<T: bytemuck::Pod>(&self, what: &'static str, blocks: &[T]) -> Result<Blocks, GpuError> {
        let limits = self.device.limits();
        let block = (std::mem::size_of::<T>() as u64).max(16);
        let stride = block.next_multiple_of(u64::from(limits.min_uniform_buffer_offset_alignment));
        let len = blocks.len().max(1);
        let bytes = stride * len as u64;
        let limit = limits.max_buffer_size.min(u64::from(u32::MAX));
        if block > limits.max_uniform_buffer_binding_size || bytes > limit {
            return Err(GpuError::BufferTooLarge {
                adapter: self.adapter_info.name.clone(),
                what,
                needed_mib: bytes.div_ceil(1 << 20),
                limit_mib: limit >> 20,
            });
        }
        let mut contents = vec![0u8; bytes as usize];
        for (k, b) in blocks.iter().enumerate() {
            let at = k * stride as usize;
            contents[at..at + std::mem::size_of::<T>()].copy_from_slice(bytemuck::bytes_of(b));
        }
        let buffer = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(what),
            contents: &contents,
            usage: wgpu::BufferUsages::UNIFORM,
        });
        Ok(Blocks { buffer, stride, block, len: blocks.len() })
    }

    pub fn storage_buffer(&self, label: &str, contents: &[u8]) -> wgpu::Buffer {
        self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
        })
    }

    /// Submits `commands` to the queue: every stage's work goes through here, counted.
    pub fn submit(&self, commands: wgpu::CommandBuffer) -> wgpu::SubmissionIndex {
        self.counters[0].fetch_add(1, Ordering::Relaxed);
        let submission = self.queue.submit([commands]);
        self.collect_timestamps_if_half_full();
        submission
    }

    /// The round trips so far.
    pub fn counters(&self) -> GpuCounters {
        let [submissions, readbacks, bytes] = &self.counters;
        GpuCounters {
            submissions: submissions.load(Ordering::Relaxed),
            readbacks: readbacks.load(Ordering::Relaxed),
            bytes_read_back: bytes.load(Ordering::Relaxed),
        }
    }

    /// Blocks until the queued work is done (for timing).
    pub fn wait(&self) {
        if let Err(e) = self.device.poll(wgpu::PollType::wait_indefinitely()) {
            tracing::warn!("waiting for the GPU failed: {e}");
        }
    }

    /// A zeroed storage buffer of `size` bytes (at least 4: wgpu refuses empty bindings).
    pub fn zeroed_buffer(&self, label: &str, size: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: size.max(4).next_multiple_of(4),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// Copies `size` bytes of `buffer` back to the host (blocking).
    pub fn read_back(&self, buffer: &wgpu::Buffer, size: u64) -> Result<Vec<u8>, GpuError> {
        let mut bytes = vec![0u8; size as usize];
        self.read_back_into(buffer, &mut bytes)?;
        Ok(bytes)
    }

    /// Copies the first `out.len()` bytes of `buffer` into `out` (blocking): through one
    /// staging buffer straight into the destination, e.g. a shared-memory sample.
    pub fn read_back_into(&self, buffer: &wgpu::Buffer, out: &mut [u8]) -> Result<(), GpuError> {
        if out.is_empty() {
            return Ok(());
        }
        let pending = self.read_back_later(&[(buffer, out.len() as u64)]);
        self.finish_read(pending, out)
    }

    /// Starts reading the first bytes of each buffer of `parts` back, one after another in
    /// one staging buffer: one submission, one read-back counted. The queue runs on, and
    /// more work may be submitted behind it, until [`GpuContext::finish_read`].
    pub fn read_back_later(&self, parts: &[(&wgpu::Buffer, u64)]) -> PendingRead {
        let encoder = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read-back") });
        self.submit_and_read(encoder, parts)
    }

    /// Submits `encoder`'s work with the copies of [`GpuContext::read_back_later`] behind
    /// it: the work and its read-back in one submission.
    pub fn submit_and_read(&self, mut encoder: wgpu::CommandEncoder, parts: &[(&wgpu::Buffer, u64)]) -> PendingRead {
        let size: u64 = parts.iter().map(|(_, bytes)| bytes).sum();
        self.counters[1].fetch_add(1, Ordering::Relaxed);
        self.counters[2].fetch_add(size, Ordering::Relaxed);
        let staging = self.staging.take(&self.device, size);
        let mut at = 0;
        for (buffer, bytes) in parts {
            self.copy_buffer(&mut encoder, buffer, 0, &staging, at, *bytes);
            at += bytes;
        }
        let submission = self.submit(encoder.finish());
        PendingRead::map(staging, submission)
    }

    /// Waits for `pending` (for its own submission, not for what was queued behind it)
    /// and copies its first `out.len()` bytes into `out`.
    pub fn finish_read(&self, pending: PendingRead, out: &mut [u8]) -> Result<(), GpuError> {
        self.finish_read_parts(pending, &mut [out])
    }

    /// As [`GpuContext::finish_read`], the parts of a read of several buffers each into its
    /// own destination (a volume into a shared-memory sample, its counters beside).
    pub fn finish_read_parts(&self, pending: PendingRead, outs: &mut [&mut [u8]]) -> Result<(), GpuError> {
        let staging = pending.wait_into(&self.device, outs).map_err(GpuError::Readback)?;
        self.staging.give(staging);
        Ok(())
    }
}

/// GPU time (see [`timing`]).
impl GpuContext {
    /// Whether GPU time can be measured on this adapter.
    pub fn timestamps(&self) -> Timestamps {
        match self.timer {
            Some(_) => Timestamps::Available,
            None => Timestamps::Unavailable,
        }
    }

    /// Turns timing on or off (off: passes and copies carry no queries).
    pub fn set_timing(&self, on: bool) {
        if let Some(timer) = &self.timer {
            timer.set_on(on);
        }
    }

    /// The timestamp writes for a compute pass: a span of kernel time while timing is on.
    pub fn pass_timestamps(&self) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        let timer = self.timer.as_ref()?;
        let first = timer.reserve(SpanKind::Kernel)?;
        Some(wgpu::ComputePassTimestampWrites {
            query_set: &timer.set,
            beginning_of_pass_write_index: Some(first),
            end_of_pass_write_index: Some(first + 1),
        })
    }

    /// `encoder.copy_buffer_to_buffer`, a span of copy time while timing is on and the
    /// adapter writes timestamps between commands.
    pub fn copy_buffer(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        from: &wgpu::Buffer,
        from_offset: u64,
        to: &wgpu::Buffer,
        to_offset: u64,
        size: u64,
    ) {
        let timer = self.timer.as_ref().filter(|t| t.between_commands);
        let span = timer.and_then(|t| Some((t, t.reserve(SpanKind::Copy)?)));
        if let Some((timer, first)) = span {
            encoder.write_timestamp(&timer.set, first);
        }
        encoder.copy_buffer_to_buffer(from, from_offset, to, to_offset, size);
        if let Some((timer, first)) = span {
            encoder.write_timestamp(&timer.set, first + 1);
        }
    }

    /// The GPU time since the last call (`None` where the adapter has no timestamps).
    /// Every span must have been submitted.
    pub fn take_times(&self) -> Result<Option<GpuTimes>, GpuError> {
        let Some(timer) = &self.timer else { return Ok(None) };
        timer.collect(&self.device, &self.queue).map_err(GpuError::Readback)?;
        timer.take_totals().map(Some).map_err(GpuError::Readback)
    }

    /// After a submission: reads the spans back once half the query set is used.
    fn collect_timestamps_if_half_full(&self) {
        if let Some(timer) = self.timer.as_ref().filter(|t| t.half_full()) {
            if let Err(e) = timer.collect(&self.device, &self.queue) {
                tracing::warn!("reading GPU timestamps failed: {e}");
            }
        }
    }
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe())
    }
}

/// The GPU tests' context, for every crate's agreement tests: any adapter, software
/// included; `None` (the test skips) when there is none, unless DEFVOL_REQUIRE_GPU is set
/// (tests/run.sh sets it), when it panics saying why.
pub fn test_context() -> Option<std::sync::Arc<GpuContext>> {
    match GpuContext::open(AdapterPolicy::AllowSoftware) {
        Ok(ctx) => Some(std::sync::Arc::new(ctx)),
        Err(e) if std::env::var_os("DEFVOL_REQUIRE_GPU").is_some() => {
            panic!("DEFVOL_REQUIRE_GPU is set but no adapter opened: {e}")
        }
        Err(e) => {
            eprintln!("skipping: no GPU adapter ({e})");
            None
        }
    }
}

fn desc_backends() -> wgpu::Backends {
    wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12
}

#[cfg(test)]
mod tests {
    use crate::gpu::{test_context, GpuCounters};

    #[test]
    fn the_plumbing_counts_each_submission_and_each_blocking_read_back_with_its_bytes() {
        let Some(ctx) = test_context() else { return };
        let start = ctx.counters();
        let buffer = ctx.storage_buffer("counted", &[7u8; 256]);
        let encoder = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("empty") });
        ctx.submit(encoder.finish());
        assert_eq!(ctx.counters().since(&start), GpuCounters { submissions: 1, readbacks: 0, bytes_read_back: 0 });
        // A read-back is one submission (its copy) and one blocking wait, of its bytes.
        assert_eq!(ctx.read_back(&buffer, 64).unwrap(), vec![7u8; 64]);
        assert_eq!(ctx.counters().since(&start), GpuCounters { submissions: 2, readbacks: 1, bytes_read_back: 64 });
        // Nothing asked, nothing counted.
        assert!(ctx.read_back(&buffer, 0).unwrap().is_empty());
        assert_eq!(ctx.counters().since(&start).readbacks, 1);
        // Work and its read-back in one submission: the copy sees the work done.
        let mut encoder = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("clear") });
        encoder.clear_buffer(&buffer, 0, Some(32));
        let pending = ctx.submit_and_read(encoder, &[(&buffer, 48)]);
        let mut bytes = [1u8; 48];
        ctx.finish_read(pending, &mut bytes).unwrap();
        assert_eq!((bytes[..32].to_vec(), bytes[32..].to_vec()), (vec![0u8; 32], vec![7u8; 16]));
        assert_eq!(ctx.counters().since(&start), GpuCounters { submissions: 3, readbacks: 2, bytes_read_back: 112 });
    }

    /// Read-backs keep their staging buffer: a large read (copied on every thread), then a
    /// small read and a two-part read through that same larger buffer, each give exactly
    /// its own buffers' bytes.
    #[test]
    fn read_backs_through_a_kept_staging_buffer_give_each_buffers_own_bytes() {
        let Some(ctx) = test_context() else { return };
        let large: Vec<u8> = (0..6u32 << 20).map(|i| (i % 251) as u8).collect();
        let (big, small) = (ctx.storage_buffer("large", &large), ctx.storage_buffer("small", &[9u8; 4096]));
        assert_eq!(ctx.read_back(&big, large.len() as u64).unwrap(), large);
        assert_eq!(ctx.staging.kept(), vec![large.len() as u64]);
        assert_eq!(ctx.read_back(&small, 4096).unwrap(), vec![9u8; 4096]);
        let pending = ctx.read_back_later(&[(&small, 100), (&big, 5 << 20)]);
        let (mut head, mut tail) = (vec![0u8; 100], vec![0u8; 5 << 20]);
        ctx.finish_read_parts(pending, &mut [&mut head, &mut tail]).unwrap();
        assert_eq!((head, &tail[..]), (vec![9u8; 100], &large[..5 << 20]));
        assert_eq!(ctx.staging.kept(), vec![large.len() as u64]);
    }
}
