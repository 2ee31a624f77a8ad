//! rosbag2-compatible MCAP recording: profile `ros2`, `ros2msg` schemas with their
//! dependencies, `cdr` messages, `offered_qos_profiles` on every channel. Chunks are small
//! and flushed as they fill, so a crash or a full disk loses at most the open chunk: what
//! was written before stays readable.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use mcap::records::MessageHeader;

use super::Qos;
use crate::dpcm::markers::{MotionFile, TrackCounts};
use crate::msgs::{self, Message, MsgError, PoseStamped};
use nalgebra::Point3;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RecordError {
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
    /// The recording stopped on an earlier error, `first` (its cause).
    #[error("{path}: {first}")]
    Stopped { path: PathBuf, first: String },
    #[error(transparent)]
    Message(#[from] MsgError),
    #[error("{path}: {message}")]
    Read { path: PathBuf, message: String },
}

/// Messages per chunk are bounded by bytes: 1 MiB chunks keep the loss on a crash small.
const CHUNK_BYTES: u64 = 1 << 20;

/// An MCAP file being written. The first write error stops the recording (reported once,
/// by the call that met it); the node goes on without it.
pub struct Recorder<W: Write + Seek = BufWriter<File>> {
    path: PathBuf,
    writer: Option<mcap::Writer<SharedSink<W>>>,
    /// The sink the writer writes into, also held here: after a failure the writer may be
    /// left broken (mcap 0.24 loses its sink when a chunk cannot even start, and then panics
    /// when asked for it back), so it is forgotten and the sink kept from this handle.
    sink: SharedSink<W>,
    schemas: HashMap<&'static str, u16>,
    channels: HashMap<String, u16>,
    sequence: u32,
    messages: u64,
    failure: Option<String>,
    /// The sink as the failure left it (no summary written onto a half-written chunk).
    failed_sink: Option<SharedSink<W>>,
}

/// A sink shared by the MCAP writer and its recorder.
pub struct SharedSink<W>(Arc<Mutex<W>>);

impl<W> SharedSink<W> {
    fn lock(&self) -> std::io::Result<std::sync::MutexGuard<'_, W>> {
        self.0.lock().map_err(|_| std::io::Error::other("the recording's sink was poisoned"))
    }

    /// Runs `f` on the sink (tests look at what a failure left).
    pub fn with<R>(&self, f: impl FnOnce(&mut W) -> R) -> std::io::Result<R> {
        self.lock().map(|mut sink| f(&mut sink))
    }
}

impl<W: Write> Write for SharedSink<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.lock()?.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.lock()?.flush()
    }
}

impl<W: Seek> Seek for SharedSink<W> {
    fn seek(&mut self, pos: std::io::SeekFrom) -> std::io::Result<u64> {
        self.lock()?.seek(pos)
    }
}

/// What a finished recording holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RecordSummary {
    pub messages: u64,
    pub channels: usize,
}

impl Recorder {
    pub fn create(path: &Path) -> Result<Self, RecordError> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| RecordError::File {
                path: path.to_owned(),
                message: format!("cannot create its folder: {e}"),
            })?;
        }
        let file =
            File::create(path).map_err(|e| RecordError::File { path: path.to_owned(), message: e.to_string() })?;
        Self::new(path, BufWriter::new(file))
    }
}

