//! Scene errors that name the field: serde_yaml_ng gives the path of most errors
//! (`solver.dt: invalid type`) but loses it inside internally tagged enums (`kind: uniform`),
//! whose content it buffers, and gives a line within that buffer. There the entry at fault
//! is found by trying the file's top-level entries one at a time on a whole one (the
//! embedded default scene; a list's items one at a time), and an unknown field gets the
//! nearest name.

use serde::de::DeserializeOwned;
use serde_yaml_ng::{Mapping, Value};

use crate::io::withhold_found;

/// The `T` in `text`, or an error that names the path of the field at fault and, for an
/// unknown field, the nearest expected name. `base`: a whole `T` as YAML (the default scene)
/// to try entries on. `lines`: the user's own text, where `text` was made from it (a scene
/// over the default's), to name the line of the field at fault in; none for text made from
/// parameters.
pub fn parse<T: DeserializeOwned>(text: &str, base: &str, lines: Option<&str>) -> Result<T, String> {
    let found = match serde_yaml_ng::from_str::<T>(text) {
        Ok(scene) => return Ok(scene),
        Err(error) => error.to_string(),
    };
    // The hint compares the name found with the schema's; the message never quotes it.
    let hint = nearest_expected(&found).map(|name| format!(" (did you mean `{name}`?)"));
    let error = withhold_found(&found);
    let path = match has_path(&error) {
        true => error.split_once(": ").map(|(path, _)| path.to_owned()),
        false => serde_yaml_ng::from_str::<Value>(text).ok().and_then(|t| culprit::<T>(&t, base)),
    };
    let what = without_location(&error);
    let message = match &path {
        Some(path) if !has_path(&error) => format!("{path}: {what}{}", kinds(path, what)),
        Some(path) => format!("{what}{}", kinds(path, what)),
        None => what.to_owned(),
    };
    let line = lines.zip(path).and_then(|(user, path)| line_of(user, &path));
    let at = line.map(|n| format!(" at line {n}")).unwrap_or_default();
    Err(format!("{message}{at}{}", hint.unwrap_or_default()))
}

/// For a section given where a tagged one belongs (`mesh: [organ.vtu]`), the kinds it takes.
fn kinds(path: &str, what: &str) -> String {
    let kinds = what
        .contains("expected internally tagged enum")
        .then(|| super::descriptors::describe(&format!("{}.kind", path.replace('[', ".").replace(']', ""))))
        .flatten()
        .filter(|d| !d.additional_constraints.is_empty());
    kinds.map(|d| format!(" (kind: {})", d.additional_constraints)).unwrap_or_default()
}

/// Whether the message starts with a field path (`material.kind: …`).
fn has_path(message: &str) -> bool {
    message.split_once(": ").is_some_and(|(head, _)| !head.is_empty() && !head.contains(' '))
}

/// The location serde_yaml_ng gives inside a buffered enum is within the buffer: dropped.
fn without_location(message: &str) -> &str {
    message.rfind(" at line ").map_or(message, |at| &message[..at])
}

/// The first top-level entry of `tree` that breaks `base` on its own; for a list,
/// the first item that does.
fn culprit<T: DeserializeOwned>(tree: &Value, base: &str) -> Option<String> {
    let (Value::Mapping(user), Ok(Value::Mapping(base))) = (tree, serde_yaml_ng::from_str::<Value>(base)) else {
        return None;
    };
    let breaks = |key: &Value, value: &Value| {
        let mut trial: Mapping = base.clone();
        trial.insert(key.clone(), value.clone());
        serde_yaml_ng::from_value::<T>(Value::Mapping(trial)).is_err()
    };
    let (key, value) = user.iter().find(|(key, value)| breaks(key, value))?;
    // Only a name of the schema's: a key the file invented is text found there.
    let name = key.as_str().filter(|_| base.contains_key(key))?.to_owned();
    let item = match value {
        Value::Sequence(items) => items.iter().position(|item| breaks(key, &Value::Sequence(vec![item.clone()]))),
        _ => None,
    };
    Some(match item {
        Some(i) => format!("{name}[{i}]"),
        None => name,
    })
}

