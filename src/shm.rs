//! Warped volumes through iceoryx2 shared memory: publish-subscribe of `[f32]` behind a
//! `#[repr(C)]` header. Volumes are tens of MiB; DDS would take tens of milliseconds per
//! sample (and fails at 10 MB), shared memory hands them over without copying them again.
//! A subscriber that is slow or gone never blocks the node: full queues drop the oldest.

use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use iceoryx2::service::port_factory::PortFactory;

use crate::msgs::Time;
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
/// language map it directly. Spacing and origin are in the volume's file units (mm).
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

pub struct WarpedVolumePublisher {
    service_name: String,
    service: PubSubFactory<ipc::Service, [f32], WarpedVolumeHeader>,
    publisher: Publisher<ipc::Service, [f32], WarpedVolumeHeader>,
    elements: usize,
    // Declared last: the node outlives its ports.
    _node: Node<ipc::Service>,
}

impl WarpedVolumePublisher {
    /// Opens (or creates) `service` for volumes on `grid`, after checking that /dev/shm can
    /// hold them (iceoryx2 would die of SIGBUS otherwise).
    pub fn new(service: &str, grid: &Grid) -> Result<Self, ShmError> {
        let elements = grid.dims.iter().product::<usize>();
        let needed = bytes_needed(elements);
        if let Some(free) = shm_free_bytes().filter(|free| *free < needed) {
            return Err(ShmError::NoRoom { service: service.into(), free_mib: free as f64 / 1048576.0, needed_mib: needed as f64 / 1048576.0 });
        }
        let err = |message: String| ShmError::Service { service: service.into(), message };
        let node = NodeBuilder::new().signal_handling_mode(SignalHandlingMode::Disabled).create::<ipc::Service>().map_err(|e| err(format!("node: {e:?}")))?;
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
        tracing::info!("warped volumes on iceoryx2 service `{service}` ({:.1} MiB each)", (elements * 4) as f64 / 1048576.0);
        Ok(Self { service_name: service.into(), service: factory, publisher, elements, _node: node })
    }

    pub fn has_subscribers(&self) -> bool {
        self.service.dynamic_config().number_of_subscribers() > 0
    }

    /// Sends one volume: the samples are written once, into the loaned shared memory.
    pub fn publish(&mut self, grid: &Grid, data: &[f32], sequence: u64, stamp: Time) -> Result<usize, ShmError> {
        let err = |message: String| ShmError::Send { service: self.service_name.clone(), elements: data.len(), message };
        if data.len() != grid.dims.iter().product::<usize>() {
            return Err(err(format!("{} samples do not fill a {:?} grid", data.len(), grid.dims)));
        }
        if data.len() != self.elements {
            tracing::debug!("volume size changed: {} -> {} samples", self.elements, data.len());
            self.elements = data.len();
        }
        let mut sample = self.publisher.loan_slice_uninit(data.len()).map_err(|e| err(format!("{e:?}")))?;
        *sample.user_header_mut() = WarpedVolumeHeader {
            sequence,
            stamp_sec: stamp.sec,
            stamp_nanosec: stamp.nanosec,
            dims: grid.dims.map(|d| d as u32),
            padding: 0,
            spacing: grid.spacing,
            origin: grid.origin,
        };
        let sample = sample.write_from_slice(data);
        sample.send().map_err(|e| err(format!("{e:?}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_header_has_the_c_layout_readers_map() {
        // Offsets a C or ctypes reader computes for the same fields.
        assert_eq!(std::mem::size_of::<WarpedVolumeHeader>(), 8 + 4 + 4 + 12 + 4 + 24 + 24);
        assert_eq!(std::mem::offset_of!(WarpedVolumeHeader, dims), 16);
        assert_eq!(std::mem::offset_of!(WarpedVolumeHeader, spacing), 32);
        assert_eq!(std::mem::offset_of!(WarpedVolumeHeader, origin), 56);
    }

    #[test]
    fn too_little_shared_memory_is_refused_with_the_size_needed() {
        // A grid whose samples cannot fit in any /dev/shm here: 2^40 floats.
        let grid = Grid { dims: [1 << 14, 1 << 13, 1 << 13], spacing: [1.0; 3], origin: [0.0; 3], direction: nalgebra::Matrix3::identity() };
        let Err(e) = WarpedVolumePublisher::new("defvol/test_no_room", &grid) else { panic!("accepted a 4 TiB volume") };
        let message = e.to_string();
        assert!(message.contains("/dev/shm") && message.contains("needs") && message.contains("defvol/test_no_room"), "{message}");
    }

    #[test]
    fn a_subscriber_receives_the_volume_with_its_header() {
        let grid = Grid { dims: [8, 5, 3], spacing: [0.5, 0.5, 2.0], origin: [1.0, 2.0, 3.0], direction: nalgebra::Matrix3::identity() };
        let service = format!("defvol/test_{}", std::process::id());
        let mut publisher = WarpedVolumePublisher::new(&service, &grid).unwrap();
        let node = NodeBuilder::new().create::<ipc::Service>().unwrap();
        let factory = node.service_builder(&service.as_str().try_into().unwrap()).publish_subscribe::<[f32]>().user_header::<WarpedVolumeHeader>().open().unwrap();
        let subscriber = factory.subscriber_builder().create().unwrap();
        assert!(publisher.has_subscribers());
        let data: Vec<f32> = (0..120).map(|i| i as f32 * 0.25).collect();
        publisher.publish(&grid, &data, 7, Time { sec: 3, nanosec: 9 }).unwrap();
        let sample = subscriber.receive().unwrap().unwrap();
        assert_eq!(sample.payload(), &data[..]);
        let h = sample.user_header();
        assert_eq!((h.sequence, h.stamp_sec, h.stamp_nanosec, h.dims, h.spacing, h.origin), (7, 3, 9, [8, 5, 3], [0.5, 0.5, 2.0], [1.0, 2.0, 3.0]));
        // A subscriber that never reads does not block: later sends still go through.
        for sequence in 8..20 {
            publisher.publish(&grid, &data, sequence, Time::default()).unwrap();
        }
    }
}
