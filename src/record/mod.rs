//! Session records: rosbag2-compatible MCAP files (the `mcap` feature), rerun logs (the
//! `rerun` feature), and reading recorded tool inputs back for replay.

#[cfg(feature = "mcap")]
pub mod bag;
#[cfg(feature = "rerun")]
pub mod rerun_log;

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
