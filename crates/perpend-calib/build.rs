//! Build script of perpend-calib: records the git commit the tool was built
//! from (`PERPEND_GIT_HASH`, `git rev-parse --short HEAD`, with `-dirty`
//! when tracked files differ from that commit) for the calibration
//! record's `tool_version` ([`crate::record`]). Without git or outside a
//! checkout the hash is "unknown"; the build never fails for it.
//!
//! Limits: the marker is the checkout's state when this script last ran:
//! it runs again when HEAD moves, when the index changes (`git add`,
//! commit, checkout, stash) and when perpend-calib's own sources change
//! (which rebuild it anyway). An edit elsewhere that is neither staged
//! nor rebuilds perpend-calib leaves the marker as it was (watching every
//! file would rebuild the library at each edit). CI and release builds
//! start from a clean clone, where it is exact.

use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok()?;
    if !out.status.success() {
        return None;
    }
    Some(String::from_utf8(out.stdout).ok()?.trim().to_string())
}

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=src");
    // Rebuild when the checkout moves to another commit (HEAD switches
    // branch; logs/HEAD grows with every commit, checkout and reset) or
    // the index changes.
    for p in ["HEAD", "logs/HEAD", "index"] {
        if let Some(path) = git(&["rev-parse", "--git-path", p]).filter(|s| !s.is_empty()) {
            println!("cargo:rerun-if-changed={path}");
        }
    }
    let hash = git(&["rev-parse", "--short", "HEAD"])
        .filter(|s| !s.is_empty())
        .map_or_else(
            || "unknown".to_string(),
            |h| match git(&["status", "--porcelain", "--untracked-files=no"]) {
                Some(s) if s.is_empty() => h,
                Some(_) => format!("{h}-dirty"),
                None => format!("{h}-unknown-state"),
            },
        );
    println!("cargo:rustc-env=PERPEND_GIT_HASH={hash}");
}
