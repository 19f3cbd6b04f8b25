//! Helpers shared by the `perpend cell run` tests: the binary, a child
//! process killed on drop, the paper's head and a plan in a temporary
//! directory, a virtual board with its slcan and world addresses, a bounded
//! run, and the board's state read back over the bus (calibration, NMT
//! state, residual limit, lock).
#![allow(clippy::unwrap_used, clippy::panic, dead_code)]

use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// The `perpend` binary under test.
pub const BIN: &str = env!("CARGO_BIN_EXE_perpend");

/// A child process killed on drop.
pub struct Killed(pub Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Runs `perpend --quiet ARGS` in `dir`; its standard output; panics on
/// failure.
pub fn ok(args: &[&str], dir: &Path) -> String {
    let out = Command::new(BIN)
        .arg("--quiet")
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A cell configuration (docs/record.md): the simulated tracker's
/// figures (Chen §5) under a named model and serial.
pub const CELL_CONFIG: &str = r#"{"schema": "perpend.cell-config/1", "laboratory": "Test Lab, 1 Test Street, Testville", "site": "test cell",
 "operator": "A. Operator", "approver": "Q. Engineer", "tolerance_deg": 0.05,
 "ambient_c": 21.0, "tracker": {"model": "Tracker T1", "serial": "T1-0042",
 "calibration_due": "2099-12-31", "traceability": "cert 17-123",
 "xi_mm": 0.02, "points": 20, "patch_mm": 150}}"#;

/// The paper's head (nominal.csv, truth.csv) and a plan of `n` poses
/// around the paper's orientation (plan.csv) in `d`.
pub fn head_and_plan(d: &Path, n: usize) {
    ok(&["cell", "sim-head", "--out", "."], d);
    std::fs::write(d.join("cell-config.json"), CELL_CONFIG).unwrap();
    let n = n.to_string();
    ok(
        &[
            "plan",
            "--sensors",
            "nominal.csv",
            "--n",
            &n,
            "--tilt-max",
            "5",
            "--center-tilt",
            "17.89,-1.04",
            "--standoff",
            "34,37",
            "--draws",
            "3",
            "--out",
            "plan.csv",
        ],
        d,
    );
}

/// A virtual board storing nominal.csv, simulating `truth` (a file in
/// `dir`), with `extra` options; returns it and its slcan and world
/// addresses.
pub fn board(dir: &Path, truth: &str, extra: &[&str]) -> (Killed, String, String) {
    let mut child = Killed(
        Command::new(BIN)
            .args(["board", "--slcan", "127.0.0.1:0", "--node-id", "16"])
            .args(["--plane", "0,0,1,-28", "--noise-mm", "0.01"])
            .args(["--sensors", "nominal.csv", "--truth", truth])
            .args(["--world", "127.0.0.1:0"])
            .args(extra)
            .current_dir(dir)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let stdout = child.0.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut r = BufReader::new(stdout);
        for _ in 0..2 {
            let mut line = String::new();
            let _ = r.read_line(&mut line);
            let _ = tx.send(line.trim().rsplit(' ').next().unwrap_or("").to_string());
        }
    });
    let addr = || rx.recv_timeout(Duration::from_secs(20)).unwrap();
    let (bus, world) = (addr(), addr());
    (child, bus, world)
}

/// Waits for `child` at most `secs`; its status, standard output and error.
pub fn finish(mut child: Killed, secs: u64) -> (ExitStatus, String, String) {
    let (mut out, mut err) = (String::new(), String::new());
    let o = child.0.stdout.take();
    let e = child.0.stderr.take();
    let to = std::thread::spawn(move || {
        let mut s = String::new();
        if let Some(mut o) = o {
            let _ = o.read_to_string(&mut s);
        }
        s
    });
    let te = std::thread::spawn(move || {
        let mut s = String::new();
        if let Some(mut e) = e {
            let _ = e.read_to_string(&mut s);
        }
        s
    });
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.0.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed() < Duration::from_secs(secs), "cell run hung");
        std::thread::sleep(Duration::from_millis(50));
    };
    out.push_str(&to.join().unwrap());
    err.push_str(&te.join().unwrap());
    (status, out, err)
}

/// `perpend --quiet cell run` against the board on `bus` with `extra`
/// options (few poses, few samples), standard input from `stdin` (none:
/// closed).
pub fn cell_run(d: &Path, bus: &str, out: &str, extra: &[&str], stdin: Stdio) -> Killed {
    Killed(
        Command::new(BIN)
            .args(["--quiet", "cell", "run", "--node-id", "16"])
            .args(["--bus", &format!("tcp:{bus}")])
            .args(["--sensors", "nominal.csv", "--plan", "plan.csv"])
            .args(["--out", out, "--samples", "5", "--verify", "2"])
            .args(["--verify-samples", "5", "--settle-ms", "50"])
            .args(extra)
            .current_dir(d)
            .stdin(stdin)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    )
}