impl<W: Write + Seek> Recorder<W> {
    /// A recording into `sink`; `path` names it in errors.
    pub fn new(path: &Path, sink: W) -> Result<Self, RecordError> {
        let sink = SharedSink(Arc::new(Mutex::new(sink)));
        let writer = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("defvol ", env!("CARGO_PKG_VERSION")))
            .chunk_size(Some(CHUNK_BYTES))
            .create(SharedSink(sink.0.clone()))
            .map_err(|e| RecordError::File { path: path.to_owned(), message: e.to_string() })?;
        Ok(Self {
            path: path.to_owned(),
            writer: Some(writer),
            sink,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            sequence: 0,
            messages: 0,
            failure: None,
            failed_sink: None,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether an error stopped the recording.
    pub fn failure(&self) -> Option<&str> {
        self.failure.as_deref()
    }

    /// The error and its causes ("… : No space left on device"), recorded as the failure.
    fn fail_with(&mut self, error: &dyn std::error::Error) -> RecordError {
        let mut message = error.to_string();
        let mut source = error.source();
        while let Some(cause) = source {
            message = format!("{message}: {cause}");
            source = cause.source();
        }
        self.fail(message)
    }

    fn fail(&mut self, message: String) -> RecordError {
        self.failure = Some(message.clone());
        // No summary after a failed write: readers still get every finished chunk. The writer
        // is forgotten, not dropped: dropping a broken one panics (see `sink`).
        if let Some(writer) = self.writer.take() {
            std::mem::forget(writer);
        }
        self.failed_sink = Some(SharedSink(self.sink.0.clone()));
        RecordError::File { path: self.path.clone(), message }
    }

    /// Records `msg` on `topic` (fully qualified, as `ros2 bag` lists it) at `log_time_ns`.
    pub fn write<T: Message>(&mut self, topic: &str, qos: Qos, msg: &T, log_time_ns: u64) -> Result<(), RecordError> {
        let data = msgs::encode(msg)?;
        self.write_encoded(topic, T::NAME, qos, &data, log_time_ns)
    }

    /// Records an already CDR-encoded message of type `type_name`.
    pub fn write_encoded(
        &mut self,
        topic: &str,
        type_name: &'static str,
        qos: Qos,
        data: &[u8],
        log_time_ns: u64,
    ) -> Result<(), RecordError> {
        if let Some(first) = &self.failure {
            return Err(RecordError::Stopped { path: self.path.clone(), first: first.clone() });
        }
        let channel = match self.channels.get(topic) {
            Some(id) => *id,
            None => {
                let schema_text = msgs::ros2msg_schema(type_name)?;
                let Some(writer) = self.writer.as_mut() else {
                    return Err(RecordError::Stopped {
                        path: self.path.clone(),
                        first: "the recording has ended".into(),
                    });
                };
                let schema = match self.schemas.get(type_name) {
                    Some(id) => Ok(*id),
                    None => writer.add_schema(type_name, "ros2msg", schema_text.as_bytes()),
                };
                let metadata = BTreeMap::from([("offered_qos_profiles".to_owned(), qos.offered_profiles_yaml())]);
                let added = schema.and_then(|schema| {
                    writer.add_channel(schema, topic, "cdr", &metadata).map(|channel| (schema, channel))
                });
                let (schema, channel) = added.map_err(|e| self.fail_with(&e))?;
                self.schemas.insert(type_name, schema);
                self.channels.insert(topic.to_owned(), channel);
                channel
            }
        };
        self.sequence = self.sequence.wrapping_add(1);
        let header = MessageHeader {
            channel_id: channel,
            sequence: self.sequence,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        let Some(writer) = self.writer.as_mut() else {
            return Err(RecordError::Stopped { path: self.path.clone(), first: "the recording has ended".into() });
        };
        writer.write_to_known_channel(&header, data).map_err(|e| self.fail_with(&e))?;
        self.messages += 1;
        Ok(())
    }

    /// Closes the open chunk and writes it out: a crash after this keeps it.
    pub fn flush(&mut self) -> Result<(), RecordError> {
        let Some(writer) = self.writer.as_mut() else { return Ok(()) };
        let flushed = writer.flush();
        flushed.map_err(|e| self.fail_with(&e))
    }

    /// Writes the summary; after an error, reports what was kept.
    pub fn finish(mut self) -> Result<RecordSummary, RecordError> {
        let summary = RecordSummary { messages: self.messages, channels: self.channels.len() };
        if let Some(first) = self.failure.take() {
            return Err(RecordError::Stopped { path: self.path.clone(), first });
        }
        let Some(mut writer) = self.writer.take() else { return Ok(summary) };
        writer.finish().map_err(|e| RecordError::File { path: self.path.clone(), message: e.to_string() })?;
        drop(writer);
        self.sink
            .lock()
            .and_then(|mut sink| sink.flush())
            .map_err(|e| RecordError::File { path: self.path.clone(), message: e.to_string() })?;
        Ok(summary)
    }
}

impl<W: Write + Seek> Drop for Recorder<W> {
    fn drop(&mut self) {
        // A recorder dropped without `finish` (an error path) still closes its file properly.
        if let Some(mut writer) = self.writer.take() {
            if let Err(e) = writer.finish() {
                tracing::warn!("{}: closing the recording: {e}", self.path.display());
            }
        }
    }
}

/// A message read back from a bag.
#[derive(Debug, Clone, PartialEq)]
pub struct BagMessage {
    pub topic: String,
    pub type_name: String,
    /// The channel's message encoding (`cdr` for ROS 2).
    pub encoding: String,
    pub log_time_ns: u64,
    pub data: Vec<u8>,
}

/// Every message of `topics` (all when empty) in log-time order. A bag cut short (no
/// summary: a crash or a full disk while recording) is read up to its last whole chunk.
pub fn read_messages(path: &Path, topics: &[&str]) -> Result<Vec<BagMessage>, RecordError> {
    let bytes = std::fs::read(path).map_err(|e| RecordError::Read { path: path.to_owned(), message: e.to_string() })?;
    parse_messages(path, &bytes, topics)
}

/// The most a chunk may claim to grow when decompressed: beyond it the header is broken (a
/// damaged or hostile file), and it is refused before anything is allocated for it.
const MAX_CHUNK_EXPANSION: u64 = 4096;

/// [`read_messages`] on a bag's bytes (`path` names it in errors).
pub fn parse_messages(path: &Path, bytes: &[u8], topics: &[&str]) -> Result<Vec<BagMessage>, RecordError> {
    use mcap::records::Record;
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut channels: HashMap<u16, (String, u16, String)> = HashMap::new();
    let mut out = Vec::new();
    // One record: a schema, a channel or a message (the rest of the data section is skipped).
    walk_records(path, bytes, |record| {
        match record {
            Record::Schema { header, .. } => {
                schemas.insert(header.id, header.name.clone());
            }
            Record::Channel(channel) => {
                channels
                    .insert(channel.id, (channel.topic.clone(), channel.schema_id, channel.message_encoding.clone()));
            }
            Record::Message { header, data } => {
                let (topic, schema, encoding) = channels
                    .get(&header.channel_id)
                    .ok_or_else(|| format!("a message on unknown channel {}", header.channel_id))?;
                if topics.is_empty() || topics.contains(&topic.as_str()) {
                    let type_name = schemas.get(schema).cloned().unwrap_or_default();
                    out.push(BagMessage {
                        topic: topic.clone(),
                        type_name,
                        encoding: encoding.clone(),
                        log_time_ns: header.log_time,
                        data: data.into_owned(),
                    });
                }
            }
            _ => {}
        }
        Ok(())
    })?;
    out.sort_by_key(|m| m.log_time_ns);
    Ok(out)
}

/// How a walk through a bag ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Walked {
    /// Messages handed over.
    pub messages: u64,
    /// The bag stops short of its data section's end (a crash or a full disk while
    /// recording): what was handed over is what came before its last whole record.
    pub cut: bool,
}

/// Walks a bag's data section record by record, handing each to `visit` (the header, then
/// schemas, channels and messages, those inside chunks too). The records are walked here
/// (chunks checked before they are decompressed), so no header in the file decides how much
/// memory is taken. A bag cut short is walked up to its last whole record; cut inside its
/// header, or damaged, it is an error naming what was wrong.
pub fn walk_records(
    path: &Path,
    bytes: &[u8],
    mut visit: impl FnMut(mcap::records::Record<'_>) -> Result<(), String>,
) -> Result<Walked, RecordError> {
    use mcap::records::Record;
    let bad = |message: String| RecordError::Read { path: path.to_owned(), message };
    if bytes.is_empty() {
        return Err(bad("an empty file, not an MCAP file".into()));
    }
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(bad("not an MCAP file (it does not begin with MCAP's magic bytes)".into()));
    }
    let records = mcap::read::LinearReader::new_with_options(bytes, mcap::read::Options::IgnoreEndMagic.into())
        .map_err(|e| bad(format!("not a readable MCAP file: {e}")))?;
    let mut walked = Walked { messages: 0, cut: true };
    let mut visit = |record: Record<'_>, walked: &mut Walked| {
        walked.messages += u64::from(matches!(record, Record::Message { .. }));
        visit(record).map_err(bad)
    };
    let mut header_seen = false;
    for record in records {
        // A truncated tail is where the recording stopped; what came before counts.
        let record = match record {
            Ok(record) => record,
            Err(e) if !header_seen => return Err(bad(format!("cut or damaged inside its header record: {e}"))),
            // The writer leaves a chunk's length unset until the chunk is closed, so a cut-short
            // chunk reads as a record longer than the whole file.
            Err(
                mcap::McapError::UnexpectedEof
                | mcap::McapError::UnexpectedEoc
                | mcap::McapError::RecordTooLarge { .. }
                | mcap::McapError::BadChunkLength { .. },
            ) => {
                tracing::warn!(
                    "{}: the bag ends mid-record (recording cut short); read {} messages",
                    path.display(),
                    walked.messages
                );
                break;
            }
            Err(e) => return Err(bad(e.to_string())),
        };
        header_seen = true;
        match record {
            Record::Chunk { header, data } => {
                let plausible = (data.len() as u64).saturating_mul(MAX_CHUNK_EXPANSION).saturating_add(1 << 16);
                if header.uncompressed_size > plausible {
                    return Err(bad(format!(
                        "a chunk of {} bytes claims to hold {}",
                        data.len(),
                        header.uncompressed_size
                    )));
                }
                let records = decompress_chunk(&header, &data).map_err(|e| bad(format!("damaged chunk: {e}")))?;
                let mut at = 0;
                while at < records.len() {
                    let (record, next) = chunk_record(&records, at).map_err(|e| bad(format!("damaged chunk: {e}")))?;
                    visit(record, &mut walked)?;
                    at = next;
                }
            }
            Record::DataEnd(_) => {
                walked.cut = false;
                break;
            }
            other => visit(other, &mut walked)?,
        }
    }
    Ok(walked)
}

/// A chunk's records, decompressed into exactly the size its header gives (already checked
/// against the compressed size).
fn decompress_chunk(header: &mcap::records::ChunkHeader, data: &[u8]) -> Result<Vec<u8>, String> {
    use std::io::Read;
    let size = usize::try_from(header.uncompressed_size).map_err(|_| "a chunk larger than this machine".to_owned())?;
    let out = match header.compression.as_str() {
        "" => data.to_vec(),
        "zstd" => zstd::bulk::decompress(data, size).map_err(|e| format!("zstd: {e}"))?,
        "lz4" => {
            let mut out = Vec::new();
            lz4_flex::frame::FrameDecoder::new(data)
                .take(size as u64)
                .read_to_end(&mut out)
                .map_err(|e| format!("lz4: {e}"))?;
            out
        }
        other => return Err(format!("compression `{other}` is not zstd or lz4")),
    };
    if out.len() != size {
        return Err(format!("{} bytes decompressed, {size} announced", out.len()));
    }
    if header.uncompressed_crc != 0 && crc32fast::hash(&out) != header.uncompressed_crc {
        return Err("its CRC does not match".into());
    }
    Ok(out)
}

/// The record at `at` of a chunk's records (opcode, u64 length, body) and where the next
/// begins; the length is checked against what is there.
fn chunk_record(records: &[u8], at: usize) -> Result<(mcap::records::Record<'_>, usize), String> {
    let head = records.get(at..at + 9).ok_or("a record header cut short")?;
    let length = u64::from_le_bytes([head[1], head[2], head[3], head[4], head[5], head[6], head[7], head[8]]);
    let end = usize::try_from(length)
        .ok()
        .and_then(|l| (at + 9).checked_add(l))
        .filter(|e| *e <= records.len())
        .ok_or_else(|| format!("a record of {length} bytes where {} are left", records.len() - at - 9))?;
    let record = mcap::read::parse_record(head[0], &records[at + 9..end]).map_err(|e| e.to_string())?;
    Ok((record, end))
}

/// Tool poses recorded in a bag as DPCM marker tracks: every `geometry_msgs/msg/PoseStamped`
/// channel, or those of `topics`, one marker per topic (ids in topic order), timed by log
/// time from the first message. Positions are world metres; frame ids are not resolved.
/// Samples with non-finite positions or going back in time are dropped and counted.
pub fn motion_from_bag(path: &Path, topics: &[String]) -> Result<(MotionFile, TrackCounts), RecordError> {
    let bad = |message: String| RecordError::Read { path: path.to_owned(), message };
    let messages = read_messages(path, &[])?;
    let mut samples: BTreeMap<String, Vec<(u64, Point3<f64>)>> = BTreeMap::new();
    let mut dropped = 0;
    for message in messages {
        let is_pose = message.type_name == PoseStamped::NAME && message.encoding == "cdr";
        let wanted = if topics.is_empty() { is_pose } else { topics.contains(&message.topic) };
        if !wanted {
            continue;
        }
        if !is_pose {
            return Err(bad(format!("topic {} is not geometry_msgs/msg/PoseStamped in CDR", message.topic)));
        }
        let pose: PoseStamped = match msgs::decode(&message.data, &message.topic) {
            Ok(p) => p,
            Err(e) => {
                tracing::warn!("{}: {e}; message dropped", path.display());
                dropped += 1;
                continue;
            }
        };
        let p = pose.pose.position;
        if ![p.x, p.y, p.z].iter().all(|v| v.is_finite()) {
            dropped += 1;
            continue;
        }
        samples.entry(message.topic).or_default().push((message.log_time_ns, Point3::new(p.x, p.y, p.z)));
    }
    for topic in topics {
        if !samples.contains_key(topic) {
            return Err(bad(format!("no PoseStamped messages on topic {topic}")));
        }
    }
    if samples.is_empty() {
        return Err(bad("no geometry_msgs/msg/PoseStamped messages".into()));
    }
    MotionFile::from_tracks(samples, dropped).map_err(|e| bad(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Header, PoseStamped, Time, WrenchStamped};
    use std::io::Cursor;

    fn pose(t: f64, x: f64) -> PoseStamped {
        let mut msg = PoseStamped {
            header: Header { stamp: Time::from_secs(t), frame_id: "world".into() },
            ..Default::default()
        };
        msg.pose.position.x = x;
        msg
    }

    #[test]
    fn bags_hold_ros2_channels_and_decode_to_what_was_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.mcap");
        let mut rec = Recorder::create(&path).unwrap();
        for i in 0..50 {
            rec.write("/tool_pose", Qos::SensorData, &pose(i as f64 * 0.01, i as f64), 1_000 + i * 10_000_000).unwrap();
        }
        rec.write("/tool_feedback", Qos::Reliable, &WrenchStamped::default(), 5).unwrap();
        assert_eq!(rec.finish().unwrap(), RecordSummary { messages: 51, channels: 2 });
        let bytes = std::fs::read(&path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let channel = summary.channels.values().find(|c| c.topic == "/tool_pose").unwrap();
        assert_eq!(channel.message_encoding, "cdr");
        let schema = channel.schema.as_ref().unwrap();
        assert_eq!((schema.name.as_str(), schema.encoding.as_str()), ("geometry_msgs/msg/PoseStamped", "ros2msg"));
        assert!(std::str::from_utf8(&schema.data).unwrap().contains("MSG: std_msgs/Header"));
        assert!(channel.metadata["offered_qos_profiles"].contains("reliability: 2"));
        // The header record after the magic: opcode 0x01, length, then the profile string.
        assert_eq!((bytes[8], &bytes[17..21], &bytes[21..25]), (0x01, &4u32.to_le_bytes()[..], &b"ros2"[..]));
        let poses = read_messages(&path, &["/tool_pose"]).unwrap();
        assert_eq!(poses.len(), 50);
        assert_eq!(msgs::decode::<PoseStamped>(&poses[7].data, "t").unwrap(), pose(0.07, 7.0));
        // Everything, in log-time order: the feedback (t = 5 ns) first.
        assert_eq!(read_messages(&path, &[]).unwrap()[0].topic, "/tool_feedback");
    }

    /// A sink that fails once `room` bytes are written, like a disk filling up.
    struct FillingDisk {
        inner: Cursor<Vec<u8>>,
        room: usize,
    }
    impl Write for FillingDisk {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            let left = self.room.saturating_sub(self.inner.get_ref().len());
            if left == 0 {
                return Err(std::io::Error::new(std::io::ErrorKind::StorageFull, "No space left on device"));
            }
            self.inner.write(&buf[..buf.len().min(left)])
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    impl Seek for FillingDisk {
        fn seek(&mut self, pos: std::io::SeekFrom) -> std::io::Result<u64> {
            self.inner.seek(pos)
        }
    }

    #[test]
    fn a_full_disk_stops_the_recording_and_keeps_what_was_written() {
        let room = 3 * CHUNK_BYTES as usize + 1000;
        let disk = FillingDisk { inner: Cursor::new(Vec::new()), room };
        let mut rec = Recorder::new(Path::new("full.mcap"), disk).unwrap();
        // Noise, so that zstd cannot shrink it below the disk's size.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let noise = (0..200_000).map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state as u8
        });
        let big = crate::msgs::Image { data: noise.collect(), ..Default::default() };
        let mut written = 0;
        let error = loop {
            match rec.write("/raycast/image", Qos::SensorData, &big, written * 1000) {
                Ok(()) => written += 1,
                Err(e) => break e,
            }
            assert!(written < 1000, "the disk never filled");
        };
        assert!(error.to_string().contains("full.mcap") && error.to_string().contains("space"), "{error}");
        assert!(matches!(rec.write("/raycast/image", Qos::SensorData, &big, 0), Err(RecordError::Stopped { .. })));
        // The bytes on the "disk" read back as a bag up to the last whole chunk.
        let bytes = rec.failed_sink.take().unwrap().with(|disk| disk.inner.get_ref().clone()).unwrap();
        assert!(rec.finish().is_err());
        let dir = tempfile::tempdir().unwrap();
        let kept = dir.path().join("kept.mcap");
        std::fs::write(&kept, &bytes).unwrap();
        let read = read_messages(&kept, &[]).unwrap();
        assert!(read.len() >= 10 && read.len() <= written as usize, "{} of {written} messages kept", read.len());
        assert_eq!(msgs::decode::<crate::msgs::Image>(&read[3].data, "kept").unwrap().data, big.data);
    }
}
