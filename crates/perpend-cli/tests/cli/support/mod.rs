//! What the end-to-end tests of `perpend node` share: a virtual board (or
//! cell) started on a free loopback port and killed when the test ends,
//! also on failure, and the checks of a command's exit status.
#![allow(clippy::unwrap_used, clippy::panic, dead_code)]

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Output, Stdio};
use std::time::Duration;

/// The binary under test.
pub const BIN: &str = env!("CARGO_BIN_EXE_perpend");

/// A running `perpend board` (one board or a cell); killed on drop.
pub struct VirtualBus {
    child: Child,
    /// `tcp:127.0.0.1:PORT`.
    pub bus: String,
    /// The board's first stdout line ("perpend board: … on 127.0.0.1:PORT").
    pub banner: String,
}

impl VirtualBus {
    /// Starts `perpend board --slcan 127.0.0.1:0 ARGS` and waits (20 s at
    /// most) for the line that names its port.
    pub fn start(args: &[&str]) -> Self {
        let mut child = Command::new(BIN)
            .args(["board", "--slcan", "127.0.0.1:0"])
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let _ = BufReader::new(stdout).read_line(&mut line);
            let _ = tx.send(line);
        });
        let Ok(line) = rx.recv_timeout(Duration::from_secs(20)) else {
            let _ = child.kill();
            panic!("perpend board did not start");
        };
        let addr = line.trim().rsplit(' ').next().unwrap().to_string();
        VirtualBus {
            child,
            bus: format!("tcp:{addr}"),
            banner: line.trim().to_string(),
        }
    }
}

impl Drop for VirtualBus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A command's stdout and stderr.
pub fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// Its stdout, after checking that it succeeded.
pub fn ok(o: &Output) -> String {
    let (out, err) = text(o);
    assert!(o.status.success(), "failed:\n{out}\n{err}");
    out
}

/// Its stderr, after checking that it failed with exit code 1.
pub fn failed(o: &Output) -> String {
    let (out, err) = text(o);
    assert_eq!(o.status.code(), Some(1), "expected exit 1:\n{out}\n{err}");
    err
}
