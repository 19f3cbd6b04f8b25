//! Build script of perpend-lab: records the git commit the tool was built
//! from (`PERPEND_GIT_HASH`, `git rev-parse --short HEAD`) for the
//! calibration record's `tool_version` ([`crate::record`]). Without git or
//! outside a checkout the hash is "unknown"; the build never fails for it.

use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok()?;
    if !out.status.success() {
        return None;
    }
    let s = String::from_utf8(out.stdout).ok()?.trim().to_string();
    (!s.is_empty()).then_some(s)
}

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    // Rebuild when the checkout moves to another commit (HEAD switches
    // branch; logs/HEAD grows with every commit, checkout and reset).
    for p in ["HEAD", "logs/HEAD"] {
        if let Some(path) = git(&["rev-parse", "--git-path", p]) {
            println!("cargo:rerun-if-changed={path}");
        }
    }
    let hash = git(&["rev-parse", "--short", "HEAD"]).unwrap_or_else(|| "unknown".into());
    println!("cargo:rustc-env=PERPEND_GIT_HASH={hash}");
}
