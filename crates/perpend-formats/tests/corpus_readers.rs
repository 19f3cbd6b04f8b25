//! The corpus of bad input files (`host-tests/corpus/readers/`, written by
//! its `make.py`): every case of `cases.tsv` read by its reader gives the
//! message the manifest names (file, line, cause). The fuzz targets of the
//! readers start from the same files (`cargo xtask fuzz`).
#![allow(clippy::unwrap_used, missing_docs)]

use std::path::{Path, PathBuf};

use perpend_formats::exchange::{parse_poses, parse_readings, parse_sensors, SensorTable};
use perpend_formats::paramfile::ParamFile;
use perpend_formats::plausible::{check_readings, check_run, left_out_lines};

fn dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../host-tests/corpus/readers")
}

fn head() -> SensorTable {
    let b = std::fs::read(dir().join("head.csv")).unwrap();
    parse_sensors(b.as_slice(), "head.csv").unwrap()
}

/// The message the reader gives for `bytes` named `name` (an accepted
/// file gives the warnings, or "accepted").
fn message(reader: &str, name: &str, bytes: &[u8]) -> String {
    let err = |e: perpend_formats::exchange::ExchangeError| e.to_string();
    let r = match reader {
        "sensors" => parse_sensors(bytes, name)
            .map(|_| "accepted".into())
            .map_err(err),
        "poses" => parse_poses(bytes, name, Some(4))
            .map(|_| "accepted".into())
            .map_err(err),
        "readings" => parse_readings(bytes, name, Some(4))
            .map(|_| "accepted".into())
            .map_err(err),
        "params" => {
            let text = String::from_utf8_lossy(bytes);
            ParamFile::parse(&text, name)
                .map(|_| "accepted".into())
                .map_err(|e| format!("{e:#}"))
        }
        "run" | "run-left" => parse_poses(bytes, name, Some(4))
            .and_then(|p| check_run(name, &head(), p))
            .map(|(_, left, total)| left_out_lines(name, &left, total).join("\n"))
            .map_err(err),
        "readings-left" => parse_readings(bytes, name, Some(4))
            .and_then(|mut t| check_readings(name, &head(), &mut t))
            .map(|(left, total)| left_out_lines(name, &left, total).join("\n"))
            .map_err(err),
        other => Ok(format!("unknown reader {other}")),
    };
    r.unwrap_or_else(|e| e)
}

#[test]
fn every_bad_file_gives_its_message() {
    let manifest = std::fs::read_to_string(dir().join("cases.tsv")).unwrap();
    let mut n = 0;
    let mut wrong = Vec::new();
    for line in manifest
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let f: Vec<&str> = line.split('\t').collect();
        assert_eq!(f.len(), 3, "cases.tsv: {line}");
        let bytes = std::fs::read(dir().join(f[0])).unwrap();
        let got = message(f[1], f[0], &bytes);
        if !f[2].split("&&").all(|want| got.contains(want)) {
            wrong.push(format!("{}: want '{}', got '{got}'", f[0], f[2]));
        }
        n += 1;
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
    assert!(n >= 30, "{n} cases");
}

/// Every file of the corpus is in the manifest (a case without a message
/// is not a test).
#[test]
fn every_file_is_a_case() {
    let manifest = std::fs::read_to_string(dir().join("cases.tsv")).unwrap();
    for e in std::fs::read_dir(dir()).unwrap() {
        let name = e.unwrap().file_name().into_string().unwrap();
        let own = ["cases.tsv", "make.py", "head.csv"].contains(&name.as_str());
        let listed = manifest
            .lines()
            .any(|l| l.split('\t').next() == Some(name.as_str()));
        assert!(own || listed, "{name} is not in cases.tsv");
    }
}
