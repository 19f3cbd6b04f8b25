//! `cargo xtask hil [--qemu]`: the board's tests on its own target (issue 33
//! items 3 and 4).
//!
//! * `hil` builds and links the on-target test binary (`hil/tests/board.rs`,
//!   embedded-test, release profile) and runs it with `probe-rs run --chip
//!   STM32G474RETx` when probe-rs is installed and `probe-rs list` shows a
//!   probe. Otherwise it says so and exits with its own status:
//!   [`EXIT_NO_PROBE`] (no probe attached) or [`EXIT_NO_PROBE_RS`]
//!   (probe-rs not installed); 0 = every test passed, 1 = a test or the
//!   build failed.
//! * `hil --qemu` builds and links the same binary (what CI checks every
//!   run), then builds `xtask/qemu-tests` (the board's logic in f32 with
//!   the firmware's release profile, no STM32 peripheral) and runs it on
//!   QEMU mps2-an386 with semihosting: one line per test, exit 1 when any
//!   fails.

use std::io::Read;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use super::{cargo, root, Result};

const TARGET: &str = "thumbv7em-none-eabihf";
/// The chip of the NUCLEO-G474RE for probe-rs.
const CHIP: &str = "STM32G474RETx";
/// Exit status of `cargo xtask hil` when no probe is attached.
pub const EXIT_NO_PROBE: i32 = 2;
/// Exit status of `cargo xtask hil` when probe-rs is not installed.
pub const EXIT_NO_PROBE_RS: i32 = 3;
/// Longest run of the QEMU tests before they count as hung.
const QEMU_LIMIT: Duration = Duration::from_secs(120);

/// Why `hil` did not run the tests (each has its own exit status).
#[derive(Debug, PartialEq, Eq)]
pub enum NotRun {
    /// `probe-rs` is not on the PATH.
    NoProbeRs,
    /// `probe-rs list` lists no probe.
    NoProbe,
}

impl NotRun {
    /// The line printed and the exit status.
    pub fn report(&self) -> (&'static str, i32) {
        match self {
            Self::NoProbeRs => (
                "hil: not run: probe-rs not installed: cargo install probe-rs-tools",
                EXIT_NO_PROBE_RS,
            ),
            Self::NoProbe => (
                "hil: not run: no probe found (connect the NUCLEO-G474RE's ST-LINK by USB; `probe-rs list` lists none)",
                EXIT_NO_PROBE,
            ),
        }
    }
}

/// Whether `probe-rs list` output shows at least one probe (its lines
/// `[0]: STLink V3 -- ...`).
pub fn lists_a_probe(out: &str) -> bool {
    out.lines()
        .any(|l| l.trim_start().starts_with('[') && l.contains("]:"))
}

/// Builds and links the on-target test binary; returns its path.
pub fn build_board_tests() -> Result<PathBuf> {
    eprintln!("\n==> cargo test -p perpend-hil --target {TARGET} --release --no-run");
    let out = Command::new(cargo())
        .current_dir(root())
        .args(["test", "-p", "perpend-hil", "--target", TARGET, "--release"])
        .args(["--no-run", "--message-format=json-render-diagnostics"])
        .stderr(Stdio::inherit())
        .output()
        .map_err(|e| format!("cannot start cargo: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "the HIL test binary did not build ({})",
            out.status
        ));
    }
    executable_of(&String::from_utf8_lossy(&out.stdout), "board")
        .ok_or_else(|| "cargo reported no executable for hil/tests/board.rs".to_string())
}

/// The executable of test target `name` in cargo's JSON messages.
pub fn executable_of(json_lines: &str, name: &str) -> Option<PathBuf> {
    json_lines
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v["reason"] == "compiler-artifact" && v["target"]["name"] == name)
        .find_map(|v| v["executable"].as_str().map(PathBuf::from))
}

/// Why no probe run is possible here, if so.
pub fn probe_missing() -> Option<NotRun> {
    let Ok(out) = Command::new("probe-rs").arg("list").output() else {
        return Some(NotRun::NoProbeRs);
    };
    let text = String::from_utf8_lossy(&out.stdout);
    (!lists_a_probe(&text)).then_some(NotRun::NoProbe)
}

