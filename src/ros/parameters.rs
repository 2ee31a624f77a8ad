//! The node's parameters: every scene field declared as one, each change checked against
//! its descriptor (range, read-only) and then the whole scene before it is accepted, then
//! handed to the node's loop to reload the scene. The six `rcl_interfaces` parameter
//! services are served here rather than by ros2-client, whose `describe_parameters` knows
//! only a parameter's type: ours answers with [`descriptors`](crate::scene::descriptors).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{mpsc, Arc, Mutex};

use ros2_client::parameters::raw;
use ros2_client::rcl_interfaces::{
    DescribeParametersRequest, DescribeParametersResponse, GetParameterTypesRequest, GetParameterTypesResponse,
    GetParametersRequest, GetParametersResponse, ListParametersRequest, ListParametersResponse, ListParametersResult,
    SetParametersAtomicallyResponse, SetParametersRequest, SetParametersResponse,
};
use ros2_client::{Node, NodeOptions, ParameterValue, RmwRequestId, Server};
use serde_yaml_ng::Value;

use super::args;
use super::error::NodeError;
use super::wire::{answer, own_server};
use crate::pipeline::Pipeline;
use crate::scene::descriptors::{self, Descriptor, Range};
use crate::scene::{named_file, AllowedDirs, SceneChange};

/// The values in force and the changes accepted since the last look.
pub(super) struct Parameters {
    in_force: Arc<Mutex<BTreeMap<String, Value>>>,
    changed: mpsc::Receiver<(String, Value)>,
    allowed: AllowedDirs,
}

impl Parameters {
    /// Declares `declared` on `options`, with the validator and the set action.
    /// `allowed`: where the files a set names must lie.
    pub(super) fn declare(
        mut options: NodeOptions,
        declared: BTreeMap<String, Value>,
        allowed: AllowedDirs,
    ) -> (NodeOptions, Self) {
        let (changes, changed) = mpsc::channel::<(String, Value)>();
        for (name, value) in &declared {
            options = options.declare_parameter(name, parameter_of(value));
        }
        // The values in force: a set action repeating one of them (declaring does) changes nothing.
        let in_force = Arc::new(Mutex::new(declared));
        let validator_parameters = in_force.clone();
        let validator_allowed = allowed.clone();
        options = options.parameter_validator(Box::new(move |name, value| {
            let Ok(in_force) = validator_parameters.lock().map(|p| p.clone()) else {
                return Err("parameter store poisoned".into());
            };
            acceptable(in_force, &[(name, value)], &validator_allowed)
        }));
        let changes = Mutex::new(changes);
        options = options.parameter_set_action(Box::new(move |name, value| {
            let sent = changes
                .lock()
                .map_err(|_| "parameter channel poisoned".to_owned())?
                .send((name.to_owned(), yaml_of(value)));
            sent.map_err(|_| "the node is stopping".to_owned())
        }));
        (options, Self { in_force, changed, allowed })
    }

    /// Takes the accepted changes into the values in force, with no scene to reload (a
    /// managed node not configured yet: its configure reads them).
    pub(super) fn absorb(&self) {
        while let Ok((name, value)) = self.changed.try_recv() {
            if let Ok(mut store) = self.in_force.lock() {
                store.insert(name, value);
            }
        }
    }

    /// The scene the values in force describe.
    pub(super) fn scene(&self) -> Result<crate::scene::Scene, String> {
        self.absorb();
        let store = self.in_force.lock().map_err(|_| "parameter store poisoned".to_owned())?;
        args::scene_from_parameters(&store).map_err(|e| e.to_string())
    }

