//! What each scene field and node parameter is, as ROS 2 describes a parameter
//! (`rcl_interfaces/ParameterDescriptor`): a description, the numeric range a value must
//! lie in, whether only a restart can change it, and the constraints no range can say.
//! `ros2 param describe` and rqt_reconfigure show these; one set of ranges holds for scene
//! files, `-p` and `ros2 param set`: a value outside its range is refused before the scene
//! is built.

use std::collections::BTreeMap;

use serde::Serialize;
use serde_yaml_ng::Value;

/// The numeric range of a parameter, both ends included (as `FloatingPointRange` and
/// `IntegerRange` are); a step of 0 allows any value between them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Range {
    Unbounded,
    Float { from: f64, to: f64, step: f64 },
    Integer { from: i64, to: i64, step: i64 },
}

/// One parameter's description.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Descriptor {
    pub description: &'static str,
    pub range: Range,
    /// Set once when the node starts; `set_parameters` refuses a change.
    pub read_only: bool,
    pub additional_constraints: &'static str,
}

const fn text(description: &'static str) -> Descriptor {
    Descriptor { description, range: Range::Unbounded, read_only: false, additional_constraints: "" }
}

const fn float(description: &'static str, from: f64, to: f64) -> Descriptor {
    Descriptor { range: Range::Float { from, to, step: 0.0 }, ..text(description) }
}

const fn integer(description: &'static str, from: i64, to: i64) -> Descriptor {
    Descriptor { range: Range::Integer { from, to, step: 1 }, ..text(description) }
}

const fn constrained(descriptor: Descriptor, additional_constraints: &'static str) -> Descriptor {
    Descriptor { additional_constraints, ..descriptor }
}

const fn read_only(descriptor: Descriptor) -> Descriptor {
    Descriptor { read_only: true, ..descriptor }
}

