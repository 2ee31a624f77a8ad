//! The message structs. Field order and types follow the `.msg` texts in `msg/` exactly
//! (checked by `every_struct_matches_its_msg_text`): CDR has no field names, so order is
//! the wire format.

use serde::{Deserialize, Serialize};

use super::Message;

/// builtin_interfaces/msg/Time.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    pub fn from_secs(t: f64) -> Self {
        let sec = t.floor();
        Self { sec: sec as i32, nanosec: (((t - sec) * 1e9).round() as u32).min(999_999_999) }
    }
    /// The wall clock (what a live node stamps with).
    pub fn now() -> Self {
        let since_epoch = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        Self::from_nanos(since_epoch.as_nanos() as u64)
    }
    pub fn from_nanos(ns: u64) -> Self {
        Self { sec: (ns / 1_000_000_000) as i32, nanosec: (ns % 1_000_000_000) as u32 }
    }
    pub fn as_secs(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }
    /// Nanoseconds since the epoch (0 for times before it).
    pub fn as_nanos(&self) -> u64 {
        u64::try_from(self.sec).map_or(0, |s| s * 1_000_000_000 + u64::from(self.nanosec))
    }
}

/// builtin_interfaces/msg/Duration.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Duration {
    pub sec: i32,
    pub nanosec: u32,
}

/// std_msgs/msg/Header.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// std_msgs/msg/ColorRGBA.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRGBA {
    pub r: f32,
    pub g: f32,
    pub b: f32,
    pub a: f32,
}

/// geometry_msgs/msg/Point.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// geometry_msgs/msg/Vector3.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl From<nalgebra::Vector3<f64>> for Vector3 {
    fn from(v: nalgebra::Vector3<f64>) -> Self {
        Self { x: v.x, y: v.y, z: v.z }
    }
}
impl From<Vector3> for nalgebra::Vector3<f64> {
    fn from(v: Vector3) -> Self {
        Self::new(v.x, v.y, v.z)
    }
}

/// geometry_msgs/msg/Quaternion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }
    }
}

/// geometry_msgs/msg/Pose.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}

impl Pose {
    pub fn from_isometry(iso: &nalgebra::Isometry3<f64>) -> Self {
        let (t, q) = (iso.translation.vector, iso.rotation.quaternion());
        Self { position: Point { x: t.x, y: t.y, z: t.z }, orientation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w } }
    }
}

/// geometry_msgs/msg/PoseStamped.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

/// geometry_msgs/msg/Wrench.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Wrench {
    pub force: Vector3,
    pub torque: Vector3,
}

/// geometry_msgs/msg/WrenchStamped.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct WrenchStamped {
    pub header: Header,
    pub wrench: Wrench,
}

/// sensor_msgs/msg/Image.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// sensor_msgs/msg/CompressedImage.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// visualization_msgs/msg/UVCoordinate.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UVCoordinate {
    pub u: f32,
    pub v: f32,
}

/// visualization_msgs/msg/MeshFile.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshFile {
    pub filename: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// visualization_msgs/msg/Marker.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    pub header: Header,
    pub ns: String,
    pub id: i32,
    #[serde(rename = "type")]
    pub kind: i32,
    pub action: i32,
    pub pose: Pose,
    pub scale: Vector3,
    pub color: ColorRGBA,
    pub lifetime: Duration,
    pub frame_locked: bool,
    pub points: Vec<Point>,
    pub colors: Vec<ColorRGBA>,
    pub texture_resource: String,
    pub texture: CompressedImage,
    pub uv_coordinates: Vec<UVCoordinate>,
    pub text: String,
    pub mesh_resource: String,
    pub mesh_file: MeshFile,
    pub mesh_use_embedded_materials: bool,
}

impl Marker {
    pub const TRIANGLE_LIST: i32 = 11;
    pub const ADD: i32 = 0;
}

/// diagnostic_msgs/msg/KeyValue.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}

/// diagnostic_msgs/msg/DiagnosticStatus.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<KeyValue>,
}

impl DiagnosticStatus {
    pub const OK: u8 = 0;
    pub const WARN: u8 = 1;
    pub const ERROR: u8 = 2;
}

/// diagnostic_msgs/msg/DiagnosticArray.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

/// defvol_interfaces/msg/DeformedMesh.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DeformedMesh {
    pub header: Header,
    pub positions: Vec<f32>,
    pub triangles: Vec<u32>,
    pub scalar_name: String,
    pub scalars: Vec<f32>,
    pub step: u64,
}

