//! What ROS 2 users type after a node's name: `--ros-args` with `-p name:=value`,
//! `--params-file FILE` (`node: ros__parameters:` YAML, `/**` wildcard included) and
//! `-r __ns:=/x` / `-r __node:=name` remaps; and how parameters describe a scene: a dotted
//! parameter name is a path into the scene YAML (`solver.dt`, `stages.warp`,
//! `tools.0.shape.radius`), so every scene field is a parameter.

use std::collections::BTreeMap;
use std::path::Path;

use serde_yaml_ng::{Mapping, Value};

use crate::io::withhold_found;
use crate::scene::{descriptors, Scene, SceneError};

#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum ArgsError {
    #[error("--ros-args: `{0}` needs a value after it")]
    MissingValue(String),
    #[error("--ros-args: `{0}` is not name:=value")]
    NotAssignment(String),
    #[error("--ros-args: unknown ROS argument `{0}`")]
    Unknown(String),
    #[error("{path}: {message}")]
    ParamsFile { path: String, message: String },
    #[error("parameter `{name}`: {message}")]
    Parameter { name: String, message: String },
    #[error("parameter `{name}` = {value}: {message}")]
    Value { name: String, value: String, message: String },
    #[error("namespace `{0}` must start with '/'")]
    Namespace(String),
}

/// The node's ROS arguments, parsed.
#[derive(Debug, Clone, PartialEq)]
pub struct RosArgs {
    pub node_name: String,
    pub namespace: String,
    /// Parameters in the order given (files first, then `-p`, later ones winning).
    pub parameters: BTreeMap<String, Value>,
    /// Topic remaps `from:=to` (other than `__ns` and `__node`).
    pub remaps: BTreeMap<String, String>,
    /// Arguments outside `--ros-args … [--]`.
    pub rest: Vec<String>,
}

impl RosArgs {
    /// Parses `args` (without the program name) for a node called `default_name`.
    pub fn parse(args: &[String], default_name: &str) -> Result<Self, ArgsError> {
        let mut parsed = RosArgs {
            node_name: default_name.into(),
            namespace: "/".into(),
            parameters: BTreeMap::new(),
            remaps: BTreeMap::new(),
            rest: Vec::new(),
        };
        let mut files = Vec::new();
        let mut cli_params = Vec::new();
        let mut in_ros = false;
        let mut iter = args.iter();
        while let Some(arg) = iter.next() {
            if !in_ros {
                if arg == "--ros-args" {
                    in_ros = true;
                } else {
                    parsed.rest.push(arg.clone());
                }
                continue;
            }
            let mut value = || iter.next().cloned().ok_or_else(|| ArgsError::MissingValue(arg.clone()));
            match arg.as_str() {
                "--" => in_ros = false,
                "--ros-args" => {}
                "-p" | "--param" => cli_params.push(value()?),
                "--params-file" => files.push(value()?),
                "-r" | "--remap" => {
                    let remap = value()?;
                    let (from, to) = remap.split_once(":=").ok_or_else(|| ArgsError::NotAssignment(remap.clone()))?;
                    match from {
                        "__ns" => parsed.namespace = to.into(),
                        "__node" | "__name" => parsed.node_name = to.into(),
                        _ => {
                            parsed.remaps.insert(from.into(), to.into());
                        }
                    }
                }
                "--log-level" | "-e" | "--enclave" => {
                    let ignored = value()?;
                    tracing::warn!("--ros-args {arg} {ignored}: not used by defvol (set RUST_LOG for logging)");
                }
                "--disable-rosout-logs" | "--disable-stdout-logs" | "--enable-rosout-logs" | "--enable-stdout-logs" => {
                }
                other => return Err(ArgsError::Unknown(other.into())),
            }
        }
        if !parsed.namespace.starts_with('/') {
            return Err(ArgsError::Namespace(parsed.namespace));
        }
        for file in files {
            let found = params_file(Path::new(&file), &parsed.node_name, &parsed.namespace)?;
            parsed.parameters.extend(found);
        }
        for assignment in cli_params {
            let (name, text) =
                assignment.split_once(":=").ok_or_else(|| ArgsError::NotAssignment(assignment.clone()))?;
            // ROS reads `-p` values as YAML: 1 is an integer, 1.0 a double, [1, 2] an array.
            let value = serde_yaml_ng::from_str(text).unwrap_or_else(|_| Value::String(text.into()));
            parsed.parameters.insert(name.into(), value);
        }
        Ok(parsed)
    }
}

