//! The ROS 2 side: arguments and parameters (always built: they are plain parsing), the
//! DDS participant and the node (the `ros` feature). The node is a thin layer: it turns
//! topics into pipeline inputs and pipeline outputs into topics.

pub mod args;
#[cfg(feature = "ros")]
mod configured;
#[cfg(feature = "ros")]
pub mod dds;
#[cfg(feature = "ros")]
mod error;
#[cfg(feature = "ros")]
mod feedback_thread;
pub mod lifecycle;
#[cfg(feature = "ros")]
mod managed;
#[cfg(feature = "ros")]
pub mod node;
#[cfg(feature = "ros")]
mod parameters;
#[cfg(feature = "ros")]
mod socket_buffers;
#[cfg(feature = "ros")]
pub mod wire;

#[cfg(feature = "ros")]
pub use error::NodeError;
