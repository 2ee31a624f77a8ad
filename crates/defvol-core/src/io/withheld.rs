//! Parse errors that never quote the file: serde's messages carry the text they met
//! (`invalid type: string "root:x:0:0:…"`, ``unknown field `…` ``), so any file a caller can
//! name would be readable one error at a time. What stays: the field path, the kind of
//! value found, what was expected (the schema's words) and the line and column.

/// `message` (from serde, serde_yaml_ng or libyaml) with the input text it quotes withheld.
pub fn withhold_found(message: &str) -> String {
    if !message.contains(['`', '"']) {
        return message.to_owned();
    }
    let (rest, location) = split_location(message);
    let (path, body) = split_path(rest);
    // What follows ", expected" is the schema's expectation; what precedes it, the input.
    let (head, expected) = match body.rfind(", expected ").max(body.rfind(", there are no ")) {
        Some(at) => body.split_at(at),
        None => (body, ""),
    };
    format!("{path}{}{expected}{location}", found_kind(head))
}

/// The message's head with what it quotes of the input reduced to a kind of value.
fn found_kind(head: &str) -> String {
    for prefix in ["invalid type: ", "invalid value: "] {
        if let Some(found) = head.strip_prefix(prefix) {
            return format!("{prefix}{}", unexpected(found));
        }
    }
    for named in ["unknown field", "unknown variant"] {
        if head.starts_with(named) {
            return named.to_owned();
        }
    }
    // serde derives name these from the schema, never from the input.
    if head.starts_with("missing field `") || head.starts_with("duplicate field `") {
        return head.to_owned();
    }
    match head.find(['`', '"']) {
        Some(at) => format!("{} (the text found there is withheld)", head[..at].trim_end()),
        None => head.to_owned(),
    }
}

/// serde's `Unexpected` display (`string "…"`, ``integer `5` ``) as a kind alone.
fn unexpected(found: &str) -> &'static str {
    const KINDS: [(&str, &str); 5] = [
        ("string ", "a string"),
        ("integer ", "an integer"),
        ("floating point ", "a number"),
        ("boolean ", "a boolean"),
        ("character ", "a character"),
    ];
    if let Some((_, kind)) = KINDS.iter().find(|(prefix, _)| found.starts_with(prefix)) {
        return kind;
    }
    match found {
        "sequence" => "a sequence",
        "map" => "a map",
        "unit value" => "null",
        _ => "a value",
    }
}

/// `(text, " at line L column C")` when the message ends with a location.
fn split_location(message: &str) -> (&str, &str) {
    let Some(at) = message.rfind(" at ") else { return (message, "") };
    let words: Vec<&str> = message[at + 4..].split(' ').collect();
    let number = |w: &str| !w.is_empty() && w.bytes().all(|b| b.is_ascii_digit());
    let is_location = match words.as_slice() {
        ["line", l, "column", c] => number(l) && number(c),
        ["position", p] => number(p),
        _ => false,
    };
    if is_location {
        message.split_at(at)
    } else {
        (message, "")
    }
}

/// `("solver.dt: ", rest)` when the message starts with a field path (schema names and
/// indices only; anything else is not taken for one).
fn split_path(message: &str) -> (&str, &str) {
    let Some(at) = message.find(": ") else { return ("", message) };
    let path = &message[..at];
    let path_like = !path.is_empty()
        && path.bytes().all(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'.' | b'[' | b']' | b'?'));
    if path_like {
        message.split_at(at + 2)
    } else {
        ("", message)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// serde_yaml_ng's own messages on text holding a secret, rewritten.
    fn of_yaml<T: serde::de::DeserializeOwned + std::fmt::Debug>(text: &str) -> String {
        withhold_found(&serde_yaml_ng::from_str::<T>(text).unwrap_err().to_string())
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Solver {
        dt: f64,
        kind: Kind,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(rename_all = "snake_case")]
    enum Kind {
        Implicit,
    }

    const SECRET: &str = "s3cr3t-line";

    #[test]
    fn strings_fields_and_variants_found_become_their_kind() {
        let text = format!("dt: \"{SECRET}, expected f64\"\nkind: implicit\n");
        let message = of_yaml::<Solver>(&text);
        assert_eq!(message, "dt: invalid type: a string, expected f64 at line 1 column 5");
        let message = of_yaml::<Solver>(&format!("dt: 1.0\nkind: {SECRET}\n"));
        assert_eq!(message, "kind: unknown variant, expected `implicit` at line 2 column 7");
        let message = of_yaml::<Solver>(&format!("dt: 1.0\nkind: implicit\n{SECRET}: 1\n"));
        assert_eq!(message, "unknown field, expected `dt` or `kind` at line 3 column 1");
        let message = withhold_found(&format!("unknown field `{SECRET}, expected x`, there are no fields"));
        assert_eq!(message, "unknown field, there are no fields");
        let message = of_yaml::<Solver>("root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1\n");
        assert!(!message.contains("root") && message.starts_with("invalid type: a string"), "{message}");
    }

    #[test]
    fn the_schemas_words_and_the_parsers_own_stay() {
        assert_eq!(of_yaml::<Solver>("kind: implicit\n"), "missing field `dt`");
        let message = of_yaml::<Solver>("dt: [1, 2\n");
        assert!(message.contains("line") && !message.contains("withheld"), "{message}");
        assert_eq!(
            withhold_found("invalid value: integer `7`, expected a positive count at line 2 column 3"),
            "invalid value: an integer, expected a positive count at line 2 column 3"
        );
    }

    #[test]
    fn anything_else_that_quotes_is_cut_where_the_quote_starts() {
        let message = withhold_found(&format!("duplicate entry with key \"{SECRET}\" at line 4 column 1"));
        assert_eq!(message, "duplicate entry with key (the text found there is withheld) at line 4 column 1");
        // A location-like tail inside the quoted text is not taken for the location.
        let message = withhold_found(&format!("odd `{SECRET} at line 1 column 2`"));
        assert!(!message.contains(SECRET), "{message}");
    }
}