/// The parameters a params file gives this node: its `/**` section, then the sections
/// naming the node (`name`, `/ns/name`, `/**/name`), later ones winning.
pub fn params_file(path: &Path, node_name: &str, namespace: &str) -> Result<BTreeMap<String, Value>, ArgsError> {
    let err = |message: String| ArgsError::ParamsFile { path: path.display().to_string(), message };
    let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
    let root: Value = serde_yaml_ng::from_str(&text).map_err(|e| err(withhold_found(&e.to_string())))?;
    let Value::Mapping(sections) = root else {
        return Err(err("expected `node_name: {ros__parameters: …}` at the top".into()));
    };
    let full = format!("{}/{node_name}", namespace.trim_end_matches('/'));
    let names = [
        "/**".to_owned(),
        "**".to_owned(),
        node_name.to_owned(),
        full.clone(),
        full.trim_start_matches('/').to_owned(),
        format!("/**/{node_name}"),
    ];
    let mut out = BTreeMap::new();
    let mut matched = false;
    for name in &names {
        let Some(section) = sections.get(Value::String(name.clone())) else { continue };
        matched = true;
        let Some(params) = section.get("ros__parameters") else {
            return Err(err(format!("section `{name}` has no `ros__parameters`")));
        };
        descriptors::flatten("", params, &mut out);
    }
    if !matched {
        tracing::warn!("{}: no section for node {full} (nor /**)", path.display());
    }
    Ok(out)
}

/// Parameters that configure the node itself rather than the scene.
pub const NODE_PARAMETERS: [&str; 9] = [
    "scene_file",
    crate::scene::ALLOWED_DIRS_PARAMETER,
    "dds.open_discovery",
    "record",
    "record.max_bag_duration",
    "record.max_bag_size",
    "record.flush_interval",
    "rerun",
    "lifecycle.managed",
];

/// The scene the parameters describe: `scene_file` (or the embedded default) with every
/// other dotted parameter written into it, then checked as a whole.
pub fn scene_from_parameters(parameters: &BTreeMap<String, Value>) -> Result<Scene, ArgsError> {
    let (text, origin) = match parameters.get("scene_file") {
        Some(Value::String(path)) if !path.is_empty() => {
            let text = crate::scene::read_scene_text(Path::new(path))
                .map_err(|e| ArgsError::Parameter { name: "scene_file".into(), message: e.to_string() })?;
            (text, path.clone())
        }
        Some(Value::String(_)) | None => (crate::scene::DEFAULT_SCENE.to_owned(), "embedded default scene".to_owned()),
        Some(other) => {
            return Err(ArgsError::Parameter { name: "scene_file".into(), message: format!("{other:?} is not a path") })
        }
    };
    let file_error = || {
        let message =
            Scene::parse(&text, &origin).err().map_or_else(|| format!("{origin}: not a scene"), |e| e.to_string());
        ArgsError::Parameter { name: "scene_file".into(), message }
    };
    let mut tree: Value = serde_yaml_ng::from_str(&text).map_err(|_| file_error())?;
    if !tree.is_mapping() {
        return Err(file_error());
    }
    let base = tree.clone();
    let scene_parameters = || parameters.iter().filter(|(n, _)| !NODE_PARAMETERS.contains(&n.as_str()));
    for (name, value) in scene_parameters() {
        set_path(&mut tree, name, value.clone())
            .map_err(|message| ArgsError::Parameter { name: name.clone(), message })?;
    }
    // Through text, where serde_yaml_ng tracks the path of a field.
    let text = serde_yaml_ng::to_string(&tree)
        .map_err(|e| ArgsError::Parameter { name: origin.clone(), message: e.to_string() })?;
    crate::scene::field_path::parse(&text, crate::scene::DEFAULT_SCENE, None).map_err(|message| {
        // The parameter that breaks the scene on its own, named with its value.
        let culprit = scene_parameters().find(|(name, value)| {
            let mut alone = base.clone();
            set_path(&mut alone, name, (*value).clone()).is_ok() && serde_yaml_ng::from_value::<Scene>(alone).is_err()
        });
        if serde_yaml_ng::from_value::<Scene>(base.clone()).is_err() {
            return file_error();
        }
        match culprit {
            Some((name, value)) => {
                let message = message.strip_prefix(&format!("{name}: ")).map_or(message.clone(), str::to_owned);
                ArgsError::Value { name: name.clone(), value: inline(value), message }
            }
            None => ArgsError::Parameter { name: origin.clone(), message },
        }
    })
}

