//! The recording on a thread of its own: the caller only encodes CDR and hands the bytes
//! over, so chunk compression, splits and disk writes never stall the loop that records.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, RecvTimeoutError, SyncSender};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use super::bag::{RecordError, RecordSummary};
use super::bag_dir::Bag;
use super::{BagOptions, Qos};
use crate::msgs::{self, Message};

/// A recorder on its own thread: the caller only encodes CDR and hands the bytes over,
/// so chunk compression and disk writes never stall the loop that records.
pub struct BagThread {
    path: PathBuf,
    queue: Option<SyncSender<Entry>>,
    thread: Option<JoinHandle<Result<RecordSummary, RecordError>>>,
    failure: Arc<Mutex<Option<String>>>,
}

struct Entry {
    topic: String,
    type_name: &'static str,
    qos: Qos,
    data: Vec<u8>,
    log_time_ns: u64,
}

/// Messages waiting for the writer thread before `write` waits for it.
const QUEUE: usize = 4096;

impl BagThread {
    /// A recording at `path` (one `.mcap` file, else a bag directory) on its own thread.
    pub fn create(path: &Path, options: BagOptions) -> Result<Self, RecordError> {
        let mut bag = Bag::create(path, options)?;
        let failure = Arc::new(Mutex::new(None));
        let (queue, entries) = mpsc::sync_channel::<Entry>(QUEUE);
        let failed = failure.clone();
        let thread = std::thread::Builder::new()
            .name("defvol-record".into())
            .spawn(move || {
                crate::pipeline::priority::into_background("the recorder");
                let note = |outcome: Result<(), RecordError>| {
                    if let (Err(error), Ok(mut slot)) = (outcome, failed.lock()) {
                        // The cause alone: the errors made of it name the file.
                        let cause = match error {
                            RecordError::File { message, .. } | RecordError::Stopped { first: message, .. } => message,
                            other => other.to_string(),
                        };
                        slot.get_or_insert(cause);
                    }
                };
                loop {
                    // Woken by a message or by the flush interval, whichever comes first.
                    match entries.recv_timeout(options.flush_interval) {
                        Ok(e) if bag.failure().is_none() => {
                            note(bag.write_encoded(&e.topic, e.type_name, e.qos, &e.data, e.log_time_ns));
                        }
                        Ok(_) | Err(RecvTimeoutError::Timeout) => {}
                        Err(RecvTimeoutError::Disconnected) => break,
                    }
                    if bag.failure().is_none() {
                        note(bag.flush_if_due());
                    }
                }
                bag.finish()
            })
            .map_err(|e| RecordError::File { path: path.to_owned(), message: format!("recording thread: {e}") })?;
        Ok(Self { path: path.to_owned(), queue: Some(queue), thread: Some(thread), failure })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The error that stopped the recording, if one did.
    pub fn failure(&self) -> Option<String> {
        self.failure.lock().ok().and_then(|f| f.clone())
    }

    pub fn write<T: Message>(&self, topic: &str, qos: Qos, msg: &T, log_time_ns: u64) -> Result<(), RecordError> {
        if let Some(first) = self.failure() {
            return Err(RecordError::Stopped { path: self.path.clone(), first });
        }
        let entry = Entry { topic: topic.to_owned(), type_name: T::NAME, qos, data: msgs::encode(msg)?, log_time_ns };
        let sent = self.queue.as_ref().map(|q| q.send(entry));
        match sent {
            Some(Ok(())) => Ok(()),
            _ => Err(RecordError::Stopped { path: self.path.clone(), first: "the recording thread ended".into() }),
        }
    }

    /// Waits for the writer to drain the queue, then closes the file.
    pub fn finish(mut self) -> Result<RecordSummary, RecordError> {
        drop(self.queue.take());
        let Some(thread) = self.thread.take() else {
            return Err(RecordError::Stopped { path: self.path.clone(), first: "finished twice".into() });
        };
        thread.join().map_err(|_| RecordError::File {
            path: self.path.clone(),
            message: "the recording thread panicked".into(),
        })?
    }
}

impl Drop for BagThread {
    fn drop(&mut self) {
        // Dropped without `finish` (an error path): the file is still closed properly.
        drop(self.queue.take());
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::msgs::{self, Header, PoseStamped, Time};
    use crate::record::bag::{read_messages, RecordSummary};
    use crate::record::bag_thread::BagThread;
    use crate::record::{BagOptions, Qos};

    fn pose(t: f64, x: f64) -> PoseStamped {
        let mut msg = PoseStamped {
            header: Header { stamp: Time::from_secs(t), frame_id: "world".into() },
            ..Default::default()
        };
        msg.pose.position.x = x;
        msg
    }

    #[test]
    fn the_recording_thread_writes_what_it_is_handed_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.mcap");
        let rec = BagThread::create(&path, BagOptions::default()).unwrap();
        for i in 0..2000u64 {
            rec.write("/tool_pose", Qos::SensorData, &pose(i as f64 * 1e-3, i as f64), i * 1_000_000).unwrap();
        }
        assert_eq!(rec.finish().unwrap(), RecordSummary { messages: 2000, channels: 1 });
        let read = read_messages(&path, &[]).unwrap();
        assert_eq!(read.len(), 2000);
        assert_eq!(msgs::decode::<PoseStamped>(&read[1234].data, "t").unwrap(), pose(1.234, 1234.0));
    }

    #[test]
    fn what_was_handed_over_reaches_the_file_within_the_flush_interval() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("open.mcap");
        let options = BagOptions { flush_interval: std::time::Duration::from_millis(50), ..Default::default() };
        let rec = BagThread::create(&path, options).unwrap();
        for i in 0..100u64 {
            rec.write("/tool_pose", Qos::SensorData, &pose(i as f64 * 1e-3, i as f64), i * 1_000_000).unwrap();
        }
        std::thread::sleep(std::time::Duration::from_millis(400));
        // Still open (no summary, no footer), yet every message is on disk in a whole chunk.
        let read = read_messages(&path, &[]).unwrap();
        assert_eq!(read.len(), 100);
        assert_eq!(msgs::decode::<PoseStamped>(&read[99].data, "t").unwrap(), pose(0.099, 99.0));
        rec.finish().unwrap();
    }
}