/// Parameter names (dotted scene paths; `#` stands for a list index) and their descriptions.
const TABLE: &[(&str, Descriptor)] = &[
    ("scene_file", text("Scene YAML the other parameters are written into (empty: the embedded default scene)")),
    (
        "files.allowed_dirs",
        read_only(text(
            "Folders the files named over the wire (scene_file, volume, mesh.path, dpcm.preset, load_scene) must lie in (default: the start scene's and the package's config/)",
        )),
    ),
    ("use_sim_time", text("ROS 2's simulated-time switch (defvol stamps its outputs with the system clock)")),
    (
        "record",
        read_only(text("Recording of every input and output topic: an .mcap file, else a rosbag2 bag directory")),
    ),
    ("record.max_bag_duration", read_only(float("Seconds a split of the bag directory spans (0: no limit)", 0.0, 1e7))),
    ("record.max_bag_size", read_only(integer("Bytes a split of the bag directory holds (0: no limit)", 0, i64::MAX))),
    (
        "record.flush_interval",
        read_only(float("Seconds between writes of the open chunk (what a crash may lose)", 1e-3, 10.0)),
    ),
    ("rerun", read_only(text("rerun file (.rrd) logging the session"))),
    ("dds.open_discovery", read_only(text("Let DDS discovery reach other hosts (default: loopback only)"))),
    ("lifecycle.managed", read_only(text("Run as a managed (lifecycle) node: outputs only while active"))),
    ("backend", read_only(constrained(text("Where every stage runs"), "one of auto, cpu, gpu; chosen once per run"))),
    ("allow_software_gpu", read_only(text("Let a software Vulkan adapter (lavapipe, llvmpipe) count as a GPU"))),
    ("volume", text("Source volume: `phantom`, a .nii/.nii.gz/.nrrd/.nhdr/.mha/.mhd/.dcm file or a DICOM folder")),
    ("volume_series", text("With a DICOM folder: the SeriesInstanceUID to read (default: the largest series)")),
    ("file_to_world", float("World units (m) per file unit (0.001: millimetre files)", 1e-9, 1e3)),
    ("density", float("Tissue density (kg/m³) giving the nodes' masses", 1.0, 1e5)),
    ("frame_id", text("World frame of the tool poses and every output")),
    (
        "mesh.kind",
        constrained(text("Where the mesh comes from"), "one of file, volume_lattice, lattice, bar, ellipsoid"),
    ),
    ("mesh.path", text("Mesh file (.vtk, .vtu, .msh, .mesh, .node/.ele)")),
    ("mesh.scale", float("World units per mesh-file unit (overrides the file's own unit)", 1e-9, 1e3)),
    ("mesh.target_tets", integer("About how many tetrahedra the lattice has", 5, 20_000_000)),
    ("mesh.split", constrained(text("Tetrahedra per lattice cell"), "five or six")),
    ("mesh.min", text("Lattice box corner (m), [x, y, z]")),
    ("mesh.max", text("Lattice box corner (m), [x, y, z]")),
    ("mesh.length", float("Bar length (m)", 1e-6, 1e3)),
    ("mesh.centre", text("Ellipsoid centre (m), [x, y, z]")),
    ("mesh.radii", text("Ellipsoid semi-axes (m), [x, y, z]")),
    ("mesh.cells_per_axis", integer("Ellipsoid lattice cells along each axis", 1, 1000)),
    ("material.kind", constrained(text("Where spring stiffness comes from"), "uniform or table")),
    ("material.stiffness", float("Stiffness of every spring (N/m)", 0.0, 1e9)),
    ("material.damping", float("Damping along every spring (N·s/m)", 0.0, 1e6)),
    ("material.rows.#.intensity", text("Tissue table: the volume intensity of this row")),
    ("material.rows.#.stiffness", float("Tissue table: spring stiffness at this intensity (N/m)", 0.0, 1e9)),
    ("material.rows.#.damping", float("Tissue table: spring damping at this intensity (N·s/m)", 0.0, 1e6)),
    ("fixed.kind", constrained(text("Which nodes are held"), "one of indices, box, plane, lowest")),
    ("fixed.nodes", text("Held node indices")),
    ("fixed.min", text("Held box corner (m), [x, y, z]")),
    ("fixed.max", text("Held box corner (m), [x, y, z]")),
    ("fixed.normal", text("Clamp plane normal: nodes with normal·x <= offset are held")),
    ("fixed.offset", text("Clamp plane offset (m)")),
    ("fixed.fraction", float("Held fraction of the mesh's height above its lowest node", 0.0, 1.0)),
    (
        "solver.integrator",
        constrained(text("Time integrator"), "one of implicit_euler, explicit_euler, verlet, velocity_verlet"),
    ),
    (
        "solver.dt",
        constrained(
            float("Solver time step (s); the node ticks once per step", 1e-6, 0.1),
            "explicit integrators need dt below their stability limit, about sqrt(mass / stiffness)",
        ),
    ),
    ("solver.gravity", text("Gravity (m/s²), [x, y, z]")),
    ("solver.cg_tolerance", float("Implicit solve: relative residual at which CG stops", 1e-12, 0.5)),
    ("solver.cg_max_iterations", integer("Implicit solve: most CG iterations per step", 1, 1_000_000)),
    ("solver.cg_check_interval", integer("Implicit solve: CG iterations between residual checks (GPU)", 1, 1000)),
    (
        "solver.preconditioner",
        constrained(text("CG preconditioner"), "one of auto, block_jacobi, amg (on either backend)"),
    ),
    ("tools.#.name", text("Tool name (its topics are <name>/tool_pose … after the first tool)")),
    ("tools.#.shape.kind", constrained(text("Tool shape"), "sphere or capsule")),
    ("tools.#.shape.radius", float("Tool radius (m)", 1e-5, 1.0)),
    ("tools.#.shape.length", float("Capsule shaft length (m)", 0.0, 10.0)),
    ("tools.#.contact", constrained(text("What the tool pushes"), "surface (faces, edges, nodes) or nodes")),
    ("tools.#.contact_stiffness", float("Penalty stiffness of the tool's contact (N/m)", 0.0, 1e9)),
    ("tools.#.spread_radius", float("Radius over which a wrench on the tool is spread (m)", 0.0, 10.0)),
    ("tools.#.coupling", text("Haptic coupling {stiffness, damping, mass, max_force} (empty: none)")),
    ("tools.#.coupling.stiffness", float("Haptic coupling stiffness (N/m)", 0.0, 1e7)),
    ("tools.#.coupling.damping", float("Haptic coupling damping (N·s/m)", 0.0, 1e5)),
    ("tools.#.coupling.mass", float("Simulated tool mass (kg)", 1e-6, 100.0)),
    ("tools.#.coupling.max_force", float("Largest force the device is sent (N)", 0.0, 1e4)),
    ("tools.#.rotational_coupling", text("Torsional coupling {stiffness, damping, inertia, max_torque} (empty: none)")),
    ("tools.#.rotational_coupling.stiffness", float("Torsional coupling stiffness (N·m/rad)", 0.0, 1e5)),
    ("tools.#.rotational_coupling.damping", float("Torsional coupling damping (N·m·s/rad)", 0.0, 1e4)),
    (
        "tools.#.rotational_coupling.inertia",
        float("Simulated tool's moment of inertia about its tip (kg·m²)", 1e-12, 10.0),
    ),
    ("tools.#.rotational_coupling.max_torque", float("Largest torque the device is sent (N·m)", 0.0, 1e3)),
    ("tools.#.friction", text("Coulomb friction {static, kinetic, stick_speed} (empty: frictionless)")),
    ("tools.#.friction.static", float("Static friction coefficient", 0.0, 10.0)),
    (
        "tools.#.friction.kinetic",
        constrained(float("Kinetic friction coefficient", 0.0, 10.0), "at most the static coefficient"),
    ),
    ("tools.#.friction.stick_speed", float("Sliding speed below which the tool sticks (m/s)", 0.0, 1.0)),
    ("tools.#.path", text("Scripted path {from, to, duration} (simulate, demo; empty: none)")),
    ("tools.#.path.from", text("Scripted path start (m), [x, y, z]")),
    ("tools.#.path.to", text("Scripted path end (m), [x, y, z]")),
    ("tools.#.path.duration", float("Scripted path duration (s), then held", 0.0, 1e6)),
    ("tools.#.pose_topic", text("Pose input topic (empty: tool_pose, or <name>/tool_pose)")),
    ("tools.#.wrench_topic", text("Wrench input topic (empty: tool_wrench, or <name>/tool_wrench)")),
    ("tools.#.feedback_topic", text("Reaction output topic (empty: tool_feedback, or <name>/tool_feedback)")),
    ("stages.solver", text("Run the solver")),
    ("stages.warp", text("Warp the source volume through the deformed mesh")),
    ("stages.dpcm", text("Run the DPCM surface")),
    ("stages.raycast", text("Render raycast images")),
    (
        "inputs.max_age",
        float("Seconds a pose or wrench may be stamped before it arrives (0: any age, for an unsynchronised clock)", 0.0, 3600.0),
    ),
    ("warp.rate_hz", float("Most warps per simulated second", 0.01, 1e4)),
    ("warp.tolerance", float("Node motion (m) below which a tet is not re-warped", 0.0, 1.0)),
    ("warp.service", text("iceoryx2 service carrying the warped volumes")),
    ("dpcm.preset", text("DPCM preset (water, sand, loose_soil, fossil, oil_painting) or a DPCM YAML file")),
    ("dpcm.size", text("Phyxels along x and y, [nx, ny] (empty: the preset's)")),
    ("dpcm.spacing", float("Metres between phyxels (empty: the preset's)", 1e-6, 1.0)),
    ("dpcm.origin", text("World position of phyxel (0, 0) (m), [x, y, z]")),
    ("dpcm.rate_hz", float("Most DPCM images per simulated second", 0.01, 1e4)),
    ("dpcm.batch", integer("DPCM steps per GPU submission (empty: the steps per solver step)", 1, 4096)),
    ("camera.eye", text("Raycast camera position (m), [x, y, z]")),
    ("camera.target", text("Point the camera looks at (m), [x, y, z]")),
    ("camera.up", text("Camera up direction, [x, y, z]")),
    ("camera.fov_y_deg", float("Vertical field of view (degrees)", 1.0, 179.0)),
    ("camera.width", integer("Image width (pixels)", 1, 16384)),
    ("camera.height", integer("Image height (pixels)", 1, 16384)),
    ("camera.transfer_function", constrained(text("Transfer function preset"), "one of ct_soft_tissue, ct_bone, mri")),
    ("camera.shows", constrained(text("What the camera shows"), "one of volume, mesh, source")),
    ("camera.step", float("Ray step, in the volume's file units", 1e-3, 1e3)),
    ("camera.rate_hz", float("Most frames per simulated second", 0.01, 1e4)),
];

