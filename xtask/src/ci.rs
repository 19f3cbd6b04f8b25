//! `cargo xtask ci [--no-fuzz] [--verbose]`: everything CI checks, in order.
//!
//! Prerequisites are checked first ([`crate::setup`]), so a machine that
//! lacks one stops in the first minute with a sentence saying what to do.
//! Each step then runs with its output in `target/ci-logs/NN-step.log` and
//! prints one line (with its figures); a failing step prints its cause
//! first, then the end of its log. `--verbose` streams every step's output.
//! The last line is `ci: N passed, M failed` over the Rust and Python tests;
//! a run reduced with `--no-fuzz` says so in a further last line.
//!
//! The peer tests wait on the virtual board far more than they compute
//! (≈ 25 s of CPU in 160 s), so they run alongside the firmware steps
//! (no_std build … mcu-bench), which run at a lower priority (`nice`) so
//! that the board under test answers as promptly as when alone; the peer
//! step is reported in its place, with the time since it started.

use std::fs;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Instant;

use super::{cargo, root, setup, Result};

/// What one step reports when it passes.
struct Done {
    /// Tests passed and failed (for the closing line).
    counts: (u64, u64),
    /// One line of figures, or empty.
    figures: String,
}

struct Runner {
    logs: PathBuf,
    verbose: bool,
    n: usize,
    total: usize,
    passed: u64,
    failed: u64,
}

impl Runner {
    /// Runs `cmd` as step `name`; `summarise` turns its output into figures.
    fn step(
        &mut self,
        name: &str,
        cmd: &mut Command,
        summarise: impl Fn(&str) -> Done,
    ) -> Result<()> {
        self.n += 1;
        let log = self
            .logs
            .join(format!("{:02}-{}.log", self.n, name.replace(' ', "-")));
        let t = Instant::now();
        cmd.current_dir(root()).stdin(Stdio::null());
        let text = if self.verbose {
            eprintln!("\n==> [{}/{}] {name}: {cmd:?}", self.n, self.total);
            let st = cmd.status().map_err(|e| format!("{name}: {e}"))?;
            if !st.success() {
                return Err(format!("step {name} failed ({st})"));
            }
            String::new()
        } else {
            let out = cmd
                .output()
                .map_err(|e| format!("{name}: cannot start: {e}"))?;
            let mut text = String::from_utf8_lossy(&out.stdout).into_owned();
            text.push_str(&String::from_utf8_lossy(&out.stderr));
            let _ = fs::write(&log, &text);
            if !out.status.success() {
                return Err(format!(
                    "step {name} failed ({}); cause:\n{}\n(full log: {})",
                    out.status,
                    cause(&text),
                    log.display()
                ));
            }
            text
        };
        let d = summarise(&text);
        self.report(name, t, &d);
        Ok(())
    }

    fn report(&mut self, name: &str, t: Instant, d: &Done) {
        self.passed += d.counts.0;
        self.failed += d.counts.1;
        eprintln!(
            "[{}/{}] {name:<22} ok  {:>5.0} s  {}",
            self.n,
            self.total,
            t.elapsed().as_secs_f64(),
            d.figures
        );
    }

    /// Starts `cmd` as a step that runs while the next steps do; its output
    /// goes to its log only. [`Runner::join`] reports it.
    fn start(&self, name: &str, cmd: &mut Command) -> Result<Background> {
        let log = self.logs.join(format!("bg-{}.log", name.replace(' ', "-")));
        let file = fs::File::create(&log).map_err(|e| format!("{}: {e}", log.display()))?;
        let err = file
            .try_clone()
            .map_err(|e| format!("{}: {e}", log.display()))?;
        let child = cmd
            .current_dir(root())
            .stdin(Stdio::null())
            .stdout(file)
            .stderr(err)
            .spawn()
            .map_err(|e| format!("{name}: cannot start: {e}"))?;
        Ok(Background {
            name: name.to_string(),
            child,
            log,
            started: Instant::now(),
        })
    }

