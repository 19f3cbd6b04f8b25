//! The conventions and the file columns are where a user looks: in
//! `perpend --help` and in the help of the commands that read files.
#![allow(clippy::unwrap_used)]

use std::process::Command;

fn help(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(args)
        .output()
        .unwrap();
    assert!(out.status.success(), "{args:?}");
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn top_level_help_states_the_conventions() {
    let h = help(&["--help"]);
    for needle in [
        "+z along the spindle feed",
        "towards the head",
        "θ1",
        "Pitch",
        "Chen eq. 22",
    ] {
        assert!(
            h.contains(needle),
            "`perpend --help` lacks {needle:?}:\n{h}"
        );
    }
}

#[test]
fn commands_that_read_files_name_their_columns() {
    for cmd in ["calibrate", "diagnose", "measure"] {
        let h = help(&[cmd, "--help"]);
        for needle in [
            "sensors.csv",
            "x_mm",
            "d_mm",
            "d1_mm",
            "sigma_mm",
            "temp_c",
            "docs/data-format.md",
        ] {
            assert!(
                h.contains(needle),
                "`perpend {cmd} --help` lacks {needle:?}:\n{h}"
            );
        }
    }
}

#[test]
fn errors_with_json_are_json_and_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let sensors = dir.path().join("sensors.csv");
    std::fs::write(
        &sensors,
        "sensor;x_mm;y_mm;z_mm;m;n;q\n1;0,0;45;0;0;0,4;1\n",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(["diagnose", "--json", "--sensors"])
        .arg(&sensors)
        .arg("--poses")
        .arg(dir.path().join("poses.csv"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(v["file"].as_str().unwrap().ends_with("sensors.csv"), "{v}");
    assert_eq!(v["line"], 1, "{v}");
    let msg = v["error"].as_str().unwrap();
    assert!(msg.contains("separated by `;`"), "{msg}");
}

/// Every command path from `perpend --help` down (the `help` subcommands
/// left out), with its `--help` text.
fn command_tree() -> Vec<(Vec<String>, String)> {
    let mut out = Vec::new();
    let mut todo: Vec<Vec<String>> = vec![vec![]];
    while let Some(path) = todo.pop() {
        let args: Vec<&str> = path.iter().map(String::as_str).chain(["--help"]).collect();
        let h = help(&args);
        for sub in section(&h, "Commands:") {
            let name = sub.split_whitespace().next().unwrap_or("").to_string();
            if !name.is_empty() && name != "help" {
                todo.push([path.clone(), vec![name]].concat());
            }
        }
        out.push((path, h));
    }
    out
}

/// The lines of one section of a help text (up to the next blank line
/// that is followed by a heading).
fn section<'a>(h: &'a str, heading: &str) -> Vec<&'a str> {
    let mut lines = h.lines().skip_while(|l| *l != heading);
    lines.next();
    lines
        .take_while(|l| l.is_empty() || l.starts_with(' '))
        .filter(|l| l.len() > 2 && l.as_bytes()[2] != b' ')
        .collect()
}

/// The long options a help text lists (`--bus`, …).
fn options(h: &str) -> Vec<String> {
    // the short form puts each option's text beside it, the long form
    // (`--help` with long docs) under it: an option line starts with `-`
    let mut lines = h.lines().skip_while(|l| *l != "Options:");
    lines.next();
    lines
        .take_while(|l| l.is_empty() || l.starts_with(' '))
        .filter(|l| l.trim_start().starts_with('-'))
        .filter_map(|l| {
            l.split_whitespace()
                .find(|w| w.starts_with("--"))
                .map(|w| w.trim_end_matches(',').to_string())
        })
        .collect()
}

/// Whether the command `path` reads the option `opt` it inherits from its
/// parent: the link options only `node`'s commands, `cell run` and
/// `cell check` (the lead's interim check, on main) read,
/// `--eds` only `node sdo`'s, `--quiet` every command (`main.rs`).
fn reads(path: &[String], opt: &str) -> bool {
    let p: Vec<&str> = path.iter().map(String::as_str).collect();
    match opt {
        "--bus" | "--node-id" | "--bitrate" | "--timeout-ms" => {
            p.first() == Some(&"node") || p == ["cell", "run"] || p == ["cell", "check"]
        }
        "--eds" => p.starts_with(&["node", "sdo"]),
        _ => true,
    }
}

/// Listed but not read (issue 47 point 7: `cell sim-head` listed the
/// global link options of `perpend cell` until it flattened `NoLink`).
/// The list may only shrink: an entry that is read, or no longer listed,
/// fails the test too.
const PENDING: &[(&str, &str)] = &[];

/// Issue 47 point 7: every option a command's help lists is one it reads
/// (a global option inherited from a parent is listed by every
/// subcommand, whether it reads it or not).
#[test]
fn every_option_a_command_lists_is_one_it_reads() {
    let tree = command_tree();
    assert!(tree.len() > 30, "only {} commands found", tree.len());
    let help_of: std::collections::BTreeMap<&[String], &String> =
        tree.iter().map(|(p, h)| (p.as_slice(), h)).collect();
    let mut unread = Vec::new();
    for (path, h) in &tree {
        if !section(h, "Commands:").is_empty() {
            continue; // a parent lists its subcommands' global options
        }
        let parent = help_of
            .get(&path[..path.len().saturating_sub(1)])
            .map(|h| options(h))
            .unwrap_or_default();
        for o in options(h) {
            // only an option inherited from the parent can be unread
            if parent.contains(&o) && !reads(path, &o) {
                unread.push((path.join(" "), o));
            }
        }
    }
    let pending: Vec<(String, String)> = PENDING
        .iter()
        .map(|(c, o)| (c.to_string(), o.to_string()))
        .collect();
    let new: Vec<_> = unread.iter().filter(|u| !pending.contains(u)).collect();
    assert!(new.is_empty(), "listed but not read: {new:?}");
    let gone: Vec<_> = pending.iter().filter(|p| !unread.contains(p)).collect();
    assert!(gone.is_empty(), "fixed, remove from PENDING: {gone:?}");
}

/// Issue 47 point 7: no help shows a rustdoc link (`[`name`]`): the
/// doc comments of options are the help text.
#[test]
fn no_help_shows_a_code_reference() {
    for (path, h) in command_tree() {
        for bad in ["[`", "`]", "crate::", "super::"] {
            assert!(
                !h.contains(bad),
                "`perpend {} --help` shows {bad:?}:\n{h}",
                path.join(" ")
            );
        }
    }
}

/// The test's own parsing: commands and options of a help text.
#[test]
fn the_help_parser_finds_commands_and_options() {
    let h = help(&["node", "--help"]);
    let subs: Vec<String> = section(&h, "Commands:")
        .iter()
        .map(|l| l.split_whitespace().next().unwrap().to_string())
        .collect();
    assert!(
        subs.contains(&"sdo".to_string()) && subs.contains(&"lss".to_string()),
        "{subs:?}"
    );
    let o = options(&help(&["node", "sdo", "list", "--help"]));
    for want in ["--json", "--eds", "--bus", "--node-id", "--help"] {
        assert!(o.contains(&want.to_string()), "{o:?}");
    }
    assert!(!reads(&["cell".into(), "sim-head".into()], "--bus"));
}
