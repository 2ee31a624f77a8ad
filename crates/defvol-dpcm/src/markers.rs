//! Where markers come from (seed 004, section 4.2.1): a script, a motion file, tool poses
//! through a calibration, and the seed's UDP frames.

use std::collections::BTreeMap;
use std::io::ErrorKind;
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Point3};
use serde::Deserialize;

use crate::config::{DpcmConfig, Marker};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MarkerError {
    #[error("{path}: {message}")]
    MotionFile { path: PathBuf, message: String },
    #[error("no marker samples")]
    NoSamples,
    #[error("cannot listen for UDP markers on {addr}: {source}")]
    Bind { addr: SocketAddr, source: std::io::Error },
    #[error("receiving UDP markers failed: {0}")]
    Receive(std::io::Error),
}

/// The seed's calibration (section 7.1): where the grid sits in the world. The grid frame
/// has phyxel (0, 0) at its origin, columns along x, rows along y, Z along +z.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    pub world_from_grid: Isometry3<f64>,
    /// Metres per phyxel.
    pub spacing: f64,
    /// Metres from a given point up to its marker's centre: 0 where points are the centres
    /// of tools' tip spheres (tool poses); the marker's reach below its centre where points
    /// are tips (motion files), so that a tip at the rest height touches the surface.
    pub tip_to_centre: f64,
}

impl Calibration {
    /// The grid placed by `world_from_grid`; points are marker centres.
    pub fn new(world_from_grid: Isometry3<f64>, spacing: f64) -> Self {
        Self { world_from_grid, spacing, tip_to_centre: 0.0 }
    }

    /// A grid lying in the world's xy plane, centred on the origin; points are marker centres.
    pub fn centred(config: &DpcmConfig) -> Self {
        let half =
            nalgebra::Vector3::new((config.width - 1) as f64, (config.height - 1) as f64, 0.0) * (0.5 * config.spacing);
        Self::new(Isometry3::translation(-half.x, -half.y, 0.0), config.spacing)
    }

    /// The same grid, its points taken as tips: the lowest points of `config`'s markers.
    pub fn at_tips(self, config: &DpcmConfig) -> Self {
        Self { tip_to_centre: config.marker.reach_below_centre(), ..self }
    }

    /// A tool's point (world) as a marker: projected on the grid, its centre's height above
    /// the grid's plane.
    pub fn marker(&self, id: u32, world_point: Point3<f64>) -> Marker {
        let p = self.world_from_grid.inverse_transform_point(&world_point);
        let height = p.z + self.tip_to_centre;
        Marker { id, col: p.x / self.spacing, row: p.y / self.spacing, height, params: None }
    }
}

/// One row of a motion file: `time,marker,x,y,z` (seconds, id, world metres).
#[derive(Debug, Clone, Copy, Deserialize)]
struct MotionRow {
    time: f64,
    marker: u32,
    x: f64,
    y: f64,
    z: f64,
}

/// A motion file: per marker, timed world positions; positions in between are interpolated
/// linearly, and a marker is absent before its first and after its last sample.
#[derive(Debug, Clone)]
pub struct MotionFile {
    tracks: BTreeMap<u32, Vec<(f64, Point3<f64>)>>,
}

impl MotionFile {
    pub fn load(path: &Path) -> Result<Self, MarkerError> {
        let bad = |message: String| MarkerError::MotionFile { path: path.to_owned(), message };
        let mut reader = csv::ReaderBuilder::new()
            .trim(csv::Trim::All)
            .comment(Some(b'#'))
            .from_path(path)
            .map_err(|e| bad(e.to_string()))?;
        let mut tracks: BTreeMap<u32, Vec<(f64, Point3<f64>)>> = BTreeMap::new();
        for (line, row) in reader.deserialize::<MotionRow>().enumerate() {
            let row = row.map_err(|e| bad(format!("row {}: {e} (columns: time,marker,x,y,z)", line + 1)))?;
            if ![row.time, row.x, row.y, row.z].iter().all(|v| v.is_finite()) {
                return Err(bad(format!("row {}: marker {} has a non-finite value", line + 1, row.marker)));
            }
            let track = tracks.entry(row.marker).or_default();
            if track.last().is_some_and(|(t, _)| *t >= row.time) {
                return Err(bad(format!(
                    "row {}: marker {} goes back in time to {} s",
                    line + 1,
                    row.marker,
                    row.time
                )));
            }
            track.push((row.time, Point3::new(row.x, row.y, row.z)));
        }
        if tracks.is_empty() {
            return Err(bad("no samples".into()));
        }
        Ok(Self { tracks })
    }

