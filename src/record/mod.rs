//! Session records: rosbag2-compatible MCAP files (the `mcap` feature), rerun logs (the
//! `rerun` feature), and reading recorded tool inputs back for replay.

#[cfg(feature = "mcap")]
pub mod bag;
#[cfg(feature = "mcap")]
pub mod bag_dir;
#[cfg(feature = "mcap")]
pub mod bag_thread;
#[cfg(feature = "mcap")]
pub mod recover;
#[cfg(feature = "rerun")]
pub mod rerun_log;

use std::time::Duration;

/// How a recording splits and how often it reaches the disk.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BagOptions {
    /// A bag directory starts a new split once a split spans this long (message times).
    pub max_duration: Option<Duration>,
    /// … or once its file reaches this many bytes.
    pub max_bytes: Option<u64>,
    /// The open chunk is closed and written at least this often.
    pub flush_interval: Duration,
}

impl Default for BagOptions {
    fn default() -> Self {
        Self { max_duration: None, max_bytes: None, flush_interval: Duration::from_millis(500) }
    }
}

/// The QoS a topic is offered with, as rosbag2 records it (and as the node publishes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Qos {
    /// Best effort, keep last 5: sensor inputs and high-rate outputs.
    SensorData,
    /// Reliable, keep last 10, volatile.
    Reliable,
    /// Reliable, keep last 1, transient local: latched topology and info topics.
    Latched,
}

impl Qos {
    /// rosbag2's `offered_qos_profiles` YAML (rmw's integer enums, which every rosbag2
    /// release reads).
    pub fn offered_profiles_yaml(self) -> String {
        let (history_depth, reliability, durability) = match self {
            Qos::SensorData => (5, 2, 2),
            Qos::Reliable => (10, 1, 2),
            Qos::Latched => (1, 1, 1),
        };
        let zero = "\n    sec: 0\n    nsec: 0";
        format!(
            "- history: 1\n  depth: {history_depth}\n  reliability: {reliability}\n  durability: {durability}\n  deadline:{zero}\n  lifespan:{zero}\n  liveliness: 1\n  liveliness_lease_duration:{zero}\n  avoid_ros_namespace_conventions: false\n"
        )
    }
}
