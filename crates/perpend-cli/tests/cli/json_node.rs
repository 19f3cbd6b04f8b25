//! docs/json-node.md against real output: every example's command runs
//! (against a virtual board where it needs one) and its output has the
//! example's schema as first key and exactly the example's keys, at the top
//! level and in the first element of each array of objects (issue 31,
//! item 5).
#![allow(clippy::unwrap_used, clippy::panic)]

use crate::support;

use std::collections::BTreeSet;
use std::process::Command;

use serde_json::Value;
use support::{VirtualBus, BIN};

const DOC: &str = include_str!("../../../../docs/json-node.md");

/// (command line, example) of each `<!-- run: … -->` + ```json block.
fn examples() -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut lines = DOC.lines();
    while let Some(l) = lines.next() {
        let Some(cmd) = l
            .strip_prefix("<!-- run: ")
            .and_then(|r| r.strip_suffix(" -->"))
        else {
            continue;
        };
        assert_eq!(lines.next(), Some("```json"), "{cmd}: no json block");
        let body: Vec<&str> = lines.by_ref().take_while(|x| *x != "```").collect();
        out.push((cmd.to_string(), body.join("\n")));
    }
    out
}

/// Paths of keys: the object's keys, and recursively those of the first
/// element of each array of objects and of each nested object.
fn keys(v: &Value, at: &str, out: &mut BTreeSet<String>) {
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                let p = format!("{at}.{k}");
                out.insert(p.clone());
                keys(x, &p, out);
            }
        }
        Value::Array(a) => {
            if let Some(x) = a.first() {
                keys(x, &format!("{at}[]"), out);
            }
        }
        _ => {}
    }
}

/// The output's keys may have arrays the example shows empty (no
/// emergencies, no LSS nodes): those paths are compared only when the
/// example has an element.
fn compare(cmd: &str, example: &str, real: &str) {
    let (e, r): (Value, Value) = (
        serde_json::from_str(example).unwrap_or_else(|x| panic!("{cmd}: example: {x}")),
        serde_json::from_str(real).unwrap_or_else(|x| panic!("{cmd}: output {real}: {x}")),
    );
    let schema = e["schema"].as_str().unwrap();
    let compact: String = real.split_whitespace().collect();
    assert!(
        compact.starts_with(&format!("{{\"schema\":\"{schema}\"")),
        "{cmd}: schema not first: {real}"
    );
    let (mut ke, mut kr) = (BTreeSet::new(), BTreeSet::new());
    keys(&e, "", &mut ke);
    keys(&r, "", &mut kr);
    // keys under an array the example leaves empty are not compared
    kr.retain(|k| match k.rsplit_once("[]") {
        None => true,
        Some((p, _)) => ke.iter().any(|x| x.starts_with(&format!("{p}[]"))),
    });
    assert_eq!(ke, kr, "{cmd}: keys differ from docs/json-node.md");
}

#[test]
fn every_example_matches_the_real_output() {
    let vb = VirtualBus::start(&["--node-id", "16", "--plane", "0.035,-0.052,1,-40"]);
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().to_str().unwrap();
    let run = |args: &[&str]| {
        Command::new(BIN)
            .arg("--quiet")
            .args(args)
            .output()
            .unwrap()
    };
    assert!(run(&["simulate", "--out", d, "--seed", "3"])
        .status
        .success());
    let (s, p, o) = (
        format!("{d}/sensors.csv"),
        format!("{d}/poses.csv"),
        format!("{d}/params.json"),
    );
    let cal = run(&["calibrate", "--sensors", &s, "--poses", &p, "--out", &o]);
    assert!(
        cal.status.success(),
        "{}",
        String::from_utf8_lossy(&cal.stderr)
    );
    let ex = examples();
    assert!(ex.len() >= 11, "{} examples", ex.len());
    for (cmd, example) in ex {
        let line = cmd
            .replace("{bus}", &vb.bus)
            .replace("{node}", "16")
            .replace("{dir}", d);
        let args: Vec<&str> = line.split_whitespace().collect();
        let out = run(&args);
        let real = String::from_utf8_lossy(&out.stdout);
        let want_ok = !example.contains("perpend.error/");
        assert_eq!(out.status.success(), want_ok, "{cmd}: {real}");
        compare(&cmd, &example, real.trim());
    }
}
