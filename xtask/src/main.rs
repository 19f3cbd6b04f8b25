//! `cargo xtask ...`: project automation that needs no tool beyond cargo.
//!
//! * `ci [--no-fuzz] [--verbose]` — everything CI checks, in order (the
//!   README's test command), after the prerequisite checks of `setup`.
//! * `test [--jobs N]` — the host tests (`cargo test`), N test binaries
//!   at a time (see `testrun.rs`); CI's "host tests" step.
//! * `setup [--no-fuzz]` — check and install the prerequisites only.
//! * `demo` — build and run `perpend demo`.
//! * `cell-demo` — the cell calibration end to end against a virtual
//!   board whose true head has the paper's errors (`perpend cell run`).
//! * `bring-up --bus BUS --node-id N | --virtual` — the bus side of
//!   docs/bring-up.md against a board or a virtual board.
//! * `fw [--test-key] [--sign KEY [--allow-downgrade]]` — build the release firmware and
//!   bootloader images (and the signed field-update image); the bootloader needs
//!   `PERPEND_PUBLIC_KEY` or an explicit `--test-key` (a TEST build); `keygen OUT` — a new ed25519 key pair; `size` — its flash and static
//!   RAM use against the budget (220 KiB ACTIVE / 48 KiB), and the
//!   bootloader's (32 KiB); `mcu-bench [--json]` —
//!   instructions per update on an emulated Cortex-M4F (QEMU mps2-an386).
//! * `hil [--qemu]` — the on-target tests: with a probe, on the board
//!   (`probe-rs run`; exit 2 = no probe found, 3 = probe-rs not installed);
//!   `--qemu`, the board's logic on QEMU mps2-an386 (see `hil.rs`).
//! * `provision [--test-key] [--allow-rom-loader] [--rdp1] [--dry-run]` — a
//!   new board with probe-rs: option bytes (DBANK = 1, BFB2 = 0), both
//!   images flashed and verified, bootloader write protection, RDP level 1
//!   only with `--rdp1` (`provision.rs`; exit 2 / 3 without a probe).
//! * `fuzz [--seconds N] [TARGET...]` — run the cargo-fuzz targets of
//!   `fuzz/` (nightly toolchain; installs `cargo-fuzz` if missing) for N
//!   seconds each and print executions and coverage per target.
//!
//! Each step prints a banner and stops the run at the first failure.

mod bringup;
mod cell;
mod ci;
mod fw;
mod hil;
mod provision;
mod setup;
mod sign;
mod testrun;

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

/// Installs Debian packages that are missing, never removing another
/// package (see [`setup::apt_install`]); `pkgs` pairs a program with the
/// package that provides it.
pub fn ensure_debian_packages(pkgs: &[(&str, &str)]) -> Result<()> {
    let missing: Vec<&str> = pkgs
        .iter()
        .filter(|(bin, _)| !setup::have(bin))
        .map(|(_, pkg)| *pkg)
        .collect();
    if missing.is_empty() {
        return Ok(());
    }
    setup::apt_install(&missing)
}

/// The fuzz targets of `fuzz/fuzz_targets/`, one per parser or protocol
/// handler.
const FUZZ_TARGETS: &[&str] = &[
    "exchange_csv",
    "param_json",
    "stored_params",
    "can_device",
    "slcan_line",
    "host_inputs",
    "eds",
];

/// The reader targets, which start from the corpus of bad files of
/// `host-tests/corpus/readers/` (each a case with the message it must give,
/// `crates/perpend-formats/tests/corpus_readers.rs`).
const READER_TARGETS: &[&str] = &["exchange_csv", "param_json", "host_inputs"];

