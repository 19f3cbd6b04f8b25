//! Prerequisites, checked before any work starts: `cargo xtask setup`, and
//! the first step of `cargo xtask ci`.
//!
//! * the Rust toolchain that `rust-toolchain.toml` names, with its
//!   components and targets (added idempotently: a machine where the
//!   pinned toolchain exists but the board's target does not is repaired
//!   here, not four minutes later at the no_std build);
//! * Python ≥ 3.9 with `venv` and `ensurepip` (the peer tests make their
//!   own virtual environment);
//! * `qemu-system-arm` (instruction counts on an emulated Cortex-M4F);
//! * `chromium` (headless: the calibration certificate as a browser
//!   renders it, `crates/perpend-cli/tests/cli/cell.rs`);
//! * `flip-link` (the firmware's linker, `.cargo/config.toml`), installed
//!   with `cargo install` at [`FLIP_LINK_VERSION`] when missing;
//! * a nightly toolchain (the fuzz smoke; skipped only with `--no-fuzz`).
//!
//! Debian packages are installed only when missing, only as root, and never
//! at the cost of another package: `apt-get install --no-remove`. When the
//! distribution's package would replace a newer one from backports (the
//! machines ship `qemu-utils` from bookworm-backports, which bookworm's
//! `qemu-system-arm` would remove), the same backports suite is offered to
//! apt for this one install, without touching the machine's sources.
//! Every check prints one line; a failing one says what is missing and how
//! to get it.

use std::path::PathBuf;
use std::process::{Command, Output};

use super::{root, Result};

/// Runs a command, capturing its output; `Err` carries the command line
/// and the last lines it printed.
pub fn quiet(cmd: &mut Command) -> Result<Output> {
    let out = cmd
        .output()
        .map_err(|e| format!("cannot start {:?}: {e}", cmd.get_program()))?;
    if out.status.success() {
        return Ok(out);
    }
    let mut text = String::from_utf8_lossy(&out.stderr).into_owned();
    text.push_str(&String::from_utf8_lossy(&out.stdout));
    let tail: Vec<&str> = text.lines().rev().take(12).collect();
    let tail: Vec<&str> = tail.into_iter().rev().collect();
    Err(format!(
        "{:?} failed ({}):\n    {}",
        cmd,
        out.status,
        tail.join("\n    ")
    ))
}

/// Whether `program` is on the PATH.
pub fn have(program: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {program} >/dev/null 2>&1")])
        .status()
        .map(|s| s.success())
        .unwrap_or(false)
}

/// The toolchain `rust-toolchain.toml` pins: channel, components, targets.
#[derive(Debug, PartialEq, Eq)]
pub struct Pinned {
    /// `channel = "..."`.
    pub channel: String,
    /// `components = [...]`.
    pub components: Vec<String>,
    /// `targets = [...]`.
    pub targets: Vec<String>,
}

/// Parses the `[toolchain]` table of `rust-toolchain.toml` (the three keys
/// this project uses; strings and string arrays on one line each).
pub fn parse_pinned(text: &str) -> Result<Pinned> {
    let value = |key: &str| -> Option<&str> {
        text.lines()
            .map(str::trim)
            .filter_map(|l| l.strip_prefix(key))
            .map(str::trim_start)
            .find_map(|l| l.strip_prefix('='))
            .map(str::trim)
    };
    let strings = |v: &str| -> Vec<String> {
        v.trim_matches(|c| c == '[' || c == ']')
            .split(',')
            .map(|s| s.trim().trim_matches('"').to_string())
            .filter(|s| !s.is_empty())
            .collect()
    };
    let channel = value("channel")
        .map(|v| v.trim_matches('"').to_string())
        .filter(|c| !c.is_empty())
        .ok_or("rust-toolchain.toml names no channel")?;
    Ok(Pinned {
        channel,
        components: value("components").map(strings).unwrap_or_default(),
        targets: value("targets").map(strings).unwrap_or_default(),
    })
}