    /// Timed samples per named track (nanoseconds, world metres), one marker per track
    /// (ids in name order), timed from the earliest sample; samples sharing a time are
    /// dropped and counted (the recorded poses of a bag, say: `record::bag::motion_from_bag`).
    pub fn from_tracks(
        samples: BTreeMap<String, Vec<(u64, Point3<f64>)>>,
        dropped: usize,
    ) -> Result<(Self, TrackCounts), MarkerError> {
        let Some(start) = samples.values().flatten().map(|(t, _)| *t).min() else {
            return Err(MarkerError::NoSamples);
        };
        let mut counts = TrackCounts { dropped, ..Default::default() };
        let mut tracks = BTreeMap::new();
        for (id, (name, mut track)) in samples.into_iter().enumerate() {
            track.sort_by_key(|(t, _)| *t);
            let before = track.len();
            track.dedup_by_key(|(t, _)| *t);
            counts.dropped += before - track.len();
            counts.topics.push(name);
            tracks.insert(id as u32, track.into_iter().map(|(t, p)| ((t - start) as f64 * 1e-9, p)).collect());
        }
        counts.messages = tracks.values().map(Vec::len).sum();
        Ok((Self { tracks }, counts))
    }

    /// The last sample time.
    pub fn duration(&self) -> f64 {
        self.tracks.values().filter_map(|t| t.last().map(|s| s.0)).fold(0.0, f64::max)
    }

    /// The lowest marker centre of the file, in the grid's frame (metres above its plane).
    pub fn lowest_centre(&self, calibration: &Calibration) -> f64 {
        let points = self.tracks.iter().flat_map(|(id, track)| track.iter().map(move |(_, p)| (*id, *p)));
        points.map(|(id, p)| calibration.marker(id, p).height).fold(f64::INFINITY, f64::min)
    }

    /// The markers at time `t`, through `calibration`.
    pub fn markers_at(&self, calibration: &Calibration, t: f64) -> Vec<Marker> {
        let mut out = Vec::with_capacity(self.tracks.len());
        for (&id, track) in &self.tracks {
            let after = track.partition_point(|(ts, _)| *ts <= t);
            let Some(&(t0, p0)) = after.checked_sub(1).and_then(|i| track.get(i)) else { continue };
            let p = match track.get(after) {
                Some(&(t1, p1)) => p0 + (p1 - p0) * ((t - t0) / (t1 - t0)),
                None if t0 == t => p0,
                None => continue,
            };
            out.push(calibration.marker(id, p));
        }
        out
    }
}

/// What [`MotionFile::from_tracks`] took and left.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TrackCounts {
    /// Marker ids are indices into this.
    pub topics: Vec<String>,
    pub messages: usize,
    pub dropped: usize,
}

/// The seed's frame marker (figure 7).
pub const FRAME_FLAG: u32 = 0xFFFF_FFFF;
/// More markers than this in one frame is taken as a malformed count.
pub const MAX_FRAME_MARKERS: u32 = 65_536;

/// A frame of the seed's UDP format: frame number and (marker index, x, y) in phyxels.
#[derive(Debug, Clone, PartialEq)]
pub struct UdpFrame {
    pub frame: u32,
    pub markers: Vec<(u32, f32, f32)>,
}

/// Frame counts kept by [`FrameParser`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrameCounts {
    pub received: u64,
    /// Frame numbers skipped by the sender's sequence.
    pub lost: u64,
    /// Truncated frames, bad counts or indices, non-finite positions, stray bytes.
    pub malformed: u64,
    /// Frames older than one already taken.
    pub out_of_order: u64,
    /// Polls that stopped at [`MAX_DATAGRAMS_PER_POLL`] with datagrams still waiting (a
    /// flood: the rest wait for the next step, or the kernel drops them once its buffer
    /// is full, which shows as `lost`).
    pub backlogged: u64,
}

/// Parses the seed's frames (little-endian 32-bit words: flag, count, frame number, then
/// index, x, y per marker), resynchronising on the flag after damage.
#[derive(Debug, Default)]
pub struct FrameParser {
    last_frame: Option<u32>,
    pub counts: FrameCounts,
}

impl FrameParser {
    /// Every well-formed frame in one datagram, in order. Each damaged stretch (a bad frame
    /// and the words after it up to the next flag) counts once as malformed.
    pub fn parse(&mut self, bytes: &[u8]) -> Vec<UdpFrame> {
        let words: Vec<u32> = bytes.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let mut frames = Vec::new();
        let mut i = 0;
        let mut damaged = false;
        while i < words.len() {
            if words[i] != FRAME_FLAG {
                if !damaged {
                    self.malformed("words outside a frame");
                    damaged = true;
                }
                i += 1;
                continue;
            }
            match Self::frame_at(&words[i..]) {
                Ok((frame, used)) => {
                    i += used;
                    damaged = false;
                    self.take(frame, &mut frames);
                }
                Err(why) => {
                    self.malformed(why);
                    damaged = true;
                    i += 1;
                }
            }
        }
        if !bytes.len().is_multiple_of(4) && !damaged {
            self.malformed("a datagram length that is not a whole number of 32-bit words");
        }
        frames
    }

