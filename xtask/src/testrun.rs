//! `cargo xtask test [--jobs N]`: the workspace's host tests as `cargo test`
//! runs them (same packages, features and test binaries, then the
//! doctests), but with up to N test binaries running at once (default: the
//! machine's cores).
//!
//! `cargo test` runs its test binaries one after another: on the 2-core CI
//! machine one single-threaded binary (the study document, ≈ 70 s) leaves a
//! core idle, and the virtual-board binaries mostly wait on sockets. Here
//! `cargo test --no-run --message-format=json-render-diagnostics` builds
//! them and names their executables; each then runs in its package's
//! directory (as cargo does), its output kept whole and printed when it
//! ends (`Running …` then the harness's lines, so `test result:` lines
//! count as before). Binaries of perpend-diagnosis and perpend-calib (long,
//! CPU-bound) start first. `PERPEND_BIN` names the `perpend` binary the test build made
//! (for perpend-cli's integration tests), so tests that run it elsewhere
//! need not build it again with other features. Limits: tests that need a machine to themselves must not exist
//! (they would already be flaky under the harness's own threads); a
//! failing binary does not stop the others, and the failures are printed
//! first at the end.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::Mutex;

use super::{cargo, root, Result};

/// One test executable.
#[derive(Debug, Clone, PartialEq)]
pub struct TestBin {
    /// Package name.
    pub package: String,
    /// `unittests src/lib.rs` or `tests/NAME.rs`, as cargo names it.
    pub label: String,
    /// Path of the executable.
    pub exe: PathBuf,
    /// The package's directory (the working directory cargo gives it).
    pub dir: PathBuf,
}

/// The test executables in cargo's JSON messages (one per line).
pub fn parse_artifacts(json_lines: &str) -> Vec<TestBin> {
    json_lines
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v["reason"] == "compiler-artifact" && v["profile"]["test"] == true)
        .filter_map(|v| {
            let exe = PathBuf::from(v["executable"].as_str()?);
            let manifest = PathBuf::from(v["manifest_path"].as_str()?);
            let src = PathBuf::from(v["target"]["src_path"].as_str()?);
            let dir = manifest.parent()?.to_path_buf();
            let rel = src.strip_prefix(&dir).unwrap_or(&src).display().to_string();
            let kind = v["target"]["kind"][0].as_str().unwrap_or("");
            let label = if kind == "test" {
                rel
            } else {
                format!("unittests {rel}")
            };
            let package = v["package_id"]
                .as_str()
                .and_then(package_name)
                .unwrap_or_default();
            Some(TestBin {
                package,
                label,
                exe,
                dir,
            })
        })
        .collect()
}

/// `perpend-diagnosis` from a package id: `path+file:///…/dir#name@0.1.0` (the
/// name after `#` when the directory differs), `…/perpend-diagnosis#0.1.0`, or
/// the older `perpend-diagnosis 0.1.0 (path+file://…)`.
fn package_name(id: &str) -> Option<String> {
    if let Some((path, frag)) = id.rsplit_once('#') {
        if let Some((name, _)) = frag.split_once('@') {
            return Some(name.to_string());
        }
        return path.rsplit('/').next().map(str::to_string);
    }
    id.split_whitespace().next().map(str::to_string)
}

/// The order binaries start in: perpend-diagnosis's and perpend-calib's first
/// (long, CPU-bound), then the others as cargo listed them.
pub fn schedule(mut bins: Vec<TestBin>) -> VecDeque<TestBin> {
    bins.sort_by_key(|b| !matches!(b.package.as_str(), "perpend-diagnosis" | "perpend-calib"));
    bins.into()
}

/// What one binary printed and whether it passed.
struct Outcome {
    label: String,
    text: String,
    ok: bool,
}

fn run_one(b: &TestBin) -> Outcome {
    let out = Command::new(&b.exe)
        .current_dir(&b.dir)
        .env("CARGO_MANIFEST_DIR", &b.dir)
        .env("CARGO_PKG_NAME", &b.package)
        .env("PERPEND_BIN", crate::cell::perpend())
        .stdin(Stdio::null())
        .output();
    let label = format!("{} ({})", b.label, b.package);
    match out {
        Ok(o) => Outcome {
            label: label.clone(),
            text: format!(
                "     Running {label} ({})\n{}{}",
                b.exe.display(),
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            ),
            ok: o.status.success(),
        },
        Err(e) => Outcome {
            label: label.clone(),
            text: format!(
                "     Running {label}: cannot start {}: {e}\n",
                b.exe.display()
            ),
            ok: false,
        },
    }
}

