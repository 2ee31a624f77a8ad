//! ROS 2 message types as serde structs, field for field in the order of their `.msg` texts
//! in `msg/` (tested), and their CDR encoding (the wire format of DDS and of rosbag2's
//! MCAP files).

mod types;

use serde::de::DeserializeOwned;
use serde::Serialize;

pub use types::*;

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

/// The `.msg` texts of `msg/` (and of `defvol_interfaces/`, defvol's own), by full name.
pub const DEFINITIONS: [(&str, &str); 25] = [
    ("builtin_interfaces/msg/Time", include_str!("../../msg/builtin_interfaces/msg/Time.msg")),
    ("builtin_interfaces/msg/Duration", include_str!("../../msg/builtin_interfaces/msg/Duration.msg")),
    ("std_msgs/msg/Header", include_str!("../../msg/std_msgs/msg/Header.msg")),
    ("std_msgs/msg/ColorRGBA", include_str!("../../msg/std_msgs/msg/ColorRGBA.msg")),
    ("geometry_msgs/msg/Point", include_str!("../../msg/geometry_msgs/msg/Point.msg")),
    ("geometry_msgs/msg/Vector3", include_str!("../../msg/geometry_msgs/msg/Vector3.msg")),
    ("geometry_msgs/msg/Quaternion", include_str!("../../msg/geometry_msgs/msg/Quaternion.msg")),
    ("geometry_msgs/msg/Pose", include_str!("../../msg/geometry_msgs/msg/Pose.msg")),
    ("geometry_msgs/msg/PoseStamped", include_str!("../../msg/geometry_msgs/msg/PoseStamped.msg")),
    ("geometry_msgs/msg/Wrench", include_str!("../../msg/geometry_msgs/msg/Wrench.msg")),
    ("geometry_msgs/msg/WrenchStamped", include_str!("../../msg/geometry_msgs/msg/WrenchStamped.msg")),
    ("sensor_msgs/msg/Image", include_str!("../../msg/sensor_msgs/msg/Image.msg")),
    ("sensor_msgs/msg/CompressedImage", include_str!("../../msg/sensor_msgs/msg/CompressedImage.msg")),
    ("visualization_msgs/msg/UVCoordinate", include_str!("../../msg/visualization_msgs/msg/UVCoordinate.msg")),
    ("visualization_msgs/msg/MeshFile", include_str!("../../msg/visualization_msgs/msg/MeshFile.msg")),
    ("visualization_msgs/msg/Marker", include_str!("../../msg/visualization_msgs/msg/Marker.msg")),
    ("diagnostic_msgs/msg/KeyValue", include_str!("../../msg/diagnostic_msgs/msg/KeyValue.msg")),
    ("diagnostic_msgs/msg/DiagnosticStatus", include_str!("../../msg/diagnostic_msgs/msg/DiagnosticStatus.msg")),
    ("diagnostic_msgs/msg/DiagnosticArray", include_str!("../../msg/diagnostic_msgs/msg/DiagnosticArray.msg")),
    ("defvol_interfaces/msg/DeformedMesh", include_str!("../../defvol_interfaces/msg/DeformedMesh.msg")),
    ("defvol_interfaces/msg/WarpedVolumeInfo", include_str!("../../defvol_interfaces/msg/WarpedVolumeInfo.msg")),
    ("lifecycle_msgs/msg/State", include_str!("../../msg/lifecycle_msgs/msg/State.msg")),
    ("lifecycle_msgs/msg/Transition", include_str!("../../msg/lifecycle_msgs/msg/Transition.msg")),
    (
        "lifecycle_msgs/msg/TransitionDescription",
        include_str!("../../msg/lifecycle_msgs/msg/TransitionDescription.msg"),
    ),
    ("lifecycle_msgs/msg/TransitionEvent", include_str!("../../msg/lifecycle_msgs/msg/TransitionEvent.msg")),
];

/// The `.srv` texts of `msg/` (and of `defvol_interfaces/`), by full name.
pub const SERVICES: [(&str, &str); 6] = [
    ("std_srvs/srv/Trigger", include_str!("../../msg/std_srvs/srv/Trigger.srv")),
    ("defvol_interfaces/srv/LoadScene", include_str!("../../defvol_interfaces/srv/LoadScene.srv")),
    ("lifecycle_msgs/srv/ChangeState", include_str!("../../msg/lifecycle_msgs/srv/ChangeState.srv")),
    ("lifecycle_msgs/srv/GetState", include_str!("../../msg/lifecycle_msgs/srv/GetState.srv")),
    ("lifecycle_msgs/srv/GetAvailableStates", include_str!("../../msg/lifecycle_msgs/srv/GetAvailableStates.srv")),
    (
        "lifecycle_msgs/srv/GetAvailableTransitions",
        include_str!("../../msg/lifecycle_msgs/srv/GetAvailableTransitions.srv"),
    ),
];