/// A YAML value on one line, as a parameter was given.
fn inline(value: &Value) -> String {
    serde_yaml_ng::to_string(value).map_or_else(|_| format!("{value:?}"), |text| text.trim().to_owned())
}

/// The checks `Scene::load` would make, without loading: for parameter validators.
pub fn check_scene(parameters: &BTreeMap<String, Value>) -> Result<Scene, String> {
    let scene = scene_from_parameters(parameters).map_err(|e| e.to_string())?;
    scene.solver.validate().map_err(|e| match e {
        crate::solver::SolverError::BadParameter { name, value, why } => {
            format!("parameter `solver.{name}` = {value}: {why}")
        }
        other => SceneError::from(other).to_string(),
    })?;
    Ok(scene)
}

/// Writes `value` at the dotted `path` (numeric segments index sequences).
pub(crate) fn set_path(node: &mut Value, path: &str, value: Value) -> Result<(), String> {
    let (segment, rest) = match path.split_once('.') {
        Some((segment, rest)) => (segment, Some(rest)),
        None => (path, None),
    };
    if let (Value::Sequence(items), Ok(index)) = (&mut *node, segment.parse::<usize>()) {
        let len = items.len();
        let Some(item) = items.get_mut(index) else { return Err(format!("index {index} is past the {len} entries")) };
        return match rest {
            Some(rest) => set_path(item, rest, value),
            None => {
                *item = value;
                Ok(())
            }
        };
    }
    if node.is_null() {
        *node = Value::Mapping(Mapping::new());
    }
    let Value::Mapping(map) = node else { return Err(format!("`{segment}` is inside a value that is not a map")) };
    let key = Value::String(segment.to_owned());
    match rest {
        Some(rest) => set_path(map.entry(key).or_insert(Value::Null), rest, value),
        None => {
            map.insert(key, value);
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn ros_args_give_name_namespace_and_typed_parameters() {
        let parsed = RosArgs::parse(&args("--record a.mcap --ros-args -r __ns:=/robot -r __node:=organ -p solver.dt:=0.005 -p stages.warp:=false -p camera.width:=640 -p frame_id:=map -- --rest"), "defvol").unwrap();
        assert_eq!((parsed.node_name.as_str(), parsed.namespace.as_str()), ("organ", "/robot"));
        assert_eq!(parsed.rest, args("--record a.mcap --rest"));
        assert_eq!(parsed.parameters["solver.dt"], Value::from(0.005));
        assert_eq!(parsed.parameters["stages.warp"], Value::Bool(false));
        assert_eq!(parsed.parameters["camera.width"], Value::from(640));
        let scene = scene_from_parameters(&parsed.parameters).unwrap();
        assert_eq!(
            (scene.solver.dt, scene.stages.warp, scene.camera.width, scene.frame_id.as_str()),
            (0.005, false, 640, "map")
        );
        assert_eq!(RosArgs::parse(&args("--ros-args -p"), "n").unwrap_err(), ArgsError::MissingValue("-p".into()));
        assert_eq!(RosArgs::parse(&args("--ros-args --bogus"), "n").unwrap_err(), ArgsError::Unknown("--bogus".into()));
        assert!(matches!(RosArgs::parse(&args("--ros-args -r __ns:=robot"), "n"), Err(ArgsError::Namespace(_))));
    }

    #[test]
    fn params_files_merge_wildcard_then_node_sections() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.yaml");
        std::fs::write(
            &path,
            "/**:\n  ros__parameters:\n    solver: {dt: 0.02, cg_tolerance: 1.0e-5}\n    frame_id: map\n/robot/organ:\n  ros__parameters:\n    solver:\n      dt: 0.004\n    tools.0.shape.radius: 0.01\nother:\n  ros__parameters: {frame_id: nope}\n",
        )
        .unwrap();
        let parsed = RosArgs::parse(
            &args(&format!(
                "--ros-args -r __ns:=/robot -r __node:=organ --params-file {} -p frame_id:=odom",
                path.display()
            )),
            "defvol",
        )
        .unwrap();
        assert_eq!(parsed.parameters["solver.dt"], Value::from(0.004), "the node's section wins over /**");
        assert_eq!(parsed.parameters["solver.cg_tolerance"], Value::from(1e-5));
        assert_eq!(parsed.parameters["frame_id"], Value::from("odom"), "-p wins over the file");
        let scene = scene_from_parameters(&parsed.parameters).unwrap();
        assert_eq!(scene.tools[0].shape.radius(), 0.01);
        let bad = dir.path().join("bad.yaml");
        std::fs::write(&bad, "defvol: [1, 2\n").unwrap();
        let e = RosArgs::parse(&args(&format!("--ros-args --params-file {}", bad.display())), "defvol")
            .unwrap_err()
            .to_string();
        assert!(e.contains("bad.yaml"), "{e}");
    }

    #[test]
    fn a_misspelt_or_impossible_parameter_is_named() {
        let mut params = BTreeMap::new();
        params.insert("solver.dtt".to_owned(), Value::from(0.01));
        let e = scene_from_parameters(&params).unwrap_err().to_string();
        assert!(e.contains("solver.dtt") && e.contains("dtt"), "{e}");
        params.clear();
        params.insert("tools.3.shape.radius".to_owned(), Value::from(0.01));
        let e = scene_from_parameters(&params).unwrap_err().to_string();
        assert!(e.contains("tools.3.shape.radius") && e.contains("past the 1 entries"), "{e}");
        params.clear();
        params.insert("solver.dt".to_owned(), Value::from(-1.0));
        let e = check_scene(&params).unwrap_err();
        assert!(e.contains("parameter `solver.dt` = -1"), "{e}");
    }

    #[test]
    fn a_parameter_of_the_wrong_type_is_named_with_its_value_among_good_ones() {
        let mut params = BTreeMap::new();
        params.insert("camera.height".to_owned(), Value::from(64));
        params.insert("camera.width".to_owned(), Value::String("abc".into()));
        params.insert("solver.dt".to_owned(), Value::from(0.005));
        let e = scene_from_parameters(&params).unwrap_err().to_string();
        assert!(e.starts_with("parameter `camera.width` = abc: invalid type"), "{e}");
    }

    /// The leak `ros2 param set /defvol scene_file /etc/shadow` was: a file that is no scene
    /// is blamed as the file, with no byte of what it holds, whatever else is set.
    #[test]
    fn a_scene_file_that_is_no_scene_is_refused_as_the_file_without_its_text() {
        let dir = tempfile::tempdir().unwrap();
        let secret = "s3cr3t";
        for (name, text) in [
            ("passwd", format!("root:x:0:0:{secret}:/root:/bin/bash\ndaemon:x:1:1::/usr/sbin:/nologin\n")),
            ("shadow", format!("root:*:20228:0:99999:7:::\n{secret}:*:20228:0:99999:7:::\n")),
            ("broken", format!("volume: [{secret}\n")),
        ] {
            let path = dir.path().join(name);
            std::fs::write(&path, text).unwrap();
            let mut params = BTreeMap::new();
            params.insert("scene_file".to_owned(), Value::from(path.display().to_string()));
            params.insert("allow_software_gpu".to_owned(), Value::Bool(false));
            let e = scene_from_parameters(&params).unwrap_err().to_string();
            assert!(e.starts_with(&format!("parameter `scene_file`: {}: ", path.display())), "{e}");
            assert!(!e.contains(secret) && !e.contains("root") && !e.contains("20228"), "{e}");
        }
    }

    #[test]
    fn the_scene_round_trips_through_its_flat_parameters() {
        let scene = Scene::default_scene().unwrap();
        let flat = descriptors::flat(&scene);
        assert!(
            flat.contains_key("solver.dt") && flat.contains_key("camera.width") && flat.contains_key("stages.dpcm")
        );
        assert_eq!(scene_from_parameters(&flat).unwrap(), scene);
    }

    /// Scenes between them holding every kind of mesh, material, clamp and tool option.
    fn scenes() -> Vec<Scene> {
        let with = |changes: &[(&str, &str)]| {
            let mut tree: Value = serde_yaml_ng::from_str(crate::scene::DEFAULT_SCENE).unwrap();
            for (path, yaml) in changes {
                set_path(&mut tree, path, serde_yaml_ng::from_str(yaml).unwrap()).unwrap();
            }
            serde_yaml_ng::from_value::<Scene>(tree).unwrap()
        };
        vec![
            with(&[]),
            with(&[
                ("mesh", "{kind: lattice, min: [0, 0, 0], max: [1, 1, 1], target_tets: 100, split: six}"),
                ("material", "{kind: table, rows: [{intensity: 0, stiffness: 1, damping: 0}]}"),
                ("fixed", "{kind: box, min: [0, 0, 0], max: [1, 1, 1]}"),
                ("tools.0.shape", "{kind: capsule, radius: 0.002, length: 0.05}"),
                ("tools.0.friction", "{static: 0.5, kinetic: 0.3}"),
                ("tools.0.rotational_coupling", "{stiffness: 2.0, damping: 0.02, inertia: 1.0e-5, max_torque: 1.0}"),
            ]),
            with(&[
                ("mesh", "{kind: ellipsoid, centre: [0, 0, 0], radii: [1, 1, 1], cells_per_axis: 4}"),
                ("fixed", "{kind: lowest, fraction: 0.1}"),
            ]),
            with(&[("mesh", "{kind: bar, length: 0.1}"), ("fixed", "{kind: indices, nodes: [0, 1]}")]),
            with(&[("mesh", "{kind: file, path: organ.vtk, scale: 0.001}")]),
            with(&[("volume", "ct_series"), ("volume_series", "1.2.840.10008.99")]),
        ]
    }

    #[test]
    fn every_parameter_of_every_kind_of_scene_is_described() {
        for scene in scenes() {
            for (name, value) in descriptors::flat(&scene) {
                let descriptor = descriptors::describe(&name).unwrap_or_else(|| panic!("`{name}` has no descriptor"));
                assert_eq!(descriptor.refuses(&name, &value, false), None, "`{name}` = {value:?} in a valid scene");
            }
        }
        for name in NODE_PARAMETERS {
            assert!(descriptors::describe(name).is_some(), "{name}");
        }
        for name in ["record", "rerun", "dds.open_discovery", "backend", "allow_software_gpu"] {
            assert!(descriptors::describe(name).is_some_and(|d| d.read_only), "{name}");
        }
    }
}
