//! ROS 2 message types as serde structs, field for field in the order of their `.msg` texts
//! in `msg/` (tested), and their CDR encoding (the wire format of DDS and of rosbag2's
//! MCAP files).

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MsgError {
    #[error("{what}: {message}")]
    Cdr { what: String, message: String },
    #[error("{what}: {len} bytes is too short for a CDR encapsulation header")]
    NoHeader { what: String, len: usize },
    #[error("{what}: encapsulation {kind:#06x} is not plain CDR (0x0000 or 0x0001)")]
    Encapsulation { what: String, kind: u16 },
    #[error("unknown message type `{0}`")]
    UnknownType(String),
}

/// The `.msg` texts of `msg/`, by full name.
pub const DEFINITIONS: [(&str, &str); 6] = [
    ("builtin_interfaces/msg/Time", include_str!("../msg/builtin_interfaces/msg/Time.msg")),
    ("std_msgs/msg/Header", include_str!("../msg/std_msgs/msg/Header.msg")),
    ("geometry_msgs/msg/Point", include_str!("../msg/geometry_msgs/msg/Point.msg")),
    ("geometry_msgs/msg/Quaternion", include_str!("../msg/geometry_msgs/msg/Quaternion.msg")),
    ("geometry_msgs/msg/Pose", include_str!("../msg/geometry_msgs/msg/Pose.msg")),
    ("geometry_msgs/msg/PoseStamped", include_str!("../msg/geometry_msgs/msg/PoseStamped.msg")),
];

/// A message type with its ROS 2 name.
pub trait Message: Serialize + DeserializeOwned {
    /// "package/msg/Type".
    const NAME: &'static str;
}

/// builtin_interfaces/msg/Time.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    pub fn from_secs(t: f64) -> Self {
        let sec = t.floor();
        Self { sec: sec as i32, nanosec: (((t - sec) * 1e9).round() as u32).min(999_999_999) }
    }
    pub fn as_secs(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }
}

/// std_msgs/msg/Header.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// geometry_msgs/msg/Point.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
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

/// geometry_msgs/msg/PoseStamped.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

impl Message for Time {
    const NAME: &'static str = "builtin_interfaces/msg/Time";
}
impl Message for Header {
    const NAME: &'static str = "std_msgs/msg/Header";
}
impl Message for Point {
    const NAME: &'static str = "geometry_msgs/msg/Point";
}
impl Message for Quaternion {
    const NAME: &'static str = "geometry_msgs/msg/Quaternion";
}
impl Message for Pose {
    const NAME: &'static str = "geometry_msgs/msg/Pose";
}
impl Message for PoseStamped {
    const NAME: &'static str = "geometry_msgs/msg/PoseStamped";
}

/// Little-endian CDR with its 4-byte encapsulation header (as DDS and rosbag2 write it).
pub fn encode<T: Message>(value: &T) -> Result<Vec<u8>, MsgError> {
    let body = cdr_encoding::to_vec::<T, byteorder::LittleEndian>(value).map_err(|e| MsgError::Cdr { what: T::NAME.into(), message: e.to_string() })?;
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend([0x00, 0x01, 0x00, 0x00]);
    out.extend(body);
    Ok(out)
}

/// Decodes CDR (little- or big-endian, after its encapsulation header); `what` names the
/// source for errors (a topic, a file).
pub fn decode<T: Message>(bytes: &[u8], what: &str) -> Result<T, MsgError> {
    let (Some(header), Some(body)) = (bytes.get(..4), bytes.get(4..)) else {
        return Err(MsgError::NoHeader { what: what.into(), len: bytes.len() });
    };
    let kind = u16::from_be_bytes([header[0], header[1]]);
    let decoded = match kind {
        0x0001 => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(body),
        0x0000 => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body),
        _ => return Err(MsgError::Encapsulation { what: what.into(), kind }),
    };
    decoded.map(|(value, _)| value).map_err(|e| MsgError::Cdr { what: format!("{what} ({})", T::NAME), message: e.to_string() })
}

