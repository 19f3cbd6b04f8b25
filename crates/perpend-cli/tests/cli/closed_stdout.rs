//! `perpend eds | head -1`: a standard output closed before the command
//! writes ends it quietly (no panic, nothing on stderr, status 141 as after
//! SIGPIPE).
#![allow(clippy::unwrap_used)]

use std::process::{Command, Stdio};

fn closed_stdout(args: &[&str]) -> std::process::Output {
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(args)
        .stdout(Stdio::from(writer))
        .stderr(Stdio::piped())
        .output()
        .unwrap()
}

#[test]
fn a_closed_stdout_ends_the_command_quietly() {
    for args in [&["eds"][..], &["--help"][..]] {
        let out = closed_stdout(args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains("panicked"), "{args:?}: {err}");
        if args[0] == "eds" {
            assert_eq!(out.status.code(), Some(141), "{args:?}: {err}");
            assert!(err.is_empty(), "{args:?}: {err}");
        }
    }
}