/// defvol_interfaces/msg/WarpedVolumeInfo.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct WarpedVolumeInfo {
    pub header: Header,
    pub service_name: String,
    pub sequence: u64,
    pub dims: [u32; 3],
    pub spacing: [f64; 3],
    pub origin: [f64; 3],
    /// Row major.
    pub direction: [f64; 9],
}

/// The request half of std_srvs/srv/Trigger: an empty message, which CDR carries as one
/// placeholder byte (as rosidl generates it).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct TriggerRequest {
    pub structure_needs_at_least_one_member: u8,
}

/// The response half of std_srvs/srv/Trigger.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TriggerResponse {
    pub success: bool,
    pub message: String,
}

/// The request half of defvol_interfaces/srv/LoadScene.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LoadSceneRequest {
    pub scene: String,
}

/// The response half of defvol_interfaces/srv/LoadScene (the same fields as Trigger's).
pub type LoadSceneResponse = TriggerResponse;

/// lifecycle_msgs/msg/State: a managed node's state (the ids are the `.msg` constants).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename = "State")]
pub struct LifecycleState {
    pub id: u8,
    pub label: String,
}

/// lifecycle_msgs/msg/Transition.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename = "Transition")]
pub struct LifecycleTransition {
    pub id: u8,
    pub label: String,
}

/// lifecycle_msgs/msg/TransitionDescription: one edge of the state machine.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TransitionDescription {
    pub transition: LifecycleTransition,
    pub start_state: LifecycleState,
    pub goal_state: LifecycleState,
}

/// lifecycle_msgs/msg/TransitionEvent: what `~/transition_event` says at each state change.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TransitionEvent {
    /// Nanoseconds since the epoch.
    pub timestamp: u64,
    pub transition: LifecycleTransition,
    pub start_state: LifecycleState,
    pub goal_state: LifecycleState,
}

/// The request half of lifecycle_msgs/srv/ChangeState.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ChangeStateRequest {
    pub transition: LifecycleTransition,
}

/// The response half of lifecycle_msgs/srv/ChangeState.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ChangeStateResponse {
    pub success: bool,
}

/// The response half of lifecycle_msgs/srv/GetState (its request is empty: a
/// [`TriggerRequest`]'s placeholder byte, as for every empty request).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct GetStateResponse {
    pub current_state: LifecycleState,
}

/// The response half of lifecycle_msgs/srv/GetAvailableStates.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct GetAvailableStatesResponse {
    pub available_states: Vec<LifecycleState>,
}

/// The response half of lifecycle_msgs/srv/GetAvailableTransitions.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct GetAvailableTransitionsResponse {
    pub available_transitions: Vec<TransitionDescription>,
}

macro_rules! named {
    ($($ty:ty => $name:literal),* $(,)?) => {
        $(impl Message for $ty {
            const NAME: &'static str = $name;
        })*
    };
}

named! {
    Time => "builtin_interfaces/msg/Time",
    Duration => "builtin_interfaces/msg/Duration",
    Header => "std_msgs/msg/Header",
    ColorRGBA => "std_msgs/msg/ColorRGBA",
    Point => "geometry_msgs/msg/Point",
    Vector3 => "geometry_msgs/msg/Vector3",
    Quaternion => "geometry_msgs/msg/Quaternion",
    Pose => "geometry_msgs/msg/Pose",
    PoseStamped => "geometry_msgs/msg/PoseStamped",
    Wrench => "geometry_msgs/msg/Wrench",
    WrenchStamped => "geometry_msgs/msg/WrenchStamped",
    Image => "sensor_msgs/msg/Image",
    CompressedImage => "sensor_msgs/msg/CompressedImage",
    UVCoordinate => "visualization_msgs/msg/UVCoordinate",
    MeshFile => "visualization_msgs/msg/MeshFile",
    Marker => "visualization_msgs/msg/Marker",
    KeyValue => "diagnostic_msgs/msg/KeyValue",
    DiagnosticStatus => "diagnostic_msgs/msg/DiagnosticStatus",
    DiagnosticArray => "diagnostic_msgs/msg/DiagnosticArray",
    DeformedMesh => "defvol_interfaces/msg/DeformedMesh",
    WarpedVolumeInfo => "defvol_interfaces/msg/WarpedVolumeInfo",
    LifecycleState => "lifecycle_msgs/msg/State",
    LifecycleTransition => "lifecycle_msgs/msg/Transition",
    TransitionDescription => "lifecycle_msgs/msg/TransitionDescription",
    TransitionEvent => "lifecycle_msgs/msg/TransitionEvent",
}