/// Runs `queue` on `jobs` threads; prints each binary's output as it ends.
/// Returns the labels of the binaries that failed, in the order they ended.
fn run_queue(queue: VecDeque<TestBin>, jobs: usize) -> Vec<String> {
    let queue = Mutex::new(queue);
    let failed = Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..jobs.max(1) {
            s.spawn(|| loop {
                let next = queue.lock().map(|mut q| q.pop_front()).unwrap_or(None);
                let Some(b) = next else { break };
                let o = run_one(&b);
                print!("{}", o.text);
                if !o.ok {
                    if let Ok(mut f) = failed.lock() {
                        f.push(o.label);
                    }
                }
            });
        }
    });
    failed.into_inner().unwrap_or_default()
}

/// `cargo xtask test [--jobs N]`.
pub fn test(args: &[String]) -> Result<()> {
    let mut jobs = std::thread::available_parallelism().map_or(2, |n| n.get());
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--jobs" => {
                jobs = it
                    .next()
                    .and_then(|s| s.parse().ok())
                    .filter(|&n| n > 0)
                    .ok_or("--jobs needs a whole number ≥ 1")?;
            }
            _ => return Err(format!("test: unknown option {a} (known: --jobs N)")),
        }
    }
    let c = cargo();
    let out = Command::new(&c)
        .args([
            "test",
            "--no-run",
            "--message-format=json-render-diagnostics",
        ])
        .current_dir(root())
        .stderr(Stdio::inherit())
        .output()
        .map_err(|e| format!("cannot start cargo: {e}"))?;
    if !out.status.success() {
        return Err("the tests did not build (cargo's errors above)".into());
    }
    let bins = parse_artifacts(&String::from_utf8_lossy(&out.stdout));
    if bins.is_empty() {
        return Err("cargo built no test binary (nothing to run)".into());
    }
    eprintln!("test: {} binaries, {jobs} at a time", bins.len());
    let mut failed = run_queue(schedule(bins), jobs);
    let doc = Command::new(&c)
        .args(["test", "--doc"])
        .current_dir(root())
        .status()
        .map_err(|e| format!("cannot start cargo: {e}"))?;
    if !doc.success() {
        failed.push("doctests".into());
    }
    if failed.is_empty() {
        return Ok(());
    }
    Err(format!(
        "failed: {} (their output above)",
        failed.join(", ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn test_binaries_are_found_in_cargo_messages() {
        let lines = r#"{"reason":"compiler-artifact","package_id":"path+file:///w/crates/perpend-diagnosis#0.1.0","manifest_path":"/w/crates/perpend-diagnosis/Cargo.toml","target":{"kind":["test"],"name":"study_doc","src_path":"/w/crates/perpend-diagnosis/tests/study_doc.rs"},"profile":{"test":true},"executable":"/w/target/debug/deps/study_doc-1"}
{"reason":"compiler-artifact","package_id":"path+file:///w/crates/perpend-cli#perpend-cli@0.1.0","manifest_path":"/w/crates/perpend-cli/Cargo.toml","target":{"kind":["lib"],"name":"perpend_cli","src_path":"/w/crates/perpend-cli/src/lib.rs"},"profile":{"test":true},"executable":"/w/target/debug/deps/perpend_cli-2"}
{"reason":"compiler-artifact","package_id":"registry+https://github.com/rust-lang/crates.io-index#serde@1.0.0","manifest_path":"/r/serde/Cargo.toml","target":{"kind":["lib"],"name":"serde","src_path":"/r/serde/src/lib.rs"},"profile":{"test":false},"executable":null}
{"reason":"build-finished","success":true}
not json"#;
        let bins = parse_artifacts(lines);
        assert_eq!(bins.len(), 2);
        assert_eq!(bins[0].label, "tests/study_doc.rs");
        assert_eq!(bins[0].package, "perpend-diagnosis");
        assert_eq!(bins[0].dir, PathBuf::from("/w/crates/perpend-diagnosis"));
        assert_eq!(bins[1].label, "unittests src/lib.rs");
        assert_eq!(bins[1].package, "perpend-cli");
        assert_eq!(
            package_name("path+file:///w/host-tests#perpend-host-tests@0.1.0").as_deref(),
            Some("perpend-host-tests")
        );
        assert_eq!(
            package_name("serde 1.0.0 (registry+https://x)").as_deref(),
            Some("serde")
        );
        let q = schedule(vec![bins[1].clone(), bins[0].clone()]);
        assert_eq!(
            q[0].package, "perpend-diagnosis",
            "perpend-diagnosis starts first"
        );
    }

    #[test]
    fn a_failing_binary_is_named_and_the_others_still_run() {
        let sh = |script: &str| TestBin {
            package: "p".into(),
            label: script.into(),
            exe: PathBuf::from("/bin/sh"),
            dir: std::env::temp_dir(),
        };
        // /bin/sh without arguments reads stdin (null): exits 0.
        let ok = sh("ok");
        let missing = TestBin {
            exe: PathBuf::from("/nonexistent/test-binary"),
            ..sh("missing")
        };
        let failed = run_queue(vec![missing, ok.clone(), ok].into(), 2);
        assert_eq!(failed, vec!["missing (p)".to_string()]);
    }
}
