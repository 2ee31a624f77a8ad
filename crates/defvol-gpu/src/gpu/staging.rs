//! A read-back on its way: the copy into a mappable staging buffer submitted, the buffer
//! asked to map, and the host waiting for that submission alone when it needs the bytes.
//! Shared by the context's read-backs and the timer's query read.

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

    /// Waits for its own submission (not for what was queued behind it) and copies the
    /// staging buffer's bytes, in order, into `outs` (each takes as many as it holds).
    pub(super) fn wait_into(self, device: &wgpu::Device, outs: &mut [&mut [u8]]) -> Result<(), String> {
        let wait = wgpu::PollType::Wait { submission_index: Some(self.submission), timeout: None };
        device.poll(wait).map_err(|e| e.to_string())?;
        self.mapped.recv().map_err(|e| e.to_string())?.map_err(|e| e.to_string())?;
        let range = self.staging.get_mapped_range(..).map_err(|e| e.to_string())?;
        let mut at = 0;
        for out in outs.iter_mut() {
            out.copy_from_slice(&range[at..at + out.len()]);
            at += out.len();
        }
        drop(range);
        self.staging.unmap();
        Ok(())
    }
}