    /// Applies the accepted changes to `pipeline`, each doing no more than it needs
    /// ([`Pipeline::apply_scene`]); what they changed, together, and what the scene could
    /// not take (a file that does not read), by name, with why. Such a change is set back on
    /// `node`, so that `ros2 param get` tells the value in force.
    pub(super) fn apply(&self, pipeline: &mut Pipeline, node: &Node) -> (SceneChange, BTreeMap<String, String>) {
        let mut changed = SceneChange::default();
        let mut refused = BTreeMap::new();
        let mut set_back = Vec::new();
        while let Ok((name, value)) = self.changed.try_recv() {
            let Ok(mut store) = self.in_force.lock() else { break };
            if store.get(&name) == Some(&value)
                || (parameter_of(&value) == parameter_of(store.get(&name).unwrap_or(&Value::Null)))
            {
                continue;
            }
            let before = store.insert(name.clone(), value);
            match args::scene_from_parameters(&store)
                .map_err(|e| e.to_string())
                .and_then(|scene| pipeline.apply_scene(scene).map_err(|e| e.to_string()))
            {
                Ok(change) => {
                    let how = match (change.physics.is_empty(), change.outputs) {
                        (false, _) => "the simulation rebuilt",
                        (true, true) => "its stages rebuilt, the simulation running on",
                        (true, false) => "taken as the simulation runs",
                    };
                    tracing::info!("parameter {name} set: {how}");
                    changed.physics.extend(change.physics);
                    changed.checks |= change.checks;
                    changed.outputs |= change.outputs;
                    changed.warp |= change.warp;
                }
                Err(e) => {
                    tracing::error!("parameter {name}: {e}; kept the running scene and set the parameter back");
                    refused.insert(name.clone(), format!("{e}; the running scene is kept"));
                    match before {
                        Some(before) => {
                            store.insert(name.clone(), before.clone());
                            set_back.push((name, before));
                        }
                        None => drop(store.remove(&name)),
                    }
                }
            }
        }
        // With the store unlocked: setting runs the validator, which reads it.
        for (name, before) in set_back {
            if let Err(e) = node.set_parameter(&name, parameter_of(&before)) {
                tracing::error!("parameter {name}: not set back ({e})");
            }
        }
        (changed, refused)
    }
}

/// Whether `changes` may be set together over the values `in_force`: each within its
/// descriptor (range, read-only), a file it names inside the `allowed` directories, then the
/// scene they make checked as a whole.
fn acceptable(
    mut candidate: BTreeMap<String, Value>,
    changes: &[(&str, &ParameterValue)],
    allowed: &AllowedDirs,
) -> Result<(), String> {
    for (name, value) in changes {
        let in_force = candidate.get(*name).map_or(ParameterValue::NotSet, parameter_of);
        let refusal = descriptors::describe(name).and_then(|d| d.refuses(name, &yaml_of(value), in_force != **value));
        if let Some(reason) = refusal {
            return Err(reason);
        }
        if let (ParameterValue::String(path), true) = (value, in_force != **value) {
            if let Some(expect) = named_file(name, path) {
                allowed.admit(Path::new(path), expect).map_err(|why| format!("parameter `{name}`: {why}"))?;
            }
        }
        candidate.insert((*name).to_owned(), yaml_of(value));
    }
    args::check_scene(&candidate).map(drop)
}

/// The six parameter services of a ROS 2 node (`~/get_parameters`, …), answered from the
/// node's parameter store with rclcpp's semantics.
pub(super) struct ParameterServices {
    get: Server<GetParametersRequest, GetParametersResponse>,
    get_types: Server<GetParameterTypesRequest, GetParameterTypesResponse>,
    set: Server<SetParametersRequest, SetParametersResponse>,
    set_atomically: Server<SetParametersRequest, SetParametersAtomicallyResponse>,
    list: Server<ListParametersRequest, ListParametersResponse>,
    describe: Server<DescribeParametersRequest, DescribeParametersResponse>,
    /// Set requests taken, their answers waiting for the loop to apply them.
    waiting: Vec<Waiting>,
}

/// A set request checked and taken: its answer so far, by parameter name.
enum Waiting {
    Set(RmwRequestId, Vec<(String, raw::SetParametersResult)>),
    Atomically(RmwRequestId, Vec<String>, raw::SetParametersResult),
}

impl ParameterServices {
    pub(super) fn create(node: &mut Node) -> Result<Self, NodeError> {
        Ok(Self {
            get: own_server(node, "get_parameters", "rcl_interfaces", "GetParameters")?,
            get_types: own_server(node, "get_parameter_types", "rcl_interfaces", "GetParameterTypes")?,
            set: own_server(node, "set_parameters", "rcl_interfaces", "SetParameters")?,
            set_atomically: own_server(node, "set_parameters_atomically", "rcl_interfaces", "SetParametersAtomically")?,
            list: own_server(node, "list_parameters", "rcl_interfaces", "ListParameters")?,
            describe: own_server(node, "describe_parameters", "rcl_interfaces", "DescribeParameters")?,
            waiting: Vec::new(),
        })
    }

