//! The pipeline's health as one `diagnostic_msgs/DiagnosticArray`: a status per stage
//! (where it runs, its times, its figures) and the inputs' refusals.

use super::outputs::header;
use super::Pipeline;
use crate::msgs::{DiagnosticArray, DiagnosticStatus, KeyValue, Time};

fn kv(key: &str, value: impl ToString) -> KeyValue {
    KeyValue { key: key.into(), value: value.to_string() }
}

impl Pipeline {
    /// One status per stage plus the inputs': times, CG figures, stability, refusals.
    /// `saturated_since` counts, per tool, the steps since the last report in which its
    /// coupling held the device back with its largest force.
    pub(super) fn diagnostics(&self, stamp: Time, saturated_since: &[u64]) -> DiagnosticArray {
        let p = self;
        let times = p.times();
        let stage_backends = p.stage_backends();
        let backend_of =
            |stage: &str| stage_backends.iter().find(|(s, _)| *s == stage).map_or("off", |(_, b)| b.name()).to_owned();
        // Where each stage runs, under keys `backend.<stage>`; on a GPU, its round trips
        // since the node started (`gpu.submissions`, `gpu.readbacks`, `gpu.bytes_read_back`).
        #[cfg_attr(not(feature = "gpu"), allow(unused_mut))]
        let mut values: Vec<KeyValue> =
            stage_backends.iter().map(|(stage, backend)| kv(&format!("backend.{stage}"), backend)).collect();
        #[cfg(feature = "gpu")]
        if let Some(ctx) = p.backend().context() {
            let c = ctx.counters();
            values.extend([
                kv("gpu.submissions", c.submissions),
                kv("gpu.readbacks", c.readbacks),
                kv("gpu.bytes_read_back", c.bytes_read_back),
            ]);
        }
        let mut status = vec![DiagnosticStatus {
            level: DiagnosticStatus::OK,
            name: "defvol: backend".into(),
            message: p.backend().describe(),
            hardware_id: p.backend().describe(),
            values,
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
                if let Some(why) = &p.last_reset {
                    values.push(kv("last_reset", format!("restarted from rest: {why}")));
                }
                // Tets turned inside out: the mesh is past what it can represent there.
                let inverted = p.mesh().inverted(p.positions());
                values.push(kv("inverted_tets", inverted.count));
                if let Some((tet, ratio)) = inverted.worst {
                    values.push(kv("worst_inverted_tet", format!("{tet} at {ratio:.3} of its rest volume")));
                }
                let (level, message) = match (inverted.count, level) {
                    (0, _) => (level, message),
                    (n, DiagnosticStatus::OK) => (DiagnosticStatus::WARN, format!("{n} tets turned inside out")),
                    (n, _) => (level, format!("{message}; {n} tets turned inside out")),
                };
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
                DiagnosticStatus {
                    level,
                    name: "defvol: solver".into(),
                    message,
                    hardware_id: p.backend_name(),
                    values,
                }
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
            let mut values = vec![
                kv("warp_ms", format!("{:.3}", times.warp)),
                kv("sequence", sequence),
                kv("voxels", stats.voxels),
                kv("inside", stats.inside),
                kv("inverted_tets", stats.skipped_tets),
            ];
            // Shared memory: who takes the volumes, and whether the latest went out (a
            // subscriber that holds its samples loses its oldest; the node never waits).
            if let Some(subscribers) = p.volume_subscribers() {
                let published = p.warped_volume().is_some_and(|w| w.published);
                values.extend([kv("shared_subscribers", subscribers), kv("shared_published", published)]);
            }
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
        status.push(DiagnosticStatus {
            level,
            name: "defvol: inputs".into(),
            message,
            hardware_id: String::new(),
            values,
        });
        DiagnosticArray { header: header(stamp, &p.scene().frame_id), status }
    }
}