/// Every parameter as a Markdown table (name, what it is, its range and constraints, and
/// how a change takes effect), in the order above: the reference `docs/scenes.md` carries,
/// held to this by the suite.
pub fn reference_table() -> String {
    let mut out = String::from("| parameter | what | values | changed by |\n| --- | --- | --- | --- |\n");
    for (name, d) in TABLE {
        let range = match d.range {
            Range::Unbounded => String::new(),
            Range::Float { from, to, .. } => format!("{} to {}", number(from), number(to)),
            Range::Integer { from, to, .. } => format!("{from} to {to}"),
        };
        let values: Vec<&str> =
            [range.as_str(), d.additional_constraints].into_iter().filter(|v| !v.is_empty()).collect();
        let changed_by = match (d.read_only, effect(name)) {
            (true, _) => "a restart",
            (false, Effect::Stage) => "`ros2 param set` (its stage rebuilt, the simulation running on)",
            (false, Effect::AtOnce) => "`ros2 param set` (at once)",
            (false, Effect::Restart) => "`ros2 param set` (the simulation restarts from rest)",
        };
        let name = name.replace('#', "N");
        out += &format!("| `{name}` | {} | {} | {changed_by} |\n", d.description, values.join("; "));
    }
    out
}

/// What setting a parameter does to a running node (as `Scene::change_from` sorts it).
enum Effect {
    Stage,
    AtOnce,
    Restart,
}

