//! `defvol bag recover`: a recording cut short (a crash, a kill, a full disk) rebuilt up to
//! its last whole record into a complete MCAP (chunks, message indexes, statistics, summary
//! and footer) every reader opens, as `mcap recover` and `ros2 bag reindex` do; a bag
//! directory's `metadata.yaml` regenerated from its splits. The cut file is kept beside the
//! rebuilt one (`x.mcap.cut`); an intact file is left as it is.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use mcap::records::{MessageHeader, Record};

use super::bag::{walk_records, RecordError};
use super::bag_dir::{write_metadata, FileEntry, TopicEntry};

/// What recovering one file did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FileOutcome {
    /// Whole already (summary and footer): untouched.
    Intact { messages: u64 },
    /// Rebuilt from its whole records; the cut original kept at `kept`.
    Rebuilt { messages: u64, kept: PathBuf },
}

/// What `recover` did, file by file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Recovery {
    pub files: Vec<(PathBuf, FileOutcome)>,
    /// The bag directory's regenerated `metadata.yaml`, if `path` was one.
    pub metadata: Option<PathBuf>,
}

/// Recovers `path`: one MCAP file, or every split of a bag directory and its metadata.
pub fn recover(path: &Path) -> Result<Recovery, RecordError> {
    if !path.is_dir() {
        let outcome = recover_file(path, false)?;
        return Ok(Recovery { files: vec![(path.to_owned(), outcome)], metadata: None });
    }
    let splits = splits_of(path)?;
    let mut files = Vec::new();
    for (i, split) in splits.iter().enumerate() {
        // The last split may be empty: the recorder was killed as it opened it.
        let open = i + 1 == splits.len();
        files.push((split.clone(), recover_file(split, open)?));
    }
    let (entries, topics) = describe_splits(&splits)?;
    write_metadata(path, &entries, &topics)?;
    Ok(Recovery { files, metadata: Some(path.join("metadata.yaml")) })
}

/// The `*.mcap` files of a bag directory in split order (`name_0.mcap`, `name_1.mcap`, …).
fn splits_of(dir: &Path) -> Result<Vec<PathBuf>, RecordError> {
    let read =
        std::fs::read_dir(dir).map_err(|e| RecordError::Read { path: dir.to_owned(), message: e.to_string() })?;
    let mut splits: Vec<PathBuf> =
        read.filter_map(Result::ok).map(|e| e.path()).filter(|p| p.extension().is_some_and(|e| e == "mcap")).collect();
    let index = |p: &PathBuf| {
        let stem = p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        stem.rsplit_once('_').and_then(|(_, i)| i.parse::<u64>().ok()).unwrap_or(u64::MAX)
    };
    splits.sort_by_key(|p| (index(p), p.clone()));
    if splits.is_empty() {
        return Err(RecordError::Read { path: dir.to_owned(), message: "no .mcap splits in this directory".into() });
    }
    Ok(splits)
}

/// Whether `bytes` end in a footer whose summary reads.
fn intact(bytes: &[u8]) -> bool {
    bytes.ends_with(mcap::MAGIC) && matches!(mcap::Summary::read(bytes), Ok(Some(_)))
}

/// One file: intact files are counted and left; cut ones rebuilt beside their original. An
/// empty file is refused, unless it is a bag's `open` split, which becomes an empty bag.
fn recover_file(path: &Path, open: bool) -> Result<FileOutcome, RecordError> {
    let bytes = std::fs::read(path).map_err(|e| RecordError::Read { path: path.to_owned(), message: e.to_string() })?;
    if intact(&bytes) {
        let messages = walk_records(path, &bytes, |_| Ok(()))?.messages;
        return Ok(FileOutcome::Intact { messages });
    }
    // Everything is read (and every error found) before anything is written.
    let contents = match bytes.is_empty() && open {
        true => Contents { profile: "ros2".into(), ..Default::default() },
        false => Contents::read(path, &bytes)?,
    };
    let rebuilding = path.with_extension("mcap.recovering");
    let written = contents.write(&rebuilding);
    let messages = match written {
        Ok(messages) => messages,
        Err(e) => {
            let _ = std::fs::remove_file(&rebuilding);
            return Err(e);
        }
    };
    let kept = unused(&path.with_extension("mcap.cut"));
    let moved = |from: &Path, to: &Path| {
        std::fs::rename(from, to).map_err(|e| RecordError::File { path: to.to_owned(), message: e.to_string() })
    };
    moved(path, &kept)?;
    moved(&rebuilding, path)?;
    Ok(FileOutcome::Rebuilt { messages, kept })
}