    /// Answers every waiting request but a set, which goes through the node's store (its
    /// validator, its set action and the `/parameter_events` it publishes) and is answered
    /// by [`settle`](Self::settle) once applied.
    pub(super) fn serve(&mut self, node: &Node, parameters: &Parameters) {
        answer(&self.get, |request| GetParametersResponse {
            values: known(node, &request.names)
                .map(|values| values.into_iter().map(raw::ParameterValue::from).collect())
                .unwrap_or_default(),
        });
        answer(&self.get_types, |request| GetParameterTypesResponse {
            values: known(node, &request.names)
                .map(|values| values.iter().map(ParameterValue::to_parameter_type_raw).collect())
                .unwrap_or_default(),
        });
        while let Ok(Some((id, request))) = self.set.receive_request() {
            let results = request.parameter.into_iter().map(|p| {
                let result = outcome(node.set_parameter(&p.name, p.value.into()));
                (p.name, result)
            });
            self.waiting.push(Waiting::Set(id, results.collect()));
        }
        while let Ok(Some((id, request))) = self.set_atomically.receive_request() {
            let names = request.parameter.iter().map(|p| p.name.clone()).collect();
            self.waiting.push(Waiting::Atomically(id, names, outcome(set_atomically(node, parameters, request))));
        }
        answer(&self.list, |request| ListParametersResponse {
            result: list(&node.list_parameters(), &request.prefixes, request.depth),
        });
        answer(&self.describe, |request| DescribeParametersResponse {
            values: known(node, &request.names)
                .map(|values| request.names.iter().zip(&values).map(|(name, value)| descriptor(name, value)).collect())
                .unwrap_or_default(),
        });
    }
}

impl ParameterServices {
    /// Answers the set requests taken since the last call, now that the loop has applied
    /// them: a change the scene could not take (`refused`, by name) is answered unsuccessful
    /// with why, as rclcpp answers a refusal of its `on_set` callback.
    pub(super) fn settle(&mut self, refused: &BTreeMap<String, String>) {
        let applied = |result: raw::SetParametersResult, refusal: Option<&String>| match refusal {
            Some(reason) if result.successful => raw::SetParametersResult { successful: false, reason: reason.clone() },
            _ => result,
        };
        for waiting in self.waiting.drain(..) {
            let sent = match waiting {
                Waiting::Set(id, results) => {
                    let results = results.into_iter().map(|(name, result)| applied(result, refused.get(&name)));
                    self.set.send_response(id, SetParametersResponse { results: results.collect() })
                }
                Waiting::Atomically(id, names, result) => {
                    let result = applied(result, names.iter().find_map(|name| refused.get(name)));
                    self.set_atomically.send_response(id, SetParametersAtomicallyResponse { result })
                }
            };
            if let Err(e) = sent {
                tracing::warn!("set_parameters reply not sent: {e:?}");
            }
        }
    }
}

/// The values of `names`, or none when one is not declared (rclcpp then answers with an
/// empty list).
fn known(node: &Node, names: &[String]) -> Option<Vec<ParameterValue>> {
    names.iter().map(|name| node.get_parameter(name)).collect()
}

fn outcome(result: Result<(), String>) -> raw::SetParametersResult {
    match result {
        Ok(()) => raw::SetParametersResult { successful: true, reason: String::new() },
        Err(reason) => raw::SetParametersResult { successful: false, reason },
    }
}

/// All or none: every name declared and of its type, the changes acceptable together;
/// then each set through the store.
fn set_atomically(node: &Node, parameters: &Parameters, request: SetParametersRequest) -> Result<(), String> {
    let changes: Vec<(String, ParameterValue)> =
        request.parameter.into_iter().map(|p| (p.name, ParameterValue::from(p.value))).collect();
    for (name, value) in &changes {
        let Some(in_force) = node.get_parameter(name) else {
            return Err(format!("Setting undeclared parameter '{name}' is not allowed."));
        };
        if in_force.to_parameter_type() != value.to_parameter_type() {
            return Err(format!("Wrong parameter type, parameter {{{name}}} cannot change its type"));
        }
    }
    let in_force = parameters.in_force.lock().map_err(|_| "parameter store poisoned".to_owned())?.clone();
    let borrowed: Vec<(&str, &ParameterValue)> = changes.iter().map(|(n, v)| (n.as_str(), v)).collect();
    acceptable(in_force, &borrowed, &parameters.allowed)?;
    changes.into_iter().try_for_each(|(name, value)| node.set_parameter(&name, value))
}

