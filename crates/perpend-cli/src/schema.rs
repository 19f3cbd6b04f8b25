//! The `schema` tag of every `--json` output of `perpend` outside the
//! analysis commands: `"schema": "perpend.<kind>/<version>"`, always the
//! first key, so that a consumer can dispatch on the first bytes and refuse
//! a version it does not know. docs/json-node.md lists each shape.
//!
//! The version changes when a key is removed or changes meaning; added keys
//! keep it. serde_json's maps are sorted (no `preserve_order`), so the tag
//! is written in front of the object by [`tagged`] rather than inserted.

use serde_json::Value;

/// `perpend node info --json`.
pub const NODE_INFO: &str = "perpend.node-info/1";
/// `perpend node status --json`.
pub const NODE_STATUS: &str = "perpend.node-status/1";
/// `perpend node clear-errors --json`.
pub const CLEAR_ERRORS: &str = "perpend.clear-errors/1";
/// `perpend node pdo show --json`.
pub const PDO: &str = "perpend.pdo/1";
/// `perpend node lss scan --json`.
pub const LSS_SCAN: &str = "perpend.lss-scan/1";
/// `perpend node lss inquire --json`.
pub const LSS_INQUIRE: &str = "perpend.lss-inquire/1";
/// `perpend record history --json`.
pub const RECORD_HISTORY: &str = "perpend.record-history/2";
/// The error object of any command run with `--json`.
pub const ERROR: &str = "perpend.error/1";
/// `DIR/cell.json`, the figures and outcome of `perpend cell run`.
pub const CELL: &str = "perpend.cell/2";
/// `perpend frames --json`: the frame errors of a reversal run.
pub const FRAMES: &str = "perpend.frames/1";

/// `v` as one line of JSON with `"schema": schema` as its first key (a
/// `schema` key `v` has is replaced). A value that is not an object is
/// wrapped as `{"schema": …, "value": v}`.
pub fn tagged(schema: &str, v: &Value) -> String {
    let without;
    let body = match v {
        Value::Object(m) if m.contains_key("schema") => {
            let mut m = m.clone();
            m.remove("schema");
            without = Value::Object(m);
            &without
        }
        other => other,
    };
    // Serialising a `Value` cannot fail.
    perpend_formats::schema::to_json(schema, body).unwrap_or_default()
}

/// [`tagged`] for a file a person reads too: the object `v` indented, its
/// `schema` the first key. A value that is not an object is wrapped as in
/// [`tagged`].
pub fn tagged_pretty(schema: &str, v: &Value) -> String {
    let mut m = match v {
        Value::Object(m) => m.clone(),
        other => {
            let mut m = serde_json::Map::new();
            m.insert("value".into(), other.clone());
            m
        }
    };
    m.remove("schema");
    let head = format!("{{\n  \"schema\": {}", Value::from(schema));
    if m.is_empty() {
        return head + "\n}";
    }
    let body = serde_json::to_string_pretty(&Value::Object(m)).unwrap_or_default();
    // `body` is "{\n  …\n}": the schema goes in front of its first key.
    format!("{head},\n{}", body.get(2..).unwrap_or(""))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn the_schema_comes_first_and_the_rest_is_kept() {
        let v = json!({"a": 1, "schema": "old", "z": {"k": [1, "\"q\""]}});
        let s = tagged(PDO, &v);
        assert!(
            s.starts_with("{\"schema\":\"perpend.pdo/1\",\"a\":1"),
            "{s}"
        );
        let back: Value = serde_json::from_str(&s).unwrap();
        assert_eq!(back["z"], v["z"]);
        assert_eq!(back["schema"], PDO);
        assert_eq!(back.as_object().unwrap().len(), 3);
        let w: Value = serde_json::from_str(&tagged(ERROR, &json!([1]))).unwrap();
        assert_eq!(w["value"], json!([1]));
    }

    #[test]
    fn the_pretty_form_is_the_same_object_with_the_schema_first() {
        let v = json!({"b": [1, 2], "schema": "old", "a": {"k": "\"q\""}});
        let s = tagged_pretty(CELL, &v);
        assert!(
            s.starts_with("{\n  \"schema\": \"perpend.cell/2\",\n  \"a\""),
            "{s}"
        );
        let back: Value = serde_json::from_str(&s).unwrap();
        assert_eq!(
            back,
            serde_json::from_str::<Value>(&tagged(CELL, &v)).unwrap()
        );
        let empty: Value = serde_json::from_str(&tagged_pretty(CELL, &json!({}))).unwrap();
        assert_eq!(empty, json!({"schema": CELL}));
    }
}
