//! Golden outputs of `perpend diagnose`: the guard of the diagnosis'
//! restructuring (issue 35, item 1), which must leave every output
//! byte-identical.
//!
//! Each case is a run checked in under `tests/golden/`: `blind/*` written
//! by the independent generator `host-tests/blind/gen.py`
//! (`tests/golden/cases.py` lists the cases: null, gain, incidence,
//! thermal, drift, blunders, a mixture, a ripple no candidate has, a run
//! without declared noise) and `sim/*` by `perpend simulate` (the
//! crate's own test runs: the 40-pose seed-3 run of `json_schema.rs`, a
//! timed warm-up with missing readings). Every case runs through
//! [`perpend_diagnosis::diagnose::run_to`], the entry point of the command, with
//! default options, twice: the text report with `--out` (the report, the
//! parameter file and the calibration record written beside it), then
//! `--json`. Each output is compared byte for byte with
//! `tests/golden/<group>/<case>/expected/`:
//!
//! - `report.txt`: the text, with the temporary `--out` directory written
//!   as `$OUT`;
//! - `diagnose.json`: the `--json` line;
//! - `params.json`: the parameter file;
//! - `record.json`: the calibration record without its times of writing
//!   (`utc`, `events`) and `tool_version`, the directory again as `$OUT`.
//!
//! Regenerate (only when an output is meant to change, and say so in the
//! commit): `PERPEND_BLESS=1 cargo test -p perpend-diagnosis --test
//! diagnose_golden`. The diagnosis is seeded and single-threaded, and
//! serde_json writes floats round-trip exact, so a run is reproducible
//! byte for byte on one platform; the whole test takes about 20 s of CPU
//! in the debug build.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::{Path, PathBuf};

use clap::Parser;

#[derive(Parser)]
struct Diag {
    #[command(flatten)]
    a: perpend_diagnosis::diagnose::Args,
}

/// The case directory, relative to the crate (the paths appear in the
/// report as given).
fn case_dir(group: &str, name: &str) -> PathBuf {
    Path::new("tests/golden").join(group).join(name)
}

/// Runs the command with `extra` options; returns what it printed.
fn run(dir: &Path, draws: Option<&str>, extra: &[&str]) -> String {
    let s = dir.join("sensors.csv");
    let p = dir.join("poses.csv");
    let mut argv = vec!["d", "--sensors", s.to_str().unwrap(), "--poses"];
    argv.push(p.to_str().unwrap());
    argv.extend_from_slice(extra);
    if let Some(d) = draws {
        argv.extend_from_slice(&["--draws", d]);
    }
    let a = Diag::parse_from(argv).a;
    let mut buf = Vec::new();
    perpend_diagnosis::diagnose::run_to(&a, &mut buf).unwrap();
    String::from_utf8(buf).unwrap()
}

/// The outputs of one case, by file name.
fn outputs(dir: &Path, draws: Option<&str>) -> Vec<(&'static str, String)> {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("params.json");
    let text = run(dir, draws, &["--out", out.to_str().unwrap()]);
    let text = text.replace(tmp.path().to_str().unwrap(), "$OUT");
    let params = std::fs::read_to_string(&out).unwrap();
    let record = std::fs::read_to_string(perpend_calib::record::record_path(&out)).unwrap();
    let mut record: serde_json::Value = serde_json::from_str(&record).unwrap();
    if let Some(m) = record.as_object_mut() {
        for k in ["utc", "events", "tool_version"] {
            m.remove(k);
        }
    }
    let record = serde_json::to_string_pretty(&record).unwrap() + "\n";
    let record = record.replace(tmp.path().to_str().unwrap(), "$OUT");
    let json = run(dir, draws, &["--json"]);
    vec![
        ("report.txt", text),
        ("diagnose.json", json),
        ("params.json", params),
        ("record.json", record),
    ]
}

/// Compares (or, with `PERPEND_BLESS=1`, writes) the outputs of a case.
fn golden(group: &str, name: &str, draws: Option<&str>) {
    let dir = case_dir(group, name);
    assert!(
        dir.join("poses.csv").is_file(),
        "missing case {}",
        dir.display()
    );
    let expected = dir.join("expected");
    let bless = std::env::var_os("PERPEND_BLESS").is_some_and(|v| v == "1");
    let mut differ = Vec::new();
    for (file, got) in outputs(&dir, draws) {
        let path = expected.join(file);
        if bless {
            std::fs::create_dir_all(&expected).unwrap();
            std::fs::write(&path, &got).unwrap();
            continue;
        }
        let want = std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("{}: {e}; write it with PERPEND_BLESS=1", path.display()));
        if want != got {
            let line = want
                .lines()
                .zip(got.lines())
                .position(|(a, b)| a != b)
                .map_or(want.lines().count().min(got.lines().count()), |i| i);
            differ.push(format!(
                "{} differs from line {}:\n  want: {}\n  got:  {}",
                path.display(),
                line + 1,
                want.lines().nth(line).unwrap_or("<end>"),
                got.lines().nth(line).unwrap_or("<end>")
            ));
        }
    }
    assert!(differ.is_empty(), "{}", differ.join("\n"));
}

macro_rules! cases {
    ($($test:ident: $group:literal / $name:literal, $draws:expr;)*) => {
        $(
            #[test]
            fn $test() {
                golden($group, $name, $draws);
            }
        )*
    };
}

cases! {
    blind_null: "blind" / "null", None;
    blind_null_undeclared: "blind" / "null_undeclared", Some("6");
    blind_gain: "blind" / "gain", Some("6");
    blind_incidence: "blind" / "incidence", Some("6");
    blind_thermal: "blind" / "thermal", Some("6");
    blind_drift: "blind" / "drift", Some("6");
    blind_blunder: "blind" / "blunder", Some("6");
    blind_mixture: "blind" / "mixture", Some("6");
    blind_ripple: "blind" / "ripple", Some("6");
    sim_paper40: "sim" / "paper40", None;
    sim_timed60: "sim" / "timed60", None;
}

/// Every case directory checked in has a test above (a case added to
/// `cases.py` but not here would silently go unchecked).
#[test]
fn every_checked_in_case_is_tested() {
    let listed = [
        "blind/null",
        "blind/null_undeclared",
        "blind/gain",
        "blind/incidence",
        "blind/thermal",
        "blind/drift",
        "blind/blunder",
        "blind/mixture",
        "blind/ripple",
        "sim/paper40",
        "sim/timed60",
    ];
    let mut found = Vec::new();
    for group in ["blind", "sim"] {
        for e in std::fs::read_dir(Path::new("tests/golden").join(group)).unwrap() {
            let e = e.unwrap();
            if e.path().is_dir() {
                found.push(format!("{group}/{}", e.file_name().to_string_lossy()));
            }
        }
    }
    found.sort();
    let mut want: Vec<String> = listed.iter().map(|s| s.to_string()).collect();
    want.sort();
    assert_eq!(found, want);
}