/// Installs the pinned toolchain, its components and targets (idempotent).
pub fn toolchain() -> Result<String> {
    if !have("rustup") {
        return Err("rustup is missing: install it (https://rustup.rs), then run again".into());
    }
    let path = root().join("rust-toolchain.toml");
    let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let p = parse_pinned(&text)?;
    let rustup = |args: &[&str]| quiet(Command::new("rustup").args(args).current_dir(root()));
    rustup(&["toolchain", "install", &p.channel, "--profile", "minimal"])
        .map_err(|e| format!("cannot install Rust {}: {e}", p.channel))?;
    if !p.components.is_empty() {
        let mut a = vec!["component", "add", "--toolchain", &p.channel];
        a.extend(p.components.iter().map(String::as_str));
        rustup(&a).map_err(|e| format!("cannot add components to Rust {}: {e}", p.channel))?;
    }
    if !p.targets.is_empty() {
        let mut a = vec!["target", "add", "--toolchain", &p.channel];
        a.extend(p.targets.iter().map(String::as_str));
        rustup(&a).map_err(|e| format!("cannot add targets to Rust {}: {e}", p.channel))?;
    }
    let mut what = p.components.clone();
    what.extend(p.targets.iter().cloned());
    Ok(format!("Rust {} with {}", p.channel, what.join(", ")))
}

/// Python ≥ 3.9 with `venv` and `ensurepip`, installing `python3-venv`
/// from Debian when only that is missing.
pub fn python() -> Result<String> {
    let py = std::env::var("PYTHON").unwrap_or_else(|_| "python3".to_string());
    let probe = |py: &str| {
        quiet(Command::new(py).args([
            "-c",
            "import sys, venv, ensurepip; assert sys.version_info >= (3, 9), sys.version; print(sys.version.split()[0])",
        ]))
    };
    let out = match probe(&py) {
        Ok(o) => o,
        Err(_) if have(&py) && have("apt-get") => {
            apt_install(&["python3-venv"])?;
            probe(&py)
                .map_err(|e| format!("{py} lacks venv/ensurepip or is older than 3.9: {e}"))?
        }
        Err(e) => {
            return Err(format!(
                "need Python ≥ 3.9 with venv (Debian: apt-get install python3 python3-venv): {e}"
            ))
        }
    };
    Ok(format!(
        "Python {} with venv",
        String::from_utf8_lossy(&out.stdout).trim()
    ))
}

/// `qemu-system-arm`, from Debian when missing.
pub fn qemu() -> Result<String> {
    if !have("qemu-system-arm") {
        apt_install(&["qemu-system-arm"])?;
    }
    let out = quiet(Command::new("qemu-system-arm").arg("--version"))?;
    let text = String::from_utf8_lossy(&out.stdout);
    Ok(text.lines().next().unwrap_or("qemu-system-arm").to_string())
}

/// Headless `chromium`, from Debian when missing: the certificate's
/// rendering test reads the page as the browser lays it out.
pub fn chromium() -> Result<String> {
    if !have("chromium") {
        apt_install(&["chromium"])?;
    }
    let out = quiet(Command::new("chromium").arg("--version"))?;
    let text = String::from_utf8_lossy(&out.stdout);
    Ok(text.lines().next().unwrap_or("chromium").trim().to_string())
}

/// The flip-link version installed when it is missing (knurling-rs; 0.1.12
/// also moves `_stack_end` to the bottom of RAM, which cortex-m-rt 0.7.7's
/// `_stack_start >= _stack_end` check needs).
pub const FLIP_LINK_VERSION: &str = "0.1.12";

/// The installed flip-link's version, from `cargo install --list`
/// (`None`: not installed with cargo).
fn flip_link_installed() -> Option<String> {
    let out = quiet(Command::new("cargo").args(["install", "--list"])).ok()?;
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .find_map(|l| l.strip_prefix("flip-link v"))
        .map(|v| v.trim_end_matches(':').to_string())
}

/// `flip-link`, the firmware's linker: the stack below `.data`/`.bss`, so
/// an overflow hits the bottom of RAM (and the MPU guard there) instead of
/// static data. Installed with cargo at [`FLIP_LINK_VERSION`] when it is
/// not on the PATH.
pub fn flip_link() -> Result<String> {
    if !have("flip-link") {
        quiet(Command::new("cargo").args([
            "install",
            "flip-link",
            "--version",
            FLIP_LINK_VERSION,
            "--locked",
        ]))
        .map_err(|e| {
            format!(
                "flip-link (the firmware's linker) is missing and could not be installed; \
                 run `cargo install flip-link --version {FLIP_LINK_VERSION} --locked`: {e}"
            )
        })?;
    }
    if !have("flip-link") {
        return Err(
            "flip-link was installed but is not on the PATH: add ~/.cargo/bin to PATH".into(),
        );
    }
    Ok(match flip_link_installed() {
        Some(v) => format!("flip-link {v}"),
        None => "flip-link (not installed by cargo)".to_string(),
    })
}

