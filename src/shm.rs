//! Warped volumes through iceoryx2 shared memory: publish-subscribe of `[f32]` behind a
//! `#[repr(C)]` header. Volumes are tens of MiB; DDS would take tens of milliseconds per
//! sample (and fails at 10 MB). The publisher is the pipeline's [`VolumeSink`]: the warp
//! writes each volume straight into the loaned sample, and since samples come back to the
//! pool, the publisher remembers which volume each one last carried, so the CPU warp
//! rewrites only what moved since. A subscriber that is slow or gone never blocks the node:
//! full queues drop the oldest.

use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use iceoryx2::service::port_factory::PortFactory;

use std::collections::HashMap;
use std::sync::Mutex;

use crate::pipeline::{VolumeSink, WarpedVolume, WriteVolume};
use crate::volume::Grid;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ShmError {
    #[error("/dev/shm has {free_mib:.1} MiB free; the warped volume service `{service}` needs {needed_mib:.1} MiB (raise the size of /dev/shm, e.g. docker --shm-size)")]
    NoRoom { service: String, free_mib: f64, needed_mib: f64 },
    #[error("iceoryx2 service `{service}`: {message}")]
    Service { service: String, message: String },
    #[error("iceoryx2 sample of {elements} floats for `{service}`: {message}")]
    Send { service: String, elements: usize, message: String },
}

/// What precedes the samples (x fastest, then y, then z), as a C struct: readers in any
/// language map it directly. Spacing and origin are in the volume's file units (mm); voxel
/// (i, j, k) sits at `origin + direction · (i·spacing[0], j·spacing[1], k·spacing[2])`, the
/// direction row major, as ITK places it.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("WarpedVolumeHeader")]
#[repr(C)]
pub struct WarpedVolumeHeader {
    pub sequence: u64,
    pub stamp_sec: i32,
    pub stamp_nanosec: u32,
    pub dims: [u32; 3],
    /// Keeps the doubles 8-byte aligned, spelled out so every language sees the same layout.
    pub padding: u32,
    pub spacing: [f64; 3],
    pub origin: [f64; 3],
    pub direction: [f64; 9],
}

impl WarpedVolumeHeader {
    fn new(volume: &WarpedVolume) -> Self {
        let grid = &volume.grid;
        let d = &grid.direction;
        Self {
            sequence: volume.sequence,
            stamp_sec: volume.stamp.sec,
            stamp_nanosec: volume.stamp.nanosec,
            dims: grid.dims.map(|d| d as u32),
            padding: 0,
            spacing: grid.spacing,
            origin: grid.origin,
            direction: [
                d[(0, 0)],
                d[(0, 1)],
                d[(0, 2)],
                d[(1, 0)],
                d[(1, 1)],
                d[(1, 2)],
                d[(2, 0)],
                d[(2, 1)],
                d[(2, 2)],
            ],
        }
    }
}

/// Samples the service keeps: subscribers' queues and loans in flight.
const SUBSCRIBER_QUEUE: usize = 2;
const MAX_SUBSCRIBERS: usize = 8;
const MAX_LOANS: usize = 2;

/// Shared memory the publisher's data segment takes for `elements` floats, with iceoryx2's
/// own bookkeeping rounded generously up.
pub fn bytes_needed(elements: usize) -> u64 {
    let sample = (elements * 4 + std::mem::size_of::<WarpedVolumeHeader>() + 256) as u64;
    // Each subscriber may hold its queue plus one borrowed sample; the publisher its loans.
    sample * (MAX_SUBSCRIBERS * (SUBSCRIBER_QUEUE + 1) + MAX_LOANS + 1) as u64
}

/// Free bytes under /dev/shm.
fn shm_free_bytes() -> Option<u64> {
    let stat = nix::sys::statvfs::statvfs("/dev/shm").ok()?;
    Some(stat.blocks_available() as u64 * stat.fragment_size() as u64)
}

/// The iceoryx2 service type: the thread-safe flavour of `ipc` (the same shared memory and
/// wire, so any `ipc` subscriber reads it), so that the frame worker can publish while the
/// node asks for subscribers.
type Service = ipc_threadsafe::Service;

pub struct WarpedVolumePublisher {
    service_name: String,
    service: PubSubFactory<Service, [f32], WarpedVolumeHeader>,
    publisher: Publisher<Service, [f32], WarpedVolumeHeader>,
    /// Per sample chunk (its payload address), the sequence of the volume it last carried.
    chunks: Mutex<HashMap<usize, u64>>,
    // Declared last: the node outlives its ports.
    _node: Node<Service>,
}

