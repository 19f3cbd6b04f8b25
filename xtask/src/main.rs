//! `cargo xtask ...`: project automation that needs no tool beyond cargo.
//!
//! * `ci` — everything CI checks, in order (the README's test command).
//! * `demo` — build and run `perpend demo`.
//!
//! Each step prints a banner and stops the run at the first failure.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};

type Result<T> = std::result::Result<T, String>;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

fn cargo() -> String {
    std::env::var("CARGO").unwrap_or_else(|_| "cargo".to_string())
}

/// Runs a command in the repository root, echoing it; fails on non-zero exit.
fn run(program: &str, args: &[&str]) -> Result<()> {
    eprintln!("\n==> {program} {}", args.join(" "));
    let status = Command::new(program)
        .args(args)
        .current_dir(root())
        .status()
        .map_err(|e| format!("cannot start {program}: {e}"))?;
    if status.success() {
        Ok(())
    } else {
        Err(format!("`{program} {}` failed ({status})", args.join(" ")))
    }
}

fn have(program: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {program} >/dev/null 2>&1")])
        .status()
        .map(|s| s.success())
        .unwrap_or(false)
}

/// Installs Debian packages that are missing (CI and developer machines are
/// Debian and we are root there; elsewhere say what to install).
pub fn ensure_debian_packages(pkgs: &[(&str, &str)]) -> Result<()> {
    let missing: Vec<&str> = pkgs
        .iter()
        .filter(|(bin, _)| !have(bin))
        .map(|(_, pkg)| *pkg)
        .collect();
    if missing.is_empty() {
        return Ok(());
    }
    if !have("apt-get") {
        return Err(format!("please install: {}", missing.join(" ")));
    }
    run("apt-get", &["update", "-qq"])?;
    let mut args = vec!["install", "-y", "-qq", "--no-install-recommends"];
    args.extend(missing.iter().copied());
    run("apt-get", &args)
}

fn ci() -> Result<()> {
    let c = cargo();
    run(&c, &["fmt", "--all", "--", "--check"])?;
    run(&c, &["clippy", "--all-targets", "--", "-D", "warnings"])?;
    run(&c, &["test"])?;
    run(
        &c,
        &[
            "build",
            "-p",
            "perpend-core",
            "-p",
            "perpend-can",
            "-p",
            "perpend-board",
            "--target",
            "thumbv7em-none-eabihf",
        ],
    )?;
    eprintln!("\nci: all steps passed");
    Ok(())
}

fn demo() -> Result<()> {
    let c = cargo();
    run(&c, &["run", "--quiet", "-p", "perpend-cli", "--", "demo"])
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let res = match args.first().map(String::as_str) {
        Some("ci") => ci(),
        Some("demo") => demo(),
        _ => Err("usage: cargo xtask <ci|demo>".to_string()),
    };
    match res {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("xtask: {e}");
            ExitCode::FAILURE
        }
    }
}
