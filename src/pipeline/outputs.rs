//! The pipeline's state as ROS messages.

use nalgebra::Vector3;

use super::Pipeline;
use crate::mesh::TetMesh;
use crate::msgs::{
    self, ColorRGBA, DeformedMesh, DiagnosticArray, DiagnosticStatus, Header, Image, KeyValue, Marker, Point, Time,
    Wrench, WrenchStamped,
};
use crate::solver::StepReport;

fn header(stamp: Time, frame: &str) -> Header {
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

fn kv(key: &str, value: impl ToString) -> KeyValue {
    KeyValue { key: key.into(), value: value.to_string() }
}

/// One status per stage plus the inputs': times, CG figures, stability, refusals.
/// `saturated_since` counts, per tool, the steps since the last report in which its
/// coupling held the device back with its largest force.
pub(super) fn diagnostics(p: &Pipeline, stamp: Time, saturated_since: &[u64]) -> DiagnosticArray {
    let times = p.times();
    let stage_backends = p.stage_backends();
    let backend_of =
        |stage: &str| stage_backends.iter().find(|(s, _)| *s == stage).map_or("off", |(_, b)| b.name()).to_owned();
    // Where each stage runs, under keys `backend.<stage>`.
    let mut status = vec![DiagnosticStatus {
        level: DiagnosticStatus::OK,
        name: "defvol: backend".into(),
        message: p.backend().describe(),
        hardware_id: p.backend().describe(),
        values: stage_backends.iter().map(|(stage, backend)| kv(&format!("backend.{stage}"), backend)).collect(),
    }];
    let solver = match (p.feedback.engine_backend(), p.last_report()) {
        (None, _) => DiagnosticStatus {
            level: DiagnosticStatus::OK,
            name: "defvol: solver".into(),
            message: "disabled by the scene".into(),
            ..Default::default()
        },
        (Some(_), report) => {
            let converged =
                report.is_none_or(|r| r.residual <= p.scene().solver.cg_tolerance * 10.0 || r.cg_iterations == 0);
            let saturated: Vec<String> = (p.scene().tools.iter().zip(saturated_since))
                .filter(|(_, n)| **n > 0)
                .map(|(tool, n)| format!("tool `{}` held back in {n} steps", tool.name))
                .collect();
            let (level, message) = match (p.paused(), p.asleep(), converged, saturated.is_empty()) {
                (true, ..) => (DiagnosticStatus::OK, "paused".to_owned()),
                (_, _, _, false) => (
                    DiagnosticStatus::WARN,
                    format!(
                        "coupling saturated, the device pose ran away from the tool (a dropped packet, a teleport?): {}",
                        saturated.join(", ")
                    ),
                ),
                (_, _, false, _) => (DiagnosticStatus::WARN, "CG did not reach its tolerance".to_owned()),
                (_, true, ..) => (DiagnosticStatus::OK, "asleep: the mesh is at rest and untouched".to_owned()),
                _ => (DiagnosticStatus::OK, "running".to_owned()),
            };
            let mut values = vec![kv("backend", p.backend_name()), kv("step_ms", format!("{:.3}", times.solver))];
            if let Some(r) = report {
                values.extend([
                    kv("step", r.step),
                    kv("sim_time_s", format!("{:.4}", r.time)),
                    kv("cg_iterations", r.cg_iterations),
                    kv("cg_residual", format!("{:.3e}", r.residual)),
                    kv("kinetic_energy_j", format!("{:.3e}", r.kinetic_energy)),
                    kv("max_displacement_m", format!("{:.4e}", r.max_displacement)),
                ]);
            }
            for (tool, total) in p.scene().tools.iter().zip(p.saturated_steps()) {
                if tool.coupling.is_some() {
                    values.push(kv(&format!("coupling_saturated_steps.{}", tool.name), total));
                }
            }
            DiagnosticStatus { level, name: "defvol: solver".into(), message, hardware_id: p.backend_name(), values }
        }
    };
    status.push(solver);
    if p.warped_grid().is_some() {
        let (stats, sequence) = p.warped_volume().map_or((Default::default(), 0), |w| (w.stats, w.sequence));
        let level = if stats.skipped_tets > 0 { DiagnosticStatus::WARN } else { DiagnosticStatus::OK };
        let message = if stats.skipped_tets > 0 {
            format!("{} inverted or degenerate tets skipped", stats.skipped_tets)
        } else {
            "ok".into()
        };
        let values = vec![
            kv("warp_ms", format!("{:.3}", times.warp)),
            kv("sequence", sequence),
            kv("voxels", stats.voxels),
            kv("inside", stats.inside),
            kv("inverted_tets", stats.skipped_tets),
        ];
        status.push(DiagnosticStatus {
            level,
            name: "defvol: warp".into(),
            message,
            hardware_id: backend_of("warp"),
            values,
        });
    }
    if let Some(d) = &p.dpcm {
        let values = vec![
            kv("step_ms", format!("{:.3}", times.dpcm)),
            kv("steps_per_tick", d.steps_per_tick),
            kv("asleep", d.asleep),
        ];
        status.push(DiagnosticStatus {
            level: DiagnosticStatus::OK,
            name: "defvol: dpcm".into(),
            message: "ok".into(),
            hardware_id: d.engine.name(),
            values,
        });
    }
    if p.scene().stages.raycast {
        let values = vec![kv("frame_ms", format!("{:.3}", times.raycast))];
        status.push(DiagnosticStatus {
            level: DiagnosticStatus::OK,
            name: "defvol: raycast".into(),
            message: "ok".into(),
            hardware_id: backend_of("raycast"),
            values,
        });
    }
    let counters = p.counters();
    let mut values = vec![kv("accepted", counters.accepted)];
    values.extend(counters.rejected.iter().map(|(kind, n)| kv(&format!("rejected_{kind}"), n)));
    let (level, message) = match &counters.last_rejection {
        Some(last) => (DiagnosticStatus::WARN, format!("{} refused; last: {last}", counters.total_rejected())),
        None => (DiagnosticStatus::OK, "ok".into()),
    };
    status.push(DiagnosticStatus { level, name: "defvol: inputs".into(), message, hardware_id: String::new(), values });
    DiagnosticArray { header: header(stamp, &p.scene().frame_id), status }
}
