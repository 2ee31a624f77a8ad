//! The node's parameters: every scene field declared as one, each change checked against
//! the whole scene before it is accepted, then handed to the node's loop to reload the
//! scene; the run's choices (backend) are refused once running.

use std::collections::BTreeMap;
use std::sync::{mpsc, Arc, Mutex};

use ros2_client::{NodeOptions, ParameterValue};
use serde_yaml_ng::Value;

use super::args;
use crate::pipeline::Pipeline;

/// The values in force and the changes accepted since the last look.
pub(super) struct Parameters {
    in_force: Arc<Mutex<BTreeMap<String, Value>>>,
    changed: mpsc::Receiver<(String, Value)>,
}

impl Parameters {
    /// Declares `declared` on `options`, with the validator and the set action.
    pub(super) fn declare(mut options: NodeOptions, declared: BTreeMap<String, Value>) -> (NodeOptions, Self) {
        let (changes, changed) = mpsc::channel::<(String, Value)>();
        for (name, value) in &declared {
            options = options.declare_parameter(name, parameter_of(value));
        }
        // The values in force: a set action repeating one of them (declaring does) changes nothing.
        let in_force = Arc::new(Mutex::new(declared));
        let validator_parameters = in_force.clone();
        options = options.parameter_validator(Box::new(move |name, value| {
            let Ok(mut candidate) = validator_parameters.lock().map(|p| p.clone()) else {
                return Err("parameter store poisoned".into());
            };
            let in_force = candidate.get(name).map_or(ParameterValue::NotSet, parameter_of);
            if args::RUN_PARAMETERS.contains(&name) && in_force != *value {
                return Err(format!("`{name}` is chosen once per run: restart the node to change it"));
            }
            candidate.insert(name.to_owned(), yaml_of(value));
            args::check_scene(&candidate).map(drop)
        }));
        let changes = Mutex::new(changes);
        options = options.parameter_set_action(Box::new(move |name, value| {
            let sent = changes
                .lock()
                .map_err(|_| "parameter channel poisoned".to_owned())?
                .send((name.to_owned(), yaml_of(value)));
            sent.map_err(|_| "the node is stopping".to_owned())
        }));
        (options, Self { in_force, changed })
    }

    /// Applies the accepted changes to `pipeline` (a scene reload each); true when one
    /// reloaded the scene.
    pub(super) fn apply(&self, pipeline: &mut Pipeline) -> bool {
        let mut reloaded = false;
        while let Ok((name, value)) = self.changed.try_recv() {
            let Ok(mut store) = self.in_force.lock() else { break };
            if store.get(&name) == Some(&value)
                || (parameter_of(&value) == parameter_of(store.get(&name).unwrap_or(&Value::Null)))
            {
                continue;
            }
            store.insert(name.clone(), value);
            match args::scene_from_parameters(&store)
                .map_err(|e| e.to_string())
                .and_then(|scene| pipeline.load_scene(scene).map_err(|e| e.to_string()))
            {
                Ok(()) => {
                    tracing::info!("parameter {name} set: scene reloaded");
                    reloaded = true;
                }
                Err(e) => tracing::error!("parameter {name}: {e}; kept the running scene"),
            }
        }
        reloaded
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
