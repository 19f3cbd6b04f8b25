//! Every `--json` output of the lab's commands starts with
//! `"schema": "perpend.<kind>/<version>"`, and docs/json.md shows each
//! shape: the example's keys (recursively, first element of arrays) are
//! those of the real output of the command on a simulated run.
//! `JSON_DUMP=1` prints the real outputs (to refresh the examples).
#![allow(clippy::unwrap_used, missing_docs)]

use std::collections::BTreeSet;
use std::path::Path;

use clap::Parser;
use perpend_formats::schema;
use serde_json::Value;

#[derive(Parser)]
struct Sim {
    #[command(flatten)]
    a: perpend_calib::sim::Args,
}

#[derive(Parser)]
struct Diag {
    #[command(flatten)]
    a: perpend_diagnosis::diagnose::Args,
}

#[derive(Parser)]
struct Meas {
    #[command(flatten)]
    a: perpend_calib::measure::Args,
}

/// The ```json blocks of docs/json.md, by their `schema`.
fn examples() -> Vec<(String, Value)> {
    let doc = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/json.md"))
        .unwrap();
    let mut out = Vec::new();
    let mut rest = doc.as_str();
    while let Some(i) = rest.find("```json\n") {
        let body = &rest[i + 8..];
        let end = body.find("```").unwrap();
        let v: Value = serde_json::from_str(&body[..end]).unwrap();
        let s = v["schema"].as_str().unwrap().to_string();
        out.push((s, v));
        rest = &body[end..];
    }
    out
}

fn example(schema: &str) -> Value {
    let found = examples().into_iter().find(|(s, _)| s == schema);
    assert!(found.is_some(), "docs/json.md has no example of {schema}");
    found.unwrap().1
}

/// The key paths of `v` (objects' keys, arrays through their first
/// element).
fn keys(v: &Value, path: &str, out: &mut BTreeSet<String>) {
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                let p = format!("{path}.{k}");
                out.insert(p.clone());
                keys(x, &p, out);
            }
        }
        Value::Array(a) => {
            if let Some(x) = a.first() {
                keys(x, &format!("{path}[]"), out);
            }
        }
        _ => {}
    }
}

/// The real output starts with the schema and has the example's keys.
fn check(schema: &str, text: &str) {
    if std::env::var_os("JSON_DUMP").is_some() {
        eprintln!("{text}");
    }
    let head = format!("{{\"schema\":\"{schema}\"");
    assert!(text.starts_with(&head), "{}", &text[..text.len().min(80)]);
    let real: Value = serde_json::from_str(text).unwrap();
    let (mut want, mut got) = (BTreeSet::new(), BTreeSet::new());
    keys(&example(schema), "", &mut want);
    keys(&real, "", &mut got);
    let missing: Vec<_> = want.difference(&got).collect();
    let extra: Vec<_> = got.difference(&want).collect();
    assert!(
        missing.is_empty() && extra.is_empty(),
        "{schema}: docs/json.md has {missing:?} the output lacks; the output has {extra:?} the doc lacks"
    );
}

fn simulate(dir: &Path) {
    let out = dir.to_str().unwrap();
    let a = Sim::parse_from(["s", "--out", out, "--poses", "40", "--seed", "3"]).a;
    perpend_calib::sim::run(&a).unwrap();
}

#[test]
fn diagnose_and_measure_json_match_the_doc() {
    let dir = tempfile::tempdir().unwrap();
    simulate(dir.path());
    let s = dir.path().join("sensors.csv");
    let p = dir.path().join("poses.csv");
    let (s, p) = (s.to_str().unwrap(), p.to_str().unwrap());
    let a = Diag::parse_from(["d", "--sensors", s, "--poses", p, "--json", "--draws", "8"]).a;
    let mut buf = Vec::new();
    perpend_diagnosis::diagnose::run_to(&a, &mut buf).unwrap();
    check(schema::DIAGNOSE, &String::from_utf8(buf).unwrap());
    let a = Meas::parse_from(["m", "--sensors", s, "--poses", p, "--json"]).a;
    let mut buf = Vec::new();
    perpend_calib::measure::run_to(&a, &mut buf).unwrap();
    check(schema::MEASURE, &String::from_utf8(buf).unwrap());
}

#[test]
fn bench_speed_json_matches_the_doc() {
    let r = perpend_diagnosis::bench::speed(1).unwrap();
    check(
        schema::BENCH_SPEED,
        &schema::to_json(schema::BENCH_SPEED, &r).unwrap(),
    );
}

/// The heavy outputs (minutes to compute) are checked by their schema and
/// that the doc has each.
#[test]
fn every_schema_has_an_example() {
    let all = [
        schema::DIAGNOSE,
        schema::MEASURE,
        schema::BENCH_ACCURACY,
        schema::BENCH_SPEED,
        schema::BENCH_DIAGNOSE_SELF,
        schema::BENCH_CURVATURE,
        schema::STUDY,
    ];
    let ex = examples();
    for s in all {
        assert!(s.starts_with("perpend.") && s.contains('/'), "{s}");
        assert!(
            ex.iter().any(|(e, _)| e == s),
            "docs/json.md: no example of {s}"
        );
    }
    for (s, v) in &ex {
        let first = v.as_object().unwrap().keys().next().cloned();
        assert!(
            all.contains(&s.as_str()),
            "docs/json.md: unknown schema {s}"
        );
        assert!(v.is_object() && first.is_some(), "{s}");
    }
}