/// The corpus directories of target `t`: its own (`fuzz/corpus/<t>`, where
/// libFuzzer writes what it finds; created if absent), then, for a reader,
/// the seed files of `host-tests/corpus/readers/` (read only).
fn corpus_dirs(t: &str) -> Result<Vec<PathBuf>> {
    let own = root().join("fuzz").join("corpus").join(t);
    std::fs::create_dir_all(&own).map_err(|e| format!("cannot create {}: {e}", own.display()))?;
    let mut dirs = vec![own];
    if READER_TARGETS.contains(&t) {
        dirs.push(root().join("host-tests").join("corpus").join("readers"));
    }
    Ok(dirs)
}

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
    setup::nightly()?;
    if !setup::have("cargo-fuzz") {
        run(
            &cargo(),
            &["install", "cargo-fuzz", "--locked", "--version", "0.13.2"],
        )?;
    }
    // cargo-fuzz needs nightly; `rustup run` overrides the pinned stable
    // toolchain for this command only. No sanitizer (`-s none`): the
    // targets are safe Rust (the one `unsafe` of the workspace, the M4F's
    // VSQRT, is not built on the host), so what the smoke can find is a
    // panic, an overflow or a hang, which libFuzzer reports without ASan;
    // instrumenting every dependency for ASan doubled the step's build.
    run(
        "rustup",
        &[
            "run",
            "nightly",
            "cargo",
            "fuzz",
            "build",
            "--sanitizer",
            "none",
            "--fuzz-dir",
            "fuzz",
        ],
    )?;
    // Two targets at a time: each libFuzzer run is one process on one core.
    let mut summary = Vec::new();
    for pair in targets.chunks(2) {
        let done: Vec<Result<String>> = std::thread::scope(|s| {
            let runs: Vec<_> = pair
                .iter()
                .map(|t| s.spawn(move || fuzz_one(t, seconds)))
                .collect();
            runs.into_iter()
                .map(|h| {
                    h.join()
                        .unwrap_or_else(|_| Err("a fuzz thread panicked".into()))
                })
                .collect()
        });
        for d in done {
            summary.push(d?);
        }
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

/// One fuzz target for `seconds`: its summary line, or why it failed.
fn fuzz_one(t: &str, seconds: u64) -> Result<String> {
    let max = format!("-max_total_time={seconds}");
    eprintln!("==> fuzz {t} for {seconds} s");
    let dirs = corpus_dirs(t)?;
    let out = Command::new("rustup")
        .args([
            "run",
            "nightly",
            "cargo",
            "fuzz",
            "run",
            "--sanitizer",
            "none",
            "--fuzz-dir",
            "fuzz",
            t,
        ])
        .args(&dirs)
        .args(["--", &max])
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
        let crashed = log.contains("==ERROR: libFuzzer") || log.contains("deadly signal");
        return Err(if crashed {
            format!("fuzz target {t} found a crash (artifact under fuzz/artifacts/{t}/)")
        } else {
            format!("fuzz target {t} did not run (build or start failed, see above)")
        });
    }
    Ok(format!("{t:>14}: {done}, coverage {cov} edges, 0 crashes"))
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let res = match args.first().map(String::as_str) {
        Some("ci") => ci::ci(&args[1..]),
        Some("test") => testrun::test(&args[1..]),
        Some("setup") => ci::setup_only(&args[1..]),
        Some("demo") => demo(),
        Some("cell-demo") => cell::cell_demo(),
        Some("bring-up") => bringup::bring_up(&args[1..]),
        Some("fuzz") => fuzz(&args[1..]),
        Some("fw") => fw::fw(&args[1..]),
        Some("keygen") => sign::keygen(&args[1..]),
        Some("size") => fw::size(&args[1..]),
        Some("mcu-bench") => fw::mcu_bench(&args[1..]),
        Some("hil") => hil::hil(&args[1..]),
        Some("provision") => provision::provision(&args[1..]),
        _ => Err("usage: cargo xtask <ci [--no-fuzz] [--verbose]|test [--jobs N]|setup [--no-fuzz]|demo|cell-demo|bring-up (--bus BUS --node-id N | --virtual)|fw [--test-key] [--provision-rom-loader] [--sign KEY [--allow-downgrade]]|keygen OUT|size [--test-key] [--no-build]|provision [--test-key] [--allow-rom-loader] [--rdp1] [--dry-run]|mcu-bench [--json]|hil [--qemu]|fuzz [--seconds N] [TARGET...]>".to_string()),
    };
    match res {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("xtask: {e}");
            ExitCode::FAILURE
        }
    }
}
