//! What a file given to `perpend node push` is, when it is not a
//! params.json: the mistakes people make (a sensors.csv or poses.csv, a
//! calibration record, the output of another command, a binary file) named
//! before the bus is opened, instead of the JSON parser's "expected value at
//! line 1 column 1".
//!
//! Recognised by content, not by name: a NUL byte or invalid UTF-8 is
//! binary; a first non-comment line holding commas is a CSV (its header's
//! columns tell sensors.csv, poses.csv, plan.csv apart, data-format.md); an
//! INI section is an EDS; a JSON object is a params.json when it has
//! `sensors`, a record when its `schema` is `perpend.record/…`, another
//! command's output for any other `schema`. Anything else is left to the
//! params.json reader, whose error then names line and column.

use std::path::Path;

use anyhow::{bail, Result};

/// What push takes, for every message.
const TAKES: &str = "push takes the params.json written by `perpend calibrate --out` \
                     (or `perpend node pull --out`)";

/// What `text` (the bytes of a file) is, when it is recognisably not a
/// params.json: a phrase like "a CSV (sensors.csv?)". `None`: JSON that may
/// be a params.json, or unrecognised.
pub fn not_params(bytes: &[u8]) -> Option<String> {
    let Ok(text) = std::str::from_utf8(bytes) else {
        return Some("a binary file (not UTF-8 text)".into());
    };
    if text.contains('\0') {
        return Some("a binary file (it holds NUL bytes)".into());
    }
    let text = text.trim_start_matches('\u{feff}');
    let first = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))?;
    if first.starts_with('{') {
        return json_kind(text);
    }
    if first.starts_with('[') && first.ends_with(']') && !first.contains(',') {
        return Some("an INI file (an EDS? `perpend eds` writes one)".into());
    }
    if first.contains(',') {
        return Some(format!("a CSV ({})", csv_kind(first)));
    }
    None
}

/// The kind of a CSV from its header line.
fn csv_kind(header: &str) -> &'static str {
    let cols: Vec<String> = header.split(',').map(|c| c.trim().to_lowercase()).collect();
    let has = |c: &str| cols.iter().any(|x| x == c);
    if has("x_mm") || has("m") {
        "sensors.csv?"
    } else if has("tilt_x_deg") {
        "a plan.csv of `perpend plan`?"
    } else if has("d_mm") || has("d1_mm") {
        "poses.csv?"
    } else {
        "sensors.csv or poses.csv?"
    }
}

/// The kind of a JSON object that is not a params.json.
fn json_kind(text: &str) -> Option<String> {
    let v: serde_json::Value = serde_json::from_str(text).ok()?;
    let o = v.as_object()?;
    if o.contains_key("sensors") {
        return None;
    }
    match o.get("schema").and_then(|s| s.as_str()) {
        Some(s) if s.starts_with("perpend.record/") => Some(
            "a calibration record (schema perpend.record): the params.json it describes \
             sits beside it without `.record`"
                .into(),
        ),
        Some(s) => Some(format!("the JSON output of another command (schema {s})")),
        None if o.contains_key("error") => Some("an error message saved as JSON".into()),
        None => None,
    }
}

/// Refuses `path` when it is recognisably not a params.json, naming what it
/// is and what push takes. Unreadable files are left to the reader.
///
/// # Errors
/// The file is a CSV, a record, another JSON, an INI or binary.
pub fn check_params(path: &Path) -> Result<()> {
    let Ok(bytes) = std::fs::read(path) else {
        return Ok(());
    };
    if let Some(kind) = not_params(&bytes) {
        bail!(
            "{}: this is {kind}, not a params.json: {TAKES}",
            path.display()
        );
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn each_kind_is_named() {
        let cases: [(&[u8], &str); 8] = [
            (
                b"sensor,x_mm,y_mm,z_mm,m,n,q\n1,0,0,0,0,0,1\n",
                "sensors.csv?",
            ),
            (
                b"\xef\xbb\xbf# c\r\npose,a,b,c,d_mm,d1_mm\r\n",
                "poses.csv?",
            ),
            (b"pose,tilt_x_deg,tilt_y_deg,standoff_mm\n", "plan.csv"),
            (
                b"{\"schema\":\"perpend.record/1\",\"utc\":\"x\"}",
                "calibration record",
            ),
            (b"{\"schema\":\"perpend.plan/1\"}", "schema perpend.plan/1"),
            (b"\x7fELF\x02\x01\x00\x00", "binary"),
            (b"\xff\xfe\x00", "binary"),
            (b"[FileInfo]\nFileName=perpend.eds\n", "EDS"),
        ];
        for (bytes, want) in cases {
            let got = not_params(bytes).unwrap_or_default();
            assert!(
                got.contains(want),
                "{:?}: {got}",
                String::from_utf8_lossy(bytes)
            );
        }
    }

    #[test]
    fn params_and_unrecognised_json_go_to_the_reader() {
        assert_eq!(not_params(b"{\"sensors\": [], \"method\": \"lsq\"}"), None);
        assert_eq!(not_params(b"{\"sensors\": [ broken"), None);
        assert_eq!(not_params(b"12.5"), None);
    }
}