/// The line (from 1) of the field at `path` (`tools[0].shape.kind`) in YAML `text`: each
/// name looked up inside its parent's block; where the text stops saying (a flow map, a field
/// inherited), the deepest one it has.
fn line_of(text: &str, path: &str) -> Option<usize> {
    let lines: Vec<&str> = text.lines().collect();
    let indent = |line: &str| line.len() - line.trim_start().len();
    let (mut found, mut from, mut parent) = (None, 0, None::<usize>);
    for key in path.split('.').map(|segment| segment.split('[').next().unwrap_or(segment)) {
        let names = |line: &&str| {
            let entry = line.trim_start().trim_start_matches("- ");
            entry.strip_prefix(key).is_some_and(|rest| rest.trim_start().starts_with(':'))
        };
        let block = lines[from..]
            .iter()
            .take_while(|line| {
                let blank = line.trim().is_empty() || line.trim_start().starts_with('#');
                blank || parent.is_none_or(|p| indent(line) > p)
            })
            .position(names);
        let Some(offset) = block else { break };
        let at = from + offset;
        found = Some(at + 1);
        (from, parent) = (at + 1, Some(indent(lines[at])));
    }
    found
}

/// For "unknown field `stifness`, expected `stiffness` or `damping`": the expected name
/// nearest the unknown one, when it is near enough to be a typo.
fn nearest_expected(message: &str) -> Option<&str> {
    let rest = message.split("unknown field `").nth(1).or_else(|| message.split("unknown variant `").nth(1))?;
    let (unknown, rest) = rest.split_once('`')?;
    let expected = rest.split_once("expected")?.1;
    let names = expected.split('`').skip(1).step_by(2);
    names
        .map(|name| (strsim::normalized_damerau_levenshtein(unknown, name), name))
        .filter(|(score, _)| *score >= 0.6)
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, name)| name)
}

#[cfg(test)]
mod tests {
    use crate::scene::{Scene, DEFAULT_SCENE};

    fn error_of(text: &str) -> String {
        Scene::parse(text, "s.yaml").unwrap_err().to_string()
    }

    #[test]
    fn a_typo_inside_a_tagged_enum_is_named_with_its_path_and_the_nearest_field() {
        let text = DEFAULT_SCENE.replace("  stiffness: 1000.0", "  stifness: 1000.0");
        let message = error_of(&text);
        assert!(message.contains("material: unknown field, expected") && !message.contains("stifness"), "{message}");
        assert!(message.ends_with("(did you mean `stiffness`?)") && !message.contains("line 3"), "{message}");
    }

    #[test]
    fn a_bad_list_item_is_named_by_its_index() {
        let text = DEFAULT_SCENE.replace("kind: sphere, radius:", "kind: sphere, radus:");
        let message = error_of(&text);
        assert!(message.contains("tools[0]: unknown field, expected") && !message.contains("radus"), "{message}");
        assert!(message.ends_with("(did you mean `radius`?)"), "{message}");
        // Where serde_yaml_ng keeps the path itself, it is its own.
        let message = error_of(&DEFAULT_SCENE.replace("kind: sphere", "kind: spere"));
        assert!(message.contains("tools[0].shape.kind: unknown variant, expected"), "{message}");
        assert!(!message.contains("spere") && message.ends_with("(did you mean `sphere`?)"), "{message}");
    }

    #[test]
    fn a_path_serde_gives_is_kept_and_far_names_get_no_guess() {
        let message = error_of(&DEFAULT_SCENE.replace("  dt: 0.01", "  dt: fast"));
        assert!(message.contains("solver.dt: invalid type: a string, expected f64"), "{message}");
        assert!(message.ends_with("at line 20"), "the line of the user's text: {message}");
        let message = error_of(&DEFAULT_SCENE.replace("  stiffness: 1000.0", "  zzzzzz: 1000.0"));
        assert!(message.contains("material: unknown field") && !message.contains("did you mean"));
    }

    /// What an error says of a file that is no scene: where, and what was expected; never
    /// a byte of what the file holds (the leak of `--scene /etc/shadow`).
    #[test]
    fn a_file_that_is_no_scene_is_refused_without_its_text() {
        let secret = "s3cr3t";
        let files = [
            format!("root:x:0:0:{secret}:/root:/bin/bash\ndaemon:x:1:1:{secret}:/usr/sbin\n"),
            format!("root:*:20228:0:99999:7:::{secret}:\ndaemon:*:20228:0:99999:7:::\n"),
            format!("[{secret}]\n"),
            format!("volume: phantom\n{secret}: 1\n"),
            DEFAULT_SCENE.replace("  dt: 0.01", &format!("  dt: {secret}")),
            DEFAULT_SCENE.replace("kind: sphere", &format!("kind: {secret}")),
            DEFAULT_SCENE.replace("  stiffness: 1000.0", &format!("  {secret}: 1000.0")),
        ];
        for text in files {
            let message = error_of(&text);
            assert!(!message.contains(secret) && !message.contains("root"), "{message}");
        }
    }
}
