//! `cargo xtask cell-demo`: the cell calibration end to end against a
//! virtual board over slcan/TCP. Writes the paper's head (nominal and true,
//! Chen Table 2) into `target/cell-demo/`, plans 16 poses around the
//! paper's orientation (θ1 17.89°, θ2 −1.04°, standoff 34-37 mm so that
//! every reading stays in the board's 20-80 mm range), starts `perpend
//! board` storing the nominal head while simulating the true one (with a
//! world channel for the simulated robot), runs `perpend cell run` against
//! it and prints its figures; the board is stopped at the end.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use crate::{cargo, root, run, Result};

/// A child process stopped on drop.
pub(crate) struct Stopped(pub(crate) Child);

impl Drop for Stopped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The workspace's debug `perpend` binary.
pub(crate) fn perpend() -> PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("target"));
    target.join("debug").join("perpend")
}

/// Runs `perpend ARGS` in `dir`; fails on non-zero exit.
fn step(dir: &Path, args: &[&str]) -> Result<()> {
    eprintln!("\n==> perpend {}", args.join(" "));
    let status = Command::new(perpend())
        .args(args)
        .current_dir(dir)
        .status()
        .map_err(|e| format!("perpend: {e}"))?;
    if !status.success() {
        return Err(format!("perpend {} failed ({status})", args.join(" ")));
    }
    Ok(())
}

/// Starts `perpend ARGS` (a `perpend board`) in `dir` and reads the
/// `n` addresses it prints first (its slcan port, then the world channel
/// if asked for): the child (stopped on drop) and the addresses.
pub(crate) fn spawn_board(dir: &Path, args: &[&str], n: usize) -> Result<(Stopped, Vec<String>)> {
    eprintln!("\n==> perpend {} &", args.join(" "));
    let mut child = Stopped(
        Command::new(perpend())
            .args(args)
            .current_dir(dir)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("perpend board: {e}"))?,
    );
    let out = child.0.stdout.take().ok_or("perpend board: no stdout")?;
    let mut r = BufReader::new(out);
    let mut addrs = Vec::new();
    for _ in 0..n {
        let mut line = String::new();
        r.read_line(&mut line).map_err(|e| e.to_string())?;
        eprintln!("{}", line.trim());
        match line.trim().rsplit(' ').next() {
            Some(a) if a.contains(':') => addrs.push(a.to_string()),
            _ => return Err(format!("perpend board: unexpected line '{}'", line.trim())),
        }
    }
    Ok((child, addrs))
}

/// Starts the board in `dir`; returns it and its slcan and world addresses.
fn board(dir: &Path) -> Result<(Stopped, String, String)> {
    let args = [
        "board",
        "--slcan",
        "127.0.0.1:0",
        "--node-id",
        "16",
        "--plane",
        "0,0,1,-28",
        "--noise-mm",
        "0.01",
        "--sensors",
        "nominal.csv",
        "--truth",
        "truth.csv",
        "--world",
        "127.0.0.1:0",
    ];
    let (child, mut a) = spawn_board(dir, &args, 2)?;
    let world = a.pop().ok_or("perpend board: no world address")?;
    let bus = a.pop().ok_or("perpend board: no bus address")?;
    Ok((child, bus, world))
}

/// `cargo xtask cell-demo`.
pub fn cell_demo() -> Result<()> {
    run(&cargo(), &["build", "--quiet", "-p", "perpend-cli"])?;
    let dir = root().join("target").join("cell-demo");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    step(&dir, &["cell", "sim-head", "--out", "."])?;
    // The reference standard a certificate names (docs/record.md): the
    // simulated tracker's figures under a demo model and serial.
    let config = dir.join("cell-config.json");
    std::fs::write(&config, DEMO_CONFIG).map_err(|e| format!("{}: {e}", config.display()))?;
    step(
        &dir,
        &[
            "--quiet",
            "plan",
            "--sensors",
            "nominal.csv",
            "--n",
            "16",
            "--tilt-max",
            "5",
            "--center-tilt",
            "17.89,-1.04",
            "--standoff",
            "34,37",
            "--out",
            "plan.csv",
        ],
    )?;
    let (_board, bus, world) = board(&dir)?;
    let (bus, robot) = (format!("tcp:{bus}"), format!("sim:{world}"));
    step(
        &dir,
        &[
            "--quiet",
            "cell",
            "run",
            "--bus",
            &bus,
            "--node-id",
            "16",
            "--robot",
            &robot,
            "--sensors",
            "nominal.csv",
            "--plan",
            "plan.csv",
            "--truth",
            "truth.csv",
            "--out",
            "run",
            "--config",
            "cell-config.json",
        ],
    )
}

/// The demo's cell configuration.
const DEMO_CONFIG: &str = r#"{"schema": "perpend.cell-config/1", "laboratory": "perpend cell-demo, on this machine", "site": "cell-demo (virtual board)",
 "operator": "demo operator", "approver": "demo approver", "tolerance_deg": 0.05,
 "tracker": {"model": "simulated tracker (Chen 2018 section 5)", "serial": "SIM-1",
 "calibration_due": "2099-12-31", "traceability": "simulation: none",
 "xi_mm": 0.02, "points": 20, "patch_mm": 150}}
"#;
