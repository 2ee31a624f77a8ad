//! What can stop the node: its arguments, DDS, ROS 2 entities, the pipeline, the recording.

use super::{args, dds};
use crate::pipeline::PipelineError;
use crate::session::SessionError;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum NodeError {
    #[error(transparent)]
    Args(#[from] args::ArgsError),
    #[error(transparent)]
    Dds(#[from] dds::DdsError),
    #[error("ROS 2: {0}")]
    Ros(String),
    /// A command-line parameter refused before anything is built, in rclcpp's words.
    #[error("{0}")]
    Refused(String),
    /// `--help` or `--version` was asked for: the text to print, not an error.
    #[error("{0}")]
    Help(String),
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error(transparent)]
    Backend(#[from] crate::backend::BackendError),
    #[error(transparent)]
    Session(#[from] SessionError),
}

pub(super) fn ros_err(what: &str) -> impl Fn(ros2_client::CreateError) -> NodeError + '_ {
    move |e| NodeError::Ros(format!("{what}: {e:?}"))
}