/// The field types of a `.msg` text that are other messages, as full names.
fn dependencies(package: &str, text: &str) -> Vec<String> {
    text.lines()
        .filter_map(|line| {
            let line = line.split('#').next()?.trim();
            let ty = line.split_whitespace().next()?;
            let base = ty.split('[').next()?;
            const PRIMITIVES: [&str; 17] = ["bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "string", "wstring", "time", "duration"];
            if PRIMITIVES.contains(&base) || base.starts_with("string<") {
                return None;
            }
            Some(match base.split_once('/') {
                Some((pkg, name)) => format!("{pkg}/msg/{name}"),
                None => format!("{package}/msg/{base}"),
            })
        })
        .collect()
}

/// The `ros2msg` schema rosbag2 writes for `name`: its text, then each dependency once as
/// `====…` (80), `MSG: pkg/Type` and its text.
pub fn ros2msg_schema(name: &str) -> Result<String, MsgError> {
    let text_of = |n: &str| DEFINITIONS.iter().find(|(d, _)| *d == n).map(|(_, t)| *t).ok_or_else(|| MsgError::UnknownType(n.to_owned()));
    let mut schema = text_of(name)?.trim_end().to_owned();
    let mut seen = vec![name.to_owned()];
    let mut queue = vec![name.to_owned()];
    while let Some(current) = queue.pop() {
        let package = current.split('/').next().unwrap_or_default();
        for dep in dependencies(package, text_of(&current)?) {
            if seen.contains(&dep) {
                continue;
            }
            let short = dep.replacen("/msg/", "/", 1);
            schema.push_str(&format!("\n{}\nMSG: {short}\n{}", "=".repeat(80), text_of(&dep)?.trim_end()));
            seen.push(dep.clone());
            queue.insert(0, dep);
        }
    }
    Ok(schema)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_reflection::{ContainerFormat, Format, Tracer, TracerConfig};

    /// (type, name) of each field line of a `.msg` text; constants left out.
    fn msg_fields(text: &str) -> Vec<(String, String)> {
        text.lines()
            .filter_map(|line| {
                let line = line.split('#').next()?.trim();
                let mut parts = line.split_whitespace();
                let (ty, name) = (parts.next()?, parts.next()?);
                (!name.contains('=')).then(|| (ty.to_owned(), name.to_owned()))
            })
            .collect()
    }

    /// The struct's fields as serde sees them, against its `.msg` text.
    fn check<T: Message>(registry: &serde_reflection::Registry, rust_name: &str) {
        let Some(ContainerFormat::Struct(fields)) = registry.get(rust_name) else { panic!("{} is not a struct", T::NAME) };
        let text = DEFINITIONS.iter().find(|(n, _)| *n == T::NAME).unwrap().1;
        let expected = msg_fields(text);
        let got: Vec<&str> = fields.iter().map(|f| f.name.as_str()).collect();
        let want: Vec<&str> = expected.iter().map(|(_, n)| n.as_str()).collect();
        assert_eq!(got, want, "{}: serde fields against the .msg text", T::NAME);
        for (field, (ty, _)) in fields.iter().zip(&expected) {
            let same = match (&field.value, ty.as_str()) {
                (Format::I32, "int32") | (Format::U32, "uint32") | (Format::F64, "float64") | (Format::Str, "string") => true,
                (Format::TypeName(rust), msg) => msg.rsplit('/').next() == Some(rust.as_str()),
                _ => false,
            };
            assert!(same, "{}: field {} is {:?}, the .msg says {ty}", T::NAME, field.name, field.value);
        }
    }

    #[test]
    fn every_struct_matches_its_msg_text() {
        let mut tracer = Tracer::new(TracerConfig::default());
        tracer.trace_simple_type::<PoseStamped>().unwrap();
        let registry = tracer.registry().unwrap();
        check::<Time>(&registry, "Time");
        check::<Header>(&registry, "Header");
        check::<Point>(&registry, "Point");
        check::<Quaternion>(&registry, "Quaternion");
        check::<Pose>(&registry, "Pose");
        check::<PoseStamped>(&registry, "PoseStamped");
        assert_eq!(registry.len(), DEFINITIONS.len(), "every traced struct has a .msg text");
    }

    #[test]
    fn pose_stamped_cdr_is_laid_out_as_the_omg_spec_says() {
        let msg = PoseStamped {
            header: Header { stamp: Time { sec: 7, nanosec: 5 }, frame_id: "tool".into() },
            pose: Pose { position: Point { x: 1.0, y: -2.0, z: 0.5 }, orientation: Quaternion::default() },
        };
        // By hand: header; sec, nanosec; string length 5 ("tool\0"); pad to 8 (offsets from
        // the body start); seven doubles.
        let mut want = vec![0x00, 0x01, 0x00, 0x00];
        want.extend(7i32.to_le_bytes());
        want.extend(5u32.to_le_bytes());
        want.extend(5u32.to_le_bytes());
        want.extend(b"tool\0");
        want.extend([0u8; 7]); // body offset 17 -> 24
        for v in [1.0f64, -2.0, 0.5, 0.0, 0.0, 0.0, 1.0] {
            want.extend(v.to_le_bytes());
        }
        assert_eq!(encode(&msg).unwrap(), want);
        assert_eq!(decode::<PoseStamped>(&want, "test").unwrap(), msg);
        // Big-endian encapsulation decodes too; a truncated sample is an error naming it.
        let mut be = vec![0x00, 0x00, 0x00, 0x00];
        be.extend(cdr_encoding::to_vec::<PoseStamped, byteorder::BigEndian>(&msg).unwrap());
        assert_eq!(decode::<PoseStamped>(&be, "test").unwrap(), msg);
        let err = decode::<PoseStamped>(&want[..30], "/tool_pose").unwrap_err().to_string();
        assert!(err.contains("/tool_pose"), "{err}");
    }

    #[test]
    fn schemas_carry_their_dependencies_in_rosbag2_form() {
        let schema = ros2msg_schema("geometry_msgs/msg/PoseStamped").unwrap();
        let sep = "=".repeat(80);
        for dep in ["MSG: std_msgs/Header", "MSG: geometry_msgs/Pose", "MSG: builtin_interfaces/Time", "MSG: geometry_msgs/Point", "MSG: geometry_msgs/Quaternion"] {
            assert_eq!(schema.matches(&format!("{sep}\n{dep}\n")).count(), 1, "{dep} once in\n{schema}");
        }
        assert!(schema.starts_with("# A Pose with reference coordinate frame and timestamp"));
        assert!(matches!(ros2msg_schema("nav_msgs/msg/Odometry"), Err(MsgError::UnknownType(_))));
    }
}