/// `path`, or `path.1`, `path.2`, … : the first name not taken.
fn unused(path: &Path) -> PathBuf {
    let mut candidate = path.to_owned();
    let mut n = 0;
    while candidate.exists() {
        n += 1;
        candidate = PathBuf::from(format!("{}.{n}", path.display()));
    }
    candidate
}

/// A bag's whole records: its profile, schemas, channels and messages.
#[derive(Default)]
struct Contents {
    profile: String,
    schemas: BTreeMap<u16, (String, String, Vec<u8>)>,
    channels: BTreeMap<u16, (u16, String, String, BTreeMap<String, String>)>,
    messages: Vec<(MessageHeader, Vec<u8>)>,
}

impl Contents {
    fn read(path: &Path, bytes: &[u8]) -> Result<Self, RecordError> {
        let mut contents = Self::default();
        walk_records(path, bytes, |record| {
            match record {
                Record::Header(header) => contents.profile = header.profile,
                Record::Schema { header, data } => {
                    contents.schemas.insert(header.id, (header.name, header.encoding, data.into_owned()));
                }
                Record::Channel(c) => {
                    contents.channels.insert(c.id, (c.schema_id, c.topic, c.message_encoding, c.metadata));
                }
                Record::Message { header, data } => contents.messages.push((header, data.into_owned())),
                _ => {}
            }
            Ok(())
        })?;
        Ok(contents)
    }

    /// Writes the records into a new, complete MCAP at `path`; the messages written.
    fn write(&self, path: &Path) -> Result<u64, RecordError> {
        let failed = |e: &dyn std::fmt::Display| RecordError::File { path: path.to_owned(), message: e.to_string() };
        let file = std::fs::File::create(path).map_err(|e| failed(&e))?;
        let mut writer = mcap::WriteOptions::new()
            .profile(self.profile.clone())
            .library(concat!("defvol ", env!("CARGO_PKG_VERSION"), " (bag recover)"))
            .create(std::io::BufWriter::new(file))
            .map_err(|e| failed(&e))?;
        let written = self.write_records(&mut writer);
        if let Err(e) = written {
            // A writer left broken by an error panics when dropped (mcap 0.24): forgotten.
            std::mem::forget(writer);
            return Err(failed(&e));
        }
        use std::io::Write as _;
        writer.into_inner().flush().map_err(|e| failed(&e))?;
        Ok(self.messages.len() as u64)
    }

    fn write_records<W: std::io::Write + std::io::Seek>(&self, writer: &mut mcap::Writer<W>) -> mcap::McapResult<()> {
        let mut schema_ids = BTreeMap::new();
        for (id, (name, encoding, data)) in &self.schemas {
            schema_ids.insert(*id, writer.add_schema(name, encoding, data)?);
        }
        let mut channel_ids = BTreeMap::new();
        for (id, (schema, topic, encoding, metadata)) in &self.channels {
            let schema = schema_ids.get(schema).copied().unwrap_or(0);
            channel_ids.insert(*id, writer.add_channel(schema, topic, encoding, metadata)?);
        }
        for (header, data) in &self.messages {
            let Some(channel_id) = channel_ids.get(&header.channel_id).copied() else { continue };
            let header = MessageHeader {
                channel_id,
                sequence: header.sequence,
                log_time: header.log_time,
                publish_time: header.publish_time,
            };
            writer.write_to_known_channel(&header, data)?;
        }
        writer.finish().map(drop)
    }
}

