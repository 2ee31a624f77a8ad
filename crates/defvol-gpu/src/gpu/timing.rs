//! Where GPU time goes: when timing is on and the adapter offers timestamp queries, every
//! compute pass a stage begins with the context's `pass_timestamps` is bracketed by two
//! queries, and every copy through its `copy_buffer` too where the adapter writes
//! timestamps between commands. The spans are summed per kind. Timing is off by default, so
//! the node never pays for it; a benchmark turns it on around what it times.
//!
//! Reading the queries back is the profiler's own round trip: it is not counted with the
//! stages' round trips, and it happens only when half the query set is used (at a
//! submission) or when the times are taken.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use super::staging::PendingRead;

/// Queries in the set: WebGPU's most (`wgpu::QUERY_SET_MAX_QUERIES`), two a span.
const QUERIES: u32 = wgpu::QUERY_SET_MAX_QUERIES;

/// Whether this adapter measures GPU time, as benchmark rows state it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timestamps {
    Available,
    Unavailable,
}

impl Timestamps {
    pub fn name(self) -> &'static str {
        match self {
            Self::Available => "available",
            Self::Unavailable => "unavailable",
        }
    }
}

/// GPU time summed over the spans measured since the times were last taken.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GpuTimes {
    pub kernel_ms: f64,
    pub copy_ms: f64,
    pub kernel_spans: u64,
    pub copy_spans: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum SpanKind {
    Kernel,
    Copy,
}

/// The query set, where it resolves to, and the spans written and not yet read.
pub(super) struct Timer {
    pub(super) set: wgpu::QuerySet,
    resolved: wgpu::Buffer,
    staging: wgpu::Buffer,
    period_ns: f64,
    pub(super) between_commands: bool,
    on: AtomicBool,
    state: Mutex<TimerState>,
}

#[derive(Default)]
struct TimerState {
    /// Each span's kind and first query (its end is the next).
    spans: Vec<(SpanKind, u32)>,
    next: u32,
    totals: GpuTimes,
}

