//! The `"schema"` key of every `--json` output of the lab's commands:
//! `"perpend.<kind>/<version>"`, always the first key, so that a reader
//! can tell the shape (and refuse one it does not know) before reading
//! the rest. The shapes, with an example each: `docs/json.md` (checked
//! against real output by `tests/diagnosis/json_schema.rs`). The version goes up
//! when a key changes meaning or goes away; adding a key keeps it.

use serde::Serialize;

/// `perpend diagnose --json`.
pub const DIAGNOSE: &str = "perpend.diagnose/1";
/// `perpend measure --json`.
pub const MEASURE: &str = "perpend.measure/1";
/// `perpend bench accuracy --json`.
pub const BENCH_ACCURACY: &str = "perpend.bench-accuracy/1";
/// `perpend bench speed --json`.
pub const BENCH_SPEED: &str = "perpend.bench-speed/1";
/// `perpend bench diagnose-self --json`.
pub const BENCH_DIAGNOSE_SELF: &str = "perpend.bench-diagnose-self/1";
/// `perpend bench curvature --json`.
pub const BENCH_CURVATURE: &str = "perpend.bench-curvature/1";
/// `perpend study paper --json`.
pub const STUDY: &str = "perpend.study/1";

/// `v` as one line of JSON with `"schema": schema` as its first key.
/// `v` must serialise to an object (every output above does); anything
/// else is wrapped as `{"schema": …, "value": v}`.
///
/// # Errors
/// Serialisation errors of `v`.
pub fn to_json<T: Serialize>(schema: &str, v: &T) -> serde_json::Result<String> {
    let body = serde_json::to_string(v)?;
    let head = format!("{{\"schema\":{}", serde_json::to_string(schema)?);
    Ok(match body.strip_prefix('{') {
        Some("}") => head + "}",
        Some(rest) => format!("{head},{rest}"),
        None => format!("{head},\"value\":{body}}}"),
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn schema_is_the_first_key_of_any_shape() {
        let v = serde_json::json!({"a": 1, "b": [2]});
        let s = to_json(MEASURE, &v).unwrap();
        assert!(
            s.starts_with("{\"schema\":\"perpend.measure/1\",\"a\":1"),
            "{s}"
        );
        let back: serde_json::Value = serde_json::from_str(&s).unwrap();
        assert_eq!(back["b"][0], 2);
        assert_eq!(
            to_json(STUDY, &serde_json::json!({})).unwrap(),
            "{\"schema\":\"perpend.study/1\"}"
        );
        let s = to_json(STUDY, &3).unwrap();
        let back: serde_json::Value = serde_json::from_str(&s).unwrap();
        assert_eq!(
            (back["schema"].as_str(), back["value"].as_i64()),
            (Some(STUDY), Some(3))
        );
    }
}