/// A nightly toolchain for cargo-fuzz, installed (minimal profile) when
/// missing.
pub fn nightly() -> Result<String> {
    let version = || quiet(Command::new("rustup").args(["run", "nightly", "rustc", "--version"]));
    let out = match version() {
        Ok(o) => o,
        Err(_) => {
            quiet(Command::new("rustup").args([
                "toolchain",
                "install",
                "nightly",
                "--profile",
                "minimal",
            ]))
            .map_err(|e| {
                format!(
                    "no nightly toolchain and none could be installed (the fuzz smoke needs one; \
                     `cargo xtask ci --no-fuzz` runs everything else and says so): {e}"
                )
            })?;
            version()?
        }
    };
    Ok(String::from_utf8_lossy(&out.stdout).trim().to_string())
}

fn is_root() -> bool {
    quiet(Command::new("id").arg("-u"))
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false)
}

fn codename() -> Option<String> {
    let text = std::fs::read_to_string("/etc/os-release").ok()?;
    text.lines()
        .find_map(|l| l.strip_prefix("VERSION_CODENAME="))
        .map(|s| s.trim_matches('"').to_string())
        .filter(|s| !s.is_empty())
}

/// Installs Debian packages without removing any other package. Needs root
/// and apt-get; says so when either is missing.
pub fn apt_install(pkgs: &[&str]) -> Result<()> {
    let list = pkgs.join(" ");
    if !have("apt-get") {
        return Err(format!(
            "please install: {list} (no apt-get on this machine)"
        ));
    }
    if !is_root() {
        return Err(format!(
            "missing: {list}; installing it needs root: run `sudo apt-get install --no-remove {list}`, then run again"
        ));
    }
    let apt = |extra: &[String], args: &[&str]| {
        quiet(
            Command::new("apt-get")
                .env("DEBIAN_FRONTEND", "noninteractive")
                .args(extra)
                .args(args),
        )
    };
    let install = [
        "install",
        "-y",
        "-qq",
        "--no-install-recommends",
        "--no-remove",
    ];
    apt(&[], &["update", "-qq"])?;
    let first = apt(&[], &[&install[..], pkgs].concat());
    let Err(e) = first else { return Ok(()) };
    // The plain install would have removed something (or failed): offer
    // the distribution's backports for this one install.
    let Some(code) = codename() else {
        return Err(e);
    };
    let suite = format!("{code}-backports");
    let list_file: PathBuf = std::env::temp_dir().join("perpend-backports.list");
    let mut sources = std::fs::read_to_string("/etc/apt/sources.list").unwrap_or_default();
    sources.push_str(&format!(
        "\ndeb http://deb.debian.org/debian {suite} main\n"
    ));
    std::fs::write(&list_file, sources).map_err(|e| format!("{}: {e}", list_file.display()))?;
    let extra = vec![format!("-o=Dir::Etc::sourcelist={}", list_file.display())];
    apt(&extra, &["update", "-qq"])?;
    apt(&extra, &[&install[..], &["-t", &suite], pkgs].concat()).map_err(|e2| {
        format!(
            "cannot install {list} without removing other packages:\n  {e}\n  with {suite}: {e2}"
        )
    })?;
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn pinned_toolchain_of_this_repository() {
        let text = std::fs::read_to_string(root().join("rust-toolchain.toml")).unwrap();
        let p = parse_pinned(&text).unwrap();
        assert!(p.channel.starts_with("1."));
        assert!(p.targets.contains(&"thumbv7em-none-eabihf".to_string()));
        assert!(p.components.contains(&"clippy".to_string()));
    }

    #[test]
    fn pinned_toolchain_forms() {
        let p =
            parse_pinned("[toolchain]\nchannel = \"1.2.3\"\ntargets = [ \"a\", \"b\" ]\n").unwrap();
        assert_eq!(p.channel, "1.2.3");
        assert_eq!(p.targets, vec!["a", "b"]);
        assert!(p.components.is_empty());
        assert!(parse_pinned("[toolchain]\n").is_err());
    }
}