impl Timer {
    /// A timer for `device`, when its features include timestamp queries.
    pub(super) fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Option<Self> {
        let features = device.features();
        if !features.contains(wgpu::Features::TIMESTAMP_QUERY) {
            return None;
        }
        let set = device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: QUERIES,
        });
        let bytes = u64::from(QUERIES) * 8;
        let buffer = |label, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage,
                mapped_at_creation: false,
            })
        };
        Some(Self {
            set,
            resolved: buffer("timestamps resolved", wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC),
            staging: buffer("timestamps read", wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST),
            period_ns: f64::from(queue.get_timestamp_period()),
            between_commands: features.contains(wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS),
            on: AtomicBool::new(false),
            state: Mutex::new(TimerState::default()),
        })
    }

    pub(super) fn set_on(&self, on: bool) {
        self.on.store(on, Ordering::Relaxed);
    }

    /// Two queries for a span of `kind`, if timing is on and the set has room.
    pub(super) fn reserve(&self, kind: SpanKind) -> Option<u32> {
        if !self.on.load(Ordering::Relaxed) {
            return None;
        }
        let mut state = self.state.lock().ok()?;
        if state.next + 2 > QUERIES {
            return None;
        }
        let first = state.next;
        state.next += 2;
        state.spans.push((kind, first));
        Some(first)
    }

    /// Whether half the set is used; checked at every submission, so without a lock
    /// while timing is off (nothing is reserved then).
    pub(super) fn half_full(&self) -> bool {
        self.on.load(Ordering::Relaxed) && self.state.lock().map(|s| s.next >= QUERIES / 2).unwrap_or(false)
    }

    /// Resolves the written queries, reads them back (waiting for the queue) and adds their
    /// spans to the totals. Every span must have been submitted.
    pub(super) fn collect(&self, device: &wgpu::Device, queue: &wgpu::Queue) -> Result<(), String> {
        let mut state = self.state.lock().map_err(|e| e.to_string())?;
        if state.next == 0 {
            return Ok(());
        }
        let bytes = u64::from(state.next) * 8;
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("timestamps") });
        encoder.resolve_query_set(&self.set, 0..state.next, &self.resolved, 0);
        encoder.copy_buffer_to_buffer(&self.resolved, 0, &self.staging, 0, bytes);
        let submission = queue.submit([encoder.finish()]);
        let mut read = vec![0u8; bytes as usize];
        PendingRead::map(self.staging.clone(), submission).wait_into(device, &mut [&mut read])?;
        let ticks: Vec<u64> = bytemuck::pod_collect_to_vec(&read);
        let ms = |first: u32| {
            let (begin, end) = (ticks[first as usize], ticks[first as usize + 1]);
            end.saturating_sub(begin) as f64 * self.period_ns * 1e-6
        };
        let spans = std::mem::take(&mut state.spans);
        for (kind, first) in spans {
            let totals = &mut state.totals;
            match kind {
                SpanKind::Kernel => {
                    (totals.kernel_ms, totals.kernel_spans) = (totals.kernel_ms + ms(first), totals.kernel_spans + 1)
                }
                SpanKind::Copy => {
                    (totals.copy_ms, totals.copy_spans) = (totals.copy_ms + ms(first), totals.copy_spans + 1)
                }
            }
        }
        state.next = 0;
        Ok(())
    }

    /// The totals since the last call.
    pub(super) fn take_totals(&self) -> Result<GpuTimes, String> {
        let mut state = self.state.lock().map_err(|e| e.to_string())?;
        Ok(std::mem::take(&mut state.totals))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::{test_context, Binding};

    const BUSY: &str = "
        @group(0) @binding(0) var<storage, read_write> out: array<f32>;
        @compute @workgroup_size(64)
        fn busy(@builtin(global_invocation_id) id: vec3<u32>) {
            var x = f32(id.x);
            for (var k = 0u; k < 2000u; k++) { x = fract(x * 1.0001 + 0.37); }
            out[id.x] = x;
        }";

    /// One timed pass of a busy kernel and one timed read-back copy: one span of each, the
    /// kernel's no longer than the wall time around its submission; nothing while timing is
    /// off.
    #[test]
    fn timed_passes_and_copies_are_spans_within_their_wall_time_and_nothing_is_timed_when_off() {
        let Some(ctx) = test_context() else { return };
        let Some(_) = ctx.timer.as_ref() else {
            assert_eq!(ctx.timestamps(), Timestamps::Unavailable);
            assert!(ctx.take_times().unwrap().is_none());
            return;
        };
        let kernels = ctx.kernels("busy", BUSY, &[Binding::ReadWrite], ["busy"]);
        let out = ctx.zeroed_buffer("busy out", 64 * 1024 * 4);
        let group = ctx.bind_group("busy", &kernels.layout, &[&out]);
        let run = || {
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("busy"),
                    timestamp_writes: ctx.pass_timestamps(),
                });
                pass.set_pipeline(&kernels.pipelines[0]);
                pass.set_bind_group(0, &group, &[]);
                pass.dispatch_workgroups(1024, 1, 1);
            }
            let start = std::time::Instant::now();
            ctx.submit(encoder.finish());
            ctx.wait();
            let wall_ms = start.elapsed().as_secs_f64() * 1e3;
            ctx.read_back(&out, 16).unwrap();
            wall_ms
        };
        run();
        assert_eq!(ctx.take_times().unwrap(), Some(GpuTimes::default()), "timing is off by default");
        ctx.set_timing(true);
        let wall_ms = run();
        ctx.set_timing(false);
        let times = ctx.take_times().unwrap().unwrap();
        assert_eq!(times.kernel_spans, 1);
        assert!(times.kernel_ms > 0.0 && times.kernel_ms <= wall_ms, "kernel {} ms in {wall_ms} ms", times.kernel_ms);
        let between = ctx.device.features().contains(wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS);
        assert_eq!(times.copy_spans, u64::from(between));
        assert_eq!(ctx.timestamps(), Timestamps::Available);
    }

    /// Without timestamp queries the work runs as before and its time reads "unavailable":
    /// no span, no times, nothing refused.
    #[test]
    fn an_adapter_without_timestamps_runs_and_says_its_gpu_time_is_unavailable() {
        let Some(_) = test_context() else { return };
        let ctx = crate::gpu::GpuContext::open_without_timestamps(crate::gpu::AdapterPolicy::AllowSoftware).unwrap();
        assert_eq!(ctx.timestamps(), Timestamps::Unavailable);
        ctx.set_timing(true);
        assert!(ctx.pass_timestamps().is_none());
        let buffer = ctx.storage_buffer("plain", &[5u8; 64]);
        assert_eq!(ctx.read_back(&buffer, 64).unwrap(), vec![5u8; 64]);
        assert_eq!(ctx.take_times().unwrap(), None);
    }
}