impl WarpedVolumePublisher {
    /// Opens (or creates) `service` for volumes on `grid`, after checking that /dev/shm can
    /// hold them (iceoryx2 would die of SIGBUS otherwise).
    pub fn new(service: &str, grid: &Grid) -> Result<Self, ShmError> {
        let elements = grid.dims.iter().product::<usize>();
        let needed = bytes_needed(elements);
        if let Some(free) = shm_free_bytes().filter(|free| *free < needed) {
            return Err(ShmError::NoRoom {
                service: service.into(),
                free_mib: free as f64 / 1048576.0,
                needed_mib: needed as f64 / 1048576.0,
            });
        }
        let err = |message: String| ShmError::Service { service: service.into(), message };
        let node = NodeBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Service>()
            .map_err(|e| err(format!("node: {e:?}")))?;
        let name: ServiceName = service.try_into().map_err(|e| err(format!("name: {e:?}")))?;
        let factory = node
            .service_builder(&name)
            .publish_subscribe::<[f32]>()
            .user_header::<WarpedVolumeHeader>()
            .enable_safe_overflow(true)
            .subscriber_max_buffer_size(SUBSCRIBER_QUEUE)
            .history_size(1)
            .max_subscribers(MAX_SUBSCRIBERS)
            .max_publishers(1)
            .open_or_create()
            .map_err(|e| err(format!("{e:?}")))?;
        let publisher = factory
            .publisher_builder()
            .initial_max_slice_len(elements)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(MAX_LOANS)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(|e| err(format!("publisher: {e:?}")))?;
        tracing::info!(
            "warped volumes on iceoryx2 service `{service}` ({:.1} MiB each)",
            (elements * 4) as f64 / 1048576.0
        );
        Ok(Self {
            service_name: service.into(),
            service: factory,
            publisher,
            chunks: Mutex::new(HashMap::new()),
            _node: node,
        })
    }

    /// Lends a sample of `volume.grid.len()` samples to `write` (told which volume of this
    /// publisher the sample still holds, if any), then sends it with its header.
    pub fn publish_with(&self, volume: &WarpedVolume, write: &mut WriteVolume<'_>) -> Result<usize, ShmError> {
        let elements = volume.grid.len();
        let err = |message: String| ShmError::Send { service: self.service_name.clone(), elements, message };
        let mut sample = self.publisher.loan_slice_uninit(elements).map_err(|e| err(format!("{e:?}")))?;
        *sample.user_header_mut() = WarpedVolumeHeader::new(volume);
        let payload = sample.payload_mut();
        let chunk = payload.as_ptr() as usize;
        let mut chunks = self.chunks.lock().map_err(|_| err("the chunk table is poisoned".into()))?;
        // Unknown until written: a failed write leaves it unknown.
        let holds = chunks.remove(&chunk);
        // SAFETY: the payload lies in the service's shared-memory segment, which the kernel
        // zero-fills when it is mapped and which only this publisher writes: every f32 in it
        // is initialised (zero, or a sample sent before). `write` gets them as plain floats,
        // told which volume they hold, and overwrites whatever of them is out of date.
        let samples = unsafe { &mut *(std::ptr::from_mut::<[std::mem::MaybeUninit<f32>]>(payload) as *mut [f32]) };
        write(samples, holds).map_err(err)?;
        // SAFETY: as above, every element is initialised.
        let sample = unsafe { sample.assume_init() };
        let sent = sample.send().map_err(|e| err(format!("{e:?}")))?;
        chunks.insert(chunk, volume.sequence);
        Ok(sent)
    }

    /// Sends `data` as one volume (a copy into the loan; the pipeline writes in place
    /// through [`VolumeSink`] instead).
    pub fn publish_slice(&self, volume: &WarpedVolume, data: &[f32]) -> Result<usize, ShmError> {
        if data.len() != volume.grid.len() {
            let message = format!("{} samples do not fill a {:?} grid", data.len(), volume.grid.dims);
            return Err(ShmError::Send { service: self.service_name.clone(), elements: data.len(), message });
        }
        self.publish_with(volume, &mut |samples, _| {
            samples.copy_from_slice(data);
            Ok(())
        })
    }
}

impl VolumeSink for WarpedVolumePublisher {
    fn has_subscribers(&self) -> bool {
        self.subscribers() > 0
    }

    fn subscribers(&self) -> usize {
        self.service.dynamic_config().number_of_subscribers()
    }

