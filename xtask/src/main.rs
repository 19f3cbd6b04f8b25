//! `cargo xtask ...`: project automation that needs no tool beyond cargo.
//!
//! * `ci` — everything CI checks, in order (the README's test command).
//! * `demo` — build and run `perpend demo`.
//! * `fw` — build the release firmware image; `size` — its flash and static
//!   RAM use against the budget (128 KiB / 48 KiB); `mcu-bench [--json]` —
//!   instructions per update on an emulated Cortex-M4F (QEMU mps2-an386).
//! * `fuzz [--seconds N] [TARGET...]` — run the cargo-fuzz targets of
//!   `fuzz/` (nightly toolchain; installs `cargo-fuzz` if missing) for N
//!   seconds each and print executions and coverage per target.
//!
//! Each step prints a banner and stops the run at the first failure.

mod fw;

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
    // no_std, no alloc: the pure crates build for the board's target.
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
    // The firmware: lints, release image and its flash/RAM budget.
    run(
        &c,
        &[
            "clippy",
            "-p",
            "perpend-fw",
            "--target",
            "thumbv7em-none-eabihf",
            "--",
            "-D",
            "warnings",
        ],
    )?;
    fw::size(&[])?;
    // Instructions per update on an emulated Cortex-M4F.
    fw::mcu_bench(&["--json".to_string()])?;
    // Peer tests: python-canopen against the virtual board over slcan.
    run("bash", &["host-tests/peer/run.sh"])?;
    // Fuzz smoke: every parser and protocol handler, briefly. cargo-fuzz
    // needs a nightly toolchain: the machines have one; if one cannot be
    // had, say so loudly rather than fail every other check.
    let secs = std::env::var("PERPEND_FUZZ_SECONDS").unwrap_or_else(|_| "15".to_string());
    if have_nightly() {
        fuzz(&["--seconds".to_string(), secs])?;
    } else {
        eprintln!("\nWARNING: no nightly toolchain could be installed: fuzz smoke SKIPPED");
    }
    eprintln!("\nci: all steps passed");
    Ok(())
}

/// Whether a nightly toolchain is there, installing a minimal one if not.
fn have_nightly() -> bool {
    let ok = |args: &[&str]| {
        Command::new("rustup")
            .args(args)
            .current_dir(root())
            .status()
            .map(|s| s.success())
            .unwrap_or(false)
    };
    ok(&["run", "nightly", "rustc", "--version"])
        || (ok(&["toolchain", "install", "nightly", "--profile", "minimal"])
            && ok(&["run", "nightly", "rustc", "--version"]))
}

/// The fuzz targets of `fuzz/fuzz_targets/`, one per parser or protocol
/// handler.
const FUZZ_TARGETS: &[&str] = &[
    "exchange_csv",
    "param_json",
    "stored_params",
    "can_device",
    "slcan_line",
];

fn fuzz(args: &[String]) -> Result<()> {
    let mut seconds = 60u64;
    let mut targets: Vec<String> = Vec::new();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        if a == "--seconds" {
            seconds = it
                .next()
                .and_then(|s| s.parse().ok())
                .ok_or("--seconds needs a whole number")?;
        } else if FUZZ_TARGETS.contains(&a.as_str()) {
            targets.push(a.clone());
        } else {
            return Err(format!("unknown fuzz target {a}; known: {FUZZ_TARGETS:?}"));
        }
    }
    if targets.is_empty() {
        targets = FUZZ_TARGETS.iter().map(|s| s.to_string()).collect();
    }
    if !have("cargo-fuzz") {
        run(
            &cargo(),
            &["install", "cargo-fuzz", "--locked", "--version", "0.13.2"],
        )?;
    }
    // cargo-fuzz needs nightly (-Zsanitizer); `rustup run` overrides the
    // pinned stable toolchain for this command only.
    run(
        "rustup",
        &[
            "run",
            "nightly",
            "cargo",
            "fuzz",
            "build",
            "--fuzz-dir",
            "fuzz",
        ],
    )?;
    let mut summary = Vec::new();
    for t in &targets {
        let max = format!("-max_total_time={seconds}");
        eprintln!("\n==> fuzz {t} for {seconds} s");
        let out = Command::new("rustup")
            .args([
                "run",
                "nightly",
                "cargo",
                "fuzz",
                "run",
                "--fuzz-dir",
                "fuzz",
                t,
                "--",
                &max,
            ])
            .current_dir(root())
            .output()
            .map_err(|e| format!("cannot start cargo fuzz: {e}"))?;
        let log = String::from_utf8_lossy(&out.stderr);
        let done = log
            .lines()
            .rev()
            .find(|l| l.starts_with("Done "))
            .unwrap_or("")
            .to_string();
        let cov = log
            .lines()
            .rev()
            .find(|l| l.starts_with('#') && l.contains("cov:"))
            .and_then(|l| l.split_whitespace().skip_while(|w| *w != "cov:").nth(1))
            .unwrap_or("?")
            .to_string();
        if !out.status.success() {
            eprintln!("{log}");
            return Err(format!(
                "fuzz target {t} found a crash (artifact under fuzz/artifacts/{t}/)"
            ));
        }
        summary.push(format!("{t:>14}: {done}, coverage {cov} edges, 0 crashes"));
    }
    eprintln!("\nfuzz summary ({seconds} s per target):");
    for s in summary {
        eprintln!("  {s}");
    }
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
        Some("fuzz") => fuzz(&args[1..]),
        Some("fw") => fw::fw(&args[1..]),
        Some("size") => fw::size(&args[1..]),
        Some("mcu-bench") => fw::mcu_bench(&args[1..]),
        _ => Err("usage: cargo xtask <ci|demo|fw|size|mcu-bench [--json]|fuzz [--seconds N] [TARGET...]>".to_string()),
    };
    match res {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("xtask: {e}");
            ExitCode::FAILURE
        }
    }
}