/// The splits as `metadata.yaml` lists them, and their topics with their counts.
fn describe_splits(splits: &[PathBuf]) -> Result<(Vec<FileEntry>, BTreeMap<String, TopicEntry>), RecordError> {
    let mut files = Vec::new();
    let mut topics: BTreeMap<String, TopicEntry> = BTreeMap::new();
    for split in splits {
        let bytes =
            std::fs::read(split).map_err(|e| RecordError::Read { path: split.to_owned(), message: e.to_string() })?;
        let contents = Contents::read(split, &bytes)?;
        let name = split.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let mut entry = FileEntry::new(name, split);
        for (header, _) in &contents.messages {
            entry.count(header.log_time);
            let Some((schema, topic, _, metadata)) = contents.channels.get(&header.channel_id) else { continue };
            let type_name = contents.schemas.get(schema).map(|(n, _, _)| n.as_str()).unwrap_or_default();
            let profiles = metadata.get("offered_qos_profiles").cloned().unwrap_or_default();
            topics
                .entry(topic.clone())
                .or_insert_with(|| TopicEntry::with_profiles(topic, type_name, profiles))
                .message_count += 1;
        }
        files.push(entry);
    }
    Ok((files, topics))
}

#[cfg(test)]
mod tests {
    use std::path::Path;
    use std::time::Duration;

    use crate::msgs::{Header, PoseStamped, Time};
    use crate::record::bag::{read_messages, Recorder};
    use crate::record::bag_dir::{Bag, Metadata};
    use crate::record::recover::{recover, FileOutcome};
    use crate::record::{BagOptions, Qos};

    fn pose(i: u64) -> PoseStamped {
        PoseStamped {
            header: Header { stamp: Time::from_nanos(i * 10_000_000), frame_id: format!("tool {i}") },
            ..Default::default()
        }
    }

    /// What a killed recorder leaves: 200 messages in two flushed chunks, 50 more in the open
    /// one, the file read before any summary is written.
    fn killed_recording(path: &Path) -> Vec<u8> {
        let mut recorder = Recorder::create(path).unwrap();
        for i in 0..250 {
            recorder.write("/tool_pose", Qos::SensorData, &pose(i), i * 10_000_000).unwrap();
            if i == 99 || i == 199 {
                recorder.flush().unwrap();
            }
        }
        let cut = std::fs::read(path).unwrap();
        drop(recorder);
        std::fs::write(path, &cut).unwrap();
        cut
    }

    #[test]
    fn a_cut_file_is_rebuilt_to_its_last_whole_chunk_and_the_original_kept() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cut.mcap");
        let cut = killed_recording(&path);
        assert!(mcap::Summary::read(&cut).is_err() || mcap::Summary::read(&cut).unwrap().is_none());
        let recovery = recover(&path).unwrap();
        let kept = dir.path().join("cut.mcap.cut");
        assert_eq!(recovery.files[0].1, FileOutcome::Rebuilt { messages: 200, kept: kept.clone() });
        assert_eq!(std::fs::read(&kept).unwrap(), cut, "the cut original is kept as it was");
        // The rebuilt file is whole: summary with statistics, indexes and footer.
        let bytes = std::fs::read(&path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let stats = summary.stats.unwrap();
        assert_eq!((stats.message_count, stats.message_start_time, stats.message_end_time), (200, 0, 1_990_000_000));
        assert!(!summary.chunk_indexes.is_empty());
        let read = read_messages(&path, &[]).unwrap();
        assert_eq!(read.len(), 200);
        assert_eq!(crate::msgs::decode::<PoseStamped>(&read[199].data, "t").unwrap(), pose(199));
        let channel = summary.channels.values().next().unwrap();
        assert!(channel.metadata["offered_qos_profiles"].contains("reliability: 2"), "its QoS carried over");
        // Recovered again, it is intact and left alone.
        assert_eq!(recover(&path).unwrap().files[0].1, FileOutcome::Intact { messages: 200 });
        assert_eq!(std::fs::read(&path).unwrap(), bytes);
    }

