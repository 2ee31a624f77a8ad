//! Where a recording goes: one MCAP file (`x.mcap`), or a rosbag2 bag directory as
//! `ros2 bag record -o DIR` makes one: `DIR/DIR_0.mcap`, `DIR_1.mcap`, … split by duration
//! or size, and `metadata.yaml` in rosbag2's format, rewritten as each split closes (so a
//! crash leaves a bag of its closed splits that every reader opens). Either way the open
//! chunk is flushed at a bounded interval: a crash loses at most that much.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::bag::{RecordError, RecordSummary, Recorder};
use super::{BagOptions, Qos};

/// The split being written.
struct Split {
    recorder: Recorder,
    entry: FileEntry,
    /// Bytes handed to the open chunk since the last flush (not yet in the file's length).
    unflushed: u64,
}

/// A recording: one file, or a directory of splits.
pub struct Bag {
    path: PathBuf,
    /// The bag directory's name (its splits are `<name>_<index>.mcap`); none for one file.
    directory: Option<String>,
    options: BagOptions,
    split: Split,
    closed: Vec<FileEntry>,
    topics: BTreeMap<String, TopicEntry>,
    last_flush: Instant,
}

impl Bag {
    /// `path` ending in `.mcap` is one file; anything else a new bag directory (an existing
    /// one is refused: a bag is never recorded over).
    pub fn create(path: &Path, options: BagOptions) -> Result<Self, RecordError> {
        let directory = match path.extension() {
            Some(ext) if ext == "mcap" => None,
            _ => Some(bag_name(path)?),
        };
        if directory.is_some() {
            if path.exists() {
                return Err(RecordError::File {
                    path: path.to_owned(),
                    message: "already exists: a bag is never recorded over".into(),
                });
            }
            std::fs::create_dir_all(path)
                .map_err(|e| RecordError::File { path: path.to_owned(), message: format!("cannot create it: {e}") })?;
        }
        let first = match &directory {
            Some(name) => path.join(format!("{name}_0.mcap")),
            None => path.to_owned(),
        };
        let bag = Self {
            path: path.to_owned(),
            directory,
            options,
            split: open_split(&first)?,
            closed: Vec::new(),
            topics: BTreeMap::new(),
            last_flush: Instant::now(),
        };
        if bag.directory.is_some() {
            bag.write_metadata()?;
        }
        Ok(bag)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn failure(&self) -> Option<&str> {
        self.split.recorder.failure()
    }

    /// Records a CDR-encoded message, in a new split first when the open one is full.
    pub fn write_encoded(
        &mut self,
        topic: &str,
        type_name: &'static str,
        qos: Qos,
        data: &[u8],
        log_time_ns: u64,
    ) -> Result<(), RecordError> {
        // After a failure (a full disk) the recording stays stopped: no new split resumes it.
        if let Some(first) = self.failure() {
            return Err(RecordError::Stopped { path: self.path.clone(), first: first.to_owned() });
        }
        if self.split_is_full(log_time_ns)? {
            self.next_split()?;
        }
        self.split.recorder.write_encoded(topic, type_name, qos, data, log_time_ns)?;
        self.split.unflushed += data.len() as u64;
        self.split.entry.count(log_time_ns);
        let entry = self.topics.entry(topic.to_owned()).or_insert_with(|| TopicEntry::new(topic, type_name, qos));
        entry.message_count += 1;
        Ok(())
    }

    /// Writes the open chunk when the flush interval has passed since the last time.
    pub fn flush_if_due(&mut self) -> Result<(), RecordError> {
        if self.last_flush.elapsed() < self.options.flush_interval {
            return Ok(());
        }
        self.last_flush = Instant::now();
        self.split.unflushed = 0;
        self.split.recorder.flush()
    }

    /// Closes the last split (summary, footer) and, for a directory, writes the final
    /// `metadata.yaml`.
    pub fn finish(self) -> Result<RecordSummary, RecordError> {
        let Self { path, directory, split, mut closed, topics, .. } = self;
        let summary = split.recorder.finish()?;
        closed.push(split.entry);
        let messages = closed.iter().map(|f| f.message_count).sum();
        if directory.is_some() {
            write_metadata(&path, &closed, &topics)?;
        }
        Ok(RecordSummary { messages, channels: topics.len().max(summary.channels) })
    }

    /// Whether the open split of a directory has reached its duration or size (its file's
    /// length on disk, as rosbag2 measures it).
    fn split_is_full(&mut self, log_time_ns: u64) -> Result<bool, RecordError> {
        if self.directory.is_none() || self.split.entry.message_count == 0 {
            return Ok(false);
        }
        let long = self.options.max_duration.is_some_and(|max| {
            let span = log_time_ns.saturating_sub(self.split.entry.starting_time.nanoseconds_since_epoch);
            span >= u64::try_from(max.as_nanos()).unwrap_or(u64::MAX)
        });
        let Some(max) = self.options.max_bytes.filter(|_| !long) else { return Ok(long) };
        let on_disk = || std::fs::metadata(&self.split.entry.full_path).map_or(0, |m| m.len());
        // The open chunk adds at most its uncompressed bytes: only when that could reach the
        // limit is it written out and the file measured again.
        if on_disk() + self.split.unflushed < max {
            return Ok(false);
        }
        self.split.recorder.flush()?;
        self.split.unflushed = 0;
        Ok(on_disk() >= max)
    }

    /// Closes the open split, lists it in `metadata.yaml`, and opens the next.
    fn next_split(&mut self) -> Result<(), RecordError> {
        let name = self.directory.clone().unwrap_or_default();
        let index = self.closed.len() + 1;
        let next = open_split(&self.path.join(format!("{name}_{index}.mcap")))?;
        let done = std::mem::replace(&mut self.split, next);
        done.recorder.finish()?;
        self.closed.push(done.entry);
        self.write_metadata()
    }

    fn write_metadata(&self) -> Result<(), RecordError> {
        write_metadata(&self.path, &self.closed, &self.topics)
    }
}

/// A bag directory's name, as its splits are named after it.
fn bag_name(path: &Path) -> Result<String, RecordError> {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .filter(|n| !n.is_empty() && n != "." && n != "..")
        .ok_or_else(|| RecordError::File { path: path.to_owned(), message: "a bag directory needs a name".into() })
}

fn open_split(path: &Path) -> Result<Split, RecordError> {
    let recorder = Recorder::create(path)?;
    let relative = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    Ok(Split { recorder, entry: FileEntry::new(relative, path), unflushed: 0 })
}

/// `metadata.yaml` for the splits `files`, written whole and then moved into place, so a
/// reader never sees half of one.
pub fn write_metadata(
    dir: &Path,
    files: &[FileEntry],
    topics: &BTreeMap<String, TopicEntry>,
) -> Result<(), RecordError> {
    let text =
        metadata_yaml(files, topics).map_err(|e| RecordError::File { path: dir.join("metadata.yaml"), message: e })?;
    let tmp = dir.join("metadata.yaml.tmp");
    let failed = |e: std::io::Error| RecordError::File { path: dir.join("metadata.yaml"), message: e.to_string() };
    std::fs::write(&tmp, text).map_err(failed)?;
    std::fs::rename(&tmp, dir.join("metadata.yaml")).map_err(failed)
}

/// rosbag2's `metadata.yaml` (version 9, Jazzy's) for `files` and `topics`.
pub fn metadata_yaml(files: &[FileEntry], topics: &BTreeMap<String, TopicEntry>) -> Result<String, String> {
    let start = files.iter().filter(|f| f.message_count > 0).map(|f| f.starting_time.nanoseconds_since_epoch).min();
    let end = files.iter().filter(|f| f.message_count > 0).map(|f| f.end_ns()).max();
    let (start, end) = (start.unwrap_or(0), end.unwrap_or(0));
    let information = BagInformation {
        version: 9,
        storage_identifier: "mcap".into(),
        duration: Nanoseconds { nanoseconds: end.saturating_sub(start) },
        starting_time: SinceEpoch { nanoseconds_since_epoch: start },
        message_count: files.iter().map(|f| f.message_count).sum(),
        topics_with_message_count: topics.values().cloned().collect(),
        compression_format: String::new(),
        compression_mode: String::new(),
        relative_file_paths: files.iter().map(|f| f.path.clone()).collect(),
        files: files.to_vec(),
        custom_data: None,
        ros_distro: "jazzy".into(),
    };
    serde_yaml_ng::to_string(&Metadata { rosbag2_bagfile_information: information }).map_err(|e| e.to_string())
}

/// The top of `metadata.yaml`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Metadata {
    pub rosbag2_bagfile_information: BagInformation,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct BagInformation {
    pub version: u32,
    pub storage_identifier: String,
    pub duration: Nanoseconds,
    pub starting_time: SinceEpoch,
    pub message_count: u64,
    pub topics_with_message_count: Vec<TopicEntry>,
    pub compression_format: String,
    pub compression_mode: String,
    pub relative_file_paths: Vec<String>,
    pub files: Vec<FileEntry>,
    pub custom_data: Option<BTreeMap<String, String>>,
    pub ros_distro: String,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct Nanoseconds {
    pub nanoseconds: u64,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct SinceEpoch {
    pub nanoseconds_since_epoch: u64,
}

/// One split as `metadata.yaml` lists it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FileEntry {
    pub path: String,
    pub starting_time: SinceEpoch,
    pub duration: Nanoseconds,
    pub message_count: u64,
    /// Where the split is (not in the YAML).
    #[serde(skip)]
    pub full_path: PathBuf,
}

impl FileEntry {
    /// A split at `full_path`, listed as `path`, with no message yet.
    pub fn new(path: String, full_path: &Path) -> Self {
        Self {
            path,
            starting_time: SinceEpoch { nanoseconds_since_epoch: 0 },
            duration: Nanoseconds { nanoseconds: 0 },
            message_count: 0,
            full_path: full_path.to_owned(),
        }
    }

    /// Counts a message logged at `t` (ns).
    pub fn count(&mut self, t: u64) {
        if self.message_count == 0 {
            self.starting_time.nanoseconds_since_epoch = t;
        }
        let start = self.starting_time.nanoseconds_since_epoch.min(t);
        let end = self.end_ns().max(t);
        self.starting_time.nanoseconds_since_epoch = start;
        self.duration.nanoseconds = end - start;
        self.message_count += 1;
    }

    fn end_ns(&self) -> u64 {
        self.starting_time.nanoseconds_since_epoch + self.duration.nanoseconds
    }
}

/// One topic as `metadata.yaml` lists it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TopicEntry {
    pub topic_metadata: TopicMetadata,
    pub message_count: u64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TopicMetadata {
    pub name: String,
    #[serde(rename = "type")]
    pub type_name: String,
    pub serialization_format: String,
    /// rosbag2 keeps the profiles as YAML text inside the YAML.
    pub offered_qos_profiles: String,
    pub type_description_hash: String,
}

impl TopicEntry {
    pub fn new(topic: &str, type_name: &str, qos: Qos) -> Self {
        Self::with_profiles(topic, type_name, qos.offered_profiles_yaml())
    }

    /// A topic offered with `profiles` (rosbag2's YAML, as a channel's metadata holds it).
    pub fn with_profiles(topic: &str, type_name: &str, profiles: String) -> Self {
        Self {
            topic_metadata: TopicMetadata {
                name: topic.to_owned(),
                type_name: type_name.to_owned(),
                serialization_format: "cdr".into(),
                offered_qos_profiles: profiles,
                type_description_hash: String::new(),
            },
            message_count: 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use crate::msgs::{self, Header, Message, PoseStamped, Time};
    use crate::record::bag::read_messages;
    use crate::record::bag_dir::{Bag, Metadata};
    use crate::record::{BagOptions, Qos};

    /// `n` poses 10 ms apart from t = 100 s, each with a frame id of `noise` bytes that
    /// hardly compress (so that a file's size follows what is written).
    fn record(bag: &mut Bag, n: u64, noise: usize) {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for i in 0..n {
            let t = 100_000_000_000 + i * 10_000_000;
            let frame_id = (0..noise)
                .map(|_| {
                    state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
                    char::from(b'!' + ((state >> 33) % 94) as u8)
                })
                .collect();
            let msg = PoseStamped { header: Header { stamp: Time::from_nanos(t), frame_id }, ..Default::default() };
            let data = msgs::encode(&msg).unwrap();
            bag.write_encoded("/tool_pose", <PoseStamped as Message>::NAME, Qos::SensorData, &data, t).unwrap();
        }
    }

    fn metadata(dir: &std::path::Path) -> Metadata {
        serde_yaml_ng::from_str(&std::fs::read_to_string(dir.join("metadata.yaml")).unwrap()).unwrap()
    }

    #[test]
    fn a_bag_directory_splits_by_duration_and_lists_each_closed_split() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("session");
        let options = BagOptions { max_duration: Some(Duration::from_secs(1)), ..Default::default() };
        let mut bag = Bag::create(&dir, options).unwrap();
        record(&mut bag, 350, 4);
        // While recording, metadata.yaml lists the closed splits only: 0, 1 and 2.
        let listed = metadata(&dir).rosbag2_bagfile_information;
        assert_eq!(listed.relative_file_paths, ["session_0.mcap", "session_1.mcap", "session_2.mcap"]);
        assert_eq!(listed.message_count, 300);
        assert_eq!(bag.finish().unwrap().messages, 350);
        let info = metadata(&dir).rosbag2_bagfile_information;
        assert_eq!(info.relative_file_paths.len(), 4);
        assert_eq!((info.version, info.storage_identifier.as_str(), info.message_count), (9, "mcap", 350));
        assert_eq!(
            (info.starting_time.nanoseconds_since_epoch, info.duration.nanoseconds),
            (100_000_000_000, 3_490_000_000)
        );
        // Each split: 100 messages spanning 0.99 s (the 101st would reach 1 s), the last 50.
        for (index, file) in info.files.iter().enumerate() {
            let read = read_messages(&dir.join(&file.path), &[]).unwrap();
            let expected = if index < 3 { 100 } else { 50 };
            assert_eq!((read.len() as u64, file.message_count), (expected, expected), "{}", file.path);
            assert_eq!(file.starting_time.nanoseconds_since_epoch, read[0].log_time_ns);
            assert_eq!(file.duration.nanoseconds, read[read.len() - 1].log_time_ns - read[0].log_time_ns);
        }
        let topic = &info.topics_with_message_count[0];
        assert_eq!((topic.topic_metadata.name.as_str(), topic.message_count), ("/tool_pose", 350));
        assert_eq!(topic.topic_metadata.type_name, "geometry_msgs/msg/PoseStamped");
        // A bag is never recorded over.
        let again = Bag::create(&dir, options).err().unwrap().to_string();
        assert!(again.contains("already exists"), "{again}");
    }

    #[test]
    fn a_bag_directory_splits_by_size_once_each_file_reaches_the_size_asked() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("sized");
        let max = 64 * 1024;
        let options = BagOptions { max_bytes: Some(max), ..Default::default() };
        let mut bag = Bag::create(&dir, options).unwrap();
        // 400 messages of ~2 KiB: ~650 KiB compressed, about ten splits.
        record(&mut bag, 400, 2000);
        bag.finish().unwrap();
        let info = metadata(&dir).rosbag2_bagfile_information;
        let sizes: Vec<u64> = info.files.iter().map(|f| std::fs::metadata(dir.join(&f.path)).unwrap().len()).collect();
        assert!((8..=12).contains(&sizes.len()), "{sizes:?}");
        // Each closed split reached the limit and passed it by at most one message's chunk
        // and its summary.
        let (closed, last) = sizes.split_at(sizes.len() - 1);
        assert!(closed.iter().all(|s| (max..max + 6 * 1024).contains(s)), "{sizes:?}");
        assert!(last[0] < max + 6 * 1024, "{sizes:?}");
        let total: u64 = info.files.iter().map(|f| f.message_count).sum();
        assert_eq!(total, 400);
        let read: usize = info.files.iter().map(|f| read_messages(&dir.join(&f.path), &[]).unwrap().len()).sum();
        assert_eq!(read, 400);
    }
}