/// `list_parameters` as rclcpp answers it: with no prefixes, the names with fewer than
/// `depth` dots (0: any); else the names equal to a prefix or under `prefix.` within
/// `depth` more levels; and the namespaces of the names listed.
fn list(names: &[String], prefixes: &[String], depth: u64) -> ListParametersResult {
    let within = |rest: &str| depth == 0 || (rest.matches('.').count() as u64) < depth;
    let mut result = ListParametersResult { names: vec![], prefixes: vec![] };
    for name in names {
        let under = |prefix: &String| {
            name == prefix || name.strip_prefix(prefix.as_str()).and_then(|r| r.strip_prefix('.')).is_some_and(within)
        };
        if (prefixes.is_empty() && within(name)) || prefixes.iter().any(under) {
            result.names.push(name.clone());
            if let Some((namespace, _)) = name.rsplit_once('.') {
                if !result.prefixes.iter().any(|p| p == namespace) {
                    result.prefixes.push(namespace.to_owned());
                }
            }
        }
    }
    result
}

/// The wire descriptor of `name`: the table's, else (a parameter the table does not know)
/// its type alone.
fn descriptor(name: &str, value: &ParameterValue) -> raw::ParameterDescriptor {
    const UNKNOWN: Descriptor =
        Descriptor { description: "", range: Range::Unbounded, read_only: false, additional_constraints: "" };
    let d = descriptors::describe(name).unwrap_or(&UNKNOWN);
    let (floating_point_range, integer_range) = match d.range {
        Range::Unbounded => (vec![], vec![]),
        Range::Float { from, to, step } => {
            (vec![raw::FloatingPointRange { from_value: from, to_value: to, step }], vec![])
        }
        Range::Integer { from, to, step } => (vec![], vec![raw::IntegerRange { from_value: from, to_value: to, step }]),
    };
    raw::ParameterDescriptor {
        name: name.to_owned(),
        r#type: ParameterValue::to_parameter_type_raw(value),
        description: d.description.to_owned(),
        additional_constraints: d.additional_constraints.to_owned(),
        read_only: d.read_only,
        dynamic_typing: false,
        floating_point_range,
        integer_range,
    }
}

/// A parameter as YAML (how the scene reads it).
fn yaml_of(value: &ParameterValue) -> Value {
    match value {
        ParameterValue::NotSet => Value::Null,
        ParameterValue::Boolean(b) => Value::Bool(*b),
        ParameterValue::Integer(i) => Value::from(*i),
        ParameterValue::Double(d) => Value::from(*d),
        ParameterValue::String(s) => Value::String(s.clone()),
        ParameterValue::ByteArray(v) => Value::Sequence(v.iter().map(|b| Value::from(*b)).collect()),
        ParameterValue::BooleanArray(v) => Value::Sequence(v.iter().map(|b| Value::Bool(*b)).collect()),
        ParameterValue::IntegerArray(v) => Value::Sequence(v.iter().map(|i| Value::from(*i)).collect()),
        ParameterValue::DoubleArray(v) => Value::Sequence(v.iter().map(|d| Value::from(*d)).collect()),
        ParameterValue::StringArray(v) => Value::Sequence(v.iter().map(|s| Value::String(s.clone())).collect()),
    }
}

/// A YAML value as a ROS parameter (integers stay integers, lists become arrays).
fn parameter_of(value: &Value) -> ParameterValue {
    match value {
        Value::Bool(b) => ParameterValue::Boolean(*b),
        Value::Number(n) if n.is_i64() => ParameterValue::Integer(n.as_i64().unwrap_or_default()),
        Value::Number(n) => ParameterValue::Double(n.as_f64().unwrap_or_default()),
        Value::String(s) => ParameterValue::String(s.clone()),
        Value::Sequence(items) if items.iter().all(Value::is_bool) => {
            ParameterValue::BooleanArray(items.iter().filter_map(Value::as_bool).collect())
        }
        Value::Sequence(items) if items.iter().all(|v| v.as_i64().is_some()) => {
            ParameterValue::IntegerArray(items.iter().filter_map(Value::as_i64).collect())
        }
        Value::Sequence(items) if items.iter().all(Value::is_number) => {
            ParameterValue::DoubleArray(items.iter().filter_map(Value::as_f64).collect())
        }
        Value::Sequence(items) => ParameterValue::StringArray(
            items.iter().map(|v| serde_yaml_ng::to_string(v).unwrap_or_default().trim().to_owned()).collect(),
        ),
        Value::Null => ParameterValue::NotSet,
        other => ParameterValue::String(serde_yaml_ng::to_string(other).unwrap_or_default().trim().to_owned()),
    }
}
