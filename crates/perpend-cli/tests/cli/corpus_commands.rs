//! host-tests/corpus/commands: each bad command line gives its message
//! (issue 31, item 6). The format is in that directory's README.md.
#![allow(clippy::unwrap_used, clippy::panic)]

use crate::support;

use std::path::{Path, PathBuf};
use std::process::Command;

use support::{VirtualBus, BIN};

/// One case: its directory and its `key: value` lines.
struct Case {
    dir: PathBuf,
    lines: Vec<(String, String)>,
}

impl Case {
    fn read(dir: &Path) -> Self {
        let text = std::fs::read_to_string(dir.join("case"))
            .unwrap_or_else(|e| panic!("{}: no case file: {e}", dir.display()));
        let lines = text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .map(|l| {
                let (k, v) = l
                    .split_once(':')
                    .unwrap_or_else(|| panic!("{}: '{l}' is not key: value", dir.display()));
                (k.trim().to_string(), v.trim().to_string())
            })
            .collect();
        Case {
            dir: dir.to_path_buf(),
            lines,
        }
    }

    fn all<'a>(&'a self, key: &'a str) -> impl Iterator<Item = &'a str> {
        self.lines
            .iter()
            .filter(move |(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }

    fn one<'a>(&'a self, key: &'a str) -> Option<&'a str> {
        self.all(key).next()
    }
}

fn cases() -> Vec<Case> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../host-tests/corpus/commands");
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&root)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    dirs.iter().map(|d| Case::read(d)).collect()
}

/// Runs one case; the failures as sentences.
fn run(c: &Case, bus: Option<&VirtualBus>) -> Vec<String> {
    let name = c.dir.file_name().unwrap().to_string_lossy().into_owned();
    let tmp = tempfile::tempdir().unwrap();
    let fill = |s: &str| {
        s.replace("{case}", c.dir.to_str().unwrap())
            .replace("{dir}", tmp.path().to_str().unwrap())
            .replace("{bus}", bus.map_or("", |b| b.bus.as_str()))
            .replace("{node}", "16")
    };
    let args = fill(c.one("args").unwrap_or_else(|| panic!("{name}: no args")));
    let out = Command::new(BIN)
        .arg("--quiet")
        .args(args.split_whitespace())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    let mut bad = Vec::new();
    if let Some(code) = c.one("exit") {
        if out.status.code() != code.parse().ok() {
            bad.push(format!(
                "{name}: exit {:?}, expected {code}",
                out.status.code()
            ));
        }
    }
    for want in c.all("stderr").filter(|w| !err.contains(*w)) {
        bad.push(format!("{name}: stderr lacks '{want}':\n{err}"));
    }
    for not in c.all("stderr_not").filter(|w| err.contains(*w)) {
        bad.push(format!("{name}: stderr has '{not}':\n{err}"));
    }
    for f in c.all("absent").map(fill).filter(|f| Path::new(f).exists()) {
        bad.push(format!("{name}: {f} was written"));
    }
    bad
}

#[test]
fn every_bad_command_gives_its_message() {
    let cases = cases();
    assert!(cases.len() >= 10, "{} cases", cases.len());
    let board = cases
        .iter()
        .any(|c| c.one("board") == Some("yes"))
        .then(|| VirtualBus::start(&["--node-id", "16", "--plane", "0.035,-0.052,1,-40"]));
    let bad: Vec<String> = cases.iter().flat_map(|c| run(c, board.as_ref())).collect();
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}
