//! A scene names what it needs: every field it omits comes from the embedded default
//! scene, and `mesh: organ.vtu` stands for a mesh file. A section of another `kind` (a mesh
//! file where the default has a lattice) replaces the default's whole, and so does a list
//! (the tools: a tool written out is the one the scene has, with no coupling it does not
//! name).

use serde_yaml_ng::{Mapping, Value};

/// `user`'s scene tree over `base`'s, shorthands expanded.
pub fn inherit(mut user: Value, base: &Value) -> Value {
    expand_shorthands(&mut user);
    merge(user, base)
}

/// `mesh: PATH` as `mesh: {kind: file, path: PATH}`.
fn expand_shorthands(tree: &mut Value) {
    if let Some(mesh) = tree.get_mut("mesh") {
        if let Value::String(path) = mesh {
            let mut file = Mapping::new();
            file.insert("kind".into(), "file".into());
            file.insert("path".into(), Value::String(std::mem::take(path)));
            *mesh = Value::Mapping(file);
        }
    }
}

/// `user` where it says something, else `base`: maps field by field (unless their kinds
/// differ).
fn merge(user: Value, base: &Value) -> Value {
    match (user, base) {
        (Value::Mapping(user), Value::Mapping(base)) if kind(&user) == kind(base) || kind(&user).is_none() => {
            let mut merged = base.clone();
            for (key, value) in user {
                let inherited = match base.get(&key) {
                    Some(below) => merge(value, below),
                    None => value,
                };
                merged.insert(key, inherited);
            }
            Value::Mapping(merged)
        }
        (user, _) => user,
    }
}

/// A section's `kind`, if it names one.
fn kind(map: &Mapping) -> Option<&Value> {
    map.get("kind")
}