    /// Waits for a step started with [`Runner::start`] and reports it as
    /// the next step.
    fn join(&mut self, mut bg: Background, summarise: impl Fn(&str) -> Done) -> Result<()> {
        self.n += 1;
        let name = bg.name.clone();
        let st = bg
            .child
            .wait()
            .map_err(|e| format!("{name}: cannot wait: {e}"))?;
        let text = fs::read_to_string(&bg.log).unwrap_or_default();
        if self.verbose {
            eprintln!(
                "\n==> [{}/{}] {name} (ran alongside):\n{text}",
                self.n, self.total
            );
        }
        if !st.success() {
            return Err(format!(
                "step {name} failed ({st}); cause:\n{}\n(full log: {})",
                cause(&text),
                bg.log.display()
            ));
        }
        let d = summarise(&text);
        self.report(&name, bg.started, &d);
        Ok(())
    }
}

/// A step running alongside others; killed if CI stops before it is joined.
struct Background {
    name: String,
    child: Child,
    log: PathBuf,
    started: Instant,
}

impl Drop for Background {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// `cmd` at a lower CPU priority (`nice -n 10`) where `nice` exists, so a
/// step running alongside keeps its response times.
fn niced(cmd: Command) -> Command {
    if !cfg!(unix) || !super::setup::have("nice") {
        return cmd;
    }
    let mut n = Command::new("nice");
    n.args(["-n", "10"])
        .arg(cmd.get_program())
        .args(cmd.get_args());
    n
}

/// The lines of a failed step's log that say why: compiler errors, failed
/// tests and panics first, then the last lines.
fn cause(text: &str) -> String {
    let key: Vec<&str> = text
        .lines()
        .filter(|l| {
            l.starts_with("error")
                || l.contains("panicked at")
                || l.contains("FAILED")
                || l.starts_with("E ")
                || l.contains("Diff in")
        })
        .take(20)
        .collect();
    let tail: Vec<&str> = text.lines().rev().take(30).collect();
    let mut s = key.join("\n");
    s.push_str("\n--- end of log ---\n");
    s.push_str(&tail.into_iter().rev().collect::<Vec<_>>().join("\n"));
    s
}

fn nothing(_: &str) -> Done {
    Done {
        counts: (0, 0),
        figures: String::new(),
    }
}

/// Sums cargo's `test result: ok. N passed; M failed` lines.
pub fn cargo_counts(text: &str) -> (u64, u64) {
    let num = |l: &str, word: &str| -> u64 {
        l.split([';', '.'])
            .find_map(|p| p.trim().strip_suffix(word))
            .and_then(|n| n.trim().parse().ok())
            .unwrap_or(0)
    };
    text.lines()
        .filter(|l| l.starts_with("test result:"))
        .fold((0, 0), |(p, f), l| {
            (p + num(l, "passed"), f + num(l, "failed"))
        })
}

/// pytest's closing `N passed[, M failed] in T s`.
pub fn pytest_counts(text: &str) -> (u64, u64) {
    let Some(line) = text
        .lines()
        .rev()
        .find(|l| l.contains(" passed") || l.contains(" failed"))
    else {
        return (0, 0);
    };
    let words: Vec<&str> = line
        .split(|c: char| c.is_whitespace() || c == ',' || c == '=')
        .filter(|w| !w.is_empty())
        .collect();
    let num = |word: &str| -> u64 {
        words
            .windows(2)
            .find(|w| w[1] == word)
            .and_then(|w| w[0].parse().ok())
            .unwrap_or(0)
    };
    (num("passed"), num("failed"))
}

fn tests_done(text: &str) -> Done {
    let (p, f) = cargo_counts(text);
    Done {
        counts: (p, f),
        figures: format!("{p} passed, {f} failed"),
    }
}

fn line_starting(prefix: &'static str) -> impl Fn(&str) -> Done {
    move |text: &str| Done {
        counts: (0, 0),
        figures: text
            .lines()
            .find(|l| l.trim_start().starts_with(prefix))
            .unwrap_or("")
            .trim()
            .to_string(),
    }
}

fn xtask(args: &[&str]) -> Command {
    let exe = std::env::current_exe().unwrap_or_else(|_| PathBuf::from("xtask"));
    let mut c = Command::new(exe);
    c.args(args);
    c
}

fn cmd(program: &str, args: &[&str]) -> Command {
    let mut c = Command::new(program);
    c.args(args);
    c
}

/// Runs the CI.
pub fn ci(args: &[String]) -> Result<()> {
    let no_fuzz = args.iter().any(|a| a == "--no-fuzz");
    let verbose = args.iter().any(|a| a == "--verbose");
    if let Some(a) = args.iter().find(|a| *a != "--no-fuzz" && *a != "--verbose") {
        return Err(format!(
            "ci: unknown option {a} (known: --no-fuzz, --verbose)"
        ));
    }
    preflight(no_fuzz)?;
    let logs = root().join("target").join("ci-logs");
    fs::create_dir_all(&logs).map_err(|e| format!("{}: {e}", logs.display()))?;
    let mut r = Runner {
        logs,
        verbose,
        n: 0,
        total: if no_fuzz { 11 } else { 12 },
        passed: 0,
        failed: 0,
    };
    let c = cargo();
    let thumb = "thumbv7em-none-eabihf";
    r.step(
        "fmt",
        &mut cmd(&c, &["fmt", "--all", "--", "--check"]),
        nothing,
    )?;
    r.step(
        "clippy",
        &mut cmd(&c, &["clippy", "--all-targets", "--", "-D", "warnings"]),
        nothing,
    )?;
    r.step("host tests", &mut xtask(&["test"]), tests_done)?;
    // The `perpend` binary is built now: the peer tests run alongside the
    // firmware steps (see the module header).
    // Both scripts take the binary the test build made (`PERPEND_BIN`): a
    // `cargo build -p perpend-cli` of their own resolves features without
    // the dev-dependencies and would build it all again.
    let peer = r.start(
        "peer tests (python)",
        cmd("bash", &["host-tests/peer/run.sh"]).env("PERPEND_BIN", crate::cell::perpend()),
    )?;
    // no_std, no alloc: the pure crates compile for the board's target
    // with their default features (`check`: the release images of the
    // next steps link them with the firmware's).
    let nostd = [
        "check",
        "-p",
        "perpend-core",
        "-p",
        "perpend-can",
        "-p",
        "perpend-board",
        "--target",
        thumb,
    ];
    r.step("no_std check", &mut niced(cmd(&c, &nostd)), nothing)?;
    // The firmware and the on-target tests (hil/, which includes its
    // modules).
    let fw_clippy = [
        "clippy",
        "-p",
        "perpend-fw",
        "-p",
        "perpend-hil",
        "-p",
        "perpend-boot",
        // a TEST bootloader, said so: the release key is not in CI
        "--features",
        "perpend-boot/test-key",
        "--all-targets",
        "--target",
        thumb,
        "--",
        "-D",
        "warnings",
    ];
    r.step("firmware clippy", &mut niced(cmd(&c, &fw_clippy)), nothing)?;
    r.step(
        "firmware size",
        &mut niced(xtask(&["size", "--test-key"])),
        line_starting("perpend-fw:"),
    )?;
    // Builds and links the on-target test binary (release, as `size`), then
    // runs the board's logic as compiled for the board on QEMU.
    r.step(
        "hil build + QEMU tests",
        &mut niced(xtask(&["hil", "--qemu"])),
        line_starting("target tests:"),
    )?;
    r.step(
        "mcu-bench (QEMU)",
        &mut niced(xtask(&["mcu-bench", "--json"])),
        line_starting("{"),
    )?;
    r.join(peer, |t| {
        let (p, f) = pytest_counts(t);
        Done {
            counts: (p, f),
            figures: format!("{p} passed, {f} failed"),
        }
    })?;
    r.step(
        "blind diagnosis",
        cmd("bash", &["host-tests/blind/run.sh"]).env("PERPEND_BIN", crate::cell::perpend()),
        line_starting("blind:"),
    )?;
    // Issue 35's cases (v3.py), six nulls a regime and two runs a case
    // and size, goals pooled: ≈ 80 s on two cores.
    r.step(
        "blind v3 (quick)",
        cmd(
            "bash",
            &["host-tests/blind/run.sh", "--v3", "--quick", "--check"],
        )
        .env("PERPEND_BIN", crate::cell::perpend()),
        line_starting("blind v3:"),
    )?;
    if !no_fuzz {
        let secs = std::env::var("PERPEND_FUZZ_SECONDS").unwrap_or_else(|_| "10".to_string());
        r.step(
            "fuzz smoke",
            &mut xtask(&["fuzz", "--seconds", &secs]),
            |t| Done {
                counts: (0, 0),
                figures: format!(
                    "{} targets × {secs} s, 0 crashes",
                    t.lines().filter(|l| l.contains("0 crashes")).count()
                ),
            },
        )?;
    }
    eprintln!("ci: all {} steps passed", r.total);
    println!("ci: {} passed, {} failed", r.passed, r.failed);
    if no_fuzz {
        println!("ci: REDUCED run (--no-fuzz): the fuzz smoke did not run");
    }
    Ok(())
}

/// One prerequisite check: what it found, or what is missing.
type Check = fn() -> Result<String>;

/// Every prerequisite, one line each, before any build starts.
fn preflight(no_fuzz: bool) -> Result<()> {
    let mut checks: Vec<(&str, Check)> = vec![
        ("toolchain", setup::toolchain),
        ("python", setup::python),
        ("qemu", setup::qemu),
        ("chromium", setup::chromium),
        ("flip-link", setup::flip_link),
    ];
    if !no_fuzz {
        checks.push(("nightly", setup::nightly));
    }
    let mut missing = Vec::new();
    for (name, check) in checks {
        match check() {
            Ok(what) => eprintln!("setup: {name:<9} ok  {what}"),
            Err(e) => {
                eprintln!("setup: {name:<9} MISSING: {e}");
                missing.push(name);
            }
        }
    }
    if missing.is_empty() {
        Ok(())
    } else {
        Err(format!(
            "prerequisites missing: {} (see the lines above); nothing was built",
            missing.join(", ")
        ))
    }
}

/// `cargo xtask setup`: the prerequisite checks alone.
pub fn setup_only(args: &[String]) -> Result<()> {
    preflight(args.iter().any(|a| a == "--no-fuzz"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_from_cargo_and_pytest() {
        let cargo = "test result: ok. 18 passed; 0 failed; 0 ignored\n\
                     noise\n\
                     test result: FAILED. 3 passed; 2 failed; 1 ignored\n";
        assert_eq!(cargo_counts(cargo), (21, 2));
        assert_eq!(pytest_counts("....\n12 passed in 21.30s\n"), (12, 0));
        assert_eq!(
            pytest_counts("==== 1 failed, 11 passed in 20.1s ====\n"),
            (11, 1)
        );
        assert_eq!(pytest_counts("nothing here\n"), (0, 0));
    }

    fn runner(dir: &std::path::Path) -> Runner {
        Runner {
            logs: dir.to_path_buf(),
            verbose: false,
            n: 0,
            total: 3,
            passed: 0,
            failed: 0,
        }
    }

    fn pytest_done(t: &str) -> Done {
        Done {
            counts: pytest_counts(t),
            figures: String::new(),
        }
    }

    /// A step started in the background runs while a foreground step does,
    /// and is counted when joined; a failing one fails CI with its cause.
    #[test]
    fn background_step_runs_alongside_and_is_joined() {
        let dir = std::env::temp_dir().join(format!("xtask-ci-bg-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let mut r = runner(&dir);
        let t = Instant::now();
        let bg = r
            .start(
                "bg",
                &mut cmd("sh", &["-c", "sleep 1; echo '4 passed in 1.0s'"]),
            )
            .unwrap();
        r.step("fg", &mut cmd("sh", &["-c", "sleep 1"]), nothing)
            .unwrap();
        r.join(bg, pytest_done).unwrap();
        assert_eq!((r.n, r.passed), (2, 4));
        assert!(t.elapsed().as_secs_f64() < 1.9, "{:?}", t.elapsed());
        let bad = r
            .start(
                "bad",
                &mut cmd("sh", &["-c", "echo 'E assert 1 == 2'; exit 1"]),
            )
            .unwrap();
        let e = r.join(bad, pytest_done).unwrap_err();
        assert!(
            e.contains("step bad failed") && e.contains("E assert 1 == 2"),
            "{e}"
        );
        let _ = fs::remove_dir_all(&dir);
    }
}