    fn publish(&self, volume: &WarpedVolume, write: &mut WriteVolume<'_>) -> Result<(), String> {
        self.publish_with(volume, write).map(drop).map_err(|e| e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::Time;

    fn volume(grid: &Grid, sequence: u64, stamp: Time) -> WarpedVolume {
        WarpedVolume { grid: grid.clone(), sequence, stamp, stats: Default::default(), published: false }
    }

    #[test]
    fn the_header_has_the_c_layout_readers_map() {
        // Offsets a C or ctypes reader computes for the same fields.
        assert_eq!(std::mem::size_of::<WarpedVolumeHeader>(), 8 + 4 + 4 + 12 + 4 + 24 + 24 + 72);
        assert_eq!(std::mem::offset_of!(WarpedVolumeHeader, dims), 16);
        assert_eq!(std::mem::offset_of!(WarpedVolumeHeader, spacing), 32);
        assert_eq!(std::mem::offset_of!(WarpedVolumeHeader, origin), 56);
        assert_eq!(std::mem::offset_of!(WarpedVolumeHeader, direction), 80);
    }

    #[test]
    fn too_little_shared_memory_is_refused_with_the_size_needed() {
        // A grid whose samples cannot fit in any /dev/shm here: 2^40 floats.
        let grid = Grid {
            dims: [1 << 14, 1 << 13, 1 << 13],
            spacing: [1.0; 3],
            origin: [0.0; 3],
            direction: nalgebra::Matrix3::identity(),
        };
        let Err(e) = WarpedVolumePublisher::new("defvol/test_no_room", &grid) else {
            panic!("accepted a 4 TiB volume")
        };
        let message = e.to_string();
        assert!(
            message.contains("/dev/shm") && message.contains("needs") && message.contains("defvol/test_no_room"),
            "{message}"
        );
    }

    #[test]
    fn a_subscriber_receives_the_volume_with_its_header() {
        let direction = nalgebra::Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        let grid = Grid { dims: [8, 5, 3], spacing: [0.5, 0.5, 2.0], origin: [1.0, 2.0, 3.0], direction };
        let service = format!("defvol/test_{}", std::process::id());
        let publisher = WarpedVolumePublisher::new(&service, &grid).unwrap();
        let node = NodeBuilder::new().create::<ipc::Service>().unwrap();
        let factory = node
            .service_builder(&service.as_str().try_into().unwrap())
            .publish_subscribe::<[f32]>()
            .user_header::<WarpedVolumeHeader>()
            .open()
            .unwrap();
        let subscriber = factory.subscriber_builder().create().unwrap();
        assert!(publisher.has_subscribers());
        let data: Vec<f32> = (0..120).map(|i| i as f32 * 0.25).collect();
        publisher.publish_slice(&volume(&grid, 7, Time { sec: 3, nanosec: 9 }), &data).unwrap();
        let sample = subscriber.receive().unwrap().unwrap();
        assert_eq!(sample.payload(), &data[..]);
        let h = sample.user_header();
        assert_eq!(
            (h.sequence, h.stamp_sec, h.stamp_nanosec, h.dims, h.spacing, h.origin),
            (7, 3, 9, [8, 5, 3], [0.5, 0.5, 2.0], [1.0, 2.0, 3.0])
        );
        assert_eq!(h.direction, [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0], "row major");
        drop(sample);
        // A subscriber that never reads does not block: later sends still go through.
        for sequence in 8..20 {
            publisher.publish_slice(&volume(&grid, sequence, Time::default()), &data).unwrap();
        }
    }

    /// Samples come back to the pool: the writer is told which volume a loaned sample last
    /// carried, and what it leaves alone arrives as it was.
    #[test]
    fn a_loaned_sample_says_which_volume_it_last_carried() {
        let grid =
            Grid { dims: [16, 4, 2], spacing: [1.0; 3], origin: [0.0; 3], direction: nalgebra::Matrix3::identity() };
        let service = format!("defvol/test_reuse_{}", std::process::id());
        let publisher = WarpedVolumePublisher::new(&service, &grid).unwrap();
        let node = NodeBuilder::new().create::<ipc::Service>().unwrap();
        let factory = node
            .service_builder(&service.as_str().try_into().unwrap())
            .publish_subscribe::<[f32]>()
            .user_header::<WarpedVolumeHeader>()
            .open()
            .unwrap();
        let subscriber = factory.subscriber_builder().create().unwrap();
        let mut told = Vec::new();
        for sequence in 1..=12u64 {
            publisher
                .publish_with(&volume(&grid, sequence, Time::default()), &mut |samples, holds| {
                    told.push(holds);
                    match holds {
                        // Only the first sample of a known volume changes: the rest is the
                        // volume it held, which equals every earlier one but there.
                        Some(_) => samples[0] = sequence as f32,
                        None => {
                            samples.fill(-1.0);
                            samples[0] = sequence as f32;
                        }
                    }
                    Ok(())
                })
                .unwrap();
            let sample = subscriber.receive().unwrap().unwrap();
            assert_eq!(sample.user_header().sequence, sequence);
            assert_eq!(sample.payload()[0], sequence as f32);
            assert!(
                sample.payload()[1..].iter().all(|v| *v == -1.0),
                "sequence {sequence}: the samples left alone kept the volume they held"
            );
        }
        assert_eq!(told[0], None, "a fresh sample holds nothing known");
        let reused: Vec<(u64, u64)> =
            told.iter().enumerate().filter_map(|(i, h)| h.map(|h| (i as u64 + 1, h))).collect();
        assert!(!reused.is_empty(), "samples return to the pool: {told:?}");
        assert!(reused.iter().all(|(now, held)| held < now), "a sample holds an earlier volume: {reused:?}");
    }
}