/// `cargo xtask hil [--qemu]` (see the module docs).
pub fn hil(args: &[String]) -> Result<()> {
    let qemu = args.iter().any(|a| a == "--qemu");
    if let Some(a) = args.iter().find(|a| *a != "--qemu") {
        return Err(format!("hil: unknown option {a} (known: --qemu)"));
    }
    let elf = build_board_tests()?;
    eprintln!("hil: on-target test binary {}", elf.display());
    if qemu {
        return qemu_tests();
    }
    if let Some(why) = probe_missing() {
        let (line, status) = why.report();
        println!("{line}");
        std::process::exit(status);
    }
    super::run("probe-rs", &["run", "--chip", CHIP, &elf.to_string_lossy()])
}

/// Builds `xtask/qemu-tests` and runs it on QEMU mps2-an386.
fn qemu_tests() -> Result<()> {
    super::ensure_debian_packages(&[("qemu-system-arm", "qemu-system-arm")])?;
    let tdir = root().join("target").join("mcu-bench");
    eprintln!("\n==> cargo build --release (xtask/qemu-tests)");
    let st = Command::new(cargo())
        .current_dir(root().join("xtask").join("qemu-tests"))
        // Shares the dependencies built for mcu-bench (same profile).
        .env("CARGO_TARGET_DIR", &tdir)
        // Replaces the workspace's target rustflags (which link defmt).
        .env("RUSTFLAGS", "-C link-arg=-Tlink.x -C link-arg=--nmagic")
        .args(["build", "--release", "--target", TARGET])
        .status()
        .map_err(|e| format!("cannot start cargo: {e}"))?;
    if !st.success() {
        return Err(format!("xtask/qemu-tests did not build ({st})"));
    }
    let elf = tdir.join(TARGET).join("release").join("perpend-qemu-tests");
    let (ok, text) = run_qemu(&elf)?;
    print!("{text}");
    let failed = text.lines().filter(|l| l.contains("... FAILED")).count();
    let passed = text.lines().filter(|l| l.ends_with("... ok")).count();
    if ok && failed == 0 && passed > 0 {
        Ok(())
    } else {
        Err(format!(
            "QEMU target tests: {passed} passed, {failed} failed (exit {})",
            if ok { "0" } else { "non-zero" }
        ))
    }
}

/// Runs `elf` on mps2-an386 with semihosting; its success and output.
fn run_qemu(elf: &std::path::Path) -> Result<(bool, String)> {
    eprintln!(
        "\n==> qemu-system-arm -M mps2-an386 ... -kernel {}",
        elf.display()
    );
    let mut child = Command::new("qemu-system-arm")
        .args(["-M", "mps2-an386", "-nographic", "-semihosting-config"])
        .arg("enable=on,target=native")
        .arg("-kernel")
        .arg(elf)
        .stdout(Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot start qemu-system-arm: {e}"))?;
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().map_err(|e| format!("qemu: {e}"))? {
            break s;
        }
        if start.elapsed() > QEMU_LIMIT {
            let _ = child.kill();
            return Err(format!("QEMU target tests hung (over {QEMU_LIMIT:?})"));
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut text = String::new();
    if let Some(mut o) = child.stdout.take() {
        o.read_to_string(&mut text)
            .map_err(|e| format!("qemu output: {e}"))?;
    }
    Ok((status.success(), text))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn probe_list_parsing() {
        let none = "No debug probes were found.\n";
        let one =
            "The following debug probes were found:\n[0]: STLink V3 -- 0483:374e:0029 (ST-LINK)\n";
        assert!(!lists_a_probe(none));
        assert!(lists_a_probe(one));
        assert_eq!(NotRun::NoProbe.report().1, EXIT_NO_PROBE);
        assert_ne!(EXIT_NO_PROBE, EXIT_NO_PROBE_RS);
        assert!(NotRun::NoProbe
            .report()
            .0
            .contains("not run: no probe found"));
    }

    #[test]
    fn executable_from_cargo_json() {
        let j = r#"{"reason":"compiler-artifact","target":{"name":"perpend_hil"},"executable":null}
{"reason":"compiler-artifact","target":{"name":"board"},"executable":"/t/board-1"}"#;
        assert_eq!(executable_of(j, "board"), Some(PathBuf::from("/t/board-1")));
        assert_eq!(executable_of(j, "other"), None);
    }
}