    #[test]
    fn a_cut_bag_directory_gets_its_open_split_rebuilt_and_its_metadata_regenerated() {
        let root = tempfile::tempdir().unwrap();
        let bag_dir = root.path().join("run");
        let options = BagOptions { max_duration: Some(Duration::from_millis(500)), ..Default::default() };
        let mut bag = Bag::create(&bag_dir, options).unwrap();
        for i in 0..170u64 {
            let data = crate::msgs::encode(&pose(i)).unwrap();
            bag.write_encoded("/tool_pose", "geometry_msgs/msg/PoseStamped", Qos::SensorData, &data, i * 10_000_000)
                .unwrap();
        }
        // Killed: three closed splits of 50, the fourth open with 20 unflushed messages.
        let snapshot = root.path().join("killed");
        std::fs::create_dir(&snapshot).unwrap();
        for entry in std::fs::read_dir(&bag_dir).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), snapshot.join(entry.file_name())).unwrap();
        }
        drop(bag);
        let closed: Vec<Vec<u8>> =
            (0..3).map(|i| std::fs::read(snapshot.join(format!("run_{i}.mcap"))).unwrap()).collect();
        let recovery = recover(&snapshot).unwrap();
        assert!(matches!(recovery.files[0].1, FileOutcome::Intact { messages: 50 }));
        for (i, bytes) in closed.iter().enumerate() {
            assert_eq!(
                &std::fs::read(snapshot.join(format!("run_{i}.mcap"))).unwrap(),
                bytes,
                "closed split {i} untouched"
            );
        }
        let metadata: Metadata =
            serde_yaml_ng::from_str(&std::fs::read_to_string(snapshot.join("metadata.yaml")).unwrap()).unwrap();
        let info = metadata.rosbag2_bagfile_information;
        assert_eq!(info.relative_file_paths, ["run_0.mcap", "run_1.mcap", "run_2.mcap", "run_3.mcap"]);
        let counts: Vec<u64> = info.files.iter().map(|f| f.message_count).collect();
        // The open split had no whole chunk: rebuilt empty (its messages were never written).
        assert_eq!(counts, [50, 50, 50, 0]);
        assert_eq!(info.message_count, 150);
        assert_eq!(info.topics_with_message_count[0].message_count, 150);
        // Killed just as it opened a fifth split: that one empty, rebuilt as an empty bag.
        std::fs::write(snapshot.join("run_4.mcap"), b"").unwrap();
        let recovery = recover(&snapshot).unwrap();
        assert!(matches!(recovery.files[4].1, FileOutcome::Rebuilt { messages: 0, .. }), "{recovery:?}");
        assert!(read_messages(&snapshot.join("run_4.mcap"), &[]).unwrap().is_empty());
        let metadata: Metadata =
            serde_yaml_ng::from_str(&std::fs::read_to_string(snapshot.join("metadata.yaml")).unwrap()).unwrap();
        assert_eq!(metadata.rosbag2_bagfile_information.relative_file_paths.len(), 5);
    }

    #[test]
    fn what_is_not_a_cut_mcap_file_is_refused_by_name_and_nothing_written() {
        let dir = tempfile::tempdir().unwrap();
        let whole = dir.path().join("whole.mcap");
        let cut = killed_recording(&whole);
        let cases = [
            ("text.mcap", b"rosbag2_bagfile_information: {}\n".to_vec(), "not an MCAP file"),
            ("empty.mcap", Vec::new(), "empty file"),
            ("header.mcap", cut[..12].to_vec(), "inside its header"),
        ];
        for (name, bytes, why) in cases {
            let path = dir.path().join(name);
            std::fs::write(&path, &bytes).unwrap();
            let before: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
            let e = recover(&path).unwrap_err().to_string();
            assert!(e.contains(name) && e.contains(why), "{name}: {e}");
            let after: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
            assert_eq!((before.len(), std::fs::read(&path).unwrap()), (after.len(), bytes), "{name}: nothing written");
        }
    }
}