/// `DIR/cell.json`.
pub fn cell_json(d: &Path, out: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(d.join(out).join("cell.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// What the board holds, read back over the bus.
#[derive(Debug, PartialEq)]
pub struct BoardState {
    /// The sensors of its calibration (`perpend node pull`).
    pub sensors: serde_json::Value,
    /// `nmt_state` of `perpend node info`.
    pub nmt: String,
    /// 0x2300 sub 4 [mm].
    pub residual_mm: f64,
    /// 0x2010 reads unlocked.
    pub unlocked: bool,
}

/// Reads the board's state (its calibration into `DIR/now.json`).
pub fn board_state(d: &Path, bus: &str, out: &str) -> BoardState {
    let bus = format!("tcp:{bus}");
    let link = ["node", "--bus", &bus, "--node-id", "16"];
    let file = format!("{out}/now.json");
    ok(&[&link[..], &["pull", "--out", &file]].concat(), d);
    let info: serde_json::Value =
        serde_json::from_str(&ok(&[&link[..], &["info", "--json"]].concat(), d)).unwrap();
    BoardState {
        sensors: calibration(d, &file),
        nmt: info["nmt_state"].as_str().unwrap().to_string(),
        residual_mm: info["residual_limit_mm"].as_f64().unwrap(),
        unlocked: info["calibration_unlocked"].as_bool().unwrap(),
    }
}

/// The sensors of a params.json in `d`.
pub fn calibration(d: &Path, file: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(d.join(file)).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["sensors"].clone()
}

/// The state of a fresh board: pre-operational, 0.05 mm, locked.
pub fn as_found(b: &BoardState, nmt: &str) {
    assert_eq!(b.nmt, nmt, "{b:?}");
    assert!((b.residual_mm - 0.05).abs() < 1e-6, "{b:?}");
    assert!(!b.unlocked, "{b:?}");
}

/// Zero points and beam directions of a params.json's sensors.
pub fn geometry(sensors: &serde_json::Value) -> Vec<f64> {
    let mut v = Vec::new();
    for s in sensors.as_array().unwrap() {
        for k in ["zero_mm", "dir"] {
            v.extend(s[k].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()));
        }
    }
    v
}

/// Whether two calibrations agree as the board holds them (REAL32).
pub fn same_geometry(a: &serde_json::Value, b: &serde_json::Value) -> bool {
    let (a, b) = (geometry(a), geometry(b));
    a.len() == b.len()
        && a.iter()
            .zip(&b)
            .all(|(x, y)| (x - y).abs() <= 1e-6 * x.abs().max(1.0))
}

/// The text of an HTML page as headless Chromium renders it (`innerText`
/// of the body: table cells separated by tabs, rows by newlines); `None`
/// when there is no `chromium` on this machine.
pub fn chromium_text(page: &Path) -> Option<String> {
    let bin = ["chromium", "chromium-browser"].into_iter().find(|b| {
        Command::new(b)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
    })?;
    let dir = tempfile::tempdir().unwrap();
    let html = std::fs::read_to_string(page).unwrap();
    // The page's own text, written into its title by a script Chromium
    // runs: --dump-dom then carries it out.
    let probe = html.replace(
        "</body>",
        "<script>document.title = 'RENDERED:' + encodeURIComponent(document.body.innerText);</script></body>",
    );
    let file = dir.path().join("page.html");
    std::fs::write(&file, probe).unwrap();
    let out = Command::new(bin)
        .args(["--headless", "--no-sandbox", "--disable-gpu", "--dump-dom"])
        .arg(format!(
            "--user-data-dir={}",
            dir.path().join("profile").display()
        ))
        .arg(format!("file://{}", file.display()))
        .output()
        .unwrap();
    let dom = String::from_utf8_lossy(&out.stdout);
    let start = dom.find("RENDERED:")? + "RENDERED:".len();
    let end = start + dom[start..].find("</title>")?;
    Some(percent_decode(&dom[start..end]))
}

/// Undoes `encodeURIComponent` (UTF-8 percent escapes).
fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            if let Ok(v) = u8::from_str_radix(&s[i + 1..i + 3], 16) {
                out.push(v);
                i += 3;
                continue;
            }
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}