fn effect(name: &str) -> Effect {
    let stage = ["camera.", "warp.", "dpcm.", "stages.warp", "stages.dpcm", "stages.raycast"];
    match name {
        _ if stage.iter().any(|prefix| name.starts_with(prefix)) => Effect::Stage,
        "frame_id" | "use_sim_time" => Effect::AtOnce,
        _ if name.starts_with("inputs.") => Effect::AtOnce,
        _ => Effect::Restart,
    }
}

/// A range's end as a reader writes it: plain where that is short, else in powers of ten.
fn number(x: f64) -> String {
    match x == 0.0 || (1e-3..1e5).contains(&x.abs()) {
        true => format!("{x}"),
        false => format!("{x:e}"),
    }
}

/// The description of the parameter called `name`, if it is one defvol knows.
pub fn describe(name: &str) -> Option<&'static Descriptor> {
    TABLE.iter().find(|(pattern, _)| matches(pattern, name)).map(|(_, descriptor)| descriptor)
}

/// Whether `name` fits `pattern`, segment by segment (`#` matches a list index).
fn matches(pattern: &str, name: &str) -> bool {
    let (mut p, mut n) = (pattern.split('.'), name.split('.'));
    loop {
        match (p.next(), n.next()) {
            (None, None) => return true,
            (Some("#"), Some(segment)) if segment.parse::<usize>().is_ok() => {}
            (Some(a), Some(b)) if a == b => {}
            _ => return false,
        }
    }
}

