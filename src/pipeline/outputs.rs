//! The pipeline's state as ROS messages.

use nalgebra::Vector3;

use crate::mesh::TetMesh;
use crate::msgs::{self, ColorRGBA, DeformedMesh, Header, Image, Marker, Point, Time, Wrench, WrenchStamped};
use crate::solver::StepReport;

pub(super) fn header(stamp: Time, frame: &str) -> Header {
    Header { stamp, frame_id: frame.to_owned() }
}

/// The reaction on tool `index` (what its haptic device renders), world frame.
pub(super) fn feedback(report: &StepReport, index: usize, stamp: Time, frame: &str) -> WrenchStamped {
    let v = |a: [f64; 3]| msgs::Vector3 { x: a[0], y: a[1], z: a[2] };
    let reaction = report.reaction(index);
    WrenchStamped {
        header: header(stamp, frame),
        wrench: Wrench { force: v(reaction.force), torque: v(reaction.torque) },
    }
}

/// A tool's feedback answered from its local model between steps.
pub(super) fn local_feedback(answer: &crate::solver::LocalAnswer, stamp: Time, frame: &str) -> WrenchStamped {
    let (f, t) = (answer.force, answer.torque);
    WrenchStamped {
        header: header(stamp, frame),
        wrench: Wrench {
            force: msgs::Vector3 { x: f.x, y: f.y, z: f.z },
            torque: msgs::Vector3 { x: t.x, y: t.y, z: t.z },
        },
    }
}

fn displacement(mesh: &TetMesh, positions: &[Vector3<f64>]) -> Vec<f32> {
    mesh.nodes().iter().zip(positions).map(|(rest, p)| (p - rest).norm() as f32).collect()
}

pub(super) fn deformed_mesh(
    mesh: &TetMesh,
    positions: &[Vector3<f64>],
    step: u64,
    stamp: Time,
    frame: &str,
) -> DeformedMesh {
    DeformedMesh {
        header: header(stamp, frame),
        positions: positions.iter().flat_map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect(),
        triangles: mesh.boundary().iter().flatten().copied().collect(),
        scalar_name: "displacement_m".into(),
        scalars: displacement(mesh, positions),
        step,
    }
}

/// The boundary as an RViz/Foxglove TRIANGLE_LIST, coloured by displacement (viridis,
/// 0 to the largest displacement).
pub(super) fn surface_marker(mesh: &TetMesh, positions: &[Vector3<f64>], stamp: Time, frame: &str) -> Marker {
    let moved = displacement(mesh, positions);
    let peak = moved.iter().fold(1e-9f32, |m, d| m.max(*d));
    let mut points = Vec::with_capacity(mesh.boundary().len() * 3);
    let mut colors = Vec::with_capacity(points.capacity());
    for node in mesh.boundary().iter().flatten().map(|n| *n as usize) {
        let p = positions[node];
        points.push(Point { x: p.x, y: p.y, z: p.z });
        let c = colorous::VIRIDIS.eval_continuous(f64::from(moved[node] / peak));
        colors.push(ColorRGBA {
            r: f32::from(c.r) / 255.0,
            g: f32::from(c.g) / 255.0,
            b: f32::from(c.b) / 255.0,
            a: 1.0,
        });
    }
    Marker {
        header: header(stamp, frame),
        ns: "defvol".into(),
        id: 0,
        kind: Marker::TRIANGLE_LIST,
        action: Marker::ADD,
        pose: msgs::Pose::default(),
        scale: msgs::Vector3 { x: 1.0, y: 1.0, z: 1.0 },
        color: ColorRGBA { r: 1.0, g: 1.0, b: 1.0, a: 1.0 },
        points,
        colors,
        ..Default::default()
    }
}

fn image(
    encoding: &str,
    bytes_per_pixel: usize,
    data: Vec<u8>,
    width: usize,
    height: usize,
    stamp: Time,
    frame: &str,
) -> Image {
    Image {
        header: header(stamp, frame),
        height: height as u32,
        width: width as u32,
        encoding: encoding.into(),
        is_bigendian: 0,
        step: (width * bytes_per_pixel) as u32,
        data,
    }
}

pub(super) fn rgba_image(data: Vec<u8>, width: usize, height: usize, stamp: Time, frame: &str) -> Image {
    image("rgba8", 4, data, width, height, stamp, frame)
}

pub(super) fn rgb_image(data: Vec<u8>, width: usize, height: usize, stamp: Time, frame: &str) -> Image {
    image("rgb8", 3, data, width, height, stamp, frame)
}

/// A 32FC1 image, little-endian.
pub(super) fn float_image(values: &[f32], width: usize, height: usize, stamp: Time, frame: &str) -> Image {
    image("32FC1", 4, values.iter().flat_map(|v| v.to_le_bytes()).collect(), width, height, stamp, frame)
}
