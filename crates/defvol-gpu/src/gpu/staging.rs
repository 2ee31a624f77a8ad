//! A read-back on its way: the copy into a mappable staging buffer submitted, the buffer
//! asked to map, and the host waiting for that submission alone when it needs the bytes.
//! Shared by the context's read-backs and the timer's query read; the context keeps its
//! staging buffers between read-backs in a [`StagingPool`].

use rayon::prelude::*;
use std::sync::Mutex;

/// A read-back on its way: its copy submitted and its staging buffer asked to map.
pub struct PendingRead {
    staging: wgpu::Buffer,
    submission: wgpu::SubmissionIndex,
    mapped: std::sync::mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>,
}

impl PendingRead {
    /// Asks `staging` (MAP_READ), written by `submission`, to map.
    pub(super) fn map(staging: wgpu::Buffer, submission: wgpu::SubmissionIndex) -> Self {
        let (tx, mapped) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        Self { staging, submission, mapped }
    }

    /// Waits for its own submission (not for what was queued behind it), copies the
    /// staging buffer's bytes, in order, into `outs` (each takes as many as it holds) and
    /// hands the buffer back, unmapped, for the next read.
    pub(super) fn wait_into(self, device: &wgpu::Device, outs: &mut [&mut [u8]]) -> Result<wgpu::Buffer, String> {
        let wait = wgpu::PollType::Wait { submission_index: Some(self.submission), timeout: None };
        device.poll(wait).map_err(|e| e.to_string())?;
        self.mapped.recv().map_err(|e| e.to_string())?.map_err(|e| e.to_string())?;
        let range = self.staging.get_mapped_range(..).map_err(|e| e.to_string())?;
        let mut at = 0;
        for out in outs.iter_mut() {
            copy_parallel(out, &range[at..at + out.len()]);
            at += out.len();
        }
        drop(range);
        self.staging.unmap();
        Ok(self.staging)
    }
}

/// Copies over this many bytes are split across the threads: one core's memcpy out of
/// mapped memory (~10 GB/s) would be most of a large read-back's time.
const PARALLEL_COPY_BYTES: usize = 4 << 20;

/// The piece of a split copy one task takes.
const COPY_CHUNK_BYTES: usize = 1 << 20;

/// `out.copy_from_slice(from)`, on every thread where it is large.
fn copy_parallel(out: &mut [u8], from: &[u8]) {
    if out.len() < PARALLEL_COPY_BYTES {
        out.copy_from_slice(from);
        return;
    }
    out.par_chunks_mut(COPY_CHUNK_BYTES).zip(from.par_chunks(COPY_CHUNK_BYTES)).for_each(|(o, f)| o.copy_from_slice(f));
}

/// Staging buffers kept between read-backs. Pinned host memory is slow to allocate, far
/// slower than the copies it holds (see docs/perf/journal.md#staging-buffers-kept).
#[derive(Default)]
pub(super) struct StagingPool {
    free: Mutex<Vec<wgpu::Buffer>>,
}

/// Buffers the pool keeps; past it the smallest is let go (the large ones cost the most to
/// make again).
const KEPT: usize = 4;

impl StagingPool {
    /// The smallest free buffer of at least `size` bytes, or a new one.
    pub(super) fn take(&self, device: &wgpu::Device, size: u64) -> wgpu::Buffer {
        let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        let fits = free.iter().enumerate().filter(|(_, b)| b.size() >= size).min_by_key(|(_, b)| b.size());
        match fits.map(|(i, _)| i) {
            Some(i) => free.swap_remove(i),
            None => device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("read-back"),
                size: size.max(4),
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
        }
    }

    /// Keeps `buffer` (unmapped) for a later read.
    pub(super) fn give(&self, buffer: wgpu::Buffer) {
        let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        free.push(buffer);
        if free.len() > KEPT {
            if let Some(i) = free.iter().enumerate().min_by_key(|(_, b)| b.size()).map(|(i, _)| i) {
                free.swap_remove(i);
            }
        }
    }

    /// Buffers kept now.
    #[cfg(test)]
    pub(super) fn kept(&self) -> Vec<u64> {
        self.free.lock().unwrap_or_else(|e| e.into_inner()).iter().map(wgpu::Buffer::size).collect()
    }
}