impl Descriptor {
    /// Why `value` cannot be set, as rclcpp words it; `changes` tells a new value from the
    /// one in force (a read-only parameter takes only the latter).
    pub fn refuses(&self, name: &str, value: &Value, changes: bool) -> Option<String> {
        if self.read_only && changes {
            return Some(format!("parameter '{name}' cannot be set because it is read-only"));
        }
        match (self.range, value) {
            (Range::Float { from, to, .. }, Value::Number(n)) => {
                let x = n.as_f64().unwrap_or(f64::NAN);
                // NaN lies in no range.
                (!(from..=to).contains(&x))
                    .then(|| format!("Parameter {{{name}}} doesn't comply with floating point range [{from}, {to}]"))
            }
            (Range::Integer { from, to, step }, Value::Number(n)) => {
                let i = n.as_i64()?;
                let off_step = step > 0 && (i - from) % step != 0;
                (!(from..=to).contains(&i) || off_step)
                    .then(|| format!("Parameter {{{name}}} doesn't comply with integer range [{from}, {to}]"))
            }
            _ => None,
        }
    }
}

/// A scene's fields as dotted parameter names (`solver.dt`, `tools.0.shape.radius`), as the
/// node declares them.
pub fn flat(scene: &impl Serialize) -> BTreeMap<String, Value> {
    let mut out = BTreeMap::new();
    if let Ok(tree) = serde_yaml_ng::to_value(scene) {
        flatten("", &tree, &mut out);
    }
    out
}

/// Nested maps as dotted names, as ROS 2 reads params files: lists of maps (the tools) by
/// index, lists of plain values kept whole (array parameters).
pub fn flatten(prefix: &str, value: &Value, out: &mut BTreeMap<String, Value>) {
    match value {
        Value::Mapping(map) => {
            for (key, value) in map {
                let key = match key {
                    Value::String(s) => s.clone(),
                    other => serde_yaml_ng::to_string(other).unwrap_or_default().trim().to_owned(),
                };
                let name = if prefix.is_empty() { key } else { format!("{prefix}.{key}") };
                flatten(&name, value, out);
            }
        }
        Value::Sequence(items) if items.iter().any(Value::is_mapping) => {
            for (index, item) in items.iter().enumerate() {
                flatten(&format!("{prefix}.{index}"), item, out);
            }
        }
        other => {
            out.insert(prefix.to_owned(), other.clone());
        }
    }
}

/// Every field of `scene` outside its range, by its path, with what the field is; none
/// when all lie in theirs.
pub fn out_of_range(scene: &impl Serialize) -> Vec<String> {
    let outside = flat(scene).into_iter().filter_map(|(name, value)| {
        let d = describe(&name)?;
        let range = match d.range {
            Range::Unbounded => return None,
            Range::Float { from, to, .. } => format!("[{}, {}]", number(from), number(to)),
            Range::Integer { from, to, .. } => format!("[{from}, {to}]"),
        };
        d.refuses(&name, &value, false)?;
        let shown = serde_yaml_ng::to_string(&value).unwrap_or_default();
        Some(format!("{name} = {} is outside {range} ({})", shown.trim(), d.description))
    });
    outside.collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_outside_the_declared_range_are_refused_as_rclcpp_words_it() {
        let dt = describe("solver.dt").unwrap();
        assert_eq!(dt.refuses("solver.dt", &Value::from(0.005), true), None);
        let huge = dt.refuses("solver.dt", &Value::from(1e9), true).unwrap();
        assert_eq!(huge, "Parameter {solver.dt} doesn't comply with floating point range [0.000001, 0.1]");
        assert!(dt.refuses("solver.dt", &Value::from(f64::NAN), true).is_some());
        assert!(dt.refuses("solver.dt", &Value::from(-0.01), true).is_some());
        let width = describe("camera.width").unwrap();
        assert!(width.refuses("camera.width", &Value::from(0), true).unwrap().contains("integer range [1, 16384]"));
        let radius = describe("tools.3.shape.radius").unwrap();
        assert_eq!(radius.range, Range::Float { from: 1e-5, to: 1.0, step: 0.0 });
        assert!(describe("tools.x.shape.radius").is_none() && describe("solver.dtt").is_none());
        let backend = describe("backend").unwrap();
        assert_eq!(backend.refuses("backend", &Value::from("auto"), false), None);
        assert_eq!(
            backend.refuses("backend", &Value::from("gpu"), true).unwrap(),
            "parameter 'backend' cannot be set because it is read-only"
        );
    }
}