    fn malformed(&mut self, why: &str) {
        self.counts.malformed += 1;
        tracing::warn!("UDP markers: malformed frame dropped ({why})");
    }

    fn take(&mut self, frame: UdpFrame, frames: &mut Vec<UdpFrame>) {
        match self.last_frame {
            // A sender that restarts its count at 0 starts a new sequence.
            Some(last) if frame.frame <= last && frame.frame != 0 => {
                self.counts.out_of_order += 1;
                return;
            }
            Some(last) if frame.frame > last => self.counts.lost += u64::from(frame.frame - last - 1),
            _ => {}
        }
        self.counts.received += 1;
        self.last_frame = Some(frame.frame);
        frames.push(frame);
    }

    fn frame_at(words: &[u32]) -> Result<(UdpFrame, usize), &'static str> {
        let [_, count, number, ..] = *words else { return Err("truncated header") };
        if count > MAX_FRAME_MARKERS {
            return Err("implausible marker count");
        }
        let used = 3 + 3 * count as usize;
        let Some(body) = words.get(3..used) else { return Err("fewer markers than its count") };
        let mut markers = Vec::with_capacity(count as usize);
        let mut seen = vec![false; count as usize];
        for m in body.chunks_exact(3) {
            let (index, x, y) = (m[0], f32::from_bits(m[1]), f32::from_bits(m[2]));
            let Some(slot) = seen.get_mut(index as usize) else { return Err("a marker index beyond its count") };
            if std::mem::replace(slot, true) {
                return Err("a repeated marker index");
            }
            if !(x.is_finite() && y.is_finite()) {
                return Err("a non-finite marker position");
            }
            markers.push((index, x, y));
        }
        Ok((UdpFrame { frame: number, markers }, used))
    }
}

/// Datagrams one poll reads at most: markers come at a device's rate (about one frame a
/// step), so a sender faster than that is a flood, and a step must not loop on it.
pub const MAX_DATAGRAMS_PER_POLL: usize = 32;

/// A non-blocking UDP marker source (the seed's network reading pass never blocks a step,
/// and never reads more than [`MAX_DATAGRAMS_PER_POLL`] in one).
#[derive(Debug)]
pub struct UdpSource {
    socket: UdpSocket,
    pub parser: FrameParser,
    latest: Option<UdpFrame>,
    buffer: Vec<u8>,
}

impl UdpSource {
    /// Binds `addr` (the CLI's default is loopback: other hosts only when asked).
    pub fn bind(addr: SocketAddr) -> Result<Self, MarkerError> {
        let socket = UdpSocket::bind(addr).map_err(|source| MarkerError::Bind { addr, source })?;
        socket.set_nonblocking(true).map_err(|source| MarkerError::Bind { addr, source })?;
        Ok(Self { socket, parser: FrameParser::default(), latest: None, buffer: vec![0; 65_536] })
    }

    pub fn local_addr(&self) -> Option<SocketAddr> {
        self.socket.local_addr().ok()
    }

    /// Reads the pending datagrams, up to [`MAX_DATAGRAMS_PER_POLL`]; the newest
    /// well-formed frame so far.
    pub fn poll(&mut self) -> Result<Option<&UdpFrame>, MarkerError> {
        for _ in 0..MAX_DATAGRAMS_PER_POLL {
            match self.socket.recv(&mut self.buffer) {
                Ok(n) => {
                    let frames = self.parser.parse(&self.buffer[..n]);
                    if let Some(last) = frames.into_iter().last() {
                        self.latest = Some(last);
                    }
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => return Ok(self.latest.as_ref()),
                Err(e) if e.kind() == ErrorKind::Interrupted || e.kind() == ErrorKind::ConnectionRefused => continue,
                Err(e) => return Err(MarkerError::Receive(e)),
            }
        }
        self.parser.counts.backlogged += 1;
        Ok(self.latest.as_ref())
    }
}

impl UdpFrame {
    /// The frame's markers at `height` (the format carries x and y only).
    pub fn markers(&self, height: f64) -> Vec<Marker> {
        self.markers
            .iter()
            .map(|&(id, x, y)| Marker { id, col: f64::from(x), row: f64::from(y), height, params: None })
            .collect()
    }

    /// The frame as the seed's words, little-endian (for senders and tests).
    pub fn encode(&self) -> Vec<u8> {
        let mut words = vec![FRAME_FLAG, self.markers.len() as u32, self.frame];
        for &(index, x, y) in &self.markers {
            words.extend([index, x.to_bits(), y.to_bits()]);
        }
        words.iter().flat_map(|w| w.to_le_bytes()).collect()
    }
}