/// A message type with its ROS 2 name.
pub trait Message: Serialize + DeserializeOwned {
    /// "package/msg/Type".
    const NAME: &'static str;
}

/// Little-endian CDR with its 4-byte encapsulation header (as DDS and rosbag2 write it).
pub fn encode<T: Message>(value: &T) -> Result<Vec<u8>, MsgError> {
    let body = cdr_encoding::to_vec::<T, byteorder::LittleEndian>(value)
        .map_err(|e| MsgError::Cdr { what: T::NAME.into(), message: e.to_string() })?;
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
    decoded
        .map(|(value, _)| value)
        .map_err(|e| MsgError::Cdr { what: format!("{what} ({})", T::NAME), message: e.to_string() })
}

/// The field types of a `.msg` text that are other messages, as full names.
fn dependencies(package: &str, text: &str) -> Vec<String> {
    text.lines()
        .filter_map(|line| {
            let line = line.split('#').next()?.trim();
            let ty = line.split_whitespace().next()?;
            let base = ty.split('[').next()?;
            const PRIMITIVES: [&str; 17] = [
                "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
                "int64", "uint64", "string", "wstring", "time", "duration",
            ];
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
    let text_of = |n: &str| {
        DEFINITIONS.iter().find(|(d, _)| *d == n).map(|(_, t)| *t).ok_or_else(|| MsgError::UnknownType(n.to_owned()))
    };
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

    /// (type, name) of each field line of a `.msg` text; constants (`uint8 NAME = 1`,
    /// `NAME=1`) left out.
    fn msg_fields(text: &str) -> Vec<(String, String)> {
        text.lines()
            .filter_map(|line| {
                let line = line.split('#').next()?.trim();
                let mut parts = line.split_whitespace();
                let (ty, name) = (parts.next()?, parts.next()?);
                (!line.contains('=')).then(|| (ty.to_owned(), name.to_owned()))
            })
            .collect()
    }

    /// Whether a serde format is the `.msg` field type `ty`.
    fn same_type(format: &Format, ty: &str) -> bool {
        if let Some(element) = ty.strip_suffix("[]") {
            return match format {
                Format::Bytes => element == "uint8",
                Format::Seq(inner) => same_type(inner, element),
                _ => false,
            };
        }
        if let Some((element, size)) = ty.strip_suffix(']').and_then(|t| t.split_once('[')) {
            return matches!(format, Format::TupleArray { content, size: n } if size.parse() == Ok(*n) && same_type(content, element));
        }
        match (format, ty) {
            (Format::Bool, "bool")
            | (Format::U8, "uint8" | "byte")
            | (Format::I32, "int32")
            | (Format::U32, "uint32")
            | (Format::U64, "uint64")
            | (Format::F32, "float32")
            | (Format::F64, "float64")
            | (Format::Str, "string") => true,
            (Format::TypeName(rust), msg) => msg.rsplit('/').next() == Some(rust.as_str()),
            _ => false,
        }
    }

    /// The fields of `rust_name` as serde sees them, against a `.msg` text.
    fn check_fields(registry: &serde_reflection::Registry, rust_name: &str, what: &str, text: &str) {
        let Some(ContainerFormat::Struct(fields)) = registry.get(rust_name) else {
            panic!("{what}: {rust_name} is not a struct")
        };
        let expected = msg_fields(text);
        let got: Vec<&str> = fields.iter().map(|f| f.name.as_str()).collect();
        let want: Vec<&str> = expected.iter().map(|(_, n)| n.as_str()).collect();
        assert_eq!(got, want, "{what}: serde fields against the .msg text");
        for (field, (ty, _)) in fields.iter().zip(&expected) {
            assert!(
                same_type(&field.value, ty),
                "{what}: field {} is {:?}, the .msg says {ty}",
                field.name,
                field.value
            );
        }
    }

    fn check<T: Message>(registry: &serde_reflection::Registry) {
        let text = DEFINITIONS.iter().find(|(n, _)| *n == T::NAME).unwrap().1;
        check_fields(registry, T::NAME.rsplit('/').next().unwrap(), T::NAME, text);
    }

    #[test]
    fn every_struct_matches_its_msg_text() {
        let mut tracer = Tracer::new(TracerConfig::default());
        let traces: [fn(&mut Tracer) -> serde_reflection::Result<()>; 16] = [
            |t: &mut Tracer| t.trace_simple_type::<PoseStamped>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<WrenchStamped>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<Image>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<Marker>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<DiagnosticArray>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<DeformedMesh>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<WarpedVolumeInfo>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<TriggerRequest>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<TriggerResponse>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<LoadSceneRequest>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<TransitionEvent>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<ChangeStateRequest>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<ChangeStateResponse>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<GetStateResponse>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<GetAvailableStatesResponse>().map(drop),
            |t: &mut Tracer| t.trace_simple_type::<GetAvailableTransitionsResponse>().map(drop),
        ];
        for trace in traces {
            trace(&mut tracer).unwrap();
        }
        let registry = tracer.registry().unwrap();
        check::<Time>(&registry);
        check::<Duration>(&registry);
        check::<Header>(&registry);
        check::<ColorRGBA>(&registry);
        check::<Point>(&registry);
        check::<Vector3>(&registry);
        check::<Quaternion>(&registry);
        check::<Pose>(&registry);
        check::<PoseStamped>(&registry);
        check::<Wrench>(&registry);
        check::<WrenchStamped>(&registry);
        check::<Image>(&registry);
        check::<CompressedImage>(&registry);
        check::<UVCoordinate>(&registry);
        check::<MeshFile>(&registry);
        check::<Marker>(&registry);
        check::<KeyValue>(&registry);
        check::<DiagnosticStatus>(&registry);
        check::<DiagnosticArray>(&registry);
        check::<DeformedMesh>(&registry);
        check::<WarpedVolumeInfo>(&registry);
        check::<LifecycleState>(&registry);
        check::<LifecycleTransition>(&registry);
        check::<TransitionDescription>(&registry);
        check::<TransitionEvent>(&registry);
        // Services: each half against its side of the `---`.
        let halves = |name: &str| {
            let text = SERVICES.iter().find(|(n, _)| *n == name).unwrap().1;
            let (request, response) = text.split_once("---").unwrap();
            (request.to_owned(), response.to_owned())
        };
        let (request, response) = halves("std_srvs/srv/Trigger");
        assert!(msg_fields(&request).is_empty(), "Trigger's request is empty: CDR's placeholder byte stands for it");
        check_fields(&registry, "TriggerResponse", "Trigger response", &response);
        let (request, response) = halves("defvol_interfaces/srv/LoadScene");
        check_fields(&registry, "LoadSceneRequest", "LoadScene request", &request);
        check_fields(&registry, "TriggerResponse", "LoadScene response", &response);
        let (request, response) = halves("lifecycle_msgs/srv/ChangeState");
        check_fields(&registry, "ChangeStateRequest", "ChangeState request", &request);
        check_fields(&registry, "ChangeStateResponse", "ChangeState response", &response);
        for (service, rust) in [
            ("GetState", "GetStateResponse"),
            ("GetAvailableStates", "GetAvailableStatesResponse"),
            ("GetAvailableTransitions", "GetAvailableTransitionsResponse"),
        ] {
            let (request, response) = halves(&format!("lifecycle_msgs/srv/{service}"));
            assert!(msg_fields(&request).is_empty(), "{service}'s request is empty: TriggerRequest's placeholder");
            check_fields(&registry, rust, service, &response);
        }
        // Every traced struct has a text: the 25 messages and the 8 service halves.
        assert_eq!(registry.len(), DEFINITIONS.len() + 8);
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
        for dep in [
            "MSG: std_msgs/Header",
            "MSG: geometry_msgs/Pose",
            "MSG: builtin_interfaces/Time",
            "MSG: geometry_msgs/Point",
            "MSG: geometry_msgs/Quaternion",
        ] {
            assert_eq!(schema.matches(&format!("{sep}\n{dep}\n")).count(), 1, "{dep} once in\n{schema}");
        }
        assert!(schema.starts_with("# A Pose with reference coordinate frame and timestamp"));
        assert!(matches!(ros2msg_schema("nav_msgs/msg/Odometry"), Err(MsgError::UnknownType(_))));
    }
}
